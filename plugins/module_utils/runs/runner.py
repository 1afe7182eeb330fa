# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""What the two run modules do on their host: one experience to its verdict
(Runner.experience, for isaac_sim_experience) and a host's share of a suite (Runner.share,
for isaac_sim_test_suite).

Each checks what it was given, tidies what earlier runs left (runs whose runner was killed,
runs no controller fetched, runs past retention), borrows or starts the simulator, runs
through testrun.execute, gives a borrowed instance back through the lifecycle and packs the
runs' directories into one bundle. The host is a Runner: lifecycle.Host (commands, files,
clock), a Docker API client and the little else a module knows (its host name, its pid, the
GPU count, warnings, check mode), so the unit tests drive it with scripted ones.

Both return the module's result; one with "failed" set is the module's failure (its "msg" and
the rest as fail_json takes them).
"""

from __future__ import annotations

import os
import secrets
import threading
import time

from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib import gpu_usage, layout
from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib.docker_socket import DockerError, DockerSocket
from ansible_collections.isaacsim.fleet.plugins.module_utils.instance import hostprobe, lifecycle
from ansible_collections.isaacsim.fleet.plugins.module_utils.runs import experience, run_store, testrun

# what a suite's result keeps of its run, whatever became of it
KEEP = ("title", "key", "experience", "timeout")
# the options a run and a suite share: the host's GPUs to reserve from and where runs keep their directories
HOST_OPTIONS = {
    "gpus": {"type": "list", "elements": "str", "default": []},
    "data_root": {"type": "path", "default": layout.DATA_ROOT},
    "unfetched_after": {"type": "float", "default": 600},
    "keep_days": {"type": "float", "default": 14},
    "allowed_docker_args": {"type": "list", "elements": "str", "default": []},
}


class _FailError(Exception):
    """The module fails with this result (taken when raised: what comes later is not in it)."""

    def __init__(self, msg: str, **result):
        super().__init__(msg)
        self.result = dict(result, msg=msg, failed=True)


def _errors(errors: list, **result):
    if errors:
        raise _FailError(" ".join(errors), errors=errors, **result)


def stamped_run_id(name: str) -> str:
    """A new run's name: the experience's (or suite key's), the time and a random token."""
    return testrun.run_id(name, time.strftime("%Y%m%d-%H%M%S"), secrets.token_hex(2))


class Runner:
    """The host as a run module sees it.

    host: lifecycle.Host; api: the Docker API client (image, labelled, stats); gpu_count() ->
    (GPUs of the host, why none); warn(text); companions() -> {instance: [companion]} of the
    host's instances; new_run(name) -> a new run's name; wall() epoch seconds.
    """

    def __init__(
        self,
        host,
        api,
        *,
        hostname: str,
        pid: int,
        gpu_count,
        warn,
        check_mode: bool = False,
        companions=None,
        new_run=stamped_run_id,
        wall=time.time,
    ):
        self.host, self.api, self.hostname, self.pid = host, api, hostname, pid
        self.gpu_count, self.warn, self.check_mode = gpu_count, warn, check_mode
        self.companions = companions or (lambda: hostprobe.existing_companions(layout.CONFIG_DIR))
        self.new_run, self.wall = new_run, wall

    def alive(self, pid) -> bool:
        return self.host.exists(f"/proc/{pid}")

    def tidy(self, store: str, unfetched_after: float, keep_days: float, companions: dict) -> tuple:
        """(recovered, expired): runs whose runner was killed torn down, their instances back
        clean, then free (through the lifecycle); runs no controller brought back taken for this
        one's bundle; what is past retention removed, with a warning naming it."""
        host = self.host
        lent_out, ended = testrun.sweep(host, testrun.cli(host), self.alive)
        for i, gone in lent_out:
            lifecycle.give_back(host, i, gone, companions=companions)
        recovered, expired = run_store.take(
            store, testrun.live_runs(host), self.wall(), unfetched_after, keep_days, host.remove, ended
        )
        if expired:
            self.warn(f"removed from {store}, older than keep_days ({keep_days:g}): {', '.join(expired)}")
        return recovered, expired

    # one experience (isaac_sim_experience)

    def experience(self, p: dict) -> dict:
        """isaac_sim_experience's result for its parameters p."""
        try:
            return self._experience(p)
        except _FailError as failed:
            return failed.result

    def _borrowed(self, exp: dict, instance, simulator_mode: str, lent_to=None):
        """What the services are given of the borrowed instance; fails when it cannot be lent
        (and ends the loan `lent_to` holds: nothing ran on it)."""
        if exp["simulator"] is None or simulator_mode == "dedicated":
            return None
        if instance is None:
            raise _FailError(
                f"{exp['name']}: service {exp['simulator']} is the simulator (image: isaac-sim), and no instance was "
                "given to borrow. Fix: set instance (experience_instance) to a ready instance of the host."
            )
        host = self.host
        # another run has it (it may be restarting on its way back): readiness is asked once lent
        held = not lent_to and lifecycle.lent_to(host, instance) is not None
        simulator, error = testrun.borrowed(host, exp["simulator"], instance, lambda path: held or host.exists(path))
        if error:
            if lent_to:
                lifecycle.unlend(host, instance, lent_to)
            raise _FailError(error)
        return simulator

    def _dedicated(self, p: dict, exp: dict) -> tuple:
        """({image, release, gpu, limits}, errors) for a run with a simulator of its own; None when
        the run borrows (or has no simulator)."""
        if exp["simulator"] is None or p["simulator"] != "dedicated":
            return None, []
        host_gpus, why = self.gpu_count()
        settings, errors = testrun.dedicated_settings(
            p["simulator_image"],
            p["simulator_release"],
            testrun.deployed_simulator(self.host.read),
            p["instance"],
            p["gpus"],
            host_gpus,
        )
        if settings and not settings["gpu"]:
            self.warn(
                f"{exp['name']}: this host has no GPU ({why}); the dedicated simulator runs without one, which only a "
                "stand-in image can."
            )
        return settings, errors

    def _checked(self, p: dict) -> tuple:
        """(experience as read, run name, result so far): what was given, checked; fails on an error."""
        env = dict(p["environment"], **p["secret_environment"])
        exp, errors, warnings = experience.read(
            p["compose"],
            env,
            p["profiles"],
            p["name"],
            p["secret_environment"],
            allowed=p.get("allowed_docker_args") or (),
        )
        run = p["run"] or self.new_run(p["name"])
        if not layout.RUN_ID_RE.match(run):
            errors.append(f"run: {run!r} is not a run name. Fix: lower case letters, digits and dashes, 63 at most.")
        if p["timeout"] <= 0:
            errors.append(f"timeout: {p['timeout']:g}. Fix: a number of seconds above 0.")
        errors += testrun.store_errors(p["unfetched_after"], p["keep_days"])
        for warning in warnings:
            self.warn(warning)
        base = {
            "run": run,
            "directory": layout.run_dir(run, p["data_root"]),
            "ignored": warnings,
            "borrowed_instance": None,
            "recovered": [],
            "expired": [],
        }
        _errors(errors, **base)
        return exp, run, base

    def _experience(self, p: dict) -> dict:
        host = self.host
        exp, run, base = self._checked(p)
        pull = testrun.puller(host, enabled=p["pull"] and not self.check_mode)
        dedicated, errors = self._dedicated(p, exp)
        _errors(errors, **base)
        read = exp
        if dedicated:
            # the slot is taken once nothing stops the run; its directory does not change what is checked
            exp, _given = testrun.dedicate(
                read, cache=testrun.slot_dir(0, p["data_root"]), start_period=p["timeout"], **dedicated
            )
        try:
            errors = testrun.preflight(self.api, exp, p["gpus"], pull)
        except DockerError as exc:
            raise _FailError(f"Docker cannot be asked about the images: {exc}", **base) from exc
        _errors(errors, **base)
        simulator = self._borrowed(exp, p["instance"], p["simulator"])
        if self.check_mode:
            return dict(changed=True, order=exp["order"], **base)
        companions = self.companions()
        store = os.path.join(p["data_root"], "runs")
        base["recovered"], base["expired"] = self.tidy(store, p["unfetched_after"], p["keep_days"], companions)
        lent = simulator and simulator["instance"] is not None
        if lent:
            # another run's loan is waited out, up to this run's timeout
            try:
                holder = lifecycle.lend(
                    host, simulator["instance"], run, wait_s=p["timeout"], pid=self.pid, companions=companions
                )
            except lifecycle.DrainedError as exc:
                raise _FailError(f"instance: {exc}", **base) from exc
            if holder:
                raise _FailError(
                    f"instance: isaac-sim@{simulator['instance']} stayed lent to run {holder} for this run's whole "
                    f"timeout ({p['timeout']:g} s). Fix: pick a free one, or a longer timeout.",
                    **base,
                )
            # lent only once ready: a run waited for may have found it restarting
            simulator = self._borrowed(exp, p["instance"], p["simulator"], lent_to=run)
            base["borrowed_instance"] = simulator["instance"]
        if dedicated:
            exp, simulator, error = testrun.own_simulator(host, run, read, dedicated, p["data_root"], p["timeout"])
            if error:
                raise _FailError(error, **base)
            base["simulator_slot"] = simulator["slot"]
        try:
            result = testrun.execute(
                host,
                self.api,
                exp,
                run,
                hostname=self.hostname,
                timeout=p["timeout"],
                data_root=p["data_root"],
                simulator=simulator,
                gpus_free=p["gpus"],
                poll=p["poll"],
                metrics_every=p["metrics_interval"],
                pid=self.pid,
                secret_keys=set(exp["secret_keys"]),
            )
        except (RuntimeError, DockerError) as exc:
            raise _FailError(f"run {run} could not start: {exc}. Nothing of it is left on the host.", **base) from exc
        finally:
            testrun.give_back(host, simulator)
            # restarted clean and ready, then free: here, on the host, so a controller that is gone
            # (or an Ansible task that never comes) cannot leave the next run a used instance
            if lent:
                error = lifecycle.give_back(host, simulator["instance"], run, companions=companions)
                if error:
                    base["restart_error"] = f"isaac-sim@{simulator['instance']} did not come back: {error}"
        result.pop("orchestrator_output", None)
        base.update(result)
        base["bundle"], packed = run_store.pack(store, [run] + base["recovered"])
        base["directories"] = [os.path.join(store, name) for name in packed]
        return dict(changed=True, **base)

    # a host's share of a suite (isaac_sim_test_suite)

    def share(self, p: dict) -> dict:
        """isaac_sim_test_suite's result for its parameters p."""
        try:
            return _Share(self, p).run()
        except _FailError as failed:
            return failed.result


class _Share:
    """One host's share of a suite: its runs read and checked, then run at most p["parallel"] at
    once (testrun.run_queue), each borrowing, running and giving back through execute_one."""

    def __init__(self, runner: Runner, p: dict):
        self.runner, self.host, self.p = runner, runner.host, p
        self.read = []  # each run's experience, as read
        self.unusable = {}  # image: why it cannot be had
        self.own, self.own_errors = None, []  # a dedicated simulator's settings, or why there are none
        self.companions = {}
        # one give-back at a time: each restart ends ready before the next begins
        self.restart_lock = threading.Lock()

    def _failed(self, run: dict, error: str) -> dict:
        return dict({k: run[k] for k in KEEP}, host=self.runner.hostname, error=error)

    def _check(self):
        p = self.p
        if p["parallel"] < 1:
            raise _FailError(f"parallel: {p['parallel']}. Fix: 1 or more runs at once.")
        _errors(testrun.store_errors(p["unfetched_after"], p["keep_days"]))
        errors = []
        for run in p["runs"]:
            exp, exp_errors, _warnings = experience.read(
                run["compose"],
                run.get("environment") or {},
                run.get("profiles") or [],
                run["experience"],
                allowed=p.get("allowed_docker_args") or (),
                allow_var=experience.SUITE_ALLOW_VAR,
            )
            errors += exp_errors
            self.read.append(exp)
        _errors(errors)

    def _images(self):
        """An image that cannot be had fails the runs that need it, not the host's whole share."""
        pull = testrun.puller(self.host, enabled=not self.runner.check_mode)
        try:
            for image in sorted({i for exp in self.read for i in exp["images"]}):
                found = testrun.preflight(
                    self.runner.api, {"name": image, "images": [image], "gpus": 0, "services": {}}, [], pull
                )
                if found:
                    self.unusable[image] = found[0]
        except DockerError as exc:
            raise _FailError(f"Docker cannot be asked about the images: {exc}") from exc

    def run(self) -> dict:
        p, runner = self.p, self.runner
        self._check()
        self._images()
        if runner.check_mode:
            return dict(changed=bool(p["runs"]), results=[], errors=list(self.unusable.values()))
        self.companions = runner.companions()
        # runs with a simulator of their own: the host's image, release and limits, one GPU where it has any
        if any(run.get("dedicated") for run in p["runs"]):
            host_gpus, _why = runner.gpu_count()
            self.own, self.own_errors = testrun.dedicated_settings(
                None, None, testrun.deployed_simulator(self.host.read), None, p["gpus"], host_gpus
            )
        store = os.path.join(p["data_root"], "runs")
        recovered, expired = runner.tidy(store, p["unfetched_after"], p["keep_days"], self.companions)
        runs = [
            dict(
                run,
                _index=n,
                gpus=self._gpus_of(n, run),
                simulator=bool(self.read[n]["simulator"]) and not run.get("dedicated"),
            )
            for n, run in enumerate(p["runs"])
        ]
        # an instance a session or another suite holds is taken last: its claim is waited out only where none is free
        results = testrun.run_queue(
            runs,
            p["parallel"],
            p["instances"],
            p["gpus"],
            self.execute_one,
            threading,
            held=lambda i: lifecycle.lent_to(self.host, i) is not None,
        )
        for n, result in enumerate(results):
            if "error" in result and "run" not in result:
                results[n] = self._failed(runs[n], result["error"])
        # every run's directory in one file: one fetch per host, not one per artefact; the directories
        # stay until the controller has it (one that dies first leaves them to the host's next run)
        ran = [r["run"] for r in results if r.get("directory") and os.path.isdir(r["directory"])]
        bundle, packed = run_store.pack(store, ran + recovered)
        return dict(
            changed=True,
            results=results,
            bundle=bundle,
            directories=[os.path.join(store, name) for name in packed],
            recovered=recovered,
            expired=expired,
        )

    def _gpus_of(self, n: int, run: dict) -> int:
        """GPUs a run reserves: its services', and its own simulator's."""
        if run.get("dedicated") and self.own:
            return testrun.dedicate(self.read[n], cache="", start_period=1, **self.own)[0]["gpus"]
        return self.read[n]["gpus"]

    def _simulator(self, run: dict, exp: dict, run_id: str, instance):
        """(experience, simulator, error): the run's own simulator started, or an instance lent to
        it; error None when the run can go on."""
        host, p = self.host, self.p
        if run.get("dedicated"):
            if self.own is None:
                return exp, None, " ".join(self.own_errors)
            return testrun.own_simulator(host, run_id, exp, self.own, p["data_root"], float(run["timeout"]))
        if not exp["simulator"]:
            return exp, None, None
        # another suite's or run's loan is waited out, up to the run's own timeout
        try:
            holder = lifecycle.lend(
                host, instance, run_id, wait_s=float(run["timeout"]), pid=self.runner.pid, companions=self.companions
            )
        except lifecycle.DrainedError as exc:
            return exp, None, str(exc)
        if holder:
            return exp, None, f"isaac-sim@{instance} stayed lent to {holder} for the run's whole timeout"
        simulator, error = testrun.borrowed(host, exp["simulator"], instance, host.exists)
        if error:
            lifecycle.unlend(host, instance, run_id)
        return exp, simulator, error

    def execute_one(self, run: dict, instance, gpu_ids) -> dict:
        """One run of the share: its simulator, the run, the instance given back; its result."""
        host = self.host
        exp = self.read[run["_index"]]
        missing = [self.unusable[i] for i in exp["images"] if i in self.unusable]
        if missing:
            return self._failed(run, " ".join(missing))
        run_id = self.runner.new_run(run["key"])
        exp, simulator, error = self._simulator(run, exp, run_id, instance)
        if error is not None:
            return self._failed(run, error)
        restart_error = None
        try:
            result = testrun.execute(
                host,
                self.runner.api,
                exp,
                run_id,
                hostname=self.runner.hostname,
                timeout=float(run["timeout"]),
                data_root=self.p["data_root"],
                simulator=simulator,
                gpus_free=gpu_ids,
                pid=self.runner.pid,
            )
        finally:
            testrun.give_back(host, simulator)
            if simulator and simulator.get("instance") is not None:
                with self.restart_lock:
                    restart_error = lifecycle.give_back(host, instance, run_id, companions=self.companions)
        result.pop("orchestrator_output", None)
        result.update({k: run[k] for k in KEEP})
        if instance is not None:
            result["instance"] = instance
        if restart_error:
            result["restart_error"] = f"isaac-sim@{instance} did not come back: {restart_error}"
        return result


def bind(module) -> Runner:
    """The real host, for a module running on it."""
    return Runner(
        lifecycle.bind(module),
        DockerSocket(),
        hostname=os.uname().nodename,
        pid=os.getpid(),
        gpu_count=lambda: gpu_usage.count_on(module),
        warn=module.warn,
        check_mode=module.check_mode,
    )


def finish(module, result: dict):
    """End the module with the result Runner gave: its failure, or its exit."""
    if result.pop("failed", False):
        module.fail_json(**result)
    module.exit_json(**result)
