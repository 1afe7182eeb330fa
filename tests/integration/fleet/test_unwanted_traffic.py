"""The firewall (isaac_sim_allowed_networks) on the fleet's three hosts, probed from the others.

Runs after every fleet module but the gateway's (file order), which finds the first host's viewers
in place. The first host gets a site table of its own whose input chain drops by default (policy
drop, SSH and established traffic accepted; in the file /etc/nftables.conf includes) and is then
deployed with the second host as its only allowed network (and the third for the status endpoint
alone): isaac_sim_firewall_site_policy refuse stops before any change and prints the exact rules,
which, run as given, let the next deploy through; add keeps the same accepts itself. From the
second every instance's signal port, stream port (a real UDP exchange with the stand-in) and web
viewer answer; from the third, and from this machine, none does. Docker's rules and the site's own
stay byte for byte (but our accepts in the site's chain); a Docker restart, a reboot and a restart
of the site's nftables.service keep the rules. playbooks/audit.yml finds the first host clean,
knocked on from inside and outside the allowed networks, and names each finding planted on it (a
container with an added capability and Docker's socket, one started by hand under an instance's
name as root with no-new-privileges off, a file with the registry key, a port opened by hand, and
the ports the site's chain drops once an accept of ours is taken from it). Then firewalld (Debian's
package, its default zone) runs on the third host (no web viewer there), and a deploy that scales
it 4 -> 2 (the rules of instances 2 and 3 go) opens the instances to the first host alone through
a firewalld policy of the collection's.
"""

from __future__ import annotations

import json
import os
import re
import socket
import subprocess

import pytest
import testbed
from fleethosts import (
    INSTANCES,
    PLAIN,
    SIGNAL,
    all_ready,
    ip,
    playbook,
    playbook_argv,
    probe,
    ready_fleet,
    sh,
    squash,
)
from test_stream_addresses import VIEWER, viewer_image
from testbed import ROOT

STREAM = 47998
# the site's own table: its input chain drops what it does not accept, as a hardened host's does
SITE_FILE = "/etc/nftables-site.nft"
SITE_TABLE = """table inet site
delete table inet site
table inet site {
\tchain input {
\t\ttype filter hook input priority 10; policy drop;
\t\tct state established,related accept
\t\tiifname "lo" accept
\t\ttcp dport { 22, 2222 } accept
\t}
}
"""
OUR_COMMENT = 'comment "isaac-sim '


@pytest.fixture(scope="module")
def fleet():
    found = ready_fleet()
    yield found
    # the gateway's module comes next: the first host without the site's default drop, the third without firewalld
    sh(found[0], f"sed -i '\\|{SITE_FILE}|d' /etc/nftables.conf; rm -f {SITE_FILE}; nft delete table inet site || true")
    sh(found[2], "systemctl disable --now firewalld 2>/dev/null || true")


def block(i: int) -> list:
    return [("tcp", SIGNAL + i, ""), ("udp", STREAM + i, ""), ("tcp", VIEWER + i, "/stream-config.js")]


def ours(host: str) -> str:
    return sh(host, "nft list table inet isaac_sim; nft list table netdev isaac_sim 2>/dev/null; true")


def others(host: str) -> str:
    """Every table but the collection's, counters left out (Docker's count the traffic), and the
    accepts of ours in the site's chain left out."""
    tables = [line.split()[1:] for line in sh(host, "nft list tables").splitlines() if line.strip()]
    # (nft's warning that iptables-nft owns Docker's tables goes to stderr)
    text = "".join(
        sh(host, f"nft list table {family} {name} 2>/dev/null") for family, name in tables if name != "isaac_sim"
    )
    text = "".join(line for line in text.splitlines(keepends=True) if OUR_COMMENT not in line)
    return re.sub(r"counter packets \d+ bytes \d+", "counter", text)


def accepts_of_ours(host: str) -> list:
    """The rules of ours in the site's chain, as nft lists them."""
    return [line.strip() for line in sh(host, "nft list chain inet site input").splitlines() if OUR_COMMENT in line]


def digests(rules: list) -> list:
    return sorted(re.findall(r'comment "(isaac-sim [0-9a-f]+)"', "\n".join(rules)))


def refusal(run) -> str:
    """The plan's refusal as the module returned it (the JSON result format: its message exact), on
    stdout or stderr (molecule's ansible.cfg: display_failed_stderr)."""
    for line in (run.stdout + "\n" + run.stderr).splitlines():
        if "FAILED! =>" in line:
            msg = json.loads(line.split("=>", 1)[1]).get("msg", "")
            if "rejected before any change" in msg:
                return msg
    raise AssertionError(run.stdout[-3000:] + run.stderr[-3000:])


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


def test_ports_answer_the_allowed_networks_only_beside_a_site_table_that_drops_by_default(fleet):
    first, second, third = fleet
    sh(first, f"printf '%s' '{SITE_TABLE}' > {SITE_FILE} && nft -f {SITE_FILE} && "
              f"echo 'include \"{SITE_FILE}\"' >> /etc/nftables.conf")  # fmt: skip
    before = others(first)
    assert "tcp dport { 22, 2222 } accept" in before and "table ip filter" in before
    ours_before = ours(first)
    # with NVIDIA's web viewer beside each instance: a companion's port is covered too
    allowed = {
        "isaac_sim_web_viewer_image": viewer_image(first),
        "isaac_sim_allowed_networks": [f"{ip(second)}/32"],
        "isaac_sim_allowed_networks_by_port": {"status": [f"{ip(third)}/32"]},
    }
    # refuse: the site's chain is named, with the exact rules, and nothing changed
    argv = playbook_argv("deploy.yml", dict(allowed, isaac_sim_firewall_site_policy="refuse"), first)
    env = dict(os.environ, **PLAIN, ANSIBLE_CALLBACK_RESULT_FORMAT="json")
    run = subprocess.run(argv, capture_output=True, text=True, env=env, cwd=ROOT, timeout=900, check=False)
    assert run.returncode != 0
    msg = refusal(run)
    assert "the site's chain inet site input drops by default (policy drop)" in msg, msg
    commands = re.findall(r"nft '(insert rule inet site input [^']+)'", msg)
    # TCP from the second, the status endpoint's TCP from the third, UDP from the second, and each protocol
    # from the loopback and Docker's bridges (two rules: an exact name set, and br-*)
    assert len(commands) == 7 and all(OUR_COMMENT in c for c in commands), msg
    assert others(first) == before and ours(first) == ours_before and accepts_of_ours(first) == []
    # run as given, the next deploy goes on
    for command in commands:
        sh(first, f"nft '{command}'")
    run = playbook("deploy.yml", dict(allowed, isaac_sim_firewall_site_policy="refuse"), limit=first)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-2000:]
    answered_only_from(second, third, ip(first))

    # add (the default): the site's file loaded again (our copies gone), the deploy puts the accepts back
    sh(first, f"nft -f {SITE_FILE}")
    run = playbook("deploy.yml", allowed, limit=first)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-2000:]
    assert digests(accepts_of_ours(first)) == digests(commands)
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
    first, second, third = fleet
    # one run, knocked on from this machine and from the second and the third
    run, report = audit(tmp_path, first, audit_probe_hosts=["localhost", second, third])
    assert run.returncode == 0 and report["clean"], run.stdout[-3000:]
    # knocked on from this machine, outside every allowed network: every port silent
    mine = [r for r in report["probed"] if r["host"] == first and r["prober"] == "localhost"]
    assert len(mine) == 13 and {r["answer"] for r in mine} == {"silent"} and not any(r["inside"] for r in mine)
    # from the second (inside the instances' networks, outside the status endpoint's) and the third (the other
    # way round): every port answers where it must and is silent where it must, both directions knocked on
    inside = {(r["prober"], r["port"], r["answer"]) for r in report["probed"] if r["inside"]}
    assert {(p, port) for p, port, _a in inside} == {(third, 8290)} | {
        (second, port) for i in range(INSTANCES) for port in (SIGNAL + i, STREAM + i, VIEWER + i)
    }
    assert {a for _p, _port, a in inside} == {"open"} and not report["table"][-1].startswith("(")

    key = (ROOT / "tests" / "fixtures" / "registry" / "ngc-api-key").read_text().strip()
    image = sh(first, "docker inspect -f '{{.Config.Image}}' isaac-sim-0").strip()
    # the accept of ours for the second host's TCP taken from the site's chain (the site's doing)
    [taken] = [a for a in accepts_of_ours(first) if f"ip saddr {ip(second)} tcp dport" in a]
    # a container started by hand under instance 3's own name, as root with no-new-privileges turned off
    # in Go's spelling: judged against what instance 3's plan gives it; a port opened by hand in our table and
    # the site's
    sh(
        first,
        f"systemctl stop isaac-sim@3 && docker run -d --name isaac-sim-3 --user 0 --security-opt no-new-privileges=f "
        f"--entrypoint sleep {image} 600 && "
        f"docker run -d --name planted --cap-add NET_ADMIN -v /var/run/docker.sock:/var/run/docker.sock "
        f"--entrypoint sleep {image} 600 && printf %s '{key}' > /root/leak.txt && "
        "nft insert rule inet isaac_sim isaac-sim-0 tcp dport 49100 accept && "
        "nft insert rule inet site input tcp dport 49100 accept && "
        f"nft delete rule inet site input handle $(nft -a list chain inet site input | grep -F '{taken}' "
        "| awk '{print $NF}')",
    )
    try:
        run, report = audit(tmp_path, first, audit_probe_hosts=["localhost", second])
    finally:
        handle = sh(first, "nft -a list chain inet isaac_sim isaac-sim-0 | awk '/accept # handle/ {print $NF}'").strip()
        site = sh(first, "nft -a list chain inet site input | awk '/dport 49100 accept # handle/ {print $NF}'").strip()
        sh(
            first,
            f"docker rm -f planted isaac-sim-3; rm -f /root/leak.txt; "
            f"nft delete rule inet isaac_sim isaac-sim-0 handle {handle}; "
            f"nft delete rule inet site input handle {site}; "
            # the site's accepts of ours back as isaac-sim-firewall-site puts them (after the site's reload)
            "python3 /usr/local/libexec/isaac-sim/isaac-sim-firewall-site apply; systemctl start isaac-sim@3",
        )
    # 49100 answers the second through the site's own accept; the other TCP ports the second may reach are dropped
    silent = [SIGNAL + i for i in range(1, INSTANCES)] + [VIEWER + i for i in range(INSTANCES)]
    assert run.returncode != 0 and f"{7 + len(silent)} finding(s) on " + first in squash(run.stdout + run.stderr)
    found = {(f["check"], f["what"], f["why"].split(":", 1)[0]) for f in report["hosts"][0]["findings"]}
    here = next(r["source"] for r in report["probed"] if r["prober"] == "localhost")
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
            f"answers {here} (localhost), which is outside the allowed networks",
        ),
    } | {
        (
            "port",
            f"{first} tcp/{ip(first)}:{port} ({'signal' if port >= SIGNAL else 'web_viewer'})",
            f"does not answer {ip(second)} ({second}), which is inside its allowed networks",
        )
        for port in silent
    }
    assert key not in run.stdout + run.stderr + (tmp_path / "audit.json").read_text()
    # no audit again to see the host clean (its clean verdict is the first run's): the plants are gone, and
    # the site's chain has every accept of ours back
    assert sh(first, "docker ps -aq --filter name=^planted$; ls /root/leak.txt 2>/dev/null; true").strip() == ""
    assert len(accepts_of_ours(first)) == 7


def test_rules_survive_a_docker_restart_a_reboot_and_the_site_s_nftables_restart(fleet):
    first, second, third = fleet
    listing = ours(first)
    assert f"ip saddr {{ {ip(second)} }} accept" in listing or f"ip saddr {ip(second)} accept" in listing
    # (one Docker restart, the last step below, after the site's flush: it rewrites Docker's rules beside
    # ours as any restart does)

    # a reboot, a power cut as before: systemd (PID 1, no STOPSIGNAL) takes Docker's SIGTERM for a
    # re-exec, so any grace time only waited for the kill
    testbed.client().containers.get(first).restart(timeout=0)
    testbed.wait_for(
        lambda: sh(first, "systemctl is-system-running --wait || true").strip() in ("running", "degraded"),
        timeout=120,
        what="systemd to boot",
    )
    testbed.wait_for(lambda: all_ready(first), timeout=240, what=f"{first} ready after its reboot")
    assert ours(first) == listing
    answered_only_from(second, third, ip(first))

    # Debian's /etc/nftables.conf flushes the whole ruleset and loads the site's table again (policy drop,
    # without our accepts); ours come back after it, the accepts in the site's chain too
    sh(first, "systemctl restart nftables && systemctl reload nftables")
    assert ours(first) == listing and len(accepts_of_ours(first)) == 7
    answered_only_from(second, third, ip(first))
    # the flush took Docker's rules too (the site's doing): Docker puts them back when it starts
    sh(first, "systemctl restart docker")
    testbed.wait_for(lambda: all_ready(first), timeout=240, what=f"{first} ready after Docker's restart")
    assert ours(first) == listing
    answered_only_from(second, third, ip(first))


def rules_of(i: int) -> set:
    """The lines of instance i in our table (stripped), as nft lists them."""
    return {
        f"chain isaac-sim-{i} {{",
        f"jump isaac-sim-{i}",
        f"tcp dport {SIGNAL + i} jump allow-signal",
        f"udp dport {STREAM + i} jump allow-stream",
    }


def test_with_firewalld_running_the_instances_answer_the_allowed_host_through_a_policy_of_ours(fleet):
    first, second, third = fleet
    # Debian's firewalld, started by its package in its default zone (public: SSH and DHCPv6 only)
    install = "DEBIAN_FRONTEND=noninteractive apt-get install -y -q firewalld >/tmp/firewalld.log 2>&1"
    sh(third, f"{install} || (apt-get update -q >/dev/null && {install})")
    # (the package starts it; a start still under way answers "not running")
    sh(third, "systemctl enable --now firewalld")
    testbed.wait_for(
        lambda: sh(third, "firewall-cmd --state 2>&1; true").strip() == "running", timeout=60, what="firewalld"
    )
    # its default configuration, whatever an earlier run of this test left (our policy is permanent)
    sh(third, "firewall-cmd --permanent --delete-policy isaac-sim >/dev/null 2>&1; firewall-cmd --reload")
    two = [("tcp", SIGNAL + i, "") for i in range(2)] + [("udp", STREAM + i, "") for i in range(2)]
    # the third host's own instances closed to everyone by firewalld's reject, whatever our table accepts
    closed = probe(first, ip(third), two)
    assert not [v for v in closed.values() if v.startswith("isaac-sim-standin")], closed
    allowed = {
        "isaac_sim_instance_count": 2,
        "isaac_sim_allowed_networks": [f"{ip(first)}/32"],
        # the gateway's module reads this host's status endpoint from the mirror's host
        "isaac_sim_allowed_networks_by_port": {"status": ["172.16.0.0/12"]},
    }
    four = {line.strip() for line in ours(third).splitlines()}
    assert set().union(*map(rules_of, range(INSTANCES))) <= four, sorted(four)
    run = playbook("deploy.yml", allowed, limit=third)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-2000:]
    # the deploy scaled 4 -> 2: the rules of instances 2 and 3 went with them, those of 0 and 1 stay (that a
    # scale-down's rules differ by exactly these lines is test_firewall.py's, a unit test)
    two_left = {line.strip() for line in ours(third).splitlines()}
    assert not (rules_of(2) | rules_of(3)) & two_left, sorted(two_left)
    assert (rules_of(0) | rules_of(1)) <= two_left, sorted(two_left)
    rich = sh(third, "firewall-cmd --policy isaac-sim --list-rich-rules")
    assert f'source address="{ip(first)}/32" port port="{SIGNAL}-{SIGNAL + 1}" protocol="tcp" accept' in rich, rich
    permanent = sh(third, "firewall-cmd --permanent --policy isaac-sim --list-rich-rules")
    assert sorted(permanent.splitlines()) == sorted(rich.splitlines())
    yes = probe(first, ip(third), two)
    assert all(yes[f"tcp/{SIGNAL + i}"].startswith("isaac-sim-standin signal") for i in range(2)), yes
    assert all(yes[f"udp/{STREAM + i}"].startswith("isaac-sim-standin stream") for i in range(2)), yes
    assert set(probe(second, ip(third), two).values()) == {"timeout"}
    # firewalld's own reload keeps the policy (permanent), and a re-run changes nothing
    sh(third, "firewall-cmd --reload")
    assert probe(first, ip(third), two)[f"tcp/{SIGNAL}"].startswith("isaac-sim-standin signal")
    again = playbook("deploy.yml", allowed, limit=third)
    assert again.returncode == 0 and re.search(rf"{third}\s*:.*changed=0", again.stdout), again.stdout[-2000:]
