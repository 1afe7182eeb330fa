"""The security audit (module_utils/host/audit.py): containers out of their confinement, the key in
files and the journal, modes, the firewall as the lifecycle left it, and the probe's knocks on real
sockets of this machine."""

from __future__ import annotations

import json
import os
import socket
import threading

import pytest
from ansible_collections.isaacsim.fleet.plugins.module_utils.host import audit
from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib import layout

KEY = "nvapi-0123456789abcdef"


def inspected(name, **host_config):
    return {"Name": f"/{name}", "HostConfig": host_config}


def test_containers_out_of_their_confinement_are_named_with_the_argument_and_why():
    ours = inspected(
        "isaac-sim-0",
        SecurityOpt=["no-new-privileges"],
        DeviceRequests=[{"Driver": "nvidia", "DeviceIDs": ["0"]}],
        Binds=["/var/lib/isaac-sim/instance-0/cache:/isaac-sim/.cache:rw"],
    )
    bad = inspected(
        "planted",
        Privileged=True,
        CapAdd=["NET_ADMIN"],
        PidMode="host",
        SecurityOpt=["seccomp=unconfined"],
        Devices=[{"PathOnHost": "/dev/mem"}],
        Binds=["/var/run/docker.sock:/var/run/docker.sock"],
        Mounts=[{"Type": "bind", "Source": "/run", "Target": "/host-run"}],
    )
    found = audit.container_findings([ours, bad])
    assert {f["what"] for f in found} == {"planted"}
    whys = [f["why"] for f in found]
    assert whys[0] == "--privileged: gives the container every capability and device"
    assert any(w.startswith("--cap-add=NET_ADMIN: adds the capability NET_ADMIN") for w in whys)
    assert any(w.startswith("--pid=host: shares the host's PID namespace") for w in whys)
    assert any(w.startswith("--security-opt=seccomp=unconfined: turns off the seccomp filter") for w in whys)
    assert any(w.startswith("--device=/dev/mem") for w in whys)
    assert sum("socket" in w for w in whys) == 2  # the bind and the mount of /run, which holds it


def test_a_container_under_an_instance_s_name_is_held_to_what_its_plan_gave_it():
    """Started by hand as isaac-sim-0: everything beyond the instance's env file is a finding; what the
    plan itself gave it (its caches, its GPU, its user, a capability the site allowed) is none."""
    data = "/var/lib/isaac-sim/instance-0"
    planned = [
        "--network=host", "--user=1234:1234", "--security-opt=no-new-privileges", "--cap-add=SYS_PTRACE",
        f"--volume={data}/cache:/isaac-sim/.cache:rw", "--runtime=nvidia", "--gpus=device=0",
    ]  # fmt: skip
    env_text = "\n".join([
        f"{layout.K_CONTAINER}=isaac-sim-0", f"{layout.K_GPU}=0",
        f"{layout.K_DOCKER_ARGS}={layout.quote(layout.join_args(planned))}",
    ])  # fmt: skip
    as_planned = {
        "Name": "/isaac-sim-0",
        "Config": {"User": "1234:1234"},
        "HostConfig": {
            "SecurityOpt": ["no-new-privileges"], "CapAdd": ["CAP_SYS_PTRACE"],
            "Binds": [f"{data}/cache:/isaac-sim/.cache:rw"],
            "DeviceRequests": [{"Driver": "", "Count": 0, "DeviceIDs": ["0"], "Capabilities": [["gpu"]]}],
        },
    }  # fmt: skip
    envs = {f"{layout.CONFIG_DIR}/instance-0.env": env_text}
    assert audit.container_findings([as_planned], envs) == []
    by_hand = {
        "Name": "/isaac-sim-0",
        "Config": {"User": "0"},
        "HostConfig": {
            "SecurityOpt": ["no-new-privileges", "no-new-privileges=f"],
            "Binds": [f"{data}/cache:/isaac-sim/.cache:rw", "/srv/other:/o", "rootvol:/h"],
            "DeviceRequests": [{"Driver": "", "Count": -1, "DeviceIDs": None, "Capabilities": [["gpu"]]}],
        },
    }
    volumes = {"rootvol": {"type": "none", "o": "bind", "device": "/"}}
    found = [f["why"].split(":")[0] for f in audit.container_findings([by_hand], envs, volumes)]
    assert found == [
        "--security-opt=no-new-privileges=false",
        "--gpus=all",
        "--volume=/srv/other",
        "--volume=rootvol",
        "--user=0",
    ]
    # the same container under a name that is not ours: only what hands it the host
    foreign = dict(by_hand, Name="/planted")
    found = [f["why"].split(":")[0] for f in audit.container_findings([foreign], envs, volumes)]
    assert found == ["--security-opt=no-new-privileges=false", "--volume=rootvol"]


def test_the_key_is_found_in_files_and_the_journal_and_never_returned(tmp_path):
    (tmp_path / "etc").mkdir()
    (tmp_path / "etc" / "leak.json").write_text(f'{{"auth": "{KEY}"}}')
    (tmp_path / "etc" / "clean.txt").write_text("nothing here")
    (tmp_path / "etc" / "link").symlink_to(tmp_path / "etc" / "leak.json")
    (tmp_path / "skip").mkdir()
    (tmp_path / "skip" / "layer").write_text(KEY)
    (tmp_path / "etc" / "big").write_bytes(b"x" * 64 + KEY.encode())
    files = audit.key_files(KEY, roots=[str(tmp_path)], skip=[str(tmp_path / "skip")], max_file=60)
    assert files == [str(tmp_path / "etc" / "leak.json")]
    found = audit.key_findings(KEY, files, f"Nov 25 docker login -p {KEY}\n")
    assert [f["what"] for f in found] == [files[0], "journal"]
    assert KEY not in json.dumps(found)
    assert audit.key_files("", roots=[str(tmp_path)]) == []


def test_modes_wider_than_they_should_be():
    files = {
        "/etc/isaac-sim/instance-0.env": (0o644, "ISAAC_SIM_INSTANCE=0\nTOKEN=abc\n"),
        "/etc/isaac-sim/instance-1.env": (0o600, "ISAAC_SIM_INSTANCE=1\nTOKEN=abc\n"),
        "/etc/systemd/system/isaac-sim@.service": (0o664, "[Unit]\n"),
        "/usr/local/libexec/isaac-sim/isaac-sim-run": (0o755, "#!/bin/sh\n"),
    }
    found = audit.mode_findings(files, ["TOKEN"])
    assert [(f["what"], f["why"]) for f in found] == [
        ("/etc/isaac-sim/instance-0.env", "mode 0644 lets others than root read TOKEN"),
        ("/etc/systemd/system/isaac-sim@.service", "mode 0664 lets group or others write it"),
    ]


def env(i, ports, address=""):
    lines = [f"{layout.K_CONTAINER}=isaac-sim-{i}", f'{layout.K_PORTS}="{ports}"']
    return "\n".join(lines + ([f"{layout.K_ADDRESS}={address}"] if address else [])) + "\n"


def test_opened_ports_and_the_firewall_as_the_lifecycle_left_it():
    envs = {"a": env(0, "tcp/49100 udp/47998"), "b": env(1, "tcp/49100", "10.0.0.50")}
    status = f"{layout.K_STATUS_URL}=http://10.0.0.5:8290/status\n"
    ports = audit.opened_ports(envs, status, hub=True)
    assert [(p["proto"], p["port"], p["address"]) for p in ports] == [
        ("tcp", 8290, ""),
        ("tcp", 14090, ""),
        ("udp", 47998, ""),
        ("tcp", 49100, ""),
        ("tcp", 49100, "10.0.0.50"),
    ]
    kept = {"listing": "table inet isaac_sim {}\n"}
    assert audit.firewall_findings(kept, "table inet isaac_sim {}\n", ports) == []
    assert audit.firewall_findings(None, "", ports)[0]["why"].startswith("no firewall guards")
    assert "not loaded" in audit.firewall_findings(kept, "", ports)[0]["why"]
    assert "differ" in audit.firewall_findings(kept, "table inet isaac_sim { x }\n", ports)[0]["why"]
    assert audit.firewall_findings(None, "", []) == []


@pytest.fixture
def servers():
    """A TCP listener, a UDP port that answers and one that stays silent, on 127.0.0.1."""
    tcp = socket.create_server(("127.0.0.1", 0))
    echo = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    echo.bind(("127.0.0.1", 0))
    silent = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    silent.bind(("127.0.0.1", 0))
    closed = socket.create_server(("127.0.0.1", 0))
    closed_port = closed.getsockname()[1]
    closed.close()

    def answer():
        data, peer = echo.recvfrom(512)
        echo.sendto(b"hi " + data, peer)

    threading.Thread(target=answer, daemon=True).start()
    yield {
        "tcp": tcp.getsockname()[1],
        "udp": echo.getsockname()[1],
        "silent": silent.getsockname()[1],
        "closed": closed_port,
    }
    for s in (tcp, echo, silent):
        s.close()


def test_the_probe_knocks_on_real_sockets_and_knows_when_it_is_inside(servers):
    def target(proto, port, networks=()):
        return {"host": "h1", "address": "127.0.0.1", "proto": proto, "port": port, "kind": "signal",
                "networks": list(networks)}  # fmt: skip

    rows = audit.probe(
        [
            target("tcp", servers["tcp"]),
            target("udp", servers["udp"]),
            target("udp", servers["silent"]),
            target("tcp", servers["closed"]),
            target("tcp", servers["tcp"], ["127.0.0.0/8"]),
            # knocked on at once: each answer still in its target's place
            target("udp", servers["silent"]),
            target("tcp", servers["closed"]),
        ],
        timeout=0.5,
    )
    assert [r["answer"] for r in rows] == ["open", "open", "silent", "closed", "open", "silent", "closed"]
    assert [r["inside"] for r in rows] == [False, False, False, False, True, False, False]
    rows = rows[:5]
    assert rows[0]["source"] == "127.0.0.1"
    found = audit.probe_findings(rows)
    assert [f["what"] for f in found] == [
        f"h1 tcp/127.0.0.1:{servers['tcp']} (signal)",
        f"h1 udp/127.0.0.1:{servers['udp']} (signal)",
    ]
    report = audit.fleet({"h1": {"findings": []}, "h2": {}}, rows)
    assert report["findings"] == 2 and report["clean"] is False
    assert "h2                       host          did not answer: not audited" in report["table"]
    # the TCP port knocked on from inside its networks answered: nothing to find there; the others were not
    assert report["table"][-1].startswith("(not knocked on from inside: 3 port(s), no probe host is in their")


def row(answer, inside, proto="tcp", port=49100, prober="h3"):
    return {"host": "h1", "address": "10.0.0.5", "proto": proto, "port": port, "kind": "signal", "source": "10.0.0.7",
            "prober": prober, "inside": inside, "answer": answer}  # fmt: skip


def test_a_port_must_be_silent_outside_its_networks_and_answer_inside_them():
    rows = [
        row("open", False, port=1),
        row("silent", False, port=2),
        row("open", True, port=3),
        # dropped on the way from an allowed network: a site firewall that closes what must answer
        row("silent", True, port=4),
        # nothing listens (the instance is down: status's business), or UDP that may not answer a datagram
        row("closed", True, port=5),
        row("silent", True, "udp", port=6),
    ]
    found = audit.probe_findings(rows)
    assert [(f["what"], f["why"].split(",")[0]) for f in found] == [
        ("h1 tcp/10.0.0.5:1 (signal)", "answers 10.0.0.7 (h3)"),
        ("h1 tcp/10.0.0.5:4 (signal)", "does not answer 10.0.0.7 (h3)"),
    ]
    report = audit.fleet({"h1": {"findings": [], "ports": [{}]}, "h3": {"findings": [], "ports": [{}]}}, rows, ["h3"])
    assert report["findings"] == 2
    assert report["table"][-4:] == [
        "(not knocked on: 1 port(s) of h3, the probe host itself; audit it from another audit_probe_host)",
        "(not knocked on from outside: 4 port(s), every probe host is inside their allowed networks; add a host "
        "outside them to audit_probe_hosts)",
        "(not knocked on from inside: 2 port(s), no probe host is in their allowed networks; add one to "
        "audit_probe_hosts to check that they answer there)",
        "(not judged: 1 UDP port(s) gave no answer from inside their allowed networks; a UDP port may not answer a "
        "stray datagram)",
    ]


class FakeIO(audit.HostIO):
    def __init__(self, files, containers, journal="", listing=""):
        class Docker:
            def get(self, endpoint):
                if endpoint.startswith("/containers/json"):
                    return [{"Id": c["Name"]} for c in containers]
                if endpoint == "/volumes":
                    return {"Volumes": [{"Name": "rootvol", "Options": {"type": "none", "o": "bind", "device": "/"}}]}
                return next(c for c in containers if endpoint == f"/containers/{c['Name']}/json")

        def run(argv):
            if argv[0] == "journalctl":
                return 0, journal, ""
            family = argv[3]
            return (0, listing, "") if family == "inet" and listing else (1, "", "No such file or directory")

        def glob(pattern):
            folder, _sep, name = pattern.rpartition("/")
            return [p for p in files if p.startswith(folder + "/") and (name == "*" or p == pattern
                    or (name.endswith("*") and os.path.basename(p).startswith(name[:-1])))]  # fmt: skip

        def lstat(path):
            return os.stat_result((0o100000 | files[path][0], 0, 0, 1, 0, 0, len(files[path][1]), 0, 0, 0))

        super().__init__(Docker(), run, glob, lstat, lambda p: files.get(p, (0, None))[1], lambda key: [],
                         lambda: "10.0.0.5")  # fmt: skip


def test_a_host_report_lists_its_ports_with_their_networks_and_its_findings():
    model = {
        "default": ["10.20.0.0/16"],
        "by_kind": {"status": ["10.9.0.0/24"]},
        "ports": [["isaac-sim-0", "tcp", 49100, "signal", ""], ["host", "tcp", 8290, "status", ""]],
    }
    listing = "table inet isaac_sim {}\n"
    files = {
        f"{layout.CONFIG_DIR}/instance-0.env": (0o644, env(0, "tcp/49100")),
        f"{layout.CONFIG_DIR}/{layout.STATUS_ENV}": (0o644, f"{layout.K_STATUS_URL}=http://10.0.0.5:8290/status\n"),
        layout.FIREWALL_STATE: (0o644, json.dumps({"model": model, "listing": listing})),
    }
    io = FakeIO(files, [inspected("isaac-sim-0", SecurityOpt=["no-new-privileges"])], listing=listing)
    report = audit.host_report(io, KEY, [])
    assert report["findings"] == [] and report["address"] == "10.0.0.5"
    assert [(p["port"], p["kind"], p["networks"]) for p in report["ports"]] == [
        (8290, "status", ["10.9.0.0/24"]),
        (49100, "signal", ["10.20.0.0/16"]),
    ]
    assert audit.targets({"h1": report, "h2": {}})[0] == dict(
        report["ports"][0], host="h1", address="10.0.0.5", prober=""
    )
    # a probe host that is itself audited knocks on the others only, and the table says so: from itself every
    # port of its own answers (six false findings were reported that way)
    assert audit.targets({"h1": report, "h2": report}, probe_host="h1") == [
        dict(p, host="h2", address="10.0.0.5", prober="h1") for p in report["ports"]
    ]
    table = audit.fleet({"h1": report, "h2": report}, [], ["h1"])["table"]
    assert table[-1] == (
        "(not knocked on: 2 port(s) of h1, the probe host itself; audit it from another audit_probe_host)"
    )
    flushed = audit.host_report(FakeIO(files, [], journal=f"login {KEY}"), KEY, [])
    assert [f["check"] for f in flushed["findings"]] == ["registry key", "firewall"]
