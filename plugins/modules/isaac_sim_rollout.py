#!/usr/bin/python
# Copyright: isaacsim.fleet contributors
# Apache-2.0

DOCUMENTATION = r"""
---
module: isaac_sim_rollout
short_description: Restart or upgrade a host's Isaac Sim instances one at a time, with health gates and revert
version_added: "0.2.0"
description:
  - With O(record_only), keeps each instance's env file (its image and configuration) under O(record_dir),
    so a later rollout can revert to it.
  - Otherwise, for each instance in O(instances), in order, one at a time - writes its new env file (when
    O(instances[].env) is given and differs), restarts it (C(systemctl restart) returns once the readiness
    gate saw the ready line, or fails at the unit's deadline), then soaks it - it must stay active and ready,
    with systemd's restart count unchanged, for O(soak_seconds).
  - When an instance fails, it is reverted to its recorded env file (pinned to its recorded image id when
    the tag has moved since) and restarted until ready; the instances after it are left untouched and the
    module fails with the instance and the reason. The other N-1 instances of the host keep serving all along.
  - An instance whose new env file equals the current one is left alone, so a rollout that stopped can be
    run again and goes on where it stopped.
author: isaacsim.fleet contributors
attributes:
  check_mode:
    support: full
    description: Reports what would be applied or restarted; changes nothing.
  diff_mode:
    support: none
    description: Env files may hold secrets; no diff is shown.
options:
  instances:
    description: The instances to roll, in order.
    type: list
    elements: dict
    default: []
    suboptions:
      id:
        description: Instance number.
        type: int
        required: true
      env:
        description: The instance's new env file; omitted means restart it as it is.
        type: str
  record_only:
    description: Only record the env files of O(instances) for a later revert.
    type: bool
    default: false
  soak_seconds:
    description: How long a restarted instance must stay ready with its restart count unchanged.
    type: float
    default: 30
  env_mode:
    description: File mode of a newly written env file (V(0600) when it holds secrets).
    type: str
    default: "0644"
  config_dir:
    description: Where the env files are.
    type: path
    default: /etc/isaac-sim
  run_dir:
    description: Where the readiness gate writes its markers.
    type: path
    default: /run/isaac-sim
  record_dir:
    description: Where the recorded env files are kept (mode 0700).
    type: path
    default: /var/lib/isaac-sim/rollout
notes:
  - The module runs for as long as the instances take; one call per host keeps Ansible's per-task cost out
    of the rollout's time.
seealso:
  - module: isaacsim.fleet.isaac_sim_info
"""

EXAMPLES = r"""
- name: Record what runs now
  isaacsim.fleet.isaac_sim_rollout:
    instances: [{id: 0}, {id: 1}]
    record_only: true

- name: Restart instances 0 and 1 one at a time, each soaked 30 s
  isaacsim.fleet.isaac_sim_rollout:
    instances: [{id: 0}, {id: 1}]
    soak_seconds: 30
"""

RETURN = r"""
recorded:
  description: With O(record_only), the image reference and id recorded per instance.
  returned: when record_only
  type: dict
  sample: {"0": {"image": "nvcr.io/nvidia/isaac-sim:5.1.0", "image_id": "sha256:9c15..."}}
done:
  description: Instances rolled, in order, each with C(action) (apply, restart, unchanged) and its timings.
  returned: always
  type: list
  elements: dict
  sample: [{"id": 0, "action": "apply", "restart_s": 6.2, "soak_s": 30.0}]
failed_instance:
  description: The instance that failed, why, and whether the revert brought it back.
  returned: always
  type: dict
  sample: {"id": 0, "reason": "isaac-sim-0 was not ready within 20 s", "reverted": true,
           "reverted_to": "nvcr.io/nvidia/isaac-sim:5.0.0", "revert_error": null}
untouched:
  description: Instances not reached because of the failure.
  returned: always
  type: list
  elements: int
"""

import os
import time

from ansible.module_utils.basic import AnsibleModule
from ansible_collections.isaacsim.fleet.plugins.module_utils import rollout


def main():
    module = AnsibleModule(
        argument_spec=dict(
            instances=dict(
                type="list",
                elements="dict",
                default=[],
                options=dict(id=dict(type="int", required=True), env=dict(type="str", no_log=True)),
            ),
            record_only=dict(type="bool", default=False),
            soak_seconds=dict(type="float", default=30),
            env_mode=dict(type="str", default="0644"),
            config_dir=dict(type="path", default="/etc/isaac-sim"),
            run_dir=dict(type="path", default="/run/isaac-sim"),
            record_dir=dict(type="path", default="/var/lib/isaac-sim/rollout"),
        ),
        supports_check_mode=True,
    )
    p = module.params

    def run(argv):
        return module.run_command([module.get_bin_path(argv[0], required=True)] + argv[1:])

    def read(path):
        try:
            with open(path) as fh:
                return fh.read()
        except OSError:
            return None

    def write(path, text, mode):
        directory = os.path.dirname(path)
        tmp = os.path.join(directory, f".{os.path.basename(path)}.rollout")
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, mode)
        with os.fdopen(fd, "w") as fh:
            fh.write(text)
        os.chmod(tmp, mode)
        os.replace(tmp, path)

    def mode(path):
        try:
            return os.stat(path).st_mode & 0o777
        except OSError:
            return None

    host = rollout.Host(run, read, write, mode, os.path.exists, time.sleep, time.monotonic, time.time)
    paths = rollout.Paths(p["config_dir"], p["run_dir"], p["record_dir"])
    ids = [inst["id"] for inst in p["instances"]]

    if p["record_only"]:
        if module.check_mode:
            module.exit_json(changed=False, recorded={}, done=[], failed_instance=None, untouched=[])
        os.makedirs(p["record_dir"], mode=0o700, exist_ok=True)
        os.chmod(p["record_dir"], 0o700)
        recorded = rollout.record(host, paths, ids)
        missing = sorted(set(ids) - set(recorded))
        if missing:
            module.fail_json(
                msg=f"instances {missing} have no env file in {p['config_dir']}: not deployed here. "
                "Fix: deploy first (playbooks/deploy.yml), or select instances that exist.",
                recorded=recorded,
            )
        module.exit_json(changed=False, recorded=recorded, done=[], failed_instance=None, untouched=[])

    result = rollout.roll(
        host,
        paths,
        [{"id": inst["id"], "env": inst.get("env")} for inst in p["instances"]],
        p["soak_seconds"],
        env_mode=int(p["env_mode"], 8),
        check=module.check_mode,
    )
    out = dict(
        changed=result["changed"], done=result["done"], failed_instance=result["failed"], untouched=result["untouched"]
    )
    failed = result["failed"]
    if failed:
        if failed.get("reverted") is None:
            back = "nothing was changed on it"
        elif failed.get("reverted"):
            back = f"reverted to {failed.get('reverted_to')} and ready again"
        else:
            back = f"the revert failed too: {failed.get('revert_error')}"
        module.fail_json(msg=f"isaac-sim-{failed['id']}: {failed['reason']}; {back}", **out)
    module.exit_json(**out)


if __name__ == "__main__":
    main()
