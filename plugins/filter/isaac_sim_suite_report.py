# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""A test suite's results as a table and one JUnit file."""

from __future__ import annotations

DOCUMENTATION = r"""
name: isaac_sim_suite_report
short_description: A test suite's results as lines for a person and one JUnit file
version_added: "0.3.0"
description:
  - For the results of M(isaacsim.fleet.isaac_sim_test_suite) on every host, C(lines) (one per run and the totals)
    and C(junit) (a JUnit XML text with a test case per run).
positional: _input, wall, previous, plan, why
options:
  _input:
    description: The results of every host, one list.
    type: list
    elements: dict
    required: true
  wall:
    description: The suite's wall time in seconds, for the totals line.
    type: float
  previous:
    description: The previous suite's results, when this one re-ran the runs that failed there.
    type: list
    elements: dict
  plan:
    description: The suite's plan ({host - runs}); a planned run without a result is reported as an error.
    type: dict
  why:
    description: Per host, why its share gave no results (the failed task's message).
    type: dict
"""

EXAMPLES = r"""
report: "{{ results | isaacsim.fleet.isaac_sim_suite_report(120.5) }}"
"""

RETURN = r"""
_value:
  description: C(results) (merged with O(previous)), C(failed) (how many did not pass), C(lines) and C(junit).
  type: dict
"""


def suite_report(results, wall=None, previous=None, plan=None, why=None):
    # on use, not at load: Ansible loads every filter file here to find one (docs/docsite/rst/contributing.rst, Layout)
    from ansible_collections.isaacsim.fleet.plugins.module_utils.runs import suite

    results = suite.with_missing(results, plan or {}, why or {})
    if previous:
        results = suite.merge(previous, results)
    failed = [r for r in results if suite.outcome(r) != "passed"]
    return {
        "results": results,
        "failed": len(failed),
        "lines": suite.summary_lines(results, wall),
        "junit": suite.junit(results),
    }


class FilterModule:
    def filters(self):
        return {"isaac_sim_suite_report": suite_report}
