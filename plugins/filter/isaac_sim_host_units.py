# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""The units of the collection's host services, written the one way every unit is (module_utils/common/units.py)."""

from __future__ import annotations

from ansible.errors import AnsibleFilterError

DOCUMENTATION = r"""
name: isaac_sim_host_units
short_description: The systemd units of a host service of isaacsim.fleet (status endpoint, metrics, action agent)
version_added: "0.3.0"
description:
  - Renders the unit files of one of the host services that are not instances, from the collection's layout,
    for M(isaacsim.fleet.isaac_sim_host_service) to install.
positional: _input, service
options:
  _input:
    description:
      - The service's settings. C(status) - C(name), C(address), C(port), C(allow), C(logs_allow), C(origins),
        C(gpu_source).
        C(metrics) - C(textfile_dir), C(interval), C(gpu_source).
        C(agent) - C(name), C(port), C(allow), C(soak), C(data_root).
    type: dict
    required: true
  service:
    description: Which host service.
    type: str
    choices: [status, metrics, agent]
    required: true
"""

EXAMPLES = r"""
units: "{{ {'textfile_dir': '/var/lib/prometheus/node-exporter', 'interval': '30s', 'gpu_source': 'auto'}
           | isaacsim.fleet.isaac_sim_host_units('metrics') }}"
"""

RETURN = r"""
_value:
  description: The unit's file name (under /etc/systemd/system) to its content.
  type: dict
"""

_NEEDS = {
    "status": ("name", "address", "port", "gpu_source"),
    "metrics": ("textfile_dir", "interval", "gpu_source"),
    "agent": ("name", "port", "allow", "soak", "data_root"),
}


def isaac_sim_host_units(settings: dict, service: str) -> dict:
    # on use, not at load: Ansible loads every filter file here to find one (docs/docsite/rst/contributing.rst, Layout)
    from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib import layout
    from ansible_collections.isaacsim.fleet.plugins.module_utils.instance import unit_files

    if service not in _NEEDS:
        raise AnsibleFilterError(f"isaac_sim_host_units: no host service {service!r}; one of {sorted(_NEEDS)}")
    missing = [key for key in _NEEDS[service] if key not in (settings or {})]
    if missing:
        raise AnsibleFilterError(f"isaac_sim_host_units({service!r}): settings lack {', '.join(missing)}")
    if service == "status":
        return {layout.STATUS_UNIT: unit_files.render_status_unit(settings)}
    if service == "agent":
        return {layout.AGENT_UNIT: unit_files.render_agent_unit(settings)}
    return unit_files.render_metrics_units(settings)


class FilterModule:
    def filters(self):
        return {"isaac_sim_host_units": isaac_sim_host_units}
