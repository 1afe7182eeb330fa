"""What the run modules do on their host (runs/runner.py): one experience, a host's share of a
suite, against a scripted systemd and Docker whose run directories are real (they are packed)."""

from __future__ import annotations

import os
import tarfile

import pytest
import yaml
from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib import layout
from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib.docker_socket import DockerSocket
from ansible_collections.isaacsim.fleet.plugins.module_utils.instance import lifecycle
from ansible_collections.isaacsim.fleet.plugins.module_utils.runs import runner
from ansible_collections.isaacsim.fleet.tests.unit.plugins.module_utils.runs.test_testrun import PAIR, ScriptedHost

# the simulator service's name has no dash: ScriptedHost finds a service by its unit name's last word
SIM = yaml.safe_load(
    """
services:
  sim:
    image: isaac-sim
  check:
    image: reg/check:1
    labels: {isaacsim.fleet/test-orchestrator: "true"}
    depends_on: {sim: {condition: service_healthy}}
"""
)
INSTANCE_ENV = "ISAAC_SIM_IMAGE=nvcr.io/nvidia/isaac-sim:6.0.1\nISAAC_SIM_PORT_SIGNAL=49100\n"


class Host(ScriptedHost):
    """The scripted host, with the Docker API's image list, borrowed instances that stay active,
    and run directories under `root` written to disk as well."""

    def __init__(self, root, images=("reg/robot:1", "reg/check:1"), **kw):
        super().__init__(**kw)
        self.root, self.images = str(root), set(images)

    def image(self, name):
        return {"Id": name} if name in self.images else None

    def run(self, argv):
        if argv[:2] == ["systemctl", "is-active"]:
            self.calls.append(argv)
            return 0, "active\n", ""
        if argv[:3] == ["mkdir", "-p", "-m"] and argv[-1].startswith(self.root):
            os.makedirs(argv[-1], exist_ok=True)
        return super().run(argv)

    def write(self, path, text, mode):
        super().write(path, text, mode)
        if path.startswith(self.root):
            os.makedirs(os.path.dirname(path), exist_ok=True)
            with open(path, "w") as fh:
                fh.write(text)


def make(host, **kw):
    """A Runner over the host; the warnings it gave."""
    warnings = []
    args = dict(
        hostname="h1",
        pid=42,
        gpu_count=lambda: (0, "no NVIDIA driver"),
        warn=warnings.append,
        companions=lambda: {},
        new_run=lambda name: f"{name}-20261124-0000-ab12",
        wall=lambda: 1_800_000_000.0,
    )
    args.update(kw)
    return runner.Runner(host, host, **args), warnings


def binder(host, warn):
    """runner.bind for a module's test: make(host)'s Runner, in the module's check mode."""

    def bind(module):
        return make(host, check_mode=module.check_mode, warn=warn)[0]

    return bind


def experience_params(root, **over) -> dict:
    """isaac_sim_experience's parameters as its argument spec gives them."""
    p = {
        "compose": PAIR,
        "name": "pair",
        "environment": {},
        "secret_environment": {},
        "profiles": [],
        "run": None,
        "timeout": 60.0,
        "instance": None,
        "simulator": "borrow",
        "simulator_image": None,
        "simulator_release": None,
        "gpus": ["0"],
        "data_root": str(root),
        "unfetched_after": 600.0,
        "keep_days": 14.0,
        "pull": True,
        "poll": 0.5,
        "metrics_interval": 2.0,
    }
    p.update(over)
    return p


def members(bundle) -> set:
    with tarfile.open(bundle) as tar:
        return set(tar.getnames())


def test_an_experience_runs_to_its_verdict_and_comes_back_in_one_bundle(tmp_path):
    host = Host(tmp_path)
    result = make(host)[0].experience(experience_params(tmp_path))
    run = "pair-20261124-0000-ab12"
    assert "failed" not in result and result["changed"] is True
    assert result["run"] == run and result["verdict"]["result"] == "passed"
    assert result["directory"] == f"{tmp_path}/runs/{run}" and result["directories"] == [result["directory"]]
    assert result["borrowed_instance"] is None and result["recovered"] == [] and result["expired"] == []
    assert "orchestrator_output" not in result and "simulator_slot" not in result
    assert result["bundle"].startswith(f"{tmp_path}/runs/bundle-") and result["bundle"].endswith(".tar.gz")
    assert {f"{run}/junit.xml", f"{run}/result.json", f"{run}/{run}-check.log"} <= members(result["bundle"])
    # each image was on the host: nothing pulled
    assert not any(c[:2] == ["/usr/bin/docker", "pull"] for c in host.calls)


def test_what_is_wrong_with_the_input_fails_before_anything_runs(tmp_path):
    host = Host(tmp_path)
    result = make(host)[0].experience(experience_params(tmp_path, run="Bad Name", timeout=0.0, keep_days=-1.0))
    assert result["failed"] is True
    assert result["errors"] == [
        "run: 'Bad Name' is not a run name. Fix: lower case letters, digits and dashes, 63 at most.",
        "timeout: 0. Fix: a number of seconds above 0.",
        "keep_days: -1. Fix: days, 0 or more (0 keeps runs for ever).",
    ]
    assert result["msg"] == " ".join(result["errors"]) and result["run"] == "Bad Name"
    assert host.calls == []


def test_check_mode_checks_the_images_and_starts_nothing(tmp_path):
    host = Host(tmp_path, images=["reg/robot:1"])
    result = make(host, check_mode=True)[0].experience(experience_params(tmp_path))
    # check mode pulls nothing: an image missing on the host cannot be had
    assert result["failed"] and "image reg/check:1 cannot be had (it is not on this host)" in result["msg"]
    host = Host(tmp_path)
    result = make(host, check_mode=True)[0].experience(experience_params(tmp_path))
    assert result == {
        "changed": True,
        "order": ["robot", "check"],
        "run": "pair-20261124-0000-ab12",
        "directory": f"{tmp_path}/runs/pair-20261124-0000-ab12",
        "ignored": [],
        "borrowed_instance": None,
        "recovered": [],
        "expired": [],
    }
    assert host.calls == [] and not os.path.exists(tmp_path / "runs")


def test_an_image_that_cannot_be_pulled_is_named(tmp_path):
    host = Host(tmp_path, images=["reg/robot:1"], fail_on="pull")
    result = make(host)[0].experience(experience_params(tmp_path))
    assert result["failed"] and result["errors"] == [
        "pair: image reg/check:1 cannot be had (boom). Fix: correct the image name or tag, or push the image to the "
        "fleet's registry."
    ]


def test_a_simulator_with_no_instance_to_borrow_is_refused(tmp_path):
    result = make(Host(tmp_path))[0].experience(experience_params(tmp_path, compose=SIM, name="sim"))
    assert result["failed"] and result["msg"].startswith("sim: service sim is the simulator (image: isaac-sim)")
    assert result["msg"].endswith("Fix: set instance (experience_instance) to a ready instance of the host.")


@pytest.fixture()
def given_back(monkeypatch):
    """lifecycle.give_back recorded (the real one restarts the instance through systemd)."""

    class GiveBack(list):
        error = None  # why the restart failed

        def __call__(self, host, i, run, companions=None):
            self.append((i, run))
            host.remove(layout.lent_marker(i))
            return self.error

    calls = GiveBack()
    monkeypatch.setattr(lifecycle, "give_back", calls)
    return calls


def test_a_borrowed_instance_is_lent_then_given_back_restarted(tmp_path, given_back):
    host = Host(tmp_path)
    host.files[layout.env_file(0)] = INSTANCE_ENV
    host.files[layout.marker(0)] = ""
    result = make(host)[0].experience(experience_params(tmp_path, compose=SIM, name="sim", instance=0))
    run = "sim-20261124-0000-ab12"
    assert result["verdict"]["result"] == "passed" and result["borrowed_instance"] == 0
    assert ["mkdir", layout.lent_marker(0)] in host.calls and given_back == [(0, run)]
    assert "restart_error" not in result
    # the orchestrator was told where the instance listens
    assert "ISAAC_SIM_PORT_SIGNAL=49100" in host.files[f"/run/isaac-sim/runs/{run}/check.env"]


def test_an_instance_that_does_not_come_back_is_reported(tmp_path, given_back):
    given_back.error = "not ready within 300 s"
    host = Host(tmp_path)
    host.files[layout.env_file(0)] = INSTANCE_ENV
    host.files[layout.marker(0)] = ""
    result = make(host)[0].experience(experience_params(tmp_path, compose=SIM, name="sim", instance=0))
    assert result["restart_error"] == "isaac-sim@0 did not come back: not ready within 300 s"
    assert "failed" not in result


def test_an_instance_lent_to_another_run_for_the_whole_timeout_fails_the_run(tmp_path, given_back):
    host = Host(tmp_path)
    host.files[layout.env_file(0)] = INSTANCE_ENV
    host.files[layout.marker(0)] = ""
    host.dirs.add(layout.lent_marker(0))
    host.files[f"{layout.lent_marker(0)}/run"] = "other-run\n\n"
    result = make(host)[0].experience(experience_params(tmp_path, compose=SIM, name="sim", instance=0, timeout=3.0))
    assert result["failed"] and result["msg"] == (
        "instance: isaac-sim@0 stayed lent to run other-run for this run's whole timeout (3 s). Fix: pick a free one, "
        "or a longer timeout."
    )
    assert given_back == [] and not any(c[:2] == ["systemctl", "start"] for c in host.calls)


def test_a_run_on_a_drained_host_is_refused_before_it_borrows_anything(tmp_path, given_back):
    host = Host(tmp_path)
    host.files[layout.env_file(0)] = INSTANCE_ENV
    host.files[layout.marker(0)] = ""
    host.files[layout.DRAINED] = '{"by": "olga", "at": 1795000000}'
    result = make(host)[0].experience(experience_params(tmp_path, compose=SIM, name="sim", instance=0, timeout=3.0))
    assert result["failed"] and result["msg"].startswith("instance: the host is drained (by olga at ")
    assert "isaac-sim-0 is not lent" in result["msg"] and layout.lent_marker(0) not in host.dirs
    assert given_back == []


def test_a_dedicated_simulator_on_a_host_without_gpus_is_warned_about_and_takes_a_slot(tmp_path):
    host = Host(tmp_path, images=["reg/check:1", "nvcr.io/nvidia/isaac-sim:6.0.1"])
    r, warnings = make(host)
    params = experience_params(
        tmp_path, compose=SIM, name="sim", simulator="dedicated", simulator_image="nvcr.io/nvidia/isaac-sim:6.0.1"
    )
    result = r.experience(params)
    assert result["verdict"]["result"] == "passed" and result["simulator_slot"] == 0
    assert warnings == [
        "sim: this host has no GPU (no NVIDIA driver); the dedicated simulator runs without one, which only a "
        "stand-in image can."
    ]
    assert ["mkdir", "/run/isaac-sim/simulator-0.lent"] in host.calls
    assert "/run/isaac-sim/simulator-0.lent" in host.removed  # the slot is free again
    # the simulator ran as a service of the run
    assert ["systemctl", "start", "--no-block", "isaac-sim-run-sim-20261124-0000-ab12-sim.service"] in host.calls


def test_runs_past_retention_are_removed_with_a_warning(tmp_path):
    old = tmp_path / "runs" / "old-run"
    old.mkdir(parents=True)
    os.utime(old, (0, 0))
    host = Host(tmp_path)
    r, warnings = make(host)
    result = r.experience(experience_params(tmp_path))
    assert result["expired"] == ["old-run"] and f"{old}" in host.removed
    assert warnings == [f"removed from {tmp_path}/runs, older than keep_days (14): old-run"]


def share_params(root, runs, **over) -> dict:
    """isaac_sim_test_suite's parameters as its argument spec gives them."""
    p = {
        "runs": runs,
        "parallel": 2,
        "instances": [],
        "gpus": ["0"],
        "data_root": str(root),
        "unfetched_after": 600.0,
        "keep_days": 14.0,
    }
    p.update(over)
    return p


def suite_run(key, compose=PAIR, **over) -> dict:
    run = {"key": key, "title": key, "experience": "pair", "compose": compose, "timeout": 60, "environment": {}}
    run.update(over)
    return run


def test_a_share_runs_each_run_and_one_image_missing_fails_only_its_runs(tmp_path):
    host = Host(tmp_path, fail_on="pull --quiet reg/gone:1")
    missing = yaml.safe_load(yaml.safe_dump(PAIR).replace("reg/check:1", "reg/gone:1"))
    runs = [suite_run("a"), suite_run("b", compose=missing)]
    result = make(host)[0].share(share_params(tmp_path, runs, parallel=1))
    assert "failed" not in result and result["changed"] is True
    a, b = result["results"]
    assert (a["title"], a["run"], a["verdict"]["result"], a["host"]) == ("a", "a-20261124-0000-ab12", "passed", "h1")
    assert "orchestrator_output" not in a and "instance" not in a
    assert b == {
        "title": "b",
        "key": "b",
        "experience": "pair",
        "timeout": 60,
        "host": "h1",
        "error": "reg/gone:1: image reg/gone:1 cannot be had (boom). Fix: correct the image name or tag, or push the "
        "image to the fleet's registry.",
    }
    assert result["directories"] == [f"{tmp_path}/runs/a-20261124-0000-ab12"]
    assert "a-20261124-0000-ab12/junit.xml" in members(result["bundle"])
    assert result["recovered"] == [] and result["expired"] == []


def test_a_share_is_refused_as_a_whole_for_bad_settings_or_files(tmp_path):
    host = Host(tmp_path)
    result = make(host)[0].share(share_params(tmp_path, [suite_run("a")], parallel=0))
    assert result == {"failed": True, "msg": "parallel: 0. Fix: 1 or more runs at once."}
    result = make(host)[0].share(share_params(tmp_path, [suite_run("a", compose={"services": {}})]))
    assert result["failed"] and result["errors"] and result["msg"] == " ".join(result["errors"])
    result = make(host)[0].share(share_params(tmp_path, [suite_run("a")], unfetched_after=-1.0))
    assert result == {
        "failed": True,
        "msg": "unfetched_after: -1. Fix: seconds, 0 or more.",
        "errors": ["unfetched_after: -1. Fix: seconds, 0 or more."],
    }
    assert host.calls == []


def test_a_share_in_check_mode_names_the_images_it_cannot_have_and_runs_nothing(tmp_path):
    host = Host(tmp_path, images=["reg/robot:1"])
    result = make(host, check_mode=True)[0].share(share_params(tmp_path, [suite_run("a")]))
    assert result == {
        "changed": True,
        "results": [],
        "errors": [
            "reg/check:1: image reg/check:1 cannot be had (it is not on this host). Fix: correct the image name or "
            "tag, or push the image to the fleet's registry."
        ],
    }
    assert host.calls == []


def test_a_share_lends_each_borrowing_run_an_instance_and_gives_it_back(tmp_path, given_back):
    host = Host(tmp_path)
    host.files[layout.env_file(1)] = INSTANCE_ENV
    host.files[layout.marker(1)] = ""
    runs = [suite_run("s", compose=SIM, simulator=True), suite_run("t")]
    result = make(host)[0].share(share_params(tmp_path, runs, instances=[1]))
    s, t = result["results"]
    assert s["verdict"]["result"] == "passed" and s["instance"] == 1 and "instance" not in t
    assert given_back == [(1, "s-20261124-0000-ab12")]
    # a run that needs an instance where the host lends none is an error, not a failed share
    result = make(Host(tmp_path))[0].share(share_params(tmp_path, [suite_run("s", compose=SIM)], instances=[]))
    assert result["results"] == [
        {
            "title": "s",
            "key": "s",
            "experience": "pair",
            "timeout": 60,
            "host": "h1",
            "error": "this host cannot give it the GPUs or the instance it needs",
        }
    ]


def test_a_dedicated_run_without_an_image_to_take_is_an_error_result(tmp_path):
    runs = [suite_run("d", compose=SIM, dedicated=True), suite_run("a")]
    result = make(Host(tmp_path))[0].share(share_params(tmp_path, runs))
    d, a = result["results"]
    assert d["error"].startswith("simulator_image: not given, and no Isaac Sim instance is deployed on this host")
    assert a["verdict"]["result"] == "passed"


def test_bind_gives_the_module_s_host_warnings_and_check_mode():
    class Module:
        check_mode = True

        def __init__(self):
            self.warnings = []

        def warn(self, text):
            self.warnings.append(text)

        def run_command(self, argv):
            return 0, f"ran {argv[0]}", ""

        def get_bin_path(self, name, required=False):
            return f"/usr/bin/{name}"

    module = Module()
    r = runner.bind(module)
    assert r.check_mode is True and r.hostname == os.uname().nodename and r.pid == os.getpid()
    r.warn("careful")
    assert module.warnings == ["careful"]
    assert r.host.run(["systemctl", "show"]) == (0, "ran /usr/bin/systemctl", "")
    assert isinstance(r.api, DockerSocket) and r.alive(os.getpid()) and not r.alive(2**22 + 1)
