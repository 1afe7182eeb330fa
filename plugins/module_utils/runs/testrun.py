# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""One test run of an experience on one host, from start to verdict to clean host.

The engine is systemd: each service of the experience becomes a unit in /run/systemd/system
whose ExecStart is the service's `docker run` in the foreground, so systemd restarts it (by
the compose restart policy), the journal keeps its log and `systemctl stop` stops it. The
run gets its own bridge network (services reach each other by service name) and its own
named volumes. The judge (judge.py) decides the verdict from what the units do; this module
starts the units the judge names, samples CPU and memory through Docker's stats, and after
the verdict stops every container and removes the units, the network and the volumes,
keeping the logs, exit codes, metrics and a JUnit file in the run's directory.

The host is reached through lifecycle.Host (run, read, write, remove, ...) and a Docker API
client (get), so the unit tests drive it with scripted ones.
"""

from __future__ import annotations

import json
import math
import re
import signal

from ansible_collections.isaacsim.fleet.plugins.module_utils.common import parse, sandbox, units
from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib import fleet_status, layout
from ansible_collections.isaacsim.fleet.plugins.module_utils.instance import hostprobe, lifecycle, releases
from ansible_collections.isaacsim.fleet.plugins.module_utils.runs import judge
from ansible_collections.isaacsim.fleet.plugins.module_utils.runs import junit as junit_xml

DOCKER = "/usr/bin/docker"
PROPS = "Id,LoadState,ActiveState,SubState,NRestarts,Result,ExecMainCode,ExecMainStatus"
CLD_EXITED = "1"  # ExecMainCode: the main process exited (else it was killed: status is the signal)
_SLUG = re.compile(r"[^a-z0-9]+")


def run_id(name: str, stamp: str, token: str) -> str:
    """A run's name: the experience's, a time stamp and a random token (unit and Docker safe)."""
    slug = _SLUG.sub("-", name.lower()).strip("-")[:32].strip("-") or "run"
    return f"{slug}-{stamp}-{token}"


def systemd_quote(word: str) -> str:
    """One word of an ExecStart= line that systemd passes on exactly (specifiers and
    variables escaped, C escapes inside double quotes)."""
    text = str(word).replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n").replace("\t", "\\t")
    return '"' + text.replace("%", "%%").replace("$", "$$") + '"'


def service_env(run: str, svc: dict, simulator=None, gpus=()) -> dict:
    """The environment a service's container gets: the file's (with the experience's over it),
    the borrowed instance's address and ports, the run's name and outputs directory."""
    env = dict(svc["environment"])
    if simulator and svc.get("name") != simulator["service"]:
        env.update(simulator["env"])
    if not gpus:
        # a default nvidia runtime would otherwise show every GPU (the instances' too) to a CUDA image
        env.setdefault("NVIDIA_VISIBLE_DEVICES", "void")
    env[layout.K_RUN] = run
    env[layout.K_RUN_OUTPUTS] = layout.RUN_OUTPUTS
    return env


def env_file_text(env: dict) -> str:
    """Docker's --env-file format: KEY=VALUE a line, the value taken as it is (no quotes, no
    newlines: experience.read refuses those)."""
    return "".join(f"{k}={v}\n" for k, v in env.items())


def _ms(seconds) -> str:
    return f"{max(int(round(float(seconds) * 1000)), 0)}ms"


# a compose key given a value: docker run's flag, and the word it takes (in this order on the line)
_SET_FLAGS = (
    ("working_dir", "workdir", str),
    ("user", "user", str),
    ("shm_size", "shm-size", parse.docker_size),
    ("memory", "memory", parse.docker_size),
    ("cpus", "cpus", str),
)


def docker_argv(run: str, name: str, svc: dict, *, outputs: str, env_file: str, simulator=None, gpus=()) -> list:
    """The `docker run` of one service (foreground: the unit's main process is the container).

    env_file: the service's environment, in a file only root reads (values stay off command
    lines and unit files); simulator: {"service": name, "address": ..., "env": {...}} when the
    run borrows an instance (address None: a dedicated one, on the run's network); gpus: the
    host's GPU ids given to this service (dedicated).
    """
    container = layout.run_name(run, name)
    argv = [
        DOCKER,
        "run",
        f"--name={container}",
        f"--network={layout.run_name(run)}",
        f"--network-alias={name}",
        f"--hostname={name}",
        "--pull=never",
        f"--label={layout.LABEL_RUN}={run}",
        f"--label={layout.LABEL_RUN_SERVICE}={name}",
        f"--mount=type=bind,source={outputs},target={layout.RUN_OUTPUTS}",
    ]
    # what the operator allowed the service (experience_allowed_docker_args); no-new-privileges unless
    # that turns it off
    allowed = list(svc.get("docker_args") or [])
    if not any(a.startswith("--security-opt=no-new-privileges") for a in allowed):
        argv.append("--security-opt=no-new-privileges")
    argv += allowed
    for key, value in sorted((svc.get("labels") or {}).items()):
        argv.append(f"--label={key}={value}")
    if simulator and simulator.get("address") and name != simulator["service"]:
        argv.append(f"--add-host={simulator['service']}:{simulator['address']}")
    argv.append(f"--env-file={env_file}")
    argv += [f"--{flag}={word(svc[key])}" for key, flag, word in _SET_FLAGS if svc.get(key)]
    if svc.get("init"):
        argv.append("--init")
    if svc.get("stop_signal"):
        argv.append(f"--stop-signal={svc['stop_signal']}")
    argv.append(f"--stop-timeout={math.ceil(svc.get('stop_grace_period') or 10)}")
    if gpus:
        # the quotes keep the comma inside one --gpus value (Docker reads it as CSV)
        argv.append(f'--gpus="device={",".join(str(g) for g in gpus)}"')
    # a dedicated simulator's caches (never from the file: experience.read refuses host paths)
    argv += [f"--mount=type=bind,source={source},target={target}" for source, target in svc.get("binds", ())]
    for volume, target, read_only in svc["volumes"]:
        ro = ",readonly" if read_only else ""
        argv.append(f"--mount=type=volume,source={layout.run_volume(run, volume)},target={target}{ro}")
    argv += [f"--tmpfs={target}" for target in svc["tmpfs"]]
    health = svc.get("healthcheck")
    if health:
        argv += [
            f"--health-cmd={health['test']}",
            f"--health-interval={_ms(health['interval'])}",
            f"--health-timeout={_ms(health['timeout'])}",
            f"--health-retries={health['retries']}",
            f"--health-start-period={_ms(health['start_period'])}",
        ]
    entrypoint, command = svc.get("entrypoint"), svc.get("command") or []
    if entrypoint is not None:
        argv.append(f"--entrypoint={entrypoint[0] if entrypoint else ''}")
        return argv + [svc["image"]] + list(entrypoint[1:]) + list(command)
    return argv + [svc["image"]] + list(command)


def unit_text(run: str, name: str, svc: dict, argv: list) -> str:
    """The service's unit: systemd runs, restarts (compose's policy) and stops its container."""
    container = layout.run_name(run, name)
    grace = math.ceil(svc.get("stop_grace_period") or 10)
    limit = []
    if svc["restart"] == "no":
        restart = "no"
    else:
        # every policy restarts on failure only: a service may finish (exit 0) at any time
        retries = svc.get("restart_retries") or 0
        limit = (
            [("StartLimitIntervalSec", "1d"), ("StartLimitBurst", retries + 1)]
            if retries
            else [("StartLimitIntervalSec", 0)]
        )
        restart = "on-failure"
    service = [
        ("Type", "exec"),
        # -v: an image's own VOLUMEs (a database's data) go with their container
        ("ExecStartPre", f"-{DOCKER} rm -f -v {container}"),
        ("ExecStartPre", f"-/bin/rm -f {exit_file(run, name)}"),
        ("ExecStart", " ".join(systemd_quote(w) for w in argv)),
        ("ExecStop", f"-{DOCKER} stop --time={grace} {container}"),
        ("ExecStopPost", f"-{DOCKER} rm -f -v {container}"),
        # systemd gives ExecStopPost how the main process ended; kept past the unit's unloading
        ("ExecStopPost", f"-/bin/sh -c 'echo \"$$EXIT_CODE $$EXIT_STATUS\" > {exit_file(run, name)}'"),
        ("Restart", restart),
        ("RestartSec", 1),
        ("TimeoutStopSec", grace + 30),
        # the docker client only; the container is confined by experience.py's checks
        *sandbox.docker_client(),
    ]
    unit = [("Description", f"isaacsim.fleet test run {run}: service {name}")] + limit
    return units.render([("Unit", unit), ("Service", service)])


def runtime_file(run: str, service: str, kind: str) -> str:
    """A service's file in the run's runtime directory (/run: gone at reboot, as the run is)."""
    return f"{layout.RUN_DIR}/runs/{run}/{service}.{kind}"


def exit_file(run: str, service: str) -> str:
    """Where a service's unit writes how its last container ended: systemd forgets the exit
    status of a unit that ended well as soon as it unloads it (garbage collection)."""
    return runtime_file(run, service, "exit")


def parse_exit(text):
    """The exit code in an exit file ("exited 3", "killed TERM"), or None."""
    words = (text or "").split()
    if len(words) != 2:
        return None
    how, status = words
    if how == "exited" and status.isdigit():
        return int(status)
    if status.isdigit():
        return 128 + int(status)
    signum = getattr(signal, "SIG" + status, None)
    return 128 + int(signum) if signum is not None else None


def observe(shown: dict, containers: list, run: str, services, started, ran, exits=None, retries=None) -> dict:
    """{service: judge.observation} from `systemctl show` of the run's units, Docker's list of
    the run's containers and the units' exit files ({service: text}). started: services the
    runner started; ran: those seen running; retries: {service: compose's on-failure:N}."""
    exits = exits or {}
    retries = retries or {}
    by_service = {}
    for c in containers:
        svc = (c.get("Labels") or {}).get(layout.LABEL_RUN_SERVICE)
        if svc:
            by_service[svc] = c
    out = {}
    for name in services:
        props = shown.get(layout.run_unit(run, name)) or {}
        restarts = int(props.get("NRestarts") or 0)
        if retries.get(name):
            # systemd counts the restart its start limit refused too: on-failure:2 is 3 starts, 2 restarts
            restarts = min(restarts, retries[name])
        if name not in started:
            out[name] = judge.observation()
            continue
        state, sub = props.get("ActiveState", ""), props.get("SubState", "")
        code = parse_exit(exits.get(name))
        if code is None and props.get("ExecMainCode") not in (None, "", "0"):
            status = int(props.get("ExecMainStatus") or 0)
            code = status if props["ExecMainCode"] == CLD_EXITED else 128 + status
        container = by_service.get(name) or {}
        health = fleet_status.health_of(container.get("Status"))
        health = None if health == "none" else health
        if state == "activating" and sub.startswith("auto-restart"):
            obs = judge.observation(judge.RESTARTING, code, restarts, None, True)
        elif state in ("inactive", "failed", "") and code is not None:
            obs = judge.observation(judge.EXITED, code, restarts, None, True)
        elif state == "active" and container.get("State") == "running":
            ran.add(name)
            obs = judge.observation(judge.RUNNING, None, restarts, health, True)
        else:
            obs = judge.observation(judge.STARTING, None, restarts, None, name in ran)
        out[name] = obs
    return out


def stats_sample(stats: dict):
    """(cpu nanoseconds used so far, memory bytes in use) from Docker's stats of a container,
    memory counted as `docker stats` does (without the page cache it can drop)."""
    cpu = int(((stats.get("cpu_stats") or {}).get("cpu_usage") or {}).get("total_usage") or 0)
    memory = stats.get("memory_stats") or {}
    detail = memory.get("stats") or {}
    cache = detail.get("total_inactive_file", detail.get("inactive_file", 0)) or 0
    return cpu, max(int(memory.get("usage") or 0) - int(cache), 0)


class Metrics:
    """CPU (percent of one core, between samples) and memory per service over the run."""

    def __init__(self):
        self.rows = []  # [seconds, service, cpu percent, memory bytes]
        self._last = {}

    def add(self, seconds: float, service: str, cpu_ns: int, memory: int, container_id: str):
        last = self._last.get(service)
        self._last[service] = (seconds, cpu_ns, container_id)
        cpu = None
        if last and last[2] == container_id and seconds > last[0] and cpu_ns >= last[1]:
            cpu = round((cpu_ns - last[1]) / ((seconds - last[0]) * 1e9) * 100, 1)
        self.rows.append([round(seconds, 3), service, cpu, memory])

    def summary(self) -> dict:
        out = {}
        for _t, svc, cpu, mem in self.rows:
            s = out.setdefault(svc, {"samples": 0, "cpu_peak_percent": 0.0, "memory_peak_bytes": 0, "_cpu": []})
            s["samples"] += 1
            s["memory_peak_bytes"] = max(s["memory_peak_bytes"], mem)
            if cpu is not None:
                s["_cpu"].append(cpu)
                s["cpu_peak_percent"] = max(s["cpu_peak_percent"], cpu)
        for s in out.values():
            cpus = s.pop("_cpu")
            s["cpu_mean_percent"] = round(sum(cpus) / len(cpus), 1) if cpus else None
        return out

    def csv(self) -> str:
        lines = ["seconds,service,cpu_percent,memory_bytes"]
        lines += [f"{t},{svc},{'' if cpu is None else cpu},{mem}" for t, svc, cpu, mem in self.rows]
        return "\n".join(lines) + "\n"


def junit(result: dict) -> str:
    """A JUnit XML file of one run: one test case, failed or errored with the verdict's reason
    (junit's rule), the run's properties, the orchestrators' log tails as its output."""
    verdict = result["verdict"]
    case = {
        "host": result["host"],
        "name": result["experience"],
        "verdict": verdict,
        "output": result.get("orchestrator_output") or "",
    }
    props = (("run", result["run"]), ("host", result["host"]), ("result", verdict["result"]))
    return junit_xml.testsuite("isaacsim.fleet experiences", [case], props)


def puller(host, enabled=True):
    """pull(image) -> None once pulled, else why not (the last line Docker said)."""

    def pull(image):
        if not enabled:
            return "it is not on this host"
        rc, out, err = host.run([DOCKER, "pull", "--quiet", image])
        return None if rc == 0 else ((err or out).strip().splitlines() or [f"exit {rc}"])[-1]

    return pull


def preflight(api, experience: dict, gpus_free, pull=None) -> list:
    """Errors that stop a run before anything is created: images neither on the host nor
    pullable (pull(image) -> error text or None), GPUs the host cannot give the run."""
    errors = []
    for image in experience["images"]:
        if api.image(image) is not None:
            continue
        why = pull(image) if pull else "it is not on this host"
        if why:
            errors.append(
                f"{experience['name']}: image {image} cannot be had ({why}). Fix: correct the image name or tag, or "
                "push the image to the fleet's registry."
            )
    wanted = experience["gpus"]
    if wanted > len(gpus_free):
        errors.append(
            f"{experience['name']}: the services ask for {wanted} dedicated GPU(s); this host has {len(gpus_free)} "
            "free. Fix: ask for fewer, or run it where more GPUs are free."
        )
    for name, svc in experience["services"].items():
        missing = [g for g in svc["gpu_device_ids"] if g not in gpus_free]
        if missing and name != experience.get("simulator"):
            errors.append(
                f"{experience['name']}: services.{name} asks for GPU {', '.join(missing)}, which this run cannot have "
                f"(free: {', '.join(gpus_free) or 'none'}). Fix: ask for a count instead of device_ids."
            )
    return errors


def _gpu_share(experience: dict, gpus_free) -> dict:
    """Dedicated GPU ids per service, in service order (the simulator is the borrowed instance: none)."""
    free, out = list(gpus_free), {}
    for name in experience["order"]:
        if name == experience.get("simulator"):
            continue
        svc = experience["services"][name]
        ids = [g for g in svc["gpu_device_ids"] if g in free]
        for g in ids:
            free.remove(g)
        need = max(svc["gpus"] - len(ids), 0)
        out[name], free = ids + free[:need], free[need:]
    return out


def as_compose(experience: dict, secret_keys=()) -> str:
    """The compose file as it was run: interpolated, the experience's environment applied (its
    values shown as such, never written out), as YAML (JSON is YAML)."""
    services = {}
    for name, svc in experience["services"].items():
        out = {"image": svc["image"]}
        if svc["orchestrator"]:
            out["labels"] = {"isaacsim.fleet/test-orchestrator": "true"}
        for key in ("command", "entrypoint", "working_dir", "user", "shm_size", "stop_signal"):
            if svc.get(key) is not None:
                out[key] = svc[key]
        if svc["environment"]:
            out["environment"] = {
                k: "(the experience's environment)" if k in secret_keys else v for k, v in svc["environment"].items()
            }
        if svc["depends_on"]:
            out["depends_on"] = {d: {"condition": c} for d, c in svc["depends_on"].items()}
        if svc["restart"] != "no":
            retries = svc.get("restart_retries") or 0
            out["restart"] = svc["restart"] + (f":{retries}" if retries else "")
        if svc["volumes"]:
            out["volumes"] = [f"{v}:{t}" + (":ro" if ro else "") for v, t, ro in svc["volumes"]]
        if svc["tmpfs"]:
            out["tmpfs"] = svc["tmpfs"]
        if svc.get("init"):
            out["init"] = True
        h = svc.get("healthcheck")
        if h:
            out["healthcheck"] = {
                "test": ["CMD-SHELL", h["test"]],
                "interval": _ms(h["interval"]),
                "timeout": _ms(h["timeout"]),
                "retries": h["retries"],
                "start_period": _ms(h["start_period"]),
            }
        resources = {}
        if svc.get("memory") or svc.get("cpus"):
            resources["limits"] = {k: svc[k] for k in ("memory", "cpus") if svc.get(k)}
        if svc["gpus"]:
            resources["reservations"] = {"devices": [{"capabilities": ["gpu"], "count": svc["gpus"]}]}
        if resources:
            out["deploy"] = {"resources": resources}
        services[name] = out
    doc = {"name": experience["name"], "services": services}
    if experience["volumes"]:
        doc["volumes"] = {v: {} for v in experience["volumes"]}
    return json.dumps(doc, indent=2)


def cli(host):
    """docker(*args, check=True) -> stdout, through the host's run."""

    def docker(*args, check=True):
        rc, out, err = host.run([DOCKER, *args])
        if rc != 0 and check:
            raise RuntimeError(f"docker {' '.join(args)} failed ({rc}): {(err or out).strip()}")
        return out

    return docker


def store_errors(unfetched_after: float, keep_days: float) -> list:
    """What is wrong with how long a host keeps finished runs (run_store)."""
    errors = []
    if unfetched_after < 0:
        errors.append(f"unfetched_after: {unfetched_after:g}. Fix: seconds, 0 or more.")
    if keep_days < 0:
        errors.append(f"keep_days: {keep_days:g}. Fix: days, 0 or more (0 keeps runs for ever).")
    elif keep_days and keep_days * 86400 < max(unfetched_after, 0):
        errors.append(
            f"keep_days: {keep_days:g} would remove runs before their controller has had unfetched_after "
            f"({unfetched_after:g} s) to fetch them. Fix: a longer keep_days."
        )
    return errors


def owner_file(run: str) -> str:
    """Who runs a run: the runner's pid, its services and lent instance, so a run whose runner
    was killed (an async limit, a reboot of the controller's connection) is swept later."""
    return f"{layout.RUN_DIR}/runs/{run}.json"


def execute(
    host,
    api,
    experience: dict,
    run: str,
    *,
    hostname: str,
    timeout: float,
    data_root: str,
    simulator=None,
    gpus_free=(),
    poll: float = 0.5,
    metrics_every: float = 2.0,
    pid: int = 0,
    secret_keys=(),
) -> dict:
    """Run one experience to its verdict and leave the host as it was, but for the run's directory
    (logs, exit codes, metrics, the compose file as run, junit.xml, the services' outputs).
    Returns the run's result."""
    services = [s for s in experience["order"] if s != experience.get("simulator")]
    retries = {s: experience["services"][s].get("restart_retries") or 0 for s in services}
    units = [layout.run_unit(run, s) for s in services]
    directory = layout.run_dir(run, data_root)
    outputs = f"{directory}/outputs"
    share = _gpu_share(experience, gpus_free)
    created = {"network": False, "volumes": [], "units": [], "directory": directory}

    docker = cli(host)
    began = host.now()
    result = {"run": run, "host": hostname, "experience": experience["name"], "directory": directory}
    metrics = Metrics()
    judgement = None
    observations = {}
    owner = {"pid": pid, "services": services, "volumes": experience["volumes"], "directory": directory}
    if simulator and simulator.get("instance") is not None:
        owner["instance"] = simulator["instance"]
    if simulator and simulator.get("slot") is not None:
        owner["slot"] = simulator["slot"]
    host.write(owner_file(run), json.dumps(owner) + "\n", 0o600)
    try:
        host.run(["mkdir", "-p", "-m", "0755", directory])
        # any uid a service runs as writes its outputs here
        host.run(["mkdir", "-p", "-m", "1777", outputs])
        host.run(["chmod", "1777", outputs])
        host.write(f"{directory}/compose.yml", as_compose(experience, secret_keys) + "\n", 0o644)
        labels = [f"--label={layout.LABEL_RUN}={run}"]
        docker("network", "create", "--driver=bridge", *labels, layout.run_name(run))
        created["network"] = True
        for volume in experience["volumes"]:
            docker("volume", "create", *labels, layout.run_volume(run, volume))
            created["volumes"].append(volume)
        for name in services:
            svc = experience["services"][name]
            env_file = runtime_file(run, name, "env")
            host.write(env_file, env_file_text(service_env(run, svc, simulator, share.get(name, ()))), 0o600)
            argv = docker_argv(
                run, name, svc, outputs=outputs, env_file=env_file, simulator=simulator, gpus=share.get(name, ())
            )
            host.write(f"{layout.RUN_UNIT_DIR}/{layout.run_unit(run, name)}", unit_text(run, name, svc, argv), 0o644)
            created["units"].append(name)
        rc, _out, err = host.run(["systemctl", "daemon-reload"])
        if rc != 0:
            raise RuntimeError(f"systemctl daemon-reload failed: {err.strip()}")

        start = host.now()
        judgement = judge.Judge(experience, timeout, start)
        started, ran = set(), set()
        last_metrics = -metrics_every
        quiet = 0  # looks in a row that Docker did not answer
        while True:
            now = host.now()
            shown = lifecycle.show(host, units, PROPS)
            try:
                found = api.labelled(f"{layout.LABEL_RUN}={run}")
                quiet = 0
            except Exception as exc:  # noqa: BLE001 - a busy daemon may miss one look
                quiet += 1
                if quiet >= 20:
                    judgement.fail(now, None, f"the Docker daemon did not answer for {quiet} looks: {exc}")
                    break
                host.sleep(poll)
                continue
            exits = {s: host.read(exit_file(run, s)) for s in started}
            observations = observe(shown, found, run, services, started, ran, exits, retries)
            if experience.get("simulator"):
                observations[experience["simulator"]] = simulator_state(host, simulator)
            to_start = judgement.step(now, observations)
            if judgement.verdict:
                break
            if to_start:
                rc, _out, err = host.run(
                    ["systemctl", "start", "--no-block"] + [layout.run_unit(run, s) for s in to_start]
                )
                if rc != 0:
                    judgement.fail(now, to_start[0], f"systemd would not start {', '.join(to_start)}: {err.strip()}")
                    break
                started.update(to_start)
            if now - last_metrics >= metrics_every:
                last_metrics = now
                for c in found:
                    svc = (c.get("Labels") or {}).get(layout.LABEL_RUN_SERVICE)
                    if c.get("State") != "running" or not svc:
                        continue
                    try:
                        cpu, memory = stats_sample(api.stats(c["Id"]))
                    except Exception:  # noqa: BLE001 - a container that just exited has no stats
                        continue
                    metrics.add(now - start, svc, cpu, memory, c["Id"])
            host.sleep(poll)
        result["verdict"] = judgement.verdict
    finally:
        teardown(host, run, created, docker, keep_directory=judgement is not None)
    result["services"] = {}
    logs = {}
    for name in services:
        log = journal(host, run, name)
        logs[name] = log
        host.write(f"{directory}/{run}-{name}.log", log, 0o644)
        obs = observations.get(name) or judge.observation()
        result["services"][name] = {
            "orchestrator": name in experience["orchestrators"],
            "started": name in judgement.started,
            "exit_code": obs["exit_code"] if obs["state"] == judge.EXITED else None,
            "last_exit_code": obs["exit_code"],
            # an unloaded unit forgets its count: the most the judge saw
            "restarts": max(obs["restarts"], judgement.seen_restarts.get(name, 0)),
            "state_at_verdict": obs["state"],
        }
    result["events"] = judgement.events
    result["metrics"] = metrics.summary()
    result["orchestrator_output"] = "".join(
        f"--- {name} ---\n" + "\n".join(logs.get(name, "").splitlines()[-40:]) + "\n"
        for name in experience["orchestrators"]
    )
    host.write(f"{directory}/metrics.csv", metrics.csv(), 0o644)
    # the run's whole cost on the host: setting up, the run, tearing down, writing artefacts
    result["elapsed"] = round(host.now() - began, 3)
    host.write(f"{directory}/result.json", json.dumps(result, indent=2) + "\n", 0o644)
    host.write(f"{directory}/junit.xml", junit(result), 0o644)
    _rc, out, _err = host.run(["find", outputs, "-type", "f", "-printf", "%P\\n"])
    produced = [f"outputs/{p}" for p in out.splitlines() if p.strip()]
    result["artefacts"] = sorted(
        [f"{run}-{name}.log" for name in services] + ["compose.yml", "metrics.csv", "result.json", "junit.xml"]
    ) + sorted(produced)
    host.remove(owner_file(run))
    return result


def journal(host, run: str, service: str) -> str:
    """A service's log as the journal kept it."""
    # -a: a log with colours or progress bars is text, not "[blob data]"
    _rc, log, _err = host.run(
        ["journalctl", "--no-pager", "-a", "-o", "short-iso", "-u", layout.run_unit(run, service)]
    )
    return log


def live_runs(host) -> set:
    """The runs going on on the host now (each has an owner file until it ends or is swept)."""
    _rc, out, _err = host.run(["find", f"{layout.RUN_DIR}/runs", "-maxdepth", "1", "-name", "*.json"])
    return {p.rsplit("/", 1)[1][: -len(".json")] for p in out.splitlines() if p.strip()}


def simulator_state(host, simulator) -> dict:
    """The borrowed instance as the judge sees the simulator service: running while its unit is active."""
    _rc, out, _err = host.run(["systemctl", "is-active", layout.unit(simulator["instance"])])
    state = judge.RUNNING if out.strip() == "active" else judge.EXITED
    return judge.observation(state, None, 0, "healthy" if state == judge.RUNNING else None, True)


def teardown(host, run: str, created: dict, docker, keep_directory=True) -> None:
    """Stop every container of the run and remove its units, network, volumes and env files
    (logs stay in the journal and the run's directory; the directory goes too when the run
    never started). Safe on a half-created run, and on one whose runner was killed."""
    units = [layout.run_unit(run, s) for s in created["units"]]
    if units:
        # one job for all: systemd stops them together, each with its grace period
        host.run(["systemctl", "stop"] + units)
    for c in docker("ps", "-aq", f"--filter=label={layout.LABEL_RUN}={run}", check=False).split():
        docker("rm", "-f", "-v", c, check=False)
    for name in created["units"]:
        host.remove(f"{layout.RUN_UNIT_DIR}/{layout.run_unit(run, name)}")
    host.remove(f"{layout.RUN_DIR}/runs/{run}")
    if units:
        host.run(["systemctl", "daemon-reload"])
        host.run(["systemctl", "reset-failed"] + units)
    for volume in created["volumes"]:
        docker("volume", "rm", "-f", layout.run_volume(run, volume), check=False)
    if created["network"]:
        docker("network", "rm", layout.run_name(run), check=False)
    if not keep_directory and created.get("directory"):
        host.remove(created["directory"])


def sweep(host, docker, alive) -> tuple:
    """Tear down the runs whose runner is gone (alive(pid) is False), keeping what each got to in
    its directory (its logs, and a result.json that says it ended without a verdict). Returns
    ([(instance, run)] of the instances they had borrowed, still lent - the caller gives them
    back through the lifecycle, restarted clean, then free - and [run] of the runs swept)."""
    _rc, out, _err = host.run(["find", f"{layout.RUN_DIR}/runs", "-maxdepth", "1", "-name", "*.json"])
    lent, ended = [], []
    for path in sorted(p for p in out.splitlines() if p.strip()):
        try:
            owner = json.loads(host.read(path) or "{}")
        except ValueError:
            owner = {}
        if owner.get("pid") and alive(owner["pid"]):
            continue
        run = path.rsplit("/", 1)[1][: -len(".json")]
        created = {
            "network": True,
            "volumes": owner.get("volumes", []),
            "units": owner.get("services", []),
            "directory": owner.get("directory"),
        }
        teardown(host, run, created, docker, keep_directory=True)
        directory = owner.get("directory")
        if directory and host.exists(directory) and not host.exists(f"{directory}/result.json"):
            # what the run got to, for the controller that takes it (run_store)
            services = owner.get("services", [])
            for name in services:
                host.write(f"{directory}/{run}-{name}.log", journal(host, run, name), 0o644)
            why = f"its runner (pid {owner.get('pid') or '?'}) ended before a verdict; torn down by a later run"
            result = {
                "run": run,
                "directory": directory,
                "verdict": {"result": judge.ERROR, "service": None, "reason": why, "seconds": None},
                "services": {name: {"orchestrator": False, "started": None} for name in services},
                "swept": True,
            }
            host.write(f"{directory}/result.json", json.dumps(result, indent=2) + "\n", 0o644)
        if owner.get("instance") is not None:
            lent.append((owner["instance"], run))
        if owner.get("slot") is not None:
            release_slot(host, owner["slot"])
        host.remove(path)
        ended.append(run)
    return lent, ended


def _bytes(n) -> str:
    for unit, size in (("GiB", 1 << 30), ("MiB", 1 << 20), ("KiB", 1 << 10)):
        if n >= size:
            return f"{n / size:.1f} {unit}"
    return f"{n} B"


def summary_lines(result: dict) -> list:
    """A run for a person: its verdict, one row per service, and a borrowed instance that did not come back."""
    verdict = result.get("verdict") or {}
    lines = [
        f"{result.get('experience')} on {result.get('host')} ({result.get('run')}): "
        f"{verdict.get('result', '?').upper()} - {verdict.get('reason', '')} ({verdict.get('seconds', 0):.1f} s)",
        f"{'service':<20} {'role':<12} {'exit':>5} {'restarts':>8} {'cpu peak':>9} {'memory peak':>12}",
    ]
    for name, svc in sorted((result.get("services") or {}).items()):
        m = (result.get("metrics") or {}).get(name) or {}
        code = svc.get("exit_code")
        exit_text = "-" if code is None else str(code)
        if not svc.get("started"):
            exit_text = "not started"
        cpu = f"{m['cpu_peak_percent']:.0f}%" if m.get("samples") else "-"
        mem = _bytes(m["memory_peak_bytes"]) if m.get("samples") else "-"
        role = "orchestrator" if svc.get("orchestrator") else "service"
        lines.append(f"{name:<20} {role:<12} {exit_text:>5} {svc.get('restarts', 0):>8} {cpu:>9} {mem:>12}")
    if result.get("restart_error"):
        # the instance is not lent again until it is ready; nothing else of the run says so
        lines.append(f"after the run, {result['restart_error']}")
    return lines


def borrowed(host, service: str, instance: int, marker_exists) -> tuple:
    """(simulator, error): what a run's services are given of a borrowed instance, or why it
    cannot be lent. marker_exists(path) tells whether the instance is ready. Lending itself
    (lifecycle.lend, lifecycle.give_back) is the lifecycle's."""
    env = layout.parse(host.read(layout.env_file(instance)) or "")
    if not env:
        return None, f"instance: {instance} is not configured on this host. Fix: pick one of its instances."
    if not marker_exists(layout.marker(instance)):
        return None, f"instance: isaac-sim@{instance} is not ready, so it cannot be lent. Fix: start it first."
    if env.get(layout.K_ADDRESS):
        return None, (
            f"instance: isaac-sim@{instance} has an address of its own (macvlan), which the run's containers on this "
            "host cannot reach. Fix: borrow an instance on the host's network."
        )
    given = {layout.K_HOST: service, layout.K_INSTANCE: str(instance)}
    given.update({k: v for k, v in env.items() if k.startswith(layout.K_PORT_PREFIX)})
    # the address clients use: 6.x listens on its public address (ISAACSIM_HOST), not on every
    # address of the host, so Docker's host-gateway is only for an instance that names none
    address = env.get(layout.K_PUBLIC_ADDRESS) or "host-gateway"
    return {"service": service, "address": address, "env": given, "instance": instance}, None


# at most this many dedicated simulators at once on a host (each keeps a cache directory)
SIMULATOR_SLOTS = 16


def slot_marker(slot: int) -> str:
    return f"{layout.RUN_DIR}/simulator-{slot}.lent"


def slot_dir(slot: int, data_root: str = layout.DATA_ROOT) -> str:
    """A dedicated simulator's caches, kept from run to run: the next run on the slot starts warm."""
    return f"{data_root}/simulators/{slot}"


def claim_slot(host, run: str, slots: int = SIMULATOR_SLOTS):
    """The first free simulator slot, taken for the run (mkdir is atomic), or None when all are taken."""
    for slot in range(slots):
        rc, _out, _err = host.run(["mkdir", slot_marker(slot)])
        if rc == 0:
            host.write(f"{slot_marker(slot)}/run", run + "\n", 0o644)
            return slot
    return None


def release_slot(host, slot: int) -> None:
    host.remove(slot_marker(slot))


def deployed_simulator(read, ids=None, config_dir: str = layout.CONFIG_DIR) -> dict:
    """The image, release and memory and shm limits of the host's lowest configured instance of
    ids (by default the instances set up on this host; {} when none is)."""
    if ids is None:
        ids = hostprobe.existing_instances(config_dir, f"{layout.UNIT_DIR}/{layout.TARGET}.wants")
    for i in sorted(ids):
        env = layout.parse(read(layout.env_file(i, config_dir)) or "")
        if env.get(layout.K_IMAGE):
            limits = fleet_status.parse_limits(env.get(layout.K_DOCKER_ARGS, ""))
            return {
                # the digest the fleet runs, where its deploy pinned one
                "image": env.get(layout.K_IMAGE_PINNED) or env[layout.K_IMAGE],
                "release": env.get(layout.K_RELEASE),
                "memory": limits.get("memory"),
                "shm_size": limits.get("shm_size"),
            }
    return {}


def dedicated_settings(image, release, deployed: dict, instance, gpus_given, host_gpus: int) -> tuple:
    """({image, release, gpu, limits}, errors) of a dedicated simulator: the image and release
    given, else those of the host's instances (deployed_simulator), else the release the image's
    tag names; one GPU when the host has any (then the run must be given one)."""
    errors = []
    if instance is not None:
        errors.append(
            f"instance: {instance} with simulator: dedicated; a run with its own simulator borrows no instance. "
            "Fix: leave instance out, or use simulator: borrow."
        )
    if not image:
        image, release = deployed.get("image"), release or deployed.get("release")
    names = ", ".join(releases.RELEASES)
    if not image:
        errors.append(
            "simulator_image: not given, and no Isaac Sim instance is deployed on this host to take it from. "
            "Fix: set simulator_image (experience_simulator_image) to the Isaac Sim image to run."
        )
    elif parse.parse_image(image) is None:
        errors.append(
            f"simulator_image: {image!r} is not an image reference. Fix: e.g. {releases.default_image('6.x')}."
        )
    elif not release:
        release = releases.release_of_tag(parse.parse_image(image)[1] or "")
        if not release:
            errors.append(
                f"simulator_release: not given, and the tag of {image} names no release. Fix: set simulator_release "
                f"(experience_simulator_release) to one of {names}."
            )
    if release and release not in releases.RELEASES:
        errors.append(f"simulator_release: {release!r}. Fix: one of {names}.")
    if host_gpus and not gpus_given:
        errors.append(
            f"gpus: none given, and this host has {host_gpus} GPU(s): the dedicated simulator needs one. Fix: give "
            "the run a free GPU id (experience_gpus), or borrow an instance (simulator: borrow)."
        )
    if errors:
        return None, errors
    limits = {k: deployed.get(k) for k in ("memory", "shm_size")}
    return {"image": image, "release": release, "gpu": bool(host_gpus), "limits": limits}, []


def dedicate(experience: dict, *, release: str, image: str, cache: str, start_period: float, gpu: bool, limits=None):
    """(experience, simulator): the experience with its simulator service as a headless Isaac Sim
    of its own, run like every other service of the run, and what the other services are given.

    The service keeps what it says: an entrypoint of its own (a standalone script, say) replaces
    the release's headless launch, a command is added to it as the app's arguments; its user,
    environment, healthcheck, limits and GPU request win over the release's. cache: the slot's
    directory, mounted where the release keeps its caches, logs and data. gpu: reserve one GPU
    when the service asks for none (False on a host without GPUs). limits: the memory and
    shm_size the host's instances have (Docker's 64 MB of shm is too little for Isaac Sim).
    """
    name = experience["simulator"]
    profile = releases.RELEASES[release]
    launch = profile["profiles"][releases.HEADLESS]
    svc = dict(experience["services"][name], image=image, simulator=False, dedicated=True)
    if svc["entrypoint"] is None:
        svc["entrypoint"] = [launch["entrypoint"]] + list(launch["args"])
    svc["user"] = svc["user"] or f"{profile['uid']}:{profile['gid']}"
    for key in ("memory", "shm_size"):
        svc[key] = svc[key] or (limits or {}).get(key)
    svc["environment"] = dict({"ACCEPT_EULA": "Y"}, **svc["environment"])
    # NVIDIA's own check (AppReady in the newest kit log); no port: headless opens none
    svc["healthcheck"] = svc["healthcheck"] or {
        "test": releases.healthcheck(release, None),
        "interval": 2.0,
        "timeout": 10.0,
        "retries": 3,
        "start_period": float(start_period),
    }
    svc["binds"] = [(f"{cache}/{sub}", target) for sub, target in sorted(profile["mounts"].items())]
    if not svc["gpus"] and not svc["gpu_device_ids"] and gpu:
        svc["gpus"] = 1
    services = dict(experience["services"], **{name: svc})
    out = dict(
        experience,
        services=services,
        simulator=None,
        gpus=sum(s["gpus"] for s in services.values() if not s["simulator"]),
        images=sorted(set(experience["images"]) | {image}),
    )
    given = {layout.K_HOST: name}
    given.update({layout.K_PORT_PREFIX + kind.upper(): str(spec[1]) for kind, spec in profile["ports"].items()})
    # no address: the run's network resolves the service's name
    return out, {"service": name, "address": None, "env": given, "instance": None}


def own_simulator(host, run: str, experience: dict, settings: dict, data_root: str, start_period: float) -> tuple:
    """(experience, simulator, error): a slot taken for the run's dedicated simulator, its
    directories made the release's user's, and the experience with the simulator in it
    (dedicate). On an error nothing is held."""
    slot = claim_slot(host, run)
    if slot is None:
        return None, None, f"{SIMULATOR_SLOTS} dedicated simulators already run on this host. Fix: run fewer at once."
    cache = slot_dir(slot, data_root)
    for argv in cache_argv(cache, settings["release"]):
        rc, _out, err = host.run(argv)
        if rc != 0:
            release_slot(host, slot)
            return None, None, f"could not prepare {cache}: {err.strip()}; nothing of the run started"
    experience, simulator = dedicate(experience, cache=cache, start_period=start_period, **settings)
    simulator["slot"] = slot
    return experience, simulator, None


def give_back(host, simulator) -> None:
    """Release a dedicated simulator's slot (a borrowed instance goes back through the lifecycle)."""
    if simulator and simulator.get("slot") is not None:
        release_slot(host, simulator["slot"])


def cache_argv(cache: str, release: str) -> list:
    """The commands that make a slot's directories the release's user's (re-owned only when a
    release of another user had them)."""
    profile = releases.RELEASES[release]
    owner = f"{profile['uid']}:{profile['gid']}"
    dirs = [f"{cache}/{sub}" for sub in sorted(profile["mounts"])]
    return [
        ["mkdir", "-p", "-m", "0750"] + dirs,
        [
            "find",
            cache,
            "(",
            "!",
            "-uid",
            str(profile["uid"]),
            "-o",
            "!",
            "-gid",
            str(profile["gid"]),
            ")",
            "-exec",
            "chown",
            "-h",
            owner,
            "{}",
            "+",
        ],
    ]


def _pick(free: list, held) -> int:
    """Where in `free` the next borrowing run's instance is: the first nobody else holds, else the first."""
    if held is None:
        return 0
    return next((n for n, i in enumerate(free) if not held(i)), 0)


def run_queue(runs: list, parallel: int, instances, gpus, execute_one, threading, held=None) -> list:
    """Run a host's share of a suite, at most `parallel` at once, and return one result per run
    (in the order given).

    A run that borrows the simulator waits for a free instance of `instances`; one that reserves
    GPUs waits for that many free ids of `gpus`. execute_one(run, instance, gpu_ids) -> result
    borrows the instance and gives it back through the lifecycle itself (lend, run, restart,
    free); a result with `restart_error` means the instance did not come back, and it is not
    lent again. `threading` is the threading module. held(i): whether instance i is claimed
    outside this suite now (a person's session, another suite's run): such an instance is taken
    only when no other is free, and then its claim is waited out.
    """
    lock = threading.Condition()
    results = [None] * len(runs)
    pending = []
    for index, run in enumerate(runs):
        if run["gpus"] > len(gpus) or (run["simulator"] and not instances):
            results[index] = dict(run, error="this host cannot give it the GPUs or the instance it needs")
        else:
            pending.append((index, run))
    free_instances = list(instances)
    free_gpus = list(gpus)
    busy = [0]

    def take():
        """The next run that can start now, with what it takes; None when the queue is empty."""
        with lock:
            while pending:
                for n, (index, run) in enumerate(pending):
                    if run["simulator"] and not free_instances:
                        continue
                    if run["gpus"] > len(free_gpus):
                        continue
                    pending.pop(n)
                    instance = free_instances.pop(_pick(free_instances, held)) if run["simulator"] else None
                    ids, free_gpus[:] = free_gpus[: run["gpus"]], free_gpus[run["gpus"] :]
                    busy[0] += 1  # counted before the lock is let go: no other worker sees it idle
                    return index, run, instance, ids
                if not busy[0]:
                    # nothing runs, so nothing will come back: every instance failed its restart
                    index, run = pending.pop(0)
                    return index, run, None, None
                lock.wait()
            return None

    def one(index, run, instance, ids):
        try:
            results[index] = execute_one(run, instance, ids)
        except BaseException as exc:  # noqa: BLE001 - one run's failure never stops the others
            results[index] = dict(run, error=f"{type(exc).__name__}: {exc}")
        return instance is None or not results[index].get("restart_error")

    def worker():
        while True:
            taken = take()
            if taken is None:
                return
            index, run, instance, ids = taken
            if ids is None:
                results[index] = dict(run, error="no instance of the host could be lent (their restarts failed)")
                continue
            back = False
            try:
                back = one(index, run, instance, ids)
            finally:
                with lock:
                    busy[0] -= 1
                    if instance is not None and back:
                        free_instances.append(instance)
                    free_gpus.extend(ids)
                    lock.notify_all()

    workers = [threading.Thread(target=worker, daemon=True) for _n in range(max(1, parallel))]
    for w in workers:
        w.start()
    for w in workers:
        w.join()
    return results
