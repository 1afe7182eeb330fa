# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""The registry mirror's settings checked, and its files (module_utils/host/registry_mirror.py)."""

from __future__ import annotations

from ansible.errors import AnsibleFilterError

DOCUMENTATION = r"""
name: isaac_sim_registry_mirror
short_description: Check a registry mirror's settings, or render its files (isaacsim.fleet.registry_mirror)
version_added: "0.3.0"
description:
  - C(errors) lists what is wrong with the settings, each naming the variable and the fix.
  - C(files) renders the mirror's unit, configuration, certificate, key and firewall rules for
    M(isaacsim.fleet.isaac_sim_host_service).
positional: _input, what
options:
  _input:
    description:
      - The mirror's settings - C(upstream), C(username), C(password), C(address), C(port), C(allowed_networks);
        for C(files) also C(cert) and C(key) (their PEM text).
    type: dict
    required: true
  what:
    description: What to return.
    type: str
    choices: [errors, files]
    required: true
"""

EXAMPLES = r"""
errors: "{{ settings | isaacsim.fleet.isaac_sim_registry_mirror('errors') }}"
"""

RETURN = r"""
_value:
  description: A list of errors (C(errors)), or each file's path to its C(content) and C(mode) (C(files)).
  type: raw
"""


def isaac_sim_registry_mirror(settings: dict, what: str):
    # on use, not at load: Ansible loads every filter file here to find one (docs/docsite/rst/contributing.rst, Layout)
    from ansible_collections.isaacsim.fleet.plugins.module_utils.host import registry_mirror
    from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib import layout

    if what == "errors":
        return registry_mirror.check(settings or {})
    if what == "files":
        errors = registry_mirror.check(settings or {})
        if errors:
            raise AnsibleFilterError("; ".join(errors))
        return registry_mirror.files(settings, layout.MANAGED, settings.get("cert", ""), settings.get("key", ""))
    raise AnsibleFilterError(f"isaac_sim_registry_mirror: {what!r} is not errors or files")


class FilterModule:
    def filters(self):
        return {"isaac_sim_registry_mirror": isaac_sim_registry_mirror}
