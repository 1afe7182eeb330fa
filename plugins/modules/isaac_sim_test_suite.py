#!/usr/bin/python
# Copyright: isaacsim.fleet contributors
# SPDX-License-Identifier: Apache-2.0 (the collection's license, see galaxy.yml)
# Apache-2.0 is compatible with the GNU General Public License v3.0 that ansible-core is
# released under; ansible-test's validate-modules looks for that license's name here.

DOCUMENTATION = r"""
---
module: isaac_sim_test_suite
short_description: Run a host's share of a test suite, a bounded number of experiences at a time
version_added: "0.3.0"
description:
  - Runs the given runs (experiences as M(isaacsim.fleet.isaac_sim_experience) runs them) with at most O(parallel)
    at once. A run whose file has the simulator (C(image=isaac-sim)) waits for a free instance of O(instances) and
    borrows it; a run that reserves GPUs waits for that many free ids of O(gpus).
  - Lending is the collection's one lifecycle's (C(module_utils/instance/lifecycle.py)) - a run borrows an instance, and
    after it the instance is restarted clean and ready before it is free again, one at a time; one that does not come
    back is not lent again. An instance that another suite or run holds is waited for, up to the run's timeout;
    no restart ever touches an instance lent to another run.
  - One run failing, hanging (it ends at its own timeout) or not starting never stops the others.
  - Use C(async) - a suite takes as long as its runs.
author: isaacsim.fleet contributors (@isaacsim-fleet)
options:
  runs:
    description:
      - The runs, each with C(key) (short, unique), C(title), C(experience) (name), C(compose) (parsed),
        C(environment), C(profiles), C(timeout), C(gpus) (count), C(simulator) (bool, borrows) and C(dedicated)
        (bool, a simulator of its own, as M(isaacsim.fleet.isaac_sim_experience) starts one with
        O(isaacsim.fleet.isaac_sim_experience#module:simulator=dedicated)), as the suite filter makes them.
    type: list
    elements: dict
    required: true
  parallel:
    description: Runs at once on this host.
    type: int
    default: 2
  instances:
    description: The instances of this host that runs may borrow.
    type: list
    elements: int
    default: []
  gpus:
    description: The host's GPU ids that runs may reserve.
    type: list
    elements: str
    default: []
  data_root:
    description: Where runs keep their directories.
    type: path
    default: /var/lib/isaac-sim
  unfetched_after:
    description:
      - Seconds a finished run's directory waits for the controller that started it; after that, the next run or
        suite on the host takes it and brings it back with its own (RV(recovered)).
    type: float
    default: 600
  keep_days:
    description: Days a run's directory stays on the host at most, fetched or not (RV(expired)); C(0) keeps them.
    type: float
    default: 14
notes:
  - Check mode reads every file and checks the images; nothing starts.
"""

EXAMPLES = r"""
- name: Run this host's share of the suite
  isaacsim.fleet.isaac_sim_test_suite:
    runs: "{{ my_share }}"
    parallel: 2
    instances: [0, 1]
  async: 7200
  poll: 5
"""

RETURN = r"""
results:
  description:
    - One per run, in the order given - C(title), C(key), C(run), C(host), C(verdict), C(services), C(metrics),
      C(directory), C(artefacts); C(error) when the run could not start, C(restart_error) when its borrowed
      instance did not come back.
  returned: always
  type: list
  elements: dict
bundle:
  description:
    - Every run's directory in one gzipped tar file on the host (a directory per run), with those of RV(recovered),
      to fetch at once; remove it, and then the directories in RV(directories), once the controller has it.
  returned: when the runs ran
  type: str
directories:
  description: The run directories RV(bundle) holds.
  returned: when the runs ran
  type: list
  elements: str
recovered:
  description: Earlier runs whose controller went away before bringing them back; they are in RV(bundle).
  returned: when the runs ran
  type: list
  elements: str
expired:
  description: Run directories (and bundles nobody fetched) removed because they were older than O(keep_days).
  returned: when the runs ran
  type: list
  elements: str
"""

import os
import secrets
import threading
import time

from ansible.module_utils.basic import AnsibleModule
from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib import gpu_usage, layout
from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib.docker_socket import DockerError, DockerSocket
from ansible_collections.isaacsim.fleet.plugins.module_utils.instance import hostprobe, lifecycle
from ansible_collections.isaacsim.fleet.plugins.module_utils.runs import experience, run_store, testrun

KEEP = ("title", "key", "experience", "timeout")


def main():
    module = AnsibleModule(
        argument_spec={
            "runs": {"type": "list", "elements": "dict", "required": True},
            "parallel": {"type": "int", "default": 2},
            "instances": {"type": "list", "elements": "int", "default": []},
            "gpus": {"type": "list", "elements": "str", "default": []},
            "data_root": {"type": "path", "default": layout.DATA_ROOT},
            "unfetched_after": {"type": "float", "default": 600},
            "keep_days": {"type": "float", "default": 14},
        },
        supports_check_mode=True,
    )
    p = module.params
    if p["parallel"] < 1:
        module.fail_json(msg=f"parallel: {p['parallel']}. Fix: 1 or more runs at once.")
    store_errors = testrun.store_errors(p["unfetched_after"], p["keep_days"])
    if store_errors:
        module.fail_json(msg=" ".join(store_errors), errors=store_errors)
    host = lifecycle.bind(module)
    api = DockerSocket()
    hostname = os.uname().nodename
    read, errors = [], []
    for run in p["runs"]:
        exp, exp_errors, _warnings = experience.read(
            run["compose"], run.get("environment") or {}, run.get("profiles") or [], run["experience"]
        )
        errors += exp_errors
        read.append(exp)

    if errors:
        module.fail_json(msg=" ".join(errors), errors=errors)

    pull = testrun.puller(host, enabled=not module.check_mode)

    # an image that cannot be had fails the runs that need it, not the host's whole share
    unusable = {}
    try:
        for image in sorted({i for exp in read for i in exp["images"]}):
            found = testrun.preflight(api, {"name": image, "images": [image], "gpus": 0, "services": {}}, [], pull)
            if found:
                unusable[image] = found[0]
    except DockerError as exc:
        module.fail_json(msg=f"Docker cannot be asked about the images: {exc}")
    if module.check_mode:
        module.exit_json(changed=bool(p["runs"]), results=[], errors=list(unusable.values()))
    companions = hostprobe.existing_companions(layout.CONFIG_DIR)
    # runs with a simulator of their own: the host's image, release and limits, one GPU where it has any
    own, own_errors = None, []
    if any(run.get("dedicated") for run in p["runs"]):
        host_gpus, _why = gpu_usage.count_on(module)
        own, own_errors = testrun.dedicated_settings(
            None, None, testrun.deployed_simulator(host.read), None, p["gpus"], host_gpus
        )
    # runs whose runner was killed: torn down, their instances back clean, then free
    lent_out, ended = testrun.sweep(host, testrun.cli(host), lambda pid: os.path.exists(f"/proc/{pid}"))
    for i, gone in lent_out:
        lifecycle.give_back(host, i, gone, companions=companions)
    # runs no controller brought back go with this share; what is past retention goes
    store = os.path.join(p["data_root"], "runs")
    recovered, expired = run_store.take(
        store, testrun.live_runs(host), time.time(), p["unfetched_after"], p["keep_days"], host.remove, ended
    )
    if expired:
        module.warn(f"removed from {store}, older than keep_days ({p['keep_days']:g}): {', '.join(expired)}")
    # one give-back at a time: each restart ends ready before the next begins
    restart_lock = threading.Lock()

    def execute_one(run, instance, gpu_ids):
        exp = read[run["_index"]]
        missing = [unusable[i] for i in exp["images"] if i in unusable]
        if missing:
            return dict({k: run[k] for k in KEEP}, host=hostname, error=" ".join(missing))
        run_id = testrun.run_id(run["key"], time.strftime("%Y%m%d-%H%M%S"), secrets.token_hex(2))
        simulator = None
        if run.get("dedicated"):
            if own is None:
                return dict({k: run[k] for k in KEEP}, host=hostname, error=" ".join(own_errors))
            exp, simulator, error = testrun.own_simulator(host, run_id, exp, own, p["data_root"], float(run["timeout"]))
            if error:
                return dict({k: run[k] for k in KEEP}, host=hostname, error=error)
        elif exp["simulator"]:
            # another suite's or run's loan is waited out, up to the run's own timeout
            holder = lifecycle.lend(
                host, instance, run_id, wait_s=float(run["timeout"]), pid=os.getpid(), companions=companions
            )
            if holder:
                return dict(
                    {k: run[k] for k in KEEP},
                    host=hostname,
                    error=f"isaac-sim@{instance} stayed lent to {holder} for the run's whole timeout",
                )
            simulator, error = testrun.borrowed(host, exp["simulator"], instance, os.path.exists)
            if error:
                lifecycle.unlend(host, instance, run_id)
                return dict({k: run[k] for k in KEEP}, host=hostname, error=error)
        restart_error = None
        try:
            result = testrun.execute(
                host,
                api,
                exp,
                run_id,
                hostname=hostname,
                timeout=float(run["timeout"]),
                data_root=p["data_root"],
                simulator=simulator,
                gpus_free=gpu_ids,
                pid=os.getpid(),
            )
        finally:
            testrun.give_back(host, simulator)
            if simulator and simulator.get("instance") is not None:
                with restart_lock:
                    restart_error = lifecycle.give_back(host, instance, run_id, companions=companions)
        result.pop("orchestrator_output", None)
        result.update({k: run[k] for k in KEEP})
        if instance is not None:
            result["instance"] = instance
        if restart_error:
            result["restart_error"] = f"isaac-sim@{instance} did not come back: {restart_error}"
        return result

    def gpus_of(n, run):
        """GPUs a run reserves: its services', and its own simulator's."""
        if run.get("dedicated") and own:
            return testrun.dedicate(read[n], cache="", start_period=1, **own)[0]["gpus"]
        return read[n]["gpus"]

    runs = [
        dict(run, _index=n, gpus=gpus_of(n, run), simulator=bool(read[n]["simulator"]) and not run.get("dedicated"))
        for n, run in enumerate(p["runs"])
    ]
    results = testrun.run_queue(runs, p["parallel"], p["instances"], p["gpus"], execute_one, threading)
    for n, result in enumerate(results):
        if "error" in result and "run" not in result:
            results[n] = dict({k: runs[n][k] for k in KEEP}, host=hostname, error=result["error"])
    # every run's directory in one file: one fetch per host, not one per artefact; the directories
    # stay until the controller has it (one that dies first leaves them to the host's next run)
    ran = [result["run"] for result in results if result.get("directory") and os.path.isdir(result["directory"])]
    bundle, packed = run_store.pack(store, ran + recovered)
    module.exit_json(
        changed=True,
        results=results,
        bundle=bundle,
        directories=[os.path.join(store, name) for name in packed],
        recovered=recovered,
        expired=expired,
    )


if __name__ == "__main__":
    main()
