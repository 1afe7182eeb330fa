"""What the unit tests share: outputs recorded on real hosts, and a way to run a module.

Recorded (tests/unit/recorded) from the molecule default host with four 6.x
stand-in instances, instance 3 stopped and a stray `isaac-sim-9` container
started by hand: `systemctl show` (systemd 252), the Docker API's container
and image lists (Docker 20.10, API 1.41), an env file, and a reverse JSON
journal read. standin-nvidia-smi-q-x.xml comes from the stand-in nvidia-smi
fixture, which prints nvidia-smi's layout; the h100-* files were recorded on an
NVIDIA H100 80GB HBM3 with driver 580.159.04 (tests/hardware/gpu_check.py).

Tests import this module by its collection name
(ansible_collections.isaacsim.fleet.tests.unit.helpers), which works under
both `ansible-test units` and plain pytest (tests/conftest.py).
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from ansible.module_utils import basic
from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib import fleet_status

REC = Path(__file__).resolve().parent / "recorded"
NOW = 1795354574  # `date +%s` on the host right after the recording
MONOTONIC_NOW = 11900.0
RECORDED_MARKERS = {0: NOW - 200, 1: NOW - 195, 2: NOW - 190}


def recorded(name: str) -> str:
    return (REC / name).read_text()


def containers() -> dict:
    return fleet_status.parse_containers(
        json.loads(recorded("docker-containers.json")), json.loads(recorded("docker-images.json")), NOW
    )


def env(i: int) -> dict:
    """Instance i's env file: the recorded instance-2.env with i's port block."""
    text = recorded("instance-2.env")
    if i == 2:
        return fleet_status.parse_env_file(text)
    return fleet_status.parse_env_file(
        text.replace("49102", str(49100 + i)).replace("48000", str(47998 + i)).replace("8212", str(8210 + i))
    )


def build_records(**kw) -> list:
    """fleet_status.build over the recordings; keyword arguments replace its inputs."""
    args = dict(
        envs={i: env(i) for i in range(4)},
        units=fleet_status.parse_systemctl_show(recorded("systemctl-show.txt")),
        containers=containers(),
        markers=dict(RECORDED_MARKERS),
        gpu=None,
        pid_containers={},
        default_address="10.9.9.9",
        now=NOW,
        monotonic_now=MONOTONIC_NOW,
    )
    args.update(kw)
    return fleet_status.build(**args)


def host_result(**kw) -> dict:
    """One host's isaac_sim_info result built from the recordings."""
    instances = build_records(default_address="10.0.0.1")
    result = {"deployed": True, "instances": instances, "summary": fleet_status.summarize(instances), "errors": []}
    result.update(kw)
    return result


def no_nvml():
    raise ImportError("No module named 'pynvml'")


class RecordedDocker:
    """The Docker API's answers as recorded, counting the calls."""

    def __init__(self):
        self.calls = 0

    def containers(self, prefix):
        self.calls += 1
        return json.loads(recorded("docker-containers.json"))

    def images(self):
        self.calls += 1
        return json.loads(recorded("docker-images.json"))


try:
    from ansible.module_utils.testing import patch_module_args  # ansible-core 2.19 and later
except ImportError:  # older ansible-core: set the arguments the way AnsibleModule reads them
    from contextlib import contextmanager
    from unittest import mock

    @contextmanager
    def patch_module_args(args=None):
        data = json.dumps({"ANSIBLE_MODULE_ARGS": args or {}}).encode()
        with mock.patch.object(basic, "_ANSIBLE_ARGS", data):
            yield


def run_module(main, args: dict, capsys) -> dict:
    """Run a module's main() with these arguments; its result, with "failed" set when it failed."""
    with patch_module_args(args), pytest.raises(SystemExit) as exc:
        main()
    result = json.loads(capsys.readouterr().out)
    assert result.get("failed", False) is (exc.value.code != 0), result
    return result


def plan_config(**over) -> dict:
    """The isaac_sim role's variables as the plan takes them: four 6.x instances without GPUs."""
    base = {
        "release": "6.x",
        "image": "nvcr.io/nvidia/isaac-sim:6.0.1",
        "instance_count": 4,
        "max_instances": 8,
        "port_bases": {},
        "port_stride": 1,
        "gpu_enabled": False,
        "gpu_map": {},
        "gpu_exclusive": False,
        "memory_limit": "8g",
        "shm_size": "2g",
        "data_root": "/var/lib/isaac-sim",
        "public_address": "10.0.0.5",
        "accept_eula": True,
        "privacy_consent": False,
        "env": {},
        "secret_env_names": [],
        "docker_args": [],
        "allowed_docker_args": [],
        "app_args": [],
        "ready_timeout": 300,
        "stop_timeout": 60,
        "restart_sec": 10,
        "start_limit_burst": 5,
        "health_interval": 30,
        "health_retries": 3,
        "unhealthy_restart": 300,
        "firewall": True,
        "allowed_networks": ["10.0.0.0/8"],
        "allowed_networks_by_port": {},
    }
    base.update(over)
    return base


# two runs on two controllers, as the lock's action plugin names them (plugins/action/isaac_sim_lock.py)
ALICE = {"id": "ctl-1:100:5", "user": "alice", "controller": "ctl-1", "pid": 100, "started": "5", "play": "Deploy"}
BOB = {"id": "ctl-2:200:7", "user": "bob", "controller": "ctl-2", "pid": 200, "started": "7", "play": "Deploy"}


def lock_files(where: Path, monkeypatch) -> Path:
    """The host's lock files (runlock's LOCK, GUARD and RECORD) moved under `where`; the lock's path."""
    from ansible_collections.isaacsim.fleet.plugins.module_utils.instance import runlock

    monkeypatch.setattr(runlock, "LOCK", str(where / "isaac-sim.json"))
    monkeypatch.setattr(runlock, "GUARD", str(where / ".isaac-sim.guard"))
    monkeypatch.setattr(runlock, "RECORD", str(where / "isaac-sim.rollout.json"))
    return where / "isaac-sim.json"


def _openssl(cwd: Path, *args) -> None:
    import subprocess

    subprocess.run(["openssl", *args], cwd=cwd, check=True, capture_output=True)


def issue(cwd: Path, ca: str, name: str, usage: str, san: str = "", serial: int = 1, stem: str = "") -> None:
    """STEM.key and STEM.crt (stem: the name) in cwd for the subject name, issued by the CA of the files
    ca.key and ca.crt (paths from cwd)."""
    stem = stem or name
    (cwd / f"{stem}.ext").write_text(f"extendedKeyUsage = {usage}\n" + (f"subjectAltName = {san}\n" if san else ""))
    _openssl(cwd, "req", "-new", "-newkey", "rsa:2048", "-nodes", "-subj", f"/CN={name}", "-keyout", f"{stem}.key",
             "-out", f"{stem}.csr")  # fmt: skip
    _openssl(cwd, "x509", "-req", "-days", "2", "-in", f"{stem}.csr", "-CA", f"{ca}.crt", "-CAkey", f"{ca}.key",
             "-set_serial", str(serial), "-extfile", f"{stem}.ext", "-out", f"{stem}.crt")  # fmt: skip


def make_pki(d: Path, door_name: str) -> Path:
    """The collection's CA (ca), another CA (other); issued by ca: host gpu-1's agent's server certificate
    for 127.0.0.1 (agent.crt, named "gpu-1 agent" as the role names it), the front door's client
    certificate (door_name), a client certificate of another name; issued by other: a client certificate
    of the door's own name (in other-door/)."""
    for ca in ("ca", "other"):
        _openssl(d, "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "2", "-subj", f"/CN={ca} CA",
                 "-keyout", f"{ca}.key", "-out", f"{ca}.crt")  # fmt: skip
    issue(d, "ca", "gpu-1 agent", "serverAuth", "IP:127.0.0.1", 1, stem="agent")
    issue(d, "ca", door_name, "clientAuth", "", 2)
    issue(d, "ca", "someone else", "clientAuth", "", 3)
    (d / "other-door").mkdir()
    issue(d / "other-door", "../other", door_name, "clientAuth", "", 4)
    return d
