# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""Read-only facts about a host that the plan is checked against.

Reads /proc directly (no ss or lsof needed on the host); commands go through
a runner function so the unit tests can feed recorded output.
"""

from __future__ import annotations

import glob
import os
import re

from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib import layout

TCP_LISTEN = "0A"
UDP_UNCONNECTED = "07"


def proc_net_entries(text: str | None):
    """[(local port, state, inode)] of a /proc/net/{tcp,tcp6,udp,udp6} text; malformed lines are skipped."""
    out = []
    for line in (text or "").splitlines()[1:]:
        fields = line.split()
        if len(fields) < 10:
            continue
        try:
            port = int(fields[1].rsplit(":", 1)[1], 16)
        except (IndexError, ValueError):
            continue
        out.append((port, fields[3], fields[9]))
    return out


def parse_proc_net(text: str, proto: str, listening_state: str):
    """[(proto, port, inode)] for sockets in the listening state."""
    return [(proto, port, inode) for port, state, inode in proc_net_entries(text) if state == listening_state]


def listening_sockets(proc="/proc"):
    found = []
    for name, proto, state in (
        ("tcp", "tcp", TCP_LISTEN),
        ("tcp6", "tcp", TCP_LISTEN),
        ("udp", "udp", UDP_UNCONNECTED),
        ("udp6", "udp", UDP_UNCONNECTED),
    ):
        try:
            with open(os.path.join(proc, "net", name)) as fh:
                found += parse_proc_net(fh.read(), proto, state)
        except OSError:
            continue
    return found


def socket_owners(inodes, proc="/proc"):
    """{inode: pid} for the given socket inodes, by walking /proc/PID/fd."""
    wanted = {f"socket:[{i}]": i for i in inodes}
    owners = {}
    for fd_dir in glob.glob(os.path.join(proc, "[0-9]*", "fd")):
        pid = int(fd_dir.split(os.sep)[-2])
        try:
            for fd in os.listdir(fd_dir):
                target = os.readlink(os.path.join(fd_dir, fd))
                if target in wanted:
                    owners[wanted[target]] = pid
        except OSError:
            continue
        if len(owners) == len(wanted):
            break
    return owners


def _read(path):
    try:
        with open(path) as fh:
            return fh.read()
    except OSError:
        return ""


_CONTAINER_ID = re.compile(r"[0-9a-f]{64}")


def lost_container(cgroup: str, environ: str) -> bool:
    """Whether a process runs in a container (a 64-hex id in its cgroup) that carries the collection's
    mark in its environment (ISAAC_SIM_INSTANCE, which every container of ours gets)."""
    marks = environ.split("\0")
    return bool(_CONTAINER_ID.search(cgroup)) and any(m.startswith(layout.K_INSTANCE + "=") for m in marks)


def ports_held(wanted_ports, our_container_ids, proc="/proc", our_units=()):
    """Sockets on the ports we want, each with its process and whether it is ours.

    our_container_ids is a function, called only when a wanted port is taken.
    A socket is ours when its process runs inside one of our containers: the
    container id appears in the process's cgroup path, under cgroup v1 and v2,
    with the cgroupfs or the systemd driver; or when it runs in one of our_units (a host
    service of the collection, such as the status endpoint).
    """
    wanted = set(wanted_ports)
    socks = [s for s in listening_sockets(proc) if (s[0], s[1]) in wanted]
    if not socks:
        return []
    owners = socket_owners([s[2] for s in socks], proc)
    ids = [cid for cid in our_container_ids() if cid]
    held = []
    for proto, port, inode in socks:
        pid = owners.get(inode)
        comm = _read(os.path.join(proc, str(pid), "comm")).strip() if pid else ""
        cgroup = _read(os.path.join(proc, str(pid), "cgroup")) if pid else ""
        ours = any(cid in cgroup for cid in ids) or any(f"/{unit}" in cgroup for unit in our_units)
        process = f"{comm} (pid {pid})" if pid else "a process in another namespace"
        entry = {"proto": proto, "port": port, "process": process, "ours": ours}
        # a container of ours that containerd runs and a crashed dockerd forgot: its unit's start clears it
        if not ours and pid and lost_container(cgroup, _read(os.path.join(proc, str(pid), "environ"))):
            entry.update(ours=True, lost=True)
        held.append(entry)
    return held


def memory_bytes(proc="/proc"):
    match = re.search(r"^MemTotal:\s+(\d+) kB", _read(os.path.join(proc, "meminfo")), re.M)
    return int(match.group(1)) * 1024 if match else 0


def parse_gpu_list(text):
    """[{index, name, memory_total_mib, driver}] from nvidia-smi's csv query."""
    gpus = []
    for line in text.strip().splitlines():
        parts = [p.strip() for p in line.split(",")]
        if len(parts) >= 4 and parts[0].isdigit():
            mem = re.match(r"(\d+)", parts[2])
            gpus.append(
                {
                    "index": int(parts[0]),
                    "name": parts[1],
                    "memory_total_mib": int(mem.group(1)) if mem else None,
                    "driver": parts[3],
                }
            )
    return gpus


GPU_QUERY = ["nvidia-smi", "--query-gpu=index,name,memory.total,driver_version", "--format=csv,noheader,nounits"]


def existing_instances(config_dir, wants_dir, find=glob.glob):
    """Instance numbers this collection set up before: env files and enabled units.

    find: how a glob pattern is matched (glob.glob; a scripted host's own in the tests)."""
    ids = set()
    for path in find(os.path.join(config_dir, "instance-*.env")):
        match = re.search(r"instance-(\d+)\.env$", path)
        if match:
            ids.add(int(match.group(1)))
    for path in find(os.path.join(wants_dir, "isaac-sim@*.service")):
        match = re.search(r"isaac-sim@(\d+)\.service$", path)
        if match:
            ids.add(int(match.group(1)))
    return sorted(ids)


def existing_companions(config_dir, find=glob.glob) -> dict:
    """{instance: [companion names]} of the companion env files this collection wrote."""
    found = {}
    for path in find(os.path.join(config_dir, "instance-*.*.env")):
        match = layout.COMPANION_ENV_RE.match(os.path.basename(path))
        if match:
            found.setdefault(int(match.group(1)), []).append(match.group(2))
    return {i: sorted(names) for i, names in sorted(found.items())}


def companion_templates(unit_dir, find=glob.glob) -> list:
    """Names of the companion unit templates (isaac-sim-NAME@.service) in unit_dir."""
    names = []
    for path in find(os.path.join(unit_dir, layout.COMPANION_TEMPLATE_GLOB)):
        match = layout.COMPANION_TEMPLATE_RE.match(os.path.basename(path))
        if match:
            names.append(match.group(1))
    return sorted(names)
