# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""Filters for files that systemd reads."""

from __future__ import annotations

DOCUMENTATION = r"""
name: systemd_env_quote
short_description: Quote a value for a systemd EnvironmentFile
version_added: "0.1.0"
description:
  - Wraps the value in double quotes and escapes backslashes, double quotes, dollar signs and
    backquotes (a newline stays inside the quotes), so systemd reads back exactly the value given.
positional: _input
options:
  _input:
    description: The value.
    type: str
    required: true
"""

EXAMPLES = r"""
line: "NGC_API_KEY={{ key | isaacsim.fleet.systemd_env_quote }}"
"""

RETURN = r"""
_value:
  description: The quoted value.
  type: str
"""


def systemd_env_quote(value):
    # on use, not at load: Ansible loads every filter file here to find one (docs/docsite/rst/contributing.rst, Layout)
    from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib.layout import quote

    return quote(value)


class FilterModule:
    def filters(self):
        return {"systemd_env_quote": systemd_env_quote}
