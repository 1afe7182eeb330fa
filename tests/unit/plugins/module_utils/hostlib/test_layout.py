"""The host-layout contract: names, paths and the env-file quote/parse pair."""

import random
import shlex

import pytest
from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib import layout
from ansible_collections.isaacsim.fleet.plugins.module_utils.instance import plan
from ansible_collections.isaacsim.fleet.tests.unit.helpers import plan_config

HARD = [
    "plain",
    "",
    "with spaces  and  tabs\t",
    'double "quotes" inside',
    "single 'quotes' inside",
    "back\\slash and \\\\ two and trailing \\",
    "dollar $HOME ${HOME} $$",
    "back`tick`",
    "a=b=c",
    "new\nline",
    "  leading and trailing  ",
    "#not a comment",
    "mixed $'\"\\`= \n end",
]


@pytest.mark.parametrize("value", HARD)
def test_quote_and_parse_round_trip(value):
    text = f"# comment\nKEY={layout.quote(value)}\nOTHER=plain\n"
    assert layout.parse(text) == {"KEY": value, "OTHER": "plain"}


def test_parse_reads_what_systemd_reads():
    text = "A=one\n\n; note\nB='single quoted'\nC=\"x\\\ny\"\nD = spaced\n"
    # a backslash-newline inside double quotes is a line continuation
    assert layout.parse(text) == {"A": "one", "B": "single quoted", "C": "xy", "D": "spaced"}


@pytest.mark.parametrize("args", [["--memory=1 gb"], ["--label=a b", "--env=X", "it's", '"q"', "$x", "a\\b", ""]])
def test_arguments_stay_one_argument_each(args):
    value = layout.parse("K=" + layout.quote(layout.join_args(args)) + "\n")["K"]
    assert layout.split_args(value) == args


def test_names_and_paths():
    assert layout.unit(2) == "isaac-sim@2.service"
    assert layout.container(2) == "isaac-sim-2"
    assert layout.env_file(2) == "/etc/isaac-sim/instance-2.env"
    assert layout.marker(2) == "/run/isaac-sim/instance-2.ready"
    assert layout.data_dir(2, "/data") == "/data/instance-2"
    assert layout.instance_id(layout.UNIT_RE, "isaac-sim@7.service") == 7
    assert layout.instance_id(layout.ENV_FILE_RE, "/etc/isaac-sim/instance-3.env") == 3
    assert layout.instance_id(layout.UNIT_RE, "isaac-sim-metrics.service") is None


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
    text = layout.render_env(p["instances"][1], p, "sha256:abc", {"NGC_KEY": "k$y\"'\\"}, "managed")
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
    env = layout.parse(layout.render_env(headless["instances"][1], headless, "sha256:abc", {}, "managed"))
    # checked free at start: nothing, as the headless app opens nothing
    assert env[layout.K_PROFILE] == "headless" and env[layout.K_PORTS] == ""


def test_unit_numbers_are_numbers_whatever_was_given():
    unit = layout.render_unit(_plan()["settings"], "managed")
    assert "StartLimitBurst=3\n" in unit
    assert "StartLimitIntervalSec=156\n" in unit  # 3 * (2 + 20 + 30)
    assert "RestartSec=2\n" in unit and "TimeoutStartSec=50\n" in unit and "TimeoutStopSec=35\n" in unit
    assert "Restart=always\n" in unit and "RestartPreventExitStatus=76\n" in unit
    # session ends restart for ever while crash loops stop: every exit restarts, the start limit
    # is on (isaac-sim-run flushes it on a clean exit after ready), and no exit status is a
    # success that would end the unit instead of restarting it
    assert "StartLimitIntervalSec=0" not in unit and "SuccessExitStatus" not in unit
    assert "ExecStart=/usr/local/libexec/isaac-sim/isaac-sim-run\n" in unit
    # a stop while dockerd is down (systemd restarting it) must not wait on Docker's socket
    assert "ExecStop=-/bin/sh -c 'systemctl -q is-active docker.service || exit 0; exec /usr/bin/docker stop" in unit
    assert "EnvironmentFile=/etc/isaac-sim/instance-%i.env\n" in unit


@pytest.mark.parametrize("seed", range(5))
def test_split_args_reads_as_shlex_does(seed):
    """The regular-expression reader gives shlex.split's words, or its refusal, on any text, and
    join_args' own output back exactly."""
    rng = random.Random(seed)
    alphabet = " \t\n'\"\\$a-=b,`;#"
    for _n in range(4000):
        text = "".join(rng.choice(alphabet) for _m in range(rng.randint(0, 14)))
        try:
            want = shlex.split(text)
        except ValueError:
            with pytest.raises(ValueError):
                layout.split_args(text)
        else:
            assert layout.split_args(text) == want, text
        args = ["".join(rng.choice(alphabet) for _m in range(rng.randint(0, 8))) for _k in range(rng.randint(0, 5))]
        assert layout.split_args(layout.join_args(args)) == args
