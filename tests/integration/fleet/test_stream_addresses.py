"""Instances at addresses of their own (isaac_sim_network_mode: macvlan), reached from another host.

Runs after test_rollout.py, in file order. NVIDIA's WebRTC Streaming Client for 4.x/5.x connects to
port 49100 only; with own addresses every instance keeps that port. The first host of the fleet moves
its four instances onto a Docker macvlan network on its eth0 (the test network), with NVIDIA's web
viewer (the stand-in) beside each in the instance's namespace; a second host reaches each instance
at its own address and at no other. Bad input is refused before anything changes, and the last
test moves the instances back onto the host's network, which removes the macvlan network.
"""

from __future__ import annotations

import ipaddress
import json
import re

import pytest
import testbed
from fleethosts import INSTANCES, SIGNAL, all_ready, containers, hosts, ip, playbook, probe, sh, squash

VIEWER = 8210


@pytest.fixture(scope="module")
def fleet():
    found = hosts()
    for h in found[:2]:
        testbed.wait_for(lambda h=h: all_ready(h), timeout=180, what=f"{h} ready")
    return found


def lan(host: str) -> ipaddress.IPv4Interface:
    [link] = json.loads(sh(host, "ip -j -4 addr show eth0"))
    info = link["addr_info"][0]
    return ipaddress.IPv4Interface(f"{info['local']}/{info['prefixlen']}")


def pool(host: str, n: int = INSTANCES) -> list:
    """n addresses at the top of the test network, far from those Docker gives the test hosts."""
    net = lan(host).network
    return [str(net.broadcast_address - 20 + k) for k in range(n)]


def viewer_image(host: str) -> str:
    current = re.search(r'^ISAAC_SIM_IMAGE="([^"]+)"', sh(host, "cat /etc/isaac-sim/instance-0.env"), re.M).group(1)
    registry = current.split("/", 1)[0]
    return f"{registry}/fixtures/isaac-sim-web-viewer:2.1.5"


def own(host: str, addresses: list, **extra) -> dict:
    return {"isaac_sim_network_mode": "macvlan", "isaac_sim_address_pool": addresses, **extra}


def tcp(from_host: str, address: str, port: int) -> str:
    """What a client on from_host reads from address:port: its first line, "refused" when the address
    answers that nothing listens there, "timeout" when nothing answers at all."""
    probe = f"exec 3<>/dev/tcp/{address}/{port} && printf 'hello\\r\\n' >&3 && head -c 200 <&3"
    out = sh(
        from_host,
        f'out=$(timeout 5 bash -c "{probe}" 2>&1); rc=$?; '
        'if [ "$rc" = 124 ]; then echo timeout; '
        'elif printf %s "$out" | grep -q "Connection refused"; then echo refused; '
        'else printf "%s\\n" "$out"; fi',
    )
    return out.strip()


def env_files(host: str) -> str:
    return sh(host, "cat /etc/isaac-sim/instance-*.env | sha256sum")


def no_network(host: str) -> bool:
    return "isaac-sim-macvlan" not in sh(host, "docker network ls --format '{{.Name}}'")


def test_bad_addresses_are_refused_on_every_host_before_anything_changes(fleet):
    first, second = fleet[0], fleet[1]
    before = {h: (containers(h), env_files(h)) for h in (first, second)}
    addresses = pool(first)
    # a wrong interface, and a pool of two of which one is the host's own address
    run = playbook(
        "deploy.yml",
        own(
            first,
            [str(lan(first).ip), addresses[0]],
            isaac_sim_macvlan_parent="eth9",
            isaac_sim_macvlan_subnet=str(lan(first).network),
        ),
        limit=first,
    )
    out = squash(run.stdout + run.stderr)
    assert run.returncode != 0
    assert "isaac_sim_macvlan_parent: 'eth9' is not a network interface of this host" in out
    assert (
        f"isaac_sim_address_pool: 1 usable address(es) for the 4 instance(s) that need one from the pool "
        f"(0, 1, 2, 3) ({lan(first).ip} is an address of this host)" in out
    )
    # two hosts given the same pool: each host's plan is fine, the fleet's is not
    run = playbook("deploy.yml", own(first, addresses), limit=f"{first},{second}")
    out = squash(run.stdout + run.stderr)
    assert run.returncode != 0
    assert f"{addresses[0]} is given to isaac-sim-0 on {first} and isaac-sim-0 on {second}" in out
    for h in (first, second):
        assert (containers(h), env_files(h)) == before[h], f"{h} changed"
        assert no_network(h)


def test_each_instance_answers_at_its_own_address_and_at_no_other(fleet):
    first, second, third = fleet
    addresses = pool(first)
    untouched = containers(second)
    # the second host alone may reach them: their traffic never passes the host's input chain, so the
    # firewall filters it at the macvlan parent's ingress
    extra = {"isaac_sim_web_viewer_image": viewer_image(first), "isaac_sim_allowed_networks": [f"{ip(second)}/32"]}
    run = playbook("deploy.yml", own(first, addresses, **extra), limit=first)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-2000:]
    assert containers(second) == untouched
    # one instance at a time, through the lifecycle: each new container started only once the
    # one before it was ready again (the markers hold the second the readiness gate passed)
    started = [
        float(sh(first, f"date -d \"$(docker inspect -f '{{{{.State.StartedAt}}}}' isaac-sim-{i})\" +%s.%N"))
        for i in range(INSTANCES)
    ]
    ready = [int(sh(first, f"cat /run/isaac-sim/instance-{i}.ready")) for i in range(INSTANCES)]
    for i in range(1, INSTANCES):
        assert started[i] >= ready[i - 1], f"isaac-sim-{i} started before isaac-sim-{i - 1} was ready"

    network = json.loads(sh(first, "docker network inspect isaac-sim-macvlan"))[0]
    assert network["Driver"] == "macvlan" and network["Options"]["parent"] == "eth0"
    on_it = {c["Name"]: c["IPv4Address"].split("/")[0] for c in network["Containers"].values()}
    assert on_it == {f"isaac-sim-{i}": addresses[i] for i in range(INSTANCES)}
    short_ids = {name: cid[:12] for name, (cid, _image) in containers(first).items()}

    for i, address in enumerate(addresses):
        # the release's own port at the instance's address, answered by that instance's container
        assert tcp(second, address, SIGNAL) == f"isaac-sim-standin signal {short_ids[f'isaac-sim-{i}']}"
        # its old place in a port block is gone: the same ports at every address, nothing else
        assert tcp(second, address, SIGNAL + 1) == "refused"
        # its viewer, in its namespace, told its address and the default ports
        config = sh(second, f"curl -sf http://{address}:{VIEWER}/stream-config.js").splitlines()[0]
        assert config == f'window.ISAACSIM_STREAM = {{"host": "{address}", "signalPort": 49100, "streamPort": 47998}};'

    # from outside the allowed networks no instance answers at its address
    for address in addresses:
        refused = probe(third, address, [("tcp", SIGNAL, ""), ("udp", 47998, ""), ("tcp", VIEWER, "/")])
        assert set(refused.values()) == {"timeout"}, (address, refused)
    assert 'type filter hook ingress device "eth0"' in sh(first, "nft list table netdev isaac_sim")

    # nothing of the instances on the host's own address any more
    for port in range(SIGNAL, SIGNAL + INSTANCES):
        assert tcp(second, ip(first), port) == "refused"

    # what the host reports (its status endpoint, read from the other host) says the same
    live = json.loads(sh(second, f"curl -sf http://{ip(first)}:8290/status"))
    instances = {inst["name"]: inst for inst in live["instances"]}
    for i, address in enumerate(addresses):
        inst = instances[f"isaac-sim-{i}"]
        assert inst["state"] == "ready", inst
        assert inst["urls"]["signal"] == f"{address}:{SIGNAL}"
        assert inst["urls"]["web_viewer"] == f"http://{address}:{VIEWER}/"


def test_back_on_the_host_s_network_the_macvlan_network_goes(fleet):
    first, second = fleet[0], fleet[1]
    run = playbook("deploy.yml", {}, limit=first)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-2000:]
    assert no_network(first)
    assert "isaac-sim-0-viewer" not in sh(first, "docker ps --format '{{.Names}}'")
    # no instance has an address of its own: no rule at the parent's ingress either
    assert "netdev" not in sh(first, "nft list tables")
    for i in range(INSTANCES):
        assert tcp(second, ip(first), SIGNAL + i).startswith("isaac-sim-standin signal")
