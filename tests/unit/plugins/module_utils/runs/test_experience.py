import yaml
from ansible_collections.isaacsim.fleet.plugins.module_utils.runs import experience

# the shape of the reference platform's example: an orchestrator, a robot stack, the simulator
COMPOSE = yaml.safe_load(
    """
name: pick-and-place
services:
  isaac-sim:
    image: isaac-sim
  planner:
    image: registry.lab:5000/robot/planner:1.4
    command: ["planner", "--sim", "${SIM_HOST:-isaac-sim}"]
    environment:
      LOG_LEVEL: info
      SEED:
    depends_on:
      isaac-sim:
        condition: service_healthy
    restart: on-failure:3
    volumes: [maps:/maps:ro]
    deploy:
      resources:
        reservations:
          devices: [{driver: nvidia, capabilities: [gpu], count: 1}]
        limits: {memory: 4g, cpus: "2"}
  checker:
    image: registry.lab:5000/robot/checker:1.4
    labels:
      resim.ai/isTestOrchestrator: "true"
    restart: always
    depends_on: [planner]
    volumes:
      - type: volume
        source: maps
        target: /maps
    ports: ["8080:8080"]
    healthcheck:
      test: ["CMD", "curl", "-f", "http://localhost:8080/"]
      interval: 1m30s
  recorder:
    image: registry.lab:5000/robot/recorder:1.4
    profiles: [record]
volumes:
  maps: {}
"""
)


def test_a_team_s_compose_file_reads_as_the_fleet_runs_it():
    exp, errors, warnings = experience.read(COMPOSE, env={"SEED": "42", "RUN": "7"}, name="pick")
    assert errors == []
    assert exp["orchestrators"] == ["checker"] and exp["simulator"] == "isaac-sim"
    assert sorted(exp["services"]) == ["checker", "isaac-sim", "planner"]  # recorder: profile not chosen
    assert exp["order"] == ["isaac-sim", "planner", "checker"]
    assert exp["volumes"] == ["maps"] and exp["gpus"] == 1
    assert exp["images"] == ["registry.lab:5000/robot/checker:1.4", "registry.lab:5000/robot/planner:1.4"]
    planner = exp["services"]["planner"]
    assert planner["command"] == ["planner", "--sim", "isaac-sim"]
    # the experience's environment wins and reaches every service; SEED came from it
    assert planner["environment"] == {"LOG_LEVEL": "info", "SEED": "42", "RUN": "7"}
    assert exp["services"]["checker"]["environment"] == {"SEED": "42", "RUN": "7"}
    assert (planner["restart"], planner["restart_retries"]) == ("on-failure", 3)
    assert planner["volumes"] == [("maps", "/maps", True)] and planner["memory"] == "4g" and planner["cpus"] == "2"
    assert planner["depends_on"] == {"isaac-sim": "service_healthy"}
    checker = exp["services"]["checker"]
    assert checker["orchestrator"] and checker["restart"] == "no"
    assert checker["healthcheck"]["test"] == "curl -f http://localhost:8080/"
    assert checker["healthcheck"]["interval"] == 90.0
    assert any("services.checker.restart: ignored; an orchestrator never restarts" in w for w in warnings)
    assert any("services.checker.ports: ignored" in w for w in warnings)


def test_profiles_choose_services_and_a_dependency_left_out_is_an_error():
    exp, errors, _w = experience.read(COMPOSE, profiles=["record"])
    assert errors == [] and "recorder" in exp["services"]
    compose = yaml.safe_load(
        """
services:
  t: {image: t:1, labels: {isaacsim.fleet/test-orchestrator: "true"}, depends_on: [extra]}
  extra: {image: e:1, profiles: [full]}
"""
    )
    _e, errors, _w = experience.read(compose, name="x")
    assert errors == [
        "x: services.t.depends_on: extra is not in the profiles this experience runs (none). "
        "Fix: add its profile, or remove the dependency."
    ]


def test_what_cannot_be_honoured_is_refused_with_the_fix():
    compose = yaml.safe_load(
        """
services:
  t:
    build: .
    labels: [isaacsim.fleet/test-orchestrator=true]
    privileged: true
    volumes: ["./data:/data", "/tmp"]
    env_file: .env
    deploy: {resources: {reservations: {devices: [{capabilities: [gpu], count: all}]}}}
"""
    )
    _e, errors, _w = experience.read(compose, name="x")
    text = "\n".join(errors)
    assert "services.t.build: cannot be honoured on the fleet. Fix: the fleet does not build images" in text
    assert (
        "x: services.t: --privileged gives the container every capability and device (a test run's service). "
        "Fix: remove it; where this host must allow it, add '--privileged' to experience_allowed_docker_args"
    ) in text
    assert "services.t.env_file: cannot be honoured" in text
    assert "./data is a path on the machine the file was written on" in text
    assert "'/tmp' is an anonymous volume" in text
    assert "count: 'all'; a service gets dedicated GPUs" in text


def test_no_orchestrator_a_cycle_an_unknown_dependency_and_a_missing_healthcheck():
    compose = yaml.safe_load(
        """
services:
  a: {image: a:1, depends_on: [b]}
  b: {image: b:1, depends_on: {c: {condition: service_healthy}}}
  c: {image: c:1, depends_on: [a, ghost]}
"""
    )
    _e, errors, _w = experience.read(compose, name="x")
    assert "x: services.c.depends_on: ghost is not a service of the file. Fix: remove it." in errors
    assert (
        "x: services.b.depends_on.c: service_healthy, but c has no healthcheck. "
        "Fix: give it one, or use service_started." in errors
    )
    assert "x: depends_on goes round in a cycle: a -> b -> c -> a. Fix: remove one of those dependencies." in errors
    assert any(e.startswith("x: no test orchestrator, so nothing would decide the verdict") for e in errors)


def test_not_a_compose_file_and_a_missing_image():
    assert experience.read({"version": "3"}, name="x")[1] == [
        "x: not a compose file with services. Fix: give the file the team runs with docker compose."
    ]
    _e, errors, _w = experience.read({"services": {"t": {"labels": {"resim.ai/isTestOrchestrator": "true"}}}})
    assert errors == [
        "experience: services.t.image: missing. Fix: give the image, with its tag, from the fleet's registry."
    ]


def test_interpolation_follows_compose():
    errors, warnings = [], []
    env = {"A": "1", "EMPTY": ""}
    assert experience.interpolate("$A ${A} $$A ${B:-two} ${EMPTY:-d} ${EMPTY-d}", env, "w", errors, warnings) == (
        "1 1 $A two d "
    )
    assert experience.interpolate("${NOPE}", env, "w", errors, warnings) == "" and "${NOPE} is not set" in warnings[0]
    experience.interpolate("${NEED:?give the seed}", env, "w", errors, warnings)
    assert errors == ["w: ${NEED} is required (give the seed). Fix: set NEED in the experience's environment."]


def test_durations():
    errors = []
    assert experience.duration("1m30s", "w", errors) == 90.0
    assert experience.duration("500ms", "w", errors) == 0.5
    assert experience.duration(12, "w", errors) == 12.0
    assert experience.duration("soon", "w", errors) is None and len(errors) == 1


def test_the_simulator_s_gpu_is_its_instance_s_and_newlines_cannot_reach_a_container():
    compose = {
        "services": {
            "isaac-sim": {
                "image": "isaac-sim",
                "deploy": {"resources": {"reservations": {"devices": [{"capabilities": ["gpu"], "count": 1}]}}},
            },
            "check": {
                "image": "reg/check:1",
                "labels": {"isaacsim.fleet/test-orchestrator": "true"},
                "environment": {"NOTE": "two\nlines"},
            },
        }
    }
    exp, errors, _warnings = experience.read(compose, name="sim")
    assert exp["gpus"] == 0
    assert errors == [
        "sim: services.check.environment: NOTE holds a newline, which a run cannot pass to the container. "
        "Fix: give the value on one line without control characters (or put the text in the image or a volume)."
    ]
    # from the experience's environment: that is what is named; a trailing carriage return too
    compose["services"]["check"]["environment"] = {}
    _exp, errors, _warnings = experience.read(compose, {"TOKEN": "abc\r", "NOTE": "a\nb"}, name="sim")
    assert errors == [
        "experience_environment: TOKEN holds a carriage return, which a run cannot pass to the container. "
        "Fix: give the value on one line without control characters (or put the text in the image or a volume).",
        "experience_environment: NOTE holds a newline, which a run cannot pass to the container. "
        "Fix: give the value on one line without control characters (or put the text in the image or a volume).",
    ]


def test_a_volume_driver_is_said_to_be_ignored_and_privileged_names_no_ignored_key():
    compose = {
        "services": {
            "check": {
                "image": "reg/check:1",
                "labels": {"isaacsim.fleet/test-orchestrator": "true"},
                "volumes": ["maps:/maps"],
            }
        },
        "volumes": {"maps": {"driver": "nfs", "driver_opts": {"o": "addr=10.0.0.1"}}},
    }
    _exp, errors, warnings = experience.read(compose, name="v")
    assert errors == [] and any("volume maps: driver and driver_opts are ignored" in w for w in warnings)
    compose["services"]["check"]["privileged"] = True
    _exp, errors, _warnings = experience.read(compose, name="v")
    assert len(errors) == 1 and "--privileged" in errors[0] and "experience_allowed_docker_args" in errors[0]


def test_a_size_docker_cannot_read_is_refused_before_the_run():
    compose = {
        "services": {
            "check": {
                "image": "reg/check:1",
                "labels": {"isaacsim.fleet/test-orchestrator": "true"},
                "shm_size": "lots",
                "deploy": {"resources": {"limits": {"memory": "1 GB"}}},
            }
        }
    }
    _exp, errors, _warnings = experience.read(compose, name="size")
    assert errors == ["size: services.check.shm_size: 'lots' is not a size. Fix: e.g. 2g or 512m."]


def test_a_secret_substituted_into_another_variable_is_masked_and_never_reaches_a_command_line():
    from ansible_collections.isaacsim.fleet.plugins.module_utils.runs import testrun

    compose = {
        "services": {
            "check": {
                "image": "reg/check:1",
                "labels": {"isaacsim.fleet/test-orchestrator": "true"},
                "environment": {"URL": "https://bot:${TOKEN}@git.example", "PLAIN": "${REGION}"},
            },
            "robot": {"image": "reg/robot:1", "environment": ["AUTH=Bearer ${TOKEN}", "MODE=fast"]},
        }
    }
    env = {"TOKEN": "s3cr3t-value", "REGION": "eu"}
    exp, errors, _warnings = experience.read(compose, env, name="leak", secret={"TOKEN": "s3cr3t-value"})
    assert errors == []
    assert exp["secret_keys"] == ["AUTH", "TOKEN", "URL"]
    written = testrun.as_compose(exp, exp["secret_keys"])
    assert "s3cr3t-value" not in written and "eu" in written
    # in an argument it would be in the unit file and in ps: refused, with the way that works
    compose["services"]["check"]["entrypoint"] = ["curl", "-H", "token: ${TOKEN}", "https://x"]
    compose["services"]["check"]["healthcheck"] = {"test": ["CMD", "probe", "--key=$TOKEN"]}
    _exp, errors, _warnings = experience.read(compose, env, name="leak", secret={"TOKEN": "s3cr3t-value"})
    assert len(errors) == 2 and all("${TOKEN} is a secret (experience_secret_environment)" in e for e in errors)
    assert errors[0].startswith("leak: services.check.entrypoint:") and "$$TOKEN" in errors[0]
    assert errors[1].startswith("leak: services.check.healthcheck.test:")


def orchestrated(**service):
    spec = {"image": "reg/check:1", "labels": {"isaacsim.fleet/test-orchestrator": "true"}, **service}
    return {"services": {"check": spec}}


def test_a_service_out_of_its_confinement_is_refused_unless_the_operator_names_each_argument():
    compose = orchestrated(
        cap_add=["NET_ADMIN"],
        security_opt=["seccomp:unconfined", "label=level:s0"],
        pid="host",
        devices=["/dev/fuse"],
    )
    _exp, errors, warnings = experience.read(compose, name="x")
    assert [e.split(" (a test run's service)", maxsplit=1)[0] for e in errors] == [
        "x: services.check: --cap-add=NET_ADMIN adds the capability NET_ADMIN to the container",
        "x: services.check: --pid=host shares the host's PID namespace with the container",
        "x: services.check: --security-opt=seccomp=unconfined turns off the seccomp filter",
        "x: services.check: --device=/dev/fuse gives the container a host device beyond the GPU the plan gives each "
        "instance",
    ]
    assert "x: services.check: --security-opt=label=level:s0 is ignored" in warnings[0]
    allowed = ["--cap-add", "NET_ADMIN", "--security-opt=seccomp:unconfined", "--pid=host", "--device=/dev/fuse"]
    exp, errors, _w = experience.read(compose, name="x", allowed=allowed, allow_var="test_suite_allowed_docker_args")
    assert errors == []
    assert exp["services"]["check"]["docker_args"] == [
        "--cap-add=NET_ADMIN",
        "--device=/dev/fuse",
        "--pid=host",
        "--security-opt=seccomp:unconfined",
    ]
    # one argument allowed is not another: the operator names each
    _exp, errors, _w = experience.read(compose, name="x", allowed=["--cap-add=SYS_ADMIN"], allow_var="test_suite_x")
    assert len(errors) == 4 and "add '--cap-add=NET_ADMIN' to test_suite_x" in errors[0]


def test_sharing_another_service_s_namespace_is_refused_and_privileged_false_is_nothing():
    _exp, errors, _w = experience.read(orchestrated(ipc="service:db", privileged=False), name="x")
    assert errors == [
        "x: services.check.ipc: 'service:db' cannot be honoured on the fleet: a run's services share only their "
        "network. Fix: remove it."
    ]
