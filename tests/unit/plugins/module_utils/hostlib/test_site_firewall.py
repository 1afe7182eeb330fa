"""The site's own firewall beside the collection's (module_utils/hostlib/site_firewall.py).

The rulesets were recorded (nft -j list ruleset, nft 1.0.6) on a Debian 12 test host: with
firewalld 1.3.3 running (its default zone), and with a site's `table inet filter` whose input chain
has policy drop, a site table that accepts by default but drops one address, and iptables-nft's
`ip filter INPUT`. The rules written from them were loaded by a real nft on that host, and firewalld
took the policy and its rich rules from real firewall-cmd calls (the fleet scenario does both end
to end: tests/integration/fleet/test_unwanted_traffic.py).
"""

from __future__ import annotations

import json

import pytest
from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib import site_firewall as sf
from ansible_collections.isaacsim.fleet.plugins.module_utils.instance import plan
from ansible_collections.isaacsim.fleet.tests.unit.helpers import plan_config, recorded

MODEL = {
    "default": ["10.0.0.0/8", "fd00::/8"],
    "by_kind": {"status": ["192.168.1.0/24"]},
    "ports": [
        ["isaac-sim-0", "tcp", 49100, "signal", ""],
        ["isaac-sim-1", "tcp", 49101, "signal", ""],
        ["isaac-sim-0", "udp", 47998, "stream", ""],
        ["host", "tcp", 8290, "status", ""],
        # an instance with an address of its own: its traffic never passes the host's input hook
        ["isaac-sim-2", "tcp", 49102, "signal", "10.0.9.2"],
    ],
    "site": "add",
}


def site_ruleset(**policy) -> str:
    """The recorded site ruleset, iptables' INPUT given another policy where asked."""
    data = json.loads(recorded("nft-ruleset-site.json"))
    for item in data["nftables"]:
        chain = item.get("chain") or {}
        if (chain.get("table"), chain.get("name")) == ("filter", "INPUT") and "iptables" in policy:
            chain["policy"] = policy["iptables"]
    return json.dumps(data)


def test_only_the_input_chains_that_drop_by_default_are_found():
    found = sf.read(site_ruleset())
    # not ours, not the site table that accepts by default (its one drop is for one address), not Docker's
    # iptables-nft INPUT (policy accept), not a forward chain
    assert found["chains"] == [
        {"family": "inet", "table": "filter", "chain": "input", "why": "policy drop", "owner": "nft", "comments": []}
    ]
    [firewalld] = sf.read(recorded("nft-ruleset-firewalld.json"))["chains"]
    assert (firewalld["table"], firewalld["chain"], firewalld["owner"]) == ("firewalld", "filter_INPUT", "firewalld")
    assert firewalld["why"].startswith("an unconditional reject (rule handle ")
    [iptables] = [
        c for c in sf.read(site_ruleset(iptables="drop"))["chains"] if c["table"] == "filter" and c["family"] == "ip"
    ]
    assert iptables["owner"] == "iptables"


def test_what_a_site_chain_must_accept_follows_the_networks_of_each_port_and_the_local_interfaces():
    rules = sf.nft_rules(sf.groups(MODEL))
    bodies = [r.rsplit(" comment ", 1)[0] for r in rules]
    assert bodies == [
        'iifname { "lo", "docker0" } tcp dport { 8290, 49100, 49101 } accept',
        'iifname "br-*" tcp dport { 8290, 49100, 49101 } accept',
        "ip saddr 10.0.0.0/8 tcp dport { 49100, 49101 } accept",
        "ip saddr 192.168.1.0/24 tcp dport 8290 accept",
        "ip6 saddr fd00::/8 tcp dport { 49100, 49101 } accept",
        'iifname { "lo", "docker0" } udp dport 47998 accept',
        'iifname "br-*" udp dport 47998 accept',
        "ip saddr 10.0.0.0/8 udp dport 47998 accept",
        "ip6 saddr fd00::/8 udp dport 47998 accept",
    ]
    # each rule named by the digest of its own text: a changed rule is a new one
    assert all(r.endswith(f'comment "isaac-sim {sf._digest(b)}"') for r, b in zip(rules, bodies))
    assert sf.rich_rules(sf.groups(MODEL)) == [
        'rule family="ipv4" source address="10.0.0.0/8" port port="47998" protocol="udp" accept',
        'rule family="ipv4" source address="10.0.0.0/8" port port="49100-49101" protocol="tcp" accept',
        'rule family="ipv4" source address="192.168.1.0/24" port port="8290" protocol="tcp" accept',
        'rule family="ipv6" source address="fd00::/8" port port="47998" protocol="udp" accept',
        'rule family="ipv6" source address="fd00::/8" port port="49100-49101" protocol="tcp" accept',
    ]
    assert sf.groups(None) == [] and sf._ranges([1, 2, 3, 5, 7, 8]) == ["1-3", "5", "7-8"]


def test_refuse_names_the_chain_and_gives_the_exact_rules_until_they_are_there():
    found = sf.read(site_ruleset())
    assert sf.judge(found, MODEL, "add", "h1") == []
    [error] = sf.judge(found, MODEL, "refuse", "h1")
    assert error.startswith("h1: the site's chain inet filter input drops by default (policy drop)")
    assert "nothing was changed (isaac_sim_firewall_site_policy: refuse)" in error
    for rule in sf.nft_rules(sf.groups(MODEL)):
        assert f"nft '{sf._nft_insert(found['chains'][0], rule)}'" in error
    # the site added them as told (nft lists their comments): the deploy goes on
    found["chains"][0]["comments"] = sorted(r.rsplit('"', 2)[-2] for r in sf.nft_rules(sf.groups(MODEL)))
    assert sf.judge(found, MODEL, "refuse", "h1") == []
    # no firewall of ours, or nothing that drops by default: nothing to judge
    assert sf.judge(sf.read(site_ruleset()), None, "refuse") == []
    assert sf.judge({"chains": []}, MODEL, "refuse") == []


def test_iptables_own_chain_is_never_written_the_exact_iptables_commands_are_given():
    found = sf.read(site_ruleset(iptables="drop"))
    errors = sf.judge(found, MODEL, "add", "h1")
    [error] = [e for e in errors if "ip filter INPUT" in e]
    assert "the collection never writes into iptables' own tables" in error
    assert (
        "iptables -I INPUT -s 10.0.0.0/8 -p tcp -m multiport --dports 49100:49101 -m comment --comment "
        "'isaac-sim " in error
    )
    assert "fd00::/8" not in error  # ip6tables' rules are for ip6tables' INPUT
    wanted = {r[r.index("--comment") + 1] for r in sf.iptables_rules(sf.groups(MODEL), "iptables")}
    [c for c in found["chains"] if c["owner"] == "iptables"][0]["comments"] = sorted(wanted)
    assert not [e for e in sf.judge(found, MODEL, "add", "h1") if "ip filter INPUT" in e]


def test_firewalld_gets_a_policy_of_ours_unless_refused_or_its_unsaved_changes_would_be_lost():
    found = sf.read(recorded("nft-ruleset-firewalld.json"))
    found["firewalld"] = {"running": True, "runtime": None, "permanent": None, "unsaved": []}
    assert sf.judge(found, MODEL, "add") == []
    [error] = sf.judge(found, MODEL, "refuse")
    assert "firewall-cmd --permanent --new-policy isaac-sim" in error and "--add-ingress-zone ANY" in error
    assert '--add-rich-rule=\'rule family="ipv4" source address="10.0.0.0/8"' in error
    found["firewalld"]["unsaved"] = ["zones"]
    [error] = sf.judge(found, MODEL, "add")
    assert "firewalld has changes in its running zones that are not permanent" in error
    assert "firewall-cmd --runtime-to-permanent" in error
    # the policy is there: no reload needed, nothing to lose
    wanted = sf.rich_rules(sf.groups(MODEL))
    found["firewalld"].update(runtime=wanted, permanent=wanted)
    assert sf.judge(found, MODEL, "add") == [] and sf.judge(found, MODEL, "refuse") == []


class Nft:
    """nft as the kernel answers it: a site chain with policy drop, rules inserted at its top."""

    def __init__(self, rules=()):
        self.rules, self.handle, self.calls = list(rules), 10, []

    def run(self, argv):
        if argv[1:] == ["-j", "list", "ruleset"]:
            items = [{"chain": {"family": "inet", "table": "filter", "name": "input", "hook": "input",
                                "type": "filter", "policy": "drop"}}]  # fmt: skip
            for handle, text in self.rules:
                rule = {"family": "inet", "table": "filter", "chain": "input", "handle": handle, "expr": []}
                if ' comment "' in text:
                    rule["comment"] = text.rsplit('"', 2)[-2]
                items.append({"rule": rule})
            return 0, json.dumps({"nftables": items}), ""
        self.calls.append(argv[1])
        for cmd in argv[1].split("; "):
            if cmd.startswith("delete rule"):
                self.rules = [r for r in self.rules if r[0] != int(cmd.split()[-1])]
            else:
                self.handle += 1
                self.rules.insert(0, (self.handle, cmd.split(" ", 5)[5]))
        return 0, "", ""


def test_the_accepts_go_in_once_in_one_transaction_and_come_out_on_remove():
    nft = Nft([(1, "tcp dport 22 accept")])
    rules = sf.nft_rules(sf.groups(MODEL))
    assert sf.apply_nft(nft.run, rules) is True
    assert [text for _h, text in nft.rules] == [*rules, "tcp dport 22 accept"] and len(nft.calls) == 1
    # again: nothing to do, no call at all
    assert sf.apply_nft(nft.run, rules) is False and len(nft.calls) == 1
    # the networks changed: the old rules out, the new in, one transaction
    fewer = sf.nft_rules(sf.groups(dict(MODEL, default=["10.0.0.0/8"])))
    assert sf.apply_nft(nft.run, fewer) is True and len(nft.calls) == 2
    assert [text for _h, text in nft.rules] == [*fewer, "tcp dport 22 accept"]
    # isaac-sim-firewall-site: without the deploy's file the site's chains are not touched (refuse)
    assert sf.main(["x", "remove"], nft.run, lambda: None, print) == 0 and len(nft.calls) == 2
    assert sf.main(["x", "remove"], nft.run, lambda: json.dumps({"nft": fewer}), print) == 0
    assert nft.rules == [(1, "tcp dport 22 accept")]
    assert sf.main(["x", "apply"], nft.run, lambda: json.dumps({"nft": fewer}), print) == 0
    assert [text for _h, text in nft.rules] == [*fewer, "tcp dport 22 accept"]
    # nft refused the transaction: said (in the unit's journal), a failed ExecStartPost that does not fail the unit
    said = []

    def refusing(argv):
        return nft.run(argv) if argv[1] == "-j" else (1, "", "Error: Could not process rule: No such file")

    assert sf.main(["x", "remove"], refusing, lambda: json.dumps({"nft": fewer}), said.append) == 1
    assert said[0].startswith("isaac-sim-firewall-site: /usr/sbin/nft delete rule inet filter input handle")
    assert said[0].endswith("failed: Error: Could not process rule: No such file")


class Firewalld:
    """firewall-cmd's answers: a running firewalld, the policy of ours once made permanent."""

    def __init__(self, unsaved=False):
        self.runtime, self.permanent, self.calls, self.unsaved = None, None, [], unsaved

    def run(self, argv):
        args = argv[1:]
        self.calls.append(" ".join(args))
        permanent = "--permanent" in args
        args = [a for a in args if a != "--permanent"]
        if args == ["--state"]:
            return 0, "running\n", ""
        if args[:1] in (["--list-all-zones"], ["--list-all-policies"]):
            return 0, "public\n  ports: 1/tcp\n" if self.unsaved and not permanent else "public\n  ports: \n", ""
        if args == ["--reload"]:
            self.runtime = list(self.permanent or [])
            return 0, "success\n", ""
        if args == ["--new-policy", sf.POLICY]:
            self.permanent = []
            return 0, "success\n", ""
        have = self.permanent if permanent else self.runtime
        if have is None:
            return 2, "", "Error: INVALID_POLICY: isaac-sim"
        if args[-1] == "--list-rich-rules":
            return 0, "\n".join(have) + "\n", ""
        for a in args[2:]:
            verb, _sep, rule = a.partition("=")
            if verb == "--add-rich-rule":
                have.append(rule)
            elif verb == "--remove-rich-rule":
                have.remove(rule)
        return 0, "success\n", ""


def test_firewalld_s_policy_is_made_once_then_changed_rule_by_rule_runtime_and_permanent():
    fw = Firewalld()
    wanted = sf.rich_rules(sf.groups(MODEL))
    assert sf.apply_firewalld(fw.run, wanted) is True
    assert fw.calls.count("--reload") == 1 and sorted(fw.runtime) == wanted == sorted(fw.permanent)
    fw.calls.clear()
    assert sf.apply_firewalld(fw.run, wanted) is False and "--reload" not in fw.calls
    fewer = sf.rich_rules(sf.groups(dict(MODEL, default=["10.0.0.0/8"])))
    assert sf.apply_firewalld(fw.run, fewer) is True and "--reload" not in fw.calls
    assert sorted(fw.runtime) == fewer == sorted(fw.permanent)
    sf.remove_firewalld(fw.run)
    assert fw.runtime == [] and fw.calls[-1] == "--permanent --delete-policy isaac-sim"


def test_the_plan_stops_before_any_change_on_a_chain_it_may_not_change():
    host = {"memory_bytes": 64 * 1024**3, "image_present": True, "site_firewall": sf.read(site_ruleset())}
    cfg = plan_config(allowed_networks=["10.0.0.0/8"], firewall_site_policy="refuse")
    with pytest.raises(plan.PlanError) as exc:
        plan.build(cfg, host)
    [error] = exc.value.errors
    assert error.startswith("this host: the site's chain inet filter input drops by default")
    assert plan.build(dict(cfg, firewall_site_policy="add"), host)["firewall"]["site"] == "add"
    with pytest.raises(plan.PlanError) as exc:
        plan.build(dict(cfg, firewall_site_policy="open"), host)
    assert exc.value.errors[0].startswith("isaac_sim_firewall_site_policy: 'open' is not one of add, refuse.")
