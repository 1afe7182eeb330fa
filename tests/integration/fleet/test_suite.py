"""A suite of 9 runs over the three fleet hosts (one borrowing an instance, one with a simulator
of its own): each run's verdict, at most the configured number of runs at once per host (measured
from the hosts' journals), every run's artefacts on the controller, nothing left on the hosts, and
a re-run of only the failed ones."""

import json
import time
import xml.etree.ElementTree as ET
from concurrent.futures import ThreadPoolExecutor

import pytest
import yaml
from fleethosts import hosts, playbook, sh, squash
from testbed import ROOT, RUN_LEFTOVERS

FIXTURES = ROOT / "tests" / "fixtures" / "experiences"
PARALLEL = 2
STARTED = "39f53479d3a045ac8e11786248231fbf"  # systemd's "Started UNIT" journal message
# title -> the verdict the reference platform's rules give it. 9 runs: 3 a host, more than PARALLEL,
# so the limit holds some back; every verdict kind, and one experience repeated (fail#1, fail#2)
EXPECTED = {
    "pass": "passed",
    "fail#1": "failed",
    "fail#2": "failed",
    "crash[CRASH_RESTART=no]": "failed",
    "crash[CRASH_RESTART=on-failure]": "passed",
    "late": "passed",
    "hang": "timeout",
    "sim": "passed",
    "dedicated": "passed",
}


def image(host: str) -> str:
    env = sh(host, "cat /etc/isaac-sim/instance-0.env")
    line = next(x for x in env.splitlines() if x.startswith("ISAAC_SIM_IMAGE="))
    return line.split("=", 1)[1].strip('"')


@pytest.fixture(scope="module")
def suite(tmp_path_factory):
    out = tmp_path_factory.mktemp("suite")
    spec = {
        "environment": {"IMAGE": image(hosts()[0])},
        "timeout": 120,
        "experiences": [
            {"file": str(FIXTURES / "pass.yml")},
            {"file": str(FIXTURES / "fail.yml"), "repeat": 2},
            {
                "file": str(FIXTURES / "crash.yml"),
                "parameters": [{"CRASH_RESTART": "no"}, {"CRASH_RESTART": "on-failure"}],
            },
            {"file": str(FIXTURES / "late.yml")},
            {"file": str(FIXTURES / "hang.yml"), "timeout": 5},
            {"file": str(FIXTURES / "sim.yml")},
            # a headless Isaac Sim of the run's own: no instance lent
            {"file": str(FIXTURES / "dedicated.yml"), "simulator": "dedicated"},
        ],
    }
    (out / "suite.yml").write_text(yaml.safe_dump(spec))
    extra = {"test_suite_file": str(out / "suite.yml"), "test_suite_dir": str(out / "runs")}
    since = {h: sh(h, "date +%s").strip() for h in hosts()}
    run = playbook("test_suite.yml", dict(extra, test_suite_parallel_per_host=PARALLEL))
    return out, extra, run, since


def results(out) -> dict:
    return {r["title"]: r for r in json.loads((out / "runs" / "suite.json").read_text())["results"]}


def runs_at_once(host: str, runs: list, since: str) -> int:
    """The most runs that were going on together on a host, from systemd's own journal lines
    about the runs' units (first start to last stop of each run)."""
    out = sh(host, f"journalctl -o json --no-pager --since @{since} _PID=1")
    spans = {}
    for line in out.splitlines():
        entry = json.loads(line)
        unit = entry.get("UNIT") or ""
        for run in runs:
            if unit.startswith(f"isaac-sim-run-{run}-"):
                t = int(entry["__REALTIME_TIMESTAMP"]) / 1e6
                first, last = spans.get(run, (t, t))
                spans[run] = (min(first, t), max(last, t))
    assert set(spans) == set(runs), f"{host}: journal has {sorted(spans)}, ran {sorted(runs)}"
    edges = sorted([(a, 1) for a, _b in spans.values()] + [(b, -1) for _a, b in spans.values()])
    live = peak = 0
    for _t, step in edges:
        live += step
        peak = max(peak, live)
    return peak


def test_every_run_gets_the_verdict_the_rules_give_it(suite):
    out, _extra, run, _since = suite
    assert run.returncode != 0  # four runs are meant to fail
    # Ansible prints a task's failure on stderr
    assert "4 of 9 runs did not pass" in squash(run.stdout + run.stderr), run.stdout[-3000:]
    found = results(out)
    assert {t: r["verdict"]["result"] for t, r in found.items()} == EXPECTED
    junit = ET.parse(out / "runs" / "junit.xml").getroot()
    assert (junit.get("tests"), junit.get("failures"), junit.get("errors")) == ("9", "4", "0")
    for title, r in found.items():
        directory = out / "runs" / r["run"]
        assert (directory / "junit.xml").exists() and (directory / "result.json").exists(), title


def test_no_host_ran_more_than_its_parallel_and_every_host_took_a_share(suite):
    out, _extra, _run, since = suite
    by_host = {}
    for r in results(out).values():
        by_host.setdefault(r["host"], []).append(r["run"])
    assert sorted(by_host) == hosts()
    for host, runs in by_host.items():
        assert 1 <= runs_at_once(host, runs, since[host]) <= PARALLEL, host


def test_nothing_of_any_run_is_left_on_the_hosts_and_lent_instances_serve_again(suite):
    out, _extra, _run, _since = suite
    for host in hosts():
        left = sh(host, RUN_LEFTOVERS)
        assert left.strip() == "", f"{host}: {left}"
        assert sh(host, "ls /run/isaac-sim").count(".ready") >= 4
        assert ".lent" not in sh(host, "ls /run/isaac-sim")
    # the run with a simulator of its own borrowed no instance; its simulator ran the host's image headless
    own = results(out)["dedicated"]
    assert "instance" not in own
    log = (out / "runs" / own["run"] / f"{own['run']}-isaac-sim.log").read_text()
    assert "(script isaac-sim.sh, shader cache" in log


def test_re_running_the_failed_ones_runs_only_those(suite):
    out, extra, _run, _since = suite
    first = results(out)
    again = playbook("test_suite.yml", dict(extra, test_suite_rerun_failed=True))
    assert again.returncode != 0
    after = results(out)
    rerun = {t for t in after if after[t]["run"] != first[t]["run"]}
    assert rerun == {t for t, v in EXPECTED.items() if v != "passed"}
    assert {t: r["verdict"]["result"] for t, r in after.items()} == EXPECTED


def test_two_suites_at_once_on_one_host_share_its_instances_and_a_third_on_a_busy_directory_is_refused(
    tmp_path,
):
    # both suites borrow from one host's four instances, two runs at a time: a run takes one that neither
    # suite holds, and none is restarted under another's run
    host = hosts()[0]
    spec = {
        "environment": {"IMAGE": image(host), "HOLD_S": "4"},
        "timeout": 300,
        "experiences": [{"file": str(FIXTURES / "sim.yml"), "repeat": 3}],
    }
    (tmp_path / "suite.yml").write_text(yaml.safe_dump(spec))
    extra = {
        "test_suite_file": str(tmp_path / "suite.yml"),
        "test_suite_parallel_per_host": 2,
        "test_suite_gpus": [],
    }
    started = {}
    since = sh(host, "date +%s").strip()
    with ThreadPoolExecutor(2) as pool:
        for name in ("a", "b"):
            started[name] = pool.submit(
                playbook, "test_suite.yml", dict(extra, test_suite_dir=str(tmp_path / name)), host
            )
        # a third suite into a directory the first is writing changes nothing there
        wait = time.monotonic() + 120
        while not (tmp_path / "a" / ".suite-lock.json").exists() and time.monotonic() < wait:
            time.sleep(0.5)
        third = playbook("test_suite.yml", dict(extra, test_suite_dir=str(tmp_path / "a")), host)
        done = {name: future.result() for name, future in started.items()}
    text = squash(third.stdout + third.stderr)
    assert third.returncode != 0 and "is being written by another suite" in text, text[-2000:]
    assert "test_suite_dir" in text and "Run this host's share" not in third.stdout
    for name, run in done.items():
        assert run.returncode == 0, squash(run.stdout + run.stderr)[-3000:]
        found = json.loads((tmp_path / name / "suite.json").read_text())["results"]
        assert [r["verdict"]["result"] for r in found] == ["passed"] * 3, found
        for r in found:
            banner = (tmp_path / name / r["run"] / "outputs" / "banner.txt").read_text()
            assert banner.startswith("isaac-sim-standin signal"), (name, r["run"])
    # each run's instance was given back restarted once, and never restarted under another run (every
    # one passed): six starts in all since they began
    used = [r["instance"] for name in done for r in json.loads((tmp_path / name / "suite.json").read_text())["results"]]
    assert len(used) == 6 and set(used) <= set(range(4)), used
    starts = sh(host, f"journalctl --no-pager -o cat --since @{since} _PID=1 MESSAGE_ID={STARTED}")
    assert sum(line.startswith("Started isaac-sim@") for line in starts.splitlines()) == 6, starts
    assert ".lent" not in sh(host, "ls /run/isaac-sim")
    assert sh(host, RUN_LEFTOVERS).strip() == ""
    assert sh(host, "ls -A /var/lib/isaac-sim/runs").split() == [".store.lock"]
    assert not (tmp_path / "a" / ".suite-lock.json").exists()
