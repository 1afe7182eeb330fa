"""The instances' firewall (module_utils/instance/firewall.py): the networks checked before any
change, the rules rendered from a plan, and the lifecycle loading the union of before and after
while instances change, the planned rules alone once they run as planned."""

from __future__ import annotations

import json

import pytest
from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib import layout, site_firewall
from ansible_collections.isaacsim.fleet.plugins.module_utils.instance import firewall, lifecycle, plan
from ansible_collections.isaacsim.fleet.tests.unit.helpers import plan_config
from ansible_collections.isaacsim.fleet.tests.unit.plugins.module_utils.instance.test_lifecycle import (
    NEVER,
    NEW,
    OLD,
    ScriptedHost,
    want,
)

HOST = {"memory_bytes": 64 * 1024**3, "image_present": True}
KINDS = {"signal", "stream", "web_viewer", "status", "hub_cache"}


def built(**over):
    return plan.build(plan_config(**over), HOST)


def errors_of(**over):
    with pytest.raises(plan.PlanError) as exc:
        built(**over)
    return exc.value.errors


def test_an_empty_list_is_refused_unless_the_firewall_is_off_and_off_warns():
    [error] = errors_of(allowed_networks=[])
    assert error.startswith("isaac_sim_allowed_networks: empty") and "isaac_sim_firewall: false" in error
    off = built(allowed_networks=[], firewall=False)
    assert off["firewall"] is None
    assert any(w.startswith("isaac_sim_firewall: false, so the instances'") for w in off["warnings"])


@pytest.mark.parametrize(
    ("given", "needle"),
    [
        (
            ["10.0.0.5/8"],
            "isaac_sim_allowed_networks: '10.0.0.5/8' has bits set after its prefix length. "
            "Fix: write the network, 10.0.0.0/8",
        ),
        (["10.0.0.0/33"], "isaac_sim_allowed_networks: '10.0.0.0/33' is not a network. Fix: write it in CIDR"),
        (["office"], "isaac_sim_allowed_networks: 'office' is not a network."),
        ("10.0.0.0/8", "isaac_sim_allowed_networks: '10.0.0.0/8' is not a list."),
    ],
)
def test_networks_are_checked_before_anything_changes(given, needle):
    assert any(e.startswith(needle) for e in errors_of(allowed_networks=given))


def test_networks_per_port_kind_name_a_kind_these_instances_have():
    [error] = errors_of(allowed_networks_by_port={"strem": ["10.1.0.0/16"]})
    assert error.startswith("isaac_sim_allowed_networks_by_port: 'strem' is not a port kind of these instances (")
    assert "stream" in error and "status" in error
    [error] = errors_of(allowed_networks_by_port={"status": ["10.1.0.1/16"]})
    assert error.startswith("isaac_sim_allowed_networks_by_port.status: '10.1.0.1/16' has bits set")


def test_everyone_allowed_is_accepted_with_a_warning():
    fw, errors, warnings = firewall.settings({"allowed_networks": ["0.0.0.0/0", "::/0"]}, KINDS)
    assert errors == [] and fw["default"] == ["0.0.0.0/0", "::/0"]
    assert len(warnings) == 2 and "keeps nobody out" in warnings[0]


def test_each_opened_port_answers_only_its_kind_s_networks():
    p = built(
        allowed_networks=["10.20.0.0/16", "fd00::/8"],
        allowed_networks_by_port={"status": ["10.9.0.0/24"]},
        instance_count=2,
        instance_profiles={"1": "headless"},
        status_server={"enabled": True, "port": 8290, "allow": ["10.9.0.0/24"]},
        web_viewer_image="reg.lab/viewer:1",
    )
    rows = p["firewall"]["ports"]
    # the streaming instance's signal and stream and its viewer's port; the headless one opens nothing
    assert sorted(map(tuple, rows)) == [
        ("host", "tcp", 8290, "status", ""),
        ("isaac-sim-0", "tcp", 8210, "web_viewer", ""),
        ("isaac-sim-0", "tcp", 49100, "signal", ""),
        ("isaac-sim-0", "udp", 47998, "stream", ""),
    ]
    text = firewall.render(p["firewall"], "managed")
    assert "table inet isaac_sim\ndelete table inet isaac_sim\ntable inet isaac_sim {" in text
    assert "\t\tudp dport 47998 jump allow-stream\n" in text and "\t\ttcp dport 49100 jump allow-signal\n" in text
    stream = text.split("chain allow-stream {", 1)[1].split("}\n", 1)[0]
    assert "ip saddr { 10.20.0.0/16 } accept" in stream and "ip6 saddr { fd00::/8 } accept" in stream
    assert stream.rstrip().endswith("drop")
    status = text.split("chain allow-status {", 1)[1].split("\t}", 1)[0]
    assert "ip saddr { 10.9.0.0/24 } accept" in status and "ip6" not in status
    assert "chain isaac-sim-1" not in text
    # the host, its containers on Docker's bridges: accepted before any rule
    assert '\t\tiifname "lo" accept\n\t\tiifname "docker0" accept\n\t\tiifname "br-*" accept\n' in text
    # no instance with an address of its own: the netdev table is only deleted
    assert text.endswith("table netdev isaac_sim\ndelete table netdev isaac_sim\n")


def test_instances_with_addresses_of_their_own_are_filtered_at_their_parent_s_ingress():
    p = {
        "instances": [
            {
                "name": "isaac-sim-0",
                "address": "10.0.0.50",
                "listens": ["signal"],
                "ports": {"signal": 49100},
                "protocols": {"signal": "tcp"},
                "companions": [],
            },
        ],
        "network": {"mode": "macvlan", "parent": "eth0"},
    }
    m = firewall.model({"enabled": True, "default": ["10.0.0.0/24"], "by_kind": {}}, p)
    assert m["parents"] == {"10.0.0.50": "eth0"}
    text = firewall.render(m, "managed")
    netdev = text.split("table netdev isaac_sim {", 1)[1]
    assert 'type filter hook ingress device "eth0" priority filter; policy accept;' in netdev
    assert "ip daddr 10.0.0.50 tcp dport 49100 jump allow-signal" in netdev
    assert "chain allow-signal {" in netdev
    # the host's input chain has no rule of an instance that is not on the host's network
    assert "49100" not in text.split("table netdev isaac_sim", 1)[0]


def test_a_merge_keeps_the_ports_of_both_and_takes_the_new_networks():
    four = built(allowed_networks=["10.1.0.0/16"])["firewall"]
    two = built(allowed_networks=["10.2.0.0/16"], instance_count=2)["firewall"]
    both = firewall.merge(four, two)
    assert sorted(map(tuple, both["ports"])) == sorted(map(tuple, four["ports"]))
    assert both["default"] == ["10.2.0.0/16"]
    assert firewall.merge(None, two) == two and firewall.merge(four, None) is None
    # 4 -> 2: exactly the chains (and jumps) of instances 2 and 3 go
    gone = set(firewall.render(four, "m").splitlines()) - set(firewall.render(two, "m").splitlines())
    assert {line.strip() for line in gone if "10.1.0.0/16" not in line} == {
        "chain isaac-sim-2 {",
        "chain isaac-sim-3 {",
        "jump isaac-sim-2",
        "jump isaac-sim-3",
        "tcp dport 49102 jump allow-signal",
        "tcp dport 49103 jump allow-signal",
        "udp dport 48000 jump allow-stream",
        "udp dport 48001 jump allow-stream",
    }


def test_the_unit_loads_the_rules_before_docker_and_comes_back_after_the_site_s_nftables():
    text = firewall.unit("managed")
    assert f"ExecStart={firewall.NFT} -f {firewall.RULES}\n" in text and "WantedBy=multi-user.target" in text
    dropin = firewall.site_dropin("managed")
    assert f"ExecStartPost=-{firewall.NFT} -f {firewall.RULES}\n" in dropin
    assert f"ExecReload=-{firewall.NFT} -f {firewall.RULES}\n" in dropin
    assert "Before=network-pre.target docker.service isaac-sim.target shutdown.target" in text
    assert "ExecStop=/usr/sbin/nft 'table inet isaac_sim; delete table inet isaac_sim; table netdev " in text


def model_of(n, networks=("10.0.0.0/8",)):
    return built(instance_count=n, allowed_networks=list(networks))["firewall"]


def loaded_ports(h) -> set:
    return {line.strip() for line in (h.tables or "").splitlines() if " dport " in line}


def test_a_fresh_host_has_its_rules_before_any_instance_starts_and_a_re_run_changes_nothing():
    h = ScriptedHost(4, running=False)
    result = lifecycle.apply(h.host, want({i: NEW for i in range(4)}, firewall=model_of(4), managed="m"))
    assert result["failed"] is None and result["plan"]["firewall"] == "load"
    first_load = h.log.index(f"{firewall.NFT} -f {firewall.RULES}")
    first_start = next(n for n, line in enumerate(h.log) if line.startswith("systemctl start isaac-sim@"))
    assert first_load < first_start
    assert h.wall_enabled and h.files[firewall.RULES][0] == firewall.render(model_of(4), "m")
    assert json.loads(h.files[firewall.STATE][0])["model"] == model_of(4)
    assert len(loaded_ports(h)) == 8
    h.log.clear()
    again = lifecycle.apply(h.host, want({i: NEW for i in range(4)}, firewall=model_of(4), managed="m"))
    assert again["changed"] is False and again["plan"]["firewall"] is None
    assert not [line for line in h.log if line.startswith(firewall.NFT + " -f")]


def test_a_site_chain_that_drops_by_default_gets_our_accepts_with_the_first_rules_and_keeps_them_in_step():
    h = ScriptedHost(4, running=False)
    site = ("inet", "filter", "input")
    h.site[site] = {"policy": "drop", "rules": [(1, "tcp dport 22 accept")]}
    result = lifecycle.apply(h.host, want({i: NEW for i in range(4)}, firewall=model_of(4), managed="m"))
    assert result["failed"] is None
    ours = site_firewall.nft_rules(site_firewall.groups(model_of(4)))
    # before the first instance starts, as our own table's rules
    site_call = next(n for n, line in enumerate(h.log) if "insert rule inet filter input" in line)
    first_start = next(n for n, line in enumerate(h.log) if line.startswith("systemctl start isaac-sim@"))
    assert site_call < first_start
    assert [text for _h, text in h.site[site]["rules"]] == [*ours, "tcp dport 22 accept"]
    # for isaac-sim-firewall-site (the site's nftables.service reloading its rules, the boot)
    assert json.loads(h.files[firewall.SITE_RULES][0]) == {"nft": ours}
    h.log.clear()
    again = lifecycle.apply(h.host, want({i: NEW for i in range(4)}, firewall=model_of(4), managed="m"))
    assert again["changed"] is False and not [line for line in h.log if "insert rule" in line]
    # the site dropped one of ours (a reload of its own file): the next deploy puts it back
    h.site[site]["rules"].pop(0)
    assert lifecycle.apply(h.host, want({i: NEW for i in range(4)}, firewall=model_of(4), managed="m"))["changed"]
    assert [text for _h, text in h.site[site]["rules"]] == [*ours, "tcp dport 22 accept"]
    # refuse: the site's chain is the site's; what is there stays, nothing is added
    refused = dict(model_of(4), site="refuse")
    lifecycle.apply(h.host, want({i: NEW for i in range(4)}, firewall=refused, managed="m"))
    assert firewall.SITE_RULES not in h.files and len(h.site[site]["rules"]) == len(ours) + 1
    # no firewall of ours: our accepts leave the site's chain with our tables
    lifecycle.apply(h.host, want({i: NEW for i in range(4)}, firewall=model_of(4), managed="m"))
    lifecycle.apply(h.host, want({i: NEW for i in range(4)}, firewall=None, managed="m"))
    assert h.site[site]["rules"] == [(1, "tcp dport 22 accept")]


def test_a_scale_down_keeps_the_rules_of_the_instances_that_go_until_they_are_gone():
    h = ScriptedHost(4, running=False)
    lifecycle.apply(h.host, want({i: NEW for i in range(4)}, firewall=model_of(4), managed="m"))
    seen = []
    remove = lifecycle.remove

    def watch(host, ids, *args, **kw):
        seen.append(set(loaded_ports(h)))
        return remove(host, ids, *args, **kw)

    lifecycle.remove = watch
    try:
        result = lifecycle.apply(h.host, want({0: NEW, 1: NEW}, remove=[2, 3], firewall=model_of(2), managed="m"))
    finally:
        lifecycle.remove = remove
    assert result["failed"] is None and result["plan"]["firewall"] == "load"
    assert len(seen[0]) == 8  # while 2 and 3 still ran
    assert loaded_ports(h) == {
        "tcp dport 49100 jump allow-signal",
        "tcp dport 49101 jump allow-signal",
        "udp dport 47998 jump allow-stream",
        "udp dport 47999 jump allow-stream",
    }


def test_a_failed_change_leaves_the_rules_of_before_and_after_loaded():
    h = ScriptedHost(2, running=True)
    lifecycle.apply(h.host, want({0: OLD, 1: OLD}, firewall=model_of(2), managed="m"))
    result = lifecycle.apply(h.host, want({0: OLD, 1: OLD, 2: NEVER}, firewall=model_of(3), managed="m"))
    assert result["failed"]["id"] == 2
    # nothing running lost its rule, and the new instance's rules stay until an apply that completes
    assert len(loaded_ports(h)) == 6
    kept = json.loads(h.files[firewall.STATE][0])["model"]
    assert kept == firewall.merge(model_of(2), model_of(3))


def test_check_mode_says_what_it_would_load_and_changes_nothing():
    h = ScriptedHost(4, running=True)
    result = lifecycle.apply(h.host, want({i: OLD for i in range(4)}, firewall=model_of(4), managed="m"), check=True)
    assert result["changed"] is True and result["plan"]["firewall"] == "load"
    assert h.tables is None and firewall.RULES not in h.files and not h.wall_enabled


def test_turned_off_the_rules_the_file_and_the_unit_go():
    h = ScriptedHost(2, running=False)
    lifecycle.apply(h.host, want({0: NEW, 1: NEW}, firewall=model_of(2), managed="m"))
    result = lifecycle.apply(h.host, want({0: NEW, 1: NEW}, firewall=None, managed="m"))
    assert result["changed"] is True and result["plan"]["firewall"] == "remove"
    assert h.tables is None and not h.wall_enabled
    assert firewall.RULES not in h.files and firewall.STATE not in h.files
    assert f"{layout.UNIT_DIR}/{firewall.UNIT}" not in h.files and firewall.SITE_DROPIN not in h.files


def test_a_host_without_nft_is_told_what_to_install():
    h = ScriptedHost(2, running=False)
    h.nft = False
    with pytest.raises(firewall.FirewallError, match=r"Fix: install nftables \(nft\) on the host"):
        lifecycle.apply(h.host, want({0: NEW, 1: NEW}, firewall=model_of(2), managed="m"))
    assert not any(line.startswith("systemctl start isaac-sim@") for line in h.log)


def test_rules_flushed_by_someone_else_are_loaded_again():
    h = ScriptedHost(2, running=False)
    lifecycle.apply(h.host, want({0: NEW, 1: NEW}, firewall=model_of(2), managed="m"))
    h.tables = None  # nft flush ruleset
    result = lifecycle.apply(h.host, want({0: NEW, 1: NEW}, firewall=model_of(2), managed="m"))
    assert result["changed"] is True and result["plan"]["firewall"] == "load" and len(loaded_ports(h)) == 4
