"""The rollout sequence against a scripted host.

The scripted host answers systemctl, journalctl and docker the way a real one
does for the cases that matter: an image that becomes ready, one that never
does (the gate's message in the journal), one that crashes during the soak.
The real thing runs in the molecule fleet scenario.
"""

import pytest
from ansible_collections.isaacsim.fleet.plugins.module_utils import rollout

OLD = 'ISAAC_SIM_IMAGE="reg/isaac-sim:5.0.0"\nISAAC_SIM_IMAGE_ID="sha256:old"\n'
NEW = 'ISAAC_SIM_IMAGE="reg/isaac-sim:5.1.0"\nISAAC_SIM_IMAGE_ID="sha256:new"\n'
NEVER = 'ISAAC_SIM_IMAGE="reg/isaac-sim:never-ready"\nISAAC_SIM_IMAGE_ID="sha256:never"\n'
CRASHY = 'ISAAC_SIM_IMAGE="reg/isaac-sim:crashy"\nISAAC_SIM_IMAGE_ID="sha256:crashy"\n'
P = rollout.Paths("/etc/isaac-sim", "/run/isaac-sim", "/var/lib/isaac-sim/rollout")


class ScriptedHost:
    def __init__(self, n=4, tags=None):
        self.files = {P.env(i): (OLD, 0o600) for i in range(n)}
        self.units = {
            i: {"ActiveState": "active", "SubState": "running", "NRestarts": 0, "Result": "success"} for i in range(n)
        }
        self.markers = set(range(n))
        self.tags = tags or {"reg/isaac-sim:5.0.0": "sha256:old"}
        self.clock = 1000.0
        self.log = []
        self.journal = {i: [] for i in range(n)}
        self.host = rollout.Host(
            self.run,
            self.read,
            self.write,
            self.mode,
            self.exists,
            self.sleep,
            self.now,
            lambda: 1795000000 + self.clock,
        )

    def read(self, path):
        return self.files.get(path, (None, None))[0]

    def write(self, path, text, mode):
        self.files[path] = (text, mode)

    def mode(self, path):
        return self.files.get(path, (None, None))[1]

    def exists(self, path):
        return any(path == P.marker(i) for i in self.markers)

    def sleep(self, s):
        self.clock += s
        for i, u in self.units.items():
            # the crashy image dies 3 s into the soak and systemd restarts it
            crashy = rollout.env_value(self.read(P.env(i)), "ISAAC_SIM_IMAGE").endswith("crashy")
            if crashy and u.get("since") and self.clock - u["since"] > 3 and u["NRestarts"] == u.get("base", 0):
                u["NRestarts"] += 1

    def now(self):
        return self.clock

    def run(self, argv):
        self.log.append(" ".join(argv))
        if argv[:2] == ["systemctl", "show"]:
            u = self.units[int(argv[-1].split("@")[1].split(".")[0])]
            return 0, "".join(f"{k}={v}\n" for k, v in u.items() if k[0].isupper()), ""
        if argv[:2] == ["systemctl", "restart"]:
            i = int(argv[2].split("@")[1].split(".")[0])
            image = rollout.env_value(self.read(P.env(i)), "ISAAC_SIM_IMAGE")
            self.markers.discard(i)
            if "never-ready" in image:
                self.clock += 20
                self.units[i].update(ActiveState="failed", Result="exit-code")
                self.journal[i].append(f"isaac-sim-{i} was not ready within 20 s (waiting for /App is loaded\\./)")
                return 1, "", "Job for isaac-sim@.service failed"
            self.clock += 5
            self.units[i].update(
                ActiveState="active", Result="success", since=self.clock, base=self.units[i]["NRestarts"]
            )
            self.markers.add(i)
            return 0, "", ""
        if argv[0] == "journalctl":
            i = int(argv[2].split("@")[1].split(".")[0])
            return 0, "\n".join(self.journal[i]), ""
        if argv[:3] == ["docker", "image", "inspect"]:
            tag = argv[-1]
            return (0, self.tags[tag] + "\n", "") if tag in self.tags else (1, "", "No such image")
        return 0, "", ""


def test_record_keeps_each_env_file_with_its_mode():
    h = ScriptedHost(2)
    assert rollout.record(h.host, P, [0, 1]) == {
        i: {"image": "reg/isaac-sim:5.0.0", "image_id": "sha256:old"} for i in (0, 1)
    }
    assert h.files[P.record(0)] == (OLD, 0o600)


def test_an_upgrade_goes_one_instance_at_a_time_with_a_soak_each():
    h = ScriptedHost(3)
    rollout.record(h.host, P, [0, 1, 2])
    result = rollout.roll(h.host, P, [{"id": i, "env": NEW} for i in range(3)], soak_seconds=10)
    assert result["failed"] is None and result["changed"]
    assert [d["action"] for d in result["done"]] == ["apply"] * 3
    assert all(d["restart_s"] == 5 and d["soak_s"] >= 10 for d in result["done"])
    restarts = [line for line in h.log if line.startswith("systemctl restart")]
    assert restarts == [f"systemctl restart isaac-sim@{i}.service" for i in range(3)]
    # each restart comes after the previous instance's soak: reset-failed precedes every restart
    assert h.log.index("systemctl reset-failed isaac-sim@1.service") > h.log.index(
        "systemctl restart isaac-sim@0.service"
    )
    assert h.files[P.env(2)] == (NEW, 0o644)


def test_a_rerun_leaves_applied_instances_alone():
    h = ScriptedHost(2)
    h.files[P.env(0)] = (NEW, 0o644)
    result = rollout.roll(h.host, P, [{"id": i, "env": NEW} for i in range(2)], soak_seconds=0)
    assert [d["action"] for d in result["done"]] == ["unchanged", "apply"]
    assert "systemctl restart isaac-sim@0.service" not in h.log


def test_never_ready_is_reverted_and_stops_the_host():
    h = ScriptedHost(4)
    rollout.record(h.host, P, range(4))
    result = rollout.roll(h.host, P, [{"id": i, "env": NEVER} for i in range(4)], soak_seconds=5)
    failed = result["failed"]
    assert failed["id"] == 0 and "was not ready within 20 s" in failed["reason"]
    assert failed["reverted"] is True and failed["reverted_to"] == "reg/isaac-sim:5.0.0"
    assert result["untouched"] == [1, 2, 3] and result["done"] == []
    # back on the recorded file, with its mode, and ready; the others never touched
    assert h.files[P.env(0)] == (OLD, 0o600) and 0 in h.markers
    assert all(h.files[P.env(i)][0] == OLD for i in (1, 2, 3))
    assert not any(f"isaac-sim@{i}" in line for line in h.log for i in (1, 2, 3))


def test_a_crash_during_the_soak_fails_the_instance():
    h = ScriptedHost(2)
    rollout.record(h.host, P, [0, 1])
    result = rollout.roll(h.host, P, [{"id": 0, "env": CRASHY}, {"id": 1, "env": CRASHY}], soak_seconds=10)
    assert result["failed"]["id"] == 0 and "restarted during the soak (NRestarts 0 -> 1)" in result["failed"]["reason"]
    assert result["failed"]["reverted"] and result["untouched"] == [1]


def test_revert_pins_the_image_id_when_the_tag_moved():
    h = ScriptedHost(1, tags={"reg/isaac-sim:5.0.0": "sha256:retagged"})
    rollout.record(h.host, P, [0])
    result = rollout.roll(h.host, P, [{"id": 0, "env": NEVER}], soak_seconds=0)
    assert result["failed"]["reverted_to"] == "sha256:old"
    assert 'ISAAC_SIM_IMAGE="sha256:old"' in h.files[P.env(0)][0]


def test_a_restart_stops_an_instance_still_starting_first():
    h = ScriptedHost(1)
    h.units[0]["ActiveState"] = "activating"
    rollout.roll(h.host, P, [{"id": 0}], soak_seconds=0)
    assert h.log.index("systemctl stop isaac-sim@0.service") < h.log.index("systemctl restart isaac-sim@0.service")


@pytest.mark.parametrize("env", [None, NEW])
def test_check_mode_changes_nothing(env):
    h = ScriptedHost(2)
    result = rollout.roll(h.host, P, [{"id": 0, "env": env}, {"id": 1, "env": env}], soak_seconds=5, check=True)
    assert [d["action"] for d in result["done"]] == (["restart"] * 2 if env is None else ["apply"] * 2)
    assert not any(line.startswith(("systemctl restart", "systemctl reset-failed")) for line in h.log)
    assert h.files[P.env(0)][0] == OLD


def test_a_missing_env_file_stops_with_a_reason():
    h = ScriptedHost(1)
    result = rollout.roll(h.host, P, [{"id": 5}], soak_seconds=0)
    assert result["failed"]["id"] == 5 and "missing" in result["failed"]["reason"]
    assert result["failed"]["reverted"] is None
    lines = rollout.summary({"a": {"done": [], "failed_instance": result["failed"], "untouched": []}}, ["a", "b"])
    assert (
        "reverted: a: isaac-sim-5 (/etc/isaac-sim/instance-5.env is missing (not deployed here)) - not changed" in lines
    )
    assert "untouched: b: every instance (not reached)" in lines


def test_summary_of_a_completed_rollout():
    ok = {"done": [{"id": 0, "action": "apply"}, {"id": 1, "action": "unchanged"}], "failed_instance": None}
    lines = rollout.summary({"a": ok, "b": ok}, ["a", "b"])
    assert lines == [
        "rolled: a: isaac-sim-0; b: isaac-sim-0",
        "already current: a: isaac-sim-1; b: isaac-sim-1",
        "reverted: none",
        "untouched: none",
        "completed: every host rolled",
    ]
