"""The one JUnit writer: how a CI server counts each run, and the file it reads."""

import xml.etree.ElementTree as ET

import pytest
from ansible_collections.isaacsim.fleet.plugins.module_utils.runs import junit, suite, testrun


@pytest.mark.parametrize(
    ("verdict", "expected"),
    [
        ({"result": "passed"}, None),
        ({"result": "failed"}, junit.FAILURE),
        ({"result": "timeout"}, junit.FAILURE),
        ({"result": "error"}, junit.ERROR),
        # no verdict at all, or one the judge never gives: the run was not judged
        (None, junit.ERROR),
        ({}, junit.ERROR),
        ({"result": "cancelled"}, junit.ERROR),
    ],
)
def test_a_failed_verdict_is_a_failure_and_a_run_without_one_an_error(verdict, expected):
    assert junit.kind(verdict) == expected


def case(name, result, seconds=1.0, output=None, host="h1"):
    verdict = {"result": result, "reason": f"{name} {result}", "seconds": seconds}
    return {"host": host, "name": name, "verdict": verdict, "output": output}


def test_a_suite_counts_failures_and_errors_and_sums_the_time():
    cases = [
        case("a", "passed", 2),
        case("b", "failed", 1.25),
        case("c", "timeout", 9.5),
        case("d", "error", 0.5, output="docker said no"),
        {"host": None, "name": "e", "verdict": None, "output": None},
    ]
    root = ET.fromstring(junit.testsuite("s", cases))
    assert root.tag == "testsuite" and root.get("name") == "s"
    assert (root.get("tests"), root.get("failures"), root.get("errors"), root.get("time")) == (
        "5",
        "2",
        "2",
        "13.250",
    )
    found = {c.get("name"): c for c in root.findall("testcase")}
    assert found["a"].find("failure") is None and found["a"].find("error") is None
    assert found["b"].find("failure").attrib == {"message": "b failed", "type": "failed"}
    assert found["c"].find("failure").get("type") == "timeout"
    assert found["d"].find("error").attrib == {"message": "d error", "type": "error"}
    assert found["d"].find("system-out").text == "docker said no" and found["a"].find("system-out") is None
    assert found["e"].find("error").get("message") == "no verdict" and found["e"].get("time") == "0.000"
    assert found["e"].get("classname") == "isaacsim.fleet.None" and found["b"].get("classname") == "isaacsim.fleet.h1"


def test_the_file_is_what_ci_servers_read():
    text = junit.testsuite("x", [case("a", "failed", 4.5, output="<boom> & done")], [("run", "r1"), ("host", "h1")])
    assert text == (
        '<?xml version="1.0" encoding="UTF-8"?>\n'
        '<testsuite name="x" tests="1" failures="1" errors="0" skipped="0" time="4.500">\n'
        "  <properties>\n"
        '      <property name="run" value="r1"/>\n'
        '      <property name="host" value="h1"/>\n'
        "  </properties>\n"
        '  <testcase classname="isaacsim.fleet.h1" name="a" time="4.500">\n'
        '    <failure message="a failed" type="failed"/>\n'
        "    <system-out>&lt;boom&gt; &amp; done</system-out>\n"
        "  </testcase>\n"
        "</testsuite>\n"
    )
    # no properties: no properties element; an empty output is an empty system-out
    text = junit.testsuite("x", [case("a", "passed", output="")])
    assert "<properties>" not in text and "    <system-out></system-out>\n" in text


def test_a_run_and_the_suite_count_the_same_verdict_the_same_way():
    for result, failures, errors in (
        ("passed", "0", "0"),
        ("failed", "1", "0"),
        ("timeout", "1", "0"),
        ("error", "0", "1"),
    ):
        verdict = {"result": result, "service": None, "reason": "why", "seconds": 2.0}
        run = {"run": "r1", "host": "h1", "experience": "pair", "verdict": verdict}
        one = ET.fromstring(testrun.junit(run))
        many = ET.fromstring(suite.junit([dict(run, title="pair")]))
        for root in (one, many):
            assert (root.get("failures"), root.get("errors")) == (failures, errors), (result, root.get("name"))
    # a suite's run that never started has no verdict: an error, with the reason it gave
    root = ET.fromstring(suite.junit([{"title": "b", "host": "h1", "error": "image missing"}]))
    assert root.get("errors") == "1" and root.find("testcase/error").get("message") == "image missing"
