# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""The host layout of the collection, defined once.

Paths, unit, container and marker names, env-file keys, labels, and the
env-file format (one quote/parse pair). Modules, filters, the role's
templates (through the plan's ``layout``) and the host-side scripts (through
the env file, which carries the names they need) take them from here.
"""

from __future__ import annotations

import os
import re
import shlex

try:
    from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib import units
except ImportError:  # copied next to the host's scripts (roles/isaac_sim: the status library)
    import units

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
# isaac-sim-run's exit status when a port of the block is held by another process
PORTS_HELD_STATUS = 76
SCRIPTS = (RUN_SCRIPT, READY_SCRIPT, PORTS_SCRIPT)
# the host's read-only status endpoint (a host service, not an instance)
STATUS_UNIT = "isaac-sim-status.service"
STATUS_SCRIPT = "isaac-sim-status-server"
STATUS_ENV = "status.env"
K_STATUS_URL = "ISAAC_SIM_STATUS_URL"
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
# the Docker network that gives instances addresses of their own (isaac_sim_network_mode: macvlan)
NETWORK = "isaac-sim-macvlan"
LABEL_NETWORK = "org.isaacsim.fleet.network"

# test runs (experiences): one unit per service, in /run so a run does not outlive a reboot
RUN_UNIT_DIR = "/run/systemd/system"
RUN_PREFIX = "isaac-sim-run-"
LABEL_RUN = "org.isaacsim.fleet.run"
LABEL_RUN_SERVICE = "org.isaacsim.fleet.run-service"
RUN_OUTPUTS = "/isaacsim-fleet/outputs"
RUN_ID_RE = re.compile(r"^[a-z0-9][a-z0-9-]{0,62}$")

UNIT_RE = re.compile(r"^isaac-sim@(\d+)\.service$")
CONTAINER_RE = re.compile(r"^/?(isaac-sim-(\d+|.+))$")
ENV_FILE_RE = re.compile(r"^instance-(\d+)\.env$")
MARKER_RE = re.compile(r"^instance-(\d+)\.ready$")
# companions: a unit template per companion, one unit per instance (isaac-sim-viewer@2.service)
COMPANION_NAME_RE = re.compile(r"^[a-z][a-z0-9]*(?:-[a-z0-9]+)*$")
COMPANION_TEMPLATE_RE = re.compile(r"^isaac-sim-([a-z][a-z0-9-]*)@\.service$")
COMPANION_UNIT_RE = re.compile(r"^isaac-sim-([a-z][a-z0-9-]*)@(\d+)\.service$")
COMPANION_ENV_RE = re.compile(r"^instance-(\d+)\.([a-z][a-z0-9-]*)\.env$")
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


def companion_template(name: str) -> str:
    return f"isaac-sim-{name}@.service"


def companion_unit(i: int, name: str) -> str:
    return f"isaac-sim-{name}@{i}.service"


def companion_container(i: int, name: str) -> str:
    return f"{CONTAINER_PREFIX}{i}-{name}"


def companion_env_file(i: int, name: str, config_dir: str = CONFIG_DIR) -> str:
    return os.path.join(config_dir, f"instance-{i}.{name}.env")


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
        "unit_template": UNIT_TEMPLATE,
        "target": TARGET,
        "container_prefix": CONTAINER_PREFIX,
        "label_instance": LABEL_INSTANCE,
        "status_unit": STATUS_UNIT,
        "status_script": STATUS_SCRIPT,
        "status_env": f"{CONFIG_DIR}/{STATUS_ENV}",
        "k_status_url": K_STATUS_URL,
        "metrics_unit": METRICS_UNIT,
        "metrics_timer": METRICS_TIMER,
        "metrics_script": METRICS_SCRIPT,
        "metrics_file": METRICS_FILE,
        "hub_unit": HUB_UNIT,
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


# --- files rendered from a plan ---


def render_env(instance: dict, plan: dict, image_id: str, secret_env: dict, managed: str) -> str:
    """The env file of one instance. Every value quoted; arguments kept one per word."""
    settings = plan["settings"]
    i = instance["id"]
    lines = [
        f"# {managed}",
        f"# Isaac Sim instance {i}, read by {unit(i)}.",
        f"{K_INSTANCE}={i}",
        f"{K_CONTAINER}={quote(container(i))}",
        f"{K_UNIT}={quote(unit(i))}",
        f"{K_RELEASE}={quote(plan['release'])}",
        f"{K_IMAGE}={quote(plan['image'])}",
        f"{K_IMAGE_ID}={quote(image_id)}",
    ]
    lines += [f"{K_PORT_PREFIX}{kind.upper()}={port}" for kind, port in instance["ports"].items()]
    protocols = instance.get("protocols", {})
    # checked free at start (isaac-sim-ports): the ports the app itself opens, not a companion's
    listens = instance.get("listens", list(instance["ports"]))
    ports = " ".join(
        f"{protocols.get(kind, 'tcp')}/{port}" for kind, port in instance["ports"].items() if kind in listens
    )
    lines.append(f"{K_PORTS}={quote(ports)}")
    lines += [
        f"{K_PROFILE}={quote(instance.get('profile', 'streaming'))}",
        f"{K_GPU}={'' if instance.get('gpu') is None else instance['gpu']}",
        f"{K_PUBLIC_ADDRESS}={quote(instance.get('address') or plan.get('public_address') or '')}",
        f"{K_READY_TIMEOUT}={settings['ready_timeout']}",
        f"{K_READY_PATTERN}={quote(plan['ready_pattern'])}",
        f"{K_READY_MARKER}={quote(marker(i))}",
        f"{K_STOP_TIMEOUT}={settings['stop_timeout']}",
        f"{K_HEALTH_INTERVAL}={settings['health_interval']}",
        f"{K_UNHEALTHY_RESTART}={settings['unhealthy_restart']}",
    ]
    env = list(instance["container_env"].items()) + list((secret_env or {}).items())
    return "\n".join(lines + _container_lines(instance, env)) + "\n"


def render_companion_env(companion: dict, plan: dict, managed: str) -> str:
    """The env file of one companion of one instance (a planned companion, see plan.py)."""
    settings = plan["settings"]
    i, name = companion["instance"], companion["name"]
    own = " ".join(f"{companion['protocols'][p]}/{companion['ports'][p]}" for p in companion["own_ports"])
    lines = [
        f"# {managed}",
        f"# Companion {name} of Isaac Sim instance {i}, read by {companion_unit(i, name)}.",
        f"{K_INSTANCE}={i}",
        f"{K_COMPANION}={quote(name)}",
        f"{K_CONTAINER}={quote(companion_container(i, name))}",
        f"{K_UNIT}={quote(companion_unit(i, name))}",
        f"{K_IMAGE}={quote(companion['image'])}",
        f"{K_PORTS}={quote(own)}",
        f"{K_READY_TIMEOUT}={companion['ready_timeout']}",
        # no ready line: ready once the container runs (and is healthy, with a healthcheck)
        f"{K_READY_PATTERN}=",
        f"{K_READY_MARKER}={quote(companion_marker(i, name))}",
        f"{K_STOP_TIMEOUT}={companion['stop_timeout']}",
        f"{K_HEALTH_INTERVAL}={companion['health_interval']}",
        f"{K_UNHEALTHY_RESTART}={settings['unhealthy_restart'] if companion['health_interval'] else 0}",
    ]
    return "\n".join(lines + _container_lines(companion, list(companion["container_env"].items()))) + "\n"


def _container_lines(planned: dict, env: list) -> list:
    """The end of an instance's or a companion's env file: its docker and app arguments, its address,
    then the container's environment ([(name, value)])."""
    lines = [
        f"{K_DOCKER_ARGS}={quote(join_args(planned['docker_args']))}",
        f"{K_APP_ARGS}={quote(join_args(planned['app_args']))}",
    ]
    # only when set: an instance on the host's network keeps the env file it had; a companion with an
    # address is in its instance's network namespace (isaac-sim-ports has no host port to check)
    if planned.get("address"):
        lines.append(f"{K_ADDRESS}={quote(planned['address'])}")
    lines.append("# Container environment (passed by name with docker run --env NAME)")
    return lines + [f"{name}={quote(value)}" for name, value in env]


def _service(env: str, name: str, restart_sec, ready_timeout, stop_timeout) -> list:
    """The [Service] section shared by instances and companions: everything from the env file."""
    return [
        ("Type", "simple"),
        ("EnvironmentFile", env),
        ("SyslogIdentifier", name),
        "# A container left by a crash or an unclean reboot would block the name.",
        ("ExecStartPre", f"-/usr/bin/docker rm -f ${{{K_CONTAINER}}}"),
        f"# {RUN_SCRIPT} refuses to start while a port of the block is held (Kit would move to",
        f"# another port) and exits {PORTS_HELD_STATUS}: not retried, so systemctl status keeps saying why.",
        ("RestartPreventExitStatus", PORTS_HELD_STATUS),
        ("ExecStart", f"{LIBEXEC_DIR}/{RUN_SCRIPT}"),
        ("ExecStartPost", f"{LIBEXEC_DIR}/{READY_SCRIPT}"),
        "# the container may have exited already (an app that quit): not an error",
        ("ExecStop", "-" + docker_if_up(f"stop -t ${{{K_STOP_TIMEOUT}}} ${{{K_CONTAINER}}}")),
        ("ExecStopPost", "-" + docker_if_up(f"rm -f ${{{K_CONTAINER}}}")),
        ("ExecStopPost", f"-/bin/rm -f ${{{K_READY_MARKER}}}"),
        "# Any exit, status 0 included, is restarted (6.x quits when a stream session ends);",
        f"# only systemctl stop keeps it down. {RUN_SCRIPT} flushes the start-limit counter on a",
        "# clean exit after ready (a session end), so only crashes and failed starts count.",
        ("Restart", "always"),
        ("RestartSec", restart_sec),
        ("TimeoutStartSec", ready_timeout + 30),
        ("TimeoutStopSec", stop_timeout + 30),
    ]


def _start_limit(settings: dict, ready_timeout: int) -> list:
    burst = settings["start_limit_burst"]
    interval = burst * (settings["restart_sec"] + ready_timeout + 30)
    return [
        f"# Wide enough that {burst} failed starts, each up to the ready deadline apart, still count.",
        ("StartLimitIntervalSec", interval),
        ("StartLimitBurst", burst),
    ]


def docker_if_up(args: str) -> str:
    """A docker command for a unit's stop, run only while Docker runs: when dockerd died, systemd
    restarts it after stopping the units that need it, and a docker call would wait on the socket
    for the daemon that waits for this stop (until TimeoutStopSec). The daemon that comes back
    removes the containers left."""
    return f"/bin/sh -c 'systemctl -q is-active docker.service || exit 0; exec /usr/bin/docker {args}'"


def render_unit(settings: dict, managed: str) -> str:
    """The template unit isaac-sim@.service. Everything per instance comes from its env file."""
    env = env_file("%i")
    unit_section = [
        ("Description", "Isaac Sim instance %i"),
        ("Requires", "docker.service"),
        ("After", "docker.service network-online.target"),
        ("Wants", "network-online.target"),
        ("PartOf", TARGET),
        ("AssertPathExists", env),
    ] + _start_limit(settings, settings["ready_timeout"])
    service = _service(
        env, CONTAINER_PREFIX + "%i", settings["restart_sec"], settings["ready_timeout"], settings["stop_timeout"]
    )
    return units.render(
        [("Unit", unit_section), ("Service", service), ("Install", [("WantedBy", TARGET)])],
        header=[
            managed,
            "One Isaac Sim container per instance: systemctl start isaac-sim@2",
            f"The instance's settings live in {env}.",
        ],
    )


def render_companion_unit(companion: dict, settings: dict, managed: str) -> str:
    """The template unit of one companion, isaac-sim-NAME@.service: a unit per instance that
    starts once its instance is ready (After= its unit, whose start ends at the readiness gate),
    stops with it (BindsTo=), restarts with it (PartOf=) and is started by it (WantedBy=)."""
    name = companion["name"]
    env = companion_env_file("%i", name)
    owner = unit("%i")
    unit_section = [
        ("Description", f"Isaac Sim instance %i: companion {name}"),
        ("BindsTo", owner),
        ("After", owner),
        ("PartOf", owner),
        ("AssertPathExists", env),
        "# No start limit: when its instance restarts, systemd (252) counts the start that waits for the",
        "# companion to finish stopping once per step of the stop, and would leave it failed for good.",
        "# RestartSec paces a companion that crash-loops; its instance keeps its own limit.",
        ("StartLimitIntervalSec", 0),
    ]
    service = _service(
        env,
        companion_container("%i", name),
        settings["restart_sec"],
        companion["ready_timeout"],
        companion["stop_timeout"],
    )
    return units.render(
        [("Unit", unit_section), ("Service", service), ("Install", [("WantedBy", owner)])],
        header=[
            managed,
            f"Companion {name} of each Isaac Sim instance: systemctl status {companion_unit('%i', name)}",
            f"The companion's settings for instance %i live in {env}.",
        ],
    )


def render_hub_unit(hub: dict, managed: str) -> str:
    """NVIDIA's Hub Workstation Cache as one unit per host (their docs run it with docker run):
    host networking, user 1234, the host's cache directory at /var/cache/hub. Its start ends
    when it listens, so the instances that want it start after it answers."""
    wait = (
        f"for i in $$(seq 1 120); do (exec 3<>/dev/tcp/127.0.0.1/{HUB_PORT}) 2>/dev/null && exit 0; sleep 0.5; done; "
        f"echo 'the Hub cache did not listen on {HUB_PORT} within 60 s' >&2; exit 1"
    )
    run = [
        "/usr/bin/docker run --rm",
        f"--name={HUB_CONTAINER}",
        "--network=host",
        "--pull=never",
        "--user=1234:1234",
        "--security-opt=no-new-privileges",
        f"--label={LABEL_HOST_SERVICE}=hub",
        f"--volume={hub['dir']}:{HUB_MOUNT}:rw",
        hub["image"],
    ]
    unit_section = [
        ("Description", "NVIDIA Hub Workstation Cache for the Isaac Sim instances of this host"),
        ("Requires", "docker.service"),
        ("After", "docker.service network-online.target"),
        ("Wants", "network-online.target"),
    ]
    service = [
        ("ExecStartPre", f"-/usr/bin/docker rm -f {HUB_CONTAINER}"),
        ("ExecStart", " ".join(run)),
        ("ExecStartPost", f'/bin/bash -c "{wait}"'),
        ("ExecStop", "-" + docker_if_up(f"stop -t 10 {HUB_CONTAINER}")),
        ("Restart", "always"),
        ("RestartSec", 5),
        ("TimeoutStartSec", 90),
    ]
    return units.render(
        [("Unit", unit_section), ("Service", service), ("Install", [("WantedBy", "multi-user.target")])],
        header=[
            managed,
            "NVIDIA's Hub Workstation Cache for this host's Isaac Sim instances (isaac_sim_hub_cache_enabled).",
        ],
    )


def render_hub_dropin(managed: str) -> str:
    """Every instance wants the Hub cache and starts after it (a drop-in: no instance restarts for it)."""
    return units.render([("Unit", [("Wants", HUB_UNIT), ("After", HUB_UNIT)])], header=[managed])


# systemd's sandbox for a host service that only reads (the status endpoint: 2.3 in systemd-analyze security)
SANDBOX = (
    ("User", "root"),
    ("CapabilityBoundingSet", ""),
    ("AmbientCapabilities", ""),
    ("NoNewPrivileges", "yes"),
    ("ProtectSystem", "strict"),
    ("ProtectHome", "yes"),
    ("PrivateTmp", "yes"),
    ("ProtectKernelTunables", "yes"),
    ("ProtectKernelModules", "yes"),
    ("ProtectKernelLogs", "yes"),
    ("ProtectControlGroups", "yes"),
    ("ProtectClock", "yes"),
    ("ProtectHostname", "yes"),
    ("RestrictNamespaces", "yes"),
    ("RestrictRealtime", "yes"),
    ("RestrictSUIDSGID", "yes"),
    ("LockPersonality", "yes"),
    ("MemoryDenyWriteExecute", "yes"),
    ("RestrictAddressFamilies", "AF_UNIX AF_INET AF_INET6"),
    ("SystemCallArchitectures", "native"),
    ("SystemCallFilter", "@system-service"),
    ("UMask", "0077"),
)


def render_status_unit(server: dict, managed: str = MANAGED) -> str:
    """The host's read-only status endpoint. server: name (the inventory's), address, port, allow
    (networks), origins, gpu_source."""
    argv = [
        f"/usr/bin/python3 {LIBEXEC_DIR}/{STATUS_SCRIPT} --lib {LIB_DIR} --name {shlex.quote(server['name'])}",
        f"--address {server['address']} --port {server['port']}",
    ]
    argv += [f"--allow {net}" for net in server.get("allow") or ()]
    argv += [f"--origin {shlex.quote(origin)}" for origin in server.get("origins") or ()]
    argv.append(f"--gpu-source {server['gpu_source']}")
    service = [
        ("ExecStart", " ".join(argv)),
        ("Restart", "always"),
        ("RestartSec", 5),
        "# It reads the instances' env files (root's, mode 0600) and asks systemd, Docker and",
        "# nvidia-smi: root for the files it owns, without any capability, with nothing writable.",
        *SANDBOX,
        ("MemoryMax", "256M"),
        ("TasksMax", 64),
    ]
    unit = [
        ("Description", "Isaac Sim status of this host, read-only, for the fleet dashboard"),
        ("After", "network-online.target docker.service"),
        ("Wants", "network-online.target"),
    ]
    return units.render(
        [("Unit", unit), ("Service", service), ("Install", [("WantedBy", "multi-user.target")])], header=[managed]
    )


def render_metrics_units(metrics: dict, managed: str = MANAGED) -> dict:
    """{unit name: text} of the metrics exporter: a oneshot that writes METRICS_FILE in
    metrics["textfile_dir"] and the timer that runs it every metrics["interval"]."""
    service = [
        ("Type", "oneshot"),
        (
            "ExecStart",
            f"/usr/bin/python3 {LIBEXEC_DIR}/{METRICS_SCRIPT} --lib {LIB_DIR} "
            f"--output {metrics['textfile_dir']}/{METRICS_FILE} --gpu-source {metrics['gpu_source']}",
        ),
        ("Nice", 10),
    ]
    timer = [("OnActiveSec", "5s"), ("OnUnitActiveSec", metrics["interval"]), ("AccuracySec", "1s")]
    return {
        METRICS_UNIT: units.render(
            [
                (
                    "Unit",
                    [
                        ("Description", "Isaac Sim instance metrics for node_exporter's textfile collector"),
                        ("After", "docker.service"),
                    ],
                ),
                ("Service", service),
            ],
            header=[managed],
        ),
        METRICS_TIMER: units.render(
            [
                ("Unit", [("Description", f"Write Isaac Sim instance metrics every {metrics['interval']}")]),
                ("Timer", timer),
                ("Install", [("WantedBy", "timers.target")]),
            ],
            header=[managed],
        ),
    }


def render_target(managed: str) -> str:
    return units.render(
        [
            (
                "Unit",
                [("Description", "Isaac Sim instances"), ("Requires", "docker.service"), ("After", "docker.service")],
            ),
            ("Install", [("WantedBy", "multi-user.target docker.service")]),
        ],
        header=[
            managed,
            f"All Isaac Sim instances of this host: systemctl stop {TARGET}",
            "Docker stopping stops it and every instance (Requires=); whenever Docker starts again, however it",
            "went away, it starts this target and so every enabled instance (WantedBy=docker.service).",
        ],
    )
