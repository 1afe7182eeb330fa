"""Where clients reach an instance, per release (module_utils/hostlib/endpoints.py)."""

from __future__ import annotations

from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib import endpoints


def test_endpoints_2023_1():
    eps = endpoints.endpoints("2023.1", {"http": 8212, "webrtc": 8012, "native": 8900}, "10.0.0.5")
    assert eps["webrtc_client"] == "http://10.0.0.5:8212/streaming/webrtc-client?server=10.0.0.5"
    assert eps["native"] == "10.0.0.5:8900"


def test_endpoints_5x_have_the_api_port():
    eps = endpoints.endpoints("5.x", {"signal": 49100, "stream": 47998, "http": 8011}, "10.0.0.5")
    assert eps == {"signal": "10.0.0.5:49100", "stream": "10.0.0.5:47998/udp", "api": "http://10.0.0.5:8011/"}


def test_endpoints_6x():
    block = {"signal": 49101, "stream": 47999, "web_viewer": 8211}
    eps = endpoints.endpoints("6.x", block, "gpu-3", served=[8211])
    assert eps == {"signal": "gpu-3:49101", "stream": "gpu-3:47999/udp", "web_viewer": "http://gpu-3:8211/"}
    # no viewer listens on the block's web-viewer port: no URL names it
    assert "web_viewer" not in endpoints.endpoints("6.x", block, "gpu-3")


def test_summary_lines_one_per_instance():
    plan = {
        "release": "6.x",
        "instances": [
            {"name": "isaac-sim-0", "gpu": None, "ports": {"signal": 49100, "stream": 47998}},
            {"name": "isaac-sim-1", "gpu": 1, "ports": {"signal": 49101, "stream": 47999}},
        ],
    }
    assert endpoints.summary_lines(plan, "h") == [
        "isaac-sim-0 gpu=- signal=h:49100 stream=h:47998/udp",
        "isaac-sim-1 gpu=1 signal=h:49101 stream=h:47999/udp",
    ]


def test_only_what_the_profile_opens_is_reported():
    block = {"signal": 49101, "stream": 47999, "web_viewer": 8211}
    # headless: nothing opened, so nothing to point a client at
    assert endpoints.endpoints("6.x", block, "h", served=[], listens=[]) == {}
    native = endpoints.endpoints("2023.1", {"http": 8212, "webrtc": 8012, "native": 48011}, "h", listens=["native"])
    assert native == {"native": "h:48011"}
    webrtc = endpoints.endpoints(
        "2023.1", {"http": 8212, "webrtc": 8012, "native": 48011}, "h", listens=["http", "webrtc"]
    )
    assert list(webrtc) == ["webrtc_client"]


def test_summary_lines_name_a_profile_other_than_streaming():
    plan = {
        "release": "6.x",
        "instances": [
            {"name": "isaac-sim-0", "gpu": None, "ports": {"signal": 49100}, "listens": [], "profile": "headless"}
        ],
    }
    assert endpoints.summary_lines(plan, "h") == ["isaac-sim-0 gpu=- profile=headless "]
