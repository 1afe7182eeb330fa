# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""The site's own firewall beside the collection's (isaac_sim_firewall_site_policy).

In nftables every base chain on a hook sees each packet: an accept in ours ends only our chain,
and a drop in any other is final. So a site table whose input chain drops by default (its policy,
or a last unconditional drop or reject, as firewalld's), or iptables' INPUT with policy DROP,
closes the instances' ports to everyone, whatever ours accepts. Such a chain has to accept what
ours lets in, in its own terms:

- a site's nftables chain: rules of ours at its top, each with a comment "isaac-sim <digest>";
- firewalld: a policy of ours (isaac-sim: ingress ANY, egress HOST, target CONTINUE) whose rich
  rules accept the same, through firewall-cmd, so that firewalld's reloads keep them;
- iptables' own tables (iptables-nft's or legacy): never written by the collection (a rule nft
  writes there breaks iptables-save for the site); the exact iptables commands are given instead.

Only what a chain drops by default is judged here (reading the kernel's rules as nft lists them);
a drop the site wrote for a port or an address is the site's, and the audit's knock from an
allowed network finds what it does to the instances (host/audit.py).

Copied beside isaac-sim-firewall-site on the host, which puts the rules back into a site's chain
after the site's nftables.service flushed them: standard library only.
"""

from __future__ import annotations

import hashlib
import json
import shlex

NFT = "/usr/sbin/nft"
FIREWALL_CMD = "/usr/bin/firewall-cmd"
OURS = "isaac_sim"
COMMENT = "isaac-sim"
POLICY = "isaac-sim"
VAR = "isaac_sim_firewall_site_policy"
CHOICES = ("add", "refuse")
# traffic that never comes from another machine (as firewall.LOCAL_INTERFACES): in firewalld,
# lo is always accepted and Docker puts docker0 in its zone "docker" (target ACCEPT)
LOCAL_EXACT = ("lo", "docker0")
LOCAL_WILDCARD = "br-*"
_IPTABLES = {("ip", "filter", "INPUT"): "iptables", ("ip6", "filter", "INPUT"): "ip6tables"}
_PASSIVE = {"counter", "log"}


def _digest(text: str) -> str:
    return hashlib.sha256(text.encode()).hexdigest()[:12]


def groups(m: dict | None) -> list:
    """What the site's chains must accept for the firewall model m (instance/firewall.py's): one
    group per protocol and network list, from the networks allowed for each port, and one per
    protocol from the local interfaces. Ports of instances with addresses of their own are not
    here: their traffic never passes the host's input hook."""
    if not m:
        return []
    by = {}
    for _chain, proto, port, kind, address in m.get("ports") or []:
        if address:
            continue
        nets = tuple((m.get("by_kind") or {}).get(kind, m.get("default") or []))
        for version in (4, 6):
            chosen = tuple(n for n in nets if (":" in n) == (version == 6))
            if chosen:
                by.setdefault((proto, version, chosen), set()).add(int(port))
        by.setdefault((proto, 0, ()), set()).add(int(port))
    out = []
    for (proto, version, nets), ports in sorted(by.items()):
        out.append({"proto": proto, "version": version, "nets": list(nets), "ports": sorted(ports)})
    return out


def _set(items) -> str:
    items = [str(i) for i in items]
    return items[0] if len(items) == 1 else "{ " + ", ".join(items) + " }"


def nft_rules(gs: list) -> list:
    """The rules (nft's syntax, without the chain) for a site's nftables chain, each commented with
    the digest of its own text: how a later run (and the refusal's recognition) knows them."""
    out = []
    for g in gs:
        ports = f"{g['proto']} dport {_set(g['ports'])} accept"
        if g["version"]:
            bodies = [f"{'ip' if g['version'] == 4 else 'ip6'} saddr {_set(g['nets'])} {ports}"]
        else:
            names = _set([f'"{n}"' for n in LOCAL_EXACT])
            bodies = [f"iifname {names} {ports}", f'iifname "{LOCAL_WILDCARD}" {ports}']
        out += [f'{body} comment "{COMMENT} {_digest(body)}"' for body in bodies]
    return out


def comment_of(rule: str) -> str:
    """The comment of one of nft_rules() ("isaac-sim <digest>"), as nft lists it back."""
    return rule.rsplit('"', 2)[-2]


def _ranges(ports) -> list:
    """Consecutive ports as "a-b" (firewalld's and iptables' ranges), the rest one by one."""
    out, ports = [], sorted(ports)
    start = prev = None
    for p in ports + [None]:
        if start is not None and p == prev + 1:
            prev = p
            continue
        if start is not None:
            out.append(str(start) if start == prev else f"{start}-{prev}")
        start = prev = p
    return out


def rich_rules(gs: list) -> list:
    """firewalld's rich rules for the policy of ours, as firewall-cmd lists them back."""
    out = []
    for g in gs:
        if not g["version"]:
            continue
        family = "ipv4" if g["version"] == 4 else "ipv6"
        for net in g["nets"]:
            for r in _ranges(g["ports"]):
                out.append(
                    f'rule family="{family}" source address="{net}" port port="{r}" protocol="{g["proto"]}" accept'
                )
    return sorted(set(out))


def iptables_rules(gs: list, tool: str) -> list:
    """iptables' arguments (after -I INPUT) for iptables' INPUT chain, at most 15 ports a rule."""
    out = []
    for g in gs:
        if g["version"] and (g["version"] == 6) != (tool == "ip6tables"):
            continue
        ranges = [r.replace("-", ":") for r in _ranges(g["ports"])]
        chunks = [ranges[i : i + 7] for i in range(0, len(ranges), 7)]
        sources = [["-s", n] for n in g["nets"]] if g["version"] else [["-i", n] for n in (*LOCAL_EXACT, "br+")]
        for src in sources:
            for chunk in chunks:
                body = [*src, "-p", g["proto"], "-m", "multiport", "--dports", ",".join(chunk)]
                out.append(
                    [*body, "-m", "comment", "--comment", f"{COMMENT} {_digest(' '.join(body))}", "-j", "ACCEPT"]
                )
    return out


def _comment_of(rule: dict) -> str:
    comment = rule.get("comment") or ""
    return comment if comment.startswith(COMMENT + " ") else ""


def _drops_by_default(chain: dict, rules: list) -> str:
    """Why this base chain drops what no rule of it accepts ("" when it does not)."""
    if chain.get("policy") == "drop":
        return "policy drop"
    for rule in rules:
        exprs = rule.get("expr") or []
        verdicts = [k for e in exprs for k in e if k in ("drop", "reject")]
        if verdicts and all(k in _PASSIVE or k in ("drop", "reject") for e in exprs for k in e):
            return f"an unconditional {verdicts[0]} (rule handle {rule.get('handle')})"
    return ""


def read(listing: str) -> dict:
    """From nft -j list ruleset: {"chains": the other tables' input chains that drop by default,
    each {"family", "table", "chain", "why", "owner" (nft, iptables, firewalld), "comments"},
    "ours": [[family, table, chain, handle, comment]] of every rule of ours in any nftables chain}."""
    items = json.loads(listing or '{"nftables": []}').get("nftables") or []
    chains, rules = [], {}
    for item in items:
        if "chain" in item:
            chains.append(item["chain"])
        elif "rule" in item:
            r = item["rule"]
            rules.setdefault((r["family"], r["table"], r["chain"]), []).append(r)
    found, ours = [], []
    for c in chains:
        key = (c["family"], c["table"], c["name"])
        for r in rules.get(key, []):
            if _comment_of(r) and c["table"] != OURS:
                ours.append([*key, r["handle"], _comment_of(r)])
        if c.get("hook") != "input" or c.get("type") != "filter" or c["family"] not in ("ip", "ip6", "inet"):
            continue
        if c["table"] == OURS:
            continue
        why = _drops_by_default(c, rules.get(key, []))
        if not why:
            continue
        owner = "firewalld" if c["table"] == "firewalld" else _IPTABLES.get(key, "nft")
        comments = sorted({_comment_of(r) for r in rules.get(key, []) if _comment_of(r)})
        found.append(
            {"family": key[0], "table": key[1], "chain": key[2], "why": why, "owner": owner, "comments": comments}
        )
    return {"chains": found, "ours": ours}


def _iptables_comments(run, tool: str) -> list:
    rc, out, _err = run([f"/usr/sbin/{tool}", "-w", "-S", "INPUT"])
    if rc != 0:
        return []
    found = set()
    for line in out.splitlines():
        words = shlex.split(line)
        for i, w in enumerate(words[:-1]):
            if w == "--comment" and words[i + 1].startswith(COMMENT + " "):
                found.add(words[i + 1])
    return sorted(found)


def _firewalld(run) -> dict:
    """firewalld as firewall-cmd sees it: running, the policy of ours (rich rules now and
    permanent; None where there is none), whether its runtime has changes not made permanent
    (which the reload that creating a policy takes would lose)."""
    rc, _out, _err = run([FIREWALL_CMD, "--state"])
    if rc != 0:
        return {"running": False}
    out = {"running": True}
    for where, extra in (("runtime", []), ("permanent", ["--permanent"])):
        rc, text, _err = run([FIREWALL_CMD, *extra, "--policy", POLICY, "--list-rich-rules"])
        out[where] = sorted(line.strip() for line in text.splitlines() if line.strip()) if rc == 0 else None
    differs = []
    # only where the policy is still to be made: the reload that takes is what would lose them
    for what in ("--list-all-zones", "--list-all-policies") if out["permanent"] is None else ():
        now = run([FIREWALL_CMD, what])[1]
        kept = run([FIREWALL_CMD, "--permanent", what])[1]
        if _without_ours(now) != _without_ours(kept):
            differs.append(what[len("--list-all-") :])
    out["unsaved"] = differs
    return out


def _without_ours(text: str) -> str:
    """firewall-cmd's listing with the policy of ours left out."""
    blocks = text.split("\n\n")
    return "\n\n".join(b for b in blocks if not b.startswith(POLICY + " ") and not b.startswith(POLICY + "\n"))


def survey(run) -> dict:
    """What the plan judges on the host: read() of nft's ruleset, iptables' comments of ours,
    firewalld's state. run(argv) -> (rc, out, err). {"nft": False} without nft."""
    rc, listing, _err = run([NFT, "-j", "list", "ruleset"])
    if rc != 0:
        return {"nft": False, "chains": [], "ours": []}
    out = dict(read(listing), nft=True)
    for c in out["chains"]:
        if c["owner"] in ("iptables", "ip6tables"):
            c["comments"] = _iptables_comments(run, c["owner"])
    if any(c["owner"] == "firewalld" for c in out["chains"]):
        out["firewalld"] = _firewalld(run)
    return out


def _q(text: str) -> str:
    return shlex.quote(text)


def _nft_insert(c: dict, rule: str) -> str:
    return f"insert rule {c['family']} {c['table']} {c['chain']} {rule}"


def judge(found: dict, m: dict | None, policy: str, host: str = "this host") -> list:
    """The errors that stop the deploy before any change: a chain that drops by default and does
    not accept what ours lets in, where the collection does not add it (policy refuse, iptables'
    tables, firewalld with unsaved changes); each names the chain and the exact commands to run."""
    gs = groups(m)
    if not gs or not found.get("chains"):
        return []
    errors = []
    add = policy == "add"
    for c in found["chains"]:
        where = f"{c['family']} {c['table']} {c['chain']}"
        head = (
            f"{host}: the site's chain {where} drops by default ({c['why']}), so no allowed network would reach "
            "the instances"
        )
        if c["owner"] == "nft":
            rules = nft_rules(gs)
            missing = [r for r in rules if comment_of(r) not in c["comments"]]
            if missing and not add:
                cmds = "; ".join(f"nft {_q(_nft_insert(c, r))}" for r in missing)
                errors.append(
                    f"{head}; nothing was changed ({VAR}: refuse). Fix: add the collection's accept at the top of that "
                    f"chain (and to the file the site loads it from): {cmds}; or set {VAR}: add to let each deploy "
                    "keep these rules there."
                )
        elif c["owner"] in ("iptables", "ip6tables"):
            tool = c["owner"]
            rules = iptables_rules(gs, tool)
            wanted = {r[r.index("--comment") + 1] for r in rules}
            if not wanted <= set(c["comments"]):
                cmds = "; ".join(f"{tool} -I INPUT {' '.join(_q(w) for w in r)}" for r in rules)
                errors.append(
                    f"{head}; nothing was changed (the collection never writes into iptables' own tables). Fix: "
                    f"add these rules (and save them where the site keeps its iptables rules): {cmds}"
                )
        elif c["owner"] == "firewalld":
            fw = found.get("firewalld") or {}
            wanted = rich_rules(gs)
            if not fw.get("running"):
                continue
            if not add and set(wanted) - set(fw.get("runtime") or []):
                errors.append(
                    f"{head}; nothing was changed ({VAR}: refuse). Fix: give firewalld the collection's policy: "
                    + "; ".join(firewalld_commands(wanted, fw))
                    + f"; or set {VAR}: add to let each deploy keep it."
                )
            elif add and fw.get("permanent") is None and fw.get("unsaved"):
                errors.append(
                    f"{host}: firewalld has changes in its running {' and '.join(fw['unsaved'])} that are not "
                    f"permanent; creating the policy {POLICY} takes a reload, which would lose them, so nothing was "
                    "changed. Fix: keep them (firewall-cmd --runtime-to-permanent) or drop them "
                    "(firewall-cmd --reload), then deploy again."
                )
    return errors


def firewalld_commands(wanted: list, fw: dict) -> list:
    """The firewall-cmd commands that give firewalld the policy of ours with these rich rules."""
    cmds = []
    if fw.get("permanent") is None:
        cmds += [
            f"{FIREWALL_CMD} --permanent --new-policy {POLICY}",
            f"{FIREWALL_CMD} --permanent --policy {POLICY} --set-target CONTINUE",
            f"{FIREWALL_CMD} --permanent --policy {POLICY} --add-ingress-zone ANY",
            f"{FIREWALL_CMD} --permanent --policy {POLICY} --add-egress-zone HOST",
        ]
    adds = " ".join(f"--add-rich-rule={_q(r)}" for r in wanted)
    cmds.append(f"{FIREWALL_CMD} --permanent --policy {POLICY} {adds}")
    cmds.append(f"{FIREWALL_CMD} --reload")
    return cmds


class SiteError(Exception):
    pass


def _check(run, argv) -> str:
    rc, out, err = run(argv)
    if rc != 0:
        raise SiteError(f"{' '.join(argv[:4])} failed: {(err or out).strip()}")
    return out


def apply_nft(run, rules: list) -> bool:
    """The rules of ours in every nftables chain of the site that drops by default, and nowhere
    else, in one nft transaction; nothing done when they are there already. True when changed."""
    rc, listing, _err = run([NFT, "-j", "list", "ruleset"])
    if rc != 0:
        return False
    found = read(listing)
    targets = [c for c in found["chains"] if c["owner"] == "nft"]
    wanted = sorted(comment_of(r) for r in rules)
    keep = {(c["family"], c["table"], c["chain"]) for c in targets if c["comments"] == wanted}
    stray = [o for o in found["ours"] if tuple(o[:3]) not in keep]
    todo = [c for c in targets if (c["family"], c["table"], c["chain"]) not in keep]
    if not stray and not (todo and rules):
        return False
    cmds = [f"delete rule {f} {t} {ch} handle {h}" for f, t, ch, h, _c in stray]
    # inserted one after the other at the top: the last one ends first
    cmds += [_nft_insert(c, r) for c in todo for r in reversed(rules)]
    _check(run, [NFT, "; ".join(cmds)])
    return True


def apply_firewalld(run, wanted: list, fw: dict | None = None) -> bool:
    """The policy of ours in firewalld with exactly these rich rules, runtime and permanent; made
    (with the one reload it takes) where it is not there. True when changed. fw: _firewalld()'s
    answer where the caller has it."""
    fw = fw if fw is not None else _firewalld(run)
    if not fw.get("running"):
        return False
    if fw.get("permanent") is None:
        if not wanted:
            return False
        for cmd in firewalld_commands(wanted, fw):
            _check(run, shlex.split(cmd))
        return True
    changed = False
    for extra, have in (([], fw.get("runtime") or []), (["--permanent"], fw["permanent"])):
        # firewall-cmd takes adds and removes in separate calls
        for verb, rules in (("add", set(wanted) - set(have)), ("remove", set(have) - set(wanted))):
            if rules:
                _check(
                    run, [FIREWALL_CMD, *extra, "--policy", POLICY, *[f"--{verb}-rich-rule={r}" for r in sorted(rules)]]
                )
                changed = True
    return changed


def remove_firewalld(run) -> None:
    """No policy of ours in firewalld: its rules go now, the (empty) policy at firewalld's next
    reload; no reload of ours, which would lose the site's unsaved changes."""
    fw = _firewalld(run)
    if fw.get("running") and (fw.get("runtime") or fw.get("permanent") is not None):
        apply_firewalld(run, [], fw)
        if fw.get("permanent") is not None:
            _check(run, [FIREWALL_CMD, "--permanent", "--delete-policy", POLICY])


def main(argv, run, read_file, say) -> int:
    """isaac-sim-firewall-site apply|remove: after the site's nftables.service (re)loaded its
    rules, or at boot, the rules of ours in its chains again (the file the lifecycle left).
    say(text): where a failure is told (the unit's journal)."""
    text = read_file()
    if text is None:
        # no file: the site's chains are not the collection's to change (isaac_sim_firewall_site_policy: refuse)
        return 0
    try:
        wanted = json.loads(text).get("nft") or []
    except ValueError:
        wanted = []
    try:
        apply_nft(run, wanted if argv[1:] == ["apply"] else [])
    except SiteError as exc:
        say(f"isaac-sim-firewall-site: {exc}")
        return 1
    return 0
