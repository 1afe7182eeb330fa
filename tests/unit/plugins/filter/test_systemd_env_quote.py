"""The systemd_env_quote filter."""

from __future__ import annotations

import pytest
from ansible_collections.isaacsim.fleet.plugins.filter.systemd_env_quote import FilterModule, systemd_env_quote


@pytest.mark.parametrize(
    "value, quoted",
    [
        ("plain", '"plain"'),
        ('a"b', '"a\\"b"'),
        ("back\\slash", '"back\\\\slash"'),
        ("App is loaded\\.", '"App is loaded\\\\."'),
        ("pa$s`x", '"pa\\$s\\`x"'),
    ],
)
def test_systemd_env_quote(value, quoted):
    assert systemd_env_quote(value) == quoted


def test_filter_name():
    assert FilterModule().filters()["systemd_env_quote"] is systemd_env_quote
