"""What goes in each unit and env file: values read back exactly, numbers as numbers."""

from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib import layout
from ansible_collections.isaacsim.fleet.plugins.module_utils.instance import plan, unit_files
from ansible_collections.isaacsim.fleet.tests.unit.helpers import plan_config


def _plan(**over):
    cfg = plan_config(
        image="reg/isaac-sim:6.0.1",
        instance_count=2,
        memory_limit="1 GB",
        shm_size="256m",
        env={"TRICKY": 'a "b" $c\nd'},
        secret_env_names=["NGC_KEY"],
        docker_args=["--label=team=a b"],
        ready_timeout="20",
        stop_timeout=5,
        restart_sec="2",
        start_limit_burst="3",
    )
    cfg.update(over)
    return plan.build(cfg, {"memory_bytes": 64 * 1024**3})


def test_env_file_carries_every_value_exactly():
    p = _plan()
    text = unit_files.render_env(p["instances"][1], p, "sha256:abc", {"NGC_KEY": "k$y\"'\\"}, "managed")
    env = layout.parse(text)
    assert env[layout.K_CONTAINER] == "isaac-sim-1"
    assert env[layout.K_READY_MARKER] == "/run/isaac-sim/instance-1.ready"
    assert env[layout.K_READY_TIMEOUT] == "20"
    assert env["TRICKY"] == 'a "b" $c\nd'
    assert env["NGC_KEY"] == "k$y\"'\\"
    args = layout.split_args(env[layout.K_DOCKER_ARGS])
    # a size with a space becomes Docker's one word; a label with a space stays one argument
    assert "--memory=1g" in args and "--label=team=a b" in args
    assert env[layout.K_PORT_PREFIX + "SIGNAL"] == "49101"
    assert env[layout.K_PROFILE] == "streaming" and env[layout.K_PORTS] == "tcp/49101 udp/47999"
    headless = _plan(instance_profiles={1: "headless"})
    env = layout.parse(unit_files.render_env(headless["instances"][1], headless, "sha256:abc", {}, "managed"))
    # checked free at start: nothing, as the headless app opens nothing
    assert env[layout.K_PROFILE] == "headless" and env[layout.K_PORTS] == ""
    # not pinned: no line; pinned: the digest runs, the tag stays what the reports name
    assert layout.K_IMAGE_PINNED not in env
    pinned = dict(p, image_pinned="reg/isaac-sim@sha256:" + "c" * 64)
    env = layout.parse(unit_files.render_env(pinned["instances"][1], pinned, "sha256:abc", {}, "managed"))
    assert env[layout.K_IMAGE_PINNED] == "reg/isaac-sim@sha256:" + "c" * 64 and env[layout.K_IMAGE] == p["image"]


def test_unit_numbers_are_numbers_whatever_was_given():
    unit = unit_files.render_unit(_plan()["settings"], "managed")
    assert "StartLimitBurst=3\n" in unit
    assert "StartLimitIntervalSec=156\n" in unit  # 3 * (2 + 20 + 30)
    assert "RestartSec=2\n" in unit and "TimeoutStartSec=50\n" in unit and "TimeoutStopSec=35\n" in unit
    assert "Restart=always\n" in unit and "RestartPreventExitStatus=76 77\n" in unit
    # session ends restart for ever while crash loops stop: every exit restarts, the start limit
    # is on (isaac-sim-run flushes it on a clean exit after ready), and no exit status is a
    # success that would end the unit instead of restarting it
    assert "StartLimitIntervalSec=0" not in unit and "SuccessExitStatus" not in unit
    assert "ExecStart=/usr/local/libexec/isaac-sim/isaac-sim-run\n" in unit
    # a stop while dockerd is down (systemd restarting it) must not wait on Docker's socket
    assert "ExecStop=-/bin/sh -c 'systemctl -q is-active docker.service || exit 0; exec /usr/bin/docker stop" in unit
    assert "EnvironmentFile=/etc/isaac-sim/instance-%i.env\n" in unit


def test_an_instance_says_at_each_start_whether_its_caches_were_warm_or_cold():
    p = _plan()
    env = layout.parse(unit_files.render_env(p["instances"][1], p, "sha256:abc", {}, "managed"))
    root = "/var/lib/isaac-sim/instance-1"
    # the shader, GL and compute caches 6.x keeps: not pip's, not the Hub's (assets, shared by the host)
    assert layout.split_args(env[layout.K_CACHES]) == [
        f"{root}/cache/main",
        f"{root}/cache/computecache",
        f"{root}/cache/kit",
    ]
    # written where status reads it (fleet_status.read_cache_states)
    assert env[layout.K_CACHE_STATE] == "/run/isaac-sim/instance-1.cache"
    assert layout.CACHE_STATE_RE.match(env[layout.K_CACHE_STATE].rsplit("/", 1)[1])
    unit = unit_files.render_unit(p["settings"], "managed")
    # with root's rights (the caches are the container user's), never failing the start, before docker run
    step = "ExecStartPre=-+/usr/local/libexec/isaac-sim/isaac-sim-cache-state\n"
    assert step in unit and unit.index(step) < unit.index("ExecStart=/usr/local/libexec/isaac-sim/isaac-sim-run")
    assert "isaac-sim-cache-state" in layout.SCRIPTS
    old = _plan(release="4.x", image="reg/isaac-sim:4.5.0")
    env = layout.parse(unit_files.render_env(old["instances"][0], old, "sha256:abc", {}, "managed"))
    names = [d.rsplit("/", 1)[1] for d in layout.split_args(env[layout.K_CACHES])]
    assert names == ["kit", "ov", "glcache", "computecache"]
