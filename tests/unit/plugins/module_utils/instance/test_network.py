import json

from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib import layout
from ansible_collections.isaacsim.fleet.plugins.module_utils.instance import network

# `ip -j -4 addr show` and `ip -j -4 route show default` as iproute2 6.1 (Debian 12) prints them
LINKS = json.dumps(
    [
        {"ifindex": 1, "ifname": "lo", "addr_info": [{"family": "inet", "local": "127.0.0.1", "prefixlen": 8}]},
        {"ifindex": 2, "ifname": "eth0", "addr_info": [{"family": "inet", "local": "10.20.0.5", "prefixlen": 24}]},
        {"ifindex": 3, "ifname": "docker0", "addr_info": [{"family": "inet", "local": "172.18.0.1", "prefixlen": 16}]},
    ]
)
ROUTE = json.dumps([{"dst": "default", "gateway": "10.20.0.1", "dev": "eth0", "flags": []}])
HOST = {
    "links": network.parse_links(LINKS),
    "interfaces": ["lo", "eth0", "docker0"],
    "default_route": network.parse_default_route(ROUTE),
    "network": None,
}


def cfg(**over):
    base = {"network_mode": "macvlan", "address_pool": ["10.20.0.50-10.20.0.57"], "max_instances": 8}
    base.update(over)
    return base


def test_defaults_come_from_the_default_route_and_addresses_from_the_pool_in_order():
    net, addresses, errors = network.plan(cfg(), HOST, [0, 1, 2, 3])
    assert errors == []
    assert net == {
        "mode": "macvlan",
        "name": layout.NETWORK,
        "driver": "macvlan",
        "parent": "eth0",
        "subnet": "10.20.0.0/24",
        "gateway": "10.20.0.1",
    }
    assert addresses == {0: "10.20.0.50", 1: "10.20.0.51", 2: "10.20.0.52", 3: "10.20.0.53"}


def test_a_fixed_address_wins_and_the_pool_fills_the_rest_skipping_what_cannot_be_used():
    host = dict(HOST, network={"ours": True, "containers": {"someone-else": "10.20.0.51"}, **_net()})
    _net_, addresses, errors = network.plan(
        cfg(address_pool=["10.20.0.5", "10.20.0.1", "10.20.0.48/30"], instance_addresses={"2": "10.20.0.60"}),
        host,
        [0, 1, 2],
    )
    # .5 is the host's and .1 the gateway: skipped; the block's first and last are LAN addresses like any
    assert errors == [] and addresses == {0: "10.20.0.48", 1: "10.20.0.49", 2: "10.20.0.60"}
    _n, addresses, _e = network.plan(cfg(address_pool=["10.20.0.50/31"]), host, [0])
    assert addresses == {0: "10.20.0.50"}  # .51 is someone else's


def _net():
    return {"driver": "macvlan", "parent": "eth0", "subnet": "10.20.0.0/24", "gateway": "10.20.0.1"}


def test_a_pool_too_small_says_how_many_and_why_addresses_were_refused():
    _n, _a, errors = network.plan(cfg(address_pool=["10.20.0.5", "10.20.0.50"]), HOST, [0, 1, 2])
    assert errors == [
        "isaac_sim_address_pool: 1 usable address(es) for the 3 instance(s) that need one from the pool (0, 1, 2) "
        "(10.20.0.5 is an address of this host). Fix: add addresses of 10.20.0.0/24 that no machine uses, or give "
        "instances isaac_sim_instance_addresses."
    ]


def test_a_missing_interface_bad_subnet_and_gateway_are_named():
    _n, _a, errors = network.plan(cfg(macvlan_parent="eth9"), HOST, [0])
    assert errors[0].startswith("isaac_sim_macvlan_parent: 'eth9' is not a network interface of this host")
    assert "docker0, eth0" in errors[0]
    _n, _a, errors = network.plan(cfg(macvlan_subnet="10.20.0.0/33"), HOST, [0])
    assert errors == [
        "isaac_sim_macvlan_subnet: '10.20.0.0/33' is not an IPv4 network. Fix: give the LAN's, e.g. 192.168.10.0/24."
    ]
    _n, _a, errors = network.plan(cfg(macvlan_gateway="10.30.0.1"), HOST, [0])
    assert errors == [
        "isaac_sim_macvlan_gateway: 10.30.0.1 is not in the subnet 10.20.0.0/24. Fix: give the LAN's router address."
    ]
    no_route = dict(HOST, default_route={})
    _n, _a, errors = network.plan(cfg(), no_route, [0])
    assert errors[0].startswith("isaac_sim_macvlan_parent: empty, and this host has no IPv4 default route")


def test_addresses_outside_the_subnet_in_the_map_or_twice_are_refused():
    _n, _a, errors = network.plan(
        cfg(address_pool=[], instance_addresses={0: "10.30.0.9", 1: "10.20.0.70", 2: "10.20.0.70", 9: "10.20.0.71"}),
        HOST,
        [0, 1, 2],
    )
    assert any(e.startswith("isaac_sim_instance_addresses.0: 10.30.0.9 is not a host address of") for e in errors)
    assert any("10.20.0.70 is given to instances 1 and 2" in e for e in errors)
    assert any(e.startswith("isaac_sim_instance_addresses.9: 9 is not an instance number (0..7)") for e in errors)


def test_pool_entries_that_do_not_parse_are_named():
    errors = []
    assert network.expand_pool(["10.0.0.9-10.0.0.2", "10.0.0.0/40", "nope", "10.0.0.4", "10.0.0.5/30"], errors) == [
        network.ipaddress.IPv4Address("10.0.0.4")
    ]
    assert len(errors) == 4 and all(e.startswith("isaac_sim_address_pool") for e in errors)


def test_a_network_in_use_cannot_change_under_its_instances_and_a_foreign_one_is_refused():
    in_use = dict(_net(), ours=True, containers={"isaac-sim-0": "10.20.0.50"})
    _n, _a, errors = network.plan(cfg(macvlan_subnet="10.20.0.0/23"), dict(HOST, network=in_use), [0])
    assert len(errors) == 1 and "isaac-sim-0 use it, so it cannot change under them" in errors[0]
    assert "isaac_sim_network_mode: host first" in errors[0]
    foreign = dict(_net(), ours=False, containers={})
    _n, _a, errors = network.plan(cfg(), dict(HOST, network=foreign), [0])
    assert errors[0].startswith(f"isaac_sim_network_mode: a Docker network named {layout.NETWORK} exists")


def test_the_action_on_the_host_network():
    wanted, _a, _e = network.plan(cfg(), HOST, [0])
    assert network.action(wanted, None) == "create"
    assert network.action(wanted, dict(_net(), ours=True, containers={"isaac-sim-0": "x"})) is None
    assert network.action(wanted, dict(_net(), subnet="10.20.0.0/23", ours=True, containers={})) == "recreate"
    assert network.action(wanted, dict(_net(), subnet="10.20.0.0/23", ours=True, containers={"a": "x"})) == "conflict"
    assert network.action({"mode": "host"}, dict(_net(), ours=True, containers={})) == "remove"
    assert network.action({"mode": "host"}, dict(_net(), ours=False, containers={})) is None
    assert network.action({"mode": "host"}, None) is None
    assert network.create_argv(wanted) == [
        "docker", "network", "create", "--driver", "macvlan", "--subnet", "10.20.0.0/24", "--gateway", "10.20.0.1",
        "--opt", "parent=eth0", "--label", f"{layout.LABEL_NETWORK}=macvlan", layout.NETWORK,
    ]  # fmt: skip


def test_docker_s_answer_is_read():
    # GET /networks/isaac-sim-macvlan from Docker 20.10, trimmed
    answer = {
        "Name": layout.NETWORK,
        "Driver": "macvlan",
        "IPAM": {"Driver": "default", "Config": [{"Subnet": "10.20.0.0/24", "Gateway": "10.20.0.1"}]},
        "Options": {"parent": "eth0"},
        "Labels": {layout.LABEL_NETWORK: "macvlan"},
        "Containers": {"ab12": {"Name": "isaac-sim-0", "IPv4Address": "10.20.0.50/24", "IPv6Address": ""}},
    }
    found = network.parse_network(answer)
    assert found == dict(_net(), ours=True, containers={"isaac-sim-0": "10.20.0.50"})
    assert network.parse_network([answer]) == found and network.parse_network(None) is None


def test_host_mode_needs_nothing_and_an_unknown_mode_is_named():
    assert network.plan({"network_mode": "host"}, {}, [0]) == ({"mode": "host", "found": False}, {}, [])
    _n, _a, errors = network.plan({"network_mode": "ipvlan"}, {}, [0])
    assert errors == ["isaac_sim_network_mode: 'ipvlan' is not a network mode. Fix: choose host or macvlan."]


def test_an_address_on_two_hosts_is_a_clash():
    assert network.clashes({"a": {0: "10.20.0.50", 1: "10.20.0.51"}, "b": {0: "10.20.0.51"}}) == [
        "isaac_sim_address_pool / isaac_sim_instance_addresses: 10.20.0.51 is given to isaac-sim-1 on a and "
        "isaac-sim-0 on b. Fix: give each host a pool of its own."
    ]


def test_a_subnet_the_parent_is_not_on_is_refused_and_a_foreign_container_named_like_ours_counts():
    _n, _a, errors = network.plan(cfg(macvlan_subnet="10.2.0.0/24", macvlan_gateway="10.2.0.1"), HOST, [0])
    # and the pool of 10.20.0.x is outside it too
    assert len(errors) == 2 and errors[1].startswith("isaac_sim_address_pool: 0 usable address(es)")
    assert errors[:1] == [
        "isaac_sim_macvlan_subnet: 10.2.0.0/24 is not a network of eth0, which is on 10.20.0.0/24: the instances' "
        "addresses would be unreachable. Fix: give eth0's network, or the interface on 10.2.0.0/24 as "
        "isaac_sim_macvlan_parent."
    ]
    host = dict(HOST, network=dict(_net(), ours=True, containers={"isaac-sim-web": "10.20.0.50"}))
    _n, addresses, _e = network.plan(cfg(), host, [0])
    assert addresses == {0: "10.20.0.51"}
