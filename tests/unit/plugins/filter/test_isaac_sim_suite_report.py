"""The isaac_sim_suite_report filter, as playbooks/test_suite.yml's report play calls it: every
host's share results | isaac_sim_suite_report(wall time, the previous suite.json's results when
re-running, the plan, why each host's share gave none). The shares are run on the scripted hosts
of test_runner; the report's suite.json and junit.xml are read back as the playbook writes them."""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET

import yaml
from ansible_collections.isaacsim.fleet.plugins.filter.isaac_sim_suite_report import FilterModule
from ansible_collections.isaacsim.fleet.tests.unit.plugins.module_utils.runs.test_runner import (
    PAIR,
    Host,
    make,
    share_params,
    suite_run,
)

HEADER = f"{'run':<40} {'host':<20} {'result':<8} {'seconds':>8}  reason"
PASSED = "every orchestrator exited 0 (check)"
GONE = (
    "reg/gone:1: image reg/gone:1 cannot be had (boom). Fix: correct the image name or tag, or push the image to the "
    "fleet's registry."
)


def report(results, wall, previous, plan, why) -> dict:
    return FilterModule().filters()["isaac_sim_suite_report"](results, wall, previous, plan, why)


def row(title, host, result, seconds, reason) -> str:
    return f"{title:<40} {host:<20} {result:<8} {seconds:>8.1f}  {reason}"


def share(tmp_path, host: str, runs: list, **kw) -> dict:
    """The host's isaac_sim_test_suite result (registered as __suite_ran)."""
    root = tmp_path / host
    root.mkdir()
    scripted = Host(root, fail_on="pull --quiet reg/gone:1")
    return make(scripted, hostname=host)[0].share(share_params(root, runs, **dict({"parallel": 1}, **kw)))


def junit(text: str) -> tuple:
    root = ET.fromstring(text)
    cases = [
        (c.get("classname"), c.get("name"), [(e.tag, e.get("message")) for e in c if e.tag != "system-out"])
        for c in root.iter("testcase")
    ]
    return (root.get("tests"), root.get("failures"), root.get("errors")), cases


def test_every_planned_run_is_reported_even_those_of_a_share_that_never_ran(tmp_path):
    gone = yaml.safe_load(yaml.safe_dump(PAIR).replace("reg/check:1", "reg/gone:1"))
    plan = {
        "gpu-1": [suite_run("pair-1-1", title="pair#1"), suite_run("gone-1-1", title="gone", compose=gone)],
        "gpu-2": [suite_run("pair-1-2", title="pair#2")],
        "gpu-3": [suite_run("pair-1-3", title="pair#3")],
    }
    ran = share(tmp_path, "gpu-1", plan["gpu-1"])
    refused = share(tmp_path, "gpu-2", plan["gpu-2"], parallel=0)
    assert refused == {"failed": True, "msg": "parallel: 0. Fix: 1 or more runs at once."}
    # gpu-3 stopped answering: no __suite_ran, so the playbook's default message
    why = {"gpu-1": "", "gpu-2": refused["msg"], "gpu-3": "the host did not answer"}
    found = report(ran["results"], 61.5, [], plan, why)

    assert found["failed"] == 3
    assert found["lines"] == [
        HEADER,
        row("gone", "gpu-1", "error", 0, GONE),
        row("pair#1", "gpu-1", "passed", 3, PASSED),
        row("pair#2", "gpu-2", "error", 0, "gpu-2: parallel: 0. Fix: 1 or more runs at once."),
        row("pair#3", "gpu-3", "error", 0, "gpu-3: the host did not answer"),
        "4 runs: 3 error, 1 passed in 61.5 s",
    ]
    # the playbook's suite.json and junit.xml
    saved = json.loads(json.dumps({"results": found["results"]}))["results"]
    assert [(r["title"], r["host"], r.get("run")) for r in saved] == [
        ("pair#1", "gpu-1", "pair-1-1-20261124-0000-ab12"),
        ("gone", "gpu-1", None),
        ("pair#2", "gpu-2", None),
        ("pair#3", "gpu-3", None),
    ]
    assert saved[2] == {
        "title": "pair#2",
        "key": "pair-1-2",
        "host": "gpu-2",
        "error": "gpu-2: parallel: 0. Fix: 1 or more runs at once.",
    }
    counts, cases = junit(found["junit"])
    assert counts == ("4", "0", "3")
    assert cases == [
        ("isaacsim.fleet.gpu-1", "pair#1", []),
        ("isaacsim.fleet.gpu-1", "gone", [("error", GONE)]),
        ("isaacsim.fleet.gpu-2", "pair#2", [("error", "gpu-2: parallel: 0. Fix: 1 or more runs at once.")]),
        ("isaacsim.fleet.gpu-3", "pair#3", [("error", "gpu-3: the host did not answer")]),
    ]
    # a share that ran gives no reason: a run of it with no result still says so
    found = report([], None, [], {"gpu-1": plan["gpu-1"][:1]}, {"gpu-1": ""})
    assert found["lines"][1:] == [row("pair#1", "gpu-1", "error", 0, "gpu-1: no result came back"), "1 runs: 1 error"]


def verdict(result, reason, seconds=12.0, service="check") -> dict:
    return {"result": result, "service": service, "reason": reason, "seconds": seconds}


def test_a_re_run_keeps_the_previous_result_of_every_run_it_did_not_run_again(tmp_path):
    previous = [
        {"title": "pass#1", "host": "gpu-1", "run": "pass-1-1-a", "verdict": verdict("passed", PASSED, 20.0)},
        {"title": "fail#1", "host": "gpu-1", "run": "fail-1-1-a", "verdict": verdict("failed", "check exited 3")},
        {"title": "hang", "host": "gpu-2", "run": "hang-1-1-a", "verdict": verdict("timeout", "no verdict in 5 s", 5)},
    ]
    (tmp_path / "suite.json").write_text(json.dumps({"results": previous}, indent=4))
    # as the playbook reads it: lookup('file', test_suite_dir ~ '/suite.json') | from_json).results
    previous = json.loads((tmp_path / "suite.json").read_text())["results"]
    plan = {"gpu-1": [suite_run("fail-1-1", title="fail#1")], "gpu-2": [suite_run("hang-1-1", title="hang")]}
    again = [
        {"title": "fail#1", "host": "gpu-1", "run": "fail-1-1-b", "verdict": verdict("failed", "check exited 3")},
        {
            "title": "hang",
            "host": "gpu-2",
            "run": "hang-1-1-b",
            "instance": 0,
            "verdict": verdict("passed", PASSED, 4.5),
            "restart_error": "isaac-sim@0 did not come back: not ready within 300 s",
        },
    ]
    found = report(again, 30.0, previous, plan, {"gpu-1": "", "gpu-2": ""})
    assert [(r["title"], r["run"]) for r in found["results"]] == [
        ("pass#1", "pass-1-1-a"),
        ("fail#1", "fail-1-1-b"),
        ("hang", "hang-1-1-b"),
    ]
    assert found["failed"] == 1
    assert found["lines"] == [
        HEADER,
        row("fail#1", "gpu-1", "failed", 12, "check exited 3"),
        row("hang", "gpu-2", "passed", 4.5, f"{PASSED}; isaac-sim@0 did not come back: not ready within 300 s"),
        row("pass#1", "gpu-1", "passed", 20, PASSED),
        "3 runs: 1 failed, 2 passed in 30.0 s",
    ]
    counts, cases = junit(found["junit"])
    assert counts == ("3", "1", "0") and cases[1] == ("isaacsim.fleet.gpu-1", "fail#1", [("failure", "check exited 3")])
    assert ET.fromstring(found["junit"]).get("time") == "36.500"
