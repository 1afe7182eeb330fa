"""No YAML of the collection starts, restarts, stops or removes an instance by itself:
every such change goes through the isaac_sim_lifecycle module (plugins/module_utils/instance/lifecycle.py)."""

from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[2]
SYSTEMD = {"ansible.builtin.systemd_service", "ansible.builtin.systemd", "ansible.builtin.service"}
COMMANDS = {"ansible.builtin.command", "ansible.builtin.shell", "ansible.builtin.raw"}
FILES = {"ansible.builtin.file"}


def tasks(node):
    """Every task in a playbook, task file or handler file, blocks included."""
    if isinstance(node, list):
        for item in node:
            yield from tasks(item)
    elif isinstance(node, dict):
        for key in ("tasks", "pre_tasks", "post_tasks", "handlers", "block", "rescue", "always"):
            if key in node:
                yield from tasks(node[key])
        if not any(k in node for k in ("tasks", "block", "hosts", "import_playbook")):
            yield node


def offences(text: str) -> list:
    found = []
    for task in tasks(yaml.safe_load(text) or []):
        for module, args in task.items():
            body = str(args)
            if module in SYSTEMD and "isaac-sim@" in body:
                found.append(f"{task.get('name')}: {module} on an instance unit")
            if module in COMMANDS and ("isaac-sim@" in body or "isaac-sim-" in body):
                found.append(f"{task.get('name')}: a command on an instance")
            if module in FILES and "instance-" in body and "absent" in body:
                found.append(f"{task.get('name')}: removes an instance's files")
    return found


def test_the_check_finds_what_it_looks_for():
    bad = """
- name: Restart by hand
  ansible.builtin.systemd_service: {name: "isaac-sim@{{ item }}.service", state: restarted}
- name: In a block
  block:
    - name: Reset
      ansible.builtin.command: systemctl reset-failed isaac-sim@1.service
- name: Forget
  ansible.builtin.file: {path: "/etc/isaac-sim/instance-1.env", state: absent}
"""
    assert len(offences(bad)) == 3


def test_no_yaml_changes_instances_outside_the_lifecycle_module():
    files = [p for d in ("roles", "playbooks") for p in (ROOT / d).rglob("*.yml") if "meta" not in p.parts]
    assert len(files) > 20
    found = {str(p.relative_to(ROOT)): offences(p.read_text()) for p in files}
    assert {p: o for p, o in found.items() if o} == {}
