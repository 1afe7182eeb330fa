# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""Where a person or a client points to reach an instance, per release."""

from __future__ import annotations

try:
    from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib import builtin_companions
except ImportError:  # copied flat next to the status endpoint and metrics scripts on a host
    import builtin_companions

# Who opens a port of the block: the instance (when its profile opens it) or a companion (when one
# serves it: a port kept for a companion, the 6.x web viewer's, is reported only when one does).
INSTANCE, COMPANION = "instance", "companion"

# What the Isaac Sim WebRTC Streaming Client asks for (4.x and later), then the services API where the
# block has it (a built-in companion's port, the 6.x web viewer's, has its shape in builtin_companions.py)
_STREAMING_CLIENT = (
    ("signal", "signal", "{host}:{port}", INSTANCE),
    ("stream", "stream", "{host}:{port}/udp", INSTANCE),
    ("http", "api", "http://{host}:{port}/", INSTANCE),
)

# The URL shapes of each release (the release table's releases, plugins/module_utils/instance/releases.py):
# (kind of port in the release's block, name reported, address with {host} and {port}, who opens it),
# in the order they are reported. Here, not in the release table: hosts read an instance's release
# from its env file and this library imports nothing outside itself (tests/unit/test_release_choices.py
# checks that every release has its shapes, of its own ports).
URLS = {
    "2023.1": (
        # served by the instance itself: the browser client, told where the signalling is
        ("http", "webrtc_client", "http://{host}:{port}/streaming/webrtc-client?server={host}", INSTANCE),
        # the native livestream, for the Omniverse Streaming Client
        ("native", "native", "{host}:{port}", INSTANCE),
    ),
    "4.x": _STREAMING_CLIENT,
    "5.x": _STREAMING_CLIENT,
    "6.x": _STREAMING_CLIENT,
}


def endpoints(release: str, ports: dict, host: str, served=(), listens=None) -> dict:
    """{name: address} for one instance's port block: only what listens, in the shapes of its
    release (URLS; a release this library does not know has the streaming client's), then the built-in
    companions' where one serves its port.

    listens: the kinds of the block the instance itself opens (its profile's; None: all of them).
    served: the ports of the block a companion listens on.
    """
    opened = set(ports) if listens is None else set(listens)
    served = set(served)
    out = {}
    for kind, name, shape, by in [*URLS.get(release, _STREAMING_CLIENT), *builtin_companions.shapes()]:
        if kind in ports and (ports[kind] in served if by == COMPANION else kind in opened):
            out[name] = shape.format(host=host, port=ports[kind])
    return out


def summary_lines(plan: dict, host: str) -> list:
    lines = []
    for inst in plan["instances"]:
        served = [port for c in inst.get("companions", []) for port in c["ports"].values()]
        eps = endpoints(plan["release"], inst["ports"], inst.get("address") or host, served, inst.get("listens"))
        gpu = "-" if inst.get("gpu") is None else inst["gpu"]
        mode = "" if inst.get("profile", "streaming") == "streaming" else f" profile={inst['profile']}"
        lines.append(f"{inst['name']} gpu={gpu}{mode} " + " ".join(f"{k}={v}" for k, v in eps.items()))
    return lines
