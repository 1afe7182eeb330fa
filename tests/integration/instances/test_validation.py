"""Bad input fails with a message naming the variable and the fix, and the host is left exactly as it was.

Also: --check on a fresh host reports changes and changes nothing.
"""

import subprocess

import pytest
import testbed
import testinfra
from testbed import INSTANCES, ROOT, sh

NVIDIA_SMI = ROOT / "tests" / "fixtures" / "nvidia-driver" / "nvidia-smi"


def assert_rejected(host, extra_vars, *needles):
    before = testbed.snapshot(host)
    result = testbed.run_playbook(host, extra_vars)
    out = result.stdout + result.stderr
    assert result.returncode != 0, out[-3000:]
    for needle in needles:
        assert needle in out, f"{needle!r} not in output:\n{out[-3000:]}"
    assert testbed.snapshot(host) == before, "a rejected run changed the host"
    return out


# Each run is refused for every mistake it carries at once (each one a line of its own), so mistakes
# the same check reads go together: one playbook run for each group, not one for each mistake.
# An unknown release (the plan's first check, refused alone) is the plan module's unit test's
# (tests/unit/plugins/modules/test_isaac_sim_plan.py: the module end to end, facts and message): its
# way out of the play is every plan error's, as plan-words here.
@pytest.mark.parametrize(
    "extra_vars, needles",
    [
        # the plan's checks of words and numbers
        (
            {
                "isaac_sim_port_bases": {"signal": 47999},
                "isaac_sim_image": "nvcr.io/nvidia/Isaac Sim:5",
                "isaac_sim_memory_limit": "lots",
                "isaac_sim_shm_size": "2 gigs",
            },
            [
                "isaac_sim_port_bases",
                "overlaps instance",
                "Fix:",
                "isaac_sim_image",
                "not a valid image reference",
                "isaac_sim_memory_limit: 'lots' is not a size",
                "isaac_sim_shm_size: '2 gigs' is not a size",
            ],
        ),
        # the plan's sums: ports past the end, memory past the host's
        (
            {"isaac_sim_port_bases": {"web_viewer": 65534}, "isaac_sim_memory_limit": "4096g"},
            [
                "isaac_sim_port_bases",
                "outside 1024-65535",
                "isaac_sim_memory_limit: 4 instances x 4096g",
                "more than this host's",
            ],
        ),
        # against what the host has and what the image needs
        (
            {
                "isaac_sim_instance_count": 9,
                "isaac_sim_gpu_enabled": True,
                "isaac_sim_image": "nvcr.io/nvidia/isaac-sim:6.0.1",
                "isaac_sim_registry_password": "",
            },
            [
                "isaac_sim_instance_count: 9 is above isaac_sim_max_instances (8)",
                "isaac_sim_gpu_enabled: true, but this host has no nvidia-smi",
                "isaac_sim_registry_password: empty, but nvcr.io/nvidia/isaac-sim:6.0.1 is on NGC",
            ],
        ),
        # types, before any role runs
        (
            {"isaac_sim_instance_count": "many", "isaac_sim_rollout_soak": "abc"},
            [
                "isaac_sim_instance_count: 'many' is not a whole number. Fix: give a whole number",
                "isaac_sim_rollout_soak: 'abc' is not a number. Fix: give a number",
            ],
        ),
        ({"isaac_sim_port_bases": {"signal": "abc"}}, ["isaac_sim_port_bases.signal: 'abc' is not a port number"]),
        # every way out of the container at once, each named with the containers it would reach, judged on
        # what Docker makes of the words (a short-flag cluster, a CSV-quoted field, Go's "0" for false); the
        # one allowed by name, spelled otherwise, passes
        (
            {
                "isaac_sim_extra_docker_args": [
                    "--privileged",
                    "--cap-add",
                    "SYS_ADMIN",
                    "--pid=host",
                    "-Pv",
                    "/var/run/docker.sock:/var/run/docker.sock",
                    "--mount",
                    'type=bind,"source=/run/containerd/containerd.sock",target=/c',
                    "--security-opt",
                    "no-new-privileges=0",
                    "--user=0",
                    "--device=/dev/fuse",
                    "--cap-add=sys_ptrace",
                ],
                "isaac_sim_allowed_docker_args": ["--cap-add=CAP_SYS_PTRACE"],
                "isaac_sim_companions": [
                    {
                        "name": "bridge",
                        "image": "reg/bridge:1",
                        "instances": [2],
                        "volumes": ["/run:/host-run"],
                        "docker_args": ["--security-opt=seccomp=unconfined"],
                    }
                ],
            },
            [
                "isaac_sim_extra_docker_args: --privileged gives the container every capability and device "
                "(on isaac-sim-0, isaac-sim-1, isaac-sim-2, isaac-sim-3). Fix: remove it;",
                "isaac_sim_extra_docker_args: --cap-add=SYS_ADMIN adds the capability SYS_ADMIN",
                "add '--cap-add=SYS_ADMIN' to isaac_sim_allowed_docker_args",
                "isaac_sim_extra_docker_args: --pid=host shares the host's PID namespace",
                "isaac_sim_extra_docker_args: --volume=/var/run/docker.sock:/var/run/docker.sock binds host path "
                "/run/docker.sock into it: Docker's socket",
                "isaac_sim_extra_docker_args: --mount=type=bind,source=/run/containerd/containerd.sock,target=/c "
                "binds host path /run/containerd/containerd.sock into it: containerd's socket",
                "isaac_sim_extra_docker_args: --security-opt=no-new-privileges=false lets the container's processes "
                "gain privileges",
                "isaac_sim_extra_docker_args: --user=0 runs the container as root",
                "isaac_sim_extra_docker_args: --device=/dev/fuse gives the container a host device",
                "isaac_sim_companions[bridge].volumes: --volume=/run:/host-run binds host path /run into it",
                "isaac_sim_companions[bridge].docker_args: --security-opt=seccomp=unconfined turns off the seccomp "
                "filter (the companion of isaac-sim-2)",
            ],
        ),
    ],
    ids=["plan-words", "plan-sums", "host-and-image", "types", "port-base-type", "confinement"],
)
def test_bad_input_is_rejected_before_any_change(host, extra_vars, needles):
    out = assert_rejected(host, extra_vars, *needles)
    # no raw Python error, and no dump of the argument spec after the message
    assert "Traceback" not in out and "invalid literal" not in out and "[Errno" not in out
    # a wrong type is refused before Ansible's own role argument validation, which prints the spec
    assert "argument_spec" not in out and "_AnsibleTagged" not in out
    # an argument allowed by name is not refused (the confinement case allows --cap-add=sys_ptrace, spelled
    # --cap-add=CAP_SYS_PTRACE in the allowance: the same capability to Docker)
    assert "--cap-add=SYS_PTRACE adds" not in out


def test_more_instances_than_gpus(host):
    host_name = testbed.name(host)
    subprocess.run(["docker", "cp", str(NVIDIA_SMI), f"{host_name}:/usr/local/bin/nvidia-smi"], check=True)
    try:
        assert_rejected(
            host,
            {"isaac_sim_gpu_enabled": True, "isaac_sim_gpu_exclusive": True},
            "isaac_sim_instance_count: 4 instances with isaac_sim_gpu_exclusive: true need 4 GPUs, this host has 2",
        )
    finally:
        sh(host, "rm -f /usr/local/bin/nvidia-smi")


def test_a_port_held_by_another_process(host):
    # the signal port a fifth instance would get (the four hold every port of their own blocks)
    # 49104 is in the kernel's ephemeral range and not reserved (no instance has it): a passing
    # outbound connection may hold it a moment, so the squatter retries its bind until it holds it
    sh(
        host,
        "systemd-run --unit=port-squatter -p Restart=on-failure -p RestartSec=1 "
        "-p StartLimitIntervalSec=0 python3 -m http.server 49104",
    )

    def listening():
        return sh(host, "ss -Hltn 'sport = :49104'").stdout.strip()

    try:
        try:
            testbed.wait_for(listening, timeout=60, what="squatter")
        except AssertionError as exc:
            said = sh(host, "journalctl -u port-squatter --no-pager -n 30; ss -Htanu | grep -w 49104", check=False)
            raise AssertionError(f"{exc}\n{said.stdout}") from exc
        assert_rejected(
            host,
            {"isaac_sim_instance_count": 5},
            "port 49104/tcp is already held on this host by python3",
            "isaac_sim_port_bases",
        )
    finally:
        sh(host, "systemctl stop port-squatter; systemctl reset-failed port-squatter", check=False)


def test_check_mode_on_a_fresh_host_reports_changes_and_changes_nothing(tmp_path):
    fresh = "isaacsim-test-fresh"
    create = ROOT / "molecule" / "resources" / "create.yml"
    destroy = ROOT / "molecule" / "resources" / "destroy.yml"
    hosts = f'{{"testbed_hosts": ["{fresh}"]}}'
    subprocess.run(["ansible-playbook", str(create), "-e", hosts], check=True, capture_output=True, cwd=ROOT)
    try:
        fresh_host = testinfra.get_host(f"docker://{fresh}")
        state = "dpkg-query -W -f '${Package} ${Status}\\n' | sort; ls -la /etc /etc/systemd/system /var/lib"
        before = sh(fresh_host, state).stdout
        inventory = tmp_path / "fresh.yml"
        inventory.write_text(
            f"all:\n  children:\n    isaac_sim_hosts:\n      hosts:\n        {fresh}:\n"
            "      vars:\n        ansible_connection: docker\n"
        )
        result = testbed.run_playbook(fresh_host, check=True, extra_inventory=inventory)
        assert result.returncode == 0, result.stdout[-3000:] + result.stderr
        assert testbed.changed_count(result, fresh_host) > 0
        assert sh(fresh_host, state).stdout == before
        assert sh(fresh_host, "test -e /etc/isaac-sim", check=False).rc != 0
    finally:
        subprocess.run(["ansible-playbook", str(destroy), "-e", hosts], capture_output=True, cwd=ROOT, check=False)


def test_an_inventory_without_the_group_says_which_group_to_fill(tmp_path):
    inventory = tmp_path / "hosts.yml"
    inventory.write_text("all:\n  children:\n    gpu_servers:\n      hosts:\n        gpu-01:\n")
    for book in ("deploy.yml", "status.yml", "test_suite.yml"):
        run = subprocess.run(
            ["ansible-playbook", "-i", str(inventory), str(ROOT / "playbooks" / book)],
            capture_output=True,
            text=True,
            cwd=ROOT,
            timeout=120,
            check=False,
        )
        out = " ".join((run.stdout + run.stderr).split())
        assert run.returncode != 0, out[-2000:]
        assert "The inventory has no host in group isaac_sim_hosts" in out and "(groups found: gpu_servers)" in out
        assert "Fix: list your GPU servers under isaac_sim_hosts" in out
        assert "has no attribute" not in out


def test_a_refused_registry_login_names_the_registry_and_the_user_never_the_key(host):
    key = "wrong-key-0123456789"
    out = assert_rejected(
        host,
        {"isaac_sim_image_pull": "always", "isaac_sim_registry_password": key},
        "refused the login of user $oauthtoken from " + testbed.name(host),
        "Fix: check isaac_sim_registry_username and isaac_sim_registry_password",
    )
    assert key not in out
    # refused once, in the deploy's first play, when the tag's digest was asked: before any pull
    assert "when asked which digest" in out and "Pull the Isaac Sim image" not in out


def test_a_pull_with_the_key_leaves_it_nowhere_on_the_host_nor_in_the_play_s_output(host, monkeypatch):
    # a pull forced with the scenario's key, the play at -vvv: the key is on the host only while
    # the pull runs, in a Docker config of its own under /run, removed at its end
    key = (ROOT / "tests" / "fixtures" / "registry" / "ngc-api-key").read_text().strip()
    # what a run killed during its pull leaves: its config, with the key, never removed by its `always`
    left = "/run/isaac-sim-pull.killed"
    sh(host, f"mkdir -m 0700 {left}")
    subprocess.run(
        ["docker", "exec", "-i", testbed.name(host), "sh", "-c", f"cat > {left}/config.json"],
        input=key + "\n",
        text=True,
        check=True,
    )
    monkeypatch.setenv("ANSIBLE_VERBOSITY", "3")
    result = testbed.run_playbook(host, {"isaac_sim_image_pull": "always"})
    out = result.stdout + result.stderr
    assert result.returncode == 0, out[-3000:]
    assert "Log in to the image's registry, into the pull's own config" in out and "Pull the Isaac Sim image" in out
    assert key not in out
    # the key is given to grep in a file on /dev/shm, never on a command line; every place it could stay
    pattern = "/dev/shm/isaac-sim-test-key"
    subprocess.run(
        ["docker", "exec", "-i", testbed.name(host), "sh", "-c", f"cat > {pattern}"],
        input=key + "\n",
        text=True,
        check=True,
    )
    try:
        found = sh(
            host,
            f"grep -rIlsF -f {pattern} /etc /root /var/lib /run /tmp; "
            f"journalctl --no-pager -o cat | grep -cF -f {pattern}; "
            f"ps -eo args | grep -F -f {pattern}; true",
        ).stdout.split()
    finally:
        sh(host, f"rm -f {pattern}")
    # grep -c prints the journal's count (0); anything else is a file or a process holding the key
    assert found == ["0"], found
    assert not sh(host, "ls -d /run/isaac-sim-pull.* 2>/dev/null", check=False).stdout.strip()


def test_check_mode_on_the_deployed_host_runs_and_changes_nothing(host):
    before = testbed.snapshot(host)
    result = testbed.run_playbook(host, check=True)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr
    assert testbed.changed_count(result, host) == 0
    assert testbed.snapshot(host) == before
    # a dry run of a change to every instance says which would restart and why, and changes nothing
    result = testbed.run_playbook(host, {"isaac_sim_env": {"DRY_RUN_PROBE": "1"}}, check=True)
    out = " ".join((result.stdout + result.stderr).split())
    assert result.returncode == 0, out[-3000:]
    for i in range(INSTANCES):
        assert f"isaac-sim-{i} would restart, one at a time: its settings changed" in out, out[-3000:]
    assert testbed.snapshot(host) == before
