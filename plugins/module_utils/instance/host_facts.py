# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""What the plan is checked against, read from the host, and the plan built on it: the
isaac_sim_plan module's whole call.

The host is reached through a Probe (which, run, Docker's API, default_ipv4, and where /proc and
/sys/class/net are) that the module binds to the real host and the unit tests to a scripted
one, as lifecycle.Host is. Everything here only reads.
"""

from __future__ import annotations

import contextlib
import json
import os
import sys

from ansible_collections.isaacsim.fleet.plugins.module_utils.host import host_service, min_facts
from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib import (
    builtin_companions,
    fleet_status,
    gpu_usage,
    layout,
    site_firewall,
)
from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib.docker_socket import DockerError, DockerSocket
from ansible_collections.isaacsim.fleet.plugins.module_utils.instance import (
    companions,
    hostprobe,
    network,
    nvenc,
    plan,
    runlock,
)
from ansible_collections.isaacsim.fleet.plugins.module_utils.instance.releases import RELEASES, STREAMS, default_image

PROC = "/proc"
SYS_NET = "/sys/class/net"
# where Docker finds the CA of a registry (a mirror's, docker_engine_registry_cas)
CERTS_D = "/etc/docker/certs.d"


class Probe:
    """The host as the plan reads it.

    which(name) -> the command's path, or None when it is not installed; run(argv) -> (rc, out,
    err), argv[0] a path from which; docker: Docker's API as DockerSocket answers it (image(ref),
    containers(name_prefix), network(name); each raises DockerError), asked only where the docker
    command is installed: a socket call instead of a CLI process each (milliseconds, not tens);
    default_ipv4() -> the source address of the default route; proc and sys_net: where /proc and
    /sys/class/net are; python: the interpreter the encoder probe runs in (nvenc.py); check_mode:
    nothing is written (the encoder cache is kept only by a real run); min_facts() -> the facts
    setup's gather_subset [min] returns, collected in the plan's call (host/min_facts.py).
    """

    def __init__(
        self,
        which,
        run,
        docker,
        default_ipv4,
        proc=PROC,
        sys_net=SYS_NET,
        python=sys.executable,
        check_mode=False,
        min_facts=dict,
    ):
        self.which, self.run, self.docker, self.default_ipv4 = which, run, docker, default_ipv4
        self.proc, self.sys_net, self.python, self.check_mode = proc, sys_net, python, check_mode
        self.min_facts = min_facts


def bind(module) -> Probe:
    """The real host, for a module running on it."""
    return Probe(
        module.get_bin_path,
        module.run_command,
        DockerSocket(),
        fleet_status.default_ipv4,
        PROC,
        SYS_NET,
        sys.executable,
        module.check_mode,
        lambda: min_facts.collect(module),
    )


class PlanRefusedError(Exception):
    """The module fails with this message and these fields."""

    def __init__(self, msg: str, **fields):
        super().__init__(msg)
        self.msg, self.fields = msg, fields


def _image(probe: Probe, ref):
    """(the image as Docker describes it or None, whether the daemon answered); a daemon that
    does not answer has no image (image.yml then says Docker does not run)."""
    try:
        return probe.docker.image(ref), True
    except DockerError:
        return None, False


def _image_id(probe: Probe, ref):
    """(present, id) of an image on the host."""
    image = _image(probe, ref)[0]
    return (True, image.get("Id")) if image else (False, None)


def _gpus(probe: Probe, p: dict, host: dict, docker) -> None:
    """The GPUs as placement weighs them (placement.py): memory, what other processes hold, brand,
    video encoder; and where each instance runs now."""
    # a missing binary would end the module with a raw OSError; the plan says it in words instead
    smi = probe.which("nvidia-smi") if p["gpu_enabled"] else None
    host["nvidia_smi"] = bool(smi)
    if not smi:
        return
    rc, out, err = probe.run([smi] + gpu_usage.SMI_XML[1:])
    try:
        usage = gpu_usage.parse_smi_xml(out) if rc == 0 else None
    except SyntaxError:  # ElementTree's ParseError
        usage = None
    if usage is None:
        host["gpu_error"] = (err or out).strip()[-300:] or f"nvidia-smi -q -x exited {rc}"
        return
    ours = set()
    if docker and usage["processes"]:
        with contextlib.suppress(DockerError):
            ours = {c["Id"] for c in probe.docker.containers("^" + layout.CONTAINER_PREFIX) if c.get("Id")}
    # what processes outside the collection's containers hold: our instances are re-placed anyway
    held = {}
    for proc in usage["processes"]:
        if gpu_usage.container_of_pid(proc["pid"], probe.proc) not in ours:
            held[proc["gpu"]] = held.get(proc["gpu"], 0) + (proc["used_mib"] or 0)
    streams = p["profile"] in STREAMS or any(v in STREAMS for v in (p["instance_profiles"] or {}).values())
    encoders, why, keep = _encoders(probe, p, usage) if streams else ({}, None, None)
    if keep:
        host["encoders_to_keep"] = keep
    host["gpus"] = [
        dict(gpu, others_mib=held.get(gpu["index"], 0), encoder=encoders.get(gpu["uuid"]), encoder_why=why)
        for gpu in usage["gpus"]
    ]
    host["gpu_count"] = len(host["gpus"])
    host["gpu_driver"] = usage["driver"]
    envs, _errors = fleet_status.read_env_files(p["config_dir"])
    host["gpu_current"] = {
        i: int(env[layout.K_GPU]) for i, env in envs.items() if str(env.get(layout.K_GPU, "")).isdigit()
    }


ENCODER_CACHE = "gpu-encoders.json"


def _encoders(probe: Probe, p: dict, usage: dict) -> tuple:
    """({GPU uuid: True | False | None}, why not asked, what to keep): the answers kept for this
    driver, else the driver's encode API (one session per GPU, nvenc.py). Only what the driver
    answered is kept (by keep_encoders, once the plan is accepted): a GPU it could not be asked
    about is asked again next time."""
    known = {}
    try:
        with open(os.path.join(p["data_root"], ENCODER_CACHE)) as fh:
            kept = json.load(fh)
        if kept.get("driver") == usage["driver"]:
            known = {k: v for k, v in kept.get("gpus", {}).items() if isinstance(v, bool)}
    except (OSError, ValueError, AttributeError):
        pass
    if all(gpu["uuid"] in known for gpu in usage["gpus"]):
        return known, None, None
    found, why = nvenc.probe(probe.run, probe.python, probe.which("timeout"))
    answered = {k: v for k, v in found.items() if isinstance(v, bool)}
    keep = {"driver": usage["driver"], "gpus": {**known, **answered}} if answered else None
    return {**found, **known, **answered}, why, keep


def keep_encoders(probe: Probe, p: dict, host: dict) -> None:
    """Keep what the driver answered under the data root (not in check mode, nor on a host the
    collection has not set up yet): the next plan does not ask again."""
    keep = host.pop("encoders_to_keep", None)
    if keep and not probe.check_mode and os.path.isdir(p["data_root"]):
        path = os.path.join(p["data_root"], ENCODER_CACHE)
        with open(path + ".tmp", "w") as fh:
            json.dump(keep, fh, sort_keys=True)
        os.replace(path + ".tmp", path)


def _images(probe: Probe, p: dict, host: dict, docker) -> None:
    image = p["image"] or (default_image(p["release"]) if p["release"] in RELEASES else "")
    # what later tasks would otherwise ask the host again: the image (its id), the metrics timer
    host["image_present"], host["image_id"], host["image_digests"], host["docker_answers"] = False, None, [], False
    if docker and image:
        found, host["docker_answers"] = _image(probe, image)
        if found:
            # the references it was pulled by (REPOSITORY@DIGEST): whether the host has the one the
            # fleet's tag is pinned to, by that name (a mirror's is another name for the same digest)
            host["image_present"], host["image_id"] = True, found.get("Id")
            host["image_digests"] = [d for d in found.get("RepoDigests") or [] if "@" in d]
    # a mirror this host's Docker trusts can be asked for the fleet's digest before anything changes
    mirror = p.get("registry_mirror") or ""
    host["mirror_trusted"] = bool(mirror) and os.path.exists(os.path.join(CERTS_D, mirror, "ca.crt"))
    # what the instances set up before run: a deploy says which hosts it moves
    envs, _errors = fleet_status.read_env_files(p["config_dir"])
    host["images_configured"] = sorted(
        {env.get(layout.K_IMAGE_PINNED) or env.get(layout.K_IMAGE) for env in envs.values()} - {None, ""}
    )
    # companion images not on the host yet: the role pulls them with the instance's image
    # (image, the variable that names it), the one a missing image is reported by
    host["companion_images_missing"], host["companion_images_missing_named"] = [], []
    wanted = [
        (c.get("image"), "isaac_sim_companions") for c in p["companions"] if isinstance(c, dict) and c.get("image")
    ]
    release_ports = RELEASES[p["release"]]["ports"] if p["release"] in RELEASES else {}
    profiles = [p["profile"], *p["instance_profiles"].values()]
    wanted[:0] = builtin_companions.images(release_ports, profiles, builtin_companions.given(p))
    if p["hub_cache"].get("enabled") and p["hub_cache"].get("image"):
        wanted.insert(0, (p["hub_cache"]["image"], "isaac_sim_hub_cache_image"))
    for ref, variable in dict.fromkeys((str(r), v) for r, v in wanted):
        present = _image_id(probe, ref)[0] if docker else False
        if not present and ref not in host["companion_images_missing"]:
            host["companion_images_missing"].append(ref)
            host["companion_images_missing_named"].append(f"{ref} ({variable})")


def _units(probe: Probe, p: dict, host: dict) -> None:
    host["metrics_timer"] = os.path.exists(os.path.join(p["systemd_dir"], layout.METRICS_TIMER))
    host["status_unit"] = os.path.exists(os.path.join(p["systemd_dir"], layout.STATUS_UNIT))
    host["agent_unit"] = os.path.exists(os.path.join(p["systemd_dir"], layout.AGENT_UNIT))
    host["hub_unit"] = os.path.exists(os.path.join(p["systemd_dir"], layout.HUB_UNIT))
    # the firewall's nft: installed by the role only where missing (no package manager call on a re-run)
    host["nft"] = probe.which("nft") is not None
    # the site's input chains that drop by default, and what of ours they hold (site_firewall.py)
    if host["nft"]:
        host["site_firewall"] = site_firewall.survey(probe.run)
    # instances serving now: a Docker restart on this host waits for the canary batches; which ones
    # (None: systemd did not say) tells the deploy whether any instance could start on empty caches
    systemctl = probe.which("systemctl")
    host["serving"], host["active_ids"] = 0, None
    if systemctl:
        argv = [systemctl, "list-units", layout.UNIT_GLOB, "--state=active", "--plain", "--no-legend"]
        rc, out, _err = probe.run(argv)
        if rc == 0:
            names = [line.split()[0] for line in out.splitlines() if line.strip()]
            host["serving"] = len(names)
            host["active_ids"] = sorted(int(m.group(1)) for m in map(layout.UNIT_RE.match, names) if m)


def _host_services(probe: Probe, p: dict, host: dict) -> None:
    """The host services the plan was asked about ({unit: {files, directories}}), as host_service.seen reads
    them: the deploy leaves out the module call of one that is as wanted already."""
    wanted = p.get("host_services") or {}
    systemctl = probe.which("systemctl")
    shows = {}
    if wanted and systemctl:
        rc, out, _err = probe.run([systemctl, "show", "-p", "Id", "-p", "ActiveState", "-p", "UnitFileState", *wanted])
        shows = layout.parse_shown(out) if rc == 0 else {}
    host["host_services"] = {
        name: host_service.seen(list(spec.get("files") or []), list(spec.get("directories") or []), shows.get(name, {}))
        for name, spec in wanted.items()
    }


def _warm_leftovers(probe: Probe, p: dict, host: dict, docker) -> None:
    """Whether a killed deploy left a warm run or its scratch behind (instance/warm_cache.py sweeps them):
    True when it cannot be told (Docker does not answer)."""
    store = layout.warm_dir(p["data_root"])
    names = os.listdir(store) if os.path.isdir(store) else []
    scratch = any(layout.warm_scratch(store, n) for n in names)
    runs = False
    if docker:
        try:
            runs = bool(probe.docker.labelled(layout.LABEL_WARM))
        except DockerError:
            runs = True
    host["warm_leftovers"] = scratch or runs


def cold_start_possible(ids: list, host: dict) -> bool:
    """Whether an instance of this host could start on empty caches: not when every instance of the plan
    runs now and nothing of a warm run is left (its probe would find and sweep nothing). The deploy leaves
    the probes out only where no host of the play could: each probe also says which caches its host keeps
    for the others."""
    active = host.get("active_ids")
    return active is None or not set(ids) <= set(active) or host.get("warm_leftovers", True)


def _lan(probe: Probe, host: dict, docker) -> None:
    """The LAN the instances join: interfaces, their addresses, the default route, our network."""
    host["interfaces"] = sorted(os.listdir(probe.sys_net)) if os.path.isdir(probe.sys_net) else []
    ip = probe.which("ip")
    if ip:
        host["links"] = network.parse_links(probe.run([ip, "-j", "-4", "addr", "show"])[1])
        host["default_route"] = network.parse_default_route(probe.run([ip, "-j", "-4", "route", "show", "default"])[1])
    if docker:
        try:
            host["network"] = network.parse_network(probe.docker.network(layout.NETWORK))
        except DockerError as exc:
            raise PlanRefusedError(f"could not ask Docker for the network {layout.NETWORK}: {exc}") from exc


def _ports(probe: Probe, p: dict, docker, own_addresses: bool) -> list:
    """The sockets on the ports the plan wants, each with its process and whether it is ours."""
    profile = RELEASES[p["release"]]["ports"]
    blocks = plan.port_blocks(p["release"], max(p["instance_count"], 0), p["port_bases"], max(p["port_stride"], 1))
    # with addresses of their own, the instances' and companions' ports are not the host's
    wanted = set()
    if not own_addresses:
        wanted = {(profile[kind][0], port) for block in blocks.values() for kind, port in block.items()}
    if p["status_server"].get("enabled") and str(p["status_server"].get("port", "")).isdigit():
        wanted.add(("tcp", int(p["status_server"]["port"])))
    if p["hub_cache"].get("enabled"):
        wanted.add(("tcp", layout.HUB_PORT))
    for spec in p["companions"] if isinstance(p["companions"], list) and not own_addresses else []:
        for proto, base in companions.own_ports(spec if isinstance(spec, dict) else {}).values():
            wanted |= {(proto, base + i * max(p["port_stride"], 1)) for i in blocks}

    def our_ids():
        if not docker:
            return []
        try:
            return [c.get("Id", "") for c in probe.docker.containers("^" + layout.CONTAINER_PREFIX)]
        except DockerError:
            return []

    return hostprobe.ports_held(wanted, our_ids, probe.proc, our_units=[layout.STATUS_UNIT])


def facts(probe: Probe, p: dict) -> dict:
    """What was found on the host: memory, GPUs, ports held, images, units, the LAN."""
    host = {"memory_bytes": hostprobe.memory_bytes(probe.proc), "gpu_count": 0, "gpus": [], "ports_held": []}
    docker = probe.which("docker")
    _gpus(probe, p, host, docker)
    _images(probe, p, host, docker)
    _units(probe, p, host)
    _host_services(probe, p, host)
    _warm_leftovers(probe, p, host, docker)
    own_addresses = p["network_mode"] == network.MACVLAN
    if own_addresses:
        _lan(probe, host, docker)
    if p["check_host_ports"] and p["release"] in RELEASES:
        host["ports_held"] = _ports(probe, p, docker, own_addresses)
    return host


def plan_host(probe: Probe, p: dict) -> dict:
    """The module's result (plan, stale_ids, host) and the plan's warnings, from its parameters;
    raises PlanRefusedError with every error of a configuration the plan rejects."""
    cfg = {k: p[k] for k in p}
    # empty: the source address of the host's default route, as the status module finds it
    cfg["public_address"] = p["public_address"] or probe.default_ipv4()
    host = facts(probe, p)
    try:
        result = plan.build(cfg, host)
    except plan.PlanError as exc:
        raise PlanRefusedError(
            "Isaac Sim configuration rejected before any change:\n- " + "\n- ".join(exc.errors),
            errors=exc.errors,
        ) from exc
    keep_encoders(probe, p, host)
    existing = hostprobe.existing_instances(p["config_dir"], os.path.join(p["systemd_dir"], layout.TARGET + ".wants"))
    stale = [i for i in existing if i not in result["ids"]]
    host["cold_start_possible"] = cold_start_possible(result["ids"], host)
    return {"plan": result, "stale_ids": stale, "host": host, "warnings": result["warnings"]}


def plan_held(probe: Probe, p: dict, now: float) -> dict:
    """plan_host, with the host's lock taken first in the same call where p["lock"] is given (its result
    under "lock", as isaac_sim_lock returns it), and where p["gather_facts"] the facts setup's gather_subset
    [min] would return (as ansible_facts). Held by another run: only the lock's result, nothing planned,
    but in check mode, where the lock is only looked at and the dry run plans all the same."""
    out = _locked_plan(probe, p, now)
    # only with a plan: a call that waits for another run's lock gathers nothing
    if p.get("gather_facts") and "plan" in out:
        out["ansible_facts"] = probe.min_facts()
    return out


def _locked_plan(probe: Probe, p: dict, now: float) -> dict:
    if not p.get("lock"):
        return plan_host(probe, p)
    try:
        held = {"lock": runlock.request(dict(p["lock"], state="present"), now, probe.check_mode)}
    except runlock.LockError as exc:
        raise PlanRefusedError(str(exc)) from exc
    if not held["lock"]["acquired"] and not probe.check_mode:
        return held
    try:
        return dict(plan_host(probe, p), **held)
    except Exception as exc:
        # the run stops here (refused, or a fault of the plan's): the host it took is given back at once,
        # not left held by a run that ended
        if held["lock"]["acquired"] and not probe.check_mode:
            # the refusal is what the user must read; the next run takes over an ended run's lock
            with contextlib.suppress(runlock.LockError, OSError):
                held["lock"] = runlock.request(dict(p["lock"], state="absent"), now)
        if isinstance(exc, PlanRefusedError):
            exc.fields.update(held)
        raise
