"""Companions: the list checked, placed per instance, rendered as a unit and an env file."""

import pytest
from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib import endpoints, layout
from ansible_collections.isaacsim.fleet.plugins.module_utils.instance import plan, unit_files
from ansible_collections.isaacsim.fleet.tests.unit.helpers import plan_config

VIEWER = {
    "name": "viewer",
    "image": "reg/web-viewer:1",
    "command": ["serve", "--host", "{host}", "--port", "{port.web_viewer}", "--signal", "{port.signal}"],
    "ports": {"http": "web_viewer"},
    "healthcheck": {"test": ["CMD", "curl", "-f", "http://{host}:{port.http}/"], "interval": 5},
}
BRIDGE = {
    "name": "ros-bridge",
    "image": "reg/bridge:2",
    "command": "bridge --instance {instance} --ws {port.ws}",
    "env": {"ROS_DOMAIN_ID": "{instance}"},
    "ports": {"ws": 9100},
    "volumes": ["bags:/bags", "/srv/maps:/maps:ro"],
}


HOST = {"memory_bytes": 64 * 1024**3, "image_present": True}


def build(companions, **over):
    # BRIDGE binds /srv/maps: a directory the site declares (the container policy's bind roots)
    over.setdefault("allowed_bind_roots", ["/srv/maps"])
    return plan.build(plan_config(companions=companions, **over), HOST)


def errors_of(companions, **over):
    with pytest.raises(plan.PlanError) as exc:
        build(companions, **over)
    return exc.value.errors


def test_each_instance_gets_its_companions_with_its_own_ports_and_values():
    result = build([VIEWER, BRIDGE], port_stride=2)
    inst = result["instances"][1]
    viewer, bridge = inst["companions"]
    # the viewer takes the port the release keeps for it in the instance's block
    assert viewer["ports"] == {"http": 8212} and inst["ports"]["web_viewer"] == 8212
    assert viewer["app_args"] == ["serve", "--host", "10.0.0.5", "--port", "8212", "--signal", "49102"]
    assert "--health-cmd=curl -f 'http://10.0.0.5:8212/'" in viewer["docker_args"]
    # a port of its own: base + instance * stride, as the instance's ports
    assert bridge["ports"] == {"ws": 9102} and bridge["app_args"] == ["bridge", "--instance", "1", "--ws", "9102"]
    assert bridge["container_env"]["ROS_DOMAIN_ID"] == "1"
    assert bridge["container_env"][layout.K_HOST] == "10.0.0.5"
    assert bridge["container_env"]["ISAAC_SIM_PORT_SIGNAL"] == "49102"
    assert "--volume=/var/lib/isaac-sim/instance-1/companions/ros-bridge/bags:/bags:rw" in bridge["docker_args"]
    assert "--volume=/srv/maps:/maps:ro" in bridge["docker_args"]
    assert "/var/lib/isaac-sim/instance-1/companions/ros-bridge/bags" in inst["dirs"]
    assert f"--label={layout.LABEL_COMPANION}=ros-bridge" in bridge["docker_args"]
    # stopped at once even when its server is PID 1
    assert "--init" in bridge["docker_args"] and "--security-opt=no-new-privileges" in bridge["docker_args"]
    assert [u["name"] for u in result["companion_units"]] == ["viewer", "ros-bridge"]


def test_a_companion_can_be_given_to_some_instances_only():
    result = build([dict(BRIDGE, instances=[0, 2])])
    assert [len(inst["companions"]) for inst in result["instances"]] == [1, 0, 1, 0]
    # an instance scaled away may stay listed
    assert [len(inst["companions"]) for inst in build([dict(BRIDGE, instances=[1, 5])])["instances"]] == [0, 1, 0, 0]


@pytest.mark.parametrize(
    "spec, words",
    [
        ({"name": "Viewer", "image": "x"}, "cannot name a companion"),
        ({"name": "metrics", "image": "x"}, "cannot name a companion"),
        ({"name": "rec"}, "isaac_sim_companions[rec].image: missing"),
        ({"name": "rec", "image": "x", "restart": "no"}, "restart is not a companion setting"),
        ({"name": "rec", "image": "x", "ports": {"ws": "signal"}}, "the Isaac Sim instance itself listens on"),
        ({"name": "rec", "image": "x", "ports": {"ws": "lots"}}, "neither a base port"),
        ({"name": "rec", "image": "x", "volumes": ["data"]}, "is not SOURCE:TARGET"),
        ({"name": "rec", "image": "x", "volumes": ["../up:/x"]}, "must be an absolute host path or a plain name"),
        ({"name": "rec", "image": "x", "env": {"ISAAC_SIM_X": "1"}}, "is not a usable variable name"),
        ({"name": "rec", "image": "x", "healthcheck": {"test": ["NONE"]}}, "is not a healthcheck command"),
        ({"name": "rec", "image": "x", "gpu": True}, "isaac_sim_gpu_enabled is false"),
        ({"name": "rec", "image": "x", "instances": [8]}, "is not an instance number (0..7"),
        ({"name": "rec", "image": "x", "command": "run {gpu}"}, None),
        ({"name": "rec", "image": "x", "command": "run {port.nope}"}, "{port.nope} is not known here"),
        ({"name": "rec", "image": "x", "ready_timeout": "soon"}, "ready_timeout: 'soon' is not a whole number"),
    ],
)
def test_bad_companions_are_refused_naming_the_setting(spec, words):
    if words is None:  # braces that are not a placeholder are left alone
        assert build([spec])["instances"][0]["companions"][0]["app_args"] == ["run", "{gpu}"]
        return
    found = errors_of([spec])
    assert any(words in e for e in found), found
    assert all(e.startswith("isaac_sim_companions") for e in found)


def test_two_companions_with_one_name_are_refused():
    assert any("two companions are named rec" in e for e in errors_of([{"name": "rec", "image": "x"}] * 2))


def test_companion_ports_may_not_land_on_another_port_or_one_held_by_another_process():
    # 49102 is instance 2's signal port
    found = errors_of([{"name": "rec", "image": "x", "ports": {"ws": 49100}}])
    assert any("instance 0's port 49100 is also instance 0 signal's port" in e for e in found)
    found = errors_of(
        [{"name": "a", "image": "x", "ports": {"p": 9100}}, {"name": "b", "image": "x", "ports": {"p": 9102}}]
    )
    assert any(
        "isaac_sim_companions[b].ports.p: instance 0's port 9102 is also instance 2 companion a p's port" in e
        for e in found
    )
    with pytest.raises(plan.PlanError) as exc:
        plan.build(
            plan_config(companions=[BRIDGE], allowed_bind_roots=["/srv/maps"]),
            dict(HOST, ports_held=[{"proto": "tcp", "port": 9101, "process": "nginx (pid 9)"}]),
        )
    assert any(
        "instance 1's port 9101/tcp is already held on this host by nginx (pid 9)" in e for e in exc.value.errors
    )


def test_the_companion_unit_starts_after_its_instance_and_stops_and_restarts_with_it():
    result = build([VIEWER])
    text = unit_files.render_companion_unit(result["companion_units"][0], result["settings"], "managed")
    for line in (
        "BindsTo=isaac-sim@%i.service",
        "After=isaac-sim@%i.service",
        "PartOf=isaac-sim@%i.service",
        "WantedBy=isaac-sim@%i.service",
        "EnvironmentFile=/etc/isaac-sim/instance-%i.viewer.env",
        "ExecStartPost=/usr/local/libexec/isaac-sim/isaac-sim-ready",
        "TimeoutStartSec=90",
        "Restart=always",
        # a start waiting for the companion to stop (its instance restarting) must not use up a limit
        "StartLimitIntervalSec=0",
    ):
        assert line in text.splitlines(), line


def test_the_companion_env_file_reads_back_exactly():
    result = build([BRIDGE])
    comp = result["instances"][3]["companions"][0]
    env = layout.parse(unit_files.render_companion_env(comp, result, "managed"))
    assert (
        env[layout.K_CONTAINER] == "isaac-sim-3-ros-bridge" and env[layout.K_UNIT] == "isaac-sim-ros-bridge@3.service"
    )
    assert env[layout.K_PORTS] == "tcp/9103" and env[layout.K_READY_PATTERN] == ""
    assert env[layout.K_READY_MARKER] == "/run/isaac-sim/instance-3.ros-bridge.ready"
    assert layout.split_args(env[layout.K_APP_ARGS]) == ["bridge", "--instance", "3", "--ws", "9103"]
    assert env["ROS_DOMAIN_ID"] == "3" and f"--env={layout.K_INSTANCE}" in layout.split_args(env[layout.K_DOCKER_ARGS])
    # no healthcheck: nothing for the host to watch
    assert env[layout.K_UNHEALTHY_RESTART] == "0"


def test_the_web_viewer_is_a_built_in_companion_of_each_6x_instance():
    result = build([BRIDGE], web_viewer_image="reg.lab:5000/isaac-sim/web-viewer:2.1.5")
    inst = result["instances"][2]
    viewer = inst["companions"][0]
    assert [c["name"] for c in inst["companions"]] == ["viewer", "ros-bridge"]
    assert viewer["image"] == "reg.lab:5000/isaac-sim/web-viewer:2.1.5" and viewer["ports"] == {"http": 8212}
    env = viewer["container_env"]
    # told the instance's address and ports when it starts: one image for every instance
    assert (env["ISAACSIM_HOST"], env["ISAACSIM_SIGNAL_PORT"], env["ISAACSIM_STREAM_PORT"], env["WEB_VIEWER_PORT"]) == (
        "10.0.0.5",
        "49102",
        "48000",
        "8212",
    )
    assert "--user=1234:1234" in viewer["docker_args"]
    assert "--health-cmd=curl -f 'http://10.0.0.5:8212/'" in viewer["docker_args"]
    # the instance does not check the viewer's port as its own at start; the viewer does
    assert "web_viewer" not in inst["listens"] and viewer["own_ports"] == ["http"]
    lines = endpoints.summary_lines(result, "10.0.0.5")
    assert lines[2].endswith("web_viewer=http://10.0.0.5:8212/")
    assert "web_viewer" not in endpoints.summary_lines(build([]), "10.0.0.5")[2]


def test_the_web_viewer_is_refused_when_its_name_or_image_is_wrong_and_ignored_before_6x():
    assert any(
        "the name viewer is the built-in web viewer's" in e
        for e in errors_of([{"name": "viewer", "image": "x"}], web_viewer_image="reg/viewer:1")
    )
    assert any("isaac_sim_web_viewer_image: 'no good' is not" in e for e in errors_of([], web_viewer_image="no good"))
    five = build([], release="5.x", image="nvcr.io/nvidia/isaac-sim:5.1.0", web_viewer_image="reg/viewer:1")
    assert all(inst["companions"] == [] for inst in five["instances"])
