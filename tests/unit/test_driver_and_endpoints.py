import pytest
from ansible_collections.isaacsim.fleet.plugins.filter.systemd_env_quote import systemd_env_quote
from ansible_collections.isaacsim.fleet.plugins.module_utils import driver, endpoints


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


def test_endpoints_2023_1():
    eps = endpoints.endpoints("2023.1", {"http": 8212, "webrtc": 8012, "native": 8900}, "10.0.0.5")
    assert eps["webrtc_client"] == "http://10.0.0.5:8212/streaming/webrtc-client?server=10.0.0.5"


def test_endpoints_6x():
    eps = endpoints.endpoints("6.x", {"signal": 49101, "stream": 47999, "web_viewer": 8211}, "gpu-3")
    assert eps == {"signal": "gpu-3:49101", "stream": "gpu-3:47999/udp", "web_viewer": "http://gpu-3:8211/"}


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
