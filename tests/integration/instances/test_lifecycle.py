"""The one lifecycle on a real systemd host: a deploy that breaks an instance goes back
and stops, as does one whose container Docker makes other than the plan read it (the
container policy's check before the start); an app that quits by itself comes back; values typed on the command line
reach systemd as numbers; a size with a space reaches Docker as one word; a changed setting and a secret reach each
instance with one restart of each (the same deploy as the typed values: one rolling deploy for both).

Runs in molecule's verify step on molecule/default; each test leaves every instance ready.
"""

import json
import re
import signal
import socket
import time

import testbed
from testbed import INSTANCES, container_id, sh, unit_show


def ids(host) -> dict:
    return {i: container_id(host, f"isaac-sim-{i}") for i in range(INSTANCES)}


def test_a_deploy_that_breaks_an_instance_stops_there_and_puts_it_back(host):
    before, envs = ids(host), {i: sh(host, f"cat /etc/isaac-sim/instance-{i}.env").stdout for i in range(INSTANCES)}
    started = time.monotonic()
    # a setting that makes the app die at once, before it is ready
    run = testbed.run_playbook(host, {"isaac_sim_env": {"STANDIN_CRASH_AFTER": "0"}})
    took = time.monotonic() - started
    out = " ".join((run.stdout + run.stderr).split())
    assert run.returncode != 0, out[-3000:]
    # named: host, instance, reason, with the container's own last words
    # "stopped" when the readiness gate saw the container exited, "went away" when docker run --rm
    # had removed it already: which one depends on when the gate looked
    stopped = rf"Rollout stopped on {testbed.name(host)}: isaac-sim-0: isaac-sim-0 (stopped|went away) before it was"
    assert re.search(stopped, out), out[-3000:]
    assert "simulated crash" in out
    assert "it went back to" in out and "not reached: isaac-sim-1, isaac-sim-2, isaac-sim-3" in out
    # the gate failed at once, not at the ready deadline (180 s here)
    assert took < 120, took
    testbed.all_ready(host)
    after = ids(host)
    assert after[0] != before[0], "isaac-sim-0 was not restarted on its previous settings"
    assert {i: after[i] for i in (1, 2, 3)} == {i: before[i] for i in (1, 2, 3)}
    assert {i: sh(host, f"cat /etc/isaac-sim/instance-{i}.env").stdout for i in range(INSTANCES)} == envs


def test_a_container_docker_makes_other_than_the_plan_read_it_never_starts(host):
    """A named volume made by hand with bind options: the plan sees a volume's name, Docker makes a bind
    of the host's /etc of it. The unit's check of the created container (isaac-sim-policy) refuses it
    before it starts; the rollout stops on instance 0, names why, and puts it back."""
    before, envs = ids(host), {i: sh(host, f"cat /etc/isaac-sim/instance-{i}.env").stdout for i in range(INSTANCES)}
    sh(host, "docker volume create --opt type=none --opt o=bind --opt device=/etc hostetc")
    try:
        run = testbed.run_playbook(host, {"isaac_sim_extra_docker_args": ["-v", "hostetc:/h:ro"]})
        out = " ".join((run.stdout + run.stderr).split())
        assert run.returncode != 0, out[-3000:]
        assert f"Rollout stopped on {testbed.name(host)}: isaac-sim-0: " in out, out[-3000:]
        assert (
            "isaac-sim-0 was not started: the container policy refuses what Docker made of its arguments: "
            "--volume=hostetc:/h:ro binds (a local volume's options) host path /etc into it"
        ) in out, out[-3000:]
        assert "it went back to" in out and "not reached: isaac-sim-1, isaac-sim-2, isaac-sim-3" in out
        testbed.all_ready(host)
        after = ids(host)
        assert {i: after[i] for i in (1, 2, 3)} == {i: before[i] for i in (1, 2, 3)}
        assert {i: sh(host, f"cat /etc/isaac-sim/instance-{i}.env").stdout for i in range(INSTANCES)} == envs
        # the refused container never ran: nothing of it is left
        assert "hostetc" not in sh(host, "docker ps -a --format '{{.Mounts}}'").stdout
    finally:
        sh(host, "docker volume rm hostetc", check=False)


def test_two_deploys_at_once_one_waits_or_is_refused_and_a_dead_runs_lock_never_blocks(host):
    lock = "/run/lock/isaac-sim.json"
    envs = {i: sh(host, f"cat /etc/isaac-sim/instance-{i}.env").stdout for i in range(INSTANCES)}
    # ready as the rolling restart's preflight reads it (isaac_sim_info), or it ends at once and frees the host
    testbed.wait_for(
        lambda: all(i["ready"] for i in testbed.info(host)["instances"]), timeout=180, what="every instance ready"
    )
    # a rolling restart holds the host for its four restarts and 4 x 4 s soak (about 60 s here): time
    # enough for the refused deploy and for the waiting one to ask (about 20 s here); the restarts, the
    # bulk of the hold, slow down with the machine as the two deploys do (if it ends early: raised below)
    first = testbed.start_playbook(host, {"isaac_sim_rollout_soak": 4}, playbook="playbooks/rolling_restart.yml")
    third = None
    try:
        # held by the rolling restart itself (the lock names its ansible-playbook's pid): a lock file alone may be
        # another's, left by a run that ended earlier, which the deploy below would take first (seen in CI)
        def held_by_first() -> bool:
            try:
                return json.loads(sh(host, f"cat {lock}", check=False).stdout or "{}").get("pid") == first.pid
            except ValueError:
                return False

        testbed.wait_for(held_by_first, timeout=120, what="the rolling restart's hold on the lock")
        # a deploy with other settings meanwhile: refused before it plans, naming the first run
        second = testbed.run_playbook(host, {"isaac_sim_env": {"STANDIN_CRASH_AFTER": "0"}})
        out = " ".join((second.stdout + second.stderr).split())
        if first.poll() is not None:  # the first run ended early: say why, not only that the second ran
            raise AssertionError(
                f"the rolling restart ended before the second run asked: {first.communicate()[0][-3000:]}"
            )
        assert second.returncode != 0, out[-3000:]
        assert f"{testbed.name(host)} is held by " in out and "(ansible-playbook pid " in out and " since " in out
        assert "isaac_sim_lock_wait" in out and "isaac_sim_lock_break=true" in out
        # another waits for it instead, then runs
        third = testbed.start_playbook(host, {"isaac_sim_lock_wait": 600})
        said_first = first.communicate(timeout=600)[0]
        assert first.returncode == 0, said_first[-3000:]
        said = third.communicate(timeout=600)[0]
        assert third.returncode == 0 and "waiting up to 600 s" in said, said[-3000:]
    finally:
        for proc in (first, third):
            if proc is not None and proc.poll() is None:
                proc.kill()
    assert {i: sh(host, f"cat /etc/isaac-sim/instance-{i}.env").stdout for i in range(INSTANCES)} == envs
    assert sh(host, f"test -e {lock}", check=False).rc == 1, "the lock was not given back"

    # a run of this controller killed mid-deploy: its lock is taken at once, with a word
    dead = {"id": "x", "user": "carol", "controller": socket.gethostname(), "pid": 999999, "started": "1"}
    dead.update(play="Deploy", since=time.time(), renewed=time.time())
    sh(host, f"mkdir -p /run/lock && echo '{json.dumps(dead)}' > {lock}")
    taken = testbed.run_playbook(host)
    said = taken.stdout + taken.stderr
    assert taken.returncode == 0 and "took the lock left by carol" in said, said[-3000:]
    # another controller's run: refused while fresh, taken when the operator says that run is dead
    sh(host, f"echo '{json.dumps(dict(dead, controller='elsewhere', id='y'))}' > {lock}")
    refused = testbed.run_playbook(host)
    said = refused.stdout + refused.stderr
    assert refused.returncode != 0 and "is held by carol on elsewhere" in said, said[-3000:]
    broken = testbed.run_playbook(host, {"isaac_sim_lock_break": True})
    said = broken.stdout + broken.stderr
    assert broken.returncode == 0 and "(isaac_sim_lock_break)" in said, said[-3000:]
    testbed.all_ready(host)


def test_ctrl_c_mid_rollout_stops_after_the_instance_in_hand_and_the_next_run_says_what_it_did(host):
    def invocations():
        return {i: unit_show(host, f"isaac-sim@{i}.service")["InvocationID"] for i in range(INSTANCES)}

    def journal():
        return sh(host, f"journalctl -t isaac-sim-lifecycle --since @{since} --no-pager").stdout

    before, since = invocations(), sh(host, "date +%s").stdout.strip()
    # each instance soaks 20 s: far longer than the whole rollout takes to notice a silent controller
    run = testbed.start_playbook(host, {"isaac_sim_rollout_soak": 20}, playbook="playbooks/rolling_restart.yml")
    try:
        testbed.wait_for(lambda: invocations()[0] != before[0], timeout=180, what="isaac-sim@0 restarted")
        run.send_signal(signal.SIGINT)
        run.communicate(timeout=60)
    finally:
        if run.poll() is None:
            run.kill()
    # the host stops at its next instance once the heartbeat is 30 s silent: never all four
    testbed.wait_for(lambda: "rollout interrupted" in journal(), timeout=150, what="the lifecycle to stop")
    restarted = [i for i, inv in invocations().items() if inv != before[i]]
    assert restarted in ([0], [0, 1]), restarted
    said = journal()
    assert "its controller stopped renewing its hold on the host" in said and "left as they were: isaac-sim-" in said
    testbed.all_ready(host)
    # the next run takes the lock the interrupted one left, and says what it did
    again = testbed.run_playbook(host)
    out = " ".join((again.stdout + again.stderr).split())
    assert again.returncode == 0, out[-3000:]
    assert "took the lock left by" in out and "its rollout here was interrupted" in out, out[-3000:]


def test_an_app_that_quits_by_itself_with_status_0_is_restarted(host):
    before = unit_show(host, "isaac-sim@1.service")
    old = container_id(host, "isaac-sim-1")
    # SIGTERM from inside: the app shuts down cleanly and exits 0, as 6.x does when a stream session ends
    sh(host, "docker kill --signal=TERM isaac-sim-1")
    testbed.wait_for(lambda: container_id(host, "isaac-sim-1") not in ("", old), timeout=60, what="a new isaac-sim-1")
    testbed.all_ready(host, [1])
    after = unit_show(host, "isaac-sim@1.service")
    # restarted by systemd, as a session end: not counted against the start limit
    assert after["InvocationID"] != before["InvocationID"]
    journal = sh(host, "journalctl -u isaac-sim@1 -n 60 --no-pager").stdout
    assert "SIGTERM received" in journal
    assert "isaac-sim-1: session ended (the app exited 0 after it was ready)" in journal


def test_values_typed_on_the_command_line_a_changed_setting_and_a_secret_restart_each_instance_once(host):
    """One rolling deploy (and one restore) for what each would restart every instance for: values typed on
    the command line reach systemd and Docker typed; a changed setting and a secret reach each instance
    exactly, the secret written nowhere else; every instance restarts once and ends ready."""
    raw = [
        "isaac_sim_start_limit_burst=4",
        "isaac_sim_ready_timeout=60",
        "isaac_sim_stop_timeout=20",
        "isaac_sim_restart_sec=5",
        'isaac_sim_memory_limit="1 gb"',
        "isaac_sim_gpu_enabled=false",
        "isaac_sim_rollout_soak=1",
        'isaac_sim_extra_docker_args="--label=from-the-command-line=a b"',
    ]
    old = ids(host)
    # the journal's position now: what follows is the deploy's
    cursor = sh(host, "journalctl -n 0 --show-cursor --no-pager").stdout.strip().split("cursor: ", 1)[1]
    secret = 'nvapi-$ecret"with`quotes\\and$HOME'
    changed = {"isaac_sim_env": {"SCENE": "warehouse"}, "isaac_sim_secret_env": {"OMNI_PASS": secret}}
    try:
        run = testbed.run_playbook(host, changed, raw_vars=raw)
        assert run.returncode == 0, run.stdout[-3000:] + run.stderr
        assert secret not in run.stdout + run.stderr
        testbed.all_ready(host)
        verify = sh(host, "systemd-analyze verify /etc/systemd/system/isaac-sim@.service isaac-sim@0.service 2>&1")
        assert "isaac-sim" not in verify.stdout, verify.stdout
        props = sh(
            host,
            "systemctl show isaac-sim@0 -p StartLimitBurst -p StartLimitIntervalUSec -p RestartUSec "
            "-p TimeoutStartUSec -p TimeoutStopUSec",
        ).stdout.splitlines()
        # 4 * (5 + 60 + 30) = 380 s
        assert sorted(props) == [
            "RestartUSec=5s",
            "StartLimitBurst=4",
            "StartLimitIntervalUSec=6min 20s",
            "TimeoutStartUSec=1min 30s",
            "TimeoutStopUSec=50s",
        ], props
        inspect = sh(host, "docker inspect -f '{{.HostConfig.Memory}} {{json .Config.Labels}}' isaac-sim-0").stdout
        assert inspect.startswith("1073741824 ")
        assert '"from-the-command-line":"a b"' in inspect
        for i in range(INSTANCES):
            assert testbed.instance_ready(host, i)
            cid = container_id(host, f"isaac-sim-{i}")
            assert cid and cid != old[i]
            assert "SCENE=warehouse" in sh(host, f"docker inspect -f '{{{{.Config.Env}}}}' isaac-sim-{i}").stdout
            assert sh(host, f"stat -c %a /etc/isaac-sim/instance-{i}.env").stdout.strip() == "600"
            env = sh(host, f"docker exec isaac-sim-{i} env").stdout.splitlines()
            assert f"OMNI_PASS={secret}" in env
            # passed by name: the value is not on any command line
            assert secret not in sh(host, "ps -eo args").stdout
            # once: one start of its app since the deploy began
            journal = f"journalctl -u isaac-sim@{i} --no-pager --after-cursor='{cursor}'"
            starts = sh(host, f"{journal} | grep -c 'starting as uid'")
            assert starts.stdout.strip() == "1", i
    finally:
        restored = testbed.run_playbook(host)
        assert restored.returncode == 0, restored.stdout[-3000:] + restored.stderr
        testbed.all_ready(host)
    for i in range(INSTANCES):
        assert sh(host, f"stat -c %a /etc/isaac-sim/instance-{i}.env").stdout.strip() == "644"


def test_a_port_held_by_another_process_keeps_the_instance_from_starting(host):
    sh(host, "systemctl stop isaac-sim@2")
    # a foreign server takes instance 2's signal port while the instance is down
    sh(host, "nohup python3 -m http.server 49102 >/dev/null 2>&1 & echo $! >/tmp/holder.pid")
    holder = sh(host, "cat /tmp/holder.pid").stdout.strip()
    testbed.wait_for(lambda: "49102" in sh(host, "ss -Hltn 'sport = :49102'").stdout, timeout=20, what="the holder")
    try:
        assert sh(host, "systemctl start isaac-sim@2", check=False).rc != 0
        # the unit's sandbox cannot read a root process's sockets (no CAP_SYS_PTRACE): the way to name it
        said = (
            "isaac-sim-2 cannot start: port 49102/tcp of its block is held by another process"
            " (as root: ss -lnp 'sport = :49102')."
        )

        def status_saying_why():
            text = sh(host, "systemctl status isaac-sim@2 --no-pager -l -n 20", check=False).stdout
            return text if said in text else ""

        # systemctl status shows the journal's last lines, once journald has them
        status = testbed.wait_for(status_saying_why, timeout=20, what="the reason in systemctl status")
        assert "isaac_sim_port_bases" in status
        assert container_id(host, "isaac-sim-2") == ""
    finally:
        sh(host, f"kill {holder}", check=False)
        sh(host, "systemctl reset-failed isaac-sim@2; systemctl start isaac-sim@2")
    testbed.all_ready(host)


def test_a_hung_instance_turns_unhealthy_and_its_host_restarts_it(host):
    def health():
        return testbed.by_name(testbed.info(host))["isaac-sim-2"]["health"]

    testbed.wait_for(lambda: health() == "healthy", timeout=60, what="isaac-sim-2 healthy")
    before = unit_show(host, "isaac-sim@2.service")
    old = container_id(host, "isaac-sim-2")
    since = sh(host, "date +%s").stdout.strip()
    # the app hangs: its ports stay open and nothing answers
    sh(host, "docker exec isaac-sim-2 touch /tmp/standin-hang")
    testbed.wait_for(lambda: health() == "unhealthy", timeout=60, what="isaac-sim-2 reported unhealthy")
    # restarted by the host itself (no Ansible run), after 8 s unhealthy
    testbed.wait_for(lambda: container_id(host, "isaac-sim-2") not in ("", old), timeout=90, what="a new isaac-sim-2")
    testbed.all_ready(host, [2])
    assert int(unit_show(host, "isaac-sim@2.service")["NRestarts"]) == int(before["NRestarts"]) + 1
    journal = sh(host, f"journalctl -u isaac-sim@2 --since @{since} --no-pager").stdout
    assert "isaac-sim-2 unhealthy for" in journal and "stopping it so systemd restarts it" in journal
    testbed.wait_for(lambda: health() == "healthy", timeout=60, what="the new isaac-sim-2 healthy")


def reserved_ports(host):
    return sh(host, "cat /proc/sys/net/ipv4/ip_local_reserved_ports").stdout.strip()


def test_a_port_layout_change_rolls_without_an_instance_starting_on_a_held_port(host):
    # stride 1 -> 2 with the stream port next to the signal port: new instance 1 wants
    # 49102-49103, which old instances 2 and 3 still hold until they are rolled
    layout = {"isaac_sim_port_bases": {"signal": 49100, "stream": 49101}, "isaac_sim_port_stride": 2}
    since = sh(host, "date +%s").stdout.strip()
    try:
        run = testbed.run_playbook(host, layout)
        assert run.returncode == 0, run.stdout[-3000:] + run.stderr
        # the order that frees each port before it is taken again
        order = f"rolled: {testbed.name(host)}: isaac-sim-2, isaac-sim-3, isaac-sim-1, isaac-sim-0"
        assert order in " ".join(run.stdout.split()), run.stdout[-3000:]
        testbed.all_ready(host)
        for i in range(INSTANCES):
            ports = sh(host, f"ss -Hltnp 'sport = :{49100 + 2 * i}'").stdout
            assert '"python3",pid=' in ports, (i, ports)
        journal = sh(host, f"journalctl -u 'isaac-sim@*' --since @{since} --no-pager").stdout
        assert "cannot start: port" not in journal
        # the new blocks (the web viewer strides too) are reserved, the old ports let go
        assert reserved_ports(host) == "8210,8212,8214,8216,49100-49107", reserved_ports(host)
    finally:
        restored = testbed.run_playbook(host)
        assert restored.returncode == 0, restored.stdout[-3000:] + restored.stderr
        testbed.all_ready(host)
    assert reserved_ports(host) == "8210-8213,47998-48001,49100-49103"
