"""Names that reach unit names, file names, journal lines and JSON (users, tokens, runs, companions,
environment variables) are checked whole: Python's `$` also matches before a final newline, so a
name like "olga\\n" passed `^...$` checks and could split a journal line or an env file's line."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest
from ansible_collections.isaacsim.fleet.plugins.module_utils.front import door_store, front_door
from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib import layout
from ansible_collections.isaacsim.fleet.plugins.module_utils.instance import agent, companions, plan

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize(
    "check",
    [
        door_store.NAME_RE,
        agent.NAME_RE,
        agent.ACTION_ID_RE,
        layout.RUN_ID_RE,
        layout.COMPANION_NAME_RE,
        companions.ENV_NAME_RE,
        companions.PORT_NAME_RE,
        plan.ENV_NAME_RE,
        front_door._NAME_RE,  # pylint: disable=protected-access
    ],
)
def test_a_name_with_a_trailing_newline_is_refused(check):
    good = "0123456789abcdef" if check is agent.ACTION_ID_RE else "ab"
    assert check.match(good)
    assert not check.match(good + "\n")


def test_the_agent_refuses_a_user_or_token_with_a_newline():
    for field in ("user", "token"):
        body = {"host": "h", "action": "restart", "ids": [1], "user": "olga", field: "olga\n"}
        with pytest.raises(agent.RefusedError) as exc:
            agent.parse_request(json.dumps(body).encode())
        assert exc.value.code == 400 and "user, token" in exc.value.body["error"]
    assert door_store.token_errors("olga", "operator", "ci\n", ["read"], 30)[0].startswith("name: 'ci\\n'")


def test_no_check_of_the_collection_ends_in_a_dollar():
    # a whole-string check anchors with \Z (or uses fullmatch); `$` lets a trailing newline through
    found = [
        f"{path.relative_to(ROOT)}:{n}"
        for path in sorted((ROOT / "plugins").rglob("*.py"))
        for n, line in enumerate(path.read_text().splitlines(), 1)
        if re.search(r"re\.(compile|match|fullmatch|search)\(r?f?\"\^[^\"]*\$\"", line)
    ]
    assert found == []
