"""The firewall (isaac_sim_allowed_networks) on the fleet's three hosts, probed from the others.

Runs after every fleet module but the gateway's (file order), which finds the first host's viewers
in place. The first host is deployed with the second host as its only allowed network (and the
third for the status endpoint alone): from the second every instance's signal port, stream port (a
real UDP exchange with the stand-in) and web viewer answer; from the third, and from this machine,
none does. The site's own nftables table and Docker's rules stay byte for byte; a Docker restart, a
reboot and a restart of the site's nftables.service keep the rules. playbooks/audit.yml finds the
first host clean, probed from this machine and from the third, and names each finding planted on it
(a container with an added capability and Docker's socket, one started by hand under an instance's
name as root with no-new-privileges off, a file with the registry key, a port opened by hand). The
third host (no web viewer there) scales 4 -> 2 and exactly the rules of instances 2 and 3 go.
"""

from __future__ import annotations

import difflib
import json
import re
import socket

import pytest
import testbed
from fleethosts import INSTANCES, SIGNAL, all_ready, ip, playbook, probe, ready_fleet, sh, squash
from test_stream_addresses import VIEWER, viewer_image
from testbed import ROOT

STREAM = 47998
SITE_RULES = (
    "nft 'table inet site; delete table inet site' && nft add table inet site && "
    "nft add chain inet site input '{ type filter hook input priority 10; policy accept; }' && "
    "nft add rule inet site input tcp dport 2222 accept"
)


@pytest.fixture(scope="module")
def fleet():
    return ready_fleet()


def block(i: int) -> list:
    return [("tcp", SIGNAL + i, ""), ("udp", STREAM + i, ""), ("tcp", VIEWER + i, "/stream-config.js")]


def ours(host: str) -> str:
    return sh(host, "nft list table inet isaac_sim; nft list table netdev isaac_sim 2>/dev/null; true")


def others(host: str) -> str:
    """Every table but the collection's, counters left out (Docker's count the traffic)."""
    tables = [line.split()[1:] for line in sh(host, "nft list tables").splitlines() if line.strip()]
    # (nft's warning that iptables-nft owns Docker's tables goes to stderr)
    text = "".join(
        sh(host, f"nft list table {family} {name} 2>/dev/null") for family, name in tables if name != "isaac_sim"
    )
    return re.sub(r"counter packets \d+ bytes \d+", "counter", text)


def from_here(address: str, port: int) -> str:
    try:
        socket.create_connection((address, port), timeout=3).close()
    except socket.timeout:
        return "timeout"
    except OSError as exc:
        return str(exc)
    return "open"


def answered_only_from(allowed: str, refused: str, target: str) -> None:
    wanted = [p for i in range(INSTANCES) for p in block(i)]

    def every_one_answers():
        yes = probe(allowed, target, wanted)
        for i in range(INSTANCES):
            assert yes[f"tcp/{SIGNAL + i}"].startswith("isaac-sim-standin signal"), yes
            assert yes[f"udp/{STREAM + i}"].startswith("isaac-sim-standin stream"), yes
            assert yes[f"tcp/{VIEWER + i}"].startswith("HTTP/1.") and " 200" in yes[f"tcp/{VIEWER + i}"], yes
        return True

    # the viewers start once their instance is ready: after a restart, give them their time
    testbed.wait_for(every_one_answers, timeout=120, what=f"every port of {target} to answer {allowed}")
    no = probe(refused, target, wanted)
    assert set(no.values()) == {"timeout"}, no


def test_ports_answer_the_allowed_networks_only_and_other_rules_stay_as_they_were(fleet):
    first, second, third = fleet
    sh(first, SITE_RULES)
    before = others(first)
    assert "tcp dport 2222 accept" in before and "table ip filter" in before
    # with NVIDIA's web viewer beside each instance: a companion's port is covered too
    allowed = {
        "isaac_sim_web_viewer_image": viewer_image(first),
        "isaac_sim_allowed_networks": [f"{ip(second)}/32"],
        "isaac_sim_allowed_networks_by_port": {"status": [f"{ip(third)}/32"]},
    }
    run = playbook("deploy.yml", allowed, limit=first)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-2000:]
    answered_only_from(second, third, ip(first))
    # the status endpoint: the third host's alone
    assert sh(third, f"curl -sf -m 4 http://{ip(first)}:8290/status >/dev/null && echo ok").strip() == "ok"
    assert probe(second, ip(first), [("tcp", 8290, "/status")]) == {"tcp/8290": "timeout"}
    # this machine is in neither network
    assert from_here(ip(first), SIGNAL) == "timeout"
    assert others(first) == before
    # a re-run changes nothing, the rules included
    again = playbook("deploy.yml", allowed, limit=first)
    assert again.returncode == 0 and re.search(rf"{first}\s*:.*changed=0", again.stdout), again.stdout[-2000:]


def audit(tmp_path, limit: str, **extra) -> tuple:
    run = playbook("audit.yml", {"audit_report_dir": str(tmp_path), **extra}, limit=limit)
    return run, json.loads((tmp_path / "audit.json").read_text())


def test_the_audit_finds_the_host_clean_and_each_planted_finding(fleet, tmp_path):
    first, third = fleet[0], fleet[2]
    run, report = audit(tmp_path, first)
    assert run.returncode == 0 and report["clean"], run.stdout[-3000:]
    # knocked on from this machine, outside every allowed network: every port silent
    mine = [r for r in report["probed"] if r["host"] == first]
    assert len(mine) == 13 and {r["answer"] for r in mine} == {"silent"} and not any(r["inside"] for r in mine)
    # from the third host, inside the status endpoint's network only: that one is not checked, the rest are
    run, report = audit(tmp_path, first, audit_probe_host=third)
    assert run.returncode == 0 and report["clean"], run.stdout[-3000:]
    inside = {r["port"] for r in report["probed"] if r["inside"]}
    assert inside == {8290} and "(not checked: 1 port(s)" in report["table"][-1]

    key = (ROOT / "tests" / "fixtures" / "registry" / "ngc-api-key").read_text().strip()
    image = sh(first, "docker inspect -f '{{.Config.Image}}' isaac-sim-0").strip()
    # a container started by hand under instance 3's own name, as root with no-new-privileges turned off
    # in Go's spelling: judged against what instance 3's plan gives it
    sh(
        first,
        f"systemctl stop isaac-sim@3 && docker run -d --name isaac-sim-3 --user 0 --security-opt no-new-privileges=f "
        f"--entrypoint sleep {image} 600 && "
        f"docker run -d --name planted --cap-add NET_ADMIN -v /var/run/docker.sock:/var/run/docker.sock "
        f"--entrypoint sleep {image} 600 && printf %s '{key}' > /root/leak.txt && "
        "nft insert rule inet isaac_sim isaac-sim-0 tcp dport 49100 accept",
    )
    try:
        run, report = audit(tmp_path, first)
    finally:
        handle = sh(first, "nft -a list chain inet isaac_sim isaac-sim-0 | awk '/accept # handle/ {print $NF}'").strip()
        sh(
            first,
            f"docker rm -f planted isaac-sim-3; rm -f /root/leak.txt; "
            f"nft delete rule inet isaac_sim isaac-sim-0 handle {handle}; systemctl start isaac-sim@3",
        )
    assert run.returncode != 0 and "7 finding(s) on " + first in squash(run.stdout + run.stderr)
    found = {(f["check"], f["what"], f["why"].split(":", 1)[0]) for f in report["hosts"][0]["findings"]}
    assert found == {
        ("container", "planted", "--cap-add=NET_ADMIN"),
        ("container", "planted", "--volume=/var/run/docker.sock"),
        ("container", "isaac-sim-3", "--user=0"),
        ("container", "isaac-sim-3", "--security-opt=no-new-privileges=false"),
        ("registry key", "/root/leak.txt", "holds the registry key (isaac_sim_registry_password)"),
        ("firewall", "isaac_sim", "the loaded rules differ from those the last deploy loaded"),
        (
            "port",
            f"{first} tcp/{ip(first)}:{SIGNAL} (signal)",
            f"answers {report['probed'][0]['source']}, which is outside the allowed networks",
        ),
    }
    assert key not in run.stdout + run.stderr + (tmp_path / "audit.json").read_text()
    run, report = audit(tmp_path, first)
    assert run.returncode == 0 and report["clean"]


def test_rules_survive_a_docker_restart_a_reboot_and_the_site_s_nftables_restart(fleet):
    first, second, third = fleet
    listing = ours(first)
    assert f"ip saddr {{ {ip(second)} }} accept" in listing or f"ip saddr {ip(second)} accept" in listing
    sh(first, "systemctl restart docker")
    testbed.wait_for(lambda: all_ready(first), timeout=240, what=f"{first} ready after Docker's restart")
    assert ours(first) == listing
    answered_only_from(second, third, ip(first))

    testbed.client().containers.get(first).restart(timeout=30)
    testbed.wait_for(
        lambda: sh(first, "systemctl is-system-running --wait || true").strip() in ("running", "degraded"),
        timeout=120,
        what="systemd to boot",
    )
    testbed.wait_for(lambda: all_ready(first), timeout=240, what=f"{first} ready after its reboot")
    assert ours(first) == listing
    answered_only_from(second, third, ip(first))

    # Debian's /etc/nftables.conf flushes the whole ruleset; ours comes back after it
    sh(first, "systemctl restart nftables && systemctl reload nftables")
    assert ours(first) == listing
    assert probe(third, ip(first), block(0)) == dict.fromkeys(["tcp/49100", "udp/47998", "tcp/8210"], "timeout")
    # the flush took Docker's rules too (the site's doing): Docker puts them back when it starts
    sh(first, "systemctl restart docker")
    testbed.wait_for(lambda: all_ready(first), timeout=240, what=f"{first} ready after Docker's restart")
    assert ours(first) == listing


def test_a_scale_down_removes_exactly_the_rules_of_the_instances_that_go(fleet):
    third = fleet[2]
    before = ours(third).splitlines()
    run = playbook("deploy.yml", {"isaac_sim_instance_count": 2}, limit=third)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-2000:]
    after = ours(third).splitlines()
    diff = [line for line in difflib.ndiff(before, after) if line[:1] in "+-"]
    assert not [line for line in diff if line.startswith("+")], diff
    removed = sorted(line[2:].strip() for line in diff if line[2:].strip() not in ("", "}"))
    assert removed == sorted(
        [
            "chain isaac-sim-2 {",
            "chain isaac-sim-3 {",
            "jump isaac-sim-2",
            "jump isaac-sim-3",
            f"tcp dport {SIGNAL + 2} jump allow-signal",
            f"tcp dport {SIGNAL + 3} jump allow-signal",
            f"udp dport {STREAM + 2} jump allow-stream",
            f"udp dport {STREAM + 3} jump allow-stream",
        ]
    ), diff
