#!/usr/bin/python
# Copyright: isaacsim.fleet contributors
# SPDX-License-Identifier: Apache-2.0 (the collection's license, see galaxy.yml)
# Apache-2.0 is compatible with the GNU General Public License v3.0 that ansible-core is
# released under; ansible-test's validate-modules looks for that license's name here.

DOCUMENTATION = r"""
---
module: isaac_sim_plan
short_description: Validate an Isaac Sim instance configuration against a host and plan each instance
version_added: "0.1.0"
description:
  - Checks the configuration of the P(isaacsim.fleet.isaac_sim#role) role against the release it names
    and against the host (memory, GPUs, ports already held), and computes each instance's port block,
    GPU, directories, container arguments and environment.
  - Reports every problem at once, each naming the variable to change and how.
  - Read-only; never changes the host, but for the host's lock where O(lock) is given. Runs the same in check
    mode, where the lock is only looked at.
author: isaacsim.fleet contributors (@isaacsim-fleet)
extends_documentation_fragment:
  - isaacsim.fleet.attributes
  - isaacsim.fleet.attributes.platform
  - isaacsim.fleet.attributes.action
  - isaacsim.fleet.layout.data_root
  - isaacsim.fleet.layout.config_dir
  - isaacsim.fleet.secret_env
attributes:
  action:
    support: full
    details: Where O(lock) is given, names this run to the host's lock and waits while another run holds it.
  check_mode:
    support: full
    details: Changes nothing but the host's lock where O(lock) is given; in check mode that lock is only looked at,
      not taken, and the plan is made all the same.
  diff_mode:
    support: none
    details: Nothing changes, so there is no diff.
  platform:
    platforms: posix
options:
  release:
    description:
      - Isaac Sim release family, one of the release table's (V(2023.1), V(4.x), V(5.x), V(6.x)).
      - An unknown one is refused by the plan with a short message naming C(isaac_sim_release).
    type: str
    required: true
  image:
    description: Image reference the instances run; NVIDIA's image of O(release) when empty.
    type: str
    default: ""
  instance_count:
    description: Number of instances, numbered 0 to N-1.
    type: int
    required: true
  max_instances:
    description: Upper bound on O(instance_count) for this host.
    type: int
    default: 8
  scale_to_zero:
    description: Confirms an O(instance_count) of 0 on a host where instances serve (all of them go).
    type: bool
    default: false
  port_bases:
    description: Base port per port kind, overriding the release's defaults.
    type: dict
    default: {}
  port_stride:
    description: Distance between two instances' ports of the same kind.
    type: int
    default: 1
  gpu_enabled:
    description: Give each instance a GPU.
    type: bool
    default: true
  gpu_map:
    description: Instance number to GPU index; instances not in it are placed by the GPU memory they need.
    type: dict
    default: {}
  gpu_exclusive:
    description: Require one GPU per instance.
    type: bool
    default: false
  gpu_memory:
    description: GPU memory each instance needs, with its unit; empty is NVIDIA's minimum for the release.
    type: str
    default: ""
  instance_gpu_memory:
    description: Instance number to the GPU memory it needs.
    type: dict
    default: {}
  gpu_consumer_encode_sessions:
    description: Encode sessions NVIDIA's driver allows at once on a system's GeForce GPUs.
    type: int
    default: 8
  memory_limit:
    description: Memory limit per container, in Docker's size format.
    type: str
    default: 32g
  shm_size:
    description: Shared memory size per container.
    type: str
    default: 2g
  public_address:
    description: Address clients use to reach the streams; empty means the host's default IPv4.
    type: str
  ready_pattern:
    description: Regular expression of the ready line; the release's own when empty.
    type: str
  accept_eula:
    description: Whether the Isaac Sim license was accepted.
    type: bool
    default: false
  privacy_consent:
    description: Whether to consent to Isaac Sim's data collection.
    type: bool
    default: false
  env:
    description: Extra environment variables for the containers.
    type: dict
    default: {}
  docker_args:
    description:
      - Extra C(docker run) arguments, one per item.
      - Read as Docker's own client reads them (short flags run together, C(=) forms, C(--mount)'s CSV,
        Go's booleans, the last of a repeated option), then judged by the container policy
        (plugins/module_utils/hostlib/container_policy.py) here and in each companion's C(docker_args),
        C(volumes) and C(user). Refused unless O(allowed_docker_args) names them - privileged, an added
        capability, the host's PID, IPC, UTS, user or cgroup namespace, a confinement turned off or replaced
        with C(--security-opt), a host device or GPU, a bind mount from outside O(data_root) and
        O(allowed_bind_roots) (a local volume that binds a host path too), another container's volumes,
        root where the release runs as a user.
    type: list
    elements: str
    default: []
  allowed_docker_args:
    description: Arguments of O(docker_args) and of the companions' C(docker_args) that the container policy
      refuses and that are allowed all the same, each matched on what Docker makes of it
      (C(--cap-add=SYS_PTRACE), C(--volume=/var/run/docker.sock:/s) allows that one socket however written).
    type: list
    elements: str
    default: []
  allowed_bind_roots:
    description: Host directories the instances and companions may bind mount from, besides O(data_root)
      (and the Hub cache's directory); a root that is or holds what hands over the host (C(/), C(/etc),
      C(/var/lib/docker), Docker's socket) is refused.
    type: list
    elements: path
    default: []
  app_args:
    description: Extra arguments for the Isaac Sim launch script, one per item.
    type: list
    elements: str
    default: []
  companions:
    description:
      - Containers that belong to each instance (a viewer, a ROS 2 bridge, a recorder), each a unit of its own
        started once its instance is ready and stopped and restarted with it. Each item has C(name) and
        C(image), and may have C(command), C(entrypoint), C(env), C(ports) (name to a base port, placed
        per instance like the instance's own, or the name of a port the release reserves for companions such as
        C(web_viewer)), C(volumes), C(healthcheck), C(gpu), C(user), C(instances), C(ready_timeout),
        C(stop_timeout) and C(docker_args). See the isaac_sim role's README.
    type: list
    elements: raw
    default: []
  profile:
    description:
      - How the instances run. C(streaming) - the release's default stream (WebRTC). C(headless) - no stream,
        no port opened, no viewer (batch work, synthetic data). C(native) - 2023.1 only, its native livestream
        instead of the WebRTC client.
    type: str
    default: streaming
  instance_profiles:
    description: Instance number to profile, for the instances that run otherwise than O(profile).
    type: dict
    default: {}
  status_server:
    description:
      - The host's read-only status endpoint - C(enabled), C(port), C(address) (empty - O(public_address)) and
        C(allow) (the networks that may read it), C(logs_allow) (those that may read the instances' journals)
        and C(origins). Its port is checked against the instances' blocks and the host's listening sockets.
    type: dict
    default: {enabled: false}
  agent:
    description:
      - The host's action agent, the front door's way to act on instances (mutual TLS) - C(enabled), C(port),
        C(allow) (the networks the front door reaches it from; the firewall lets only these reach its port) and
        C(soak) (seconds a restarted instance soaks). Its port is checked as the status endpoint's.
    type: dict
    default: {enabled: false}
  hub_cache:
    description:
      - NVIDIA's Hub Workstation Cache, one per host for its 6.x instances - C(enabled), C(image), C(dir) (empty -
        C(DATA_ROOT/hub-cache)). Its port (14090) is checked against the instances' blocks and the host's sockets.
    type: dict
    default: {enabled: false}
  firewall:
    description:
      - Let the instances', companions' and host services' ports answer only O(allowed_networks) (nftables, see
        the isaac_sim role's README). V(false) opens them to every network that routes to the host, with a warning.
    type: bool
    default: true
  allowed_networks:
    description: The networks (CIDR, or single addresses) that may reach the ports; required with O(firewall).
    type: list
    elements: str
    default: []
  allowed_networks_by_port:
    description: Port kind (C(signal), C(stream), C(web_viewer), a companion's port name, C(status), C(hub_cache))
      to the networks that may reach ports of that kind, instead of O(allowed_networks).
    type: dict
    default: {}
  firewall_site_policy:
    description:
      - What a site chain that drops by default (a site's nftables table, firewalld, iptables' INPUT with policy
        DROP) gets - V(add) the collection's accepts in its own terms (rules of ours at the top of a site's nftables
        chain, a firewalld policy of ours), V(refuse) nothing - the plan stops before any change, naming the chain
        and giving the exact rules to add, until they are there. iptables' own tables are never written.
    type: str
    choices: [add, refuse]
    default: add
  web_viewer_image:
    description:
      - NVIDIA's web viewer image (built once by P(isaacsim.fleet.web_viewer_image#role)); for 6.x each instance
        gets it as its companion C(viewer) on the block's C(web_viewer) port. Empty - no viewer, and no web viewer
        URL is reported.
    type: str
    default: ""
  network_mode:
    description:
      - C(host) - the instances share the host's network, each on its own port block. C(macvlan) - each instance
        gets an address of its own on the host's LAN (a Docker macvlan network on O(macvlan_parent)) and keeps the
        release's default ports, so clients fixed to one port (NVIDIA's WebRTC Streaming Client, 49100) reach
        every instance; its companions share its address.
    type: str
    default: host
  macvlan_parent:
    description: The interface on the instances' LAN; empty - the interface of the host's IPv4 default route.
    type: str
    default: ""
  macvlan_subnet:
    description: The LAN's IPv4 network; empty - the network of O(macvlan_parent)'s first address.
    type: str
    default: ""
  macvlan_gateway:
    description: The LAN's router; empty - the gateway of the host's default route (when it is on the parent).
    type: str
    default: ""
  address_pool:
    description:
      - Addresses for the instances in O(network_mode=macvlan) - single addresses, C(FIRST-LAST) ranges or CIDR
        blocks, taken in order, instance 0 first. Addresses of the host, the gateway, or of another container
        on the network are skipped; too few usable ones is an error.
    type: raw
    default: []
  instance_addresses:
    description: Instance number to address, for instances whose address is fixed (taken before the pool).
    type: dict
    default: {}
  ready_timeout:
    description: Seconds an instance may take to print its ready line.
    type: raw
    default: 300
  stop_timeout:
    description: Seconds between SIGTERM and SIGKILL when an instance stops.
    type: raw
    default: 60
  restart_sec:
    description: Seconds systemd waits before restarting a failed instance.
    type: raw
    default: 10
  start_limit_burst:
    description: Failed starts after which systemd stops restarting an instance.
    type: raw
    default: 5
  health_interval:
    description: Seconds between two health checks of an instance.
    type: raw
    default: 30
  health_retries:
    description: Failed health checks in a row before an instance counts as unhealthy.
    type: raw
    default: 3
  unhealthy_restart:
    description: Seconds an instance may stay unhealthy before its host restarts it; 0 never restarts it.
    type: raw
    default: 300
  image_pull:
    description: The role's C(isaac_sim_image_pull); an NGC image that will be pulled needs a registry key.
    type: str
    default: missing
  image_pin:
    description: Whether the deploy pins the image's tag to one digest for the fleet (a mirror needs it).
    type: bool
    default: true
  registry_mirror:
    description: A pull-through mirror (HOST:PORT) the image is pulled through; the host then needs no registry key.
    type: str
    default: ""
  registry_mirror_upstream:
    description: The registry the mirror proxies.
    type: str
    default: ""
  registry_login:
    description: Whether a registry password (the NGC API key) is given; the key itself is not passed here.
    type: bool
    default: false
  check_host_ports:
    description: Fail when a planned port is held by a process that is not one of our instances.
    type: bool
    default: true
  systemd_dir:
    description: Where the unit files live.
    type: path
    default: /etc/systemd/system
  host_services:
    description:
      - Host services to read for the deploy, each unit's name to its C(files) and C(directories) (paths), returned in
        C(host.host_services) with their unit's state and each file's digest, mode and owner. Where one is as
        the deploy wants it, the deploy leaves out the call of M(isaacsim.fleet.isaac_sim_host_service).
    type: dict
    default: {}
  gather_facts:
    description:
      - Return the facts M(ansible.builtin.setup) returns with C(gather_subset=[min]) (same collectors), as
        C(ansible_facts), gathered in this call - for a play that needs no other call of
        M(ansible.builtin.setup) (C(gather_facts=false)).
    type: bool
    default: false
  lock:
    description:
      - Take the host's lock (as M(isaacsim.fleet.isaac_sim_lock) does) before planning, in the same call.
        Without it no lock is taken. When another run holds it, nothing is planned and the action plugin
        waits up to O(lock.wait) seconds for it.
    type: dict
    suboptions:
      holder:
        description: This run (M(isaacsim.fleet.isaac_sim_lock)'s O(isaacsim.fleet.isaac_sim_lock#module:holder)).
        type: dict
      stale_after:
        description: As M(isaacsim.fleet.isaac_sim_lock)'s O(isaacsim.fleet.isaac_sim_lock#module:stale_after).
        type: int
        default: 3600
      break_lock:
        description: As M(isaacsim.fleet.isaac_sim_lock)'s O(isaacsim.fleet.isaac_sim_lock#module:break_lock).
        type: bool
        default: false
      dead:
        description: As M(isaacsim.fleet.isaac_sim_lock)'s O(isaacsim.fleet.isaac_sim_lock#module:dead).
        type: str
        default: ""
      wait:
        description: As M(isaacsim.fleet.isaac_sim_lock)'s O(isaacsim.fleet.isaac_sim_lock#module:wait).
        type: int
        default: 0
"""

EXAMPLES = r"""
- name: Plan four 5.x instances on this host
  isaacsim.fleet.isaac_sim_plan:
    release: "5.x"
    image: nvcr.io/nvidia/isaac-sim:5.1.0
    instance_count: 4
    accept_eula: true
  register: plan
"""

RETURN = r"""
plan:
  description: The plan; C(instances) has one entry per instance.
  returned: success
  type: dict
  sample:
    release: "5.x"
    image: nvcr.io/nvidia/isaac-sim:5.1.0
    ids: [0, 1]
    instances:
      - id: 0
        name: isaac-sim-0
        ports: {signal: 49100, stream: 47998, http: 8011}
        gpu: 0
ansible_facts:
  description: Where O(gather_facts) is true and a plan was made, the facts of C(gather_subset=[min]).
  returned: when gather_facts is true
  type: dict
lock:
  description: Where O(lock) was given, what M(isaacsim.fleet.isaac_sim_lock) returns (acquired, holder, note).
  returned: when lock is given
  type: dict
stale_ids:
  description: Instances set up on this host earlier that the plan no longer has.
  returned: success
  type: list
  elements: int
  sample: [2, 3]
host:
  description: What was found on the host - memory, GPUs, ports held, whether the image is there (and its id),
    whether the metrics timer is installed, how many instances serve now and which (C(active_ids), null when
    systemd did not say), whether a killed deploy left a warm run behind (C(warm_leftovers)), and from both
    whether any instance could start on empty caches (C(cold_start_possible)), and the host services asked
    about (C(host_services)).
  returned: success
  type: dict
  sample: {memory_bytes: 68719476736, gpu_count: 2, gpus: [], ports_held: [], image_present: true,
           image_id: "sha256:9c15...", metrics_timer: false, serving: 4, active_ids: [0, 1, 2, 3],
           warm_leftovers: false, cold_start_possible: false}
"""

import time

from ansible.module_utils.basic import AnsibleModule
from ansible_collections.isaacsim.fleet.plugins.module_utils.instance import host_facts, runlock

ARGUMENT_SPEC = dict(
    release=dict(type="str", required=True),
    image=dict(type="str", default=""),
    instance_count=dict(type="int", required=True),
    max_instances=dict(type="int", default=8),
    scale_to_zero=dict(type="bool", default=False),
    port_bases=dict(type="dict", default={}),
    port_stride=dict(type="int", default=1),
    gpu_enabled=dict(type="bool", default=True),
    gpu_map=dict(type="dict", default={}),
    gpu_exclusive=dict(type="bool", default=False),
    gpu_memory=dict(type="str", default=""),
    instance_gpu_memory=dict(type="dict", default={}),
    gpu_consumer_encode_sessions=dict(type="int", default=8),
    memory_limit=dict(type="str", default="32g"),
    shm_size=dict(type="str", default="2g"),
    data_root=dict(type="path", default="/var/lib/isaac-sim"),
    public_address=dict(type="str"),
    ready_pattern=dict(type="str"),
    accept_eula=dict(type="bool", default=False),
    privacy_consent=dict(type="bool", default=False),
    env=dict(type="dict", default={}),
    secret_env_names=dict(type="list", elements="str", default=[], no_log=False),
    docker_args=dict(type="list", elements="str", default=[]),
    allowed_docker_args=dict(type="list", elements="str", default=[]),
    allowed_bind_roots=dict(type="list", elements="path", default=[]),
    app_args=dict(type="list", elements="str", default=[]),
    ready_timeout=dict(type="raw", default=300),
    stop_timeout=dict(type="raw", default=60),
    restart_sec=dict(type="raw", default=10),
    start_limit_burst=dict(type="raw", default=5),
    health_interval=dict(type="raw", default=30),
    health_retries=dict(type="raw", default=3),
    unhealthy_restart=dict(type="raw", default=300),
    image_pull=dict(type="str", default="missing"),
    image_pin=dict(type="bool", default=True),
    registry_mirror=dict(type="str", default=""),
    registry_mirror_upstream=dict(type="str", default=""),
    registry_login=dict(type="bool", default=False),
    check_host_ports=dict(type="bool", default=True),
    companions=dict(type="list", elements="raw", default=[]),
    profile=dict(type="str", default="streaming"),
    instance_profiles=dict(type="dict", default={}),
    status_server=dict(type="dict", default={"enabled": False}),
    agent=dict(type="dict", default={"enabled": False}),
    hub_cache=dict(type="dict", default={"enabled": False}),
    firewall=dict(type="bool", default=True),
    allowed_networks=dict(type="list", elements="str", default=[]),
    allowed_networks_by_port=dict(type="dict", default={}),
    firewall_site_policy=dict(type="str", choices=["add", "refuse"], default="add"),
    web_viewer_image=dict(type="str", default=""),
    network_mode=dict(type="str", default="host"),
    macvlan_parent=dict(type="str", default=""),
    macvlan_subnet=dict(type="str", default=""),
    macvlan_gateway=dict(type="str", default=""),
    address_pool=dict(type="raw", default=[]),
    instance_addresses=dict(type="dict", default={}),
    config_dir=dict(type="path", default="/etc/isaac-sim"),
    systemd_dir=dict(type="path", default="/etc/systemd/system"),
    host_services=dict(type="dict", default={}),
    gather_facts=dict(type="bool", default=False),
    lock=dict(type="dict", options=runlock.request_options(holder_required=False)),
)


def main():
    module = AnsibleModule(argument_spec=ARGUMENT_SPEC, supports_check_mode=True)
    try:
        out = host_facts.plan_held(host_facts.bind(module), module.params, time.time())
    except host_facts.PlanRefusedError as exc:
        module.fail_json(msg=exc.msg, **exc.fields)
    for warning in out.pop("warnings", []):
        module.warn(warning)
    module.exit_json(changed=False, **out)


if __name__ == "__main__":
    main()
