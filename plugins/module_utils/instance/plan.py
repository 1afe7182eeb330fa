# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""Turn the isaac_sim role's variables into a per-instance plan, or errors.

Pure functions: no I/O. The host facts (memory, GPUs, ports already held)
come in as arguments, so every rule here is unit-tested without a host.
Every error names the variable to change and how.
"""

from __future__ import annotations

import ipaddress
import os
import re

from ansible_collections.isaacsim.fleet.plugins.module_utils.common.parse import (
    as_int,
    docker_size,
    mib_of,
    parse_image,
    parse_size,
)
from ansible_collections.isaacsim.fleet.plugins.module_utils.host import registry_mirror
from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib import (
    builtin_companions,
    container_policy,
    layout,
    site_firewall,
    status_server,
)
from ansible_collections.isaacsim.fleet.plugins.module_utils.instance import (
    companions,
    firewall,
    network,
    placement,
    unit_files,
)
from ansible_collections.isaacsim.fleet.plugins.module_utils.instance.releases import (
    ENV,
    KIT,
    MIN_MEMORY,
    RELEASES,
    STREAMING,
    STREAMS,
    WARM_CACHES,
    default_image,
    healthcheck,
    release_of_tag,
)

PORT_MIN = 1024
PORT_MAX = 65535
NGC_DOMAIN = "nvcr.io"
# (name, lowest value, what it is): integers the unit and the lifecycle use
SETTINGS = (
    ("ready_timeout", 1, "seconds an instance may take to become ready"),
    ("stop_timeout", 0, "seconds between SIGTERM and SIGKILL"),
    ("restart_sec", 0, "seconds systemd waits before restarting a failed instance"),
    ("start_limit_burst", 1, "failed starts before systemd gives up"),
    ("health_interval", 1, "seconds between two health checks"),
    ("health_retries", 1, "failed health checks before an instance counts as unhealthy"),
    ("unhealthy_restart", 0, "seconds an unhealthy instance is left before its host restarts it (0: never)"),
)

ENV_NAME_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*\Z")


class PlanError(Exception):
    def __init__(self, errors):
        super().__init__("\n".join(errors))
        self.errors = errors


def _check_numbers(cfg) -> list:
    """Errors for port bases and GPU map entries that are not integers, before anything uses them."""
    errors = []
    for kind, base in (cfg.get("port_bases") or {}).items():
        if as_int(base) is None:
            errors.append(
                f"isaac_sim_port_bases.{kind}: {base!r} is not a port number. Fix: give an integer, e.g. {kind}: 49100."
            )
    for inst, gpu in (cfg.get("gpu_map") or {}).items():
        if as_int(inst) is None or as_int(gpu) is None:
            errors.append(
                f"isaac_sim_gpu_map: {inst!r}: {gpu!r} is not instance number: GPU index. "
                "Fix: use integers, e.g. {0: 0, 1: 1}."
            )
    for name, lowest, what in SETTINGS:
        value = as_int(cfg.get(name))
        if value is None or value < lowest:
            errors.append(
                f"isaac_sim_{name}: {cfg.get(name)!r} is not a valid number of {what}. "
                f"Fix: give an integer of {lowest} or more."
            )
    return errors


def human(nbytes: int) -> str:
    return f"{nbytes / 1024**3:.1f} GiB"


def port_blocks(release: str, count: int, bases: dict, stride: int):
    """{instance: {kind: port}}: each named port is base + i * stride."""
    profile = RELEASES[release]["ports"]
    merged = {kind: spec[1] for kind, spec in profile.items()}
    merged.update({k: v for k, v in (bases or {}).items() if k in profile and as_int(v) is not None})
    return {i: {kind: int(base) + i * stride for kind, base in merged.items()} for i in range(count)}


def _check_ports(release, blocks, bases, stride, held, shared=True):
    errors = []
    profile = RELEASES[release]["ports"]
    unknown = sorted(set(bases or {}) - set(profile))
    if unknown:
        errors.append(
            f"isaac_sim_port_bases: {', '.join(unknown)} is not a port of Isaac Sim {release}, "
            f"which has {', '.join(sorted(profile))}. Fix: use only those names."
        )
        return errors
    if stride < 1:
        errors.append(f"isaac_sim_port_stride: {stride} must be at least 1. Fix: set isaac_sim_port_stride: 1 or more.")
        return errors
    seen = {}
    for i, block in blocks.items():
        for kind, port in block.items():
            if not PORT_MIN <= port <= PORT_MAX:
                errors.append(
                    f"isaac_sim_port_bases: instance {i} {kind} port {port} is outside {PORT_MIN}-{PORT_MAX}. "
                    f"Fix: choose a {kind} base between {PORT_MIN} and "
                    f"{PORT_MAX} - (isaac_sim_instance_count - 1) * isaac_sim_port_stride."
                )
                continue
            if port in seen:
                j, other = seen[port]
                fix = (
                    f"Fix: move the port bases apart by at least isaac_sim_instance_count * isaac_sim_port_stride "
                    f"({len(blocks) * stride}), or change isaac_sim_port_stride."
                    if shared
                    else "Fix: give each port kind a base of its own (each instance has every port at its address)."
                )
                errors.append(
                    f"isaac_sim_port_bases: instance {i} {kind} port {port} overlaps instance {j} {other} port. {fix}"
                )
            else:
                seen[port] = (i, kind)
    for i, block in blocks.items():
        for kind, port in block.items():
            proto = profile[kind][0]
            owner = held.get((proto, port))
            if owner is not None and not owner.get("ours"):
                errors.append(
                    f"isaac_sim_port_bases: instance {i} {kind} port {port}/{proto} is already held on this host by "
                    f"{owner.get('process') or 'another process'}, which is not an Isaac Sim instance of this "
                    f"collection. Fix: stop that process, or move the {kind} base (isaac_sim_port_bases.{kind})."
                )
    return errors


def _check_companion_ports(specs, blocks, stride, held, shared=True) -> list:
    """Errors for companion ports outside the port range, on another instance's or companion's
    port, or held by a process that is not ours. shared: the instances share the host's network
    (else each has its own address, and only its own ports can collide)."""
    errors = []
    every = {port: f"instance {i} {kind}" for i, block in blocks.items() for kind, port in block.items()}
    taken_in = {
        i: every if shared else {port: f"instance {i} {kind}" for kind, port in block.items()}
        for i, block in blocks.items()
    }
    for spec in specs:
        for port_name, (proto, base) in companions.own_ports(spec).items():
            where = f"{companions.VAR}[{spec['name']}].ports.{port_name}"
            for i in blocks:
                if not companions.wanted_on(spec, i):
                    continue
                taken = taken_in[i]
                port = base + i * stride
                if not PORT_MIN <= port <= PORT_MAX:
                    errors.append(
                        f"{where}: instance {i}'s port {port} is outside {PORT_MIN}-{PORT_MAX}. Fix: choose a base "
                        f"between {PORT_MIN} and {PORT_MAX} - (isaac_sim_instance_count - 1) * isaac_sim_port_stride."
                    )
                    continue
                if port in taken:
                    errors.append(
                        f"{where}: instance {i}'s port {port} is also {taken[port]}'s port. Fix: move the base "
                        f"{base} at least isaac_sim_instance_count * isaac_sim_port_stride ({len(blocks) * stride}) "
                        "away from every other base."
                    )
                    continue
                taken[port] = f"instance {i} companion {spec['name']} {port_name}"
                owner = held.get((proto, port)) if shared else None
                if owner is not None and not owner.get("ours"):
                    errors.append(
                        f"{where}: instance {i}'s port {port}/{proto} is already held on this host by "
                        f"{owner.get('process') or 'another process'}. Fix: stop that process, or move the base."
                    )
    return errors


# docker run options a container in another's network namespace (--network=container:) cannot take
_NAMESPACE_OPTIONS = ("-p", "--publish", "-P", "--publish-all", "-h", "--hostname", "--dns", "--add-host",
                      "--network", "--net", "--ip", "--mac-address", "--expose")  # fmt: skip


def _namespace_conflicts(specs) -> list:
    """Errors for companion docker_args that Docker refuses beside --network=container:."""
    errors = []
    for spec in specs:
        for arg in spec.get("docker_args") or [] if isinstance(spec, dict) else []:
            option = str(arg).split("=", 1)[0]
            if option in _NAMESPACE_OPTIONS:
                errors.append(
                    f"{companions.VAR}[{spec.get('name')}].docker_args: {option} cannot be given to a companion of "
                    "an instance with its own address (isaac_sim_network_mode: macvlan): it shares the instance's "
                    "network, address and name. Fix: remove it; the companion is reached at the instance's address."
                )
    return errors


def _confinement(cfg, profile, comp_specs, count) -> list:
    """Errors for docker run arguments of the instances and of the companions that the container policy
    refuses (hostlib/container_policy.py), judged on Docker's own reading of them, unless
    isaac_sim_allowed_docker_args names them; and for bind roots that would hand over the host."""
    allowed = cfg.get("allowed_docker_args") or []
    errors = container_policy.roots_errors(cfg.get("allowed_bind_roots"))
    try:
        container_policy.allowed_keys(allowed)
    except container_policy.DockerArgError as exc:
        return errors + [
            f"{container_policy.ALLOW_VAR}: {exc}. Fix: name each allowed argument as docker run takes it "
            "(--cap-add=SYS_PTRACE), one word per item."
        ]
    ids = list(range(max(count, 0)))
    # the collection's own data paths, then the site's; every bind of an instance comes from one of them
    roots = [cfg.get("data_root") or layout.DATA_ROOT] + [str(r) for r in cfg.get("allowed_bind_roots") or []]
    hub = cfg.get("hub_cache") or {}
    if hub.get("enabled") and hub.get("dir"):
        roots.append(str(hub["dir"]))
    # no GPU is given through the arguments: the plan gives each its own (isaac_sim_gpu_map)
    rules = {"bind_roots": roots, "gpus": [], "root_ok": profile["uid"] == 0}

    def names(chosen):
        return ", ".join(layout.container(i) for i in chosen) or "every instance this host will run"

    errors += container_policy.errors(
        "isaac_sim_extra_docker_args", f"on {names(ids)}", cfg.get("docker_args"), allowed, rules
    )
    # a companion's own image decides its user; one asked for as root is judged as an instance's would be
    rules = dict(rules, root_ok=False)
    for spec in comp_specs:
        if not isinstance(spec, dict):
            continue
        beside = f"the companion of {names([i for i in ids if companions.wanted_on(spec, i)])}"
        for key, args in (
            ("docker_args", spec.get("docker_args")),
            # a host path in volumes is a bind mount, judged as one
            ("volumes", [f"--volume={v}" for v in spec.get("volumes") or [] if str(v).startswith("/")]),
            ("user", [f"--user={spec['user']}"] if spec.get("user") not in (None, "") else []),
        ):
            if isinstance(args, list):
                errors += container_policy.errors(f"{companions.VAR}[{spec.get('name')}].{key}", beside, args,
                                                  allowed, rules)  # fmt: skip
    return errors


def _taken(blocks, comp_specs, stride) -> dict:
    """{port: whose} for every port of the instances' blocks and their companions."""
    taken = {port: f"instance {i} {kind}" for i, block in blocks.items() for kind, port in block.items()}
    for spec in comp_specs:
        for port_name, (_proto, base) in companions.own_ports(spec).items():
            taken.update({base + i * stride: f"instance {i} companion {spec['name']} {port_name}" for i in blocks})
    return taken


def _foreign(held: dict, port: int) -> str:
    """Who holds TCP `port` on the host when it is not one of ours; "" when free or ours."""
    owner = held.get(("tcp", port))
    if not owner or owner.get("ours"):
        return ""
    return owner.get("process") or "another process"


def _service_port(var: str, value, service: str, example: int, taken: dict, held: dict) -> tuple:
    """(port, errors) of a host service's port setting `var`: a port, none of the instances',
    companions' or other host services' (`taken`), none a foreign process holds."""
    port = as_int(value)
    if not isinstance(port, int) or not PORT_MIN <= port <= PORT_MAX:
        return port, [f"{var}: {value!r} is not a port in {PORT_MIN}-{PORT_MAX}. Fix: choose one, e.g. {example}."]
    if port in taken and " companion " in taken[port]:
        # the companion is what moved onto the service's port: name its setting
        _inst, i, _word, name, port_name = taken[port].split(" ", 4)
        return port, [
            f"{companions.VAR}[{name}].ports.{port_name}: {port} (instance {i}'s) is {service}'s port ({var}). "
            f"Fix: give the companion another port, or move {service}."
        ]
    if port in taken:
        return port, [
            f"{var}: {port} is also {taken[port]}'s port. Fix: choose a port no instance, companion or host "
            "service uses."
        ]
    if _foreign(held, port):
        return port, [
            f"{var}: {port}/tcp is already held on this host by {_foreign(held, port)}. Fix: stop it, or choose "
            "another port."
        ]
    return port, []


def _status_endpoint(cfg, taken, held) -> tuple[dict, list]:
    """(the host's status endpoint as the role installs it, errors). Off: {"enabled": False}."""
    want = cfg.get("status_server") or {}
    if not want.get("enabled"):
        return {"enabled": False}, []
    port, errors = _service_port(
        "isaac_sim_status_server_port", want.get("port"), "the status endpoint", 8290, taken, held
    )
    # every address by default: the public address may be a name, or a NAT address the host does
    # not have; who may read is the allow list's business
    address = str(want.get("address") or "0.0.0.0")
    try:
        bound = ipaddress.ip_address(address)
    except ValueError:
        errors.append(
            f"isaac_sim_status_server_address: {address!r} is not an IP address. Fix: give one of this host's "
            "addresses, or leave it empty to listen on every address."
        )
        bound = None
    networks, net_errors = status_server.parse_networks(want.get("allow"))
    errors += net_errors
    if not networks and not net_errors:
        errors.append(
            "isaac_sim_status_server_allow: empty, so nobody could read the status. Fix: list the networks the "
            "dashboard is opened from, e.g. [10.20.0.0/16], or set isaac_sim_status_server_enabled: false."
        )
    logs_networks, logs_errors = status_server.parse_networks(
        want.get("logs_allow"), "isaac_sim_status_server_logs_allow"
    )
    errors += logs_errors
    # a URL a browser can open: the host's public address when listening on every address
    shown = cfg.get("public_address") if bound is not None and bound.is_unspecified else address
    host = f"[{shown}]" if ":" in str(shown) else shown
    return {
        "enabled": True,
        "address": address,
        "port": port,
        "allow": [str(n) for n in networks],
        "logs_allow": [str(n) for n in logs_networks],
        "origins": [str(o) for o in want.get("origins") or []],
        "url": f"http://{host}:{port}/status",
    }, errors


def _agent(cfg, taken, held) -> tuple[dict, list]:
    """(the host's action agent as the role installs it, errors). Off: {"enabled": False}."""
    want = cfg.get("agent") or {}
    if not want.get("enabled"):
        return {"enabled": False}, []
    port, errors = _service_port("isaac_sim_agent_port", want.get("port"), "the action agent", 8291, taken, held)
    networks, net_errors = status_server.parse_networks(want.get("allow"), "isaac_sim_agent_allow")
    errors += net_errors
    if not networks and not net_errors:
        errors.append(
            "isaac_sim_agent_allow: empty, so the front door could not reach the agent. Fix: the front door's "
            "address, e.g. [10.20.0.5/32], or set isaac_sim_agent_enabled: false."
        )
    try:
        soak = float(want.get("soak", 0))
    except (TypeError, ValueError):
        soak = -1.0
    if isinstance(want.get("soak"), bool) or soak < 0:
        errors.append(f"isaac_sim_rollout_soak: {want.get('soak')!r} is not a number of seconds. Fix: e.g. 30.")
    shown = cfg.get("public_address") or ""
    host = f"[{shown}]" if ":" in str(shown) else shown
    return {
        "enabled": True,
        "port": port,
        "allow": [str(n) for n in networks],
        "soak": soak,
        "address": shown,
        "url": f"https://{host}:{port}",
    }, errors


# where a shared cache must never go: it is chowned to the container user
_SYSTEM_DIRS = {
    "/",
    "/bin",
    "/boot",
    "/dev",
    "/etc",
    "/home",
    "/lib",
    "/lib64",
    "/opt",
    "/proc",
    "/root",
    "/run",
    "/sbin",
    "/srv",
    "/sys",
    "/tmp",
    "/usr",
    "/var",
    "/var/lib",
    "/var/cache",
}


def _hub_cache(cfg, release, taken, held) -> tuple[dict, list]:
    """(NVIDIA's Hub Workstation Cache for this host, errors). Off: {"enabled": False}."""
    want = cfg.get("hub_cache") or {}
    if not want.get("enabled"):
        return {"enabled": False}, []
    errors = []
    if "cache/hub" not in RELEASES[release]["mounts"]:
        errors.append(
            f"isaac_sim_hub_cache_enabled: Isaac Sim {release} has no Hub client to use it (6.x has). "
            "Fix: set isaac_sim_hub_cache_enabled: false, or deploy 6.x."
        )
    image = str(want.get("image") or "")
    if parse_image(image) is None:
        errors.append(
            f"isaac_sim_hub_cache_image: {image!r} is not a valid image reference. "
            "Fix: use NVIDIA's, nvcr.io/nvidia/omniverse/hub_workstation_cache:2.0.0, or your registry's copy."
        )
    directory = str(want.get("dir") or f"{cfg['data_root']}/hub-cache")
    root = cfg["data_root"].rstrip("/")
    if (
        not directory.startswith("/")
        or re.search(r"\s|:", directory)
        or os.path.normpath(directory) != directory
        or directory in _SYSTEM_DIRS
        or directory == root
        or re.match(re.escape(root) + r"/instance-\d+(/|$)", directory)
    ):
        errors.append(
            f"isaac_sim_hub_cache_dir: {directory!r} must be a directory of its own: an absolute, normalised path "
            "without spaces or colons, not a system directory, the data root or an instance's directory (it is "
            "handed to user 1234). Fix: use e.g. /var/lib/isaac-sim/hub-cache."
        )
    if cfg.get("network_mode") == network.MACVLAN:
        errors.append(
            "isaac_sim_hub_cache_enabled: the instances have addresses of their own (isaac_sim_network_mode: "
            "macvlan), and macvlan keeps a host and its own containers apart, so they could not reach the host's "
            "Hub cache. Fix: set isaac_sim_hub_cache_enabled: false, or isaac_sim_network_mode: host."
        )
    port = layout.HUB_PORT
    if port in taken:
        errors.append(
            f"isaac_sim_hub_cache_enabled: the Hub cache listens on {port}, which is also {taken[port]}'s port. "
            "Fix: move that base (isaac_sim_port_bases)."
        )
    elif _foreign(held, port):
        errors.append(
            f"isaac_sim_hub_cache_enabled: {port}/tcp, the Hub cache's port, is already held on this host by "
            f"{_foreign(held, port)} (a Hub cache started by hand?). Fix: stop it; the collection runs the host's "
            "one Hub cache."
        )
    hub = {"enabled": True, "image": image, "dir": directory, "port": port}
    # rendered here, so the role writes exactly what the layout defines
    hub["unit"] = unit_files.render_hub_unit(hub, layout.MANAGED)
    hub["dropin"] = unit_files.render_hub_dropin(layout.MANAGED)
    return hub, errors


def instance_profiles(release, count, default, per_instance) -> tuple[dict, list]:
    """({instance: profile}, errors): isaac_sim_profile for every instance, but where
    isaac_sim_instance_profiles names another."""
    known = RELEASES[release]["profiles"]
    errors = []

    def usable(name, what):
        if name in known:
            return True
        others = [r for r, spec in RELEASES.items() if name in spec["profiles"]]
        also = f" (a profile of Isaac Sim {', '.join(others)} only)" if others else ""
        errors.append(
            f"{what}: {name!r} is not a profile of Isaac Sim {release}{also}. Fix: choose one of {', '.join(known)}."
        )
        return False

    usable(default, "isaac_sim_profile")
    chosen = {i: default for i in range(count)}
    for key, name in (per_instance or {}).items():
        inst = as_int(key)
        if not isinstance(inst, int):
            errors.append(
                f"isaac_sim_instance_profiles: {key!r} is not an instance number. Fix: map instance numbers to "
                f"profiles, e.g. {{3: headless}}."
            )
        elif not 0 <= inst < count:
            errors.append(
                f"isaac_sim_instance_profiles: instance {inst} does not exist (instances are 0..{count - 1}). "
                f"Fix: remove it from isaac_sim_instance_profiles."
            )
        elif usable(name, f"isaac_sim_instance_profiles[{inst}]"):
            chosen[inst] = name
    return chosen, errors


def gpu_needs(cfg, profile, count, profiles, comp_specs) -> tuple:
    """({instance: {"mib", "streams"}}, errors): the GPU memory each instance asks for (its own,
    isaac_sim_gpu_memory or the release's minimum, or isaac_sim_instance_gpu_memory, plus its GPU
    companions') and whether it streams (needs a video encoder)."""
    errors = []
    default = profile.get("min_vram_mib")
    if cfg.get("gpu_memory") not in (None, ""):
        default = mib_of(cfg["gpu_memory"])
        if default is None:
            errors.append(
                f"isaac_sim_gpu_memory: {cfg['gpu_memory']!r} is not a size with its unit. "
                "Fix: write it as e.g. 16g or 24576m."
            )
    per_instance = {}
    for key, value in (cfg.get("instance_gpu_memory") or {}).items():
        inst, mib = as_int(key), mib_of(value)
        if inst is None or not 0 <= inst < max(count, 1) or mib is None:
            errors.append(
                f"isaac_sim_instance_gpu_memory: {key!r}: {value!r} is not instance number: size "
                f"(instances are 0..{count - 1}). Fix: e.g. {{3: 40g}}."
            )
        else:
            per_instance[inst] = mib
    needs = {}
    for i in range(count):
        mib = per_instance.get(i, default) or 0
        for spec in comp_specs:
            if isinstance(spec, dict) and companions.wanted_on(spec, i):
                mib += companions.gpu_memory_mib(spec) or 0
        needs[i] = {"mib": mib, "streams": profiles.get(i) in STREAMS}
    return needs, errors


def assign_gpus(cfg, host, needs) -> tuple:
    """({instance: GPU index}, errors, warnings): placement.place over the host's GPUs."""
    gpus = host.get("gpus") or [{"index": i} for i in range(host.get("gpu_count", 0))]
    gpu_map = {as_int(k): as_int(v) for k, v in (cfg.get("gpu_map") or {}).items()}
    current = {as_int(k): as_int(v) for k, v in (host.get("gpu_current") or {}).items()}
    exclusive, limit = bool(cfg.get("gpu_exclusive")), cfg.get("gpu_consumer_encode_sessions", 8)
    return placement.place(gpus, needs, gpu_map, current, exclusive, limit, host.get("gpu_error", ""))


def build(cfg: dict, host: dict) -> dict:
    """The plan for one host. cfg: the role's variables; host: probed facts.

    Raises PlanError with every problem found, so a user fixes them in one go.
    """
    release = cfg["release"]
    if release not in RELEASES:
        raise PlanError(
            [
                f"isaac_sim_release: {release!r} is not a release this collection knows. "
                f"Fix: choose one of {', '.join(RELEASES)}."
            ]
        )
    errors = _check_numbers(cfg)
    if errors:
        raise PlanError(errors)
    profile = RELEASES[release]
    count = cfg["instance_count"]

    if count < 0:
        errors.append(
            f"isaac_sim_instance_count: {count} is below 0. Fix: give the number of instances this host runs "
            "(0 stops and removes them all)."
        )
    if count == 0 and as_int(host.get("serving")) and not cfg.get("scale_to_zero"):
        errors.append(
            f"isaac_sim_instance_count: 0 stops and removes every instance of this host, and "
            f"{as_int(host.get('serving'))} serve now. Fix: set isaac_sim_scale_to_zero: true "
            "(-e isaac_sim_scale_to_zero=true) to take them all down, or give the number to keep."
        )
    if count > cfg["max_instances"]:
        errors.append(
            f"isaac_sim_instance_count: {count} is above isaac_sim_max_instances ({cfg['max_instances']}). "
            f"Fix: lower isaac_sim_instance_count, or raise isaac_sim_max_instances if this host can carry them."
        )
    if not cfg.get("accept_eula"):
        errors.append(
            "isaac_sim_accept_eula: Isaac Sim does not start until its license is accepted. "
            "Fix: read the NVIDIA Isaac Sim license and set isaac_sim_accept_eula: true."
        )

    # empty means NVIDIA's image of the chosen release
    image = cfg.get("image") or default_image(release)
    parsed = parse_image(image)
    if parsed is None:
        errors.append(
            f"isaac_sim_image: {image!r} is not a valid image reference. "
            f"Fix: use REGISTRY/REPOSITORY:TAG or REPOSITORY@sha256:DIGEST, e.g. nvcr.io/nvidia/isaac-sim:5.1.0."
        )
    else:
        tag_release = release_of_tag(parsed[1]) if parsed[1] else None
        if tag_release and tag_release != release:
            errors.append(
                f"isaac_sim_image: tag {parsed[1]} is an Isaac Sim {tag_release} image but isaac_sim_release is "
                f"{release}. Fix: set isaac_sim_release: {tag_release!r}, or pick a {release} image."
            )
        # pulled through a mirror, the mirror holds the key (host/registry_mirror.py)
        mirror = cfg.get("registry_mirror") or ""
        mirrored = bool(mirror) and registry_mirror.mirror_reference(
            image, mirror, cfg.get("registry_mirror_upstream") or ""
        )
        needs_key = (
            parsed[0].split("/")[0] == NGC_DOMAIN and cfg.get("image_pull", "missing") != "never" and not mirrored
        )
        if needs_key and not cfg.get("registry_login") and not host.get("image_present"):
            errors.append(
                f"isaac_sim_registry_password: empty, but {image} is on NGC ({NGC_DOMAIN}), which refuses pulls "
                "without an API key, and the image is not on this host. Fix: set isaac_sim_registry_password to "
                "your NGC API key (from a vault), or load the image on the host and set isaac_sim_image_pull: never."
            )
        if mirrored and not cfg.get("image_pin", True):
            errors.append(
                "isaac_sim_registry_mirror: set while isaac_sim_image_pin is false, and the hosts pull through the "
                "mirror by the digest the deploy pins. Fix: set isaac_sim_image_pin: true, or leave "
                "isaac_sim_registry_mirror empty."
            )
    # a companion's image (the Hub cache's, a web viewer's) comes straight from its registry, never
    # through the mirror: one on NGC needs the key on the host
    if cfg.get("image_pull", "missing") != "never" and not cfg.get("registry_login"):
        for ref in host.get("companion_images_missing") or []:
            if (parse_image(ref) or ("",))[0].split("/")[0] == NGC_DOMAIN:
                errors.append(
                    f"isaac_sim_registry_password: empty, but {ref} (a companion's image or the Hub cache's) is on "
                    f"NGC ({NGC_DOMAIN}), which refuses pulls without an API key, is not on this host and is pulled "
                    "straight from NGC (only the instances' image goes through a mirror). Fix: set "
                    "isaac_sim_registry_password, or put that image in the fleet's own registry."
                )

    memory = parse_size(cfg["memory_limit"])
    shm = parse_size(cfg["shm_size"])
    if memory is None:
        errors.append(
            f"isaac_sim_memory_limit: {cfg['memory_limit']!r} is not a size. "
            "Fix: write it as Docker does, e.g. 8g or 16384m."
        )
    if shm is None:
        errors.append(
            f"isaac_sim_shm_size: {cfg['shm_size']!r} is not a size. Fix: write it as Docker does, e.g. 2g or 512m."
        )
    if memory is not None and memory < 6 * 1024**2:
        errors.append("isaac_sim_memory_limit: Docker needs at least 6m. Fix: raise isaac_sim_memory_limit.")
    if memory is not None and host.get("memory_bytes") and memory * count > host["memory_bytes"]:
        errors.append(
            f"isaac_sim_memory_limit: {count} instances x {cfg['memory_limit']} = {human(memory * count)} is more than "
            f"this host's {human(host['memory_bytes'])} of memory. Fix: lower isaac_sim_memory_limit or "
            f"isaac_sim_instance_count."
        )
    if memory is not None and shm is not None and shm > memory:
        errors.append(
            f"isaac_sim_shm_size: {cfg['shm_size']} is above isaac_sim_memory_limit {cfg['memory_limit']}, and shared "
            f"memory counts against that limit. Fix: lower isaac_sim_shm_size."
        )

    data_root = cfg["data_root"]
    if not data_root.startswith("/") or re.search(r"\s|:", data_root):
        errors.append(
            f"isaac_sim_data_root: {data_root!r} must be an absolute path without spaces or colons. "
            f"Fix: use e.g. /var/lib/isaac-sim."
        )

    for name in list(cfg.get("env") or {}) + list(cfg.get("secret_env_names") or []):
        if not ENV_NAME_RE.match(name) or name.startswith(layout.RESERVED_PREFIX):
            errors.append(
                f"isaac_sim_env / isaac_sim_secret_env: {name!r} is not a usable variable name "
                f"(letters, digits, _; the {layout.RESERVED_PREFIX} prefix is the collection's own). Fix: rename it."
            )

    net, addresses, net_errors = network.plan(cfg, host, list(range(max(count, 0))))
    errors += net_errors
    # own addresses: every instance keeps the release's ports, and nothing on the host can hold them
    shared = net["mode"] == network.HOST
    bases = cfg.get("port_bases") or {}
    stride = cfg.get("port_stride", 1) if shared else 0
    blocks = port_blocks(release, max(count, 0), {k: v for k, v in bases.items() if k in profile["ports"]}, stride)
    # a port can be held twice (our viewer on the host's address, another process on 0.0.0.0):
    # the foreign holder is the one that counts
    held = {}
    for p in host.get("ports_held", []):
        key = (p["proto"], p["port"])
        if key not in held or held[key].get("ours"):
            held[key] = p
    if shared:
        errors += _check_ports(release, blocks, bases, stride, held)
    else:  # one block stands for all: the same ports at other addresses
        errors += _check_ports(release, {0: blocks[0]} if blocks else {}, bases, 1, {}, shared=False)

    profiles, profile_errors = instance_profiles(
        release, max(count, 0), cfg.get("profile") or STREAMING, cfg.get("instance_profiles")
    )
    errors += profile_errors

    comp_specs = cfg.get("companions") or []
    # the built-in companions (the web viewer) first, for the instances of the profiles they serve
    images = builtin_companions.given(cfg)
    built = []
    for name, entry, instances in builtin_companions.serving(profile["ports"], profiles, images):
        # (not `image`: the instances' own, read below)
        built_image = images[entry["variable"]]
        if parse_image(built_image) is None:
            errors.append(
                f"{entry['variable']}: {built_image!r} is not a valid image reference. "
                f"Fix: give the reference {entry['made_by']} built, e.g. {entry['example']}."
            )
        if any(isinstance(c, dict) and c.get("name") == name for c in comp_specs):
            errors.append(
                f"isaac_sim_companions: the name {name} is the built-in {entry['title']}'s "
                f"({entry['variable']}). Fix: rename that companion."
            )
        built.append(companions.built_in(name, built_image, as_int(cfg["health_interval"]), instances))
    comp_specs = built + list(comp_specs)
    # {kind: True when the instance itself listens there} (web_viewer is kept for a companion)
    release_ports = {kind: spec[2] is not None for kind, spec in profile["ports"].items()}
    errors += companions.check(
        comp_specs, release_ports, max(as_int(cfg["max_instances"]) or 0, 1), cfg.get("gpu_enabled")
    )
    if not shared:
        errors += _namespace_conflicts(comp_specs)
    errors += _confinement(cfg, profile, comp_specs, count)
    if not errors:
        errors += _check_companion_ports(comp_specs, blocks, stride, held, shared)
    gpus, gpu_warnings = {}, []
    if cfg.get("gpu_enabled") and host.get("nvidia_smi") is False:
        errors.append(
            "isaac_sim_gpu_enabled: true, but this host has no nvidia-smi (no NVIDIA driver installed). "
            "Fix: install the NVIDIA driver, or set isaac_sim_gpu_enabled: false to run without GPUs."
        )
    elif cfg.get("gpu_enabled"):
        needs, need_errors = gpu_needs(cfg, profile, max(count, 0), profiles, comp_specs)
        errors += need_errors
        if not errors:
            gpus, gpu_errors, gpu_warnings = assign_gpus(cfg, host, needs)
            errors += gpu_errors
    else:
        for name in ("gpu_map", "instance_gpu_memory"):
            if cfg.get(name):
                errors.append(
                    f"isaac_sim_{name}: set while isaac_sim_gpu_enabled is false. Fix: enable GPUs or remove it."
                )
    # the host's own services (status endpoint, Hub) share its network with the instances, or not
    taken = _taken(blocks, comp_specs, stride) if shared else {}
    hub, hub_errors = _hub_cache(cfg, release, taken, held)
    errors += hub_errors
    if hub["enabled"]:
        taken[layout.HUB_PORT] = "the Hub cache"
    status, status_errors = _status_endpoint(cfg, taken, held)
    errors += status_errors
    beside = dict(taken)
    if status["enabled"] and isinstance(status["port"], int):
        beside.setdefault(status["port"], "the status endpoint")
    agent, agent_errors = _agent(cfg, beside, held)
    errors += agent_errors
    # the kinds a site may give networks of their own: any release's, the companions', the host services'
    kinds = {k for r in RELEASES.values() for k in r["ports"]} | set(firewall.HOST_KINDS)
    kinds |= {str(n) for spec in comp_specs if isinstance(spec, dict) for n in (spec.get("ports") or {})}
    fw, fw_errors, fw_warnings = firewall.settings(cfg, kinds)
    errors += fw_errors

    if errors:
        raise PlanError(errors)

    sized = dict(cfg, memory_limit=docker_size(cfg["memory_limit"]), shm_size=docker_size(cfg["shm_size"]))
    sized["hub_dir"] = hub.get("dir")
    warnings = _needs(release, memory) + gpu_warnings + fw_warnings
    instances = [
        _instance(sized, profile, profiles[i], i, blocks[i], gpus.get(i), addresses.get(i)) for i in range(count)
    ]
    for inst in instances:
        inst["companions"] = []
        for spec in comp_specs:
            if not companions.wanted_on(spec, inst["id"]):
                continue
            planned, comp_errors = companions.for_instance(
                spec,
                inst["id"],
                inst["ports"],
                inst["gpu"],
                stride,
                inst["address"] or cfg.get("public_address") or "",
                (profile["uid"], profile["gid"]),
                data_root,
                release_ports,
                # with an address of its own, an instance's companions share its network namespace
                "host" if shared else f"container:{inst['name']}",
            )
            errors += comp_errors
            # on its instance's address: no host port of its own to check at start
            planned["address"] = inst["address"]
            inst["companions"].append(planned)
            inst["dirs"] += planned["dirs"]
    # one unit template per companion, even one no instance of this host has yet
    companion_units = [companions.timeouts(spec, errors) for spec in comp_specs]
    if errors:
        raise PlanError(sorted(set(errors), key=errors.index))
    planned = {
        "release": release,
        "image": image,
        "instances": instances,
        "ids": list(range(count)),
        "ready_pattern": cfg.get("ready_pattern") or profile["ready_pattern"],
        "uid": profile["uid"],
        "gid": profile["gid"],
        "public_address": cfg.get("public_address") or "",
        "memory_limit": sized["memory_limit"],
        "shm_size": sized["shm_size"],
        "settings": {name: as_int(cfg[name]) for name, _lowest, _what in SETTINGS},
        "layout": layout.as_dict(data_root),
        # one unit template per companion name, with the timeouts it is started and stopped with
        "companion_units": companion_units,
        "status_server": status,
        "agent": agent,
        "hub_cache": hub,
        "network": net,
        # on the host's network, no outgoing connection may take one of them (reserved_ports.py)
        "reserved_ports": sorted(taken),
        "warnings": warnings,
    }
    # what isaac_sim_allowed_networks lets in, port by port (firewall.py); None: no firewall
    planned["firewall"] = firewall.model(fw, planned)
    # a site chain that drops by default, where the collection does not add its accepts: stop here
    site_errors = site_firewall.judge(host.get("site_firewall") or {}, planned["firewall"], fw.get("site", "add"))
    if site_errors:
        raise PlanError(site_errors)
    return planned


def _needs(release, memory) -> list:
    """What a real instance may lack with these settings: said, not refused (hosts differ)."""
    warnings = []
    if memory is not None and memory < MIN_MEMORY and release != "2023.1":
        warnings.append(
            f"isaac_sim_memory_limit: {human(memory)} per instance is below the {human(MIN_MEMORY)} NVIDIA names as "
            f"Isaac Sim's minimum; a real instance may be killed for memory while it loads or compiles shaders. "
            f"Fix: raise isaac_sim_memory_limit (fewer instances per host if the sum does not fit)."
        )
    return warnings


def _instance(cfg, profile, mode, i, ports, gpu, address=None):
    """One instance of release profile `profile`, run as `mode` (isaac_sim_profile); with an
    address, on the macvlan network at that address, else on the host's network."""
    launch = profile["profiles"][mode]
    root = layout.data_dir(i, cfg["data_root"])
    docker = [f"--network={layout.NETWORK}", f"--ip={address}"] if address else ["--network=host"]
    docker += [
        "--pull=never",
        f"--memory={cfg['memory_limit']}",
        f"--memory-swap={cfg['memory_limit']}",
        f"--shm-size={cfg['shm_size']}",
        f"--user={profile['uid']}:{profile['gid']}",
        f"--entrypoint={launch['entrypoint']}",
        f"--label={layout.LABEL_INSTANCE}={i}",
    ]
    docker += [f"--security-opt={opt}" for opt in profile.get("security_opts", [])]
    # ISAAC_SIM_INSTANCE (its value is the env file's own line): the mark that finds the container as ours
    # where Docker lost it (isaac-sim-orphans, the plan's port check)
    env_names = [layout.K_INSTANCE, "ACCEPT_EULA"]
    container_env = {"ACCEPT_EULA": "Y"}
    # NVIDIA's convention: PRIVACY_CONSENT=Y opts in; not setting it opts out
    if cfg.get("privacy_consent"):
        env_names.append("PRIVACY_CONSENT")
        container_env["PRIVACY_CONSENT"] = "Y"
    # only the settings of what this profile opens: a port set but never opened would be reported
    app = list(launch["args"])
    for kind, port in ports.items():
        if kind not in launch["opens"]:
            continue
        how, setting = profile["ports"][kind][2], profile["ports"][kind][3]
        if how == KIT:
            app.append(f"--/{setting.lstrip('/')}={port}")
        elif how == ENV:
            container_env[setting] = str(port)
            env_names.append(setting)
    public = address or cfg.get("public_address")
    if public and launch["opens"]:
        how, setting = profile["public_address"]
        if how == KIT:
            app.append(f"--/{setting.lstrip('/')}={public}")
        else:
            container_env[setting] = public
            env_names.append(setting)
    for name, value in (cfg.get("env") or {}).items():
        container_env[name] = str(value)
        env_names.append(name)
    env_names += list(cfg.get("secret_env_names") or [])
    docker += [f"--env={name}" for name in env_names]
    dirs, caches = [], []
    for sub, target in profile["mounts"].items():
        # the host's one Hub cache, shared with the Hub service (NVIDIA: the same directory in both)
        source = cfg["hub_dir"] if sub == "cache/hub" and cfg.get("hub_dir") else f"{root}/{sub}"
        dirs.append(source)
        if sub in WARM_CACHES:
            caches.append(source)
        docker.append(f"--volume={source}:{target}:rw")
    probe = launch["health_port"]
    docker += [
        f"--health-cmd={healthcheck(cfg['release'], ports.get(probe), public or '')}",
        f"--health-interval={as_int(cfg['health_interval'])}s",
        "--health-timeout=10s",
        f"--health-retries={as_int(cfg['health_retries'])}",
        f"--health-start-period={as_int(cfg['ready_timeout'])}s",
    ]
    if gpu is not None:
        docker += ["--runtime=nvidia", f"--gpus=device={gpu}"]
    docker += list(cfg.get("docker_args") or [])
    app += [str(a) for a in cfg.get("app_args") or []]
    return {
        "id": i,
        "name": layout.container(i),
        "ports": ports,
        "protocols": {kind: profile["ports"][kind][0] for kind in ports},
        "address": address,
        "profile": mode,
        # the ports Isaac Sim itself opens in this profile (web_viewer is kept for a companion)
        "listens": [kind for kind in ports if kind in launch["opens"]],
        "gpu": gpu,
        "root": root,
        "dirs": dirs,
        "caches": caches,
        "docker_args": docker,
        "app_args": app,
        "container_env": container_env,
        "secret_env_names": list(cfg.get("secret_env_names") or []),
    }
