"""The filter by which the deploy leaves out a host service's module call (filter/isaac_sim_host_service_in_place)."""

from __future__ import annotations

from ansible_collections.isaacsim.fleet.plugins.filter.isaac_sim_host_service_in_place import (
    FilterModule,
    isaac_sim_host_service_in_place,
)
from ansible_collections.isaacsim.fleet.plugins.module_utils.host import host_service

UNIT = "/etc/systemd/system/isaac-sim-status.service"
FILES = {UNIT: {"content": "[Service]\n"}}
SEEN = {
    "ActiveState": "active",
    "UnitFileState": "enabled",
    "files": {UNIT: [host_service.digest("[Service]\n"), 0o644, 0, 0]},
    "directories": {"/var/lib/x": [0o755, 0, 0]},
}


def test_as_wanted_is_in_place_and_anything_else_is_not():
    assert isaac_sim_host_service_in_place(FILES, SEEN) is True
    assert isaac_sim_host_service_in_place({UNIT: {"content": "[Service]\nX=1\n"}}, SEEN) is False
    assert isaac_sim_host_service_in_place(FILES, dict(SEEN, ActiveState="inactive")) is False
    # the directories the module would make, as it would check them
    assert isaac_sim_host_service_in_place(FILES, SEEN, [{"path": "/var/lib/x", "uid": 0, "gid": 0, "mode": "0755"}])
    assert not isaac_sim_host_service_in_place(
        FILES, SEEN, [{"path": "/var/lib/x", "uid": 0, "gid": 0, "mode": "0700"}]
    )


def test_a_service_the_plan_did_not_read_is_never_in_place():
    assert isaac_sim_host_service_in_place(FILES, {}) is False
    assert isaac_sim_host_service_in_place(FILES, None) is False


def test_it_is_registered_under_its_name():
    assert FilterModule().filters() == {"isaac_sim_host_service_in_place": isaac_sim_host_service_in_place}
