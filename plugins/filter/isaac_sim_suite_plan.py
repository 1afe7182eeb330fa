# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""A test suite planned over the fleet, and its report."""

from __future__ import annotations

import json
import os

import yaml
from ansible.errors import AnsibleFilterError
from ansible.utils.unsafe_proxy import wrap_var

DOCUMENTATION = r"""
name: isaac_sim_suite_plan
short_description: The runs of a test suite, each given to a host that can take it
version_added: "0.3.0"
description:
  - Reads the suite file and every compose file it names (as the fleet runs them; an error in any stops the suite
    before it starts), makes one run per parameter set and repeat, and spreads the runs over the hosts, the least
    loaded first, each to a host with the GPUs and the instance it needs.
  - Returns C(plan) ({host - [run]}), C(runs) (how many) and C(errors).
positional: _input, hosts, previous, allowed
options:
  _input:
    description: The suite file's path on the controller.
    type: path
    required: true
  hosts:
    description: For each host, C(parallel), C(gpus) (how many) and C(instances) (how many ready ones it lends).
    type: dict
    required: true
  previous:
    description: The previous suite's C(suite.json); when given, only the runs that ran there and failed run again.
    type: path
  allowed:
    description: The confinement-loosening docker arguments a service may ask for (C(test_suite_allowed_docker_args)).
    type: list
    elements: str
"""

EXAMPLES = r"""
plan: "{{ 'suites/nightly.yml' | isaacsim.fleet.isaac_sim_suite_plan(capacities) }}"
"""

RETURN = r"""
_value:
  description: C(plan), C(runs), C(errors).
  type: dict
"""


def _load(path):
    with open(path) as fh:
        try:
            return yaml.safe_load(fh)
        except yaml.YAMLError as exc:
            raise ValueError(f"not YAML: {exc}") from exc


def _previous(path) -> list:
    try:
        with open(path) as fh:
            data = json.load(fh)
    except (OSError, ValueError) as exc:
        reason = str(exc)
    else:
        results = data.get("results") if isinstance(data, dict) else None
        if isinstance(results, list) and all(isinstance(r, dict) and "title" in r for r in results):
            return results
        reason = "not a suite's results: a list of runs, each with its title, under results"
    # the reason is in the message: Ansible 2.19 would append a chained cause to it
    raise AnsibleFilterError(
        f"test_suite_rerun_failed: the previous results {path} cannot be read ({reason}). Fix: run the whole suite."
    )


def suite_plan(path, hosts, previous=None, allowed=None):
    # on use, not at load: Ansible loads every filter file here to find one (docs/docsite/rst/contributing.rst, Layout)
    from ansible_collections.isaacsim.fleet.plugins.module_utils.runs import suite

    try:
        data = _load(path)
    except (OSError, ValueError) as exc:
        # the reason is in the message: Ansible 2.19 would append a chained cause to it
        raise AnsibleFilterError(
            f"test_suite_file: {path} cannot be read ({exc}). Fix: give the suite's path."
        ) from None
    timeout = (data or {}).get("timeout", 600) if isinstance(data, dict) else 600
    runs, errors = suite.expand(data, os.path.dirname(os.path.abspath(path)), _load, timeout, allowed or ())
    if previous:
        runs = suite.select_failed(runs, _previous(previous))
    caps = {
        h: {
            "parallel": int(c.get("parallel", 1)),
            "gpus": int(c.get("gpus", 0)),
            "instances": int(c.get("instances", 0)),
        }
        for h, c in (hosts or {}).items()
    }
    plan, assign_errors = suite.assign(runs, caps) if not errors else ({h: [] for h in caps}, [])
    # compose files are data: a healthcheck's docker --format '{{.State}}' is never a template
    return wrap_var({"plan": plan, "runs": len(runs), "errors": errors + assign_errors})


class FilterModule:
    def filters(self):
        return {"isaac_sim_suite_plan": suite_plan}
