# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""Own addresses for instances (isaac_sim_network_mode: macvlan).

NVIDIA's WebRTC Streaming Client for 4.x/5.x reaches an instance on port 49100
only, so instances that share the host's network cannot all be opened with it.
In macvlan mode each instance gets an address of its own on the host's LAN
(a Docker macvlan network on the host's interface) and keeps the release's
default ports; its companions join its network namespace, as containers of a
Kubernetes pod do. Pure functions, like plan.py: the host's interfaces,
routes and the network as Docker has it come in as arguments.
"""

from __future__ import annotations

import ipaddress
import json
import re

from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib import layout

HOST, MACVLAN = "host", "macvlan"
MODES = (HOST, MACVLAN)
# a pool is expanded only as far as the instances need; a range longer than this is a typo
MAX_RANGE = 65536
# the containers that may be on our network: the instances (their companions join their namespace)
_INSTANCE = re.compile(r"^/?" + re.escape(layout.CONTAINER_PREFIX) + r"\d+\Z")


def _address(text, where, errors):
    try:
        return ipaddress.IPv4Address(str(text).strip())
    except ValueError:
        errors.append(f"{where}: {text!r} is not an IPv4 address. Fix: write it as 192.168.10.50.")
        return None


def expand_pool(pool, errors) -> list:
    """The addresses of isaac_sim_address_pool, in order: single addresses, FIRST-LAST ranges and
    CIDR blocks (every address of the block; the subnet check drops its network and broadcast)."""
    if pool in (None, ""):
        return []
    if isinstance(pool, str):
        pool = [pool]
    if not isinstance(pool, list):
        errors.append(
            "isaac_sim_address_pool: must be a list of addresses, FIRST-LAST ranges or CIDR blocks. "
            "Fix: e.g. [192.168.10.50-192.168.10.57]."
        )
        return []
    out = []
    for entry in pool:
        text = str(entry).strip()
        where = f"isaac_sim_address_pool: {text!r}"
        if "-" in text:
            first, last = (_address(t, "isaac_sim_address_pool", errors) for t in text.split("-", 1))
            if first is None or last is None:
                continue
            if int(last) < int(first) or int(last) - int(first) >= MAX_RANGE:
                errors.append(
                    f"{where} is not a range of at most {MAX_RANGE} addresses, first to last. "
                    "Fix: write the lower address first."
                )
                continue
            out += [first + n for n in range(int(last) - int(first) + 1)]
        elif "/" in text:
            try:
                block = ipaddress.IPv4Network(text)
            except ValueError:
                errors.append(
                    f"{where} is not an IPv4 CIDR block (its first address, then the length). "
                    "Fix: e.g. 192.168.10.48/29."
                )
                continue
            if block.num_addresses > MAX_RANGE:
                errors.append(f"{where} holds more than {MAX_RANGE} addresses. Fix: give a smaller block.")
                continue
            out += list(block)
        else:
            address = _address(text, "isaac_sim_address_pool", errors)
            if address is not None:
                out.append(address)
    return out


def parse_links(text: str) -> dict:
    """{interface: [(address, prefix length)]} from `ip -j -4 addr show`."""
    try:
        links = json.loads(text or "[]")
    except ValueError:
        return {}
    return {
        link.get("ifname"): [
            (a["local"], int(a.get("prefixlen", 32))) for a in link.get("addr_info", []) if a.get("family") == "inet"
        ]
        for link in links
        if link.get("ifname")
    }


def parse_default_route(text: str) -> dict:
    """{"dev": ..., "gateway": ...} of the first IPv4 default route from `ip -j -4 route show default`."""
    try:
        routes = json.loads(text or "[]")
    except ValueError:
        return {}
    for route in routes:
        if route.get("dst") == "default" and route.get("dev"):
            return {"dev": route["dev"], "gateway": route.get("gateway")}
    return {}


def parse_network(net) -> dict | None:
    """The network as Docker describes it (GET /networks/NAME, or one item of docker network
    inspect), or None when there is none."""
    if isinstance(net, list):
        net = net[0] if net else None
    if not net:
        return None
    ipam = ((net.get("IPAM") or {}).get("Config") or [{}])[0]
    return {
        "driver": net.get("Driver"),
        "parent": (net.get("Options") or {}).get("parent"),
        "subnet": ipam.get("Subnet"),
        "gateway": ipam.get("Gateway"),
        "ours": (net.get("Labels") or {}).get(layout.LABEL_NETWORK) is not None,
        # {container name: its IPv4 address}
        "containers": {
            c.get("Name"): (c.get("IPv4Address") or "").split("/")[0] for c in (net.get("Containers") or {}).values()
        },
    }


def action(wanted: dict, found: dict | None) -> str | None:
    """What the host's network needs: create, recreate (nobody on it), remove (ours, no longer
    wanted: once nobody is on it), conflict (in use and different: the plan refuses it), or None."""
    if wanted.get("mode") == MACVLAN:
        if found is None:
            return "create"
        if not same(wanted, found):
            return "conflict" if found.get("containers") or not found.get("ours") else "recreate"
        return None
    return "remove" if found and found.get("ours") else None


def same(wanted: dict, found: dict | None) -> bool:
    """Whether Docker's network is the one wanted (driver, parent, subnet, gateway)."""
    return bool(found) and all(found.get(k) == wanted.get(k) for k in ("driver", "parent", "subnet", "gateway"))


def create_argv(net: dict) -> list:
    return [
        "docker",
        "network",
        "create",
        "--driver",
        MACVLAN,
        "--subnet",
        net["subnet"],
        "--gateway",
        net["gateway"],
        "--opt",
        f"parent={net['parent']}",
        "--label",
        f"{layout.LABEL_NETWORK}={MACVLAN}",
        layout.NETWORK,
    ]


def remove_argv() -> list:
    return ["docker", "network", "rm", layout.NETWORK]


def plan(cfg: dict, host: dict, ids: list) -> tuple:
    """(network, {instance: address}, errors) for this host.

    cfg: network_mode, macvlan_parent, macvlan_subnet, macvlan_gateway, address_pool,
    instance_addresses, max_instances; host: links (parse_links), interfaces (names),
    default_route (parse_default_route), network (parse_network of ours, or None).
    """
    mode = str(cfg.get("network_mode") or HOST)
    if mode not in MODES:
        return (
            {"mode": HOST},
            {},
            [f"isaac_sim_network_mode: {mode!r} is not a network mode. Fix: choose {' or '.join(MODES)}."],
        )
    found = host.get("network")
    if mode == HOST:
        return {"mode": HOST, "found": bool(found and found.get("ours"))}, {}, []
    errors = []
    links = host.get("links") or {}
    route = host.get("default_route") or {}
    parent = str(cfg.get("macvlan_parent") or route.get("dev") or "")
    interfaces = set(host.get("interfaces") or links)
    if not parent:
        errors.append(
            "isaac_sim_macvlan_parent: empty, and this host has no IPv4 default route to take the interface from. "
            "Fix: name the interface on the instances' LAN, e.g. eth0."
        )
    elif parent not in interfaces or parent == "lo":
        errors.append(
            f"isaac_sim_macvlan_parent: {parent!r} is not a network interface of this host (it has "
            f"{', '.join(sorted(i for i in interfaces if i != 'lo')) or 'none'}). Fix: name the interface on the "
            "instances' LAN."
        )
    subnet = None
    if cfg.get("macvlan_subnet"):
        try:
            subnet = ipaddress.IPv4Network(str(cfg["macvlan_subnet"]).strip(), strict=False)
        except ValueError:
            errors.append(
                f"isaac_sim_macvlan_subnet: {cfg['macvlan_subnet']!r} is not an IPv4 network. "
                "Fix: give the LAN's, e.g. 192.168.10.0/24."
            )
    elif links.get(parent):
        local, prefix = links[parent][0]
        subnet = ipaddress.IPv4Network(f"{local}/{prefix}", strict=False)
    elif parent in interfaces:
        errors.append(
            f"isaac_sim_macvlan_subnet: empty, and {parent} has no IPv4 address to take the LAN's network from. "
            "Fix: give the LAN's network, e.g. 192.168.10.0/24."
        )
    # a typo in the subnet would give every instance an address nobody can reach, and they would
    # still all become ready (readiness is seen from inside the container)
    if subnet is not None and links.get(parent):
        on_parent = [ipaddress.IPv4Network(f"{a}/{p}", strict=False) for a, p in links[parent]]
        if not any(subnet.overlaps(net) for net in on_parent):
            errors.append(
                f"isaac_sim_macvlan_subnet: {subnet} is not a network of {parent}, which is on "
                f"{', '.join(str(n) for n in on_parent)}: the instances' addresses would be unreachable. Fix: give "
                f"{parent}'s network, or the interface on {subnet} as isaac_sim_macvlan_parent."
            )
    gateway = None
    given_gateway = cfg.get("macvlan_gateway") or (route.get("gateway") if route.get("dev") == parent else None)
    if given_gateway:
        gateway = _address(given_gateway, "isaac_sim_macvlan_gateway", errors)
    if subnet is not None and gateway is not None and gateway not in subnet:
        errors.append(
            f"isaac_sim_macvlan_gateway: {gateway} is not in the subnet {subnet}. Fix: give the LAN's router address."
        )
        gateway = None
    parent_ok = bool(parent) and parent in interfaces and parent != "lo"
    if subnet is not None and gateway is None and not cfg.get("macvlan_gateway") and parent_ok:
        errors.append(
            f"isaac_sim_macvlan_gateway: empty, and this host's default route is not on {parent}. "
            f"Fix: give the router address of {subnet}."
        )
    if subnet is None:
        return {"mode": MACVLAN}, {}, errors

    own = {ipaddress.IPv4Address(a) for addrs in links.values() for a, _prefix in addrs}
    taken_by_others = {}
    if found:
        taken_by_others = {
            a: name for name, a in found.get("containers", {}).items() if a and not _INSTANCE.match(name)
        }

    def unusable(address):
        """Why an address cannot be an instance's, or None."""
        if address not in subnet or address in (subnet.network_address, subnet.broadcast_address):
            return f"not a host address of {subnet}"
        if address == gateway:
            return "the gateway"
        if address in own:
            return "an address of this host"
        if str(address) in taken_by_others:
            return f"container {taken_by_others[str(address)]}'s on {layout.NETWORK}"
        return None

    fixed = {}
    for key, value in (cfg.get("instance_addresses") or {}).items():
        where = f"isaac_sim_instance_addresses.{key}"
        if not str(key).strip().isdigit() or int(str(key)) >= int(cfg.get("max_instances") or 8):
            errors.append(
                f"{where}: {key!r} is not an instance number (0..{int(cfg.get('max_instances') or 8) - 1}). "
                "Fix: key the map by instance number."
            )
            continue
        address = _address(value, where, errors)
        why = unusable(address) if address is not None else None
        if why:
            errors.append(f"{where}: {address} is {why}. Fix: give an address of {subnet} that no machine uses.")
        elif address is not None:
            fixed[int(str(key))] = address
    pool = expand_pool(cfg.get("address_pool"), errors)
    refused = [(a, unusable(a)) for a in pool if unusable(a)]
    free = [a for a in pool if not unusable(a) and a not in fixed.values()]
    need = [i for i in ids if i not in fixed]
    assigned = dict(fixed)
    assigned.update(zip(need, free))
    assigned = {i: assigned[i] for i in ids if i in assigned}
    if len(free) < len(need):
        why = "; ".join(f"{a} is {reason}" for a, reason in refused[:3]) + ("; ..." if len(refused) > 3 else "")
        errors.append(
            f"isaac_sim_address_pool: {len(free)} usable address(es) for the {len(need)} instance(s) that need one "
            f"from the pool ({', '.join(map(str, need))}){' (' + why + ')' if refused else ''}. "
            f"Fix: add addresses of {subnet} that no machine uses, or give instances isaac_sim_instance_addresses."
        )
    seen = {}
    for i, address in sorted(assigned.items()):
        if address in seen:
            errors.append(
                f"isaac_sim_instance_addresses: {address} is given to instances {seen[address]} and {i}. "
                "Fix: one address per instance."
            )
        seen.setdefault(address, i)
    network = {
        "mode": MACVLAN,
        "name": layout.NETWORK,
        "driver": MACVLAN,
        "parent": parent,
        "subnet": str(subnet),
        "gateway": str(gateway),
    }
    if found and not found.get("ours"):
        errors.append(
            f"isaac_sim_network_mode: a Docker network named {layout.NETWORK} exists on this host and was not made "
            "by this collection. Fix: remove or rename it (docker network rm), then deploy again."
        )
    elif found and not same(network, found) and found.get("containers"):
        errors.append(
            f"isaac_sim_macvlan_parent / _subnet / _gateway: the instances' network {layout.NETWORK} is "
            f"{found.get('parent')} {found.get('subnet')} via {found.get('gateway')} and "
            f"{', '.join(sorted(found['containers']))} use it, so it cannot change under them. Fix: deploy with "
            "isaac_sim_network_mode: host first (the instances roll back onto the host's network one at a time), "
            "then deploy the new settings."
        )
    return network, {i: str(a) for i, a in assigned.items()}, errors


def clashes(addresses_by_host: dict) -> list:
    """Errors for an address given to instances on two hosts: {host: {instance: address}}."""
    owners = {}
    for host in sorted(addresses_by_host):
        for i, address in sorted((addresses_by_host[host] or {}).items(), key=lambda kv: int(kv[0])):
            owners.setdefault(address, []).append(f"{layout.container(int(i))} on {host}")
    return [
        f"isaac_sim_address_pool / isaac_sim_instance_addresses: {address} is given to {' and '.join(who)}. "
        "Fix: give each host a pool of its own."
        for address, who in owners.items()
        if len(who) > 1
    ]
