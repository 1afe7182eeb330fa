# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""JUnit XML of test runs: the one writer of a run's own junit.xml (testrun) and of a suite's
(suite), with one rule for how a CI server counts a run:

- a failed verdict (failed, timeout: the run was judged and did not pass) is a <failure>;
- a run that produced no verdict (error: it could not start or could not be watched, or no
  verdict at all: its host's share did not run) is an <error>;
- a passed run is neither.
"""

from __future__ import annotations

from ansible_collections.isaacsim.fleet.plugins.module_utils.common import xml_safe
from ansible_collections.isaacsim.fleet.plugins.module_utils.runs import judge

FAILURE, ERROR = "failure", "error"


def kind(verdict) -> str | None:
    """FAILURE, ERROR or None (passed) for a verdict ({"result": ...}; None when there was none)."""
    result = (verdict or {}).get("result")
    if result == judge.PASSED:
        return None
    if result in (judge.FAILED, judge.TIMEOUT):
        return FAILURE
    return ERROR


def _seconds(verdict) -> float:
    return float((verdict or {}).get("seconds") or 0)


def _case(case: dict) -> str:
    """One <testcase>: case is {"host", "name", "verdict", "output"} (output None: no system-out)."""
    verdict = case["verdict"] or {}
    out = (
        f"  <testcase classname={xml_safe.attr('isaacsim.fleet.' + str(case['host']))} "
        f'name={xml_safe.attr(case["name"])} time="{_seconds(verdict):.3f}">\n'
    )
    message = xml_safe.attr(verdict.get("reason", "no verdict"))
    found = kind(verdict)
    if found == FAILURE:
        out += f"    <failure message={message} type={xml_safe.attr(verdict['result'])}/>\n"
    elif found == ERROR:
        out += f'    <error message={message} type="error"/>\n'
    if case.get("output") is not None:
        out += f"    <system-out>{xml_safe.text(case['output'])}</system-out>\n"
    return out + "  </testcase>\n"


def testsuite(name: str, cases: list, properties=()) -> str:
    """A JUnit file: one <testsuite> called name, a <testcase> per case ({"host", "name",
    "verdict", "output"}), the suite's properties ([(name, value)]) first when there are any."""
    failures = sum(1 for c in cases if kind(c["verdict"]) == FAILURE)
    errors = sum(1 for c in cases if kind(c["verdict"]) == ERROR)
    total = 0.0
    for c in cases:
        total += _seconds(c["verdict"])
    props = ""
    if properties:
        rows = "".join(
            f"      <property name={xml_safe.attr(k)} value={xml_safe.attr(str(v))}/>\n" for k, v in properties
        )
        props = f"  <properties>\n{rows}  </properties>\n"
    return (
        '<?xml version="1.0" encoding="UTF-8"?>\n'
        f'<testsuite name={xml_safe.attr(name)} tests="{len(cases)}" failures="{failures}" errors="{errors}" '
        f'skipped="0" time="{total:.3f}">\n' + props + "".join(_case(c) for c in cases) + "</testsuite>\n"
    )
