"""Where clients reach an instance, per release (module_utils/hostlib/endpoints.py)."""

from __future__ import annotations

import hashlib
import itertools
import json

import pytest
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


# Every (release, block) below: the sha256 of what endpoints() reported, in its order, for every
# subset of the block's ports, every subset of them opened (and None) and three sets of companion
# ports, as the release branches reported it before the shapes became the URLS table. "7.x": a
# release this library does not know (a newer collection's env file) gets the streaming client's.
BLOCKS = {
    "2023.1": {"http": 8212, "webrtc": 8012, "native": 48011},
    "4.x": {"signal": 49101, "stream": 47999, "http": 8012},
    "6.x": {"signal": 49101, "stream": 47999, "web_viewer": 8211},
    "all": {"http": 8212, "webrtc": 8012, "native": 48011, "signal": 49101, "stream": 47999, "web_viewer": 8211},
}
BEFORE_THE_TABLE = {
    "2023.1 2023.1": "11e7f15c505b382326af6cdb2f649f90954f05f3e52f05c88d965d1362442598",
    "2023.1 4.x": "b458dd950d82c33be2632b472bfa00aa4017e391f1d693405fa13f1c2381af6b",
    "2023.1 6.x": "d1928dac1b11791bdf34c6c4cfd369d973d185a9a75e2ac2b1da56e4fcc75ce3",
    "2023.1 all": "5d584380befd17d0c8c2f11cff5cb3fa588c13b72aa85c4c13a02875bcef9fbd",
    "4.x 2023.1": "0b8627843f440db143fc2c24d8ff2301d77ae876eaf83e26e3b1f2f49a603914",
    "4.x 4.x": "35316d935c44f39272dde79cefe6711d522989410f06494008942fe788758bf7",
    "4.x 6.x": "eac9e4425dbd403057425d4cf9e7dae57ab2861cb28db413c0d3637789fafd33",
    "4.x all": "47c08b92fdf6512a1d6b3d90cbc227c90c873920745948fa2ddb30bb37b625ae",
    "5.x 2023.1": "0b8627843f440db143fc2c24d8ff2301d77ae876eaf83e26e3b1f2f49a603914",
    "5.x 4.x": "35316d935c44f39272dde79cefe6711d522989410f06494008942fe788758bf7",
    "5.x 6.x": "eac9e4425dbd403057425d4cf9e7dae57ab2861cb28db413c0d3637789fafd33",
    "5.x all": "47c08b92fdf6512a1d6b3d90cbc227c90c873920745948fa2ddb30bb37b625ae",
    "6.x 2023.1": "0b8627843f440db143fc2c24d8ff2301d77ae876eaf83e26e3b1f2f49a603914",
    "6.x 4.x": "35316d935c44f39272dde79cefe6711d522989410f06494008942fe788758bf7",
    "6.x 6.x": "eac9e4425dbd403057425d4cf9e7dae57ab2861cb28db413c0d3637789fafd33",
    "6.x all": "47c08b92fdf6512a1d6b3d90cbc227c90c873920745948fa2ddb30bb37b625ae",
    "7.x 2023.1": "0b8627843f440db143fc2c24d8ff2301d77ae876eaf83e26e3b1f2f49a603914",
    "7.x 4.x": "35316d935c44f39272dde79cefe6711d522989410f06494008942fe788758bf7",
    "7.x 6.x": "eac9e4425dbd403057425d4cf9e7dae57ab2861cb28db413c0d3637789fafd33",
    "7.x all": "47c08b92fdf6512a1d6b3d90cbc227c90c873920745948fa2ddb30bb37b625ae",
}


def _subsets(kinds):
    return [list(c) for n in range(len(kinds) + 1) for c in itertools.combinations(kinds, n)]


def _reported(release, block):
    out = []
    for kinds in _subsets(list(block)):
        ports = {k: block[k] for k in kinds}
        for listens in [None] + _subsets(kinds):
            for served in ([], [8211], [8212, 8211]):
                out.append(list(endpoints.endpoints(release, ports, "10.0.0.5", served, listens).items()))
    return hashlib.sha256(json.dumps(out).encode()).hexdigest()


# Since the built-in companions' shapes moved to builtin_companions.py (reported after a release's own),
# a block holding a kind its release lacks reports differently: a 2023.1 block with the 6.x web viewer's
# port, or every kind at once. No instance has such a block (the plan gives one the kinds of its release):
# those are no longer compared.
LACKING = {("2023.1", "6.x")} | {(release, "all") for release in ("2023.1", "4.x", "5.x", "6.x", "7.x")}


@pytest.mark.parametrize(
    "release, block",
    [(r, b) for r in ("2023.1", "4.x", "5.x", "6.x", "7.x") for b in BLOCKS if (r, b) not in LACKING],
)
def test_the_url_shapes_report_what_the_release_branches_reported(release, block):
    assert _reported(release, BLOCKS[block]) == BEFORE_THE_TABLE[f"{release} {block}"]


def test_a_built_in_companion_s_url_follows_the_release_s_own_where_it_serves_the_port():
    block = {"signal": 49101, "stream": 47999, "web_viewer": 8211}
    assert list(endpoints.endpoints("6.x", block, "h", served=[8211])) == ["signal", "stream", "web_viewer"]
    assert "web_viewer" not in endpoints.endpoints("6.x", block, "h", served=[8212])


def test_every_shape_is_a_port_the_instance_or_a_companion_opens():
    for release, shapes in endpoints.URLS.items():
        names = [name for _kind, name, _shape, _by in shapes]
        assert len(set(names)) == len(names), release
        assert {by for *_rest, by in shapes} <= {endpoints.INSTANCE, endpoints.COMPANION}
