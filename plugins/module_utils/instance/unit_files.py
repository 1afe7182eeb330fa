# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""Every unit and env file the collection installs, rendered from a plan with the layout's names:
an instance's and a companion's env file and units, the instances' target, and the host
services' units (the Hub cache, the status endpoint, the metrics exporter). All units are
written by common/units.py. Not on the hosts: only the controller's modules and filters render.
"""

from __future__ import annotations

import shlex

from ansible_collections.isaacsim.fleet.plugins.module_utils.common import sandbox, units
from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib import layout


def render_env(instance: dict, plan: dict, image_id: str, secret_env: dict, managed: str) -> str:
    """The env file of one instance. Every value quoted; arguments kept one per word."""
    settings = plan["settings"]
    i = instance["id"]
    lines = [
        f"# {managed}",
        f"# Isaac Sim instance {i}, read by {layout.unit(i)}.",
        f"{layout.K_INSTANCE}={i}",
        f"{layout.K_CONTAINER}={layout.quote(layout.container(i))}",
        f"{layout.K_UNIT}={layout.quote(layout.unit(i))}",
        f"{layout.K_RELEASE}={layout.quote(plan['release'])}",
        f"{layout.K_IMAGE}={layout.quote(plan['image'])}",
        f"{layout.K_IMAGE_ID}={layout.quote(image_id)}",
    ]
    # the digest the tag named when the deploy asked, for every host of it: what runs (image_pin.py)
    if plan.get("image_pinned"):
        lines.append(f"{layout.K_IMAGE_PINNED}={layout.quote(plan['image_pinned'])}")
    lines += [f"{layout.K_PORT_PREFIX}{kind.upper()}={port}" for kind, port in instance["ports"].items()]
    protocols = instance.get("protocols", {})
    # checked free at start (isaac-sim-ports): the ports the app itself opens, not a companion's
    listens = instance.get("listens", list(instance["ports"]))
    ports = " ".join(
        f"{protocols.get(kind, 'tcp')}/{port}" for kind, port in instance["ports"].items() if kind in listens
    )
    lines.append(f"{layout.K_PORTS}={layout.quote(ports)}")
    lines += [
        f"{layout.K_PROFILE}={layout.quote(instance.get('profile', 'streaming'))}",
        f"{layout.K_GPU}={'' if instance.get('gpu') is None else instance['gpu']}",
        f"{layout.K_PUBLIC_ADDRESS}={layout.quote(instance.get('address') or plan.get('public_address') or '')}",
        f"{layout.K_READY_TIMEOUT}={settings['ready_timeout']}",
        f"{layout.K_READY_PATTERN}={layout.quote(plan['ready_pattern'])}",
        f"{layout.K_READY_MARKER}={layout.quote(layout.marker(i))}",
        f"{layout.K_STOP_TIMEOUT}={settings['stop_timeout']}",
        f"{layout.K_HEALTH_INTERVAL}={settings['health_interval']}",
        f"{layout.K_UNHEALTHY_RESTART}={settings['unhealthy_restart']}",
        f"{layout.K_CACHES}={layout.quote(layout.join_args(instance.get('caches') or []))}",
        f"{layout.K_CACHE_STATE}={layout.quote(layout.cache_state(i))}",
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
        f"# Companion {name} of Isaac Sim instance {i}, read by {layout.companion_unit(i, name)}.",
        f"{layout.K_INSTANCE}={i}",
        f"{layout.K_COMPANION}={layout.quote(name)}",
        f"{layout.K_CONTAINER}={layout.quote(layout.companion_container(i, name))}",
        f"{layout.K_UNIT}={layout.quote(layout.companion_unit(i, name))}",
        f"{layout.K_IMAGE}={layout.quote(companion['image'])}",
        f"{layout.K_PORTS}={layout.quote(own)}",
        f"{layout.K_READY_TIMEOUT}={companion['ready_timeout']}",
        # no ready line: ready once the container runs (and is healthy, with a healthcheck)
        f"{layout.K_READY_PATTERN}=",
        f"{layout.K_READY_MARKER}={layout.quote(layout.companion_marker(i, name))}",
        f"{layout.K_STOP_TIMEOUT}={companion['stop_timeout']}",
        f"{layout.K_HEALTH_INTERVAL}={companion['health_interval']}",
        f"{layout.K_UNHEALTHY_RESTART}={settings['unhealthy_restart'] if companion['health_interval'] else 0}",
    ]
    return "\n".join(lines + _container_lines(companion, list(companion["container_env"].items()))) + "\n"


def _container_lines(planned: dict, env: list) -> list:
    """The end of an instance's or a companion's env file: its docker and app arguments, its address,
    then the container's environment ([(name, value)])."""
    lines = [
        f"{layout.K_DOCKER_ARGS}={layout.quote(layout.join_args(planned['docker_args']))}",
        f"{layout.K_APP_ARGS}={layout.quote(layout.join_args(planned['app_args']))}",
    ]
    # only when set: an instance on the host's network keeps the env file it had; a companion with an
    # address is in its instance's network namespace (isaac-sim-ports has no host port to check)
    if planned.get("address"):
        lines.append(f"{layout.K_ADDRESS}={layout.quote(planned['address'])}")
    lines.append("# Container environment (passed by name with docker run --env NAME)")
    return lines + [f"{name}={layout.quote(value)}" for name, value in env]


def _service(env: str, name: str, restart_sec, ready_timeout, stop_timeout, pre=()) -> list:
    """The [Service] section shared by instances and companions: everything from the env file.
    pre: more of the unit's ExecStartPre lines, after the one that clears the container's name."""
    return [
        ("Type", "simple"),
        ("EnvironmentFile", env),
        ("SyslogIdentifier", name),
        "# A container left by a crash or an unclean reboot would block the name.",
        ("ExecStartPre", f"-/usr/bin/docker rm -f ${{{layout.K_CONTAINER}}}"),
        "# Ours that containerd still runs and a crashed dockerd forgot would hold ports: cleared (root's rights).",
        ("ExecStartPre", f"-+/usr/bin/python3 {layout.LIBEXEC_DIR}/{layout.ORPHANS_SCRIPT}"),
        *pre,
        f"# {layout.RUN_SCRIPT} refuses to start while a port of the block is held (Kit would move to",
        f"# another port) and exits {layout.PORTS_HELD_STATUS}, or a container the container policy refuses",
        f"# ({layout.POLICY_SCRIPT}) and exits {layout.POLICY_REFUSED_STATUS}: not retried, so systemctl status keeps",
        "# saying why.",
        ("RestartPreventExitStatus", f"{layout.PORTS_HELD_STATUS} {layout.POLICY_REFUSED_STATUS}"),
        ("ExecStart", f"{layout.LIBEXEC_DIR}/{layout.RUN_SCRIPT}"),
        ("ExecStartPost", f"{layout.LIBEXEC_DIR}/{layout.READY_SCRIPT}"),
        "# the container may have exited already (an app that quit): not an error",
        ("ExecStop", "-" + docker_if_up(f"stop -t ${{{layout.K_STOP_TIMEOUT}}} ${{{layout.K_CONTAINER}}}")),
        ("ExecStopPost", "-" + docker_if_up(f"rm -f ${{{layout.K_CONTAINER}}}")),
        ("ExecStopPost", f"-/bin/rm -f ${{{layout.K_READY_MARKER}}}"),
        "# A start or a run that Docker's going away cut short is no crash: systemd stops what Requires",
        "# Docker, and a start it stopped would count; the counter is flushed (reset-failed) for those.",
        ("ExecStopPost", "-/bin/sh -c 'systemctl -q is-active docker.service || exec systemctl reset-failed %n'"),
        "# Any exit, status 0 included, is restarted (6.x quits when a stream session ends);",
        f"# only systemctl stop keeps it down. {layout.RUN_SCRIPT} flushes the start-limit counter on a",
        "# clean exit after ready (a session end), so only crashes and failed starts count.",
        ("Restart", "always"),
        ("RestartSec", restart_sec),
        ("TimeoutStartSec", ready_timeout + 30),
        ("TimeoutStopSec", stop_timeout + 30),
        "# The docker client and the scripts around it; the container is Docker's (container_policy.py).",
        *sandbox.docker_client(),
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
    env = layout.env_file("%i")
    unit_section = [
        # what systemctl status and the journal say of an unconfigured isaac-sim@N beside the AssertPathExists line
        ("Description", f"Isaac Sim instance %i (configured by playbooks/deploy.yml in {env})"),
        ("Requires", "docker.service"),
        ("After", "docker.service network-online.target"),
        ("Wants", "network-online.target"),
        ("PartOf", layout.TARGET),
        ("AssertPathExists", env),
    ] + _start_limit(settings, settings["ready_timeout"])
    service = _service(
        env,
        layout.CONTAINER_PREFIX + "%i",
        settings["restart_sec"],
        settings["ready_timeout"],
        settings["stop_timeout"],
        pre=[
            f"# Whether this start finds its caches warm or cold, for status ({layout.CACHE_STATE_SCRIPT}).",
            "# With root's rights (+): the caches are the container user's (0750); never fatal (-).",
            ("ExecStartPre", f"-+{layout.LIBEXEC_DIR}/{layout.CACHE_STATE_SCRIPT}"),
        ],
    )
    return units.render(
        [("Unit", unit_section), ("Service", service), ("Install", [("WantedBy", layout.TARGET)])],
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
    env = layout.companion_env_file("%i", name)
    owner = layout.unit("%i")
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
        layout.companion_container("%i", name),
        settings["restart_sec"],
        companion["ready_timeout"],
        companion["stop_timeout"],
    )
    return units.render(
        [("Unit", unit_section), ("Service", service), ("Install", [("WantedBy", owner)])],
        header=[
            managed,
            f"Companion {name} of each Isaac Sim instance: systemctl status {layout.companion_unit('%i', name)}",
            f"The companion's settings for instance %i live in {env}.",
        ],
    )


def render_hub_unit(hub: dict, managed: str) -> str:
    """NVIDIA's Hub Workstation Cache as one unit per host (their docs run it with docker run):
    host networking, user 1234, the host's cache directory at /var/cache/hub. Its start ends
    when it listens, so the instances that want it start after it answers."""
    wait = (
        "for i in $$(seq 1 120); do "
        f"(exec 3<>/dev/tcp/127.0.0.1/{layout.HUB_PORT}) 2>/dev/null && exit 0; sleep 0.5; done; "
        f"echo 'the Hub cache did not listen on {layout.HUB_PORT} within 60 s' >&2; exit 1"
    )
    run = [
        "/usr/bin/docker run --rm",
        f"--name={layout.HUB_CONTAINER}",
        "--network=host",
        "--pull=never",
        "--user=1234:1234",
        "--security-opt=no-new-privileges",
        f"--label={layout.LABEL_HOST_SERVICE}=hub",
        f"--volume={hub['dir']}:{layout.HUB_MOUNT}:rw",
        hub["image"],
    ]
    unit_section = [
        ("Description", "NVIDIA Hub Workstation Cache for the Isaac Sim instances of this host"),
        ("Requires", "docker.service"),
        ("After", "docker.service network-online.target"),
        ("Wants", "network-online.target"),
    ]
    service = [
        ("ExecStartPre", f"-/usr/bin/docker rm -f {layout.HUB_CONTAINER}"),
        ("ExecStart", " ".join(run)),
        ("ExecStartPost", f'/bin/bash -c "{wait}"'),
        ("ExecStop", "-" + docker_if_up(f"stop -t 10 {layout.HUB_CONTAINER}")),
        ("Restart", "always"),
        ("RestartSec", 5),
        ("TimeoutStartSec", 90),
        *sandbox.docker_client(localhost=True),
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
    return units.render([("Unit", [("Wants", layout.HUB_UNIT), ("After", layout.HUB_UNIT)])], header=[managed])


AGENT_MODULE = "ansible_collections.isaacsim.fleet.plugins.module_utils.instance.agent"


def render_status_unit(server: dict, managed: str = layout.MANAGED) -> str:
    """The host's read-only status endpoint. server: name (the inventory's), address, port, allow
    (networks), logs_allow (networks given the instances' logs), origins, gpu_source."""
    argv = [
        f"/usr/bin/python3 {layout.LIBEXEC_DIR}/{layout.STATUS_SCRIPT} --lib {layout.LIB_DIR} "
        f"--name {shlex.quote(server['name'])}",
        f"--address {server['address']} --port {server['port']}",
    ]
    argv += [f"--allow {net}" for net in server.get("allow") or ()]
    argv += [f"--logs-allow {net}" for net in server.get("logs_allow") or ()]
    argv += [f"--origin {shlex.quote(origin)}" for origin in server.get("origins") or ()]
    argv.append(f"--gpu-source {server['gpu_source']}")
    service = [
        ("ExecStart", " ".join(argv)),
        ("Restart", "always"),
        ("RestartSec", 5),
        "# It reads the instances' env files (root's, mode 0600) and asks systemd, Docker and",
        "# nvidia-smi: root for the files it owns, without any capability, with nothing writable.",
        *sandbox.reader(),
        ("MemoryMax", "256M"),
        ("TasksMax", 64),
    ]
    unit = [
        ("Description", "Isaac Sim status of this host, read-only, for the fleet dashboard"),
        ("After", "network-online.target docker.service"),
        ("Wants", "network-online.target"),
    ]
    return units.render(
        [("Unit", unit), ("Service", service), ("Install", [("WantedBy", "multi-user.target")])],
        header=[managed],
    )


def render_agent_unit(agent: dict, managed: str = layout.MANAGED) -> str:
    """The host's action agent (instance/agent.py), run from its copy of the collection's
    module_utils. agent: name (the inventory's), port, allow (the front door's networks), soak,
    data_root."""
    argv = [
        f"/usr/bin/python3 -m {AGENT_MODULE} --name {shlex.quote(agent['name'])} --port {agent['port']}",
        *(f"--allow {net}" for net in agent["allow"]),
        f"--soak {agent['soak']} --data-root {shlex.quote(agent['data_root'])}",
    ]
    service = [
        ("Environment", f"PYTHONPATH={layout.AGENT_LIB}"),
        ("ExecStart", " ".join(argv)),
        ("Restart", "always"),
        ("RestartSec", 5),
        # an action in hand ends with the process; systemd finishes the instance's own job
        ("KillMode", "mixed"),
        *sandbox.agent(agent["data_root"]),
        ("MemoryMax", "256M"),
        ("TasksMax", 64),
    ]
    unit = [
        ("Description", "Isaac Sim action agent of this host: the front door's actions, through the lifecycle"),
        ("After", "network-online.target docker.service"),
        ("Wants", "network-online.target"),
    ]
    return units.render(
        [("Unit", unit), ("Service", service), ("Install", [("WantedBy", "multi-user.target")])],
        header=[managed],
    )


def render_metrics_units(metrics: dict, managed: str = layout.MANAGED) -> dict:
    """{unit name: text} of the metrics exporter: a oneshot that writes METRICS_FILE in
    metrics["textfile_dir"] and the timer that runs it every metrics["interval"]."""
    service = [
        ("Type", "oneshot"),
        (
            "ExecStart",
            f"/usr/bin/python3 {layout.LIBEXEC_DIR}/{layout.METRICS_SCRIPT} --lib {layout.LIB_DIR} "
            f"--output {metrics['textfile_dir']}/{layout.METRICS_FILE} --gpu-source {metrics['gpu_source']}",
        ),
        ("Nice", 10),
        "# reads as the status endpoint does; writes its one file",
        *sandbox.reader(writable=[metrics["textfile_dir"]], network=False),
    ]
    timer = [("OnActiveSec", "5s"), ("OnUnitActiveSec", metrics["interval"]), ("AccuracySec", "1s")]
    return {
        layout.METRICS_UNIT: units.render(
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
        layout.METRICS_TIMER: units.render(
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
            f"All Isaac Sim instances of this host: systemctl stop {layout.TARGET}",
            "Docker stopping stops it and every instance (Requires=); whenever Docker starts again, however it",
            "went away, it starts this target and so every enabled instance (WantedBy=docker.service).",
        ],
    )
