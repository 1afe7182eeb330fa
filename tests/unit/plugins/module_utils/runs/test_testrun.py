"""A test run's pieces (docker run, unit, observations, metrics, JUnit) and the whole run
against a scripted host. The real thing runs in the molecule scenarios."""

import json
import xml.etree.ElementTree as ET

import pytest
import yaml
from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib import layout
from ansible_collections.isaacsim.fleet.plugins.module_utils.runs import experience, judge, testrun

PAIR = yaml.safe_load(
    """
services:
  robot:
    image: reg/robot:1
    environment: {MODE: "a $$HOME \\"q\\" 50% back\\\\slash"}
    restart: on-failure:2
    volumes: [maps:/maps:ro]
    healthcheck: {test: ["CMD", "test", "-e", "/tmp/up"], interval: 1s, retries: 5}
    deploy: {resources: {reservations: {devices: [{capabilities: [gpu], count: 1}]}, limits: {memory: 1 g}}}
  check:
    image: reg/check:1
    entrypoint: ["sh", "-c"]
    command: ["exit 0"]
    labels: {isaacsim.fleet/test-orchestrator: "true"}
    depends_on: {robot: {condition: service_healthy}}
volumes:
  maps: {}
"""
)


def read(compose=PAIR, **kw):
    exp, errors, _warnings = experience.read(compose, name="pair", **kw)
    assert errors == []
    return exp


def test_run_names_are_unit_and_docker_safe():
    run = testrun.run_id("Pick & Place (v2)", "20261123-101500", "ab12")
    assert run == "pick-place-v2-20261123-101500-ab12" and layout.RUN_ID_RE.match(run)
    assert layout.run_unit(run, "robot") == f"isaac-sim-run-{run}-robot.service"
    assert testrun.run_id("???", "20261123-101500", "ab12").startswith("run-")


def test_a_word_reaches_docker_as_it_is_written():
    assert testrun.systemd_quote('a $HOME "q" 50% back\\slash\nnext') == (
        '"a $$HOME \\"q\\" 50%% back\\\\slash\\nnext"'
    )


def test_docker_run_of_a_service_carries_what_compose_says_and_what_the_run_adds():
    exp = read(env={"SEED": "7"})
    sim = {"service": "isaac-sim", "address": "host-gateway", "env": {"ISAAC_SIM_HOST": "isaac-sim"}}
    robot = exp["services"]["robot"]
    argv = testrun.docker_argv("r1", "robot", robot, outputs="/o", env_file="/e", simulator=sim, gpus=["0"])
    assert argv[:3] == ["/usr/bin/docker", "run", "--name=isaac-sim-run-r1-robot"]
    for word in (
        "--network=isaac-sim-run-r1",
        "--network-alias=robot",
        "--label=org.isaacsim.fleet.run=r1",
        "--mount=type=bind,source=/o,target=/isaacsim-fleet/outputs",
        "--add-host=isaac-sim:host-gateway",
        "--env-file=/e",
        "--memory=1g",
        '--gpus="device=0"',
        "--mount=type=volume,source=isaac-sim-run-r1-maps,target=/maps,readonly",
        "--health-cmd=test -e /tmp/up",
        "--health-interval=1000ms",
        "--health-retries=5",
        "--security-opt=no-new-privileges",
    ):
        assert word in argv, word
    assert argv[-1] == "reg/robot:1"
    # values never reach a command line: they go in the env file
    assert not any(w.startswith(("--env=", "-e")) for w in argv)
    env = testrun.service_env("r1", robot, sim, gpus=["0"])
    assert env["MODE"] == 'a $HOME "q" 50% back\\slash' and env["SEED"] == "7"
    assert env["ISAAC_SIM_HOST"] == "isaac-sim" and env["ISAAC_SIM_RUN"] == "r1" and "NVIDIA_VISIBLE_DEVICES" not in env
    assert testrun.env_file_text({"A": 'x "y" $z'}) == 'A=x "y" $z\n'
    # a service without GPUs sees none, whatever Docker's default runtime
    assert testrun.service_env("r1", exp["services"]["check"])["NVIDIA_VISIBLE_DEVICES"] == "void"
    check = testrun.docker_argv("r1", "check", exp["services"]["check"], outputs="/o", env_file="/e")
    # compose's entrypoint list: the first word is docker's --entrypoint, the rest lead the command
    assert check[-4:] == ["--entrypoint=sh", "reg/check:1", "-c", "exit 0"]


def test_what_the_operator_allowed_a_service_reaches_docker_run_and_no_new_privileges_stays_unless_allowed_off():
    svc = dict(read()["services"]["check"], docker_args=["--cap-add=NET_ADMIN"])
    argv = testrun.docker_argv("r1", "check", svc, outputs="/o", env_file="/e")
    assert "--cap-add=NET_ADMIN" in argv and "--security-opt=no-new-privileges" in argv
    svc["docker_args"] = ["--security-opt=no-new-privileges=false"]
    argv = testrun.docker_argv("r1", "check", svc, outputs="/o", env_file="/e")
    assert [w for w in argv if "no-new-privileges" in w] == ["--security-opt=no-new-privileges=false"]


def test_the_unit_restarts_by_the_compose_policy_and_never_after_a_zero_exit():
    exp = read()
    robot = testrun.unit_text("r1", "robot", exp["services"]["robot"], ["/usr/bin/docker", "run", "x"])
    assert "Restart=on-failure\n" in robot and "StartLimitBurst=3\n" in robot  # on-failure:2 = 3 starts
    assert 'ExecStart="/usr/bin/docker" "run" "x"\n' in robot
    # -v: an image's own VOLUMEs go with each container
    assert "ExecStopPost=-/usr/bin/docker rm -f -v isaac-sim-run-r1-robot\n" in robot
    check = testrun.unit_text("r1", "check", exp["services"]["check"], ["x"])
    assert "Restart=no\n" in check and "StartLimit" not in check


def show(unit, active, sub, code="0", status="0", restarts="0"):
    return {
        "Id": unit,
        "ActiveState": active,
        "SubState": sub,
        "ExecMainCode": code,
        "ExecMainStatus": status,
        "NRestarts": restarts,
    }


def test_observations_from_systemd_and_docker():
    def u(service):
        return layout.run_unit("r1", service)

    shown = {
        u("a"): show(u("a"), "active", "running"),
        u("b"): show(u("b"), "activating", "auto-restart", "1", "2", "1"),
        u("c"): show(u("c"), "failed", "failed", "1", "3"),
        u("d"): show(u("d"), "inactive", "dead", "2", "9"),
        u("e"): show(u("e"), "active", "running"),
    }
    found = [
        {"Labels": {layout.LABEL_RUN_SERVICE: "a"}, "State": "running", "Status": "Up 3 seconds (healthy)"},
        {"Labels": {layout.LABEL_RUN_SERVICE: "e"}, "State": "created", "Status": "Created"},
    ]
    ran = set()
    seen = testrun.observe(shown, found, "r1", "abcdef", {"a", "b", "c", "d", "e"}, ran)
    assert seen["a"] == judge.observation(judge.RUNNING, None, 0, "healthy", True) and ran == {"a"}
    assert seen["b"]["state"] == judge.RESTARTING and seen["b"]["exit_code"] == 2 and seen["b"]["restarts"] == 1
    assert seen["c"]["state"] == judge.EXITED and seen["c"]["exit_code"] == 3
    assert seen["d"]["exit_code"] == 137  # killed by signal 9
    assert seen["e"]["state"] == judge.STARTING  # unit up, container not running yet
    assert seen["f"]["state"] == judge.WAITING  # not started by the runner


def test_memory_is_counted_as_docker_stats_does_on_cgroup_v1_and_v2():
    v1 = {
        "cpu_stats": {"cpu_usage": {"total_usage": 5}},
        "memory_stats": {"usage": 100, "stats": {"total_inactive_file": 30}},
    }
    v2 = {
        "cpu_stats": {"cpu_usage": {"total_usage": 5}},
        "memory_stats": {"usage": 100, "stats": {"inactive_file": 40}},
    }
    assert testrun.stats_sample(v1) == (5, 70) and testrun.stats_sample(v2) == (5, 60)
    assert testrun.stats_sample({}) == (0, 0)


def test_cpu_is_the_share_of_one_core_between_samples_of_the_same_container():
    m = testrun.Metrics()
    m.add(0.0, "a", 0, 100, "c1")
    m.add(2.0, "a", 1_000_000_000, 300, "c1")  # 1 s of CPU in 2 s
    m.add(4.0, "a", 0, 50, "c2")  # restarted: a new container, no rate across the two
    s = m.summary()["a"]
    assert s == {"samples": 3, "cpu_peak_percent": 50.0, "memory_peak_bytes": 300, "cpu_mean_percent": 50.0}
    assert m.csv().splitlines()[1:] == ["0.0,a,,100", "2.0,a,50.0,300", "4.0,a,,50"]


def test_junit_says_why_a_run_failed():
    result = {
        "run": "r1",
        "host": "h1",
        "experience": "pair",
        "verdict": {
            "result": "failed",
            "service": "check",
            "reason": "orchestrator check exited with 3",
            "seconds": 4.5,
        },
        "orchestrator_output": "--- check ---\n<boom> & done\n",
    }
    root = ET.fromstring(testrun.junit(result))
    assert root.get("failures") == "1" and root.get("tests") == "1"
    case = root.find("testcase")
    assert case.get("name") == "pair" and case.get("classname") == "isaacsim.fleet.h1"
    assert case.find("failure").get("message") == "orchestrator check exited with 3"
    assert "<boom> & done" in case.find("system-out").text
    passed = dict(result, verdict=dict(result["verdict"], result="passed"))
    assert ET.fromstring(testrun.junit(passed)).find("testcase/failure") is None


class ScriptedHost:
    """systemd and Docker as a run sees them: units start when told, robot becomes healthy,
    check exits with `check_exit` two looks later."""

    def __init__(self, check_exit=0, fail_on=None):
        self.calls, self.files, self.removed = [], {}, []
        self.started, self.t = {}, 0.0
        self.check_exit = check_exit
        self.fail_on = fail_on
        self.containers = set()
        self.objects = set()
        self.modes, self.written, self.dirs = {}, {}, set()
        self.outputs, self.find = [], []

    # lifecycle.Host's interface
    def run(self, argv):
        self.calls.append(argv)
        words = " ".join(argv)
        if self.fail_on and self.fail_on in words:
            return 1, "", "boom"
        if argv[:2] == ["systemctl", "start"]:
            for unit in argv[3:]:
                self.started[unit] = self.t
                self.containers.add(unit)
        if argv[:2] == ["systemctl", "stop"]:
            self.containers.clear()
        if argv[:2] == ["systemctl", "show"]:
            return 0, "\n\n".join(self._show(u) for u in argv[4:]), ""
        if argv[0] == "/usr/bin/docker" and argv[1] in ("network", "volume") and argv[2] == "create":
            self.objects.add(argv[-1])
        if argv[0] == "/usr/bin/docker" and argv[1] in ("network", "volume") and argv[2] == "rm":
            self.objects.discard(argv[-1])
        if argv[0] == "journalctl":
            return 0, f"log of {argv[-1]}\n", ""
        if argv[0] == "find" and argv[1].endswith("/outputs"):
            return 0, "".join(f"{o}\n" for o in self.outputs), ""
        if argv[0] == "find":
            return 0, "".join(f"{f}\n" for f in self.find), ""
        if argv == ["mkdir", argv[-1]] and argv[-1].endswith(".lent"):
            if argv[-1] in self.dirs:
                return 1, "", "File exists"
            self.dirs.add(argv[-1])
        return 0, "", ""

    def _show(self, unit):
        since = self.started.get(unit)
        if since is None:
            return f"Id={unit}\nActiveState=inactive\nSubState=dead\nExecMainCode=0\nExecMainStatus=0\nNRestarts=0"
        if unit.endswith("-check.service") and self.t - since >= 2:
            return f"Id={unit}\nActiveState=inactive\nSubState=dead\nExecMainCode=1\nExecMainStatus={self.check_exit}"
        return f"Id={unit}\nActiveState=active\nSubState=running\nExecMainCode=0\nNRestarts=0"

    def write(self, path, text, mode):
        self.files[path] = text
        self.written[path] = text
        self.modes[path] = mode

    def remove(self, path):
        self.removed.append(path)
        self.files.pop(path, None)
        self.dirs.discard(path)

    def read(self, path):
        return self.files.get(path)

    def exists(self, path):
        return path in self.files or path in self.dirs or any(f.startswith(f"{path}/") for f in self.files)

    def now(self):
        return self.t

    def sleep(self, seconds):
        self.t += 1.0

    # the Docker API client's
    def labelled(self, label):
        out = []
        for unit in self.containers:
            svc = unit[: -len(".service")].rsplit("-", 1)[1]
            out.append(
                {"Id": unit, "Labels": {layout.LABEL_RUN_SERVICE: svc}, "State": "running", "Status": "Up (healthy)"}
            )
        return out

    def stats(self, cid):
        return {"cpu_stats": {"cpu_usage": {"total_usage": int(self.t * 5e8)}}, "memory_stats": {"usage": 1000}}


def test_a_whole_run_starts_in_order_passes_and_leaves_only_its_directory():
    host = ScriptedHost()
    exp = read()
    result = testrun.execute(
        host, host, exp, "r1", hostname="h1", timeout=60, data_root="/d", gpus_free=["0"], metrics_every=1
    )
    assert result["verdict"]["result"] == "passed"
    starts = [c[3:] for c in host.calls if c[:2] == ["systemctl", "start"]]
    assert starts == [["isaac-sim-run-r1-robot.service"], ["isaac-sim-run-r1-check.service"]]
    assert result["services"]["check"]["exit_code"] == 0 and result["services"]["robot"]["exit_code"] is None
    assert result["metrics"]["robot"]["cpu_peak_percent"] == 50.0
    # torn down: units stopped and removed, network and volume gone, directory and artefacts written
    assert ["systemctl", "stop", "isaac-sim-run-r1-robot.service", "isaac-sim-run-r1-check.service"] in host.calls
    assert not host.objects and not any(p.startswith("/run/systemd/system/") for p in host.files)
    for name in result["artefacts"]:
        assert f"/d/runs/r1/{name}" in host.files, name
    assert "r1-check.log" in result["artefacts"] and "junit.xml" in result["artefacts"]


def test_a_failing_orchestrator_is_a_failed_run_with_every_container_stopped():
    host = ScriptedHost(check_exit=3)
    result = testrun.execute(host, host, read(), "r2", hostname="h1", timeout=60, data_root="/d", gpus_free=["0"])
    assert result["verdict"]["reason"] == "orchestrator check exited with 3"
    assert ET.fromstring(host.files["/d/runs/r2/junit.xml"]).get("failures") == "1"
    assert not host.containers and not host.objects


def test_a_run_that_cannot_be_set_up_leaves_nothing_behind():
    host = ScriptedHost(fail_on="volume create")
    try:
        testrun.execute(host, host, read(), "r3", hostname="h1", timeout=60, data_root="/d", gpus_free=["0"])
    except RuntimeError as exc:
        assert "docker volume create" in str(exc)
    else:
        raise AssertionError("no error")
    assert not host.objects  # the network made before the failure is removed


def test_preflight_names_missing_images_and_gpus_the_host_cannot_give():
    class Api:
        def image(self, name):
            return None if name == "reg/check:1" else {"Id": "x"}

    pulled = []

    def pull(image):
        pulled.append(image)
        return "manifest unknown"

    errors = testrun.preflight(Api(), read(), gpus_free=[], pull=pull)
    assert pulled == ["reg/check:1"]  # the image already there is not pulled again
    assert any("image reg/check:1 cannot be had (manifest unknown)" in e for e in errors)
    assert any("ask for 1 dedicated GPU(s); this host has 0 free" in e for e in errors)


def test_a_run_s_values_stay_off_command_lines_and_its_outputs_come_back():
    host = ScriptedHost()
    host.outputs = ["report.txt", "plots/a.png"]
    result = testrun.execute(
        host, host, read(), "r4", hostname="h1", timeout=60, data_root="/d", gpus_free=["0"], pid=42
    )
    env_file = "/run/isaac-sim/runs/r4/robot.env"
    assert any(c[:2] == ["systemctl", "start"] for c in host.calls)
    assert host.modes[env_file] == 0o600 and "MODE=a $HOME" in host.written[env_file]
    unit = host.written["/run/systemd/system/isaac-sim-run-r4-robot.service"]
    assert "MODE" not in unit and '"--env-file=/run/isaac-sim/runs/r4/robot.env"' in unit
    assert "outputs/plots/a.png" in result["artefacts"] and "outputs/report.txt" in result["artefacts"]
    # the owner file said who ran it while it ran, and is gone; so are the env files
    assert '"pid": 42' in host.written["/run/isaac-sim/runs/r4.json"]
    assert "/run/isaac-sim/runs/r4.json" in host.removed and "/run/isaac-sim/runs/r4" in host.removed
    compose = host.files["/d/runs/r4/compose.yml"]
    assert '"restart": "on-failure:2"' in compose and '"maps:/maps:ro"' in compose


def test_experience_level_secrets_are_not_written_into_the_compose_file_as_run():
    exp = read(env={"TOKEN": "s3cr3t"})
    text = testrun.as_compose(exp, secret_keys={"TOKEN"})
    assert "s3cr3t" not in text and "(the experience's environment)" in text


def test_a_run_that_cannot_be_set_up_leaves_not_even_its_directory():
    host = ScriptedHost(fail_on="network create")
    with pytest.raises(RuntimeError, match="docker network create"):
        testrun.execute(host, host, read(), "r5", hostname="h1", timeout=60, data_root="/d", gpus_free=["0"])
    assert "/d/runs/r5" in host.removed


def test_runs_whose_runner_was_killed_are_swept_and_their_instance_comes_back():
    host = ScriptedHost()
    owner = {"pid": 7, "services": ["robot", "check"], "volumes": ["maps"], "directory": "/d/runs/r6", "instance": 2}
    host.files["/run/isaac-sim/runs/r6.json"] = json.dumps(owner)
    host.files["/run/isaac-sim/runs/r7.json"] = json.dumps(dict(owner, pid=8))
    host.find = ["/run/isaac-sim/runs/r6.json", "/run/isaac-sim/runs/r7.json"]
    host.files["/d/runs/r6/compose.yml"] = "{}"
    lent, ended = testrun.sweep(host, testrun.cli(host), alive=lambda pid: pid == 8)
    # still lent: the caller gives it back through the lifecycle (restart, then free)
    assert lent == [(2, "r6")] and ended == ["r6"] and "/run/isaac-sim/instance-2.lent" not in host.removed
    assert ["systemctl", "stop", "isaac-sim-run-r6-robot.service", "isaac-sim-run-r6-check.service"] in host.calls
    assert ["/usr/bin/docker", "volume", "rm", "-f", "isaac-sim-run-r6-maps"] in host.calls
    assert "/run/isaac-sim/runs/r6.json" in host.removed
    assert not any("r7" in " ".join(c) for c in host.calls)  # its runner lives: untouched
    # its directory says what became of it, for the controller that takes it later
    swept = json.loads(host.files["/d/runs/r6/result.json"])
    assert swept["verdict"]["result"] == "error" and "pid 7" in swept["verdict"]["reason"] and swept["swept"]
    assert "/d/runs/r6/r6-robot.log" in host.files and "/d/runs/r6/r6-check.log" in host.files


def test_junit_leaves_out_what_xml_cannot_hold():
    result = {
        "run": "r1",
        "host": "h1",
        "experience": "pair",
        "verdict": {"result": "passed", "service": None, "reason": "ok", "seconds": 1.0},
        "orchestrator_output": "\x1b[31mred\x1b[0m done\r\n",
    }
    assert "red" in ET.fromstring(testrun.junit(result)).find("testcase/system-out").text
    # in the experience's name and the verdict's reason too
    result.update(experience="pair\x1b[1m", verdict=dict(result["verdict"], result="failed", reason="exit\x00 3"))
    case = ET.fromstring(testrun.junit(result)).find("testcase")
    assert case.get("name") == "pair[1m" and case.find("failure").get("message") == "exit 3"


def test_how_a_container_ended_survives_systemd_forgetting_the_unit():
    assert testrun.parse_exit("exited 3\n") == 3 and testrun.parse_exit("exited 0") == 0
    assert testrun.parse_exit("killed KILL") == 137 and testrun.parse_exit("dumped SEGV") == 139
    assert testrun.parse_exit("") is None and testrun.parse_exit("exited x") is None
    # a unit that ended well is unloaded: systemctl show then says nothing of its exit
    unit = layout.run_unit("r1", "check")
    shown = {unit: show(unit, "inactive", "dead")}
    seen = testrun.observe(shown, [], "r1", ["check"], {"check"}, set(), {"check": "exited 0\n"})
    assert seen["check"]["state"] == judge.EXITED and seen["check"]["exit_code"] == 0
    text = testrun.unit_text("r1", "check", read()["services"]["check"], ["x"])
    assert "ExecStopPost=-/bin/sh -c 'echo \"$$EXIT_CODE $$EXIT_STATUS\" > /run/isaac-sim/runs/r1/check.exit'\n" in text
    assert "ExecStartPre=-/bin/rm -f /run/isaac-sim/runs/r1/check.exit\n" in text


def test_restarts_are_the_restarts_a_start_limit_allowed_not_the_one_it_refused():
    # on-failure:2 gave three starts; systemd's NRestarts counts the fourth, refused, too
    unit = layout.run_unit("r1", "robot")
    shown = {unit: dict(show(unit, "failed", "failed"), NRestarts="3")}
    seen = testrun.observe(shown, [], "r1", ["robot"], {"robot"}, set(), {"robot": "exited 1\n"}, {"robot": 2})
    assert seen["robot"]["restarts"] == 2
    # without a limit (restart: on-failure, always) systemd's count is the count
    seen = testrun.observe(shown, [], "r1", ["robot"], {"robot"}, set(), {"robot": "exited 1\n"})
    assert seen["robot"]["restarts"] == 3


SIM = yaml.safe_load(
    """
services:
  isaac-sim:
    image: isaac-sim
  check:
    image: reg/check:1
    labels: {isaacsim.fleet/test-orchestrator: "true"}
    depends_on: {isaac-sim: {condition: service_healthy}}
"""
)


def dedicated(compose=SIM, **kw):
    args = dict(release="6.x", image="reg/isaac-sim:6.0.1", cache="/d/simulators/3", start_period=600, gpu=True)
    return testrun.dedicate(read(compose), **dict(args, **kw))


def test_a_dedicated_simulator_is_the_release_s_headless_isaac_sim_with_its_caches_and_a_gpu():
    exp, given = dedicated(limits={"memory": "32g", "shm_size": "2g"})
    sim = exp["services"]["isaac-sim"]
    # an ordinary service of the run now: started, judged and stopped like the others
    assert exp["simulator"] is None and "isaac-sim" in exp["order"]
    assert exp["images"] == ["reg/check:1", "reg/isaac-sim:6.0.1"] and exp["gpus"] == 1
    assert sim["entrypoint"] == ["/isaac-sim/isaac-sim.sh", "--no-window"] and sim["user"] == "1234:1234"
    assert sim["environment"] == {"ACCEPT_EULA": "Y"} and (sim["memory"], sim["shm_size"]) == ("32g", "2g")
    assert "grep -q AppReady" in sim["healthcheck"]["test"] and sim["healthcheck"]["start_period"] == 600
    assert ("/d/simulators/3/cache/main", "/isaac-sim/.cache") in sim["binds"]
    assert ("/d/simulators/3/cache/computecache", "/isaac-sim/.nv/ComputeCache") in sim["binds"]
    # the others find it by its service name on the run's network, with the release's ports
    assert given["address"] is None and given["instance"] is None
    assert given["env"] == {
        "ISAAC_SIM_HOST": "isaac-sim",
        "ISAAC_SIM_PORT_SIGNAL": "49100",
        "ISAAC_SIM_PORT_STREAM": "47998",
        "ISAAC_SIM_PORT_WEB_VIEWER": "8210",
    }
    argv = testrun.docker_argv("r1", "isaac-sim", sim, outputs="/o", env_file="/e", simulator=given, gpus=["1"])
    assert "--mount=type=bind,source=/d/simulators/3/cache/main,target=/isaac-sim/.cache" in argv
    assert not any(a.startswith("--add-host") for a in argv)
    assert argv[-2:] == ["reg/isaac-sim:6.0.1", "--no-window"] and "--entrypoint=/isaac-sim/isaac-sim.sh" in argv
    assert '--gpus="device=1"' in argv and "--shm-size=2g" in argv
    # its own environment has no ISAAC_SIM_HOST pointing at itself; the orchestrator's has
    assert "ISAAC_SIM_HOST" not in testrun.service_env("r1", sim, given)
    assert testrun.service_env("r1", exp["services"]["check"], given)["ISAAC_SIM_HOST"] == "isaac-sim"
    # the GPU comes from the run's free ones
    assert testrun._gpu_share(exp, ["1", "2"]) == {"isaac-sim": ["1"], "check": []}


def test_a_dedicated_simulator_keeps_what_its_service_says():
    compose = yaml.safe_load(yaml.safe_dump(SIM))
    compose["services"]["isaac-sim"].update(
        entrypoint=["/isaac-sim/python.sh", "/scenarios/pick.py"],
        command=["--seed", "7"],
        user="0:0",
        environment={"ACCEPT_EULA": "N", "ROS_DOMAIN_ID": "3"},
        healthcheck={"test": "test -e /tmp/scene-loaded", "interval": "1s"},
        deploy={"resources": {"reservations": {"devices": [{"capabilities": ["gpu"], "count": 2}]}}},
    )
    exp, _given = dedicated(compose, release="4.x", gpu=True)
    sim = exp["services"]["isaac-sim"]
    assert sim["entrypoint"] == ["/isaac-sim/python.sh", "/scenarios/pick.py"] and sim["command"] == ["--seed", "7"]
    assert sim["user"] == "0:0" and sim["environment"] == {"ACCEPT_EULA": "N", "ROS_DOMAIN_ID": "3"}
    assert sim["healthcheck"]["test"] == "test -e /tmp/scene-loaded" and exp["gpus"] == 2
    # the 4.x image keeps its caches under /root
    assert ("/d/simulators/3/cache/ov", "/root/.cache/ov") in sim["binds"]
    # on a host without GPUs none is reserved (only a stand-in runs so)
    exp, _given = dedicated(gpu=False)
    assert exp["gpus"] == 0 and exp["services"]["isaac-sim"]["gpus"] == 0


def test_dedicated_simulators_take_a_slot_each_and_a_swept_run_gives_its_slot_back():
    host = ScriptedHost()
    assert [testrun.claim_slot(host, run, slots=2) for run in ("a", "b", "c")] == [0, 1, None]
    assert host.files["/run/isaac-sim/simulator-1.lent/run"] == "b\n"
    testrun.release_slot(host, 0)
    assert testrun.claim_slot(host, "c", slots=2) == 0
    owner = {"pid": 7, "services": ["isaac-sim", "check"], "volumes": [], "directory": "/d/runs/r8", "slot": 1}
    host.files["/run/isaac-sim/runs/r8.json"] = json.dumps(owner)
    host.find = ["/run/isaac-sim/runs/r8.json"]
    assert testrun.sweep(host, testrun.cli(host), alive=lambda pid: False) == ([], ["r8"])
    assert "/run/isaac-sim/simulator-1.lent" in host.removed
    # the slot's directories belong to the release's user; only what another user left is re-owned
    mkdir, chown = testrun.cache_argv("/d/simulators/1", "5.x")
    assert mkdir[:4] == ["mkdir", "-p", "-m", "0750"] and "/d/simulators/1/cache/main" in mkdir
    assert chown == [
        "find", "/d/simulators/1", "(", "!", "-uid", "1234", "-o", "!", "-gid", "1234", ")",
        "-exec", "chown", "-h", "1234:1234", "{}", "+",
    ]  # fmt: skip


def test_the_dedicated_simulator_takes_the_image_release_and_limits_of_the_host_s_instances():
    env = (
        'ISAAC_SIM_IMAGE="reg/isaac-sim:5.1.0"\nISAAC_SIM_RELEASE="5.x"\n'
        'ISAAC_SIM_DOCKER_ARGS="--network=host --memory=48g --shm-size=4g"\n'
    )
    files = {"/etc/isaac-sim/instance-2.env": env}
    assert testrun.deployed_simulator(files.get, [3, 2]) == {
        "image": "reg/isaac-sim:5.1.0",
        "release": "5.x",
        "memory": "48g",
        "shm_size": "4g",
    }
    assert testrun.deployed_simulator(files.get, []) == {}
    # the fleet's pinned digest, where its deploy pinned one
    files["/etc/isaac-sim/instance-2.env"] += 'ISAAC_SIM_IMAGE_PINNED="reg/isaac-sim@sha256:' + "d" * 64 + '"\n'
    assert testrun.deployed_simulator(files.get, [2])["image"] == "reg/isaac-sim@sha256:" + "d" * 64


def test_a_dedicated_simulator_s_settings_are_checked_before_anything_runs():
    deployed = {"image": "reg/isaac-sim:6.0.1", "release": "6.x", "memory": "32g", "shm_size": "2g"}
    settings, errors = testrun.dedicated_settings(None, None, deployed, None, [], 0)
    assert errors == [] and settings == {
        "image": "reg/isaac-sim:6.0.1",
        "release": "6.x",
        "gpu": False,
        "limits": {"memory": "32g", "shm_size": "2g"},
    }
    # an image given: its tag names the release, the host's limits still apply
    settings, errors = testrun.dedicated_settings("reg/sim:4.5.0", None, deployed, None, ["1"], 2)
    assert errors == [] and (settings["release"], settings["gpu"]) == ("4.x", True)

    def refused(*args):
        settings, errors = testrun.dedicated_settings(*args)
        assert settings is None
        return " ".join(errors)

    assert "no Isaac Sim instance is deployed on this host" in refused(None, None, {}, None, [], 0)
    assert "the tag of reg/sim:latest names no release" in refused("reg/sim:latest", None, deployed, None, [], 0)
    assert "'Bad Image' is not an image reference" in refused("Bad Image", "6.x", {}, None, [], 0)
    assert "simulator_release: '7.x'. Fix: one of 2023.1, 4.x, 5.x, 6.x." in refused("reg/s:1", "7.x", {}, None, [], 0)
    assert "instance: 0 with simulator: dedicated" in refused(None, None, deployed, 0, [], 0)
    # a GPU host: the run must be given a GPU for it
    assert "this host has 2 GPU(s): the dedicated simulator needs one" in refused(None, None, deployed, None, [], 2)


def test_a_run_s_own_simulator_holds_a_slot_until_given_back_and_none_when_it_cannot_be_prepared():
    host = ScriptedHost()
    settings = {"image": "reg/isaac-sim:6.0.1", "release": "6.x", "gpu": False, "limits": {}}
    exp, sim, error = testrun.own_simulator(host, "r9", read(SIM), settings, "/d", 60)
    assert error is None and sim["slot"] == 0 and exp["simulator"] is None
    assert ("/d/simulators/0/cache/main", "/isaac-sim/.cache") in exp["services"]["isaac-sim"]["binds"]
    assert host.calls[-2][:4] == ["mkdir", "-p", "-m", "0750"] and host.calls[-1][0] == "find"
    testrun.give_back(host, sim)
    assert "/run/isaac-sim/simulator-0.lent" in host.removed
    # the slot's directories cannot be made: the slot is given back at once
    broken = ScriptedHost(fail_on="chown")
    _exp, sim, error = testrun.own_simulator(broken, "r10", read(SIM), settings, "/d", 60)
    assert sim is None and error.startswith("could not prepare /d/simulators/0: boom")
    assert "/run/isaac-sim/simulator-0.lent" in broken.removed
    # a lent instance is not: only the lifecycle gives it back, restarted first
    testrun.give_back(host, {"instance": 2})
    assert "/run/isaac-sim/instance-2.lent" not in host.removed
