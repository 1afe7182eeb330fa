"""Adding a release is one entry in the release table (instance/releases.py) and its URL shapes
(hostlib/endpoints.py URLS): with a scratch release 6.3 that opens a port kind no release has (a
telemetry port), added to those two tables only, the plan gives each instance the port in its block,
the env file tells the container and the unit's port check, the firewall opens it, the plan's summary
and the status report its URL, and the image tag 6.3.0 is 6.3's (not 6.x's, which comes first in the
table)."""

from __future__ import annotations

import pytest
from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib import endpoints, layout
from ansible_collections.isaacsim.fleet.plugins.module_utils.instance import firewall, plan, releases, unit_files
from ansible_collections.isaacsim.fleet.tests.unit.helpers import plan_config

TELEMETRY = ("tcp", 49300, releases.ENV, "ISAACSIM_TELEMETRY_PORT")


@pytest.fixture()
def release_6_3(monkeypatch):
    six = releases.RELEASES["6.x"]
    streaming = six["profiles"]["streaming"]
    entry = dict(
        six,
        default_tag="6.3.0",
        ports=dict(six["ports"], telemetry=TELEMETRY),
        profiles=dict(six["profiles"], streaming=dict(streaming, opens=[*streaming["opens"], "telemetry"])),
    )
    urls = (*endpoints.URLS["6.x"], ("telemetry", "telemetry", "http://{host}:{port}/metrics", endpoints.INSTANCE))
    entry["urls"] = urls
    # appended, as a new release would be: after 6.x, whose prefix 6 also starts the tag 6.3.0
    monkeypatch.setitem(releases.RELEASES, "6.3", entry)
    monkeypatch.setitem(endpoints.URLS, "6.3", urls)
    return entry


def test_a_release_with_a_port_kind_of_its_own_is_one_table_entry_and_its_url_shapes(release_6_3):
    assert releases.release_of_tag("6.3.0") == "6.3" and releases.release_of_tag("6.0.1") == "6.x"
    cfg = plan_config(release="6.3", image="registry.lab:5000/isaac-sim:6.3.0", instance_count=2)
    planned = plan.build(cfg, {"memory_bytes": 64 * 1024**3})
    assert not planned.get("errors"), planned.get("errors")
    assert [inst["ports"]["telemetry"] for inst in planned["instances"]] == [49300, 49301]
    # the container is told its port, and the unit checks the port free before it starts
    env = layout.parse(unit_files.render_env(planned["instances"][1], planned, "sha256:abc", {}, "managed"))
    assert env["ISAACSIM_TELEMETRY_PORT"] == "49301"
    assert env[layout.K_PORT_PREFIX + "TELEMETRY"] == "49301"
    assert "tcp/49301" in env[layout.K_PORTS].split()
    # the firewall opens it, as the block's other ports
    opened = {(row[1], row[2], row[3]) for row in firewall.entries(planned)}
    assert ("tcp", 49301, "telemetry") in opened
    # where a person reaches it, in the plan's summary and in status (the same shapes)
    assert "telemetry=http://10.0.0.5:49301/metrics" in endpoints.summary_lines(planned, "10.0.0.5")[1]
    got = endpoints.endpoints(
        "6.3", planned["instances"][1]["ports"], "gpu-1", listens=planned["instances"][1]["listens"]
    )
    assert got["telemetry"] == "http://gpu-1:49301/metrics" and got["signal"] == "gpu-1:49101"


def test_the_scratch_release_is_refused_an_image_of_another_release(release_6_3):
    cfg = plan_config(release="6.3", image="registry.lab:5000/isaac-sim:6.0.1", instance_count=1)
    with pytest.raises(plan.PlanError, match="tag 6.0.1 is an Isaac Sim 6.x image but isaac_sim_release is 6.3"):
        plan.build(cfg, {"memory_bytes": 64 * 1024**3})
