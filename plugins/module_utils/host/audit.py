# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""The security audit of a host (playbooks/audit.yml): what a host has that it should not.

Findings, each {"check", "what", "why"}: containers that left their confinement (privileged, added
capabilities, the host's namespaces, a confinement turned off, host devices, Docker's socket), files
under /etc, /root, /var/lib and the journal that hold the registry key (never the key itself in
the answer), env files and units whose mode is wider than they should be, and the firewall's
tables missing or not as the lifecycle loaded them. The ports each host opens go to a probe
(probe()), run from the controller or named probe hosts, each outside or inside the allowed
networks: a port must be silent to the first and answer the second.
"""

from __future__ import annotations

import glob
import ipaddress
import json
import os
import socket
import stat
from concurrent.futures import ThreadPoolExecutor

from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib import container_policy, fleet_status, layout
from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib.docker_socket import DockerError, DockerSocket
from ansible_collections.isaacsim.fleet.plugins.module_utils.instance import firewall

KEY_ROOTS = ("/etc", "/root", "/var/lib")
# image layers and content stores: tens of GB the key is never written to by a pull (a container's
# own config, where an env variable would land, is under /var/lib/docker/containers and is read)
SKIP = ("/var/lib/docker/overlay2", "/var/lib/docker/image", "/var/lib/docker/volumes", "/var/lib/containerd")
MAX_FILE = 16 * 1024 * 1024
# knocks at once: each a socket and a thread that mostly waits
PROBES = 64


def finding(check: str, what: str, why: str) -> dict:
    return {"check": check, "what": what, "why": why}


def container_findings(containers: list, envs: dict | None = None, volumes: dict | None = None) -> list:
    """A finding per thing the container policy refuses (hostlib/container_policy.py, the plan's own),
    judged on what Docker says each container of the host has. A container named as one of ours (an
    env file's container) is held to its plan: nothing beyond what the plan gave it. Any other
    container is held to what would hand it the host (privileged, capabilities, namespaces, a
    confinement off, devices, a bind of the host's own paths). volumes: {name: local-driver options}."""
    planned = {}
    for text in (envs or {}).values():
        env = layout.parse(text or "")
        if env.get(layout.K_CONTAINER):
            planned[env[layout.K_CONTAINER]] = env
    foreign = {"bind_roots": None, "gpus": None, "root_ok": True, "volumes": volumes or {}, "inspected": True}
    out = []
    for inspected in containers:
        name = str(inspected.get("Name", "")).lstrip("/")
        env = planned.get(name)
        try:
            if env is None:
                judged = container_policy.judge(inspected, foreign)
            else:
                args = layout.split_args(env.get(layout.K_DOCKER_ARGS, ""))
                judged = container_policy.beyond_plan(inspected, args, env.get(layout.K_GPU, ""), volumes)
        except container_policy.DockerArgError as exc:
            out.append(finding("container", name, f"Docker reports settings the policy cannot read: {exc}"))
            continue
        out += [finding("container", name, f"{text}: {why}") for _key, text, why in judged]
    return out


def key_files(key: str, roots=KEY_ROOTS, skip=SKIP, max_file=MAX_FILE) -> list:
    """The regular files under roots that contain key (symlinks not followed, big files skipped)."""
    if not key:
        return []
    needle = key.encode()
    found = []
    for root in roots:
        for folder, dirs, names in os.walk(root):
            dirs[:] = [d for d in dirs if os.path.join(folder, d) not in skip]
            for name in names:
                path = os.path.join(folder, name)
                try:
                    st = os.lstat(path)
                    if not stat.S_ISREG(st.st_mode) or st.st_size > max_file:
                        continue
                    with open(path, "rb") as fh:
                        if needle in fh.read():
                            found.append(path)
                except OSError:
                    continue
    return found


def key_findings(key: str, files: list, journal: str) -> list:
    out = [finding("registry key", path, "holds the registry key (isaac_sim_registry_password)") for path in files]
    if key and key in journal:
        out.append(finding("registry key", "journal", "the journal holds the registry key (journalctl)"))
    return out


def mode_findings(files: dict, secret_names) -> list:
    """files: {path: (mode, text)} of our env files, units and scripts. Nothing of ours is writable by
    group or others; an env file that holds a secret variable is readable by root only."""
    out = []
    for path, (mode, text) in sorted(files.items()):
        if mode & 0o022:
            out.append(finding("file mode", path, f"mode {mode:04o} lets group or others write it"))
        secret = [n for n in secret_names if f"\n{n}=" in f"\n{text or ''}"]
        if secret and mode & 0o077:
            out.append(finding("file mode", path, f"mode {mode:04o} lets others than root read {', '.join(secret)}"))
    return out


def opened_ports(envs: dict, status_env: str | None, hub: bool) -> list:
    """[{"proto", "port", "address", "kind"}] the host opens: each instance's and companion's listening
    ports (K_PORTS, at its own address when it has one), the status endpoint's, the Hub cache's."""
    out = []
    for text in envs.values():
        env = layout.parse(text or "")
        owner = env.get(layout.K_CONTAINER, "")
        for spec in env.get(layout.K_PORTS, "").split():
            proto, _sep, port = spec.partition("/")
            if port.isdigit():
                out.append({"proto": proto, "port": int(port), "address": env.get(layout.K_ADDRESS, ""), "kind": owner})
    if status_env:
        url = layout.parse(status_env).get(layout.K_STATUS_URL, "")
        port = url.rsplit(":", 1)[-1].split("/", 1)[0]
        if port.isdigit():
            out.append({"proto": "tcp", "port": int(port), "address": "", "kind": "status"})
    if hub:
        out.append({"proto": "tcp", "port": layout.HUB_PORT, "address": "", "kind": "hub_cache"})
    return sorted(out, key=lambda p: (p["address"], p["port"], p["proto"]))


def firewall_findings(state: dict | None, listing: str | None, ports: list) -> list:
    """The firewall as the lifecycle left it (state: its firewall.json, None when there is none):
    loaded and unchanged, or nothing at all to guard."""
    if not ports:
        return []
    if state is None:
        return [finding("firewall", "isaac_sim", "no firewall guards the instances' ports (isaac_sim_firewall)")]
    kept = state.get("listing")
    if not listing:
        return [finding("firewall", "isaac_sim", "the tables are not loaded (systemctl start isaac-sim-firewall)")]
    if kept is not None and listing != kept:
        return [finding("firewall", "isaac_sim", "the loaded rules differ from those the last deploy loaded")]
    return []


def probe(targets: list, timeout: float = 3.0) -> list:
    """Run on the probe host. targets: [{"host", "address", "proto", "port", "kind", "networks"}].
    Each gets "source" (this host's address towards it), "inside" (the source is in the networks
    allowed for it: nothing to learn there) and "answer": "open" (TCP connected, UDP answered),
    "closed" (refused), "silent" (dropped, or a UDP port that answers nothing).

    The knocks run at once (PROBES at a time), each answer in its target's place: behind a firewall
    that drops, each knock waits out its timeout, and a host opens a dozen ports or more."""
    out = []
    for t in targets:
        row = dict(t)
        row["source"] = _source(t["address"])
        nets = [ipaddress.ip_network(n) for n in t.get("networks") or []]
        src = ipaddress.ip_address(row["source"]) if row["source"] else None
        row["inside"] = bool(src) and any(src.version == n.version and src in n for n in nets)
        out.append(row)
    with ThreadPoolExecutor(max_workers=PROBES) as pool:
        answers = list(pool.map(lambda r: _knock(r["proto"], r["address"], int(r["port"]), timeout), out))
    for row, answer in zip(out, answers):
        row["answer"] = answer
    return out


def _source(address: str) -> str:
    sock = socket.socket(socket.AF_INET6 if ":" in address else socket.AF_INET, socket.SOCK_DGRAM)
    try:
        sock.connect((address, 9))
        return sock.getsockname()[0]
    except OSError:
        return ""
    finally:
        sock.close()


def _knock(proto: str, address: str, port: int, timeout: float) -> str:
    family = socket.AF_INET6 if ":" in address else socket.AF_INET
    try:
        if proto == "udp":
            with socket.socket(family, socket.SOCK_DGRAM) as sock:
                sock.settimeout(timeout)
                sock.connect((address, port))
                sock.send(b"isaacsim-fleet audit")
                sock.recv(512)
                return "open"
        with socket.create_connection((address, port), timeout=timeout):
            return "open"
    except socket.timeout:
        return "silent"
    except ConnectionRefusedError:
        return "closed"
    except OSError:
        return "silent"


def probe_findings(rows: list) -> list:
    """Both directions: an open port seen from outside the networks allowed for it, and a TCP port
    that is silent (dropped on the way) from inside them - a firewall, ours or the site's, that
    closes what must answer. A UDP port silent from inside is not judged (a port may not answer a
    stray datagram), nor one that refuses (nothing listens: the instance is down, status says why)."""
    out = []
    for r in rows:
        what = f"{r['host']} {r['proto']}/{r['address']}:{r['port']} ({r['kind']})"
        by = f"{r['source']} ({r['prober']})" if r.get("prober") else r["source"]
        if r["answer"] == "open" and not r["inside"]:
            out.append(finding("port", what, f"answers {by}, which is outside the allowed networks"))
        elif r["answer"] == "silent" and r["inside"] and r["proto"] == "tcp":
            out.append(
                finding(
                    "port",
                    what,
                    f"does not answer {by}, which is inside its allowed networks: a firewall on the way drops it "
                    "(a site chain that drops by default? isaac_sim_firewall_site_policy)",
                )
            )
    return out


class HostIO:
    """What the audit reads on the host: Docker's API (DockerSocket), run(argv) -> (rc, out, err),
    glob(pattern) -> paths, lstat(path) -> os.stat_result or None, read(path) -> text or None,
    key_files(key) -> paths, default_ipv4() -> address."""

    def __init__(self, docker, run, glob, lstat, read, key_files_of, default_ipv4):
        self.docker, self.run, self.glob, self.lstat, self.read = docker, run, glob, lstat, read
        self.key_files, self.default_ipv4 = key_files_of, default_ipv4


def bind(module) -> HostIO:
    """The real host, for the module running on it."""

    def run(argv):
        path = module.get_bin_path(argv[0])
        return module.run_command([path] + argv[1:]) if path else (127, "", f"{argv[0]}: not found")

    def lstat(path):
        try:
            return os.lstat(path)
        except OSError:
            return None

    def read(path):
        try:
            with open(path, errors="replace") as fh:
                return fh.read()
        except OSError:
            return None

    return HostIO(DockerSocket(), run, glob.glob, lstat, read, key_files, fleet_status.default_ipv4)


def _ours(io: HostIO) -> dict:
    """{path: (mode, text)} of the files the collection writes that hold settings or run as root."""
    patterns = [
        f"{layout.CONFIG_DIR}/*",
        f"{layout.UNIT_DIR}/isaac-sim*",
        f"{layout.UNIT_DIR}/isaac-sim*.d/*",
        f"{layout.LIBEXEC_DIR}/*",
        layout.FIREWALL_SITE_DROPIN,
    ]
    files = {}
    for pattern in patterns:
        for path in io.glob(pattern):
            st = io.lstat(path)
            if st is not None and stat.S_ISREG(st.st_mode):
                files[path] = (stat.S_IMODE(st.st_mode), io.read(path) or "")
    return files


def _state(text: str | None) -> dict | None:
    """The firewall.json the lifecycle left ({} when unreadable), None when there is none."""
    if text is None:
        return None
    try:
        return json.loads(text) or {}
    except ValueError:
        return {}


def host_report(io: HostIO, key: str, secret_names) -> dict:
    """{"findings", "ports", "address"} of this host; ports carry the networks allowed for each."""
    findings = []
    ours = _ours(io)
    envs = {p: t for p, (_m, t) in ours.items() if p.endswith(".env") and os.path.basename(p) != layout.STATUS_ENV}
    try:
        listed = io.docker.get("/containers/json?all=1")
        containers = [io.docker.get(f"/containers/{c['Id']}/json") for c in listed]
        # a named volume's options decide what it mounts (a local volume may bind a host path)
        volumes = {
            v.get("Name"): v.get("Options") or {} for v in (io.docker.get("/volumes") or {}).get("Volumes") or []
        }
        findings += container_findings(containers, envs, volumes)
    except (DockerError, OSError) as exc:
        findings.append(finding("container", "docker", f"could not ask Docker: {exc}"))
    _rc, journal, _err = io.run(["journalctl", "-o", "cat", "--no-pager"]) if key else (0, "", "")
    findings += key_findings(key, io.key_files(key), journal)
    findings += mode_findings(ours, secret_names)
    status_env = ours.get(f"{layout.CONFIG_DIR}/{layout.STATUS_ENV}", (0, None))[1]
    hub = f"{layout.UNIT_DIR}/{layout.HUB_UNIT}" in ours
    ports = opened_ports(envs, status_env, hub)
    state = _state(io.read(firewall.STATE))
    findings += firewall_findings(state, firewall.listed(io.run), ports)
    model = (state or {}).get("model") or {}
    nets = firewall.Networks(model.get("default") or [], model.get("by_kind") or {})
    kinds = {(r[1], r[2], r[4]): r[3] for r in model.get("ports") or []}
    for p in ports:
        kind = kinds.get((p["proto"], p["port"], p["address"]))
        p["networks"] = nets.of(kind) if kind else []
        p["kind"] = kind or p["kind"]
    return {"findings": findings, "ports": ports, "address": io.default_ipv4()}


def targets(reports: dict, probe_host: str = "") -> list:
    """The probe's targets from the hosts' reports ({host: host_report(), or {} when unreachable}). The
    probe host's own ports are left out: knocked on from itself, every one answers (its own traffic
    never crosses its firewall's input from another host), which says nothing of the allowed networks."""
    out = []
    for host in sorted(reports):
        if host == probe_host:
            continue
        report = reports[host] or {}
        for p in report.get("ports") or []:
            address = p.get("address") or report.get("address") or ""
            if address:
                out.append(dict(p, host=host, address=address, prober=probe_host))
    return out


def fleet(reports: dict, probed: list, probe_hosts=("",)) -> dict:
    """{"hosts": [{"host", "reachable", "findings"}], "findings": n, "clean": bool, "table": [lines]}.
    probed: the rows of every probe host's probe() (probe_hosts: their names, "" or localhost for
    the controller)."""
    if isinstance(probe_hosts, str):
        probe_hosts = [probe_hosts]
    rows = []
    by_host = {}
    for f in probe_findings(probed):
        by_host.setdefault(f["what"].split(" ", 1)[0], []).append(f)
    unjudged = [r for r in probed if r["inside"] and r["answer"] == "silent" and r["proto"] == "udp"]
    for host in sorted(reports):
        report = reports[host]
        found = list((report or {}).get("findings") or []) + by_host.get(host, [])
        rows.append({"host": host, "reachable": bool(report), "findings": found})
    count = sum(len(r["findings"]) for r in rows)
    table = [f"{'HOST':<24} {'CHECK':<13} WHAT / WHY"]
    for r in rows:
        if not r["reachable"]:
            table.append(f"{r['host']:<24} {'host':<13} did not answer: not audited")
        for f in r["findings"]:
            table.append(f"{r['host']:<24} {f['check']:<13} {f['what']}: {f['why']}")
        if r["reachable"] and not r["findings"]:
            table.append(f"{r['host']:<24} {'-':<13} clean")
    knocked = {r["host"] for r in probed}
    for host in probe_hosts:
        if host in reports and (reports[host] or {}).get("ports") and host not in knocked:
            table.append(
                f"(not knocked on: {len(reports[host]['ports'])} port(s) of {host}, the probe host itself; "
                "audit it from another audit_probe_host)"
            )
    outside = {(r["host"], r["proto"], r["port"]) for r in probed if not r["inside"]}
    ports = {(r["host"], r["proto"], r["port"]) for r in probed}
    if ports - outside:
        table.append(
            f"(not knocked on from outside: {len(ports - outside)} port(s), every probe host is inside their "
            "allowed networks; add a host outside them to audit_probe_hosts)"
        )
    insiders = {(r["host"], r["proto"], r["port"]) for r in probed if r["inside"]}
    if ports - insiders:
        table.append(
            f"(not knocked on from inside: {len(ports - insiders)} port(s), no probe host is in their allowed "
            "networks; add one to audit_probe_hosts to check that they answer there)"
        )
    if unjudged:
        table.append(
            f"(not judged: {len(unjudged)} UDP port(s) gave no answer from inside their allowed networks; a UDP "
            "port may not answer a stray datagram)"
        )
    return {
        "hosts": rows,
        "findings": count,
        "clean": count == 0 and all(r["reachable"] for r in rows),
        "probed": probed,
        "table": table,
    }
