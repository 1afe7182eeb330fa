"""The release table is the one place release knowledge lives: what lists releases agrees with it."""

import re
import socket
import subprocess
import threading
import time
from pathlib import Path

import yaml
from ansible_collections.isaacsim.fleet.plugins.module_utils.instance import releases
from ansible_collections.isaacsim.fleet.plugins.module_utils.instance.releases import (
    DEFAULT_RELEASE,
    RELEASES,
    healthcheck,
    release_of_tag,
)

ROOT = Path(__file__).resolve().parents[5]


def test_the_role_documents_exactly_the_releases_of_the_table():
    specs = yaml.safe_load((ROOT / "roles" / "isaac_sim" / "meta" / "argument_specs.yml").read_text())
    text = " ".join(specs["argument_specs"]["main"]["options"]["isaac_sim_release"]["description"])
    # the sentence that lists them: "One of C(2023.1), C(4.x), ... (the release table ...)"
    listed = re.search(r"One of ((?:C\([^)]*\)(?:, | or )?)+)", text)
    assert listed, text
    assert re.findall(r"C\(([^)]*)\)", listed.group(1)) == list(RELEASES)
    assert specs["argument_specs"]["main"]["options"]["isaac_sim_release"]["default"] == DEFAULT_RELEASE


def test_the_default_release_is_the_table_s_one_default_wherever_yaml_repeats_it():
    """YAML cannot read releases.DEFAULT_RELEASE, so each place that repeats it is checked against it."""
    assert DEFAULT_RELEASE in RELEASES

    def yaml_of(path):
        return yaml.safe_load((ROOT / path).read_text())

    assert yaml_of("roles/isaac_sim/defaults/main.yml")["isaac_sim_release"] == DEFAULT_RELEASE
    assert yaml_of("roles/slurm_node/defaults/main.yml")["slurm_node_isaac_sim_release"] == DEFAULT_RELEASE
    assert yaml_of("roles/train/defaults/main.yml")["train_release"] == DEFAULT_RELEASE
    toolkit = yaml_of("roles/nvidia_container_toolkit/defaults/main.yml")["nvidia_container_toolkit_release"]
    assert toolkit == f"{{{{ isaac_sim_release | default('{DEFAULT_RELEASE}') }}}}"
    for role in ("isaac_sim", "slurm_node", "train"):
        for entry, spec in yaml_of(f"roles/{role}/meta/argument_specs.yml")["argument_specs"].items():
            for name, option in spec["options"].items():
                if name.endswith("release") and "default" in option:
                    assert option["default"] == DEFAULT_RELEASE, (role, entry, name)


def test_a_release_is_the_longest_name_its_tag_starts_with_wherever_it_stands_in_the_table(monkeypatch):
    """A 6.3 appended after 6.x takes tag 6.3.0 (the first match in table order gave it to 6.x, and the plan
    refused 6.3's own image); 6.0.1 stays 6.x's."""
    scratch = dict(RELEASES)
    scratch["6.3"] = dict(RELEASES["6.x"], default_tag="6.3.0")
    monkeypatch.setattr(releases, "RELEASES", scratch)
    assert releases.release_of_tag("6.3.0") == "6.3"
    assert releases.release_of_tag("6.3") == "6.3"
    assert releases.release_of_tag("6.0.1") == "6.x"
    assert releases.release_of_tag("6.30.0") == "6.x"
    assert releases.release_of_tag("7.0.0") is None


def test_every_release_has_what_the_plan_and_the_gates_read():
    for name, profile in RELEASES.items():
        assert {"uid", "gid", "profiles", "mounts", "ports", "ready_pattern", "min_driver", "log_dir"} <= set(profile)
        assert "streaming" in profile["profiles"] and "headless" in profile["profiles"], name
        for mode, launch in profile["profiles"].items():
            assert launch["entrypoint"].startswith("/isaac-sim/"), (name, mode)
            assert set(launch["opens"]) <= set(profile["ports"]), (name, mode)
            assert launch["health_port"] is None or launch["health_port"] in launch["opens"], (name, mode)
        # no stream at all: nothing opened, asked only whether the app is ready
        assert profile["profiles"]["headless"]["opens"] == []
        assert "--no-window" in profile["profiles"]["headless"]["args"]
        assert ("--allow-root" in profile["profiles"]["headless"]["args"]) == (profile["uid"] == 0)
        assert release_of_tag(profile["default_tag"]) == name
        assert f"{profile['log_dir']}/Kit/*/*/kit_*.log" in healthcheck(name, 1234)


def test_a_healthcheck_without_a_port_asks_only_for_appready():
    assert healthcheck("6.x", None).endswith('grep -q AppReady "$latest"')
    # the port is asked at the address clients use; 127.0.0.1 only when the plan names none
    assert "/dev/tcp/10.1.2.3/49100" in healthcheck("6.x", 49100, "10.1.2.3")
    assert "/dev/tcp/127.0.0.1/49100" in healthcheck("6.x", 49100)


def _port_probe(port, address="127.0.0.1"):
    """The healthcheck's port probe alone (the AppReady part needs a kit log), run by a real bash."""
    probe = healthcheck("6.x", port, address).split(" && bash -c ", 1)[1]
    return subprocess.run(["sh", "-c", f"bash -c {probe}"], capture_output=True, timeout=20, check=False).returncode


def _listener(accepts: bool):
    sock = socket.socket()
    sock.bind(("127.0.0.1", 0))
    sock.listen(4)
    got = []

    def serve():
        while True:
            try:
                conn = sock.accept()[0]
            except OSError:
                return
            conn.settimeout(1)
            try:
                got.append(conn.recv(64))
            except OSError:
                got.append(None)
            conn.close()

    if accepts:
        threading.Thread(target=serve, daemon=True).start()
    return sock, got


def test_the_port_probe_passes_on_a_server_that_accepts_and_sends_it_nothing():
    sock, got = _listener(accepts=True)
    with sock:
        assert _port_probe(sock.getsockname()[1]) == 0
        time.sleep(0.2)
    # connected and left without a byte: no request a real server might refuse or take as a session
    assert got == [b""]


def test_the_port_probe_fails_on_a_server_that_accepts_nothing_or_is_not_there():
    sock, _got = _listener(accepts=False)
    with sock:
        port = sock.getsockname()[1]
        assert _port_probe(port) == 1
        # the same port at another address of the host: nothing listens there
        assert _port_probe(port, "127.0.0.2") != 0
    assert _port_probe(port) != 0


# a subreaper runs the whole healthcheck as Docker's exec does, then reaps what the check left behind:
# in a container whose PID 1 reaps nothing, each of those would stay a zombie for the container's life
ORPHANS = r"""
import ctypes, os, subprocess, sys, time
ctypes.CDLL(None, use_errno=True).prctl(36, 1, 0, 0, 0)  # PR_SET_CHILD_SUBREAPER
# the old check's leftover outlived its shell in most runs, not all: ten runs
rc = max(subprocess.run(["/bin/sh", "-c", sys.argv[1]]).returncode for _ in range(10))
time.sleep(0.3)
orphans = 0
while True:
    try:
        pid, _status = os.waitpid(-1, os.WNOHANG)
    except ChildProcessError:
        break
    if pid == 0:
        time.sleep(0.1)
        continue
    orphans += 1
print(rc, orphans)
"""


def test_a_healthcheck_leaves_no_process_behind_for_pid_1_to_reap(tmp_path):
    logs = tmp_path / "Kit" / "isaac-sim" / "6.0"
    logs.mkdir(parents=True)
    (logs / "kit_1.log").write_text("[omni.kit.app] AppReady\n")
    sock, _got = _listener(accepts=True)
    with sock:
        check = healthcheck("6.x", sock.getsockname()[1]).replace(releases.RELEASES["6.x"]["log_dir"], str(tmp_path))
        out = subprocess.run(["python3", "-c", ORPHANS, check], capture_output=True, text=True, timeout=30, check=True)
    assert out.stdout.split() == ["0", "0"], out.stdout + out.stderr
