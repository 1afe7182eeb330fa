"""The parsers every domain shares (plugins/module_utils/common/parse.py)."""

import pytest
from ansible_collections.isaacsim.fleet.plugins.module_utils.common import parse

GIB = 1024**3


@pytest.mark.parametrize(
    "text, expected",
    [("8g", 8 * GIB), ("512m", 512 * 1024**2), ("2GiB", 2 * GIB), ("1.5g", int(1.5 * GIB)), ("100", 100), ("x", None)],
)
def test_parse_size(text, expected):
    assert parse.parse_size(text) == expected


@pytest.mark.parametrize(
    "ref, ok",
    [
        ("nvcr.io/nvidia/isaac-sim:5.1.0", True),
        ("localhost:5000/isaac-sim@sha256:" + "a" * 64, True),
        ("172.17.0.1:5555/fixtures/isaac-sim-standin:6.0.1", True),
        ("isaac-sim", True),
        ("nvcr.io/nvidia/Isaac-Sim:5.1.0", False),
        ("nvcr.io/nvidia/isaac-sim:", False),
        ("nvcr.io/nvidia/isaac-sim:5.1.0@sha256:short", False),
        ("", False),
    ],
)
def test_parse_image(ref, ok):
    assert (parse.parse_image(ref) is not None) == ok


@pytest.mark.parametrize(
    "value, expected", [(3, 3), ("12", 12), (" -5 ", -5), ("--5", None), ("1.5", None), (True, None)]
)
def test_as_int_takes_ints_and_digit_strings_only(value, expected):
    assert parse.as_int(value) == expected


def test_docker_size_is_one_word_as_docker_s_flags_want_it():
    assert parse.docker_size("1 GB") == "1g" and parse.docker_size("2GiB") == "2g" and parse.docker_size("512") == "512"


@pytest.mark.parametrize(
    "text, expected",
    [
        ("10.0.0.5", True),
        ("fd00::1", True),
        ("::ffff:10.0.0.5", True),
        ("fe80::1%eth0", False),
        ("10.0.0.5\n", False),
        (" 10.0.0.5", False),
        ("10.0.0.0/8", False),
        ("gpu-1.lab", False),
        (None, False),
    ],
)
def test_an_ip_is_plain_or_it_is_none(text, expected):
    assert parse.is_ip(text) is expected
