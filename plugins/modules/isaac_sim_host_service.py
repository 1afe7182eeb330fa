#!/usr/bin/python
# Copyright: isaacsim.fleet contributors
# SPDX-License-Identifier: Apache-2.0 (the collection's license, see galaxy.yml)
# Apache-2.0 is compatible with the GNU General Public License v3.0 that ansible-core is
# released under; ansible-test's validate-modules looks for that license's name here.

DOCUMENTATION = r"""
---
module: isaac_sim_host_service
short_description: Bring one of the collection's host services (files and systemd unit) to a state in one call
version_added: "0.3.0"
description:
  - For the services of a host that are not Isaac Sim instances, such as the read-only status endpoint
    (C(isaac-sim-status.service)). Instances change only through M(isaacsim.fleet.isaac_sim_lifecycle).
  - O(state=started) writes the files whose content or mode differ (atomically), reloads systemd when a unit
    file changed, enables the unit, starts it, and restarts it when one of its files changed while it ran.
  - O(state=absent) stops and disables the unit, then removes its files and O(remove).
  - One call per service and run, whatever the number of files; supports check mode and diff.
author: isaacsim.fleet contributors (@isaacsim-fleet)
options:
  name:
    description: The systemd unit, e.g. C(isaac-sim-status.service).
    type: str
    required: true
  files:
    description:
      - Path to C(content) and C(mode) (octal string, default C(0644)) of each file of the service, the unit
        file among them.
    type: dict
    default: {}
  directories:
    description:
      - Directories the service needs before it starts - C(path), C(uid), C(gid), C(mode) (octal string). Created
        when missing and re-owned when owned otherwise; never emptied, and kept with O(state=absent).
    type: list
    elements: dict
    default: []
  remove:
    description: Further paths (files or directories) to remove with O(state=absent).
    type: list
    elements: path
    default: []
  state:
    description: Whether the service runs (C(started)) or is gone (C(absent)).
    type: str
    choices: [started, absent]
    default: started
"""

EXAMPLES = r"""
- name: Serve this host's status
  isaacsim.fleet.isaac_sim_host_service:
    name: isaac-sim-status.service
    files:
      /etc/systemd/system/isaac-sim-status.service:
        content: "{{ lookup('ansible.builtin.template', 'isaac-sim-status.service.j2') }}"
      /usr/local/libexec/isaac-sim/isaac-sim-status-server:
        content: "{{ lookup('ansible.builtin.file', 'isaac-sim-status-server') }}"
        mode: "0755"
"""

RETURN = r"""
changed_files:
  description: The files written or removed.
  returned: always
  type: list
  elements: str
actions:
  description: What was done, in order (directories, write, daemon-reload, enable, start, restart, stop, disable,
    remove).
  returned: always
  type: list
  elements: str
"""

import os

from ansible.module_utils.basic import AnsibleModule
from ansible_collections.isaacsim.fleet.plugins.module_utils.host import host_service


def main():
    module = AnsibleModule(
        argument_spec=dict(
            name=dict(type="str", required=True),
            files=dict(type="dict", default={}),
            directories=dict(type="list", elements="dict", default=[]),
            remove=dict(type="list", elements="path", default=[]),
            state=dict(type="str", choices=["started", "absent"], default="started"),
        ),
        supports_check_mode=True,
    )
    p = module.params
    files = {}
    for path in list(p["files"]) + p["remove"] + [d.get("path", "") for d in p["directories"]]:
        if not str(path).startswith("/"):
            module.fail_json(msg=f"{path!r} is not an absolute path. Fix: give every file and directory in full.")
    for path, spec in p["files"].items():
        spec = spec if isinstance(spec, dict) else {"content": spec}
        if "content" not in spec:
            module.fail_json(msg=f"files.{path}: no content. Fix: give content (and mode) for every file.")
        files[path] = {"content": str(spec["content"]), "mode": str(spec.get("mode", "0644"))}

    systemctl = module.get_bin_path("systemctl", required=True)
    rc, out, _err = module.run_command(
        [systemctl, "show", "-p", "ActiveState", "-p", "UnitFileState", "-p", "LoadState", p["name"]]
    )
    show = dict(line.split("=", 1) for line in out.splitlines() if "=" in line) if rc == 0 else {}

    if p["state"] == "absent":
        gone = [path for path in list(files) + p["remove"] if os.path.lexists(path)]
        verbs = host_service.actions("absent", show, [], gone)
        changed_files = gone
    else:
        changed_files = host_service.changed_files(files, host_service.read_file)
        fix = host_service.directories_to_fix(p["directories"])
        verbs = host_service.actions("started", show, changed_files, [], directories=bool(fix))

    diff = {
        "before": "".join(f"{path}\n" for path in changed_files if host_service.read_file(path) is not None),
        "after": "".join(f"{path}\n" for path in changed_files if p["state"] == "started"),
    }
    if not module.check_mode:
        for verb in verbs:
            if verb == "directories":
                for d in fix:
                    host_service.fix_directory(d)
            elif verb == "write":
                for path in changed_files:
                    host_service.write_file(path, files[path]["content"], files[path]["mode"])
            elif verb == "remove":
                for path in changed_files:
                    host_service.remove(path)
            else:
                argv = [systemctl, verb] + ([] if verb == "daemon-reload" else [p["name"]])
                rc, out, err = module.run_command(argv)
                if rc != 0:
                    module.fail_json(
                        msg=f"systemctl {verb} {p['name']} failed: {(err or out).strip()}. "
                        f"See: systemctl status {p['name']}; journalctl -u {p['name']}",
                        actions=verbs,
                        changed_files=changed_files,
                    )
    module.exit_json(changed=bool(verbs), actions=verbs, changed_files=changed_files, diff=diff)


if __name__ == "__main__":
    main()
