# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""The registry mirror's health and storage, for status (module isaac_sim_mirror_info, on the
mirror host): whether its unit runs and its registry answers, what its storage holds and what is
left on the disk under it. Only reads."""

from __future__ import annotations

import contextlib
import json
import os
import ssl
from http.client import HTTPSConnection

from ansible_collections.isaacsim.fleet.plugins.module_utils.host import mirror_seed, registry_mirror


def held(store: str) -> dict:
    """{repository: number of manifests} in the registry's storage."""
    found = {}
    for name, _digest in mirror_seed.manifests(store):
        found[name] = found.get(name, 0) + 1
    return found


def used_bytes(root: str) -> int:
    """Bytes of the files under root (the blobs make nearly all of it)."""
    total = 0
    for path, _dirs, files in os.walk(root):
        for name in files:
            with contextlib.suppress(OSError):  # removed by the registry meanwhile
                total += os.lstat(os.path.join(path, name)).st_size
    return total


def port_of(config_text: str) -> int:
    """The port the registry serves on, from its config's http.addr (":5443")."""
    return int(json.loads(config_text)["http"]["addr"].rsplit(":", 1)[1])


def answer(port: int, timeout: float = 5.0) -> tuple:
    """(HTTP status of GET /v2/ on the loopback, or None; what went wrong). The registry's storage
    health check makes it answer 503 when its storage fails. The certificate names the address
    the fleet uses, not the loopback: this asks whether it serves, not who it is."""
    context = ssl.create_default_context()
    context.check_hostname = False
    context.verify_mode = ssl.CERT_NONE
    conn = HTTPSConnection("127.0.0.1", port, timeout=timeout, context=context)
    try:
        conn.request("GET", "/v2/")
        status = conn.getresponse().status
        return status, None if status in (200, 401) else f"answered HTTP {status}"
    except OSError as exc:
        return None, f"did not answer on port {port}: {exc}"
    finally:
        conn.close()


# the free space below which the mirror is marked: one Isaac Sim image takes many GB, and a copy cut
# short by a full disk fails the deploy that needs it (registry_mirror_min_free_gb)
MIN_FREE_GB = 20


def collect(
    run,
    data: str = registry_mirror.DATA,
    config: str = f"{registry_mirror.CONFIG_DIR}/config.yml",
    min_free_gb: float = MIN_FREE_GB,
) -> dict:
    """The mirror's state. run(argv) -> (rc, out, err)."""
    _rc, out, _err = run(["systemctl", "is-active", registry_mirror.UNIT])
    state = {"unit": registry_mirror.UNIT, "active": out.strip() or "unknown", "errors": []}
    try:
        with open(config, encoding="utf-8") as f:
            state["port"] = port_of(f.read())
    except (OSError, ValueError, KeyError, IndexError) as exc:
        state["errors"].append(f"{config}: {exc}. Fix: run the registry_mirror role.")
    if state.get("port"):
        state["http_status"], problem = answer(state["port"])
        if problem:
            state["errors"].append(f"the registry {problem}")
    if state["active"] != "active":
        state["errors"].insert(0, f"{registry_mirror.UNIT} is {state['active']}")
    store = data + mirror_seed.STORE[len(registry_mirror.DATA) :]
    state["repositories"] = held(store)
    state["images"] = sum(state["repositories"].values())
    state["used_bytes"] = used_bytes(data)
    try:
        disk = os.statvfs(data)
        state["free_bytes"] = disk.f_bavail * disk.f_frsize
        state["size_bytes"] = disk.f_blocks * disk.f_frsize
    except OSError as exc:
        state["errors"].append(f"{data}: {exc}")
    state["healthy"] = not state["errors"]
    # it still serves what it holds: a mark, not a fault
    floor = int(float(min_free_gb) * 1024**3)
    state["low_space"] = state.get("free_bytes") is not None and state["free_bytes"] < floor
    if state["low_space"]:
        state["warnings"] = [
            f"LOW ON SPACE: {state['free_bytes'] / 1024**3:.1f} GiB free, below {min_free_gb:g} GiB "
            "(registry_mirror_min_free_gb): the next image may not fit. Fix: run playbooks/registry_mirror_gc.yml "
            "or give the mirror a larger disk"
        ]
    return state
