"""Rolling restarts and upgrades across three hosts of four instances, watched from outside.

Runs in molecule's verify step of molecule/fleet. The tests share the fleet and
run in file order: a rolling restart, a plain deploy of a new image that fails at the
canary (a changed setting that fails is the default scenario's test_lifecycle; the
fleet's canary stop is the same for both), a preflight that refuses an unhealthy fleet
and one with a host that does not answer, a rollout scoped by --limit and instance
selection, a Docker settings change that restarts Docker one host at a time (its first
deploy stops at a canary pause nobody answers), a fleet-wide scale-down, and an upgrade
approved at the canary prompt that goes through, every host on the digest its tag named
when the deploy began though the tag moves upstream while the canary waits; then that
tag is withdrawn upstream (the mirror still holds it) and the next deploy stops before
any change, while an instance restarts on the digest it runs.
"""

from __future__ import annotations

import json
import os
import pty
import re
import select
import subprocess
import time

import pytest
import testbed
from fleethosts import INSTANCES, PLAIN, SIGNAL, all_ready, containers, hosts, ip, playbook, playbook_argv, sh, squash
from portwatch import Watcher
from testbed import ROOT, client


def playbook_on_a_terminal(name: str, extra: dict, prompt: str, answer) -> tuple:
    """Run on a pseudo-terminal, as an operator would; when `prompt` shows, type answer() and Enter.

    Returns (exit code, output, whether the prompt was answered).
    """
    pid, fd = pty.fork()
    if pid == 0:  # the child: session leader on the terminal, so Ansible's pause may prompt
        os.chdir(ROOT)
        os.environ.update(PLAIN)
        argv = playbook_argv(name, extra, None)
        os.execvp(argv[0], argv)
    out, answered, deadline = b"", False, time.monotonic() + 1500
    try:
        while time.monotonic() < deadline:
            if not select.select([fd], [], [], 5)[0]:
                continue
            try:
                chunk = os.read(fd, 65536)
            except OSError:  # EIO: the playbook ended and closed the terminal
                break
            if not chunk:
                break
            out += chunk
            if not answered and prompt in squash(out.decode(errors="replace")):
                os.write(fd, answer().encode() + b"\r")
                answered = True
        else:
            os.kill(pid, 9)
    finally:
        os.close(fd)
    _first, status = os.waitpid(pid, 0)
    return os.waitstatus_to_exitcode(status), out.decode(errors="replace"), answered


@pytest.fixture(scope="module")
def fleet():
    found = hosts()
    assert len(found) >= 3
    for h in found:
        testbed.wait_for(lambda h=h: all_ready(h), timeout=180, what=f"{h} ready")
    return found


def registry_image(host, tag):
    current = re.search(r'^ISAAC_SIM_IMAGE="([^"]+)"', sh(host, "cat /etc/isaac-sim/instance-0.env"), re.M).group(1)
    return current.rsplit(":", 1)[0] + f":{tag}"


def test_rolling_restart_keeps_n_minus_1_per_host_and_one_host_at_a_time(fleet):
    before = {h: containers(h) for h in fleet}
    watcher = Watcher({h: ip(h) for h in fleet}, [SIGNAL + i for i in range(INSTANCES)])
    watcher.start()
    try:
        # a short soak: an instance answers before it is ready, so the watcher's checks hold whatever its length
        run = playbook("rolling_restart.yml", {"isaac_sim_rollout_soak": 1})
    finally:
        watcher.stop()
    assert run.returncode == 0, run.stdout[-4000:] + run.stderr
    assert "completed: every host rolled" in run.stdout
    after = {h: containers(h) for h in fleet}
    for h in fleet:
        # every instance got a new container, with the same image
        assert all(after[h][n][0] != before[h][n][0] and after[h][n][1] == before[h][n][1] for n in before[h]), h
        assert all_ready(h)
    assert len(watcher.samples) > 80, "the watcher must have seen the whole rollout"
    # every host was seen disturbed (so these checks can fail), never by more than one instance
    assert watcher.lowest() == {h: INSTANCES - 1 for h in fleet}, watcher.lowest()
    # serial [1, 25%] on three hosts rolls one host at a time
    assert watcher.most_disturbed_at_once(INSTANCES) == 1


def deploy_that_fails_at_the_canary(fleet, extra: dict, env_check: str):
    """A plain deploy whose change never gets ready: one instance of the first host changes,
    goes back, everything else keeps its container; a watcher sees >= 3 of 4 on every host."""
    canary, rest = fleet[0], fleet[1:]
    before = {h: containers(h) for h in fleet}
    envs = {h: sh(h, "cat /etc/isaac-sim/instance-1.env") for h in fleet}
    watcher = Watcher({h: ip(h) for h in fleet}, [SIGNAL + i for i in range(INSTANCES)])
    watcher.start()
    try:
        run = playbook("deploy.yml", {"isaac_sim_ready_timeout": 15, "isaac_sim_rollout_soak": 3, **extra})
    finally:
        watcher.stop()
    out = squash(run.stdout + run.stderr)
    assert run.returncode != 0
    # the message names the host, the instance and the reason
    assert f"Rollout stopped on {canary}: isaac-sim-0: isaac-sim-0 was not ready within 15 s" in out, run.stdout[-4000:]
    assert "reverted: " + canary + ": isaac-sim-0" in out
    assert f"untouched: {canary}: isaac-sim-1, isaac-sim-2, isaac-sim-3" in out
    for h in rest:
        assert f"{h}: every instance (not reached)" in out
    after = {h: containers(h) for h in fleet}
    # the canary's instance 0 is back on its old settings and ready; nothing else was touched
    assert after[canary]["isaac-sim-0"][1] == before[canary]["isaac-sim-0"][1]
    assert after[canary]["isaac-sim-0"][0] != before[canary]["isaac-sim-0"][0]
    testbed.wait_for(lambda: all_ready(canary), timeout=60, what="the canary ready")
    for h in fleet:
        for n in before[h]:
            if (h, n) != (canary, "isaac-sim-0"):
                assert after[h][n] == before[h][n], (h, n)
        assert sh(h, "cat /etc/isaac-sim/instance-1.env") == envs[h]
        assert env_check not in sh(h, "cat /etc/isaac-sim/instance-0.env")
    assert watcher.lowest() == {h: INSTANCES - 1 if h == canary else INSTANCES for h in fleet}, watcher.lowest()


def test_a_deploy_of_an_image_that_never_gets_ready_stops_at_the_canary_and_puts_it_back(fleet):
    bad = registry_image(fleet[0], "6.0.1-never-ready")
    deploy_that_fails_at_the_canary(fleet, {"isaac_sim_image": bad}, bad)


def test_preflight_refuses_an_unhealthy_instance_before_anything_restarts(fleet):
    sick = fleet[-1]
    sh(sick, "systemctl stop isaac-sim@2")
    before = {h: containers(h) for h in fleet}
    run = playbook("rolling_restart.yml", {"isaac_sim_rollout_soak": 3})
    out = squash(run.stdout + run.stderr)
    assert run.returncode != 0
    assert f"isaac-sim-2 on {sick} not ready before the rollout. Fix: repair them first" in out, run.stdout[-4000:]
    assert "isaac_sim_rollout_allow_unhealthy: true" in out
    # not one instance on any host was restarted, the canary's included
    assert {h: containers(h) for h in fleet} == before
    assert "isaac-sim-2" not in before[sick]


def test_a_host_that_does_not_answer_stops_the_rollout_before_anything_restarts(fleet):
    gone = fleet[1]
    before = {h: containers(h) for h in fleet if h != gone}
    # frozen, not stopped: nothing on it answers, and it keeps its address and instances for later tests
    client().containers.get(gone).pause()
    try:
        run = playbook("rolling_restart.yml", {"isaac_sim_rollout_soak": 3})
    finally:
        client().containers.get(gone).unpause()
    out = squash(run.stdout + run.stderr)
    assert run.returncode != 0
    assert f"Rollout stopped before any instance restarted: {gone} did not answer" in out, out[-4000:]
    assert "Fix: bring the host back, or leave it out with --limit" in out
    # any error in the preflight is fatal for all: the canary was not restarted either
    assert {h: containers(h) for h in fleet if h != gone} == before
    assert "Roll this batch" not in out


def test_limit_and_instance_selection_roll_only_what_they_name(fleet):
    target = fleet[-1]
    before = {h: containers(h) for h in fleet}
    scope = {"isaac_sim_instances_selected": [1, 2], "isaac_sim_rollout_allow_unhealthy": True}
    run = playbook("rolling_restart.yml", {"isaac_sim_rollout_soak": 1, **scope}, limit=target)
    assert run.returncode == 0, run.stdout[-4000:] + run.stderr
    assert f"rolled: {target}: isaac-sim-1, isaac-sim-2" in squash(run.stdout)
    after = {h: containers(h) for h in fleet}
    # the stopped instance is running again, 1 has a new container, 0 and 3 were not touched
    assert all_ready(target)
    assert after[target]["isaac-sim-1"][0] != before[target]["isaac-sim-1"][0]
    assert {n: after[target][n] for n in ("isaac-sim-0", "isaac-sim-3")} == {
        n: before[target][n] for n in ("isaac-sim-0", "isaac-sim-3")
    }
    for h in fleet[:-1]:
        assert after[h] == before[h], h


def docker_started(host: str) -> str:
    return sh(host, "systemctl show -p ActiveEnterTimestampMonotonic --value docker.service").strip()


def test_a_docker_settings_change_restarts_docker_one_host_at_a_time(fleet):
    canary, rest = fleet[0], fleet[1:]
    options = json.loads(sh(canary, "cat /etc/docker/daemon.json"))
    change = {"docker_engine_daemon_options": {**options, "max-concurrent-downloads": 5}}
    started = {h: docker_started(h) for h in fleet}
    before = {h: containers(h) for h in fleet}
    # the canary pause with nobody to answer (no terminal: it fails closed) stops after the canary: only the
    # canary's Docker restarted; the others keep theirs noted. (The pause is the one of every rollout playbook)
    first = playbook("deploy.yml", {**change, "isaac_sim_rollout_pause_after_canary": True})
    out = squash(first.stdout + first.stderr)
    assert first.returncode != 0
    assert f"Rollout stopped after the canary {canary}: not approved" in out, first.stdout[-4000:]
    assert "stopped: no approval after the canary" in out
    assert docker_started(canary) != started[canary]
    testbed.wait_for(lambda: all_ready(canary), timeout=120, what="the canary ready after its Docker restart")
    for h in rest:
        assert docker_started(h) == started[h], h
        assert containers(h) == before[h], h
        assert f"{h}: every instance (not reached)" in out
        assert '"max-concurrent-downloads": 5' in sh(h, "cat /etc/docker/daemon.json")
        assert "restarts in the next canary batch" in sh(h, "cat /etc/docker/restart-pending")
    # the next deploy finds the noted restarts and does them, one host at a time
    watcher = Watcher({h: ip(h) for h in fleet}, [SIGNAL + i for i in range(INSTANCES)])
    watcher.start()
    try:
        second = playbook("deploy.yml", change)
    finally:
        watcher.stop()
    assert second.returncode == 0, second.stdout[-4000:] + second.stderr
    for h in rest:
        assert docker_started(h) != started[h], h
        assert sh(h, "test -e /etc/docker/restart-pending && echo noted || echo done").strip() == "done"
        assert all_ready(h)
    # a Docker restart takes its whole host down: never more than one host at a time
    assert watcher.most_disturbed_at_once(INSTANCES) == 1
    assert all(watcher.lowest()[h] < INSTANCES for h in rest), watcher.lowest()
    assert watcher.lowest()[canary] == INSTANCES


def test_a_fleet_wide_scale_down_goes_host_by_host(fleet):
    # (to zero only when confirmed: the default scenario's test_scaling, the same deploy.yml's refusal)
    before = {h: containers(h) for h in fleet}
    # 4 -> 3 everywhere: the instances that go serve, so they go in the canary batches
    watcher = Watcher({h: ip(h) for h in fleet}, [SIGNAL + INSTANCES - 1])
    watcher.start()
    try:
        # a soak of 3 s, not 1: the hosts' instances must go more than 2 s apart (below)
        run = playbook("deploy.yml", {"isaac_sim_instance_count": INSTANCES - 1, "isaac_sim_rollout_soak": 3})
    finally:
        watcher.stop()
    assert run.returncode == 0, run.stdout[-4000:] + run.stderr
    gone = {h: next((t for t, seen in watcher.samples if seen[h] == 0), None) for h in fleet}
    assert None not in gone.values(), gone
    # one host at a time, in inventory order: the canary first, never two in one step
    assert gone[fleet[0]] + 2 < gone[fleet[1]] and gone[fleet[1]] + 2 < gone[fleet[2]], gone
    for h in fleet:
        assert sorted(containers(h)) == [f"isaac-sim-{i}" for i in range(INSTANCES - 1)]
        assert {n: before[h][n] for n in containers(h)} == containers(h), "a kept instance was restarted"
    back = playbook("deploy.yml")
    assert back.returncode == 0, back.stdout[-4000:] + back.stderr
    for h in fleet:
        testbed.wait_for(lambda h=h: all_ready(h), timeout=180, what=f"{h} ready")


# the registry as this machine reaches it (tests/fixtures/registry), to move a tag upstream
UPSTREAM = "127.0.0.1:5555/fixtures/isaac-sim-standin"


def move_tag(tag: str, source: str) -> str:
    """Push the local image `source` under `tag` upstream (logged in for that push only); the digest
    the tag names now."""
    registry = UPSTREAM.split("/", 1)[0]
    subprocess.run(
        ["docker", "login", "-u", "$oauthtoken", "--password-stdin", registry],
        input=testbed.REGISTRY_KEY_FILE.read_text().strip(),
        capture_output=True,
        text=True,
        check=True,
    )
    try:
        subprocess.run(["docker", "tag", source, f"{UPSTREAM}:{tag}"], check=True)
        pushed = subprocess.run(["docker", "push", f"{UPSTREAM}:{tag}"], capture_output=True, text=True, check=True)
    finally:
        subprocess.run(["docker", "logout", registry], capture_output=True, check=False)
    return re.search(r"digest: (sha256:[0-9a-f]{64})", pushed.stdout).group(1)


def test_upgrade_approved_at_the_canary_converges_every_host_on_one_digest_while_the_tag_moves(fleet):
    new = registry_image(fleet[0], "6.0.2")
    seen = {}

    def approve():
        # at the prompt the canary runs the new image and no other host was touched yet
        seen.update({h: {image for _key, image in containers(h).values()} for h in fleet})
        # mid-run, the tag moves upstream to another image: the hosts still to come must not follow it
        seen["moved to"] = move_tag("6.0.2", "isaacsim-fleet/isaac-sim-standin:good")
        return "yes"

    watcher = Watcher({h: ip(h) for h in fleet}, [SIGNAL + i for i in range(INSTANCES)])
    watcher.start()
    try:
        code, out, answered = playbook_on_a_terminal(
            "upgrade.yml",
            {"isaac_sim_image": new, "isaac_sim_rollout_soak": 1, "isaac_sim_rollout_pause_after_canary": True},
            prompt="Type yes and Enter to go on",
            answer=approve,
        )
    finally:
        watcher.stop()
        # the tag back where the registry fixture keeps it
        move_tag("6.0.2", "isaacsim-fleet/isaac-sim-standin:next")
    assert answered, out[-4000:]
    assert code == 0, out[-4000:]
    assert "completed: every host rolled" in out
    # the deploy said, before any change, the digest the tag named and whom it moves
    pinned = re.search(rf"{re.escape(new)} is (sha256:[0-9a-f]{{64}}) now; this deploy moves ", squash(out))
    assert pinned and pinned.group(1) != seen["moved to"], squash(out)[-3000:]
    # at the prompt the canary ran that digest (Docker names the image as it was run: by digest) and no
    # other host was touched yet
    on = {h: {image.rsplit("@", 1)[-1] for image in seen[h]} for h in fleet}
    assert on[fleet[0]] == {pinned.group(1)} and all(pinned.group(1) not in on[h] for h in fleet[1:]), seen
    # the upgrade is the deploy as a rollout: every host disturbed, never below 3 of 4
    assert watcher.lowest() == {h: INSTANCES - 1 for h in fleet}, watcher.lowest()
    digest = None
    for h in fleet:
        # the status module shows the new digest on every instance
        info = json.loads(
            subprocess.run(
                ["ansible", "-i", testbed.inventory(), h, "-m", "isaacsim.fleet.isaac_sim_info"],
                capture_output=True,
                text=True,
                cwd=ROOT,
                env=dict(os.environ, ANSIBLE_LOAD_CALLBACK_PLUGINS="1", ANSIBLE_STDOUT_CALLBACK="json"),
                check=True,
            ).stdout
        )["plays"][0]["tasks"][0]["hosts"][h]
        registry = sh(h, f"docker image inspect -f '{{{{index .RepoDigests 0}}}}' {new}").strip().split("@", 1)[1]
        digest = digest or registry
        # every host the digest the deploy pinned, none the one the tag moved to mid-run
        assert registry == digest == pinned.group(1), (h, registry, seen["moved to"])
        assert [i["digest"] for i in info["instances"]] == [digest] * INSTANCES, h
        # the reports name the tag as written; the env file runs the digest, through the fleet's mirror
        assert all(i["ready"] and i["image"] == new for i in info["instances"]), h
        through = f"{ip('isaacsim-mirror-1')}:5443/{new.split('/', 1)[1].rsplit(':', 1)[0]}@{digest}"
        assert f'ISAAC_SIM_IMAGE_PINNED="{through}"' in sh(h, "cat /etc/isaac-sim/instance-3.env"), h


def test_a_tag_withdrawn_upstream_stops_the_next_deploy_and_the_pinned_digest_still_restarts(fleet):
    # after the upgrade every host runs 6.0.2 as pinned; then the upstream withdraws 6.0.2 (the only tag of its
    # image there), as NVIDIA withdraws a broken or vulnerable image
    new = registry_image(fleet[0], "6.0.2")
    digest = sh(fleet[0], f"docker image inspect -f '{{{{index .RepoDigests 0}}}}' {new}").strip().split("@", 1)[1]
    name = UPSTREAM.split("/", 1)[1]
    mirror = f"{ip('isaacsim-mirror-1')}:5443"
    accept = "Accept: application/vnd.docker.distribution.manifest.v2+json"
    through_mirror = (
        f"curl -s -o /dev/null -w '%{{http_code}}' --cacert /etc/docker/certs.d/{mirror}/ca.crt -H '{accept}' "
        f"https://{mirror}/v2/{name}/manifests/6.0.2"
    )
    # a host once pulled the tag through the mirror, which keeps it
    assert sh(fleet[0], through_mirror) == "200"
    deleted = testbed.registry_status(f"/v2/{name}/manifests/{digest}", f"repository:{name}:delete", method="DELETE")
    assert deleted == 202
    try:
        assert testbed.registry_status(f"/v2/{name}/manifests/6.0.2", f"repository:{name}:pull") == 404
        # the mirror still answers the tag from its cached copy: asking it alone rolled the image out
        assert sh(fleet[0], through_mirror) == "200"
        # (the metrics exporter's timer runs its oneshot on its own schedule: not ours to compare)
        snapshot = testbed.SNAPSHOT + " | grep -v isaac-sim-metrics; true"
        before = {h: sh(h, snapshot) for h in fleet}
        run = playbook("deploy.yml", {"isaac_sim_image": new})
        assert run.returncode != 0
        said = squash(run.stdout + run.stderr)
        assert f"no longer has {new}" in said and "the upstream http://" in said, said[-3000:]
        assert "A withdrawn image is not rolled out; nothing was changed." in said
        assert {h: sh(h, snapshot) for h in fleet} == before
        # refused after every host was held: each was given back
        assert [h for h in fleet if sh(h, "test -e /run/lock/isaac-sim.json && echo held; true").strip()] == []
        # a host restarting an instance runs the digest it has: the unit never pulls
        sh(fleet[0], "systemctl restart isaac-sim@0")
        testbed.wait_for(lambda: all_ready(fleet[0]), timeout=120, what="instance 0 ready on the pinned digest")
        assert containers(fleet[0])["isaac-sim-0"][1].endswith(digest)
    finally:
        # the tag back where the registry fixture keeps it (the same image: the same digest)
        assert move_tag("6.0.2", "isaacsim-fleet/isaac-sim-standin:next") == digest
