#!/usr/bin/python
# Copyright: isaacsim.fleet contributors
# SPDX-License-Identifier: Apache-2.0 (the collection's license, see galaxy.yml)
# Apache-2.0 is compatible with the GNU General Public License v3.0 that ansible-core is
# released under; ansible-test's validate-modules looks for that license's name here.

DOCUMENTATION = r"""
---
module: isaac_sim_info
short_description: Status and stream URLs of every Isaac Sim instance on a host, in one call
version_added: "0.2.0"
description:
  - "Reports every instance configured by the C(isaacsim.fleet.isaac_sim) role (its env file in
    C(/etc/isaac-sim)), and every stray C(isaac-sim-*) container or C(isaac-sim@N) unit that is not
    configured: unit state, enablement and restart count, container, image digest, readiness, port
    block, stream URLs, GPU and GPU memory, and optionally the last log lines."
  - "Fixed cost per host, whatever the number of instances: one C(systemctl show), two Docker Engine
    API calls over the daemon's socket (containers, images), one GPU query (NVML in-process through
    nvidia-ml-py, else one C(nvidia-smi -q -x)), and one C(journalctl) when O(log_lines) is set
    (it reads at most O(log_lines) entries per unit; only when one unit's lines crowd out
    another's is the journal read again for the units still short). RV(cost) reports what a
    call spent."
  - Read-only; supports check mode and always returns C(changed=false).
  - Needs root (C(become)) to read env files that hold secrets.
author: isaacsim.fleet contributors (@isaacsim-fleet)
extends_documentation_fragment:
  - isaacsim.fleet.attributes
  - isaacsim.fleet.attributes.platform
  - isaacsim.fleet.layout.config_dir
attributes:
  check_mode:
    support: full
    details: Reads only; the same in check mode.
  diff_mode:
    support: none
    details: Nothing changes, so there is no diff.
  platform:
    platforms: posix
options:
  public_address:
    description:
      - Host name or address put into the stream URLs.
      - Default is the address each instance was deployed with (C(isaac_sim_public_address)),
        else the host's default IPv4 address.
    type: str
    default: ""
  log_lines:
    description: Return the last this many journal lines of each instance's unit (0 returns none).
    type: int
    default: 0
  instances:
    description: Report only these instance numbers. Default is all, strays included.
    type: list
    elements: int
  gpu_source:
    description:
      - Where GPU memory per process is read. V(auto) tries NVML (the nvidia-ml-py bindings) and
        falls back to C(nvidia-smi); V(none) skips the GPU query.
    type: str
    default: auto
    choices: [auto, nvml, nvidia-smi, none]
  docker_host:
    description: The Docker daemon's socket.
    type: str
    default: unix:///var/run/docker.sock
  run_dir:
    description: Where the readiness gate writes its ready markers.
    type: path
    default: /run/isaac-sim
notes:
  - A container's start time is its creation time; the units create a new container on every start
    (C(docker run --rm)), so the two are the same for configured instances.
seealso:
  - module: isaacsim.fleet.isaac_sim_plan
"""

EXAMPLES = r"""
- name: Read the status of every instance
  isaacsim.fleet.isaac_sim_info:
  become: true
  register: isaac_sim_status

- name: The last 20 log lines of instances 0 and 2, URLs with the host's DNS name
  isaacsim.fleet.isaac_sim_info:
    instances: [0, 2]
    log_lines: 20
    public_address: "{{ inventory_hostname }}"
  become: true
  register: isaac_sim_logs
"""

RETURN = r"""
deployed:
  description: Whether the collection deployed Isaac Sim on this host (env files or the unit template exist).
  returned: always
  type: bool
public_address:
  description: The address used in the URLs when an instance has none of its own.
  returned: always
  type: str
  sample: 10.0.0.12
host_services:
  description: The host's own services that run in containers, such as NVIDIA's Hub cache (C(name), C(container),
    C(state), C(uptime_s)); never listed as instances or strays.
  returned: always
  type: list
  elements: dict
test_runs:
  description: The containers of test runs going on (C(run), C(service), C(container), C(state)); never listed as
    instances or strays.
  returned: always
  type: list
  elements: dict
status_url:
  description: Where this host serves the same status live, read-only (the isaac_sim role's status endpoint); null when
    it does not.
  returned: always
  type: str
  sample: http://10.0.0.12:8290/status
agent_url:
  description: Where this host's action agent listens (mutual TLS; only the front door's certificate, from
    isaac_sim_agent_allow's networks, gets an answer); null when it runs none.
  returned: always
  type: str
  version_added: 0.4.0
  sample: https://10.0.0.12:8291
summary:
  description: Counts over the instances reported.
  returned: always
  type: dict
  sample: {"configured": 4, "running": 4, "ready": 3, "failed": 0, "stopped": 0, "stray": 1}
instances:
  description: One entry per instance, configured ones first, by number.
  returned: always
  type: list
  elements: dict
  contains:
    id:
      description: Instance number (null for a stray container whose name has no number).
      type: int
    name:
      description: Container name, C(isaac-sim-N).
      type: str
    unit:
      description: Unit name, C(isaac-sim@N.service).
      type: str
    configured:
      description: Whether an env file configures it.
      type: bool
    stray:
      description: Found on the host but not configured (a hand-made container or a leftover unit).
      type: bool
    state:
      description: One word - ready, running, starting, restarting, stopping, failed, stopped or stray-container.
      type: str
    ready:
      description: Whether the readiness gate saw the release's ready line since the container started.
      type: bool
    ready_since:
      description: When it became ready (epoch seconds).
      type: int
    active_state:
      description: systemd's ActiveState of the unit.
      type: str
    sub_state:
      description: systemd's SubState of the unit.
      type: str
    enabled:
      description: Whether the unit starts at boot.
      type: bool
    unit_file_state:
      description: systemd's UnitFileState.
      type: str
    restarts:
      description: >-
        systemd's NRestarts - automatic restarts since the unit's counter was last reset. A session
        end (the app exits 0 after it was ready) resets it, so it counts the crashes since the last one.
      type: int
    last_day:
      description: >-
        What ended the instance's app in the last 24 hours, from the journal (C(journalctl -t
        isaac-sim-events)), which systemd's C(restarts) count cannot keep - it is reset by every session
        end and deliberate start. Null when the journal could not be read.
      type: dict
      contains:
        session_ends:
          description: Clean exits after ready (a stream session ended).
          type: int
        crashes:
          description: Non-zero exits, and clean exits before the instance was ready.
          type: int
        unhealthy_restarts:
          description: Stops by the unhealthy restart (isaac_sim_unhealthy_restart).
          type: int
        docker_away:
          description: Ends because Docker went away under the container.
          type: int
    down_reason:
      description: >-
        Why a configured instance is down - a crash loop that hit the start limit, another failure
        with systemd's result, or a stop; null while it serves or systemd is bringing it back.
      type: str
      sample: "failed (exit-code): read journalctl -u isaac-sim@2.service"
    lent_to:
      description: >-
        The test run (experience.yml, test_suite.yml) or the person's session (C(session-ID), the front door's)
        that holds the instance, its one claim; nothing but its holder restarts it until it is given back. Null
        when nothing holds it.
      type: str
      version_added: 0.4.0
      sample: nightly-7
    lent_ending:
      description: >-
        Where a rollout ends the session that holds the instance (isaac_sim_rollout_end_sessions) - C(at) (epoch
        seconds) and C(by); null otherwise.
      type: dict
      version_added: 0.4.0
      sample: {"at": 1795000120.5, "by": "an operator"}
    active_since:
      description: When the unit became active (epoch seconds).
      type: int
    container:
      description: The container, or null when there is none.
      type: dict
      contains:
        id:
          description: Full container id.
          type: str
        state:
          description: Docker's state (running, exited, ...).
          type: str
        health:
          description: Docker's health (none, starting, healthy, unhealthy).
          type: str
        started_at:
          description: Start time (epoch seconds).
          type: int
        uptime_s:
          description: Seconds since it started, while running.
          type: int
        image:
          description: Image reference the container was run from.
          type: str
        image_id:
          description: Local image id.
          type: str
        digest:
          description: Registry digest of the image (null for an image that was never pulled).
          type: str
    uptime_s:
      description: Seconds the container has been running.
      type: int
    health:
      description: The container's healthcheck after ready (AppReady in the newest kit log and the instance's port
        answering) - V(healthy), V(unhealthy), V(starting), or V(none) without a container or healthcheck.
      type: str
    release:
      description: Isaac Sim release family.
      type: str
    image:
      description: Configured image.
      type: str
    image_id:
      description: Image id of the running container, else the configured one.
      type: str
    digest:
      description: Registry digest of the running image.
      type: str
      sample: sha256:7ea27426fd569cff89afbef669e8d74092ec644c13e2c8c73cf5a0187506ebdd
    ports:
      description: The instance's port block, by kind.
      type: dict
      sample: {"signal": 49102, "stream": 48000, "web_viewer": 8212}
    public_address:
      description: Address in the URLs.
      type: str
    urls:
      description:
        - Where to point a client. 2023.1 - C(webrtc_client), the browser client URL, and C(native).
          4.x/5.x/6.x - C(signal), the address the Isaac Sim WebRTC Streaming Client asks for,
          C(stream) (UDP), and C(web_viewer) or C(api) where the release has that port.
      type: dict
      sample: {"signal": "10.0.0.12:49102", "stream": "10.0.0.12:48000/udp", "web_viewer": "http://10.0.0.12:8212/"}
    gpu:
      description: GPU index the instance is pinned to (null without a GPU).
      type: int
    gpu_memory_used_mib:
      description: GPU memory held by the container's processes (null when no GPU could be read).
      type: int
    gpu_processes:
      description: The container's GPU processes (gpu, pid, type, used_mib).
      type: list
      elements: dict
    limits:
      description: Memory, shm and GPU limits from its docker arguments.
      type: dict
      sample: {"memory": "8g", "shm_size": "2g", "gpus": "device=0"}
    companions:
      description: The instance's companions (its web viewer, and those of C(isaac_sim_companions)) - name,
        unit, container_name, configured, state, ready, active_state, enabled, restarts, image, health, uptime_s,
        container and ports. Their containers are never reported as strays.
      type: list
      elements: dict
      sample: [{"name": "viewer", "unit": "isaac-sim-viewer@2.service", "state": "ready", "ready": true,
                "health": "healthy", "restarts": 0, "ports": [{"proto": "tcp", "port": 8212}]}]
    logs:
      description: The last O(log_lines) journal lines, oldest first.
      returned: when O(log_lines) > 0
      type: list
      elements: str
gpu:
  description: The host's GPUs and how they were read.
  returned: always
  type: dict
  sample: {"source": "nvml", "driver": "570.172.08", "gpus": [{"index": 0, "name": "NVIDIA L40S",
           "uuid": "GPU-...", "memory_total_mib": 46068, "memory_used_mib": 9120}], "error": null}
docker_available:
  description: Whether the Docker daemon answered.
  returned: always
  type: bool
errors:
  description: What could not be read (the rest is still reported).
  returned: always
  type: list
  elements: str
cost:
  description: What this call spent - processes spawned and Docker API calls. Does not grow with the instances.
  returned: always
  type: dict
  sample: {"spawns": 2, "docker_api_calls": 2}
timings_ms:
  description:
    - The milliseconds of each part of the call, in the order they end - C(files) (env files), C(docker), C(gpu),
      C(systemd), C(build), C(events) (the last day's ends in the journal), C(logs) - so a slower status shows which
      part grew. C(systemctl show) and the events' C(journalctl) start before the parts in between; C(systemd) and
      C(events) are what is left of their wait.
  returned: always
  type: dict
  sample: {"files": 0.4, "docker": 3.2, "gpu": 0.1, "systemd": 6.1, "build": 0.3, "events": 0.8, "logs": 0.0}
"""

from ansible.module_utils.basic import AnsibleModule
from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib import fleet_status, gpu_usage
from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib.docker_socket import DockerSocket


def main():
    module = AnsibleModule(
        argument_spec=dict(
            public_address=dict(type="str", default=""),
            log_lines=dict(type="int", default=0),
            instances=dict(type="list", elements="int"),
            gpu_source=dict(type="str", default="auto", choices=["auto", "nvml", "nvidia-smi", "none"]),
            docker_host=dict(type="str", default="unix:///var/run/docker.sock"),
            config_dir=dict(type="path", default="/etc/isaac-sim"),
            run_dir=dict(type="path", default="/run/isaac-sim"),
        ),
        supports_check_mode=True,
    )
    p = module.params
    if p["log_lines"] < 0:
        module.fail_json(msg="log_lines: must be 0 or more. Fix: pass a count such as log_lines: 50.")
    spawns = []

    def start(argv):
        command = fleet_status.start(argv)
        if command.spawned:
            spawns.append(argv[0])
        return command

    docker = DockerSocket(p["docker_host"])
    result = fleet_status.gather(
        run=None,
        stream=None,
        docker=docker,
        import_nvml=gpu_usage.import_nvml,
        config_dir=p["config_dir"],
        run_dir=p["run_dir"],
        public_address=p["public_address"],
        gpu_source=p["gpu_source"],
        log_lines=p["log_lines"],
        only=p["instances"],
        start=start,
    )
    result["cost"] = {"spawns": len(spawns), "docker_api_calls": docker.calls}
    module.exit_json(changed=False, **result)


if __name__ == "__main__":
    main()
