# Copyright: isaacsim.fleet contributors
# SPDX-License-Identifier: Apache-2.0 (the collection's license, see galaxy.yml)
# Apache-2.0 is compatible with the GNU General Public License v3.0 that ansible-core is
# released under; ansible-test's validate-modules looks for that license's name here.
"""ansible-core's default output, with each failed task's message printed once."""

from __future__ import annotations

DOCUMENTATION = r"""
name: fleet
type: stdout
short_description: The default output, each refusal printed once
version_added: "0.3.0"
description:
  - ansible-core's C(default) stdout callback with one difference. Since ansible-core 2.19 a failed task
    prints its message twice, in the C([ERROR]) block (with where the task is) and again as C(msg) in the
    C(fatal:) result. The collection's refusals are long (they name the variable, the host and the fix, and
    sometimes list the exact commands to run), so each is printed once here, in the C([ERROR]) block;
    the C(fatal:) result keeps every other key but a list of messages each of which the block showed (the
    plan's C(errors)).
  - A message the C([ERROR]) block did not show (a loop item's, or one that differs) stays in the result.
  - Set it with C(stdout_callback = isaacsim.fleet.fleet) in C(ansible.cfg) (the repository's own does), or
    C(ANSIBLE_STDOUT_CALLBACK=isaacsim.fleet.fleet).
extends_documentation_fragment:
  - ansible.builtin.default_callback
  - ansible.builtin.result_format_callback
requirements:
  - set as stdout callback in configuration
"""

from ansible.plugins.callback.default import CallbackModule as DefaultCallback


def messages_of(event) -> list:
    """Every message in an error's chain of causes (ansible-core's ErrorSummary event)."""
    found = []
    while event is not None:
        found.append(str(getattr(event, "msg", "")))
        chain = getattr(event, "chain", None)
        event = getattr(chain, "event", None)
    return found


def shown_in(msg, messages: list) -> bool:
    """Whether the [ERROR] block showed msg: as one of its causes, or behind ansible's own prefix
    ("Action failed: ...")."""
    if not isinstance(msg, str) or not msg.strip():
        return False
    want = msg.strip()
    return any(m.strip() == want or m.strip().endswith(": " + want) for m in messages)


class CallbackModule(DefaultCallback):
    CALLBACK_VERSION = 2.0
    CALLBACK_TYPE = "stdout"
    CALLBACK_NAME = "isaacsim.fleet.fleet"

    def _handle_exception(self, result, use_stderr=False):
        current = self._current_task_result
        exception = getattr(current, "exception", None) if "exception" in result else None
        super()._handle_exception(result, use_stderr=use_stderr)
        msg = result.get("msg")
        if exception is None or not shown_in(msg, messages_of(getattr(exception, "event", None))):
            return
        del result["msg"]
        for key, value in list(result.items()):
            if isinstance(value, list) and value and all(isinstance(v, str) and v in msg for v in value):
                del result[key]
