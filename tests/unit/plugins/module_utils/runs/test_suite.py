"""A suite: its runs, which host takes each, a host's queue and the report."""

import threading
import time
import xml.etree.ElementTree as ET

from ansible_collections.isaacsim.fleet.plugins.module_utils.runs import suite, testrun

PLAIN = {
    "services": {"check": {"image": "reg/check:1", "labels": {"isaacsim.fleet/test-orchestrator": "true"}}},
}
SIM = {
    "services": {
        "isaac-sim": {"image": "isaac-sim"},
        "check": {"image": "reg/check:1", "labels": {"isaacsim.fleet/test-orchestrator": "true"}},
    }
}
GPU = {
    "services": {
        "check": {
            "image": "reg/check:1",
            "labels": {"isaacsim.fleet/test-orchestrator": "true"},
            "deploy": {"resources": {"reservations": {"devices": [{"capabilities": ["gpu"], "count": 2}]}}},
        }
    }
}
FILES = {"/s/plain.yml": PLAIN, "/s/sim.yml": SIM, "/s/gpu.yml": GPU, "/s/bad.yml": {"services": {"a": {"image": "x"}}}}


def load(path):
    if path not in FILES:
        raise OSError("no such file")
    return FILES[path]


def test_every_parameter_set_and_repeat_is_a_run():
    entries = {
        "experiences": [
            {"file": "plain.yml", "repeat": 2, "parameters": [{"SCENE": "office"}, {"SCENE": "yard"}], "timeout": 30},
            "sim.yml",
        ]
    }
    runs, errors = suite.expand(entries, "/s", load)
    assert errors == []
    assert [r["title"] for r in runs] == [
        "plain[SCENE=office]#1",
        "plain[SCENE=office]#2",
        "plain[SCENE=yard]#1",
        "plain[SCENE=yard]#2",
        "sim",
    ]
    assert runs[2]["environment"] == {"SCENE": "yard"} and runs[2]["timeout"] == 30.0
    assert runs[4]["simulator"] and runs[4]["timeout"] == 600 and not runs[0]["simulator"]
    assert len({r["key"] for r in runs}) == 5


def test_a_run_with_a_simulator_of_its_own_needs_no_instance_to_borrow():
    entries = {"experiences": [{"file": "sim.yml", "simulator": "dedicated"}, {"file": "sim.yml", "name": "lent"}]}
    runs, errors = suite.expand(entries, "/s", load)
    assert errors == []
    assert [(r["title"], r["simulator"], r["dedicated"]) for r in runs] == [("sim", False, True), ("lent", True, False)]
    plan, errors = suite.assign(runs[:1], {"a": {"parallel": 1, "gpus": 0, "instances": 0}})
    assert errors == [] and [r["title"] for r in plan["a"]] == ["sim"]
    _runs, errors = suite.expand({"experiences": [{"file": "sim.yml", "simulator": "own"}]}, "/s", load)
    assert errors == [
        "test_suite.experiences[0].simulator: 'own'. Fix: borrow (an instance of the fleet) or dedicated."
    ]


def test_one_bad_file_stops_the_whole_suite_with_its_reasons():
    entries = {"experiences": [{"file": "plain.yml", "repeat": 0}, {"file": "bad.yml"}, {"file": "gone.yml"}, {"x": 1}]}
    _runs, errors = suite.expand(entries, "/s", load)
    text = "\n".join(errors)
    assert "experiences[0].repeat: 0" in text
    assert "experiences[1] (/s/bad.yml): bad: no test orchestrator" in text
    assert "experiences[2].file: /s/gone.yml cannot be read (no such file)" in text
    assert "experiences[3]: needs file" in text
    assert suite.expand({}, "/s", load)[1] == [
        "test_suite: no experiences. Fix: give a list under experiences, each with a file."
    ]


def test_runs_go_to_the_least_loaded_host_that_can_take_them():
    runs, _errors = suite.expand(
        {"experiences": [{"file": "plain.yml", "repeat": 6}, "sim.yml", "gpu.yml"]}, "/s", load
    )
    hosts = {
        "a": {"parallel": 2, "gpus": 0, "instances": 0},
        "b": {"parallel": 2, "gpus": 0, "instances": 4},
        "c": {"parallel": 1, "gpus": 2, "instances": 0},
    }
    plan, errors = suite.assign(runs, hosts)
    assert errors == []
    titles = {h: [r["title"] for r in rs] for h, rs in plan.items()}
    assert "sim" in titles["b"] and "gpu" in titles["c"]
    # 6 plain runs over 5 slots: the two-slot hosts take two each before the one-slot host takes a second
    assert sorted(len(v) for v in titles.values()) == [2, 3, 3]


def test_a_run_no_host_can_take_is_an_error_saying_why():
    runs, _errors = suite.expand({"experiences": ["gpu.yml", "sim.yml"]}, "/s", load)
    _plan, errors = suite.assign(runs, {"a": {"parallel": 2, "gpus": 1, "instances": 0}})
    assert errors[0].startswith("gpu: no host can give it 2 GPU(s) (the most any host has is 1)")
    assert errors[1].startswith("sim: no host can give it a ready instance to borrow")


def test_rerunning_the_failed_runs_only_and_merging_their_results():
    runs, _errors = suite.expand({"experiences": [{"file": "plain.yml", "repeat": 3}]}, "/s", load)
    previous = [
        {"title": "plain#1", "verdict": {"result": "passed", "reason": "", "seconds": 1}},
        {"title": "plain#2", "verdict": {"result": "failed", "reason": "x", "seconds": 1}},
        {"title": "plain#3", "error": "image missing"},
    ]
    again = suite.select_failed(runs, previous)
    assert [r["title"] for r in again] == ["plain#2", "plain#3"]
    new = [{"title": "plain#2", "verdict": {"result": "passed", "reason": "", "seconds": 2}}]
    merged = suite.merge(previous, new)
    assert [(r["title"], suite.outcome(r)) for r in merged] == [
        ("plain#1", "passed"),
        ("plain#3", "error"),
        ("plain#2", "passed"),
    ]


def test_the_suite_report_has_a_case_per_run():
    results = [
        {"title": "a#1", "host": "h1", "run": "a-1-1-x", "verdict": {"result": "passed", "reason": "ok", "seconds": 2}},
        {"title": "a#2", "host": "h2", "run": "a-1-2-x", "verdict": {"result": "timeout", "reason": "t", "seconds": 9}},
        {"title": "b", "host": "h1", "error": "image missing"},
    ]
    root = ET.fromstring(suite.junit(results))
    assert (root.get("tests"), root.get("failures"), root.get("errors")) == ("3", "1", "1")
    # a control character in an entry's name or parameters (a pasted colour code) keeps it valid XML
    results[0]["title"] = "a\x1b[31m#1\x00"
    results[2]["error"] = "image\x07 missing"
    root = ET.fromstring(suite.junit(results))
    assert root.find("testcase").get("name") == "a[31m#1" and "image missing" in ET.tostring(root, "unicode")
    assert suite.summary_lines(results, 12.0)[-1] == "3 runs: 1 error, 1 passed, 1 timeout in 12.0 s"


def test_a_host_queue_keeps_to_its_parallel_and_lends_each_instance_to_one_run_at_a_time():
    runs = [{"title": f"r{n}", "gpus": 0, "simulator": n % 2 == 0} for n in range(8)]
    live, peak, lent, restarts = [0], [0], set(), []
    guard = threading.Lock()

    def execute_one(run, instance, gpus):
        with guard:
            live[0] += 1
            peak[0] = max(peak[0], live[0])
            if instance is not None:
                assert instance not in lent, "one instance lent twice"
                lent.add(instance)
        time.sleep(0.02)
        with guard:
            live[0] -= 1
        if instance is not None:  # the run gives it back itself (lifecycle.give_back) before it returns
            with guard:
                lent.discard(instance)
            restarts.append(instance)
        if run["title"] == "r3":
            raise RuntimeError("docker network create failed")
        return {"title": run["title"], "instance": instance, "verdict": {"result": "passed"}}

    results = testrun.run_queue(runs, 3, [0], [], execute_one, threading)
    assert peak[0] <= 3
    assert [r["title"] for r in results] == [f"r{n}" for n in range(8)]
    assert results[3]["error"] == "RuntimeError: docker network create failed"  # and the others went on
    assert all(r.get("instance") == 0 for r in results if r["title"] in ("r0", "r2", "r4", "r6"))
    assert restarts == [0, 0, 0, 0]


def test_a_run_takes_an_instance_nobody_holds_and_waits_for_a_held_one_only_when_none_is_free():
    # instances 0 and 2 are held outside the suite (a person's session, another suite's run)
    runs = [{"title": f"r{n}", "gpus": 0, "simulator": True} for n in range(3)]
    outside = {0, 2}
    taken = []

    def execute_one(run, instance, gpus):
        taken.append(instance)
        return {"title": run["title"], "instance": instance, "verdict": {"result": "passed"}}

    results = testrun.run_queue(runs, 1, [0, 1, 2, 3], [], execute_one, threading, held=lambda i: i in outside)
    # one at a time: each given back before the next starts, so the free ones go first, then again
    assert taken == [1, 3, 1], taken
    assert [r["instance"] for r in results] == [1, 3, 1]
    # all held: the first is taken, and its claim is waited out by the run itself (lifecycle.lend)
    taken.clear()
    testrun.run_queue(runs[:2], 2, [0, 2], [], execute_one, threading, held=lambda i: True)
    assert sorted(taken) == [0, 2]


def test_an_instance_that_does_not_come_back_is_not_lent_again():
    runs = [{"title": f"r{n}", "gpus": 0, "simulator": True} for n in range(3)]

    def execute_one(run, instance, gpus):
        error = "isaac-sim@0 did not come back: not ready within 180 s"
        return {"title": run["title"], "verdict": {"result": "passed"}, "restart_error": error}

    results = testrun.run_queue(runs, 2, [0], [], execute_one, threading)
    assert results[0]["restart_error"] == "isaac-sim@0 did not come back: not ready within 180 s"
    assert "their restarts failed" in results[1]["error"] and "their restarts failed" in results[2]["error"]


def test_a_run_that_could_not_borrow_leaves_the_instance_free_for_the_next():
    # another suite held it for this run's whole timeout: nothing was restarted, nothing is broken
    runs = [{"title": f"r{n}", "gpus": 0, "simulator": True} for n in range(2)]

    def execute_one(run, instance, gpus):
        if run["title"] == "r0":
            return {"title": "r0", "error": "isaac-sim@0 stayed lent to other for the run's whole timeout"}
        return {"title": run["title"], "instance": instance, "verdict": {"result": "passed"}}

    results = testrun.run_queue(runs, 1, [0], [], execute_one, threading)
    assert "stayed lent" in results[0]["error"] and results[1]["verdict"]["result"] == "passed"


def test_a_run_that_raises_neither_hangs_the_queue_nor_stops_the_others():
    runs = [{"title": f"r{n}", "gpus": 0, "simulator": n < 2} for n in range(4)]

    def execute_one(run, instance, gpus):
        if run["title"] == "r0":
            raise OSError("systemctl went away")
        return {"title": run["title"], "verdict": {"result": "passed"}}

    done = []
    worker = threading.Thread(target=lambda: done.append(testrun.run_queue(runs, 2, [0], [], execute_one, threading)))
    worker.start()
    worker.join(10)
    assert done, "run_queue hung"
    results = done[0]
    assert results[0]["error"] == "OSError: systemctl went away"
    assert [r["verdict"]["result"] for r in results[1:]] == ["passed"] * 3


def test_a_host_whose_share_never_ran_is_reported_run_by_run():
    plan = {"h1": [{"title": "a#1"}], "h2": [{"title": "a#2"}, {"title": "b"}]}
    results = [{"title": "a#1", "host": "h1", "verdict": {"result": "passed", "reason": "", "seconds": 1}}]
    out = suite.with_missing(results, plan, {"h2": "the host did not answer"})
    assert [(r["title"], suite.outcome(r)) for r in out] == [("a#1", "passed"), ("a#2", "error"), ("b", "error")]
    assert out[1]["error"] == "h2: the host did not answer"
