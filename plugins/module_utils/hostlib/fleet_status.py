# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""Status of every Isaac Sim instance on one host, at a fixed cost.

Whatever the number of instances, one status costs:
  - one `systemctl show` for all units,
  - two Docker API calls (containers, images),
  - one GPU query (NVML in-process, or one nvidia-smi),
  - one `journalctl` for the last day's session ends and crashes,
  - one more `journalctl` only when log lines are asked for (bounded to the lines
    asked; read again only for units a chattier one crowded out).
The two first commands run while the rest is read (see start()).
Everything else is read from files: the env files the role writes
(/etc/isaac-sim/instance-N.env), the ready markers of the readiness gate
(/run/isaac-sim/instance-N.ready) and /proc.

The parsers are pure functions over recorded output; gather() does the I/O.
"""

from __future__ import annotations

import glob
import json
import os
import re
import shutil
import socket
import subprocess
import time

try:
    from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib import gpu_usage, layout
    from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib.docker_socket import DockerError
    from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib.endpoints import endpoints
except ImportError:  # copied next to the metrics script on a host (roles/isaac_sim/tasks/metrics.yml)
    import gpu_usage
    import layout
    from docker_socket import DockerError
    from endpoints import endpoints

UNIT_PROPERTIES = (
    "Id",
    "LoadState",
    "ActiveState",
    "SubState",
    "UnitFileState",
    "Result",
    "NRestarts",
    "ExecMainStatus",
    "MainPID",
    "ActiveEnterTimestampMonotonic",
)
UNIT_GLOB = layout.UNIT_GLOB
_UNIT_ID = layout.UNIT_RE
_CONTAINER_NAME = layout.CONTAINER_RE
unit_name = layout.unit


COMPANION_UNIT_GLOB = "isaac-sim-*@*.service"
_UNIT_PREFIX, _UNIT_SUFFIX = UNIT_GLOB.split("*")
_COMPANION_PREFIX = COMPANION_UNIT_GLOB.split("*", maxsplit=1)[0]


def systemctl_show_argv(ids, companions=()) -> list:
    """One call: the configured units by name (loaded or not), every other loaded instance, and the
    companions' units ([(id, name)] configured, and every other loaded one).

    The others are asked for by patterns that leave out the named units: a unit both named and
    matched by a pattern is shown twice, and each unit shown costs round trips to systemd (the
    plain globs doubled the call's time)."""
    named = [layout.companion_unit(i, name) for i, name in companions]
    names = sorted({name for _i, name in companions})
    patterns = [_UNIT_PREFIX + p + _UNIT_SUFFIX for p in others([str(i) for i in ids])]
    # a companion of another name; then each name's other instances
    patterns += [f"{_COMPANION_PREFIX}{p}@*{_UNIT_SUFFIX}" for p in others(names, end="@")]
    for name in names:
        mine = [str(i) for i, n in companions if n == name]
        patterns += [f"{_COMPANION_PREFIX}{name}@{p}{_UNIT_SUFFIX}" for p in others(mine)]
    return (
        ["systemctl", "show", "--no-pager", "-p", ",".join(UNIT_PROPERTIES)]
        + [unit_name(i) for i in ids]
        + named
        + patterns
    )


def others(words, end="") -> list:
    """Shell patterns that, each followed by a tail, match every non-empty word but those given
    (`end`: the characters a tail may begin with, which no word contains). Each one is a glob:
    systemctl shows a plain name even when it is not loaded. Built over the words' prefix tree:
    after each prefix, any character no word goes on with (nor a tail, after a whole word); after
    a whole word that no other word goes on from, any character more; a prefix that is no word, itself."""
    tree = {}
    for word in words:
        node = tree
        for char in word:
            node = node.setdefault(char, {})
        node[""] = {}
    patterns = []
    stack = [("", tree)]
    while stack:
        prefix, node = stack.pop()
        nexts = sorted(c for c in node if c)
        banned = nexts + (sorted(end) if "" in node else [])
        # '-' last in a class is itself, not a range
        banned.sort(key=lambda c: c == "-")
        patterns.append(prefix + ("[!" + "".join(banned) + "]*" if banned else "?*"))
        if prefix and "" not in node:
            patterns.append(f"{prefix[:-1]}[{prefix[-1]}]")
        stack += [(prefix + c, node[c]) for c in reversed(nexts)]
    return patterns


def parse_companion_units(text: str) -> dict:
    """{(instance id, companion name): {property: value}} from the same `systemctl show` output."""
    units = {}
    for block in re.split(r"\n\s*\n", text.strip()):
        props = dict(line.split("=", 1) for line in block.splitlines() if "=" in line)
        match = layout.COMPANION_UNIT_RE.match(props.get("Id", ""))
        if match:
            units[(int(match.group(2)), match.group(1))] = props
    return units


def parse_systemctl_show(text: str) -> dict:
    """{instance id: {property: value}} from `systemctl show` (blank-line separated blocks)."""
    units = {}
    for unit, props in layout.parse_shown(text).items():
        match = _UNIT_ID.match(unit)
        if match:
            units[int(match.group(1))] = props
    return units


def parse_env_file(text: str) -> dict:
    """KEY=VALUE lines as systemd reads them (the layout's env-file format)."""
    return layout.parse(text)


def read_env_files(config_dir: str) -> tuple:
    """({id: env}, [errors]) for every instance-N.env the role wrote."""
    found, errors = {}, []
    for i, path, text in _instance_files(config_dir, "instance-*.env", layout.ENV_FILE_RE):
        if isinstance(text, OSError):
            errors.append(f"cannot read {path}: {text.strerror} (the module needs root: become: true)")
        else:
            found[i] = parse_env_file(text)
    return found, errors


def _instance_files(directory: str, name_glob: str, pattern: re.Pattern):
    """(instance id, path, text) of each instance's file in `directory`; the OSError as text when unreadable."""
    for path in glob.glob(os.path.join(directory, name_glob)):
        i = layout.instance_id(pattern, path)
        if i is None:
            continue
        try:
            with open(path) as fh:
                yield i, path, fh.read()
        except OSError as exc:
            yield i, path, exc


def read_companion_env_files(config_dir: str) -> dict:
    """{(instance id, companion name): env} for every instance-N.NAME.env the role wrote."""
    found = {}
    for path in glob.glob(os.path.join(config_dir, "instance-*.*.env")):
        match = layout.COMPANION_ENV_RE.match(os.path.basename(path))
        if not match:
            continue
        try:
            with open(path) as fh:
                found[(int(match.group(1)), match.group(2))] = parse_env_file(fh.read())
        except OSError:
            continue
    return found


def read_companion_markers(run_dir: str) -> set:
    """{(instance id, companion name)} whose readiness gate left its marker."""
    found = set()
    for path in glob.glob(os.path.join(run_dir, "instance-*.*.ready")):
        match = re.match(r"^instance-(\d+)\.([a-z][a-z0-9-]*)\.ready\Z", os.path.basename(path))
        if match:
            found.add((int(match.group(1)), match.group(2)))
    return found


def read_ready_markers(run_dir: str) -> dict:
    """{id: epoch seconds} of the gate's markers: the instance printed its ready line then."""
    markers = {}
    for i, path, text in _instance_files(run_dir, "instance-*.ready", layout.MARKER_RE):
        if isinstance(text, OSError):
            continue
        stamp = text.strip()
        try:
            markers[i] = int(stamp) if stamp.isdigit() else int(os.path.getmtime(path))
        except OSError:
            continue
    return markers


def read_loans(run_dir: str, endings=None) -> dict:
    """{id: run} of the instances lent to a test run or a session (lifecycle.lend's marker, a directory
    whose file `run` names the borrower); a marker being made or unreadable says "a run". endings: a
    dict filled with {id: {at, by}} where a rollout ends the session (lifecycle.held_after's notice)."""
    loans = {}
    for path in glob.glob(os.path.join(run_dir, "instance-*.lent")):
        i = layout.instance_id(layout.LENT_RE, path)
        if i is None:
            continue
        try:
            with open(os.path.join(path, "run")) as fh:
                words = fh.read().split()
        except OSError:
            words = []
        loans[i] = words[0] if words else "a run"
        if endings is not None:
            try:
                with open(os.path.join(path, "ending")) as fh:
                    notice = json.load(fh)
                endings[i] = {"at": float(notice["at"]), "by": str(notice.get("by") or "an operator")}
            except (OSError, ValueError, TypeError, KeyError):
                pass
    return loans


def read_cache_states(run_dir: str) -> dict:
    """{id: "warm" or "cold"}: what isaac-sim-cache-state found in the instance's caches at its last start."""
    states = {}
    for i, _path, text in _instance_files(run_dir, "instance-*.cache", layout.CACHE_STATE_RE):
        if not isinstance(text, OSError) and text.strip() in ("warm", "cold"):
            states[i] = text.strip()
    return states


def _ready_after(marker, container: dict | None):
    """Seconds from the container's start to its ready marker, or None (the gate polls each second)."""
    started = (container or {}).get("started_at")
    if not isinstance(marker, int) or not isinstance(started, int) or marker < started:
        return None
    return marker - started


def health_of(status: str) -> str:
    """Docker's health from the list API's status text; "none" without a healthcheck."""
    for word, health in (("(healthy)", "healthy"), ("(unhealthy)", "unhealthy"), ("(health: starting)", "starting")):
        if word in (status or ""):
            return health
    return "none"


def parse_containers(containers: list, images: list, now: float) -> dict:
    """{name: container record} for the isaac-sim-* containers of the list API."""
    digests = {}
    for image in images or []:
        # every digest the image was pulled by (a tag's and a pinned one's can both name it)
        digests[image.get("Id")] = [d.split("@", 1)[1] for d in image.get("RepoDigests") or [] if "@" in d]
    out = {}
    for c in containers or []:
        names = [n for n in c.get("Names") or [] if _CONTAINER_NAME.match(n)]
        if not names:
            continue
        name = _CONTAINER_NAME.match(names[0]).group(1)
        label = (c.get("Labels") or {}).get(layout.LABEL_INSTANCE)
        host_service = (c.get("Labels") or {}).get(layout.LABEL_HOST_SERVICE)
        companion = (c.get("Labels") or {}).get(layout.LABEL_COMPANION)
        created = c.get("Created")
        running = c.get("State") == "running"
        out[name] = {
            "id": c.get("Id"),
            "short_id": (c.get("Id") or "")[:12],
            "state": c.get("State"),
            "status": c.get("Status"),
            "health": health_of(c.get("Status")),
            # systemd creates a new container on every start (docker run --rm), so creation is the start
            "started_at": created,
            "uptime_s": int(now - created) if running and created else None,
            "image": c.get("Image"),
            "image_id": c.get("ImageID"),
            "digest": (digests.get(c.get("ImageID")) or [None])[0],
            "digests": digests.get(c.get("ImageID")) or [],
            "labelled_instance": int(label) if label and label.isdigit() else None,
            "companion": companion,
            "host_service": host_service,
            # a container of a test run (an experience), with its service
            "test_run": (c.get("Labels") or {}).get(layout.LABEL_RUN),
            "test_service": (c.get("Labels") or {}).get(layout.LABEL_RUN_SERVICE),
        }
    return out


def parse_limits(docker_args: str) -> dict:
    """Memory, shm, GPU and CPU limits from the instance's docker arguments (the env file's shell words)."""
    try:
        args = layout.split_args(docker_args)
    except ValueError:
        args = (docker_args or "").split()
    limits = {}
    for arg in args:
        for flag, key in (("--memory", "memory"), ("--shm-size", "shm_size"), ("--gpus", "gpus"), ("--cpus", "cpus")):
            if arg.startswith(flag + "="):
                limits[key] = arg[len(flag) + 1 :]
    return limits


def ports_of(env: dict) -> dict:
    return {
        key[len(layout.K_PORT_PREFIX) :].lower(): int(value)
        for key, value in env.items()
        if key.startswith(layout.K_PORT_PREFIX) and value.isdigit()
    }


def state_of(unit: dict | None, container: dict | None, ready: bool) -> str:
    """One word for a person: ready, starting, running, restarting, failed, stopped, stray-container."""
    active = (unit or {}).get("ActiveState", "")
    sub = (unit or {}).get("SubState", "")
    if active == "active":
        return "ready" if ready else "running"
    if active == "activating":
        return "restarting" if sub == "auto-restart" else "starting"
    if active == "deactivating":
        return "stopping"
    if active == "failed":
        return "failed"
    if container and container.get("state") == "running":
        return "running"
    return "stopped"


def down_reason(unit: dict | None, name: str) -> str | None:
    """Why a configured instance's unit is down, in a person's words; None while it serves or
    is on its way back (systemd restarting it)."""
    unit = unit or {}
    active = unit.get("ActiveState", "")
    result = unit.get("Result", "")
    if active == "failed" and _int(unit.get("ExecMainStatus")) == layout.PORTS_HELD_STATUS:
        return (
            f"a port of its block is held by another process, so it is not restarted. Fix: read "
            f"journalctl -u {name} for the port, free it, then systemctl reset-failed {name} and start it"
        )
    if active == "failed" and _int(unit.get("ExecMainStatus")) == layout.POLICY_REFUSED_STATUS:
        return (
            f"the container policy refused the container Docker made for it, so it is not started. Fix: read "
            f"journalctl -u {name} for what Docker made, change the instance's settings, then deploy again"
        )
    # Restart=always: a failed unit is one systemd stopped restarting. A refused manual start reads
    # start-limit-hit; a refused automatic restart keeps the last run's result (systemd 247-255).
    if active == "failed" and (result == "start-limit-hit" or _int(unit.get("NRestarts")) > 0):
        return (
            f"crash loop: it crashed or failed to get ready too often within its start limit, so systemd "
            f"stopped restarting it (session ends are not counted). Fix: read journalctl -u {name}, then "
            f"deploy again, or systemctl reset-failed {name} and start it"
        )
    if active == "failed":
        return f"failed ({result or 'unknown result'}): read journalctl -u {name}"
    if active == "inactive":
        return "stopped: systemctl stop, isaac-sim.target stopped, or Docker stopped under it"
    return None


def _int(value, default=0):
    try:
        return int(value)
    except (TypeError, ValueError):
        return default


def build(
    envs: dict,
    units: dict,
    containers: dict,
    markers: dict,
    gpu: dict | None,
    pid_containers: dict,
    default_address: str,
    address_override: str = "",
    now: float | None = None,
    monotonic_now: float | None = None,
    only: list | None = None,
    companion_envs: dict | None = None,
    companion_units: dict | None = None,
    companion_markers: set | None = None,
    cache_states: dict | None = None,
) -> list:
    """Instance records, configured first, then strays, sorted by instance number.

    pid_containers maps a GPU process's pid to its container id (or None). The companions
    ({(id, name): env}, {(id, name): unit}, markers) are listed under their instance.
    cache_states: {id: "warm" or "cold"} at the container's start (read_cache_states).
    """
    now = time.time() if now is None else now
    monotonic_now = time.monotonic() if monotonic_now is None else monotonic_now
    configured = set(envs)
    by_id = {}
    comp_containers = {}
    for name, c in containers.items():
        if c.get("host_service") or c.get("test_run"):  # the Hub cache, a test run: never a stray
            continue
        if c.get("companion") and c.get("labelled_instance") is not None:
            comp_containers[(c["labelled_instance"], c["companion"])] = c
            continue
        suffix = name[len(layout.CONTAINER_PREFIX) :]
        key = int(suffix) if suffix.isdigit() else name
        by_id[key] = c
    stray_units = {
        i
        for i, u in units.items()
        if i not in configured and (u.get("ActiveState") not in ("inactive", "") or u.get("UnitFileState") == "enabled")
    }
    keys = sorted(configured | stray_units | {k for k in by_id if isinstance(k, int)}) + sorted(
        k for k in by_id if not isinstance(k, int)
    )
    gpu_by_container = {}
    for proc in (gpu or {}).get("processes", []):
        cid = pid_containers.get(proc["pid"])
        if cid:
            gpu_by_container.setdefault(cid, []).append(proc)

    records = []
    for key in keys:
        if only is not None and key not in only:
            continue
        env = envs.get(key, {})
        unit = units.get(key) if isinstance(key, int) else None
        container = by_id.get(key)
        has_unit = unit is not None and unit.get("LoadState") == "loaded"
        is_configured = key in configured
        ready = bool(
            is_configured
            and key in markers
            and (unit or {}).get("ActiveState") == "active"
            and container is not None
            and container.get("state") == "running"
        )
        ports = ports_of(env)
        release = env.get(layout.K_RELEASE)
        # an instance with an address of its own is reached there, whatever the host is called
        own = env.get(layout.K_ADDRESS) or None
        address = own or address_override or env.get(layout.K_PUBLIC_ADDRESS) or default_address
        comps = (
            companion_records(
                key, companion_envs or {}, companion_units or {}, comp_containers, companion_markers or set()
            )
            if isinstance(key, int)
            else []
        )
        served = [p["port"] for c in comps if c["configured"] for p in c["ports"]]
        # what the instance opens (its env file's checked ports), so no URL names a closed port
        opened = {spec.split("/", 1)[-1] for spec in env.get(layout.K_PORTS, "").split()}
        listens = [kind for kind, port in ports.items() if str(port) in opened] if layout.K_PORTS in env else None
        urls = endpoints(release, ports, address, served, listens) if release and ports else {}
        procs = gpu_by_container.get((container or {}).get("id"), [])
        gpu_index = env.get(layout.K_GPU, "")
        pinned = env.get(layout.K_IMAGE_PINNED, "").rpartition("@")[2] or None
        running = (container or {}).get("digests") or []
        active_enter = _int((unit or {}).get("ActiveEnterTimestampMonotonic"))
        active = (unit or {}).get("ActiveState") == "active"
        records.append(
            {
                "id": key if isinstance(key, int) else None,
                "name": layout.container(key) if isinstance(key, int) else key,
                # a stray container with no unit behind it has no unit to act on
                "unit": unit_name(key) if isinstance(key, int) and (is_configured or has_unit) else None,
                "configured": is_configured,
                "stray": not is_configured,
                "state": state_of(unit if has_unit else None, container, ready)
                if is_configured or has_unit
                else "stray-container",
                "ready": ready,
                "ready_since": markers.get(key) if ready else None,
                # from the container's start (docker run creates it then) to the ready line the gate saw
                "ready_after_s": _ready_after(markers.get(key), container) if ready else None,
                "cache_at_start": (cache_states or {}).get(key) if ready else None,
                "active_state": (unit or {}).get("ActiveState"),
                "sub_state": (unit or {}).get("SubState"),
                "enabled": (unit or {}).get("UnitFileState") == "enabled",
                "unit_file_state": (unit or {}).get("UnitFileState"),
                "restarts": _int((unit or {}).get("NRestarts")),
                "down_reason": down_reason(unit if has_unit else None, unit_name(key))
                if is_configured and isinstance(key, int)
                else None,
                "active_since": int(now - (monotonic_now - active_enter / 1e6)) if active and active_enter else None,
                "container": container,
                "uptime_s": (container or {}).get("uptime_s"),
                # the container's healthcheck: healthy, unhealthy, starting, or none
                "health": (container or {}).get("health") or "none",
                "release": release,
                "image": env.get(layout.K_IMAGE) or (container or {}).get("image"),
                "image_id": (container or {}).get("image_id") or env.get(layout.K_IMAGE_ID),
                "digest": pinned if pinned and pinned in running else (container or {}).get("digest"),
                # the digest the deploy pinned the tag to, for the whole fleet (image_pin.py)
                "pinned": pinned,
                "drift": drift(pinned, running, (container or {}).get("digest")),
                "profile": env.get(layout.K_PROFILE) or ("streaming" if env else None),
                "ports": ports,
                "public_address": address,
                "address": own,
                "urls": urls,
                "gpu": int(gpu_index) if gpu_index.isdigit() else None,
                "gpu_memory_used_mib": sum(p["used_mib"] or 0 for p in procs) if procs else (0 if gpu else None),
                "gpu_processes": procs,
                "limits": parse_limits(env.get(layout.K_DOCKER_ARGS, "")),
                "companions": comps,
            }
        )
    return records


def drift(pinned, running: list, shown) -> str | None:
    """Why a running instance is not on the digest its deploy pinned, or None: a container started
    from another image (before the deploy reached it, or by hand)."""
    if not pinned or not running or pinned in running:
        return None
    return f"runs {(shown or running[0])[:19]}, its deploy pinned {pinned[:19]}"


def companion_records(i, envs: dict, units: dict, containers: dict, markers: set) -> list:
    """The companions of instance i: configured ones (env file) and any unit or container of one."""
    names = sorted(
        {n for (j, n) in list(envs) + list(containers) if j == i}
        | {n for (j, n), u in units.items() if j == i and u.get("ActiveState") not in ("inactive", "")}
    )
    out = []
    for name in names:
        env, unit, container = envs.get((i, name)), units.get((i, name)), containers.get((i, name))
        ready = bool(
            env is not None
            and (i, name) in markers
            and (unit or {}).get("ActiveState") == "active"
            and (container or {}).get("state") == "running"
        )
        own = [spec.split("/", 1) for spec in (env or {}).get(layout.K_PORTS, "").split() if "/" in spec]
        out.append(
            {
                "name": name,
                "unit": layout.companion_unit(i, name),
                "container_name": layout.companion_container(i, name),
                "configured": env is not None,
                "state": state_of(unit, container, ready),
                "ready": ready,
                "active_state": (unit or {}).get("ActiveState"),
                "enabled": (unit or {}).get("UnitFileState") == "enabled",
                "restarts": _int((unit or {}).get("NRestarts")),
                "image": (env or {}).get(layout.K_IMAGE) or (container or {}).get("image"),
                "health": (container or {}).get("health") or "none",
                "uptime_s": (container or {}).get("uptime_s"),
                "container": container,
                "ports": [{"proto": proto, "port": int(port)} for proto, port in own if port.isdigit()],
            }
        )
    return out


def summarize(records: list) -> dict:
    configured = [r for r in records if r["configured"]]
    return {
        "configured": len(configured),
        "running": sum(1 for r in records if (r["container"] or {}).get("state") == "running"),
        "ready": sum(1 for r in records if r["ready"]),
        "failed": sum(1 for r in records if r["state"] == "failed"),
        "stopped": sum(1 for r in configured if r["state"] == "stopped"),
        "stray": sum(1 for r in records if r["stray"]),
    }


JOURNAL_FIELDS = "MESSAGE,_SYSTEMD_UNIT,UNIT"


def journal_argv(ids, limit: int) -> list:
    """One reverse read of the journal for the asked units: the newest `limit` entries, newest first, as JSON."""
    argv = ["journalctl", "--no-pager", "--reverse", "--output=json", f"--output-fields={JOURNAL_FIELDS}"]
    argv.append(f"--lines={limit}")
    for i in ids:
        argv += ["-u", unit_name(i)]
    return argv


def take_journal_tail(lines, ids, count: int) -> dict:
    """{id: [messages, oldest first]} with the last `count` per unit, from reverse JSON lines.

    Stops reading as soon as every unit has its lines.
    """
    wanted = {unit_name(i): i for i in ids}
    tails = {i: [] for i in ids}
    pending = set(ids)
    for line in lines:
        try:
            entry = json.loads(line)
        except ValueError:
            continue
        unit = entry.get("_SYSTEMD_UNIT") if entry.get("_SYSTEMD_UNIT") in wanted else entry.get("UNIT")
        i = wanted.get(unit)
        if i is None or i not in pending:
            continue
        message = entry.get("MESSAGE")
        if isinstance(message, list):  # journald sends non-UTF-8 messages as byte lists
            message = bytes(message).decode("utf-8", "replace")
        tails[i].append(message if message is not None else "")
        if len(tails[i]) >= count:
            pending.discard(i)
            if not pending:
                break
    return {i: list(reversed(t)) for i, t in tails.items()}


# isaac-sim-run's records of how an app ended (journalctl -t isaac-sim-events), by kind
EVENTS_TAG = "isaac-sim-events"
_EVENT_KINDS = {
    "session_end": "session_ends",
    "crash": "crashes",
    "unhealthy_restart": "unhealthy_restarts",
    "docker_away": "docker_away",
}
_EVENT = re.compile(r"^event=([a-z_]+) container=(isaac-sim-\d+)\Z")


def events_argv(since: str = "-24h") -> list:
    return ["journalctl", "-t", EVENTS_TAG, "--since", since, "-o", "cat", "--no-pager", "-q"]


def parse_events(text: str) -> dict:
    """{container: {kind: count}} from isaac-sim-run's records: what systemd's NRestarts, reset by
    every session end and every deliberate start, cannot keep."""
    counts = {}
    for line in text.splitlines():
        m = _EVENT.match(line.strip())
        if m and m.group(1) in _EVENT_KINDS:
            counts.setdefault(m.group(2), dict.fromkeys(_EVENT_KINDS.values(), 0))[_EVENT_KINDS[m.group(1)]] += 1
    return counts


def read_journal_tails(run, ids, count: int) -> tuple:
    """({id: [messages, oldest first]}, error or None): the last `count` journal lines of each unit.

    One journalctl for all the units reads at most count x units entries, so the output stays
    small however long the journal is. A chatty unit may fill that window before a quiet one
    has its lines; then the units still short are read again without the ones served. Each
    further read serves at least one more unit or reaches the journal's end, so the common
    case is one read (the module's fixed cost) and the worst case one per unit.
    """
    tails, pending, limit = {}, list(ids), count * len(ids)
    while pending:
        rc, out, err = run(journal_argv(pending, limit))
        if rc != 0:
            return tails, f"journalctl failed: {(err or out).strip()}"
        lines = out.splitlines()
        got = take_journal_tail(lines, pending, count)
        tails.update(got)
        if len(lines) < limit:  # the journal holds nothing older for these units
            break
        short = [i for i in pending if len(got[i]) < count]
        # entries matched by -u but kept by no unit (a core dump's) can fill the window: widen it
        limit = count * len(short) if len(short) < len(pending) else limit * 2
        pending = short
    return tails, None


def default_ipv4() -> str:
    """The source address of the default route (no packet is sent), else 127.0.0.1 (also where a
    sandbox allows no IPv4 socket at all)."""
    try:
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    except OSError:
        return "127.0.0.1"
    try:
        sock.connect(("192.0.2.1", 9))  # TEST-NET-1: never routed anywhere real
        return sock.getsockname()[0]
    except OSError:
        return "127.0.0.1"
    finally:
        sock.close()


def gather(
    run,
    stream,
    docker,
    import_nvml,
    config_dir=layout.CONFIG_DIR,
    run_dir=layout.RUN_DIR,
    unit_path=layout.UNIT_DIR + "/" + layout.UNIT_TEMPLATE,
    proc="/proc",
    public_address="",
    gpu_source="auto",
    log_lines=0,
    only=None,
    start=None,
) -> dict:
    """The whole status of this host. run(argv) -> (rc, out, err) runs a command.

    docker is a DockerSocket (or anything with containers(prefix) and images()).
    start(argv) -> wait, where wait() -> (rc, out, err): a command begun at once and read later
    (start() below): `systemctl show` and the journal's events run while the files, Docker and
    the GPU are read. Either may be None: without start a command runs when it is read; without
    run, it is started and read at once.
    `stream` is not used (the journal is read through run); it stays in the signature while
    roles/isaac_sim/files/isaac-sim-metrics passes None in its place.
    """
    if run is None and start is None:  # each is made from the other: one is needed
        raise TypeError("fleet_status.gather needs run or start")
    start = start or (lambda argv: lambda: run(argv))
    run = run or (lambda argv: start(argv)())
    lap = _Laps()
    errors = []
    events_read = start(events_argv())
    envs, env_errors = read_env_files(config_dir)
    errors += env_errors
    deployed = bool(envs) or os.path.exists(unit_path)

    companion_envs = read_companion_env_files(config_dir)
    lap("files")
    systemd_read = start(systemctl_show_argv(sorted(envs), sorted(companion_envs)))

    containers, docker_ok = {}, True
    try:
        now = time.time()
        containers = parse_containers(docker.containers(layout.CONTAINER_PREFIX), docker.images(), now)
    except DockerError as exc:
        docker_ok = False
        errors.append(str(exc))
    lap("docker")

    usage, gpu_error = gpu_usage.read(gpu_source, run, import_nvml)
    pid_containers = {p["pid"]: gpu_usage.container_of_pid(p["pid"], proc) for p in (usage or {}).get("processes", [])}
    lap("gpu")
    rc, out, err = systemd_read()
    units = parse_systemctl_show(out) if rc == 0 else {}
    companion_units = parse_companion_units(out) if rc == 0 else {}
    if rc != 0:
        errors.append(f"systemctl show failed: {err.strip()}")
    lap("systemd")

    address = public_address or default_ipv4()
    records = build(
        envs,
        units,
        containers,
        read_ready_markers(run_dir),
        usage,
        pid_containers,
        default_address=address,
        address_override=public_address,
        only=only,
        companion_envs=companion_envs,
        companion_units=companion_units,
        companion_markers=read_companion_markers(run_dir),
        cache_states=read_cache_states(run_dir),
    )
    endings = {}
    loans = read_loans(run_dir, endings)
    for r in records:
        # the one claim on an instance: a test run's loan or a person's session, the same marker
        r["lent_to"] = loans.get(r["id"]) if r["id"] is not None else None
        # when a rollout ends the session that holds it (the door warns its holder)
        r["lent_ending"] = endings.get(r["id"]) if r["id"] is not None else None
    lap("build")
    rc, out, err = events_read()
    if rc != 0:
        errors.append(f"journalctl -t {EVENTS_TAG} failed: {(err or out).strip()}")
    events = parse_events(out) if rc == 0 else {}
    for r in records:
        if r["id"] is not None:
            r["last_day"] = events.get(r["name"], dict.fromkeys(_EVENT_KINDS.values(), 0)) if rc == 0 else None
    lap("events")
    with_units = [r["id"] for r in records if r["unit"]]
    if log_lines and with_units:
        tails, journal_error = read_journal_tails(run, with_units, log_lines)
        if journal_error:
            errors.append(journal_error)
        for r in records:
            r["logs"] = tails.get(r["id"], [])
    lap("logs")
    return {
        "deployed": deployed,
        "instances": records,
        "summary": summarize(records),
        "public_address": address,
        "docker_available": docker_ok,
        "gpu": {
            "source": (usage or {}).get("source", "none"),
            "driver": (usage or {}).get("driver"),
            "gpus": (usage or {}).get("gpus", []),
            "error": gpu_error,
        },
        # where the host serves this status live (the dashboard refreshes from it), if it does
        "status_url": read_env_value(config_dir, layout.STATUS_ENV, layout.K_STATUS_URL),
        # where the host's action agent listens (the front door's mutual TLS only), if it runs one
        "agent_url": read_env_value(config_dir, layout.AGENT_ENV, layout.K_AGENT_URL),
        # drained: no new claim here (test runs, sessions); what runs goes on
        "drained": read_drained(config_dir),
        # the host's own services that run in containers (the Hub cache)
        "host_services": [
            {"name": c["host_service"], "container": name, "state": c["state"], "uptime_s": c["uptime_s"]}
            for name, c in sorted(containers.items())
            if c.get("host_service")
        ],
        # containers of the test runs going on (playbooks/experience.yml)
        "test_runs": [
            {"run": c["test_run"], "service": c["test_service"], "container": name, "state": c["state"]}
            for name, c in sorted(containers.items())
            if c.get("test_run")
        ],
        "errors": errors,
        # where this call spent its time, so a slower status shows which part grew
        "timings_ms": lap.parts,
    }


def start(argv, timeout=60):
    """Begins a command now, in the C locale; the Command returned reads it when called.

    Two commands read one after the other never wait on each other: each writes to pipes of its
    own. A command that is not installed, cannot start or outlasts `timeout` seconds reads as
    rc 127 with why.
    """
    path = argv[0] if "/" in argv[0] else shutil.which(argv[0], path=os.environ.get("PATH", "") + _SBIN)
    if not path:
        return Command(argv[0], why=f"{argv[0]} is not installed")
    try:
        proc = subprocess.Popen(
            [path] + list(argv[1:]),
            stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            env=dict(os.environ, LC_ALL="C"),
            text=True,
        )
    except OSError as exc:
        return Command(argv[0], why=f"{argv[0]}: {exc.strerror}")
    return Command(argv[0], proc, timeout=timeout)


class Command:
    """A command begun by start(): calling it waits for it and gives (rc, out, err)."""

    def __init__(self, name, proc=None, why="", timeout=60):
        self.name, self.proc, self.why, self.timeout = name, proc, why, timeout

    @property
    def spawned(self) -> bool:
        return self.proc is not None

    def __call__(self):
        if self.proc is None:
            return 127, "", self.why
        try:
            out, err = self.proc.communicate(timeout=self.timeout)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.communicate()
            return 127, "", f"{self.name} did not answer within {self.timeout} s"
        return self.proc.returncode, out, err


# where Ansible's modules look for a command beyond PATH
_SBIN = ":/sbin:/usr/sbin:/usr/local/sbin:/bin:/usr/bin"


class _Laps:
    """Milliseconds per part of gather(), each part timed from the end of the one before."""

    def __init__(self):
        self.parts = {}
        self._last = time.perf_counter()

    def __call__(self, part: str) -> None:
        now = time.perf_counter()
        self.parts[part] = round((now - self._last) * 1000, 1)
        self._last = now


def read_drained(config_dir: str):
    """{by, at} where the host is drained (the fleet API's drain, instance/agent.py), else None."""
    try:
        with open(os.path.join(config_dir, os.path.basename(layout.DRAINED))) as fh:
            said = json.loads(fh.read())
    except (OSError, ValueError):
        return None
    return (
        {"by": str(said.get("by") or "?"), "at": said.get("at")} if isinstance(said, dict) else {"by": "?", "at": None}
    )


def read_env_value(config_dir: str, name: str, key: str):
    """One value of an env file the role writes for a host service (its address); None without it."""
    try:
        with open(os.path.join(config_dir, name)) as fh:
            return parse_env_file(fh.read()).get(key) or None
    except OSError:
        return None
