# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""A suite of experiences over the fleet: the runs it makes, which host takes each, and the
suite's results (a table and one JUnit file).

A suite lists experiences, each with repeats and parameter sets; every (parameters, repeat)
pair is one run. Runs are spread over the hosts before anything starts, each to a host that can
give it what it needs (GPUs, an instance to borrow), the least loaded first; each host then
runs its share with at most `parallel` runs at a time (testrun.execute per run). A run that
fails or hangs ends on its own verdict or timeout and never holds up another host. Pure.
"""

from __future__ import annotations

import os
import re

from ansible_collections.isaacsim.fleet.plugins.module_utils.runs import experience, judge
from ansible_collections.isaacsim.fleet.plugins.module_utils.runs import junit as junit_xml

KEYS = {"file", "name", "repeat", "environment", "parameters", "profiles", "timeout", "simulator"}
SIMULATOR_MODES = ("borrow", "dedicated")
_SLUG = re.compile(r"[^a-z0-9]+")


def expand(suite, base_dir: str, load, default_timeout: float = 600, allowed=()) -> tuple:
    """([run], errors) for a suite ({"experiences": [...], "environment": {...} for every run,
    "timeout": default seconds}, as parsed). load(path) -> parsed
    compose file, or raises OSError / ValueError. Every file is read as the fleet runs it, so
    a suite with one bad file stops before any run starts."""
    errors, runs = [], []
    entries = suite.get("experiences") if isinstance(suite, dict) else None
    if not isinstance(entries, list) or not entries:
        return [], ["test_suite: no experiences. Fix: give a list under experiences, each with a file."]
    for key in sorted(set(suite) - {"experiences", "environment", "timeout"}):
        errors.append(f"test_suite: {key} is not a setting of a suite. Fix: experiences, environment or timeout.")
    given_timeout = default_timeout
    try:
        default_timeout = float(default_timeout)
    except (TypeError, ValueError):
        default_timeout = 0
    if default_timeout <= 0:
        # said once, here: not as a wrong timeout of each entry that has none of its own
        errors.append(f"test_suite.timeout: {given_timeout!r}. Fix: a number of seconds above 0.")
    names = set()
    for n, entry in enumerate(entries):
        where = f"test_suite.experiences[{n}]"
        if isinstance(entry, str):
            entry = {"file": entry}
        if not isinstance(entry, dict) or not entry.get("file"):
            errors.append(f"{where}: needs file (the compose file). Fix: - file: experiences/pick.yml")
            continue
        for key in sorted(set(entry) - KEYS):
            errors.append(f"{where}.{key}: not a setting of a suite entry. Fix: one of {', '.join(sorted(KEYS))}.")
        path = entry["file"] if os.path.isabs(entry["file"]) else os.path.join(base_dir, entry["file"])
        name = str(entry.get("name") or os.path.splitext(os.path.basename(path))[0])
        if name in names:
            errors.append(f"{where}.name: {name} is used twice. Fix: give one entry another name.")
        names.add(name)
        try:
            compose = load(path)
        except (OSError, ValueError) as exc:
            errors.append(f"{where}.file: {path} cannot be read ({exc}). Fix: correct the path.")
            continue
        repeat = entry.get("repeat", 1)
        if not str(repeat).isdigit() or int(str(repeat)) < 1:
            errors.append(f"{where}.repeat: {repeat!r}. Fix: a whole number, 1 or more.")
            continue
        timeout = entry.get("timeout", default_timeout)
        try:
            timeout = float(timeout)
        except (TypeError, ValueError):
            timeout = 0
        if timeout <= 0:
            if "timeout" in entry:
                errors.append(f"{where}.timeout: {entry['timeout']!r}. Fix: a number of seconds above 0.")
            continue
        mode = entry.get("simulator", "borrow")
        if mode not in SIMULATOR_MODES:
            errors.append(f"{where}.simulator: {mode!r}. Fix: borrow (an instance of the fleet) or dedicated.")
            continue
        params = entry.get("parameters") or [{}]
        if not isinstance(params, list) or not all(isinstance(p, dict) for p in params):
            errors.append(f"{where}.parameters: must be a list of mappings (one run each). Fix: - {{SCENE: office}}")
            continue
        base_env = {str(k): str(v) for k, v in (suite.get("environment") or {}).items()}
        base_env.update({str(k): str(v) for k, v in (entry.get("environment") or {}).items()})
        profiles = [str(p) for p in entry.get("profiles") or []]
        for p_index, param in enumerate(params):
            env = dict(base_env, **{str(k): str(v) for k, v in param.items()})
            exp, exp_errors, _warnings = experience.read(
                compose, env, profiles, name, allowed=allowed, allow_var=experience.SUITE_ALLOW_VAR
            )
            if exp_errors:
                errors += [f"{where} ({path}): {e}" for e in exp_errors]
                break
            label = ",".join(f"{k}={v}" for k, v in sorted(param.items()))
            for r in range(int(str(repeat))):
                title = name + (f"[{label}]" if label else "") + (f"#{r + 1}" if int(str(repeat)) > 1 else "")
                runs.append(
                    {
                        "key": f"{_SLUG.sub('-', name.lower()).strip('-')[:24] or 'run'}-{p_index + 1}-{r + 1}",
                        "title": title,
                        "experience": name,
                        "file": path,
                        "compose": compose,
                        "environment": env,
                        "profiles": profiles,
                        "timeout": timeout,
                        "gpus": exp["gpus"],
                        # borrows an instance; a dedicated one runs as a service of its own
                        "simulator": exp["simulator"] is not None and mode == "borrow",
                        "dedicated": exp["simulator"] is not None and mode == "dedicated",
                    }
                )
    return runs, errors


def outcome(result: dict) -> str:
    """A run's result word: its verdict's, or error when it had none (it could not start)."""
    return (result.get("verdict") or {}).get("result") or judge.ERROR


def select_failed(runs: list, previous: list) -> list:
    """The runs that ran in the previous suite (its results) and did not pass."""
    before = {r["title"]: outcome(r) for r in previous}
    return [r for r in runs if r["title"] in before and before[r["title"]] != judge.PASSED]


def merge(previous: list, results: list) -> list:
    """The suite's results after a re-run: the new result of each run that ran again, the
    previous one of every other."""
    again = {r["title"] for r in results}
    return [r for r in previous if r["title"] not in again] + list(results)


def assign(runs: list, hosts: dict) -> tuple:
    """({host: [run]}, errors): each run to a host that can take it, the least loaded first.

    hosts: {host: {"parallel": n, "gpus": count, "instances": ready instances to lend}}.
    """
    plan = {h: [] for h in hosts}
    errors = []
    for run in runs:
        able = [
            h
            for h, cap in hosts.items()
            if cap["parallel"] > 0 and cap["gpus"] >= run["gpus"] and (not run["simulator"] or cap["instances"] > 0)
        ]
        if not able:
            need = []
            if run["gpus"]:
                most = max((c["gpus"] for c in hosts.values()), default=0)
                need.append(f"{run['gpus']} GPU(s) (the most any host has is {most})")
            if run["simulator"]:
                need.append("a ready instance to borrow")
            errors.append(
                f"{run['title']}: no host can give it {' and '.join(need) or 'a slot'}. Fix: ask for less, or add "
                "hosts that have it."
            )
            continue
        # the host whose queue ends soonest, by runs per slot; ties by host name
        best = min(able, key=lambda h: (len(plan[h]) / _slots(hosts[h], run), h))
        plan[best].append(run)
    return plan, errors


def _slots(cap: dict, run: dict) -> int:
    """Runs a host takes at once for this kind of run: its parallel, and no more instances than it lends."""
    return max(1, min(cap["parallel"], cap["instances"]) if run["simulator"] else cap["parallel"])


def with_missing(results: list, plan: dict, why: dict) -> list:
    """The results, with an error result for every planned run that has none (its host's share
    did not run): a suite never reports fewer runs than it planned."""
    have = {r["title"] for r in results}
    out = list(results)
    for host, runs in plan.items():
        for run in runs:
            if run["title"] not in have:
                reason = why.get(host) or "no result came back"
                out.append({"title": run["title"], "key": run.get("key"), "host": host, "error": f"{host}: {reason}"})
    return out


def verdict_of(result: dict) -> dict:
    """A run's verdict; a run that had none (it could not start, its host did not answer) is an
    error with the reason it gave."""
    return result.get("verdict") or {"result": judge.ERROR, "reason": result.get("error", "no verdict"), "seconds": 0}


def junit(results: list) -> str:
    """One JUnit file for the suite: a test case per run (junit's rule)."""
    cases = []
    for r in results:
        output = None
        if r.get("run"):
            output = "run " + r["run"] + " on " + str(r.get("host"))
        elif r.get("error"):
            output = str(r["error"])
        cases.append({"host": r.get("host"), "name": r["title"], "verdict": verdict_of(r), "output": output})
    return junit_xml.testsuite("isaacsim.fleet test suite", cases)


def summary_lines(results: list, wall: float | None = None) -> list:
    """The suite for a person: one line per run, then the totals."""
    lines = [f"{'run':<40} {'host':<20} {'result':<8} {'seconds':>8}  reason"]
    counts = {}
    for r in sorted(results, key=lambda r: r["title"]):
        v = verdict_of(r)
        if r.get("restart_error"):
            v = dict(v, reason=f"{v['reason']}; {r['restart_error']}")
        counts[v["result"]] = counts.get(v["result"], 0) + 1
        lines.append(f"{r['title']:<40} {str(r.get('host')):<20} {v['result']:<8} {v['seconds']:>8.1f}  {v['reason']}")
    totals = ", ".join(f"{counts[k]} {k}" for k in sorted(counts))
    lines.append(f"{len(results)} runs: {totals}" + (f" in {wall:.1f} s" if wall is not None else ""))
    return lines
