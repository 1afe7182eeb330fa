"""The isaac_sim_address_clashes filter, as roles/isaac_sim/tasks/validate.yml uses it: the plans of the
play's hosts (isaac_sim_plan's, from a real plan build) in, one error per address two hosts would
give their instances out, naming the variables to fix; the play fails once with them."""

from __future__ import annotations

import json

from ansible_collections.isaacsim.fleet.plugins.filter.isaac_sim_address_clashes import FilterModule, address_clashes
from ansible_collections.isaacsim.fleet.plugins.module_utils.instance import plan
from ansible_collections.isaacsim.fleet.tests.unit.helpers import plan_config
from ansible_collections.isaacsim.fleet.tests.unit.plugins.filter.conftest import find_task, trusted

VALIDATE = "roles/isaac_sim/tasks/validate.yml"
REFUSE = "Refuse an address given to instances on two hosts"
GIB = 1024**3
# a host on 10.0.0.0/24 whose default route is on eth0, as the plan module finds it
LAN_HOST = {
    "memory_bytes": 64 * GIB,
    "gpu_count": 0,
    "ports_held": [],
    "image_present": True,
    "interfaces": ["lo", "eth0"],
    "links": {"lo": [("127.0.0.1", 8)], "eth0": [("10.0.0.5", 24)]},
    "default_route": {"dev": "eth0", "gateway": "10.0.0.1"},
    "network": None,
}
FIX = "Fix: give each host a pool of its own."


def planned(**over) -> dict:
    """A host's __isaac_sim_plan: isaac_sim_plan's plan of four 6.x instances, as the module returns it."""
    return json.loads(json.dumps(plan.build(plan_config(**over), LAN_HOST)))


def own(pool, **over) -> dict:
    return planned(network_mode="macvlan", address_pool=pool, **over)


def refuse(render, plans: dict) -> tuple:
    """(the task's `when`, its message, the clashes) for hosts {host: plan, or None for none}, in order."""
    task = find_task(VALIDATE, REFUSE)
    hosts = list(plans)
    variables = {
        "ansible_play_hosts": hosts,
        "hostvars": {h: {} if p is None else {"__isaac_sim_plan": p} for h, p in plans.items()},
        **trusted(task["vars"]),
    }
    when = render("{{ " + task["when"] + " }}", variables)
    msg = render(task["ansible.builtin.fail"]["msg"], variables)
    return when, msg, render("{{ __isaac_sim_address_clashes }}", variables)


def test_two_hosts_on_overlapping_pools_fail_the_play_once_naming_each_shared_address(render):
    gpu1, gpu2 = own(["10.0.0.50-10.0.0.60"]), own(["10.0.0.52-10.0.0.60"])
    assert [i["address"] for i in gpu1["instances"]] == ["10.0.0.50", "10.0.0.51", "10.0.0.52", "10.0.0.53"]
    assert [i["address"] for i in gpu2["instances"]] == ["10.0.0.52", "10.0.0.53", "10.0.0.54", "10.0.0.55"]
    # gpu-3 shares its host's network (no addresses of its own), gpu-4 has no plan
    when, msg, clashes = refuse(render, {"gpu-1": gpu1, "gpu-2": gpu2, "gpu-3": planned(), "gpu-4": None})
    assert clashes == [
        "isaac_sim_address_pool / isaac_sim_instance_addresses: 10.0.0.52 is given to isaac-sim-2 on gpu-1 and "
        f"isaac-sim-0 on gpu-2. {FIX}",
        "isaac_sim_address_pool / isaac_sim_instance_addresses: 10.0.0.53 is given to isaac-sim-3 on gpu-1 and "
        f"isaac-sim-1 on gpu-2. {FIX}",
    ]
    assert when is True and msg == " ".join(clashes)


def test_an_instance_address_set_by_hand_clashes_with_another_host_s_pool(render):
    gpu1 = own(["10.0.0.50-10.0.0.53"])
    gpu2 = own(["10.0.0.60-10.0.0.62"], instance_addresses={"3": "10.0.0.51"})
    assert gpu2["instances"][3]["address"] == "10.0.0.51"
    when, _msg, clashes = refuse(render, {"gpu-2": gpu2, "gpu-1": gpu1})
    # the hosts are named in a stable order, whatever the play's order
    assert clashes == [
        "isaac_sim_address_pool / isaac_sim_instance_addresses: 10.0.0.51 is given to isaac-sim-1 on gpu-1 and "
        f"isaac-sim-3 on gpu-2. {FIX}"
    ]
    assert when is True


def test_pools_of_their_own_and_hosts_on_their_own_network_pass(render):
    # every host-network instance shares its host's address: never a clash, however many hosts
    when, _msg, clashes = refuse(
        render,
        {
            "gpu-1": own(["10.0.0.50-10.0.0.53"]),
            "gpu-2": own(["10.0.0.60-10.0.0.63"]),
            "gpu-3": planned(),
            "gpu-4": planned(),
        },
    )
    assert clashes == [] and when is False


def test_an_address_on_three_hosts_names_all_three_in_one_error():
    plans = [{"instances": [{"id": i, "address": "10.0.0.50"}]} for i in range(3)]
    plans[1]["instances"].append({"id": 0, "address": None})
    assert FilterModule().filters()["isaac_sim_address_clashes"] is address_clashes
    assert address_clashes(plans, ["c", "a", "b"]) == [
        "isaac_sim_address_pool / isaac_sim_instance_addresses: 10.0.0.50 is given to isaac-sim-1 on a and "
        f"isaac-sim-2 on b and isaac-sim-0 on c. {FIX}"
    ]
