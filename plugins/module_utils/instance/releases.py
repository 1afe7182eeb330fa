# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""What each Isaac Sim release understands at its container interface.

One profile per release family: the container user, where it keeps caches,
which ports its block holds and how each port is set (a kit flag or an
environment variable), the ways it can run (isaac_sim_profile: the launch script
and the ports each opens), where a person reaches an instance (urls: the URL shapes of
its ports), the line it prints when ready, and the oldest driver it runs on.

The URL shapes are defined in hostlib/endpoints.py (URLS) and named here: every host
reads them there, by the release its env files name, and that library imports nothing
outside itself. A new release is a new entry here and its shapes there
(tests/unit/test_release_choices.py checks that they agree).
"""

from __future__ import annotations

from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib import endpoints

# A port is set either by a kit flag ("--/path=VALUE") or an environment
# variable passed into the container.
KIT = "kit"
ENV = "env"

_ROOT_MOUNTS = {
    "cache/kit": "/isaac-sim/kit/cache",
    "cache/ov": "/root/.cache/ov",
    "cache/pip": "/root/.cache/pip",
    "cache/glcache": "/root/.cache/nvidia/GLCache",
    "cache/computecache": "/root/.nv/ComputeCache",
    "logs": "/root/.nvidia-omniverse/logs",
    "data": "/root/.local/share/ov/data",
    "documents": "/root/Documents",
}

# 5.0 and later run as the image's isaac-sim user (uid 1234, home /isaac-sim), with the
# mounts of NVIDIA's container page (its docs and tools/docker compose recipe).
_ISAAC_USER_MOUNTS = {
    "cache/main": "/isaac-sim/.cache",
    "cache/computecache": "/isaac-sim/.nv/ComputeCache",
    "logs": "/isaac-sim/.nvidia-omniverse/logs",
    "config": "/isaac-sim/.nvidia-omniverse/config",
    "data": "/isaac-sim/.local/share/ov/data",
    "pkg": "/isaac-sim/.local/share/ov/pkg",
    "documents": "/isaac-sim/Documents",
}

# 6.x adds the Hub cache (6.0) and the kit cache (NVIDIA's 6.2 recipe); the Hub cache is
# kept per instance, as NVIDIA's recipe keeps it per stack.
_ISAAC_USER_MOUNTS_6X = dict(_ISAAC_USER_MOUNTS, **{"cache/kit": "/isaac-sim/kit/cache", "cache/hub": "/var/cache/hub"})

_STREAMING_PORTS_5X = {
    # kind: (protocol, default base, how it is set, setting)
    "signal": ("tcp", 49100, KIT, "/app/livestream/port"),
    "stream": ("udp", 47998, KIT, "/app/livestream/fixedHostPort"),
    "http": ("tcp", 8011, KIT, "/exts/omni.services.transport.server.http/port"),
}

# the mounts whose content a start reuses (shader, GL and compute caches; 5.x and later keep the
# shader cache under .cache): a start with any file in them is warm, one with none is cold
WARM_CACHES = ("cache/kit", "cache/ov", "cache/main", "cache/glcache", "cache/computecache")

STREAMING, HEADLESS, NATIVE = "streaming", "headless", "native"
# the profiles that stream through the GPU's video encoder
STREAMS = (STREAMING, NATIVE)


def _launch(entrypoint, opens, health_port, args=()):
    """One way to run a release (isaac_sim_profile): its launch script and arguments, the ports of
    the block it opens, and the port its healthcheck asks (None: NVIDIA's AppReady check alone)."""
    return {"entrypoint": entrypoint, "args": list(args), "opens": list(opens), "health_port": health_port}


# No stream at all: NVIDIA's container has no launch script for it (runheadless.sh streams); its
# skill runs the full app with --no-window, which still prints "Isaac Sim Full App is loaded.".
# Kit refuses to run as root without --allow-root (NVIDIA's own root-era scripts pass it).
def _headless(uid):
    return _launch("/isaac-sim/isaac-sim.sh", (), None, ["--no-window"] + (["--allow-root"] if uid == 0 else []))


RELEASES = {
    "2023.1": {
        "default_tag": "2023.1.1",
        "uid": 0,
        "gid": 0,
        "mounts": _ROOT_MOUNTS,
        "ports": {
            "http": ("tcp", 8211, KIT, "/exts/omni.services.transport.server.http/port"),
            "webrtc": ("tcp", 8011, KIT, "/exts/omni.kit.livestream.webrtc/port"),
            # the native livestream's port (48010 by default, set by the livestream's port setting)
            "native": ("tcp", 48010, KIT, "/app/livestream/port"),
        },
        # NVIDIA: one streaming method per instance; the WebRTC browser client by default
        "profiles": {
            STREAMING: _launch("/isaac-sim/runheadless.webrtc.sh", ("http", "webrtc"), "http"),
            NATIVE: _launch("/isaac-sim/runheadless.native.sh", ("native",), None),
            HEADLESS: _headless(0),
        },
        # where a person reaches it: its ports' URL shapes (hostlib/endpoints.py)
        "urls": endpoints.URLS["2023.1"],
        "public_address": (KIT, "/app/livestream/publicEndpointAddress"),
        "ready_pattern": r"App is loaded\.",
        "min_driver": "525.85",
        "env": {},
        "security_opts": [],
        # NVIDIA's 2023.1 requirements: minimum GeForce RTX 3070, 8 GB
        "min_vram_mib": 8192,
        "log_dir": "/root/.nvidia-omniverse/logs",
    },
    "4.x": {
        "default_tag": "4.5.0",
        "uid": 0,
        "gid": 0,
        "mounts": _ROOT_MOUNTS,
        "ports": _STREAMING_PORTS_5X,
        "profiles": {
            STREAMING: _launch("/isaac-sim/runheadless.sh", _STREAMING_PORTS_5X, "signal"),
            HEADLESS: _headless(0),
        },
        # where a person reaches it: its ports' URL shapes (hostlib/endpoints.py)
        "urls": endpoints.URLS["4.x"],
        "public_address": (KIT, "/app/livestream/publicEndpointAddress"),
        "ready_pattern": r"App is loaded\.",
        "min_driver": "535.129",
        "env": {},
        "security_opts": [],
        "min_vram_mib": 16384,
        "log_dir": "/root/.nvidia-omniverse/logs",
    },
    "5.x": {
        "default_tag": "5.1.0",
        "uid": 1234,
        "gid": 1234,
        "mounts": _ISAAC_USER_MOUNTS,
        "ports": _STREAMING_PORTS_5X,
        "profiles": {
            STREAMING: _launch("/isaac-sim/runheadless.sh", _STREAMING_PORTS_5X, "signal"),
            HEADLESS: _headless(1234),
        },
        # where a person reaches it: its ports' URL shapes (hostlib/endpoints.py)
        "urls": endpoints.URLS["5.x"],
        "public_address": (KIT, "/app/livestream/publicEndpointAddress"),
        "ready_pattern": r"App is loaded\.",
        "min_driver": "570.169",
        "env": {},
        "security_opts": ["no-new-privileges"],
        "min_vram_mib": 16384,
        "log_dir": "/isaac-sim/.nvidia-omniverse/logs",
    },
    "6.x": {
        "default_tag": "6.0.1",
        "uid": 1234,
        "gid": 1234,
        "mounts": _ISAAC_USER_MOUNTS_6X,
        "ports": {
            "signal": ("tcp", 49100, ENV, "ISAACSIM_SIGNAL_PORT"),
            "stream": ("udp", 47998, ENV, "ISAACSIM_STREAM_PORT"),
            # served by the web viewer next to the instance; reserved in the block
            "web_viewer": ("tcp", 8210, None, None),
        },
        # the web viewer (a companion) comes with the streaming profile only
        "profiles": {
            STREAMING: _launch("/isaac-sim/runheadless.sh", ("signal", "stream"), "signal"),
            HEADLESS: _headless(1234),
        },
        # where a person reaches it: its ports' URL shapes (hostlib/endpoints.py)
        "urls": endpoints.URLS["6.x"],
        "public_address": (ENV, "ISAACSIM_HOST"),
        "ready_pattern": r"App is loaded\.",
        "min_driver": "570.169",
        "env": {},
        "security_opts": ["no-new-privileges"],
        "min_vram_mib": 16384,
        "log_dir": "/isaac-sim/.nvidia-omniverse/logs",
    },
}

DEFAULT_RELEASE = "6.x"
# NVIDIA's minimum system memory for Isaac Sim 4.5 to 6.x (its requirements page): a memory
# limit below it may get a real instance killed while it compiles shaders.
MIN_MEMORY = 32 * 1024**3
NGC_REPOSITORY = "nvcr.io/nvidia/isaac-sim"


# Longest wait for the app to take the probe's connection off its listening socket's queue.
ACCEPT_WAIT_S = 5


def healthcheck(release: str, port: int | None, address: str = "") -> str:
    """The container healthcheck: NVIDIA's own (AppReady in the newest kit log, as its 6.x image
    and compose recipe check it) and, where the profile opens a port, the port taking a connection
    at the address clients use. Nothing is sent and no reply is awaited (NVIDIA documents neither
    for the signalling server): the probe connects, leaves, and reads the kernel's accept queue of
    the port's listening socket in /proc/net/tcp. A running app takes a connection off that queue
    at once; a hung one leaves it there (and, once the queue is full, the connect times out)."""
    logs = RELEASES[release]["log_dir"]
    check = (
        f'latest=$(ls -t {logs}/Kit/*/*/kit_*.log 2>/dev/null | head -1) && [ -n "$latest" ] '
        f'&& grep -q AppReady "$latest"'
    )
    if port is None:
        return check
    # /proc/net/tcp: "sl local_address rem_address st tx_queue:rx_queue ..."; for a listening
    # socket (st 0A) rx_queue is the number of connections waiting to be accepted. Each file is read
    # by a command substitution, which the shell waits for: a process substitution's reader outlived
    # the check, and a PID 1 that reaps nothing (an app run without an init) kept a zombie per check.
    hexport = f"{port:04X}"
    probe = (
        f"exec 3<>/dev/tcp/{address or '127.0.0.1'}/{port} && exec 3>&- && "
        f"for t in $(seq {ACCEPT_WAIT_S * 5}); do q=0; "
        f"for f in /proc/net/tcp /proc/net/tcp6; do [ -r $f ] || continue; "
        f"while read -r _ l _ st qs _; do "
        f'[ "$st" = 0A ] && [ "${{l##*:}}" = {hexport} ] && q=$((q + 16#${{qs#*:}})); '
        f'done <<< "$(< $f)"; done; '
        f'[ "$q" = 0 ] && exit 0; sleep 0.2; done; exit 1'
    )
    return f"{check} && bash -c '{probe}'"


def default_image(release: str) -> str:
    return f"{NGC_REPOSITORY}:{RELEASES[release]['default_tag']}"


def release_of_tag(tag: str) -> str | None:
    """The release family a version-like image tag belongs to, else None: the release whose name is the
    longest prefix of the tag, wherever it stands in the table (a 6.3 entry takes 6.3.0 from 6.x)."""
    found, longest = None, -1
    for name in RELEASES:
        prefix = name[:-2] if name.endswith(".x") else name
        if (tag == prefix or tag.startswith(prefix + ".")) and len(prefix) > longest:
            found, longest = name, len(prefix)
    return found
