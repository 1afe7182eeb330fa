# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""The instances' firewall: each port an instance, a companion or a host service opens answers
only the networks allowed for its kind (isaac_sim_allowed_networks), with nftables.

The rules live in tables of the collection's own (inet isaac_sim on the host's input hook;
netdev isaac_sim on a macvlan parent's ingress hook, where the traffic of instances with
addresses of their own passes: it never reaches the host's input chain). Nothing else is
flushed or touched, but a site chain that drops by default: it is given the same accepts in its
own terms (hostlib/site_firewall.py, isaac_sim_firewall_site_policy). One file holds both tables
and replaces them in one nft transaction; the unit isaac-sim-firewall.service loads it at boot,
and a drop-in of the site's nftables.service loads it again after that flushed the ruleset. The
lifecycle (lifecycle.py) loads the union of the rules before and after a change while instances
change, and only the planned ones once every instance runs as planned: no port of a running
instance is ever without its rule.
"""

from __future__ import annotations

import ipaddress
import json
import re

from ansible_collections.isaacsim.fleet.plugins.module_utils.common import sandbox, units
from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib import layout, site_firewall

TABLE = "isaac_sim"
NFT = "/usr/sbin/nft"
RULES = layout.FIREWALL_RULES
# the model the rules were rendered from and nft's own listing of them once loaded
STATE = layout.FIREWALL_STATE
UNIT = layout.FIREWALL_UNIT
UNIT_PATH = f"{layout.UNIT_DIR}/{UNIT}"
# the site's nftables.service loads a file that starts with "flush ruleset" (Debian's, RHEL's): a
# drop-in loads ours again after each of its starts and reloads
SITE_DROPIN = layout.FIREWALL_SITE_DROPIN
SITE_RULES = layout.FIREWALL_SITE_RULES
SITE_SCRIPT = f"/usr/bin/python3 {layout.LIBEXEC_DIR}/{layout.FIREWALL_SITE_SCRIPT}"
VAR = "isaac_sim_allowed_networks"
BY_PORT = "isaac_sim_allowed_networks_by_port"
# the host services' port kinds (the instances' are the release's and the companions' port names)
HOST_KINDS = ("status", "hub_cache")
# the action agent's port: its networks are isaac_sim_agent_allow's, never a site's default
AGENT_KIND = "agent"
HOST_CHAIN = "host"
# traffic that never comes from another machine: the host itself, and containers on this host's
# Docker bridges (a test run reaching the instance it borrowed)
LOCAL_INTERFACES = ("lo", "docker0", "br-*")
_DROP_ALL = f"table inet {TABLE}\ndelete table inet {TABLE}\ntable netdev {TABLE}\ndelete table netdev {TABLE}\n"
# the same as one nft command line (the unit's stop, remove())
_DROP_ALL_LINE = _DROP_ALL.strip().replace("\n", "; ")


class Networks:
    """The allowed networks: the default list and per port kind."""

    def __init__(self, default, by_kind):
        self.default, self.by_kind = default, by_kind

    def of(self, kind: str) -> list:
        return self.by_kind.get(kind, self.default)


def _parse(texts, where: str, errors: list, warnings: list) -> list:
    """The networks of one list, as strings nft takes; errors name `where` and the fix."""
    if not isinstance(texts, list):
        errors.append(f"{where}: {texts!r} is not a list. Fix: give a list of networks, e.g. [10.20.0.0/16].")
        return []
    out = []
    for text in texts:
        value = str(text).strip()
        try:
            net = ipaddress.ip_network(value, strict=True)
        except ValueError:
            try:
                loose = ipaddress.ip_network(value, strict=False)
            except ValueError:
                errors.append(
                    f"{where}: {text!r} is not a network. Fix: write it in CIDR notation, e.g. 10.20.0.0/16, "
                    "or a single address (10.20.1.5)."
                )
                continue
            errors.append(
                f"{where}: {text!r} has bits set after its prefix length. Fix: write the network, {loose}, "
                f"or the single address, {value.split('/', maxsplit=1)[0]}."
            )
            continue
        if net.prefixlen == 0:
            warnings.append(f"{where}: {net} lets every IPv{net.version} address in: the firewall keeps nobody out.")
        if str(net) not in out:
            out.append(str(net))
    return out


def settings(cfg: dict, kinds) -> tuple:
    """({"enabled", "default", "by_kind"}, errors, warnings) from the plan's configuration.

    kinds: the port kinds a site may name in isaac_sim_allowed_networks_by_port."""
    errors, warnings = [], []
    if not cfg.get("firewall", True):
        warnings.append(
            "isaac_sim_firewall: false, so the instances', companions' and host services' ports answer every "
            "network that can route to this host (NVIDIA: the stream has no authentication and no encryption). "
            f"Set {VAR} and isaac_sim_firewall: true unless another firewall guards these hosts."
        )
        return {"enabled": False}, errors, warnings
    default = _parse(cfg.get("allowed_networks") or [], VAR, errors, warnings)
    by_kind = {}
    given = cfg.get("allowed_networks_by_port") or {}
    if not isinstance(given, dict):
        errors.append(
            f"{BY_PORT}: {given!r} is not a mapping. Fix: map a port kind to its networks, e.g. "
            "{status: [10.9.0.0/24]}."
        )
        given = {}
    for kind, texts in given.items():
        if kind not in kinds:
            errors.append(
                f"{BY_PORT}: {kind!r} is not a port kind of these instances ({', '.join(sorted(kinds))}). "
                "Fix: use one of them."
            )
            continue
        by_kind[str(kind)] = _parse(texts, f"{BY_PORT}.{kind}", errors, warnings)
    site = cfg.get("firewall_site_policy") or "add"
    if site not in site_firewall.CHOICES:
        errors.append(
            f"{site_firewall.VAR}: {site!r} is not one of {', '.join(site_firewall.CHOICES)}. Fix: add (the collection "
            "keeps its accepts in a site chain that drops by default, or in firewalld) or refuse (the deploy stops "
            "and gives the rules to add)."
        )
    if not default and not errors and not cfg.get("allowed_networks"):
        errors.append(
            f"{VAR}: empty, so every port of the instances would be closed to every other machine. Fix: list the "
            "networks that may reach them (the offices and the monitoring network, e.g. [10.20.0.0/16]), or set "
            "isaac_sim_firewall: false where another firewall guards these hosts."
        )
    return {"enabled": True, "default": default, "by_kind": by_kind, "site": site}, errors, warnings


def entries(plan: dict) -> list:
    """[[chain, proto, port, kind, address]] for every port the plan opens: the instances' (as
    their profile opens them), their companions', the status endpoint's and the Hub cache's."""
    out = []
    for inst in plan["instances"]:
        chain = inst["name"]
        address = inst.get("address") or ""
        for kind in inst.get("listens", []):
            out.append([chain, inst["protocols"].get(kind, "tcp"), inst["ports"][kind], kind, address])
        # a companion's port that is one of the block's (the web viewer's) is of the block's kind
        kind_of = {port: kind for kind, port in inst["ports"].items()}
        for comp in inst.get("companions", []):
            for name in comp["own_ports"]:
                port = comp["ports"][name]
                out.append([chain, comp["protocols"][name], port, kind_of.get(port, name), address])
    status = plan.get("status_server") or {}
    if status.get("enabled"):
        out.append([HOST_CHAIN, "tcp", status["port"], "status", ""])
    if (plan.get("hub_cache") or {}).get("enabled"):
        out.append([HOST_CHAIN, "tcp", layout.HUB_PORT, "hub_cache", ""])
    if (plan.get("agent") or {}).get("enabled"):
        out.append([HOST_CHAIN, "tcp", plan["agent"]["port"], AGENT_KIND, ""])
    return _unique(out)


def _unique(rows) -> list:
    seen, out = set(), []
    for row in rows:
        key = tuple(row)
        if key not in seen:
            seen.add(key)
            out.append(list(row))
    return out


def model(fw: dict, plan: dict) -> dict | None:
    """What the rules are made of (JSON, kept on the host to merge with the next plan's); None
    when the firewall is off."""
    if not fw.get("enabled"):
        return None
    parent = (plan.get("network") or {}).get("parent") or ""
    rows = entries(plan)
    by_kind = dict(fw["by_kind"])
    if (plan.get("agent") or {}).get("enabled"):
        # the front door's addresses alone (isaac_sim_agent_allow), whatever the other ports allow
        by_kind[AGENT_KIND] = plan["agent"]["allow"]
    return {
        "default": fw["default"],
        "by_kind": by_kind,
        "ports": rows,
        "parents": {row[4]: parent for row in rows if row[4]},
        "site": fw.get("site", "add"),
    }


def merge(old: dict | None, new: dict | None) -> dict | None:
    """The rules of both: the ports of old and new (so nothing running loses its rule while the
    instances change), the networks of new."""
    if not old or not new:
        return new
    return dict(
        new,
        ports=_unique(new["ports"] + old["ports"]),
        parents=dict(old.get("parents") or {}, **new["parents"]),
    )


def _chain_name(kind: str) -> str:
    return "allow-" + re.sub(r"[^a-z0-9_]", "_", kind.lower())


def _allow_chains(nets: Networks, kinds) -> list:
    lines = []
    for kind in sorted(set(kinds)):
        lines.append(f"\tchain {_chain_name(kind)} {{")
        lines.append(f"\t\t# {kind}: {', '.join(nets.of(kind)) or 'no network'}")
        for version, word in ((4, "ip"), (6, "ip6")):
            chosen = [n for n in nets.of(kind) if ipaddress.ip_network(n).version == version]
            if chosen:
                lines.append(f"\t\t{word} saddr {{ {', '.join(chosen)} }} accept")
        lines += ["\t\tdrop", "\t}"]
    return lines


def _rule(row) -> str:
    _chain, proto, port, kind, address = row
    to = f"ip daddr {address} " if address else ""
    return f"\t\t{to}{proto} dport {port} jump {_chain_name(kind)}"


def _order(chain: str):
    """host first, then the instances by number."""
    match = re.search(r"(\d+)$", chain)
    return (chain != HOST_CHAIN, int(match.group(1)) if match else -1, chain)


def render(m: dict | None, managed: str) -> str:
    """The rules file: both tables replaced in one transaction (created first, so that deleting a
    table that is not there yet is no error), or only deleted when there is nothing to load."""
    head = [
        f"#!{NFT} -f",
        f"# {managed}",
        f"# The Isaac Sim instances' firewall, loaded by {UNIT} and by the lifecycle.",
        "# Other tables (Docker's, the site's) are left as they are.",
    ]
    if m is None:
        return "\n".join(head) + "\n" + _DROP_ALL
    nets = Networks(m["default"], m.get("by_kind") or {})
    host_rows = [r for r in m["ports"] if not r[4]]
    own_rows = [r for r in m["ports"] if r[4]]
    lines = head + [f"table inet {TABLE}", f"delete table inet {TABLE}", f"table inet {TABLE} {{"]
    lines += _allow_chains(nets, [r[3] for r in host_rows])
    chains = sorted({r[0] for r in host_rows}, key=_order)
    for chain in chains:
        lines.append(f"\tchain {chain} {{")
        lines += [_rule(r) for r in sorted(host_rows, key=lambda r: (r[2], r[1])) if r[0] == chain]
        lines.append("\t}")
    lines += [
        "\tchain input {",
        "\t\ttype filter hook input priority filter; policy accept;",
        *[f'\t\tiifname "{name}" accept' for name in LOCAL_INTERFACES],
        *[f"\t\tjump {chain}" for chain in chains],
        "\t}",
        "}",
        f"table netdev {TABLE}",
        f"delete table netdev {TABLE}",
    ]
    if own_rows:
        parents = m.get("parents") or {}
        lines.append(f"table netdev {TABLE} {{")
        lines += _allow_chains(nets, [r[3] for r in own_rows])
        by_parent = {}
        for row in own_rows:
            by_parent.setdefault(parents.get(row[4], ""), []).append(row)
        for n, parent in enumerate(sorted(by_parent)):
            # an instance's own address is reached through its macvlan parent, before the host sees it
            lines += [
                f"\tchain ingress{n} {{",
                f'\t\ttype filter hook ingress device "{parent}" priority filter; policy accept;',
            ]
            rows = sorted(by_parent[parent], key=lambda r: (_order(r[0]), r[2], r[1]))
            lines += [_rule(r) for r in rows]
            lines.append("\t}")
        lines.append("}")
    return "\n".join(lines) + "\n"


def site_dropin(managed: str) -> str:
    """nftables.service.d/isaac-sim.conf: after the site's rules (which flush the whole ruleset),
    ours again, and our accepts in the site's chains. The "-": a missing file of ours never fails
    the site's firewall."""
    again = [f"-{NFT} -f {RULES}", f"-{SITE_SCRIPT} apply"]
    return units.render(
        [("Service", [*[("ExecStartPost", c) for c in again], *[("ExecReload", c) for c in again]])],
        header=[managed, f"The Isaac Sim instances' rules ({UNIT}) again after the site's flush the ruleset."],
    )


def unit(managed: str) -> str:
    """isaac-sim-firewall.service: loads the rules at boot, before Docker and so before any
    instance; its stop deletes them."""
    return units.render(
        [
            (
                "Unit",
                [
                    ("Description", "Firewall of the Isaac Sim instances (nftables table isaac_sim)"),
                    ("DefaultDependencies", "no"),
                    ("Wants", "network-pre.target"),
                    ("After", "nftables.service"),
                    ("Before", f"network-pre.target docker.service {layout.TARGET} shutdown.target"),
                    ("Conflicts", "shutdown.target"),
                ],
            ),
            (
                "Service",
                [
                    ("Type", "oneshot"),
                    ("RemainAfterExit", "yes"),
                    ("ExecStart", f"{NFT} -f {RULES}"),
                    "# the accepts a site chain that drops by default needs (isaac_sim_firewall_site_policy: add)",
                    ("ExecStartPost", f"-{SITE_SCRIPT} apply"),
                    "# stopped, the instances' ports answer everyone again: cleanup.yml stops it last",
                    ("ExecStop", f"-{SITE_SCRIPT} remove"),
                    ("ExecStop", f"{NFT} '{_DROP_ALL_LINE}'"),
                    *sandbox.firewall(),
                ],
            ),
            ("Install", [("WantedBy", "multi-user.target")]),
        ],
        header=[managed, "Loads /etc/isaac-sim/firewall.nft (isaac_sim_allowed_networks)."],
    )


def listed(run) -> str:
    """nft's listing of both tables as the kernel has them now ("" for a table that is not there).
    run(argv) -> (rc, out, err). The lifecycle keeps it after a load; the audit compares with it."""
    out = []
    for family in ("inet", "netdev"):
        rc, text, _err = run([NFT, "list", "table", family, TABLE])
        out.append(text if rc == 0 else "")
    return "".join(out)


def listing(host) -> str | None:
    """listed() on the host; None without nft."""
    return listed(host.run) if host.exists(NFT) else None


def state(host) -> dict:
    """The model and listing the lifecycle left on the host ({} when none)."""
    try:
        return json.loads(host.read(STATE) or "{}")
    except ValueError:
        return {}


def in_sync(host, m: dict | None, managed: str) -> bool:
    """Whether the host has exactly `m`: file, unit, and the kernel's tables as last loaded."""
    kept = state(host)
    if m is None:
        gone = (RULES, UNIT_PATH, SITE_DROPIN, SITE_RULES)
        return all(host.read(path) is None for path in gone) and not _loaded(host)
    return (
        _site_in_sync(host, m)
        and host.read(RULES) == render(m, managed)
        and host.read(UNIT_PATH) == unit(managed)
        and host.read(SITE_DROPIN) == site_dropin(managed)
        and kept.get("model") == m
        and kept.get("listing") is not None
        and listing(host) == kept["listing"]
        and _enabled(host)
        and _site_in_sync(host, m)
    )


def _site_wanted(m: dict) -> tuple:
    """(the rules of ours for a site's nftables chains, the rich rules for firewalld's policy of ours);
    both empty where the collection does not add them (isaac_sim_firewall_site_policy: refuse)."""
    if m.get("site", "add") != "add":
        return [], []
    gs = site_firewall.groups(m)
    return site_firewall.nft_rules(gs), site_firewall.rich_rules(gs)


def _site_in_sync(host, m: dict) -> bool:
    """Our accepts in the site's chains as this model wants them (refuse: never touched)."""
    if m.get("site", "add") != "add":
        return True
    rules, rich = _site_wanted(m)
    if host.read(SITE_RULES) != _site_file(rules):
        return False
    if not host.exists(NFT):
        return True
    found = site_firewall.survey(host.run)
    comments = sorted(site_firewall.comment_of(r) for r in rules)
    for c in found["chains"]:
        if c["owner"] == "nft" and c["comments"] != comments:
            return False
        running = c["owner"] == "firewalld" and (found.get("firewalld") or {}).get("running")
        if running and sorted(found["firewalld"].get("runtime") or []) != rich:
            return False
    nft_chains = {(c["family"], c["table"], c["chain"]) for c in found["chains"] if c["owner"] == "nft"}
    return all(tuple(o[:3]) in nft_chains for o in found["ours"])


def _site_file(rules: list) -> str:
    return json.dumps({"nft": rules}, indent=1) + "\n"


def _site_load(host, m: dict) -> None:
    """Our accepts in the site's chains that drop by default: its nftables chains (kept there by
    isaac-sim-firewall-site after the site reloads them) and firewalld's policy of ours."""
    if m.get("site", "add") != "add":
        # refuse: the site's chains are the site's (rules it copied from a refusal included)
        if host.read(SITE_RULES) is not None:
            host.remove(SITE_RULES)
        return
    rules, rich = _site_wanted(m)
    host.write(SITE_RULES, _site_file(rules), 0o644)
    try:
        site_firewall.apply_nft(host.run, rules)
        if host.exists(site_firewall.FIREWALL_CMD):
            site_firewall.apply_firewalld(host.run, rich)
    except site_firewall.SiteError as exc:
        raise FirewallError(f"the site's firewall would not take the collection's accepts: {exc}") from exc


def _loaded(host) -> bool:
    return bool(listing(host))


def _enabled(host) -> bool:
    rc, out, _err = host.run(["systemctl", "is-enabled", UNIT])
    return rc == 0 and out.strip() == "enabled"


class FirewallError(Exception):
    pass


def load(host, m: dict, managed: str) -> None:
    """Write the rules, the unit and the state, and load the rules into the kernel (one nft
    transaction: the tables are replaced, never missing in between)."""
    host.write(RULES, render(m, managed), 0o644)
    units_changed = False
    for path, text in ((UNIT_PATH, unit(managed)), (SITE_DROPIN, site_dropin(managed))):
        if host.read(path) != text:
            host.write(path, text, 0o644)
            units_changed = True
    if units_changed:
        host.run(["systemctl", "daemon-reload"])
    rc, _out, err = host.run([NFT, "-f", RULES]) if host.exists(NFT) else (127, "", f"{NFT}: not found")
    if rc != 0:
        raise FirewallError(
            f"nft could not load {RULES}: {err.strip()}. Fix: install nftables (nft) on the host; the instances "
            "were not changed"
        )
    _site_load(host, m)
    host.write(STATE, json.dumps({"model": m, "listing": listing(host)}, sort_keys=True) + "\n", 0o644)
    if not _enabled(host):
        host.run(["systemctl", "enable", UNIT])
    # active, so that its stop (cleanup.yml) deletes the rules
    host.run(["systemctl", "start", UNIT])


def remove(host) -> None:
    """No rule, no file, no unit (isaac_sim_firewall: false)."""
    if host.read(UNIT_PATH) is not None or host.read(SITE_DROPIN) is not None:
        host.run(["systemctl", "disable", "--now", UNIT])
        host.remove(UNIT_PATH)
        host.remove(SITE_DROPIN)
        host.run(["systemctl", "daemon-reload"])
    if host.exists(NFT):
        # the accepts of ours in the site's chains first, while the site still drops by default
        kept = state(host).get("model") or {}
        if kept.get("site", "add") == "add":
            site_firewall.apply_nft(host.run, [])
            if host.exists(site_firewall.FIREWALL_CMD):
                site_firewall.remove_firewalld(host.run)
        host.run([NFT, _DROP_ALL_LINE])
    for path in (RULES, STATE, SITE_RULES):
        if host.read(path) is not None:
            host.remove(path)
