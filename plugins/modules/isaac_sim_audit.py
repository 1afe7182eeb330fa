#!/usr/bin/python
# Copyright: isaacsim.fleet contributors
# SPDX-License-Identifier: Apache-2.0 (the collection's license, see galaxy.yml)
# Apache-2.0 is compatible with the GNU General Public License v3.0 that ansible-core is
# released under; ansible-test's validate-modules looks for that license's name here.

DOCUMENTATION = r"""
---
module: isaac_sim_audit
short_description: Audit an Isaac Sim host, or probe the fleet's ports from outside and inside the allowed networks
version_added: "0.3.0"
description:
  - O(action=host) reads the host - every container's confinement (privileged, added capabilities, the host's
    namespaces, a confinement turned off, host devices, Docker's socket mounted), the files under C(/etc), C(/root)
    and C(/var/lib) and the journal that hold O(key), the modes of the collection's env files (one that holds a
    variable of O(secret_env_names) readable by root only), units and scripts, and the firewall's tables - and lists
    the ports the host opens with the networks allowed for each.
  - O(action=probe) runs on a probe host (the controller, or a host of the fleet) and knocks on each port of
    O(reports) - a TCP connect, a UDP datagram that waits for an answer. A port must not answer a probe host
    outside the networks allowed for it, and a TCP port must answer one inside them.
  - O(action=report) makes the fleet's report of the hosts' O(reports) and every probe host's O(probed) rows.
  - Never changes anything; the key is never returned.
author: isaacsim.fleet contributors (@isaacsim-fleet)
extends_documentation_fragment:
  - isaacsim.fleet.attributes
  - isaacsim.fleet.attributes.platform
  - isaacsim.fleet.secret_env
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
  action:
    description: What to do.
    type: str
    choices: [host, probe, report]
    default: host
  key:
    description: The registry key to look for (C(isaac_sim_registry_password)); empty - not looked for.
    type: str
    default: ""
  reports:
    description: For O(action=probe) and O(action=report) - host name to the result of O(action=host) on it (empty -
      it did not answer).
    type: dict
    default: {}
  probe_host:
    description: For O(action=probe), the inventory name of the host the probe runs on, where it is one of
      O(reports)' hosts - its own ports are not knocked on (from itself every one answers) and the table says so.
    type: str
    default: ""
  probed:
    description: For O(action=report), the C(report.probed) rows of every O(action=probe) call.
    type: list
    elements: dict
    default: []
  probe_hosts:
    description: For O(action=report), the probe hosts those calls ran on (C(localhost) - the controller).
    type: list
    elements: str
    default: []
  timeout:
    description: Seconds to wait for each port's answer.
    type: float
    default: 3.0
"""

EXAMPLES = r"""
- name: Audit the host
  isaacsim.fleet.isaac_sim_audit:
    key: "{{ isaac_sim_registry_password }}"
  register: audit
"""

RETURN = r"""
findings:
  description: For O(action=host), each C(check), C(what) and C(why).
  returned: always
  type: list
  elements: dict
ports:
  description: For O(action=host), the ports the host opens, each with the networks allowed to reach it.
  returned: always
  type: list
  elements: dict
address:
  description: For O(action=host), the host's address on its default route.
  returned: always
  type: str
report:
  description: For O(action=probe) (its own knocks) and O(action=report) (every probe host's), the fleet's
    audit - C(hosts) (each C(host), C(reachable), C(findings)), C(findings) (their number), C(clean), C(probed) (each
    port with C(source), C(prober), C(inside), C(answer)) and C(table).
  returned: always
  type: dict
"""

from ansible.module_utils.basic import AnsibleModule
from ansible_collections.isaacsim.fleet.plugins.module_utils.host import audit


def main():
    module = AnsibleModule(
        argument_spec=dict(
            action=dict(type="str", choices=["host", "probe", "report"], default="host"),
            key=dict(type="str", default="", no_log=True),
            secret_env_names=dict(type="list", elements="str", default=[], no_log=False),
            reports=dict(type="dict", default={}),
            probe_host=dict(type="str", default=""),
            probed=dict(type="list", elements="dict", default=[]),
            probe_hosts=dict(type="list", elements="str", default=[]),
            timeout=dict(type="float", default=3.0),
        ),
        supports_check_mode=True,
    )
    p = module.params
    if p["action"] == "probe":
        probed = audit.probe(audit.targets(p["reports"], p["probe_host"]), p["timeout"])
        report = audit.fleet(p["reports"], probed, [p["probe_host"]])
        module.exit_json(changed=False, findings=[], ports=[], address="", report=report)
    if p["action"] == "report":
        report = audit.fleet(p["reports"], p["probed"], p["probe_hosts"])
        module.exit_json(changed=False, findings=[], ports=[], address="", report=report)
    report = audit.host_report(audit.bind(module), p["key"], p["secret_env_names"])
    module.exit_json(changed=False, report={}, **report)


if __name__ == "__main__":
    main()
