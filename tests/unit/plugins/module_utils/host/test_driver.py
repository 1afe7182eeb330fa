"""The NVIDIA driver check (module_utils/host/driver.py)."""

from __future__ import annotations

import pytest
from ansible_collections.isaacsim.fleet.plugins.module_utils.host import driver


@pytest.mark.parametrize(
    "found, minimum, ok",
    [
        ("570.169", "570.169", True),
        ("570.172.08", "570.169", True),
        ("580.65.06", "570.169", True),
        ("570.133.20", "570.169", False),
        ("535.183.01", "570.169", False),
        ("garbage", "570.169", False),
    ],
)
def test_driver_at_least(found, minimum, ok):
    assert driver.at_least(found, minimum) is ok


def test_driver_check_messages():
    assert "No NVIDIA GPU" in driver.check([], "570.169", "6.x")
    old = driver.check([{"driver": "550.54.15"}], "570.169", "5.x")
    assert "550.54.15 is older than 570.169, the minimum for Isaac Sim 5.x" in old
    assert driver.check([{"driver": "570.172.08"}], "570.169", "5.x") is None
