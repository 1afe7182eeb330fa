# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""The facts of ansible.builtin.setup with gather_subset [min], collected inside another module's call:
playbooks/deploy.yml takes them from its plan's call instead of a setup call of their own (one round trip
less per host). The same collectors, subset and namespace as setup (ansible/modules/setup.py)."""

from __future__ import annotations

# setup's own minimal subset, which gather_subset [min] collects
MINIMAL = frozenset(
    [
        "apparmor",
        "caps",
        "cmdline",
        "date_time",
        "distribution",
        "dns",
        "env",
        "fips",
        "local",
        "lsb",
        "pkg_mgr",
        "platform",
        "python",
        "selinux",
        "service_mgr",
        "ssh_pub_keys",
        "user",
    ]
)
# setup's default, where the local collector reads facts.d from
FACT_PATH = "/etc/ansible/facts.d"


def collect(module, timeout: int = 10) -> dict:
    """ansible_facts as setup with gather_subset [min] returns them, for `module` (an AnsibleModule)."""
    # on use: only a call that gathers pays for the collectors' import
    from ansible.module_utils.facts import ansible_collector, default_collectors
    from ansible.module_utils.facts.namespace import PrefixFactNamespace

    collector = ansible_collector.get_ansible_collector(
        all_collector_classes=default_collectors.collectors,
        namespace=PrefixFactNamespace(namespace_name="ansible", prefix="ansible_"),
        filter_spec=[],
        gather_subset=["min"],
        gather_timeout=timeout,
        minimal_gather_subset=MINIMAL,
    )
    # the local collector reads setup's option; this module has none of its own
    module.params.setdefault("fact_path", FACT_PATH)
    return collector.collect(module=module)
