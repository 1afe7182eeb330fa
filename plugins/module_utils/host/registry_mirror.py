# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""A LAN pull-through mirror of the fleet's image registry (roles/registry_mirror), and how the
fleet's hosts pull through it.

The mirror is the Distribution registry of the distribution's packages (Debian's docker-registry
2.8) in proxy mode: one upstream per mirror, its credentials in the mirror's config alone. It
runs as a unit of the collection's own, isaac-sim-mirror.service, as the package's system user
(docker-registry), sandboxed: its config and key are that user's alone (0600), its content lives
in the package's data directory, nothing else is writable. Its port answers the allowed networks
only: an nftables table of its own, loaded before the registry starts and deleted when it stops.
Docker's `registry-mirrors` setting applies to Docker Hub alone, so the hosts pull by a reference
rewritten to the mirror (mirror_reference), and the reports keep naming the upstream one.
"""

from __future__ import annotations

import ipaddress
import json
import re
from urllib.parse import urlparse

from ansible_collections.isaacsim.fleet.plugins.module_utils.common import sandbox, units
from ansible_collections.isaacsim.fleet.plugins.module_utils.common.parse import is_ip

UNIT = "isaac-sim-mirror.service"
CONFIG_DIR = "/etc/isaac-sim/mirror"
USER = "docker-registry"  # the package's own system user
DATA = "/var/lib/docker-registry"  # the package's own data directory, that user's
TABLE = "isaac_sim_mirror"
REGISTRY = "/usr/bin/docker-registry"
NFT = "/usr/sbin/nft"
_HOST_RE = re.compile(r"^[A-Za-z0-9.-]+\Z")
DOCKER_HUB = "docker.io"
DOCKER_HUB_NAMES = ("docker.io", "index.docker.io", "registry-1.docker.io")


def check(p: dict) -> list:
    """Errors in the role's settings, each naming the variable and the fix."""
    errors = []
    upstream = urlparse(str(p.get("upstream") or ""))
    if upstream.scheme not in ("https", "http") or not upstream.netloc or upstream.path not in ("", "/"):
        errors.append(
            f"registry_mirror_upstream: {p.get('upstream')!r} is not a registry's URL. "
            "Fix: give its scheme and host, e.g. https://nvcr.io."
        )
    elif "@" in upstream.netloc:
        errors.append(
            "registry_mirror_upstream: holds credentials (user:password@), which would be shown in the unit's "
            "description. Fix: give them as registry_mirror_username and registry_mirror_password."
        )
    if not p.get("password"):
        errors.append(
            "registry_mirror_password: empty, and the mirror logs in to its upstream with it (NGC refuses pulls "
            "without an API key). Fix: set it from a vault."
        )
    address = str(p.get("address") or "")
    if not is_ip(address) and not _HOST_RE.fullmatch(address):
        errors.append(
            f"registry_mirror_address: {address!r} is neither an IP address nor a host name. "
            "Fix: the address the fleet's hosts reach the mirror at."
        )
    port = p.get("port")
    # a number given as text (ansible-core 2.18 templates set_fact values to text)
    port = int(port) if str(port).isdigit() else port
    if not isinstance(port, int) or not 1024 <= port <= 65535:
        errors.append(f"registry_mirror_port: {port!r} is not a port of 1024-65535. Fix: e.g. 5443.")
    networks = p.get("allowed_networks") or []
    if not networks:
        errors.append(
            "registry_mirror_allowed_networks: empty, and the mirror serves what it holds to whoever reaches it. "
            "Fix: the fleet's networks, e.g. [10.20.0.0/16]."
        )
    for text in networks:
        try:
            ipaddress.ip_network(str(text).strip(), strict=True)
        except ValueError:
            errors.append(
                f"registry_mirror_allowed_networks: {text!r} is not a network. Fix: write it as CIDR with its host "
                "bits zero, e.g. 10.20.0.0/16, or a single address."
            )
    return errors


def config(p: dict) -> str:
    """The registry's configuration (JSON, which its YAML reader takes): proxy mode, TLS, no delete."""
    return (
        json.dumps(
            {
                "version": 0.1,
                "log": {"level": "info", "fields": {"service": "isaac-sim-mirror"}},
                "storage": {
                    "filesystem": {"rootdirectory": DATA},
                    "cache": {"blobdescriptor": "inmemory"},
                },
                "http": {
                    "addr": f":{p['port']}",
                    "tls": {"certificate": f"{CONFIG_DIR}/mirror.crt", "key": f"{CONFIG_DIR}/mirror.key"},
                    "headers": {"X-Content-Type-Options": ["nosniff"]},
                },
                "proxy": {
                    "remoteurl": str(p["upstream"]).rstrip("/"),
                    "username": p["username"],
                    "password": p["password"],
                },
                "health": {"storagedriver": {"enabled": True, "interval": "10s", "threshold": 3}},
            },
            indent=2,
        )
        + "\n"
    )


def rules(p: dict, managed: str) -> str:
    """The mirror's own nftables table: its port answers the allowed networks and this host only."""
    nets = [ipaddress.ip_network(str(text).strip()) for text in p["allowed_networks"]]
    v4 = sorted(str(n) for n in nets if n.version == 4)
    v6 = sorted(str(n) for n in nets if n.version == 6)
    lines = [
        f"# {managed}",
        f"# The registry mirror's port ({p['port']}/tcp) answers registry_mirror_allowed_networks only.",
        f"table inet {TABLE}",
        f"delete table inet {TABLE}",
        f"table inet {TABLE} {{",
        "  chain input {",
        "    type filter hook input priority -5; policy accept;",
        '    iifname "lo" accept',
    ]
    if v4:
        lines.append(f"    tcp dport {p['port']} ip saddr {{ {', '.join(v4)} }} accept")
    if v6:
        lines.append(f"    tcp dport {p['port']} ip6 saddr {{ {', '.join(v6)} }} accept")
    lines += [f"    tcp dport {p['port']} drop", "  }", "}"]
    return "\n".join(lines) + "\n"


def unit(p: dict, managed: str) -> str:
    """isaac-sim-mirror.service: the registry in proxy mode, under a user of its own."""
    return units.render(
        [
            (
                "Unit",
                [
                    ("Description", f"isaacsim.fleet registry mirror of {p['upstream']}"),
                    ("Wants", "network-online.target"),
                    ("After", "network-online.target"),
                ],
            ),
            (
                "Service",
                [
                    # "+": the firewall is loaded with full privileges, before the sandboxed registry starts
                    ("ExecStartPre", f"+{NFT} -f {CONFIG_DIR}/firewall.nft"),
                    ("ExecStart", f"{REGISTRY} serve {CONFIG_DIR}/config.yml"),
                    ("ExecStopPost", f"+-{NFT} delete table inet {TABLE}"),
                    ("Restart", "on-failure"),
                    ("RestartSec", 5),
                    # its config and key are this user's alone (0600): the upstream's key is in the config
                    ("User", USER),
                    ("Group", USER),
                    *sandbox.server(),
                    ("ReadWritePaths", DATA),
                ],
            ),
            ("Install", [("WantedBy", "multi-user.target")]),
        ],
        header=[managed],
    )


def files(p: dict, managed: str, cert: str, key: str) -> dict:
    """{path: {content, mode[, uid, gid]}} for isaac_sim_host_service: the unit, and the files the
    registry reads as its user (p["uid"], p["gid"]: the package user's numbers)."""
    own = {"uid": int(p["uid"]), "gid": int(p["gid"])}
    return {
        f"/etc/systemd/system/{UNIT}": {"content": unit(p, managed), "mode": "0644"},
        f"{CONFIG_DIR}/config.yml": {"content": config(p), "mode": "0600", **own},
        f"{CONFIG_DIR}/mirror.crt": {"content": cert, "mode": "0644"},
        f"{CONFIG_DIR}/mirror.key": {"content": key, "mode": "0600", **own},
        f"{CONFIG_DIR}/firewall.nft": {"content": rules(p, managed), "mode": "0644"},
    }


def mirror_reference(image: str, mirror: str, upstream: str):
    """(the reference a host pulls through the mirror, or None when the image is not on the mirror's
    upstream). mirror: HOST:PORT; upstream: the registry it proxies, as a URL or a host."""
    from ansible_collections.isaacsim.fleet.plugins.module_utils.instance.image_pin import registry_of

    repository = image.split("@", 1)[0]
    name, _colon, tag = repository.rpartition(":")
    if "/" in tag:  # the colon was a registry's port, there is no tag
        name, tag = repository, ""
    home = urlparse(upstream).netloc if "://" in upstream else upstream
    # Docker Hub answers at registry-1.docker.io; Docker names its images docker.io
    home = DOCKER_HUB if home in DOCKER_HUB_NAMES else home
    if registry_of(name) != (home or DOCKER_HUB):
        return None
    path = name.split("/", 1)[1] if registry_of(name) != "docker.io" or name.startswith("docker.io/") else name
    if "/" not in path:  # Docker Hub's official images live under library/
        path = f"library/{path}"
    rest = image[len(repository) :]
    return f"{mirror}/{path}{':' + tag if tag else ''}{rest}"
