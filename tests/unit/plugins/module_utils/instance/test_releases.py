"""The release table is the one place release knowledge lives: what lists releases agrees with it."""

import socket
import subprocess
import threading
import time
from pathlib import Path

import yaml
from ansible_collections.isaacsim.fleet.plugins.module_utils.instance.releases import (
    RELEASES,
    healthcheck,
    release_of_tag,
)

ROOT = Path(__file__).resolve().parents[5]


def test_the_role_documents_exactly_the_releases_of_the_table():
    specs = yaml.safe_load((ROOT / "roles" / "isaac_sim" / "meta" / "argument_specs.yml").read_text())
    text = " ".join(specs["argument_specs"]["main"]["options"]["isaac_sim_release"]["description"])
    named = {r for r in ("2023.1", "4.x", "5.x", "6.x", "7.x", "3.x") if f"C({r})" in text}
    assert named == set(RELEASES)
    assert specs["argument_specs"]["main"]["options"]["isaac_sim_release"]["default"] in RELEASES


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
