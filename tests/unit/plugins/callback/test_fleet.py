"""The fleet stdout callback (plugins/callback/fleet.py): a refusal printed once, by a real ansible-playbook run
with the callback and, to show the count can fail, the same run with ansible-core's default callback."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest
from ansible_collections.isaacsim.fleet.plugins.callback import fleet

REFUSAL = "isaac_sim_extra_docker_args: mounts the Docker socket. Fix: remove -v /var/run/docker.sock"
PLAYBOOK = """
- hosts: localhost
  gather_facts: false
  tasks:
    - name: A refusal
      ansible.builtin.fail:
        msg: "{refusal}"
      ignore_errors: true
    # the plan's own refusal (before it reads anything of the host): its message, and its errors as a list
    - name: A refusal of the plan
      isaacsim.fleet.isaac_sim_plan:
        release: "6.x"
        instance_count: 2
        port_bases: {{signal: not-a-port}}
        config_dir: {tmp}/etc
        systemd_dir: {tmp}/etc
      ignore_errors: true
    - name: A module's failure
      ansible.builtin.file:
        path: /nonexistent/isaac-sim
        state: file
"""


def collections_root() -> str:
    """The directory above ansible_collections/isaacsim/fleet, as ansible-test units or tools/bootstrap laid it."""
    here = os.path.realpath(fleet.__file__)
    path = os.path.abspath(fleet.__file__)
    while os.path.basename(path) != "ansible_collections":
        path = os.path.dirname(path)
    assert os.path.realpath(os.path.join(path, "isaacsim", "fleet", "plugins", "callback", "fleet.py")) == here
    return os.path.dirname(path)


def run(tmp_path, callback: str) -> str:
    book = tmp_path / "refuse.yml"
    book.write_text(PLAYBOOK.format(refusal=REFUSAL, tmp=tmp_path))
    env = dict(
        os.environ,
        ANSIBLE_COLLECTIONS_PATH=collections_root(),
        ANSIBLE_STDOUT_CALLBACK=callback,
        ANSIBLE_CALLBACK_RESULT_FORMAT="yaml",
        ANSIBLE_LOCALHOST_WARNING="false",
        ANSIBLE_INVENTORY_UNPARSED_WARNING="false",
        ANSIBLE_NOCOLOR="true",
    )
    env.pop("ANSIBLE_CONFIG", None)
    out = subprocess.run(
        [sys.executable, "-m", "ansible.cli.playbook", str(book)],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        check=False,
        timeout=120,
    )
    assert out.returncode == 2, out.stdout + out.stderr
    return out.stdout + out.stderr


@pytest.mark.parametrize("callback, times", [("isaacsim.fleet.fleet", 1), ("ansible.builtin.default", 2)])
def test_each_refusal_is_printed_once(tmp_path, callback, times):
    text = run(tmp_path, callback)
    assert text.count(REFUSAL) == times, text
    assert text.count("is not a port number") == (1 if times == 1 else 3), text
    assert text.count("is absent, cannot continue") == times, text
    # the rest of a failed result stays: the module's own keys and the ignoring
    assert "path: /nonexistent/isaac-sim" in text
    assert text.count("...ignoring") == 2


@pytest.mark.parametrize(
    "msg, messages, shown",
    [
        ("x is bad", ["Task failed.", "Action failed: x is bad"], True),
        ("x is bad", ["Task failed.", "Module failed: x is bad"], True),
        ("x is bad", ["Task failed.", "x is bad"], True),
        # another message, or a longer one that only ends alike: kept
        ("x is bad", ["Task failed.", "Action failed: y is bad"], False),
        ("x is bad", ["Task failed.", "Action failed: not x is bad"], False),
        ("", ["Task failed."], False),
        (None, ["Task failed."], False),
    ],
)
def test_shown_in(msg, messages, shown):
    assert fleet.shown_in(msg, messages) is shown
