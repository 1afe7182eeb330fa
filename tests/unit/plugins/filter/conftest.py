"""What the filter tests share: the expressions the roles and playbooks write, read from their YAML,
rendered by Ansible's own templating with the collection's filters, as a play would render them."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import yaml
from ansible.parsing.dataloader import DataLoader
from ansible.template import Templar, trust_as_template
from ansible.utils.collection_loader import AnsibleCollectionConfig

ROOT = Path(__file__).resolve().parents[4]
# where tests/conftest.py links this checkout as ansible_collections/isaacsim/fleet (plain pytest)
COLLECTIONS = ROOT / ".ansible" / "collections"
_PARTS = ("tasks", "pre_tasks", "post_tasks", "handlers", "block", "rescue", "always")


def load(path: str):
    """A YAML file of the collection (roles/..., playbooks/...), as Ansible reads it."""
    return yaml.safe_load((ROOT / path).read_text())


def find_task(path: str, name: str, within: str | None = None) -> dict:
    """The one task (or block) called `name` in a task file or playbook, at any depth; inside the
    block called `within` when the name is not unique in the file."""
    found = []

    def walk(items):
        for item in items or ():
            if item.get("name") == name:
                found.append(item)
            for part in _PARTS:
                walk(item.get(part))

    walk([find_task(path, within)] if within else load(path))
    assert len(found) == 1, f"{len(found)} tasks named {name!r} in {path}"
    return found[0]


def trusted(value):
    """Strings as Ansible trusts those of the collection's own files: templates to render."""
    if isinstance(value, str):
        return trust_as_template(value)
    if isinstance(value, dict):
        return {k: trusted(v) for k, v in value.items()}
    if isinstance(value, list):
        return [trusted(v) for v in value]
    return value


def _namespace_packages() -> dict:
    """The collection's packages that plain pytest imported as namespace packages (no __file__)."""
    return {
        name: module
        for name, module in sys.modules.items()
        if name.split(".")[0] == "ansible_collections" and getattr(module, "__file__", None) is None
    }


@pytest.fixture(scope="module")
def render():
    """render(template, variables): Ansible's templating of a role's or playbook's expression, with
    `variables` as the play gives them (strings of the collection's YAML among them are templates)."""
    restore = None
    if AnsibleCollectionConfig.collection_finder is None:
        # plain pytest (ansible-test units installs Ansible's collection loader itself): the loader
        # places a collection by its package's file, which a namespace package lacks; they are put
        # back afterwards, so the other tests keep the modules they imported
        # pylint: disable-next=import-outside-toplevel
        from ansible.utils.collection_loader._collection_finder import _AnsibleCollectionFinder

        restore = _namespace_packages()
        for name in restore:
            del sys.modules[name]
        _AnsibleCollectionFinder(paths=[str(COLLECTIONS)])._install()  # pylint: disable=protected-access

    def go(template: str, variables: dict):
        return Templar(loader=DataLoader(), variables=variables).template(trust_as_template(template))

    yield go
    if restore is not None:
        AnsibleCollectionConfig.collection_finder._remove()  # pylint: disable=protected-access
        sys.modules.update(restore)
