# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""The host layout of the collection, defined once.

Paths, unit, container and marker names, env-file keys, labels, and the
env-file format (one quote/parse pair). Modules, filters, the role's
templates (through the plan's ``layout``) and the host-side scripts (through
the env file, which carries the names they need) take them from here; what
goes in each unit and env file is instance/unit_files.py's.
"""

from __future__ import annotations

import os
import re
import shlex

CONFIG_DIR = "/etc/isaac-sim"
UNIT_DIR = "/etc/systemd/system"
LIBEXEC_DIR = "/usr/local/libexec/isaac-sim"
LIB_DIR = "/usr/local/lib/isaac-sim/status"
RUN_DIR = "/run/isaac-sim"
DATA_ROOT = "/var/lib/isaac-sim"

UNIT_TEMPLATE = "isaac-sim@.service"
TARGET = "isaac-sim.target"
# where systemctl enable links the target for docker.service (its [Install] WantedBy=)
TARGET_DOCKER_WANT = f"{UNIT_DIR}/docker.service.wants/{TARGET}"
UNIT_GLOB = "isaac-sim@*.service"
CONTAINER_PREFIX = "isaac-sim-"
LABEL_INSTANCE = "org.isaacsim.fleet.instance"
LABEL_COMPANION = "org.isaacsim.fleet.companion"
# host-side scripts, installed in LIBEXEC_DIR
RUN_SCRIPT = "isaac-sim-run"
READY_SCRIPT = "isaac-sim-ready"
PORTS_SCRIPT = "isaac-sim-ports"
# before each start (with root's rights: the caches are the container user's): a warm or a cold start
CACHE_STATE_SCRIPT = "isaac-sim-cache-state"
# isaac-sim-run's exit status when a port of the block is held by another process
PORTS_HELD_STATUS = 76
# isaac-sim-run's check of the container Docker created, before it starts (the container policy), its
# exit status when the policy refuses it; the host library files the scripts read, beside them in
# LIBEXEC_DIR (isaac-sim-policy's, isaac-sim-firewall-site's)
POLICY_SCRIPT = "isaac-sim-policy"
POLICY_REFUSED_STATUS = 77
POLICY_LIB = ("docker_cli.py", "container_policy.py", "site_firewall.py")
# before each start (root's rights, never fatal): our containers that containerd runs and Docker lost
ORPHANS_SCRIPT = "isaac-sim-orphans"
# every container of the collection carries it in its environment (K_INSTANCE's name), lost or not
# the collection's accept rules in the site's own nftables chains, again after the site reloaded them
FIREWALL_SITE_SCRIPT = "isaac-sim-firewall-site"
# installed with the scripts, but no instance runs them: a change of them restarts no instance
NOT_RUN_BY_INSTANCES = (FIREWALL_SITE_SCRIPT, "site_firewall.py")
SCRIPTS = (
    RUN_SCRIPT,
    READY_SCRIPT,
    PORTS_SCRIPT,
    CACHE_STATE_SCRIPT,
    POLICY_SCRIPT,
    ORPHANS_SCRIPT,
    FIREWALL_SITE_SCRIPT,
)
# the host's read-only status endpoint (a host service, not an instance)
STATUS_UNIT = "isaac-sim-status.service"
STATUS_SCRIPT = "isaac-sim-status-server"
STATUS_ENV = "status.env"
K_STATUS_URL = "ISAAC_SIM_STATUS_URL"
# the host's action agent: the front door's one way to act on instances (mutual TLS, a fixed list of
# actions through the one lifecycle); its code is a copy of the collection's module_utils tree
AGENT_UNIT = "isaac-sim-agent.service"
AGENT_LIB = "/usr/local/lib/isaac-sim/agent"
AGENT_TLS_DIR = f"{CONFIG_DIR}/agent"
AGENT_ENV = "agent.env"
K_AGENT_URL = "ISAAC_SIM_AGENT_URL"
AGENT_STATE_DIR = "/var/lib/isaac-sim-agent"
# the agent's code, under AGENT_LIB/ansible_collections/isaacsim/fleet/plugins/module_utils: agent.py and what
# it imports, no more (tests/unit/plugins/module_utils/instance/test_agent.py holds the list to the imports)
AGENT_CODE = (
    "common/__init__.py",
    "common/sandbox.py",
    "common/units.py",
    "host/__init__.py",
    "host/dirs.py",
    "hostlib/__init__.py",
    "hostlib/docker_socket.py",
    "hostlib/layout.py",
    "hostlib/site_firewall.py",
    "hostlib/status_server.py",
    "instance/__init__.py",
    "instance/agent.py",
    "instance/firewall.py",
    "instance/hostprobe.py",
    "instance/lifecycle.py",
    "instance/lifecycle_call.py",
    "instance/network.py",
    "instance/reserved_ports.py",
    "instance/runlock.py",
    "instance/unit_files.py",
)
AGENT_PACKAGE = "ansible_collections/isaacsim/fleet/plugins/module_utils"
# a drained host takes no new claim (a test run's, a session's); what runs there goes on
DRAINED = f"{CONFIG_DIR}/drained.json"
# the metrics exporter for node_exporter's textfile collector (a host service: a timer and its oneshot)
METRICS_UNIT = "isaac-sim-metrics.service"
METRICS_TIMER = "isaac-sim-metrics.timer"
METRICS_SCRIPT = "isaac-sim-metrics"
METRICS_FILE = "isaac_sim.prom"
# the first line of every file the collection writes on a host
MANAGED = "Ansible managed (isaacsim.fleet)"
# NVIDIA's Hub Workstation Cache, one per host, shared by its 6.x instances (a host service)
HUB_UNIT = "isaac-sim-hub.service"
HUB_CONTAINER = "isaac-sim-hub"
HUB_PORT = 14090
HUB_DROPIN = "isaac-sim@.service.d/hub.conf"
HUB_MOUNT = "/var/cache/hub"
LABEL_HOST_SERVICE = "org.isaacsim.fleet.host-service"
# the instances' firewall (instance/firewall.py): its unit, its rules and what they were made of
FIREWALL_UNIT = "isaac-sim-firewall.service"
FIREWALL_RULES = f"{CONFIG_DIR}/firewall.nft"
FIREWALL_STATE = f"{CONFIG_DIR}/firewall.json"
FIREWALL_SITE_DROPIN = f"{UNIT_DIR}/nftables.service.d/isaac-sim.conf"
# what the site's own chains must accept (site_firewall.py), for isaac-sim-firewall-site
FIREWALL_SITE_RULES = f"{CONFIG_DIR}/firewall-site.json"
# the Docker network that gives instances addresses of their own (isaac_sim_network_mode: macvlan)
NETWORK = "isaac-sim-macvlan"
LABEL_NETWORK = "org.isaacsim.fleet.network"

# test runs (experiences): one unit per service, in /run so a run does not outlive a reboot
RUN_UNIT_DIR = "/run/systemd/system"
RUN_PREFIX = "isaac-sim-run-"
LABEL_RUN = "org.isaacsim.fleet.run"
LABEL_RUN_SERVICE = "org.isaacsim.fleet.run-service"
# the one-off container that warms a cache before the first start of instances (instance/warm_cache.py);
# no "isaac-sim-" in its name: what looks for instances by name (a substring for Docker) never takes it for one
LABEL_WARM = "org.isaacsim.fleet.warm"
WARM_CONTAINER_PREFIX = "isaacsim-warm-"
RUN_OUTPUTS = "/isaacsim-fleet/outputs"
RUN_ID_RE = re.compile(r"^[a-z0-9][a-z0-9-]{0,62}\Z")

UNIT_RE = re.compile(r"^isaac-sim@(\d+)\.service\Z")
CONTAINER_RE = re.compile(r"^/?(isaac-sim-(\d+|.+))\Z")
ENV_FILE_RE = re.compile(r"^instance-(\d+)\.env\Z")
MARKER_RE = re.compile(r"^instance-(\d+)\.ready\Z")
LENT_RE = re.compile(r"^instance-(\d+)\.lent\Z")
# the name a person's session (the front door's pool) holds an instance by; any other holder is a test run
SESSION_RE = re.compile(r"^session-[a-z0-9]{1,32}\Z")
# a person's files: the instance's directory mounted as the container user's Documents (the key of the
# releases' mounts), and where a session's end moves it, whole, for the front door to take (lifecycle.take_files)
DOCUMENTS = "documents"
FILES_DIR = "files"
# a stash, or a later one of the same session beside it (session-ab12.2): a rename never lands on another
FILES_STASH_RE = re.compile(r"^(session-[a-z0-9]{1,32})(?:\.([2-9]|[1-9][0-9]{1,5}))?\Z")
# "warm" or "cold": whether the instance's caches held anything when its container last started
CACHE_STATE_RE = re.compile(r"^instance-(\d+)\.cache\Z")
# companions: a unit template per companion, one unit per instance (isaac-sim-viewer@2.service)
COMPANION_NAME_RE = re.compile(r"^[a-z][a-z0-9]*(?:-[a-z0-9]+)*\Z")
COMPANION_TEMPLATE_RE = re.compile(r"^isaac-sim-([a-z][a-z0-9-]*)@\.service\Z")
COMPANION_UNIT_RE = re.compile(r"^isaac-sim-([a-z][a-z0-9-]*)@(\d+)\.service\Z")
COMPANION_ENV_RE = re.compile(r"^instance-(\d+)\.([a-z][a-z0-9-]*)\.env\Z")
COMPANION_TEMPLATE_GLOB = "isaac-sim-*@.service"
# names a companion may not take: the collection's own units and scripts
RESERVED_COMPANIONS = ("metrics", "run", "ready", "ports", "status", "hub")

# env-file keys: the unit, the scripts and the status module read these
K_INSTANCE = "ISAAC_SIM_INSTANCE"
K_CONTAINER = "ISAAC_SIM_CONTAINER"
K_UNIT = "ISAAC_SIM_UNIT"
K_RELEASE = "ISAAC_SIM_RELEASE"
K_IMAGE = "ISAAC_SIM_IMAGE"
K_IMAGE_ID = "ISAAC_SIM_IMAGE_ID"
# REPOSITORY@DIGEST the fleet's deploy pinned the tag to (instance/image_pin.py): what runs
K_IMAGE_PINNED = "ISAAC_SIM_IMAGE_PINNED"
K_PORT_PREFIX = "ISAAC_SIM_PORT_"
K_PORTS = "ISAAC_SIM_PORTS"
K_PROFILE = "ISAAC_SIM_PROFILE"
K_GPU = "ISAAC_SIM_GPU"
K_PUBLIC_ADDRESS = "ISAAC_SIM_PUBLIC_ADDRESS"
# the instance's own address (macvlan); empty: it shares the host's network
K_ADDRESS = "ISAAC_SIM_ADDRESS"
K_READY_TIMEOUT = "ISAAC_SIM_READY_TIMEOUT"
K_READY_PATTERN = "ISAAC_SIM_READY_PATTERN"
K_READY_MARKER = "ISAAC_SIM_READY_MARKER"
K_STOP_TIMEOUT = "ISAAC_SIM_STOP_TIMEOUT"
K_HEALTH_INTERVAL = "ISAAC_SIM_HEALTH_INTERVAL"
K_UNHEALTHY_RESTART = "ISAAC_SIM_UNHEALTHY_RESTART"
# the instance's cache directories on the host (releases.WARM_CACHES), as isaac-sim-cache-state reads them
K_CACHES = "ISAAC_SIM_CACHES"
# where it writes what it found (cache_state): the path comes from here, as the ready marker's does
K_CACHE_STATE = "ISAAC_SIM_CACHE_STATE"
K_DOCKER_ARGS = "ISAAC_SIM_DOCKER_ARGS"
K_APP_ARGS = "ISAAC_SIM_APP_ARGS"
K_COMPANION = "ISAAC_SIM_COMPANION"
# given to a companion's container: its instance's public address
K_HOST = "ISAAC_SIM_HOST"
# given to a test run's containers
K_RUN = "ISAAC_SIM_RUN"
K_RUN_OUTPUTS = "ISAAC_SIM_RUN_OUTPUTS"
RESERVED_PREFIX = "ISAAC_SIM_"


def unit(i: int) -> str:
    return f"isaac-sim@{i}.service"


def container(i: int) -> str:
    return f"{CONTAINER_PREFIX}{i}"


def env_file(i: int, config_dir: str = CONFIG_DIR) -> str:
    return os.path.join(config_dir, f"instance-{i}.env")


def lent_marker(i: int, run_dir: str = RUN_DIR) -> str:
    """A directory while instance i is lent to a test run (mkdir is atomic: one borrower), with
    the run's name in its file `run`."""
    return f"{run_dir}/instance-{i}.lent"


def marker(i: int, run_dir: str = RUN_DIR) -> str:
    return os.path.join(run_dir, f"instance-{i}.ready")


def data_dir(i: int, data_root: str = DATA_ROOT) -> str:
    return os.path.join(data_root, f"instance-{i}")


def documents_dir(i: int, data_root: str = DATA_ROOT) -> str:
    """The host directory mounted as instance i's Documents (plan.py mounts data_dir/DOCUMENTS)."""
    return os.path.join(data_dir(i, data_root), DOCUMENTS)


def files_dir(holder: str, data_root: str = DATA_ROOT) -> str:
    """Where a session's Documents go when its instance is reset (holder: a session's name, else ValueError)."""
    if not isinstance(holder, str) or not SESSION_RE.match(holder):
        raise ValueError(f"{holder!r} is not a session's name (session- and 1-32 lowercase letters and digits)")
    return os.path.join(data_root, FILES_DIR, holder)


def files_stash(holder: str, n: int = 1, data_root: str = DATA_ROOT) -> str:
    """The session's n-th stash: files_dir itself, then files_dir.2, .3 for later ones while it is still there."""
    return files_dir(holder, data_root) + (f".{n}" if n > 1 else "")


def companion_template(name: str) -> str:
    return f"isaac-sim-{name}@.service"


def companion_unit(i: int, name: str) -> str:
    return f"isaac-sim-{name}@{i}.service"


def companion_container(i: int, name: str) -> str:
    return f"{CONTAINER_PREFIX}{i}-{name}"


def companion_env_file(i: int, name: str, config_dir: str = CONFIG_DIR) -> str:
    return os.path.join(config_dir, f"instance-{i}.{name}.env")


def cache_state(i: int, run_dir: str = RUN_DIR) -> str:
    return os.path.join(run_dir, f"instance-{i}.cache")


def companion_marker(i: int, name: str, run_dir: str = RUN_DIR) -> str:
    return os.path.join(run_dir, f"instance-{i}.{name}.ready")


def companion_data_dir(i: int, name: str, data_root: str = DATA_ROOT) -> str:
    return os.path.join(data_dir(i, data_root), "companions", name)


def run_name(run: str, service: str | None = None) -> str:
    """A run's network (service None), or one service's unit stem and container name."""
    return f"{RUN_PREFIX}{run}" + (f"-{service}" if service else "")


def run_unit(run: str, service: str) -> str:
    return f"{run_name(run, service)}.service"


def run_volume(run: str, volume: str) -> str:
    return f"{run_name(run)}-{volume}"


def run_dir(run: str, data_root: str = DATA_ROOT) -> str:
    return os.path.join(data_root, "runs", run)


def warm_dir(data_root: str = DATA_ROOT) -> str:
    """The host's warmed caches, one archive per cache key (instance/warm_cache.py)."""
    return os.path.join(data_root, "warm-caches")


def warm_scratch(store: str, name: str) -> bool:
    """Whether `name` in the warmed caches' directory is what a killed warm run left: its scratch (a
    dot-directory, not a link) or a partly written archive."""
    path = os.path.join(store, name)
    return (name.startswith(".") and os.path.isdir(path) and not os.path.islink(path)) or name.endswith(".partial")


def instance_id(pattern: re.Pattern, name: str):
    """The instance number in a unit, env-file or marker name, else None."""
    match = pattern.match(os.path.basename(name))
    return int(match.group(1)) if match else None


def as_dict(data_root: str = DATA_ROOT) -> dict:
    """The layout for templates and playbooks (the plan module returns it)."""
    return {
        "config_dir": CONFIG_DIR,
        "unit_dir": UNIT_DIR,
        "libexec_dir": LIBEXEC_DIR,
        "lib_dir": LIB_DIR,
        "run_dir": RUN_DIR,
        "data_root": data_root,
        "warm_dir": warm_dir(data_root),
        "label_warm": LABEL_WARM,
        "unit_template": UNIT_TEMPLATE,
        "target": TARGET,
        "container_prefix": CONTAINER_PREFIX,
        "label_instance": LABEL_INSTANCE,
        "status_unit": STATUS_UNIT,
        "status_script": STATUS_SCRIPT,
        "status_env": f"{CONFIG_DIR}/{STATUS_ENV}",
        "k_status_url": K_STATUS_URL,
        "agent_unit": AGENT_UNIT,
        "agent_lib": AGENT_LIB,
        "agent_tls_dir": AGENT_TLS_DIR,
        "agent_code": list(AGENT_CODE),
        "agent_package": f"{AGENT_LIB}/{AGENT_PACKAGE}",
        "agent_env": f"{CONFIG_DIR}/{AGENT_ENV}",
        "k_agent_url": K_AGENT_URL,
        "drained": DRAINED,
        "metrics_unit": METRICS_UNIT,
        "metrics_timer": METRICS_TIMER,
        "metrics_script": METRICS_SCRIPT,
        "metrics_file": METRICS_FILE,
        "hub_unit": HUB_UNIT,
        "firewall_unit": FIREWALL_UNIT,
        "firewall_site_dropin": FIREWALL_SITE_DROPIN,
        "hub_dropin": HUB_DROPIN,
        "hub_dir": f"{data_root}/hub-cache",
        "network": NETWORK,
    }


# --- the env-file format: what systemd's EnvironmentFile= reads back exactly ---

# inside double quotes systemd unescapes exactly these
_ESCAPES = (("\\", "\\\\"), ('"', '\\"'), ("$", "\\$"), ("`", "\\`"))


def quote(value) -> str:
    """A value for an env file, double-quoted so systemd reads back exactly ``value``.

    A newline stays inside the quotes; systemd keeps it.
    """
    text = str(value)
    for raw, escaped in _ESCAPES:
        text = text.replace(raw, escaped)
    return f'"{text}"'


def parse_shown(text: str) -> dict:
    """{unit: {property: value}} from one `systemctl show -p Id,... UNIT...` (a block of lines per unit,
    blank lines between them); a block without an Id is left out."""
    shown = {}
    for block in re.split(r"\n\s*\n", (text or "").strip()):
        fields = dict(line.split("=", 1) for line in block.splitlines() if "=" in line)
        if fields.get("Id"):
            shown[fields["Id"]] = fields
    return shown


def parse(text: str) -> dict:
    """KEY=VALUE pairs as systemd reads them: the inverse of ``quote`` (and of plain values).

    Handles double-quoted values spanning lines, backslash escapes inside them,
    single-quoted values, comments and blank lines.
    """
    env, i, n = {}, 0, len(text or "")
    while i < n:
        # one logical line: skip blanks and comments
        while i < n and text[i] in " \t\r\n":
            i += 1
        if i >= n:
            break
        if text[i] in "#;":
            i = text.find("\n", i)
            i = n if i < 0 else i + 1
            continue
        eq = text.find("=", i)
        nl = text.find("\n", i)
        if eq < 0 or (0 <= nl < eq):
            i = n if nl < 0 else nl + 1
            continue
        key = text[i:eq].strip()
        i = eq + 1
        while i < n and text[i] in " \t":
            i += 1
        out = []
        if i < n and text[i] == '"':
            i += 1
            while i < n and text[i] != '"':
                if text[i] == "\\" and i + 1 < n:
                    nxt = text[i + 1]
                    if nxt == "\n":  # a line continuation
                        i += 2
                        continue
                    out.append(nxt if nxt in '"\\$`' else "\\" + nxt)
                    i += 2
                    continue
                out.append(text[i])
                i += 1
            i += 1
            nl = text.find("\n", i)
            i = n if nl < 0 else nl + 1
        elif i < n and text[i] == "'":
            end = text.find("'", i + 1)
            end = n if end < 0 else end
            out.append(text[i + 1 : end])
            nl = text.find("\n", end)
            i = n if nl < 0 else nl + 1
        else:
            nl = text.find("\n", i)
            end = n if nl < 0 else nl
            out.append(text[i:end].rstrip())
            i = end + 1
        env[key] = "".join(out)
    return env


def join_args(args) -> str:
    """Arguments as one env value that isaac-sim-run splits back exactly (POSIX shell quoting)."""
    return shlex.join(str(a) for a in args)


def split_args(value: str) -> list:
    """The arguments join_args joined (POSIX shell words, as shlex.split reads them).

    The words are found by one regular expression: shlex reads a character at a time in Python,
    about half a millisecond for an instance's docker arguments, on every status read. Whatever
    the expression does not take whole (an unclosed quote, a lone backslash) is shlex's to read
    or refuse.
    """
    text = value or ""
    if not _WORDS.fullmatch(text):
        return shlex.split(text)
    return [_SEGMENT.sub(_unquote, word) for word in _WORD.findall(text)]


def _unquote(segment) -> str:
    single, double, escaped, plain = segment.groups()
    if single is not None:
        return single
    if double is not None:
        # inside double quotes a backslash escapes only a double quote or itself
        return _DOUBLE_ESCAPE.sub(r"\1", double)
    return escaped if escaped is not None else plain


_SEGMENT_TEXT = r"""'([^']*)'|"((?:[^"\\]|\\.)*)"|\\(.)|([^\s'"\\]+)"""
_SEGMENT = re.compile(_SEGMENT_TEXT, re.S)
_WORD = re.compile(r"(?:" + _SEGMENT_TEXT.replace("(", "(?:").replace("(?:?:", "(?:") + r")+", re.S)
_WORDS = re.compile(r"\s*(?:" + _WORD.pattern + r"\s*)*", re.S)
_DOUBLE_ESCAPE = re.compile(r'\\(["\\])')
