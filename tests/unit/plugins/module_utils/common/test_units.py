"""The one unit writer: sections, comments, blank lines and left-out keys."""

from __future__ import annotations

from ansible_collections.isaacsim.fleet.plugins.module_utils.common import units


def test_sections_are_a_blank_line_apart_under_the_header():
    text = units.render(
        [
            ("Unit", [("Description", "x"), "# why", ("After", None)]),
            ("Service", [("ExecStart", "/bin/true"), "", ("RestartSec", 5)]),
        ],
        header=["Ansible managed", "second line"],
    )
    assert text == (
        "# Ansible managed\n# second line\n[Unit]\nDescription=x\n# why\n"
        "\n[Service]\nExecStart=/bin/true\n\nRestartSec=5\n"
    )


def test_keys_repeat_in_order_and_empty_values_stay():
    text = units.render([("Service", [("ExecStopPost", "-a"), ("ExecStopPost", "-b"), ("CapabilityBoundingSet", "")])])
    assert text == "[Service]\nExecStopPost=-a\nExecStopPost=-b\nCapabilityBoundingSet=\n"
