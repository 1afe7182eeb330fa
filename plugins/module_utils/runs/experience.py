# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""An experience: a team's compose file, read as the fleet will run it.

A test run on the fleet is a compose file (the same one the team runs locally) whose test
orchestrator, marked by a label, decides pass or fail by its exit code. This module reads the
file (already parsed from YAML) into the run's plan, or into errors naming the service, the key
and the fix, before anything starts: what the fleet cannot honour is an error, what it ignores
is a warning. Pure functions, like plan.py.
"""

from __future__ import annotations

import re
import shlex

from ansible_collections.isaacsim.fleet.plugins.module_utils.common import parse
from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib import container_policy, docker_cli

ORCHESTRATOR_LABELS = ("isaacsim.fleet/test-orchestrator", "resim.ai/isTestOrchestrator")
# a service with this image is the simulator: the run borrows an Isaac Sim instance of the fleet
SIMULATOR_IMAGE = "isaac-sim"
CONDITIONS = ("service_started", "service_healthy", "service_completed_successfully")

# what each key of a service becomes on the fleet
HONOURED = {
    "image",
    "command",
    "entrypoint",
    "environment",
    "working_dir",
    "healthcheck",
    "depends_on",
    "restart",
    "volumes",
    "profiles",
    "deploy",
    "labels",
    "user",
    "shm_size",
    "stop_grace_period",
    "stop_signal",
    "init",
    "tmpfs",
}
# cannot be honoured: each needs something the fleet does not give a test run
REFUSED = {
    "build": "the fleet does not build images; push the image to the fleet's registry and give image",
    "env_file": "the file is not shipped with the experience; put the variables under environment",
    "extends": "resolve it first (docker compose config prints the file with it resolved)",
    "network_mode": "every run has one network of its own; remove it",
    "volumes_from": "share a named volume instead",
    "secrets": "give secrets at the experience level (environment), from a vault",
    "configs": "put the file in the image or in a named volume",
    "cgroup_parent": "the run places its containers itself; remove it",
}
# ignored, with a warning saying why
IGNORED = {
    "ports": "a run publishes no port; its services reach each other by service name",
    "expose": "a run publishes no port; its services reach each other by service name",
    "networks": "every run has one network of its own, where services reach each other by name",
    "container_name": "containers are named per run (isaac-sim-run-RUN-SERVICE)",
    "hostname": "a service's host name is its service name",
    "links": "services reach each other by service name anyway",
    "logging": "logs go to the host's journal and come back with the run's artefacts",
    "tty": "a run has no terminal",
    "stdin_open": "a run has no terminal",
    "platform": "the host's platform is used",
    "pull_policy": "images are pulled before the run, once per host",
    "cap_drop": "test runs keep Docker's default capabilities",
    "sysctls": "test runs keep the host's defaults",
    "ulimits": "test runs keep the host's defaults",
    "dns": "the run's network resolves service names",
    "extra_hosts": "the run's network resolves service names",
    "mem_limit": "give limits under deploy.resources.limits",
    "cpus": "give limits under deploy.resources.limits",
}
TOP_LEVEL = {"services", "volumes", "name", "version", "networks", "x-"}
# the variables that allow a confinement-loosening argument: a single run's, a suite's
ALLOW_VAR = "experience_allowed_docker_args"
SUITE_ALLOW_VAR = "test_suite_allowed_docker_args"
# keys that take a container out of its confinement: refused (hostlib/container_policy.py, as the plan
# refuses them for instances) unless the allow variable names the exact argument; then honoured
CONFINEMENT = ("privileged", "cap_add", "security_opt", "pid", "ipc", "userns_mode", "devices")
_SHARED = {"pid": "--pid", "ipc": "--ipc", "userns_mode": "--userns"}


def _listed(value) -> list:
    return [str(v) for v in (value if isinstance(value, list) else [value] if value is not None else [])]


# a test run's service: no host path (the file's volumes are named ones), no GPU through its arguments
_RULES = {"bind_roots": [], "gpus": [], "root_ok": True}


def _confinement(spec: dict, where: str, allowed, allow_var: str, errors: list, warnings: list) -> list:
    """The docker run arguments of the service's confinement keys that its run honours: those the
    allow variable names. Every other one that loosens the confinement is an error; one that does not
    (a security_opt such as label=level:s0) is ignored with a warning."""
    args = ["--privileged"] if spec.get("privileged") not in (None, False, "false") else []
    args += [f"--cap-add={c}" for c in _listed(spec.get("cap_add"))]
    args += [f"--security-opt={o}" for o in _listed(spec.get("security_opt"))]
    for key, opt in _SHARED.items():
        if spec.get(key) is None:
            continue
        if str(spec[key]) != "host":
            errors.append(
                f"{where}.{key}: {spec[key]!r} cannot be honoured on the fleet: a run's services share only their "
                "network. Fix: remove it."
            )
            continue
        args.append(f"{opt}=host")
    args += [f"--device={d}" for d in _listed(spec.get("devices"))]
    try:
        allow = container_policy.allowed_keys(allowed)
    except container_policy.DockerArgError as exc:
        errors.append(f"{allow_var}: {exc}. Fix: name each argument as docker run takes it (--cap-add=NET_ADMIN).")
        return []
    # each key is one argument of its own: judged alone, as Docker would read it
    honoured = []
    for text in sorted(set(args)):
        where_text = f"{where}: {text}"
        try:
            keys = {key for key, _t, _w in container_policy.judge(docker_cli.config([text]), _RULES)}
        except container_policy.DockerArgError as exc:
            errors.append(f"{where_text}: {exc}. Fix: write it as Docker takes it.")
            continue
        if not keys:
            warnings.append(f"{where_text} is ignored; test runs run with no-new-privileges and Docker's defaults.")
        elif keys <= allow:
            honoured.append(text)
    errors += container_policy.errors(where, "a test run's service", args, allowed, _RULES, allow_var)
    return sorted(honoured)


_DURATION = re.compile(r"(\d+(?:\.\d+)?)(us|ms|s|m|h)")
_UNITS = {"us": 1e-6, "ms": 1e-3, "s": 1.0, "m": 60.0, "h": 3600.0}
_VAR = re.compile(r"\$(?:\$|\{([A-Za-z_][A-Za-z0-9_]*)(?:(:?[-?])([^}]*))?\}|([A-Za-z_][A-Za-z0-9_]*))")
_NAME = re.compile(r"^[a-zA-Z0-9][a-zA-Z0-9_.-]*\Z")


def duration(value, where, errors, default=None):
    """Seconds of a compose duration (1m30s, 500ms, 10s, or a number of seconds)."""
    if value is None:
        return default
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        return float(value)
    text = str(value).strip()
    parts = _DURATION.findall(text)
    if not parts or "".join(n + u for n, u in parts) != text:
        errors.append(f"{where}: {value!r} is not a duration. Fix: write it as compose does, e.g. 30s or 1m30s.")
        return default
    return sum(float(n) * _UNITS[u] for n, u in parts)


def _one_line(where: str, key: str, value: str) -> list:
    """Docker's env file ends a value at a newline and drops a trailing carriage return: refused."""
    bad = next((c for c in ("\n", "\r") if c in value), None)
    if not bad:
        return []
    what = "a newline" if bad == "\n" else "a carriage return"
    return [
        f"{where}: {key} holds {what}, which a run cannot pass to the container. Fix: give the value on one "
        "line without control characters (or put the text in the image or a volume)."
    ]


def interpolate(value, env: dict, where: str, errors: list, warnings: list, used=None):
    """Compose's ${VAR}, ${VAR:-default}, ${VAR-default}, ${VAR:?message}, $VAR and $$, from the
    experience's environment (what the team's shell gives `docker compose` locally). used: a
    set that gets (where, VAR) for every variable whose value went in."""
    used = set() if used is None else used
    if isinstance(value, dict):
        return {k: interpolate(v, env, f"{where}.{k}", errors, warnings, used) for k, v in value.items()}
    if isinstance(value, list):
        return [interpolate(v, env, where, errors, warnings, used) for v in value]
    if not isinstance(value, str):
        return value

    def one(match):
        if match.group(0) == "$$":
            return "$"
        name = match.group(1) or match.group(4)
        op, arg = match.group(2), match.group(3) or ""
        present = name in env
        empty = not str(env.get(name, ""))
        if op in (":-", "-"):
            use_default = not present or (op == ":-" and empty)
            if not use_default:
                used.add((where, name))
            return arg if use_default else str(env[name])
        if op in (":?", "?"):
            if not present or (op == ":?" and empty):
                errors.append(
                    f"{where}: ${{{name}}} is required ({arg or 'no message'}). "
                    f"Fix: set {name} in the experience's environment."
                )
                return ""
            used.add((where, name))
            return str(env[name])
        if not present:
            warnings.append(f"{where}: ${{{name}}} is not set; it becomes an empty string, as with docker compose.")
            return ""
        used.add((where, name))
        return str(env[name])

    return _VAR.sub(one, value)


def _secret_fields(used, secret, where: str, environment: dict, errors: list) -> set:
    """The environment keys of a service that carry a secret's value (masked wherever the run is
    written down); a secret substituted anywhere else would reach a unit file or a command line,
    and is refused."""
    keys = set()
    prefix = f"{where}.environment"
    for path, var in sorted(used):
        if var not in secret:
            continue
        if path.startswith(prefix + "."):
            keys.add(path[len(prefix) + 1 :])
        elif path == prefix:  # the list form: the entries that hold it
            keys.update(k for k, v in environment.items() if str(secret[var]) and str(secret[var]) in str(v))
        else:
            errors.append(
                f"{path}: ${{{var}}} is a secret (experience_secret_environment), and this would put its value on a "
                "command line and in a unit file. Fix: pass it in the service's environment and read it there "
                f"(in a shell entrypoint, $${var})."
            )
    return keys


def _words(value, where, errors):
    if value is None:
        return None
    if isinstance(value, str):
        try:
            return shlex.split(value)
        except ValueError as exc:
            errors.append(f"{where}: {value!r} does not split into words ({exc}). Fix: give a list.")
            return None
    if isinstance(value, list):
        return [str(v) for v in value]
    errors.append(f"{where}: must be a string or a list of words.")
    return None


def _text(value):
    """A YAML scalar as compose passes it: true -> "true", None stays None."""
    if value is None:
        return None
    return str(value).lower() if isinstance(value, bool) else str(value)


def _mapping(value, where, errors) -> dict:
    """A compose list of KEY=VALUE (or KEY) or a mapping, as {KEY: value or None}."""
    if value is None:
        return {}
    if isinstance(value, dict):
        return {
            str(k): None if v is None else str(v).lower() if isinstance(v, bool) else str(v) for k, v in value.items()
        }
    if isinstance(value, list):
        out = {}
        for item in value:
            key, sep, val = str(item).partition("=")
            out[key] = val if sep else None
        return out
    errors.append(f"{where}: must be a mapping or a list of KEY=VALUE.")
    return {}


def _is_orchestrator(labels: dict) -> bool:
    return any(str(labels.get(name, "")).lower() == "true" for name in ORCHESTRATOR_LABELS)


def _restart(value, where, errors, warnings):
    """(policy, max retries): no, always, on-failure[:N] or unless-stopped (always, for a run)."""
    text = "no" if value in (None, False) else str(value)
    if text in ("no", "always"):
        return text, 0
    if text == "unless-stopped":
        return "always", 0
    match = re.fullmatch(r"on-failure(?::(\d+))?", text)
    if match:
        return "on-failure", int(match.group(1) or 0)
    errors.append(f"{where}: {value!r} is not a restart policy. Fix: no, always, on-failure[:N] or unless-stopped.")
    return "no", 0


def _gpus(deploy, where, errors, warnings) -> dict:
    """{"count": n} or {"device_ids": [...]} from deploy.resources.reservations.devices; limits too."""
    out = {"gpus": 0, "device_ids": [], "memory": None, "cpus": None}
    if deploy is None:
        return out
    if not isinstance(deploy, dict):
        errors.append(f"{where}: must be a mapping.")
        return out
    for key in deploy:
        if key not in ("resources", "replicas", "restart_policy"):
            warnings.append(f"{where}.{key}: ignored (a run starts one container per service).")
    replicas = deploy.get("replicas", 1)
    if str(replicas) != "1":
        errors.append(f"{where}.replicas: {replicas!r}; a run starts one container per service. Fix: remove it.")
    resources = deploy.get("resources") or {}
    limits = resources.get("limits") or {}
    out["memory"] = str(limits["memory"]) if limits.get("memory") is not None else None
    out["cpus"] = str(limits["cpus"]) if limits.get("cpus") is not None else None
    for n, device in enumerate((resources.get("reservations") or {}).get("devices") or []):
        dwhere = f"{where}.resources.reservations.devices[{n}]"
        caps = device.get("capabilities") or []
        if "gpu" not in [str(c) for c in caps] and device.get("driver") != "nvidia":
            errors.append(f"{dwhere}: only GPUs can be reserved (capabilities: [gpu]). Fix: remove it.")
            continue
        if device.get("device_ids") is not None:
            out["device_ids"] += [str(d) for d in device["device_ids"]]
            continue
        count = device.get("count", 1)
        if str(count) == "all" or not str(count).isdigit() or int(str(count)) < 1:
            errors.append(
                f"{dwhere}.count: {count!r}; a service gets dedicated GPUs, so give how many (1 or more). "
                "Fix: e.g. count: 1."
            )
            continue
        out["gpus"] += int(str(count))
    if out["device_ids"]:
        out["gpus"] += len(out["device_ids"])
    return out


def _volumes(value, declared, where, errors) -> tuple:
    """([(volume, target, read_only)], [tmpfs targets]): named volumes only; a host path is refused."""
    mounts, tmpfs = [], []
    for item in value or []:
        if isinstance(item, dict):
            kind = item.get("type", "volume")
            source, target = item.get("source"), item.get("target")
            read_only = bool(item.get("read_only"))
            if kind == "tmpfs" and target:
                tmpfs.append(str(target))
                continue
        else:
            parts = str(item).split(":")
            if len(parts) == 1:
                errors.append(f"{where}: {item!r} is an anonymous volume. Fix: name it (NAME:{parts[0]}).")
                continue
            kind = "bind" if parts[0].startswith((".", "/", "~")) else "volume"
            source, target = parts[0], parts[1]
            read_only = len(parts) > 2 and "ro" in parts[2].split(",")
        if kind == "bind":
            errors.append(
                f"{where}: {source} is a path on the machine the file was written on, which a fleet host does not "
                "have. Fix: put the files in the image, or in a named volume a service fills."
            )
            continue
        if kind != "volume" or not source or not target or not str(target).startswith("/"):
            errors.append(f"{where}: {item!r} is not NAME:/path[:ro]. Fix: use a named volume.")
            continue
        if source not in declared:
            errors.append(f"{where}: volume {source} is not declared under the file's volumes. Fix: declare it.")
            continue
        mounts.append((str(source), str(target), read_only))
    return mounts, tmpfs


def _healthcheck(value, where, errors):
    if value is None:
        return None
    if not isinstance(value, dict):
        errors.append(f"{where}: must be a mapping with test.")
        return None
    if value.get("disable"):
        return None
    test = value.get("test")
    if isinstance(test, list) and test and test[0] == "NONE":
        return None
    if isinstance(test, str):
        cmd = test
    elif isinstance(test, list) and len(test) >= 2 and test[0] in ("CMD", "CMD-SHELL"):
        cmd = test[1] if test[0] == "CMD-SHELL" else shlex.join(str(t) for t in test[1:])
    else:
        errors.append(f'{where}.test: {test!r} is not a healthcheck command. Fix: ["CMD", ...] or a shell string.')
        return None
    return {
        "test": cmd,
        "interval": duration(value.get("interval"), f"{where}.interval", errors, 30.0),
        "timeout": duration(value.get("timeout"), f"{where}.timeout", errors, 30.0),
        "retries": int(value.get("retries", 3)),
        "start_period": duration(value.get("start_period"), f"{where}.start_period", errors, 0.0),
    }


def _cycle(graph: dict):
    """One dependency cycle as a list of names (first repeated at the end), or None."""
    state, stack = {}, []

    def visit(node):
        state[node] = 1
        stack.append(node)
        for dep in graph.get(node, ()):
            if state.get(dep) == 1:
                return stack[stack.index(dep) :] + [dep]
            if state.get(dep) is None:
                found = visit(dep)
                if found:
                    return found
        stack.pop()
        state[node] = 2
        return None

    for node in sorted(graph):
        if state.get(node) is None:
            found = visit(node)
            if found:
                return found
    return None


def read(compose, env=None, profiles=(), name="experience", secret=None, allowed=(), allow_var=ALLOW_VAR) -> tuple:
    """(experience, errors, warnings) for one compose file (a parsed mapping).

    env: the experience's environment, which overrides every service's and is given to each;
    profiles: the compose profiles the experience runs; secret: {name: value} of the
    environment's secret part (also in env). The experience's `secret_keys` are the environment
    keys that carry a secret's value. allowed: the confinement-loosening docker arguments the
    operator allows (allow_var names the variable), which a service may then ask for.
    """
    errors, warnings = [], []
    env = {str(k): str(v) for k, v in (env or {}).items()}
    secret = {str(k): str(v) for k, v in (secret or {}).items()}
    secret_keys = set(secret)
    if not isinstance(compose, dict) or not isinstance(compose.get("services"), dict) or not compose["services"]:
        return (
            None,
            [f"{name}: not a compose file with services. Fix: give the file the team runs with docker compose."],
            [],
        )
    for key in compose:
        if key not in TOP_LEVEL and not str(key).startswith("x-"):
            if key in ("secrets", "configs"):
                errors.append(f"{name}: {key} cannot be given to a run. Fix: {REFUSED[key]}.")
            else:
                warnings.append(f"{name}: top-level {key} is ignored.")
    if compose.get("networks"):
        warnings.append(f"{name}: networks are ignored; {IGNORED['networks']}.")
    for key, value in (env or {}).items():
        errors += _one_line("experience_environment", key, str(value))
    declared = {}
    for vol, spec in (compose.get("volumes") or {}).items():
        if isinstance(spec, dict) and spec.get("external"):
            errors.append(
                f"{name}: volume {vol} is external; a run's volumes are created for it and removed after. "
                "Fix: drop external."
            )
        if isinstance(spec, dict) and (spec.get("driver") or spec.get("driver_opts")):
            warnings.append(
                f"{name}: volume {vol}: driver and driver_opts are ignored; a run's volumes are the host's local "
                "Docker volumes, made for the run and removed after it."
            )
        declared[str(vol)] = spec
    chosen = {str(p) for p in profiles or ()}
    services = {}
    for svc, spec in compose["services"].items():
        svc = str(svc)
        where = f"{name}: services.{svc}"
        if not _NAME.match(svc):
            errors.append(f"{where}: not a usable service name (letters, digits, _ . -). Fix: rename it.")
            continue
        if not isinstance(spec, dict):
            errors.append(f"{where}: must be a mapping with at least image.")
            continue
        used = set()
        spec = interpolate(spec, env, where, errors, warnings, used)
        active = not spec.get("profiles") or bool(chosen & {str(p) for p in spec["profiles"]})
        docker_args = _confinement(spec, where, allowed, allow_var, errors, warnings)
        for key in spec:
            if key in CONFINEMENT:
                continue
            if key in REFUSED:
                errors.append(f"{where}.{key}: cannot be honoured on the fleet. Fix: {REFUSED[key]}.")
            elif key in IGNORED:
                warnings.append(f"{where}.{key}: ignored; {IGNORED[key]}.")
            elif key not in HONOURED and not str(key).startswith("x-"):
                warnings.append(f"{where}.{key}: not a setting the fleet knows; ignored.")
        image = spec.get("image")
        if not image and "build" not in spec:
            errors.append(f"{where}.image: missing. Fix: give the image, with its tag, from the fleet's registry.")
        labels = _mapping(spec.get("labels"), f"{where}.labels", errors)
        environment = _mapping(spec.get("environment"), f"{where}.environment", errors)
        for key, value in list(environment.items()):
            if value is None:
                if key in env:
                    environment[key] = env[key]
                else:
                    warnings.append(
                        f"{where}.environment: {key} has no value (locally it comes from your shell); it is left "
                        "out. Fix: give it a value, or set it in the experience's environment."
                    )
                    environment.pop(key)
        environment.update(env)
        secret_keys |= _secret_fields(used, secret, where, environment, errors)
        for key, value in environment.items():
            if key not in env:  # the experience's own are checked once, above
                errors += _one_line(f"{where}.environment", key, value)
        restart, retries = _restart(spec.get("restart"), f"{where}.restart", errors, warnings)
        orchestrator = _is_orchestrator(labels)
        if orchestrator and restart != "no":
            warnings.append(f"{where}.restart: ignored; an orchestrator never restarts (its exit is the verdict).")
            restart, retries = "no", 0
        depends = spec.get("depends_on") or {}
        if isinstance(depends, list):
            depends = {str(d): {"condition": "service_started"} for d in depends}
        elif isinstance(depends, dict):
            depends = {str(d): (c if isinstance(c, dict) else {}) for d, c in depends.items()}
        else:
            errors.append(f"{where}.depends_on: must be a list of services or a mapping.")
            depends = {}
        conditions = {}
        for dep, how in depends.items():
            condition = how.get("condition", "service_started")
            if condition not in CONDITIONS:
                errors.append(
                    f"{where}.depends_on.{dep}.condition: {condition!r}. Fix: one of {', '.join(CONDITIONS)}."
                )
            conditions[dep] = condition
        resources = _gpus(spec.get("deploy"), f"{where}.deploy", errors, warnings)
        for key, size in (("shm_size", spec.get("shm_size")), ("deploy.resources.limits.memory", resources["memory"])):
            if size is not None and parse.parse_size(size) is None:
                errors.append(f"{where}.{key}: {size!r} is not a size. Fix: e.g. 2g or 512m.")
        mounts, tmpfs = _volumes(spec.get("volumes"), declared, f"{where}.volumes", errors)
        tmpfs += [str(t) for t in ([spec["tmpfs"]] if isinstance(spec.get("tmpfs"), str) else spec.get("tmpfs") or [])]
        services[svc] = {
            "name": svc,
            "active": active,
            "image": str(image or ""),
            "simulator": str(image or "") == SIMULATOR_IMAGE,
            "orchestrator": orchestrator,
            "command": _words(spec.get("command"), f"{where}.command", errors),
            "entrypoint": _words(spec.get("entrypoint"), f"{where}.entrypoint", errors),
            "environment": environment,
            "working_dir": spec.get("working_dir"),
            "user": None if spec.get("user") is None else str(spec["user"]),
            "healthcheck": _healthcheck(spec.get("healthcheck"), f"{where}.healthcheck", errors),
            "depends_on": conditions,
            "restart": restart,
            "restart_retries": retries,
            "volumes": mounts,
            "tmpfs": tmpfs,
            "gpus": resources["gpus"],
            "gpu_device_ids": resources["device_ids"],
            "memory": resources["memory"],
            "cpus": resources["cpus"],
            "shm_size": None if spec.get("shm_size") is None else str(spec["shm_size"]),
            "stop_grace_period": duration(spec.get("stop_grace_period"), f"{where}.stop_grace_period", errors, 10.0),
            "stop_signal": spec.get("stop_signal"),
            "init": bool(spec.get("init")),
            "docker_args": docker_args,
        }
    active = {s: v for s, v in services.items() if v["active"]}
    for svc, spec in active.items():
        for dep, condition in spec["depends_on"].items():
            if dep not in services:
                errors.append(f"{name}: services.{svc}.depends_on: {dep} is not a service of the file. Fix: remove it.")
            elif dep not in active:
                errors.append(
                    f"{name}: services.{svc}.depends_on: {dep} is not in the profiles this experience runs "
                    f"({', '.join(sorted(chosen)) or 'none'}). Fix: add its profile, or remove the dependency."
                )
            elif condition == "service_healthy" and not services[dep]["healthcheck"] and not services[dep]["simulator"]:
                errors.append(
                    f"{name}: services.{svc}.depends_on.{dep}: service_healthy, but {dep} has no healthcheck. "
                    "Fix: give it one, or use service_started."
                )
    cycle = _cycle({s: [d for d in v["depends_on"] if d in active] for s, v in active.items()})
    if cycle:
        errors.append(
            f"{name}: depends_on goes round in a cycle: {' -> '.join(cycle)}. Fix: remove one of those dependencies."
        )
    orchestrators = sorted(s for s, v in active.items() if v["orchestrator"])
    if active and not orchestrators:
        errors.append(
            f"{name}: no test orchestrator, so nothing would decide the verdict. Fix: label the service that drives "
            f'the test with {ORCHESTRATOR_LABELS[0]}: "true" (or {ORCHESTRATOR_LABELS[1]}: "true").'
        )
    simulators = sorted(s for s, v in active.items() if v["simulator"])
    if len(simulators) > 1:
        errors.append(
            f"{name}: {', '.join(simulators)} all ask for the simulator; a run borrows one Isaac Sim instance. "
            "Fix: keep one service with image: isaac-sim."
        )
    for sim in simulators:
        if services[sim]["orchestrator"]:
            errors.append(
                f"{name}: services.{sim}: the simulator cannot be the orchestrator. Fix: label another service."
            )
    if not active:
        errors.append(
            f"{name}: no service runs with the profiles {', '.join(sorted(chosen)) or '(none)'}. Fix: choose a profile "
            "the file has."
        )
    experience = {
        "name": name,
        "services": active,
        "volumes": sorted({v for s in active.values() for v, _t, _ro in s["volumes"]}),
        "orchestrators": orchestrators,
        "simulator": simulators[0] if simulators else None,
        # the simulator is the borrowed instance, with its own GPU: the run reserves none for it
        "gpus": sum(s["gpus"] for s in active.values() if not s["simulator"]),
        "order": _order(active) if not cycle else [],
        "images": sorted({s["image"] for s in active.values() if s["image"] and not s["simulator"]}),
        # masked wherever the run is written down (its compose.yml, results); given by a 0600 file
        "secret_keys": sorted(secret_keys),
    }
    return experience, errors, warnings


def _order(services: dict) -> list:
    """The services in an order where each comes after what it depends on (ties by name)."""
    done, order = set(), []
    pending = sorted(services)
    while pending:
        ready = [s for s in pending if all(d in done or d not in services for d in services[s]["depends_on"])]
        for s in ready:
            done.add(s)
            order.append(s)
        pending = [s for s in pending if s not in done]
        if not ready:
            break
    return order
