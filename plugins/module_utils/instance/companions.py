# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""Companions: containers that belong to an instance (a viewer, a ROS 2 bridge, a recorder).

Each companion of each instance is a systemd unit of its own (layout.companion_unit), started
once its instance is ready, stopped and restarted with it. This module checks the
``isaac_sim_companions`` list and turns it into one planned companion per instance, or errors
naming the variable and the fix. Pure functions, like plan.py.
"""

from __future__ import annotations

import re
import shlex

from ansible_collections.isaacsim.fleet.plugins.module_utils.common.parse import mib_of
from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib import builtin_companions, layout

VAR = "isaac_sim_companions"
KEYS = {
    "name",
    "image",
    "command",
    "entrypoint",
    "env",
    "ports",
    "volumes",
    "healthcheck",
    "gpu",
    "gpu_memory",
    "user",
    "instances",
    "ready_timeout",
    "stop_timeout",
    "docker_args",
}
HEALTH_KEYS = {"test", "interval", "timeout", "retries", "start_period"}
PORT_NAME_RE = re.compile(r"^[a-z][a-z0-9_]*\Z")
PORT_RE = re.compile(r"^(\d+)(?:/(tcp|udp))?\Z")
PLACEHOLDER_RE = re.compile(r"\{(instance|host|port\.[a-z][a-z0-9_]*)\}")
ENV_NAME_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*\Z")
DEFAULT_READY_TIMEOUT = 60
DEFAULT_STOP_TIMEOUT = 10


def built_in(name: str, image: str, health_interval: int = 30, instances=None) -> dict:
    """A built-in companion (hostlib/builtin_companions.py) as an entry of isaac_sim_companions gives one: its
    container with the image given, its healthcheck every health_interval seconds (at most 5: the readiness
    gate waits for the first healthy check, which Docker runs one interval after the start).

    instances: the instances that get it, where others do not (None: every instance)."""
    container = builtin_companions.BUILT_IN[name]["container"]
    spec = {"name": name, "image": image, "user": container["user"], "env": dict(container["env"])}
    spec["ports"] = dict(container["ports"])
    check = container.get("healthcheck")
    if check:
        spec["healthcheck"] = {"test": list(check["test"]), "interval": max(1, min(5, health_interval))}
        spec["healthcheck"].update((k, v) for k, v in check.items() if k != "test")
    if instances is not None:
        spec["instances"] = list(instances)
    return spec


def _int(value, lowest, where, errors, default):
    if value is None:
        return default
    text = str(value).strip()
    if isinstance(value, bool) or not re.fullmatch(r"\d+", text) or int(text) < lowest:
        errors.append(f"{where}: {value!r} is not a whole number of {lowest} or more. Fix: give one, e.g. {default}.")
        return default
    return int(text)


def _words(value, where, errors) -> list:
    """A command as a list of words: a list as given, a string split as a shell would."""
    if value is None:
        return []
    if isinstance(value, (list, tuple)):
        return [str(v) for v in value]
    try:
        return shlex.split(str(value))
    except ValueError as exc:
        errors.append(f"{where}: {value!r} does not split into words ({exc}). Fix: give a list of arguments.")
        return []


def health_cmd(test, where, errors) -> str | None:
    """Docker's --health-cmd (run by a shell) from a compose-style test: a string, or
    ["CMD", args...] or ["CMD-SHELL", "command"]."""
    if isinstance(test, str) and test.strip():
        return test
    if isinstance(test, (list, tuple)) and len(test) >= 2 and test[0] in ("CMD", "CMD-SHELL"):
        return str(test[1]) if test[0] == "CMD-SHELL" else shlex.join(str(t) for t in test[1:])
    errors.append(
        f"{where}.test: {test!r} is not a healthcheck command. "
        'Fix: give a shell command, or ["CMD", "curl", "-f", "http://..."] as in a compose file.'
    )
    return None


def gpu_memory_mib(spec: dict):
    """MiB of its instance's GPU this companion takes (gpu_memory; 0 when it names none), None
    for a value that is not a size."""
    value = spec.get("gpu_memory")
    if value in (None, "") or not spec.get("gpu"):
        return 0
    return mib_of(value)


def check(specs, release_ports: dict, max_instances: int, gpu_enabled: bool) -> list:
    """Errors in the companions list itself (names, keys, types), before any port is placed."""
    errors = []
    if specs in (None, ""):
        return errors
    if not isinstance(specs, list):
        return [f"{VAR}: must be a list of companions (name, image, ...). Fix: write it as a YAML list."]
    seen = set()
    for n, spec in enumerate(specs):
        where = f"{VAR}[{n}]"
        if not isinstance(spec, dict):
            errors.append(
                f"{where}: must be a mapping with at least name and image. Fix: e.g. {{name: bridge, image: ...}}."
            )
            continue
        name = str(spec.get("name") or "")
        where = f"{VAR}[{name or n}]"
        unknown = sorted(set(spec) - KEYS)
        if unknown:
            errors.append(
                f"{where}: {', '.join(unknown)} is not a companion setting. Fix: use only {', '.join(sorted(KEYS))}."
            )
        if not layout.COMPANION_NAME_RE.match(name) or len(name) > 32 or name in layout.RESERVED_COMPANIONS:
            errors.append(
                f"{where}.name: {name!r} cannot name a companion (lower-case letters, digits and single dashes, "
                f"starting with a letter, at most 32; not {', '.join(layout.RESERVED_COMPANIONS)}). "
                "Fix: rename it, e.g. ros-bridge."
            )
        elif name in seen:
            errors.append(f"{where}.name: two companions are named {name}. Fix: give each its own name.")
        seen.add(name)
        if not spec.get("image"):
            errors.append(f"{where}.image: missing. Fix: give the companion's image, e.g. registry/ros-bridge:1.0.")
        env = spec.get("env") or {}
        if not isinstance(env, dict):
            errors.append(f"{where}.env: must be a mapping of NAME: value.")
            env = {}
        for env_name in env:
            if not ENV_NAME_RE.match(str(env_name)) or str(env_name).startswith(layout.RESERVED_PREFIX):
                errors.append(
                    f"{where}.env: {env_name!r} is not a usable variable name (letters, digits, _; the "
                    f"{layout.RESERVED_PREFIX} prefix is the collection's own). Fix: rename it."
                )
        ports = spec.get("ports") or {}
        if not isinstance(ports, dict):
            errors.append(f"{where}.ports: must be a mapping of port name: base port. Fix: e.g. {{http: 9100}}.")
            ports = {}
        for port_name, value in ports.items():
            text = str(value)
            if not PORT_NAME_RE.match(str(port_name)):
                errors.append(f"{where}.ports: {port_name!r} is not a port name (lower-case, digits, _).")
            elif text in release_ports:
                if release_ports[text]:
                    errors.append(
                        f"{where}.ports.{port_name}: {text} is a port the Isaac Sim instance itself listens on. "
                        "Fix: give the companion a base port of its own, e.g. 9100."
                    )
            elif not PORT_RE.match(text):
                kept = ", ".join(k for k, v in release_ports.items() if not v) or "none"
                errors.append(
                    f"{where}.ports.{port_name}: {value!r} is neither a base port (9100, 9100/udp) nor a port the "
                    f"release reserves for companions ({kept}). Fix: give a base port."
                )
        volumes = spec.get("volumes") or []
        if not isinstance(volumes, list):
            errors.append(f"{where}.volumes: must be a list of SOURCE:TARGET[:ro].")
            volumes = []
        for volume in volumes:
            parts = str(volume).split(":")
            if (
                len(parts) not in (2, 3)
                or not parts[1].startswith("/")
                or (len(parts) == 3 and parts[2] not in ("ro", "rw"))
            ):
                errors.append(
                    f"{where}.volumes: {volume!r} is not SOURCE:TARGET[:ro|rw] with an absolute TARGET. "
                    "Fix: e.g. recordings:/data (kept per instance) or /srv/maps:/maps:ro."
                )
            elif not parts[0] or (not parts[0].startswith("/") and not re.fullmatch(r"[A-Za-z0-9._-]+", parts[0])):
                errors.append(
                    f"{where}.volumes: source {parts[0]!r} must be an absolute host path or a plain name "
                    "(a directory kept per instance). Fix: e.g. recordings or /srv/maps."
                )
        health = spec.get("healthcheck")
        if health is not None:
            if not isinstance(health, dict) or "test" not in health:
                errors.append(f"{where}.healthcheck: must be a mapping with test (and interval, timeout, retries).")
            else:
                extra = sorted(set(health) - HEALTH_KEYS)
                if extra:
                    errors.append(f"{where}.healthcheck: {', '.join(extra)} is not a healthcheck setting.")
                health_cmd(health["test"], f"{where}.healthcheck", errors)
        if spec.get("gpu") and not gpu_enabled:
            errors.append(
                f"{where}.gpu: true, but isaac_sim_gpu_enabled is false (the instances have no GPU to share). "
                "Fix: set gpu: false, or enable GPUs."
            )
        if spec.get("gpu_memory") not in (None, "") and not spec.get("gpu"):
            errors.append(
                f"{where}.gpu_memory: {spec['gpu_memory']!r}, but the companion has no GPU (gpu: false). "
                "Fix: set gpu: true, or remove gpu_memory."
            )
        elif gpu_memory_mib(spec) is None:
            errors.append(
                f"{where}.gpu_memory: {spec['gpu_memory']!r} is not a size with its unit. Fix: e.g. 4g or 2048m."
            )
        for inst in spec.get("instances") or []:
            # an instance scaled away may stay listed; one that can never exist is a mistake
            if not str(inst).strip().isdigit() or int(str(inst)) >= max_instances:
                errors.append(
                    f"{where}.instances: {inst!r} is not an instance number (0..{max_instances - 1}, "
                    "isaac_sim_max_instances). Fix: remove it."
                )
        if spec.get("docker_args") is not None and not isinstance(spec.get("docker_args"), list):
            errors.append(f"{where}.docker_args: must be a list of docker run arguments, one per item.")
    return errors


def timeouts(spec, errors) -> dict:
    """The companion's unit settings shared by all its instances: its name and its timeouts."""
    where = f"{VAR}[{spec['name']}]"
    return {
        "name": spec["name"],
        "ready_timeout": _int(spec.get("ready_timeout"), 1, f"{where}.ready_timeout", errors, DEFAULT_READY_TIMEOUT),
        "stop_timeout": _int(spec.get("stop_timeout"), 0, f"{where}.stop_timeout", errors, DEFAULT_STOP_TIMEOUT),
    }


def own_ports(spec) -> dict:
    """{port name: (protocol, base)} of the ports the companion opens in a block of its own."""
    out = {}
    for port_name, value in (spec.get("ports") or {}).items():
        match = PORT_RE.match(str(value))
        if match:
            out[str(port_name)] = (match.group(2) or "tcp", int(match.group(1)))
    return out


def _fill(text, values: dict, where, errors) -> str:
    def one(match):
        key = match.group(1)
        if key not in values:
            errors.append(
                f"{where}: {{{key}}} is not known here. Fix: use {{instance}}, {{host}} or "
                f"{{port.NAME}} with NAME one of {', '.join(k[5:] for k in values if k.startswith('port.'))}."
            )
            return match.group(0)
        return str(values[key])

    return PLACEHOLDER_RE.sub(one, str(text))


def for_instance(
    spec, i, instance_ports, instance_gpu, stride, public, uid_gid, data_root, release_ports, network="host"
) -> tuple:
    """(planned companion of instance i, errors). network: Docker's --network for it (the host's,
    or container:NAME, its instance's namespace when the instance has an address of its own)."""
    errors = []
    name = spec["name"]
    where = f"{VAR}[{name}]"
    ports, protocols, own = {}, {}, []
    for port_name, value in (spec.get("ports") or {}).items():
        text = str(value)
        if text in release_ports:  # the instance's reserved port of that kind (the web viewer's)
            ports[port_name] = instance_ports[text]
            protocols[port_name] = "tcp"
        else:
            proto, base = own_ports({"ports": {port_name: value}})[port_name]
            ports[port_name] = base + i * stride
            protocols[port_name] = proto
        own.append(port_name)
    values = {"instance": i, "host": public}
    values.update({f"port.{k}": v for k, v in instance_ports.items()})
    values.update({f"port.{k}": v for k, v in ports.items()})
    container = layout.companion_container(i, name)
    docker = [
        f"--network={network}",
        "--pull=never",
        f"--label={layout.LABEL_INSTANCE}={i}",
        f"--label={layout.LABEL_COMPANION}={name}",
        "--security-opt=no-new-privileges",
        # a server that is PID 1 ignores SIGTERM: without an init every stop waits out stop_timeout
        "--init",
    ]
    if spec.get("user"):
        docker.append(f"--user={spec['user']}")
    if spec.get("entrypoint"):
        docker.append(f"--entrypoint={_fill(spec['entrypoint'], values, where + '.entrypoint', errors)}")
    env = {layout.K_HOST: public}
    env.update({f"{layout.K_PORT_PREFIX}{k.upper()}": str(v) for k, v in instance_ports.items()})
    env.update({f"{layout.K_PORT_PREFIX}{k.upper()}": str(v) for k, v in ports.items()})
    for key, value in (spec.get("env") or {}).items():
        env[str(key)] = _fill(value, values, f"{where}.env.{key}", errors)
    docker += [f"--env={key}" for key in [layout.K_INSTANCE] + list(env)]
    dirs = []
    if any(not str(v).startswith("/") for v in spec.get("volumes") or []):
        home = layout.companion_data_dir(i, name, data_root)
        dirs += [home.rsplit("/", 1)[0], home]
    for volume in spec.get("volumes") or []:
        source, target, *mode = str(volume).split(":")
        if not source.startswith("/"):
            source = f"{layout.companion_data_dir(i, name, data_root)}/{source}"
            dirs.append(source)
        docker.append(f"--volume={source}:{target}:{mode[0] if mode else 'rw'}")
    interval = 0
    health = spec.get("healthcheck")
    if health:
        check_where = f"{where}.healthcheck"
        interval = _int(health.get("interval"), 1, f"{check_where}.interval", errors, 30)
        cmd = health_cmd(health["test"], check_where, errors)
        timeout = _int(health.get("timeout"), 1, f"{check_where}.timeout", errors, 10)
        retries = _int(health.get("retries"), 1, f"{check_where}.retries", errors, 3)
        start_period = _int(health.get("start_period"), 0, f"{check_where}.start_period", errors, 0)
        docker += [
            f"--health-cmd={_fill(cmd or '', values, check_where + '.test', errors)}",
            f"--health-interval={interval}s",
            f"--health-timeout={timeout}s",
            f"--health-retries={retries}",
            f"--health-start-period={start_period}s",
        ]
    if spec.get("gpu") and instance_gpu is not None:
        docker += ["--runtime=nvidia", f"--gpus=device={instance_gpu}"]
    docker += [_fill(a, values, f"{where}.docker_args", errors) for a in spec.get("docker_args") or []]
    app = [
        _fill(a, values, f"{where}.command", errors) for a in _words(spec.get("command"), f"{where}.command", errors)
    ]
    return {
        "name": name,
        "instance": i,
        "unit": layout.companion_unit(i, name),
        "container": container,
        "image": str(spec["image"]),
        "ports": ports,
        "protocols": protocols,
        "own_ports": own,
        "docker_args": docker,
        "app_args": app,
        "container_env": env,
        "dirs": dirs,
        "uid_gid": uid_gid,
        **{k: v for k, v in timeouts(spec, errors).items() if k != "name"},
        "health_interval": interval,
    }, errors


def wanted_on(spec, i) -> bool:
    chosen = spec.get("instances")
    return not chosen or i in {int(str(x)) for x in chosen}
