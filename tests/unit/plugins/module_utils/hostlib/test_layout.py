"""The host-layout contract: names, paths and the env-file quote/parse pair."""

import random
import shlex

import pytest
from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib import layout

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


def test_a_killed_warm_run_s_leftovers_are_its_dot_directories_and_partial_archives(tmp_path):
    (tmp_path / ".k1.abc").mkdir()
    (tmp_path / "k1.tar.partial").write_text("x")
    (tmp_path / "k1.tar").write_text("x")
    (tmp_path / ".keep").write_text("a user's file")
    (tmp_path / ".linked").symlink_to(tmp_path / ".k1.abc")
    left = sorted(
        n for n in ("k1.tar", ".k1.abc", "k1.tar.partial", ".keep", ".linked") if layout.warm_scratch(str(tmp_path), n)
    )
    assert left == [".k1.abc", "k1.tar.partial"]


def test_parse_shown_reads_systemctl_show_by_unit():
    """The one reader of `systemctl show` for many units (the lifecycle, the status code, the plan)."""
    text = "Id=a.service\nActiveState=active\n\n\nId=b.timer\nActiveState=inactive\nX=1=2\n\nActiveState=active\n"
    assert layout.parse_shown(text) == {
        "a.service": {"Id": "a.service", "ActiveState": "active"},
        "b.timer": {"Id": "b.timer", "ActiveState": "inactive", "X": "1=2"},
    }
    assert layout.parse_shown("") == {} and layout.parse_shown(None) == {}


def test_a_session_s_files_go_beside_the_instances_under_its_own_name_and_only_a_session_s_name():
    assert (
        layout.documents_dir(3, "/d") == "/d/instance-3/documents" == f"{layout.data_dir(3, '/d')}/{layout.DOCUMENTS}"
    )
    assert layout.files_dir("session-ab12") == "/var/lib/isaac-sim/files/session-ab12"
    assert layout.files_stash("session-ab12", 1, "/d") == "/d/files/session-ab12"
    assert layout.files_stash("session-ab12", 2, "/d") == "/d/files/session-ab12.2"
    for bad in ("run-a", "session-", "session-AB", "session-a/../../etc", "../session-a", "session-a\n", None):
        with pytest.raises(ValueError):
            layout.files_dir(bad)
    found = {n: layout.FILES_STASH_RE.match(n) for n in ("session-a", "session-a.2", "session-a.10", "session-a.1")}
    assert {n: m and (m.group(1), m.group(2)) for n, m in found.items()} == {
        "session-a": ("session-a", None),
        "session-a.2": ("session-a", "2"),
        "session-a.10": ("session-a", "10"),
        # never made: files_stash(holder, 1) is the name without a number
        "session-a.1": None,
    }
    assert not layout.FILES_STASH_RE.match("session-a.02") and not layout.FILES_STASH_RE.match("run-a.2")
