"""Adding a release is one entry in the release table (instance/releases.py) and its URL shapes
(hostlib/endpoints.py URLS): with a scratch release 6.3 that opens a port kind no release has (a
telemetry port), added to those two tables only, the plan gives each instance the port in its block,
the env file tells the container and the unit's port check, the firewall opens it, the plan's summary
and the status report its URL, and the image tag 6.3.0 is 6.3's (not 6.x's, which comes first in the
table).

Adding a built-in companion is one entry in hostlib/builtin_companions.py (and, for a release to keep
it a port, a port kind in the release's block): with a scratch recorder beside each streaming instance,
the plan runs it with its image and its port, its unit and env file follow, its image is pulled with
the instance's and named by its variable where it is missing, and its URL is reported. (For users, the
plan module's option and the role's variable document it: test_builtin_companion_options checks them.)"""

from __future__ import annotations

from pathlib import Path

import pytest
from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib import builtin_companions, endpoints, layout
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


RECORDER = {
    "variable": "isaac_sim_recorder_image",
    "port": "recorder",
    "profiles": ("streaming",),
    "url": ("recording", "http://{host}:{port}/live"),
    "title": "recorder",
    "made_by": "the team's own build",
    "example": "registry.lab:5000/isaac-sim/recorder:1",
    "container": {
        "user": "1234:1234",
        "env": {"RECORD_FROM": "{host}:{port.signal}", "RECORD_PORT": "{port.recorder}"},
        "ports": {"http": "recorder"},
        "healthcheck": {"test": ["CMD", "true"], "timeout": 5, "start_period": 10, "retries": 3},
    },
}


@pytest.fixture()
def recorder(monkeypatch, release_6_3):
    # the release keeps the companion a port of its block, as 6.x keeps its web viewer's
    monkeypatch.setitem(release_6_3["ports"], "recorder", ("tcp", 8600, None, None))
    monkeypatch.setitem(builtin_companions.BUILT_IN, "recorder", RECORDER)
    return RECORDER


def test_a_built_in_companion_is_one_table_entry(recorder):
    cfg = plan_config(
        release="6.3",
        image="registry.lab:5000/isaac-sim:6.3.0",
        instance_count=2,
        instance_profiles={1: "headless"},
        recorder_image="registry.lab:5000/isaac-sim/recorder:1",
    )
    planned = plan.build(cfg, {"memory_bytes": 64 * 1024**3})
    # the streaming instance 0 gets it on its block's port; the headless instance 1 streams nothing to record
    # the instances keep their own image (a built-in's image is its companion's alone)
    assert planned["image"] == "registry.lab:5000/isaac-sim:6.3.0"
    instance_env = layout.parse(unit_files.render_env(planned["instances"][0], planned, "sha256:abc", {}, "managed"))
    assert instance_env[layout.K_IMAGE] == "registry.lab:5000/isaac-sim:6.3.0"
    streaming, headless = planned["instances"]
    (comp,) = [c for c in streaming["companions"] if c["name"] == "recorder"]
    assert comp["ports"] == {"http": 8600} and not [c for c in headless["companions"] if c["name"] == "recorder"]
    env = layout.parse(unit_files.render_companion_env(comp, planned, "managed"))
    assert env[layout.K_CONTAINER] == "isaac-sim-0-recorder" and env[layout.K_PORTS] == "tcp/8600"
    (template,) = [u for u in planned["companion_units"] if u["name"] == "recorder"]
    unit = unit_files.render_companion_unit(template, planned["settings"], "managed")
    assert "EnvironmentFile=/etc/isaac-sim/instance-%i.recorder.env" in unit.splitlines()
    # where a person reaches it
    assert "recording=http://10.0.0.5:8600/live" in endpoints.summary_lines(planned, "10.0.0.5")[0]
    # its image is pulled with the instance's, named by its variable
    wanted = builtin_companions.images(release_6_3_ports(), ["streaming"], builtin_companions.given(cfg))
    assert ("registry.lab:5000/isaac-sim/recorder:1", "isaac_sim_recorder_image") in wanted
    # a bad reference is refused naming the variable
    with pytest.raises(plan.PlanError, match="isaac_sim_recorder_image: 'not an image' is not a valid image"):
        plan.build(dict(cfg, recorder_image="not an image"), {"memory_bytes": 64 * 1024**3})


def release_6_3_ports():
    return releases.RELEASES["6.3"]["ports"]


def test_builtin_companion_options():
    """What a user sets for each built-in companion: the role's variable (documented in its argument spec),
    passed by the plan's call to the plan module's option of the same name (documented there)."""
    import ast

    import yaml
    from ansible_collections.isaacsim.fleet.plugins.modules import isaac_sim_plan

    root = Path(__file__).resolve().parents[2]
    tree = ast.parse((root / "plugins/modules/isaac_sim_plan.py").read_text())
    docs = next(n.value.value for n in tree.body if isinstance(n, ast.Assign) and n.targets[0].id == "DOCUMENTATION")
    documented = yaml.safe_load(docs)["options"]
    role = yaml.safe_load((root / "roles/isaac_sim/meta/argument_specs.yml").read_text())["argument_specs"]["main"]
    call = (root / "roles/isaac_sim/tasks/validate.yml").read_text()
    for name, entry in builtin_companions.BUILT_IN.items():
        option = builtin_companions.option(name)
        assert option in isaac_sim_plan.ARGUMENT_SPEC and option in documented, option
        assert entry["variable"] in role["options"], entry["variable"]
        assert f'{option}: "{{{{ {entry["variable"]} }}}}"' in call, option
