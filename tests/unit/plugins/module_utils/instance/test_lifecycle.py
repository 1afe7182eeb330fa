"""The instance lifecycle against a scripted host.

The scripted host answers systemctl, journalctl and docker the way a real one
does for the cases that matter: an image that becomes ready, one that never
does (the gate's message in the journal), one that crashes during the soak,
an instance stuck activating. The real thing runs in the molecule scenarios.
"""

import fnmatch
import json
import os
import shutil
from pathlib import Path

import pytest
from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib import layout
from ansible_collections.isaacsim.fleet.plugins.module_utils.instance import (
    firewall,
    lifecycle,
    reserved_ports,
    unit_files,
)

UNIT_FILE = "/etc/systemd/system/isaac-sim@.service"
GATE = "/usr/local/libexec/isaac-sim/isaac-sim-ready"


def env(image, image_id, extra=""):
    return f"{layout.K_IMAGE}={layout.quote(image)}\n{layout.K_IMAGE_ID}={layout.quote(image_id)}\n{extra}"


OLD = env("reg/isaac-sim:5.0.0", "sha256:old")
NEW = env("reg/isaac-sim:5.1.0", "sha256:new")
NEVER = env("reg/isaac-sim:never-ready", "sha256:never")
CRASHY = env("reg/isaac-sim:crashy", "sha256:crashy")


class ScriptedHost:
    def __init__(self, n=4, running=True, tags=None):
        self.files = {}
        self.units = {}
        for i in range(n):
            if running:
                self.files[layout.env_file(i)] = (OLD, 0o644)
            self.units[i] = {
                "ActiveState": "active" if running else "inactive",
                "SubState": "running" if running else "dead",
                "NRestarts": 0,
                "Result": "success",
                "UnitFileState": "enabled" if running else "disabled",
            }
        if running:
            self.files[UNIT_FILE] = ("unit v1\n", 0o644)
            self.files[GATE] = ("gate v1\n", 0o755)
        self.target = "enabled" if running else "disabled"
        self.docker_want = running
        self.markers = {i for i in range(n) if running}
        # companions: {(id, name): unit state}; ready markers {(id, name)}
        self.comps = {}
        self.comp_markers = set()
        self.tags = tags or {"reg/isaac-sim:5.0.0": "sha256:old"}
        self.clock = 1000.0
        self.log = []
        self.journal = {}
        self.dirs = set()  # made with mkdir (a lent instance's marker)
        # nftables: the text of the rules last loaded (None: no table of ours), the firewall unit enabled
        self.nft = True
        # the site's own input chains (nft -j list ruleset), and the handles nft gives rules
        self.site, self.handle = {}, 100
        self.tables = None
        self.wall_enabled = False
        self.host = lifecycle.Host(
            self.run,
            lambda p: self.files.get(p, (None, None))[0],
            self.write,
            self.remove,
            lambda p: self.files.get(p, (None, None))[1],
            lambda p: any(p == layout.marker(i) for i in self.markers)
            or any(p == layout.companion_marker(i, n) for i, n in self.comp_markers)
            or (p == layout.TARGET_DOCKER_WANT and self.docker_want)
            or p in self.dirs
            or (p == firewall.NFT and self.nft),
            self.sleep,
            lambda: self.clock,
            lambda: 1795000000 + self.clock,
            find=self.find,
        )

    def write(self, path, text, mode):
        self.files[path] = (text, mode)

    def find(self, pattern):
        """glob over the files, and the target's links of the instances enabled (one directory, as glob)."""
        wants = os.path.join(layout.UNIT_DIR, layout.TARGET + ".wants")
        links = [os.path.join(wants, layout.unit(i)) for i, u in self.units.items() if u["UnitFileState"] == "enabled"]
        folder, name = os.path.split(pattern)
        return sorted(
            p
            for p in list(self.files) + links
            if os.path.dirname(p) == folder and fnmatch.fnmatch(os.path.basename(p), name)
        )

    def remove(self, path):
        self.log.append(f"rm {path}")
        self.dirs.discard(path)
        for p in [p for p in self.files if p == path or p.startswith(path + "/")]:
            del self.files[p]

    def image(self, i):
        return layout.parse(self.files.get(layout.env_file(i), ("", 0))[0]).get(layout.K_IMAGE, "")

    def sleep(self, s):
        self.clock += s
        for i, u in self.units.items():
            # the crashy image dies 3 s after its start and systemd restarts it
            crashy = self.image(i).endswith("crashy")
            if crashy and u.get("since") and self.clock - u["since"] > 3 and u["NRestarts"] == u.get("base", 0):
                u["NRestarts"] += 1

    def _start(self, i):
        u = self.units[i]
        self.markers.discard(i)
        if "never-ready" in self.image(i):
            self.clock += 20
            # Restart=always: the failed start is tried again after RestartSec
            u.update(ActiveState="activating", SubState="auto-restart", Result="exit-code")
            gate = f"isaac-sim-{i} was not ready within 20 s"
            # the gate quotes the journal's last lines, its own message among them
            self.journal.setdefault(i, []).extend([gate, "  | loading scene", "  | " + gate])
            return False
        self.clock += 5
        u.update(ActiveState="active", SubState="running", Result="success", since=self.clock, base=u["NRestarts"])
        self.markers.add(i)
        return True

    def comp(self, i, name):
        return self.comps.setdefault(
            (i, name), {"ActiveState": "inactive", "SubState": "dead", "NRestarts": 0, "UnitFileState": "disabled"}
        )

    def _start_comp(self, i, name):
        """A companion starts when its instance serves and its image is not a broken one."""
        c = self.comp(i, name)
        text = self.files.get(layout.companion_env_file(i, name), ("", 0))[0] or ""
        if self.units.get(i, {}).get("ActiveState") == "active" and "broken" not in text and text:
            c.update(ActiveState="active", SubState="running")
            self.comp_markers.add((i, name))
            return True
        c.update(ActiveState="failed", SubState="failed")
        self.comp_markers.discard((i, name))
        self.journal.setdefault(layout.companion_unit(i, name), []).append(
            f"{layout.companion_container(i, name)} stopped before it was ready"
        )
        return False

    def _stop_comps(self, i):
        """BindsTo=: an instance that stops takes its companions down."""
        for (j, name), c in self.comps.items():
            if j == i and c["ActiveState"] == "active":
                c.update(ActiveState="inactive", SubState="dead")
                self.comp_markers.discard((j, name))

    def run(self, argv):
        self.log.append(" ".join(argv))
        if argv[0] == firewall.NFT:
            return self._nft(argv)
        if firewall.UNIT in argv:
            if argv[1] == "is-enabled":
                return (0, "enabled\n", "") if self.wall_enabled else (1, "disabled\n", "")
            if argv[1] in ("enable", "disable"):
                self.wall_enabled = argv[1] == "enable"
            return 0, "", ""
        if argv[0] == "mkdir":
            if argv[1] in self.dirs:
                return 1, "", f"mkdir: cannot create directory '{argv[1]}': File exists"
            self.dirs.add(argv[1])
            return 0, "", ""
        ids = [layout.instance_id(layout.UNIT_RE, a) for a in argv if layout.instance_id(layout.UNIT_RE, a) is not None]
        comps = [
            (int(m.group(2)), m.group(1)) for m in (layout.COMPANION_UNIT_RE.match(a) for a in argv) if m is not None
        ]
        if comps and argv[:2] == ["systemctl", "show"]:
            blocks = [
                f"Id={layout.companion_unit(i, n)}\n" + "".join(f"{k}={v}\n" for k, v in self.comp(i, n).items())
                for i, n in comps
            ]
            return 0, "\n".join(blocks), ""
        if comps and argv[:2] == ["systemctl", "start"]:
            started = [self._start_comp(i, n) for i, n in comps]  # every one, as systemd does
            ok = all(started)
            return (0, "", "") if ok else (1, "", "Job failed")
        if comps and argv[:2] == ["systemctl", "enable"]:
            for i, n in comps:
                self.comp(i, n)["UnitFileState"] = "enabled"
        if comps and argv[:3] == ["systemctl", "disable", "--now"]:
            for i, n in comps:
                self.comp(i, n).update(ActiveState="inactive", SubState="dead", UnitFileState="disabled")
                self.comp_markers.discard((i, n))
        if argv[:3] == ["systemctl", "list-units", "--failed"]:
            failed = [layout.companion_unit(i, n) for (i, n), c in self.comps.items() if c["ActiveState"] == "failed"]
            return 0, "".join(f"{u} loaded failed failed Isaac Sim companion\n" for u in failed), ""
        if comps and argv[:2] == ["systemctl", "reset-failed"]:
            for i, n in comps:
                if self.comp(i, n)["ActiveState"] == "failed":
                    self.comp(i, n).update(ActiveState="inactive", SubState="dead")
        if argv[0] == "journalctl" and layout.COMPANION_UNIT_RE.match(argv[2]):
            return 0, "\n".join(self.journal.get(argv[2], [])), ""
        if argv[:2] == ["systemctl", "show"] and layout.TARGET in argv:
            return 0, self.target + "\n", ""
        if argv[:2] == ["systemctl", "show"]:
            blocks = []
            for i in ids:
                u = self.units.setdefault(
                    i,
                    {
                        "ActiveState": "inactive",
                        "SubState": "dead",
                        "NRestarts": 0,
                        "Result": "success",
                        "UnitFileState": "disabled",
                    },
                )
                blocks.append(f"Id={layout.unit(i)}\n" + "".join(f"{k}={v}\n" for k, v in u.items() if k[0].isupper()))
            return 0, "\n".join(blocks), ""
        if argv[:2] in (["systemctl", "restart"], ["systemctl", "start"]):
            if argv[1] == "restart":
                for i in ids:
                    self._stop_comps(i)
            started = [self._start(i) for i in ids]  # every one, not up to the first failure
            ok = all(started)
            return (0, "", "") if ok else (1, "", "Job for isaac-sim@.service failed")
        if argv[:2] == ["systemctl", "stop"] or argv[:3] == ["systemctl", "disable", "--now"]:
            for i in ids:
                self._stop_comps(i)
                self.units[i].update(ActiveState="inactive", SubState="dead")
                self.markers.discard(i)
                if argv[1] == "disable":
                    self.units[i]["UnitFileState"] = "disabled"
            return 0, "", ""
        if argv[:2] == ["systemctl", "enable"]:
            for i in ids:
                self.units[i]["UnitFileState"] = "enabled"
            self.target = "enabled"
            self.docker_want = True
            return 0, "", ""
        if argv[0] == "journalctl":
            return 0, "\n".join(self.journal.get(ids[0], [])), ""
        if argv[:3] == ["docker", "image", "inspect"]:
            tag = argv[-1]
            return (0, self.tags[tag] + "\n", "") if tag in self.tags else (1, "", "No such image")
        return 0, "", ""

    def _nft(self, argv):
        """nft -f RULES loads the file's tables; list answers what is loaded; the stop line drops them."""
        if argv[1] == "-f":
            self.tables = self.files[argv[2]][0]
            return 0, "", ""
        if argv[1] == "list":
            family = argv[3]
            if self.tables and f"table {family} {firewall.TABLE} {{" in self.tables:
                part = self.tables.split(f"table {family} {firewall.TABLE} {{", 1)[1].split("\n}", 1)[0]
                return 0, f"table {family} {firewall.TABLE} {{{part}\n}}\n", ""
            return 1, "", "Error: No such file or directory"
        if argv[1] == "-j":
            return 0, json.dumps({"nftables": self._site_listing()}), ""
        if argv[1].startswith(f"table inet {firewall.TABLE}"):
            self.tables = None
            return 0, "", ""
        for cmd in argv[1].split("; "):
            words = cmd.split()
            rules = self.site[tuple(words[2:5])]["rules"]
            if words[0] == "delete":
                rules[:] = [r for r in rules if r[0] != int(words[-1])]
            else:
                self.handle += 1
                rules.insert(0, (self.handle, cmd.split(" ", 5)[5]))
        return 0, "", ""

    def _site_listing(self) -> list:
        """nft -j list ruleset of the site's tables (self.site: {(family, table, chain): {"policy", "rules":
        [(handle, text)]}}), each rule's comment as nft gives it."""
        out = []
        for (family, table, chain), c in self.site.items():
            out.append(
                {
                    "chain": {
                        "family": family,
                        "table": table,
                        "name": chain,
                        "handle": 1,
                        "type": "filter",
                        "hook": "input",
                        "prio": 0,
                        "policy": c["policy"],
                    }
                }
            )
            for handle, text in c["rules"]:
                rule = {"family": family, "table": table, "chain": chain, "handle": handle, "expr": [{"accept": None}]}
                if ' comment "' in text:
                    rule["comment"] = text.rsplit('"', 2)[-2]
                out.append({"rule": rule})
        return out

    def commands(self, verb):
        return [line for line in self.log if line.startswith(f"systemctl {verb}")]


# what the lifecycle reads before it changes anything
READS = ("systemctl show", "systemctl list-units")


def want(instances, files=None, **over):
    w = {
        "files": files if files is not None else {UNIT_FILE: ("unit v1\n", 0o644), GATE: ("gate v1\n", 0o755)},
        "instances": instances,
        "env_mode": 0o644,
        "remove": [],
        "soak": 0,
    }
    w.update(over)
    return w


def test_a_fresh_host_starts_every_instance_at_once_and_enables_them():
    h = ScriptedHost(4, running=False)
    result = lifecycle.apply(h.host, want({i: NEW for i in range(4)}))
    assert result["failed"] is None and result["changed"]
    assert h.commands("start") == ["systemctl start " + " ".join(layout.unit(i) for i in range(4))]
    assert h.commands("restart") == []
    assert [d["action"] for d in result["done"]] == ["start"] * 4
    assert h.files[layout.env_file(3)] == (NEW, 0o644) and h.files[GATE] == ("gate v1\n", 0o755)
    assert all(u["UnitFileState"] == "enabled" for u in h.units.values()) and h.target == "enabled"


def test_a_target_enabled_before_docker_wanted_it_is_enabled_again_and_nothing_restarts():
    # hosts deployed before the target's WantedBy=docker.service: only systemctl enable links it
    h = ScriptedHost(3)
    h.docker_want = False
    target = os.path.join(layout.UNIT_DIR, layout.TARGET)
    h.files[target] = ("old target\n", 0o644)
    result = lifecycle.apply(h.host, want({i: OLD for i in range(3)}, files={target: ("new target\n", 0o644)}))
    assert result["failed"] is None and result["changed"]
    assert result["plan"]["enable"] == [layout.TARGET] and h.docker_want
    assert h.files[target] == ("new target\n", 0o644) and "systemctl daemon-reload" in h.log
    assert h.commands("restart") == [] and h.commands("start") == []


def test_a_new_firewall_script_is_written_and_restarts_no_instance():
    # isaac-sim-firewall-site and its library are the firewall unit's, not the instances'
    h = ScriptedHost(3)
    script = os.path.join(layout.LIBEXEC_DIR, layout.FIREWALL_SITE_SCRIPT)
    lib = os.path.join(layout.LIBEXEC_DIR, "site_firewall.py")
    files = {UNIT_FILE: ("unit v1\n", 0o644), GATE: ("gate v1\n", 0o755), script: ("v2\n", 0o644), lib: ("v2\n", 0o644)}
    h.files.update({UNIT_FILE: ("unit v1\n", 0o644), GATE: ("gate v1\n", 0o755)})
    result = lifecycle.apply(h.host, want({i: OLD for i in range(3)}, files=files))
    assert result["failed"] is None and result["changed"]
    assert h.files[script] == ("v2\n", 0o644) and h.files[lib] == ("v2\n", 0o644)
    assert h.commands("restart") == [] and h.commands("start") == [] and result["done"] == []


def test_the_target_is_started_by_docker_and_stops_with_it():
    text = unit_files.render_target("managed")
    assert "Requires=docker.service" in text and "WantedBy=multi-user.target docker.service" in text


def test_nothing_to_do_changes_nothing():
    h = ScriptedHost(4)
    result = lifecycle.apply(h.host, want({i: OLD for i in range(4)}))
    assert not result["changed"] and result["done"] == []
    assert [line for line in h.log if not line.startswith(READS)] == []


def test_a_changed_image_rolls_one_instance_at_a_time_with_a_soak_each():
    h = ScriptedHost(3)
    result = lifecycle.apply(h.host, want({i: NEW for i in range(3)}, soak=10))
    assert result["failed"] is None
    assert h.commands("restart") == [f"systemctl restart {layout.unit(i)}" for i in range(3)]
    assert all(d["action"] == "apply" and d["restart_s"] == 5 and d["soak_s"] >= 10 for d in result["done"])
    # each restart comes after the previous instance's soak: its counter is reset just before it
    assert h.log.index(f"systemctl reset-failed {layout.unit(1)}") > h.log.index(f"systemctl restart {layout.unit(0)}")


def test_a_never_ready_image_goes_back_and_leaves_the_others_untouched():
    h = ScriptedHost(4)
    result = lifecycle.apply(h.host, want({i: NEVER for i in range(4)}))
    failed = result["failed"]
    assert failed["id"] == 0 and failed["reason"].startswith("isaac-sim-0 was not ready within 20 s")
    assert failed["reason"].endswith("(last lines: loading scene)")
    assert failed["reverted"] is True and failed["reverted_to"] == "reg/isaac-sim:5.0.0" and failed["left"] == "running"
    assert result["untouched"] == [1, 2, 3]
    assert all(h.files[layout.env_file(i)][0] == OLD for i in range(4))
    assert h.commands("restart") == [f"systemctl restart {layout.unit(0)}"] * 2
    # the failed start left it activating (auto-restart): stopped before it is restarted on the old image
    assert f"systemctl stop {layout.unit(0)}" in h.log
    assert h.units[0]["ActiveState"] == "active"


def test_going_back_pins_the_previous_image_id_when_its_tag_moved():
    h = ScriptedHost(2, tags={"reg/isaac-sim:5.0.0": "sha256:moved"})
    lifecycle.apply(h.host, want({0: NEVER, 1: NEVER}))
    assert layout.parse(h.files[layout.env_file(0)][0])[layout.K_IMAGE] == "sha256:old"


def test_an_env_file_pinned_to_a_digest_goes_back_as_written():
    """Its deploy pinned the digest (image_pin.py): it runs that, whatever the tag names now."""
    h = ScriptedHost(1, tags={"reg/isaac-sim:5.0.0": "sha256:moved"})
    text = OLD + 'ISAAC_SIM_IMAGE_PINNED="reg/isaac-sim@sha256:' + "e" * 64 + '"\n'
    assert lifecycle.pinned(h.host, text) == text


def test_a_changed_shared_file_rolls_every_serving_instance_and_goes_back_with_it():
    h = ScriptedHost(3)
    ok = lifecycle.apply(h.host, want({i: OLD for i in range(3)}, files={UNIT_FILE: ("unit v2\n", 0o644)}))
    assert [d["action"] for d in ok["done"]] == ["restart"] * 3
    assert h.log.count("systemctl daemon-reload") == 1
    h = ScriptedHost(3)
    bad = lifecycle.apply(h.host, want({0: NEVER, 1: OLD, 2: OLD}, files={UNIT_FILE: ("unit v2\n", 0o644)}))
    assert bad["failed"]["id"] == 0 and bad["untouched"] == [1, 2]
    assert h.files[UNIT_FILE] == ("unit v1\n", 0o644)
    assert h.log.count("systemctl daemon-reload") == 2


def test_defer_running_changes_nothing_on_a_host_that_would_restart():
    h = ScriptedHost(2)
    result = lifecycle.apply(h.host, want({0: NEW, 1: NEW}, defer_running=True))
    assert result["deferred"] and not result["changed"] and result["plan"]["roll"] == [0, 1]
    assert h.files[layout.env_file(0)][0] == OLD and [x for x in h.log if not x.startswith(READS)] == []
    fresh = ScriptedHost(2, running=False)
    assert not lifecycle.apply(fresh.host, want({0: NEW, 1: NEW}, defer_running=True))["deferred"]


def test_defer_running_leaves_a_scale_down_of_serving_instances_to_the_batches():
    h = ScriptedHost(4)
    result = lifecycle.apply(h.host, want({}, remove=[0, 1, 2, 3], defer_running=True))
    assert result["deferred"] and not result["changed"] and h.commands("disable") == []
    assert all(u["ActiveState"] == "active" for u in h.units.values())
    # instances that no longer serve go at once
    h.units[3].update(ActiveState="failed", SubState="failed")
    result = lifecycle.apply(h.host, want({0: OLD, 1: OLD, 2: OLD}, remove=[3], defer_running=True))
    assert not result["deferred"] and result["removed"] == [3]


def test_a_rollout_whose_controller_went_away_stops_after_the_instance_in_hand():
    h = ScriptedHost(4)
    # the controller is gone once the first instance is done
    h.host.interrupted = lambda: "its controller stopped" if h.commands("restart") else ""
    result = lifecycle.apply(h.host, want({i: NEW for i in range(4)}))
    assert result["interrupted"] == "its controller stopped" and result["failed"] is None
    assert h.commands("restart") == [f"systemctl restart {layout.unit(0)}"]
    assert [d["id"] for d in result["done"]] == [0] and result["untouched"] == [1, 2, 3]
    assert all(h.units[i]["ActiveState"] == "active" for i in range(4))
    said = [line for line in h.log if line.startswith("logger -t isaac-sim-lifecycle")]
    assert said == [
        "logger -t isaac-sim-lifecycle rollout interrupted: its controller stopped; done: isaac-sim-0; "
        "left as they were: isaac-sim-1, isaac-sim-2, isaac-sim-3"
    ]


def test_a_rolling_restart_whose_controller_went_away_stops_too():
    h = ScriptedHost(3)
    h.host.interrupted = lambda: "gone" if len(h.commands("restart")) == 2 else ""
    result = lifecycle.restart_each(h.host, [0, 1, 2], 0)
    assert [d["id"] for d in result["done"]] == [0, 1] and result["untouched"] == [2]
    assert result["interrupted"] == "gone"


def test_a_new_instance_that_does_not_start_is_stopped_and_forgotten():
    h = ScriptedHost(2)
    h.units[2] = dict(h.units[0], ActiveState="inactive", UnitFileState="disabled")
    result = lifecycle.apply(h.host, want({0: OLD, 1: OLD, 2: NEVER}))
    assert (
        result["failed"]["id"] == 2 and result["failed"]["reverted"] is None and result["failed"]["left"] == "stopped"
    )
    assert layout.env_file(2) not in h.files and h.units[2]["ActiveState"] == "inactive"
    assert h.commands("restart") == []


def stopped_and_forgotten(h, i):
    """A new instance that did not start, as the lifecycle leaves it: stopped (no restart pending),
    never enabled, its env file gone."""
    return (
        layout.env_file(i) not in h.files
        and h.units[i]["ActiveState"] == "inactive"
        and h.units[i]["UnitFileState"] == "disabled"
        and i not in h.markers
    )


def test_two_new_instances_that_do_not_start_are_both_stopped_and_both_reported():
    # a scale-up from 2 to 4: the new ones start together and neither gets ready
    h = ScriptedHost(2)
    result = lifecycle.apply(h.host, want({0: OLD, 1: OLD, 2: NEVER, 3: NEVER}))
    assert h.commands("start") == ["systemctl start isaac-sim@2.service isaac-sim@3.service"]
    # the second is handled as the first: not left restarting on its new env file
    assert stopped_and_forgotten(h, 2) and stopped_and_forgotten(h, 3)
    assert h.commands("stop") == ["systemctl stop isaac-sim@2.service isaac-sim@3.service"]
    failed = result["failures"]
    assert [f["id"] for f in failed] == [2, 3] and result["failed"] == failed[0]
    for f in failed:
        assert f["reason"].startswith(f"isaac-sim-{f['id']} was not ready within 20 s")
        assert f["reverted"] is None and f["left"] == "stopped"
    assert result["done"] == [] and result["untouched"] == []
    # the serving ones are never touched
    assert all(h.units[i]["ActiveState"] == "active" and h.files[layout.env_file(i)][0] == OLD for i in (0, 1))
    assert h.commands("restart") == []


def test_a_new_instance_that_gets_ready_beside_one_that_does_not_is_done_and_left_serving():
    # a first deploy: instance 0 never gets ready, instance 1 does
    h = ScriptedHost(2, running=False)
    result = lifecycle.apply(h.host, want({0: NEVER, 1: NEW}))
    assert result["done"] == [{"id": 1, "action": "start", "restart_s": 0.0, "soak_s": 0.0}]
    assert result["failed"]["id"] == 0 and result["failed"]["left"] == "stopped" and result["untouched"] == []
    assert [f["id"] for f in result["failures"]] == [0]
    assert stopped_and_forgotten(h, 0) and h.commands("stop") == [f"systemctl stop {layout.unit(0)}"]
    assert h.units[1]["ActiveState"] == "active" and h.files[layout.env_file(1)][0] == NEW and 1 in h.markers


def test_of_three_new_instances_the_middle_one_fails_and_the_others_are_done():
    h = ScriptedHost(1)
    result = lifecycle.apply(h.host, want({0: OLD, 1: NEW, 2: NEVER, 3: NEW}))
    assert [d["id"] for d in result["done"]] == [1, 3] and all(d["action"] == "start" for d in result["done"])
    assert result["failed"]["id"] == 2 and result["failed"]["reason"].startswith("isaac-sim-2 was not ready")
    assert [f["id"] for f in result["failures"]] == [2] and result["untouched"] == []
    assert stopped_and_forgotten(h, 2) and h.commands("stop") == [f"systemctl stop {layout.unit(2)}"]
    assert all(h.units[i]["ActiveState"] == "active" for i in (0, 1, 3))
    assert h.files[layout.env_file(3)][0] == NEW and h.files[layout.env_file(0)][0] == OLD


def test_a_first_deploy_that_fails_in_part_keeps_the_files_its_ready_instances_run_on_and_enables_them():
    h = ScriptedHost(2, running=False)
    result = lifecycle.apply(h.host, want({0: NEVER, 1: NEW}))
    assert [d["id"] for d in result["done"]] == [1] and result["failed"]["id"] == 0
    # the unit and the scripts instance 1 runs on had no earlier version: they stay, and so does it
    assert h.files[UNIT_FILE] == ("unit v1\n", 0o644) and h.files[GATE] == ("gate v1\n", 0o755)
    assert f"rm {UNIT_FILE}" not in h.log and h.log.count("systemctl daemon-reload") == 1
    # enabled, as a deploy that completes leaves it: a reboot brings it back
    assert h.units[1]["UnitFileState"] == "enabled" and h.target == "enabled"
    assert stopped_and_forgotten(h, 0)
    # with none ready, nothing runs on them: they go, as before
    h = ScriptedHost(2, running=False)
    lifecycle.apply(h.host, want({0: NEVER, 1: NEVER}))
    assert UNIT_FILE not in h.files and GATE not in h.files and h.commands("enable") == []


def test_new_instances_that_fail_beside_serving_ones_put_the_changed_unit_back():
    h = ScriptedHost(1)
    result = lifecycle.apply(h.host, want({0: OLD, 1: NEW, 2: NEVER}, files={UNIT_FILE: ("unit v2\n", 0o644)}))
    assert [d["id"] for d in result["done"]] == [1] and result["failed"]["id"] == 2 and result["untouched"] == [0]
    # instance 0 still runs on unit v1, and was not rolled: the unit goes back to v1
    assert h.files[UNIT_FILE] == ("unit v1\n", 0o644) and h.units[0]["ActiveState"] == "active"
    assert h.units[1]["ActiveState"] == "active" and stopped_and_forgotten(h, 2)


def test_scale_down_goes_first_and_keeps_data_unless_purge():
    h = ScriptedHost(4)
    result = lifecycle.apply(h.host, want({0: NEW, 1: NEW}, remove=[2, 3]))
    assert result["failed"] is None
    assert h.log.index("systemctl disable --now isaac-sim@2.service isaac-sim@3.service") < h.log.index(
        "systemctl restart isaac-sim@0.service"
    )
    assert layout.env_file(2) not in h.files and "rm /var/lib/isaac-sim/instance-2" not in h.log
    h = ScriptedHost(4)
    lifecycle.apply(h.host, want({0: OLD, 1: OLD}, remove=[2, 3], purge=True))
    assert "rm /var/lib/isaac-sim/instance-3" in h.log


def test_an_instance_stuck_activating_on_old_settings_is_stopped_then_started():
    h = ScriptedHost(2)
    h.units[1].update(ActiveState="activating", SubState="start-post")
    result = lifecycle.apply(h.host, want({0: OLD, 1: NEW}))
    assert result["plan"]["start"] == [1] and result["failed"] is None
    assert h.log.index("systemctl stop isaac-sim@1.service") < h.log.index("systemctl start isaac-sim@1.service")


def test_an_instance_coming_back_on_its_settings_is_waited_for_not_stopped():
    h = ScriptedHost(2)
    # as after a Docker restart: the unit is starting again on the settings it has
    h.units[1].update(ActiveState="activating", SubState="start-post")
    result = lifecycle.apply(h.host, want({0: OLD, 1: OLD}))
    assert result["plan"]["start"] == [1] and result["failed"] is None
    assert "systemctl stop isaac-sim@1.service" not in h.log and "systemctl start isaac-sim@1.service" in h.log


def test_check_mode_reports_and_changes_nothing():
    h = ScriptedHost(2)
    result = lifecycle.apply(h.host, want({0: NEW, 1: OLD}, remove=[3]), check=True)
    assert result["changed"] and result["plan"]["roll"] == [0] and result["plan"]["remove"] == [3]
    assert h.files[layout.env_file(0)][0] == OLD and [x for x in h.log if not x.startswith(READS)] == []


def test_rolling_restart_soaks_and_stops_at_a_crash():
    h = ScriptedHost(3)
    h.files[layout.env_file(1)] = (CRASHY, 0o644)
    result = lifecycle.restart_each(h.host, [0, 1, 2], soak_seconds=10)
    assert [d["id"] for d in result["done"]] == [0]
    assert "restarted during the soak" in result["failed"]["reason"] and result["untouched"] == [2]


def test_summary_names_what_was_rolled_reverted_and_untouched():
    outcomes = {
        "a": {"done": [{"id": 0, "action": "apply"}], "failed_instance": None},
        "b": {
            "failed": True,
            "done": [],
            "failed_instance": {
                "id": 0,
                "reason": "not ready",
                "reverted": True,
                "reverted_to": "img:1",
                "left": "running",
            },
            "untouched": [1, 2],
        },
        "c": {},
    }
    lines = lifecycle.summary(outcomes, ["a", "b", "c"])
    assert lines[0] == "rolled: a: isaac-sim-0"
    assert "b: isaac-sim-0 (not ready) - back on img:1, ready" in lines[1]
    assert "b: isaac-sim-1, isaac-sim-2" in lines[2] and "c: every instance (not reached)" in lines[2]
    assert lines[-1] == "stopped: isaac-sim-0 on b: not ready"


def ports_env(image, signal, stream):
    return env(image, "sha256:x", f"{layout.K_PORT_PREFIX}SIGNAL={signal}\n{layout.K_PORT_PREFIX}STREAM={stream}\n")


def test_a_port_layout_change_rolls_in_an_order_where_no_instance_starts_on_a_held_port():
    # stride 1 -> 2 with stream next to signal: new instance 1 wants ports old 2 and 3 still hold
    old = {i: {49100 + i, 47998 + i} for i in range(4)}
    new = {i: {49100 + 2 * i, 49101 + 2 * i} for i in range(4)}
    steps, notes = lifecycle.port_order(old, new, [0, 1, 2, 3], [])
    assert steps == [("roll", 2), ("roll", 3), ("roll", 1), ("roll", 0)] and notes == []
    h = ScriptedHost(4)
    for i in range(4):
        h.files[layout.env_file(i)] = (ports_env("reg/isaac-sim:5.0.0", 49100 + i, 47998 + i), 0o644)
    result = lifecycle.apply(
        h.host, want({i: ports_env("reg/isaac-sim:5.0.0", 49100 + 2 * i, 49101 + 2 * i) for i in range(4)})
    )
    assert [d["id"] for d in result["done"]] == [2, 3, 1, 0] and result["failed"] is None
    assert result["plan"]["order"] == ["roll 2", "roll 3", "roll 1", "roll 0"]


def test_a_port_layout_change_stops_before_a_held_instance_whose_ports_another_moves_to():
    h = ScriptedHost(4)
    for i in range(4):
        h.files[layout.env_file(i)] = (ports_env("reg/isaac-sim:5.0.0", 49100 + i, 47998 + i), 0o644)
    lifecycle.lend(h.host, 2, "session-olga")
    result = lifecycle.apply(
        h.host, want({i: ports_env("reg/isaac-sim:5.0.0", 49100 + 2 * i, 49101 + 2 * i) for i in range(4)})
    )
    # instance 1 moves to 49102-49103, and held instance 2 keeps 49102: nothing moves before it
    assert result["failed"]["id"] == 2 and "port layout change" in result["failed"]["reason"]
    assert "it is held by session olga, which it serves until the session ends" in result["failed"]["reason"]
    assert result["done"] == [] and result["left"] == [] and sorted(result["untouched"]) == [0, 1, 3]
    assert h.commands("restart") == []


def test_instances_that_swap_ports_are_stopped_first_and_the_plan_says_so():
    old = {0: {49100}, 1: {49101}}
    new = {0: {49101}, 1: {49100}}
    steps, notes = lifecycle.port_order(old, new, [0, 1], [])
    assert steps == [("stop", [1]), ("roll", 0), ("start", [1])]
    assert notes == [
        "isaac-sim-1 stopped before isaac-sim-0 to free port(s) 49101: the host is below N-1 until they "
        "start again on their new ports"
    ]


def test_a_new_instance_whose_ports_are_still_held_starts_after_the_roll():
    old = {0: {49100}, 1: set()}
    new = {0: {49200}, 1: {49100}}
    steps, _rest = lifecycle.port_order(old, new, [0], [1])
    assert steps == [("roll", 0), ("start", [1])]


def user_env(image, user):
    return env(image, "sha256:x", f"{layout.K_DOCKER_ARGS}={layout.quote(layout.join_args(['--user=' + user]))}\n")


def test_a_new_container_user_gets_the_caches_while_the_instance_is_down():
    h = ScriptedHost(2)
    for i in range(2):
        h.files[layout.env_file(i)] = (user_env("reg/isaac-sim:4.5.0", "0:0"), 0o644)
    handed = []

    def reown(i):
        handed.append(i)
        h.log.append(f"reown {i}")

    new = {i: user_env("reg/isaac-sim:5.1.0", "1234:1234") for i in range(2)}
    result = lifecycle.apply(h.host, want(new, reown=reown))
    assert result["failed"] is None and handed == [0, 1]
    # stopped, handed over, started: never while the old user can still write
    first = h.log.index("reown 0")
    assert h.log[first - 1] == "systemctl stop isaac-sim@0.service"
    assert h.log[first + 1] == "systemctl start isaac-sim@0.service"
    # the same user keeps the plain restart
    same = ScriptedHost(1)
    lifecycle.apply(same.host, want({0: NEW}, reown=reown))
    assert handed == [0, 1] and same.commands("restart") == ["systemctl restart isaac-sim@0.service"]


# --- companions: an instance and its companions change as one ---

VIEWER_UNIT = "/etc/systemd/system/isaac-sim-viewer@.service"
VIEWER = f"{layout.K_IMAGE}={layout.quote('reg/viewer:1')}\n"
VIEWER_2 = f"{layout.K_IMAGE}={layout.quote('reg/viewer:2')}\n"
BROKEN = f"{layout.K_IMAGE}={layout.quote('reg/viewer:broken')}\n"


def with_viewer(n=2, running=True):
    """A host whose instances each run the viewer companion."""
    h = ScriptedHost(n, running=running)
    if running:
        h.files[VIEWER_UNIT] = ("viewer unit v1\n", 0o644)
        for i in range(n):
            h.files[layout.companion_env_file(i, "viewer")] = (VIEWER, 0o644)
            h.comps[(i, "viewer")] = {
                "ActiveState": "active",
                "SubState": "running",
                "NRestarts": 0,
                "UnitFileState": "enabled",
            }
            h.comp_markers.add((i, "viewer"))
    return h


def viewer_want(instances, comps, found=None, files=None, **over):
    shared = files or {
        UNIT_FILE: ("unit v1\n", 0o644),
        GATE: ("gate v1\n", 0o755),
        VIEWER_UNIT: ("viewer unit v1\n", 0o644),
    }
    return want(instances, files=shared, companions=comps, companions_found=found or {}, **over)


def test_a_fresh_instance_starts_first_then_its_companions_all_together_enabled():
    h = with_viewer(2, running=False)
    result = lifecycle.apply(h.host, viewer_want({0: NEW, 1: NEW}, {0: {"viewer": VIEWER}, 1: {"viewer": VIEWER}}))
    assert result["failed"] is None
    starts = h.commands("start")
    assert starts == [
        "systemctl start isaac-sim@0.service isaac-sim@1.service",
        "systemctl start isaac-sim-viewer@0.service isaac-sim-viewer@1.service",
    ]
    # enabled before the start: the instance's unit wants it (WantedBy=), so a reboot brings it back
    assert h.log.index("systemctl enable isaac-sim-viewer@0.service") < h.log.index(starts[0])
    assert all(c["ActiveState"] == "active" and c["UnitFileState"] == "enabled" for c in h.comps.values())


def test_new_instances_that_fail_together_each_take_their_companions_down_and_disabled():
    # instance 0 never gets ready; instance 1 does, but its companion does not start
    h = with_viewer(2, running=False)
    result = lifecycle.apply(h.host, viewer_want({0: NEVER, 1: NEW}, {0: {"viewer": VIEWER}, 1: {"viewer": BROKEN}}))
    for i in (0, 1):
        assert stopped_and_forgotten(h, i) and layout.companion_env_file(i, "viewer") not in h.files
        assert h.comp(i, "viewer")["UnitFileState"] == "disabled" and h.comp(i, "viewer")["ActiveState"] == "inactive"
        assert f"systemctl disable --now isaac-sim-viewer@{i}.service" in h.log
    assert [f["id"] for f in result["failures"]] == [0, 1] and result["done"] == []
    assert "companion isaac-sim-1-viewer did not start" in result["failures"][1]["reason"]
    # the shared files go back once, after both
    assert VIEWER_UNIT not in h.files and h.log.count(f"rm {VIEWER_UNIT}") == 1


def test_a_changed_companion_rolls_its_instance_and_nothing_is_done_when_all_is_current():
    h = with_viewer(2)
    same = lifecycle.apply(
        h.host,
        viewer_want({0: OLD, 1: OLD}, {0: {"viewer": VIEWER}, 1: {"viewer": VIEWER}}, {0: ["viewer"], 1: ["viewer"]}),
    )
    assert not same["changed"]
    result = lifecycle.apply(
        h.host,
        viewer_want(
            {0: OLD, 1: OLD}, {0: {"viewer": VIEWER_2}, 1: {"viewer": VIEWER_2}}, {0: ["viewer"], 1: ["viewer"]}
        ),
    )
    assert result["failed"] is None and result["plan"]["roll"] == [0, 1]
    assert h.commands("restart") == ["systemctl restart isaac-sim@0.service", "systemctl restart isaac-sim@1.service"]
    assert h.files[layout.companion_env_file(1, "viewer")][0] == VIEWER_2
    assert h.comps[(1, "viewer")]["ActiveState"] == "active"


def test_a_companion_that_does_not_start_reverts_its_instance_and_stops_the_roll():
    h = with_viewer(3)
    result = lifecycle.apply(
        h.host,
        viewer_want(
            {i: NEW for i in range(3)},
            {i: {"viewer": BROKEN} for i in range(3)},
            {i: ["viewer"] for i in range(3)},
        ),
    )
    failed = result["failed"]
    assert failed["id"] == 0 and "companion isaac-sim-0-viewer did not start" in failed["reason"]
    assert "stopped before it was ready" in failed["reason"]
    assert failed["reverted"] is True and failed["left"] == "running" and result["untouched"] == [1, 2]
    # the instance and its companion are back on their previous files, running
    assert h.files[layout.env_file(0)][0] == OLD and h.files[layout.companion_env_file(0, "viewer")][0] == VIEWER
    assert h.comps[(0, "viewer")]["ActiveState"] == "active" and h.units[0]["ActiveState"] == "active"
    assert h.files[layout.env_file(1)][0] == OLD


def test_a_companion_taken_away_is_stopped_and_disabled_before_its_file_and_template_go():
    h = with_viewer(2)
    result = lifecycle.apply(
        h.host,
        want(
            {0: OLD, 1: OLD},
            files={UNIT_FILE: ("unit v1\n", 0o644), GATE: ("gate v1\n", 0o755), VIEWER_UNIT: (None, None)},
            companions={},
            companions_found={0: ["viewer"], 1: ["viewer"]},
        ),
    )
    assert result["failed"] is None and result["plan"]["roll"] == [0, 1]
    disable = h.log.index("systemctl disable --now isaac-sim-viewer@0.service")
    assert disable < h.log.index(f"rm {layout.companion_env_file(0, 'viewer')}")
    assert layout.companion_env_file(1, "viewer") not in h.files
    # the template goes last, once no instance has the companion
    assert VIEWER_UNIT not in h.files
    assert h.log.index(f"rm {VIEWER_UNIT}") > h.log.index("systemctl restart isaac-sim@1.service")
    assert all(c["ActiveState"] == "inactive" and c["UnitFileState"] == "disabled" for c in h.comps.values())


def test_a_companion_down_beside_a_serving_instance_is_started_without_restarting_the_instance():
    h = with_viewer(2)
    h.comps[(1, "viewer")].update(ActiveState="failed", SubState="failed")
    h.comp_markers.discard((1, "viewer"))
    result = lifecycle.apply(
        h.host,
        viewer_want({0: OLD, 1: OLD}, {0: {"viewer": VIEWER}, 1: {"viewer": VIEWER}}, {0: ["viewer"], 1: ["viewer"]}),
    )
    assert result["failed"] is None and result["changed"]
    assert result["plan"]["companions"] == {1: ["isaac-sim-viewer@1.service"]}
    assert h.commands("restart") == [] and h.commands("start") == ["systemctl start isaac-sim-viewer@1.service"]
    assert h.comps[(1, "viewer")]["ActiveState"] == "active"


def test_scale_down_takes_the_companions_with_their_instance():
    h = with_viewer(3)
    lifecycle.apply(
        h.host,
        viewer_want({0: OLD}, {0: {"viewer": VIEWER}}, {i: ["viewer"] for i in range(3)}, remove=[1, 2]),
    )
    assert (
        "systemctl disable --now isaac-sim-viewer@1.service isaac-sim-viewer@2.service isaac-sim@1.service "
        "isaac-sim@2.service" in h.log
    )
    assert layout.companion_env_file(2, "viewer") not in h.files and layout.companion_env_file(0, "viewer") in h.files
    assert VIEWER_UNIT in h.files


def test_a_rolling_restart_brings_each_instance_back_with_its_companions():
    h = with_viewer(2)
    result = lifecycle.restart_each(h.host, [0, 1], 0, companions={0: ["viewer"], 1: ["viewer"]})
    assert result["failed"] is None
    assert h.log.index("systemctl start isaac-sim-viewer@0.service") < h.log.index(
        "systemctl restart isaac-sim@1.service"
    )
    assert all(c["ActiveState"] == "active" for c in h.comps.values())


def test_a_new_companion_that_fails_leaves_before_its_new_template_is_taken_back():
    h = ScriptedHost(2)
    result = lifecycle.apply(
        h.host,
        viewer_want({0: OLD, 1: OLD}, {0: {"viewer": BROKEN}, 1: {"viewer": BROKEN}}),
    )
    assert result["failed"]["id"] == 0 and result["untouched"] == [1]
    assert h.log.index("systemctl disable --now isaac-sim-viewer@0.service") < h.log.index(f"rm {VIEWER_UNIT}")
    assert VIEWER_UNIT not in h.files and layout.companion_env_file(0, "viewer") not in h.files
    assert h.units[0]["ActiveState"] == "active"
    # its failed start is not left listed (host degraded, a stray in status)
    assert "systemctl reset-failed isaac-sim-viewer@0.service" in h.log
    assert h.comp(0, "viewer")["ActiveState"] != "failed"


def test_a_failed_companion_left_by_an_earlier_run_is_cleared_and_a_wanted_one_is_not():
    h = ScriptedHost(2)
    h.comp(0, "bridge").update(ActiveState="failed", SubState="failed")
    result = lifecycle.apply(h.host, want({0: OLD, 1: OLD}))
    assert result["changed"] and result["plan"]["cleared"] == ["isaac-sim-bridge@0.service"]
    assert h.comp(0, "bridge")["ActiveState"] == "inactive" and h.commands("restart") == []
    # a companion the plan has is the lifecycle's to start again, never merely cleared
    h = ScriptedHost(2)
    h.comp(1, "viewer").update(ActiveState="failed", SubState="failed")
    assert lifecycle.leftover_companions(h.host, {1: ["viewer"]}) == []


def test_moving_to_own_addresses_keeps_the_port_numbers_and_blocks_nobody():
    text = env("reg/isaac-sim:5.1.0", "sha256:x", f"{layout.K_PORT_PREFIX}SIGNAL=49100\n{layout.K_ADDRESS}=10.0.0.51\n")
    assert lifecycle.ports_of(text) == {("10.0.0.51", 49100)}
    old = {i: {("", 49100 + i)} for i in range(4)}
    new = {i: {(f"10.0.0.{50 + i}", 49100)} for i in range(4)}
    steps, notes = lifecycle.port_order(old, new, [0, 1, 2, 3], [])
    assert steps == [("roll", 0), ("roll", 1), ("roll", 2), ("roll", 3)] and notes == []
    # two instances that swap addresses: the same port at the same address is held
    steps, notes = lifecycle.port_order(
        {0: {("10.0.0.50", 49100)}, 1: {("10.0.0.51", 49100)}},
        {0: {("10.0.0.51", 49100)}, 1: {("10.0.0.50", 49100)}},
        [0, 1],
        [],
    )
    assert steps[0] == ("stop", [1]) and "port(s) 10.0.0.51:49100" in notes[0]


def test_new_ports_are_reserved_before_an_instance_binds_one_and_the_old_ones_leave_at_the_end():
    h = ScriptedHost(2)
    h.files[reserved_ports.PROC] = ("9000 49100-49101\n".replace(" ", ","), 0o644)
    h.files[reserved_ports.CONF] = (reserved_ports.conf({9000, 49100, 49101}, {49100, 49101}, "m"), 0o644)
    seen = []
    start = h._start

    def spy(i):
        seen.append(h.files[reserved_ports.PROC][0])
        return start(i)

    h._start = spy
    result = lifecycle.apply(h.host, want({i: NEW for i in range(2)}, reserve=[49104, 49105], managed="m"))
    assert result["failed"] is None and result["plan"]["reserved_ports"]
    # while the instances roll, both layouts are reserved
    assert seen and all(s == "9000,49100-49101,49104-49105\n" for s in seen)
    assert h.files[reserved_ports.PROC][0] == "9000,49104-49105\n"
    assert reserved_ports.ours(h.files[reserved_ports.CONF][0]) == {49104, 49105}
    again = lifecycle.apply(h.host, want({i: NEW for i in range(2)}, reserve=[49104, 49105], managed="m"))
    assert not again["changed"] and not again["plan"]["reserved_ports"]


TCP_HEADER = "  sl  local_address rem_address   st tx_queue rx_queue tr tm->when retrnsmt   uid  timeout inode\n"


def tcp_line(port: int, state: str) -> str:
    return f"   0: 050011AC:{port:04X} 010011AC:15B3 {state} 00000000:00000000 00:00000000 00000000 0 0 0 1\n"


def test_an_outgoing_connection_s_time_wait_on_a_new_port_is_waited_out_before_any_instance_binds_it():
    # a pull just before the change left 49104 in TIME_WAIT: reserving it does not free it
    h = ScriptedHost(2)
    h.files[reserved_ports.PROC] = ("49100-49101\n", 0o644)
    tcp = TCP_HEADER + tcp_line(49104, "06") + tcp_line(49100, "0A")
    h.files["/proc/net/tcp"] = (tcp, 0o444)
    starts = []
    start = h._start

    def spy(i):
        starts.append(h.clock)
        return start(i)

    h._start = spy
    real_sleep = h.sleep

    def sleep(s):
        real_sleep(s)
        if h.clock >= 1030:  # its 60 s end
            h.files["/proc/net/tcp"] = (TCP_HEADER + tcp_line(49100, "0A"), 0o444)

    h.host.sleep = sleep
    result = lifecycle.apply(h.host, want({i: NEW for i in range(2)}, reserve=[49104, 49105], managed="m"))
    assert result["failed"] is None and result["lingering"] == []
    assert starts and min(starts) >= 1030
    # a listener on an old port is an instance's own, never waited for
    assert reserved_ports.lingering([TCP_HEADER + tcp_line(49100, "0A")], {49100}) == set()
    assert reserved_ports.lingering([TCP_HEADER + tcp_line(49104, "01"), None], {49104, 49105}) == {49104}
    # a connected UDP socket holds its port; an unbound-to-peer one is a listener (the plan refuses those)
    udp = [TCP_HEADER + tcp_line(49105, "01") + tcp_line(49107, "07")]
    assert reserved_ports.lingering([], {49105, 49107}, udp) == {49105}


def test_a_port_held_past_the_limit_is_said_and_the_roll_goes_on_to_its_own_verdict():
    h = ScriptedHost(2)
    h.files[reserved_ports.PROC] = ("\n", 0o644)
    h.files["/proc/net/tcp"] = (TCP_HEADER + tcp_line(49105, "01"), 0o444)
    result = lifecycle.apply(h.host, want({i: NEW for i in range(2)}, reserve=[49104, 49105], managed="m"))
    assert result["lingering"] == [49105] and result["failed"] is None


def test_reserved_ports_alone_are_a_change_that_check_mode_reports_without_writing():
    h = ScriptedHost(2)
    h.files[reserved_ports.PROC] = ("\n", 0o644)
    result = lifecycle.apply(h.host, want({i: OLD for i in range(2)}, reserve=[49100, 49101]), check=True)
    assert result["changed"] and result["plan"]["reserved_ports"]
    assert h.files[reserved_ports.PROC][0] == "\n" and reserved_ports.CONF not in h.files
    result = lifecycle.apply(h.host, want({i: OLD for i in range(2)}, reserve=[49100, 49101]))
    assert result["changed"] and h.commands("restart") == [] and h.commands("start") == []
    assert h.files[reserved_ports.PROC][0] == "49100-49101\n"


def test_a_read_only_kernel_setting_is_an_error_that_says_the_fix():
    h = ScriptedHost(1)
    h.files[reserved_ports.PROC] = ("\n", 0o644)
    real = h.host.write

    def write(path, text, mode):
        if path == reserved_ports.PROC:
            raise OSError(30, "Read-only file system")
        real(path, text, mode)

    h.host.write = write
    try:
        lifecycle.reserve(h.host, [49100], "m", grow=False)
    except OSError as exc:
        assert "docker run --sysctl net.ipv4.ip_local_reserved_ports" in str(exc)
    else:
        raise AssertionError("no error")


def test_a_drained_host_lends_nothing_new_and_what_it_lent_goes_on():
    h = ScriptedHost(2)
    assert lifecycle.lend(h.host, 0, "run-a") is None
    h.files[layout.DRAINED] = ('{"by": "olga (token ops)", "at": 1795000000}', 0o600)
    with pytest.raises(lifecycle.DrainedError) as exc:
        lifecycle.lend(h.host, 1, "run-b", wait_s=30)
    assert str(exc.value).startswith("the host is drained (by olga (token ops) at 2026-11-18 ")
    assert "Fix: undrain it" in str(exc.value) and lifecycle.lent_to(h.host, 1) is None
    # the loan made before goes on, and ends as any loan does
    assert lifecycle.lent_to(h.host, 0) == "run-a" and lifecycle.give_back(h.host, 0, "run-a") is None
    h.files[layout.DRAINED] = ("not json", 0o600)
    with pytest.raises(lifecycle.DrainedError, match="its record unreadable"):
        lifecycle.lend(h.host, 1, "run-b")
    del h.files[layout.DRAINED]
    assert lifecycle.lend(h.host, 1, "run-b") is None


def test_a_loan_ends_restarted_and_ready_before_the_instance_is_free():
    h = ScriptedHost(2)
    assert lifecycle.lend(h.host, 1, "run-a") is None and lifecycle.lent_to(h.host, 1) == "run-a"
    order = []
    start = h._start

    def spy(i):
        order.append(("start", i, lifecycle.lent_to(h.host, i)))
        return start(i)

    h._start = spy
    assert lifecycle.give_back(h.host, 1, "run-a") is None
    # restarted while still lent: no one could borrow it half-way
    assert order == [("start", 1, "run-a")] and lifecycle.lent_to(h.host, 1) is None
    assert h.log.index(f"systemctl restart {layout.unit(1)}") < h.log.index(f"rm {layout.lent_marker(1)}")


def test_a_claim_that_fails_restarts_nothing_and_a_waiting_run_gets_the_instance_once_it_is_back():
    h = ScriptedHost(2)
    assert lifecycle.lend(h.host, 0, "run-a") is None
    # run-b waits 30 s; run-a ends 10 s into the wait
    slept = []

    def sleep(s):
        slept.append(s)
        h.clock += s
        if len(slept) == 10:
            assert lifecycle.give_back(h.host, 0, "run-a") is None

    h.host.sleep = sleep
    assert lifecycle.lend(h.host, 0, "run-b", wait_s=30) is None and lifecycle.lent_to(h.host, 0) == "run-b"
    # a third run gives up at its bound, and restarts nothing
    restarts = len(h.commands("restart"))
    assert lifecycle.lend(h.host, 0, "run-c", wait_s=5) == "run-b"
    assert len(h.commands("restart")) == restarts and lifecycle.lent_to(h.host, 0) == "run-b"
    # a give-back by a run that does not hold it touches nothing
    assert "lent to run-b, not to run-c" in lifecycle.give_back(h.host, 0, "run-c")
    assert len(h.commands("restart")) == restarts


def test_a_rolling_restart_leaves_an_instance_lent_to_a_run_and_restarts_the_others():
    h = ScriptedHost(3)
    lifecycle.lend(h.host, 1, "run-a")
    result = lifecycle.restart_each(h.host, [0, 1, 2], 0)
    assert [d["id"] for d in result["done"]] == [0, 2] and result["untouched"] == [] and result["failed"] is None
    assert result["left"] == [{"id": 1, "holder": "run-a"}]
    assert h.commands("restart") == [f"systemctl restart {layout.unit(i)}" for i in (0, 2)]
    # a dry run says the same
    dry = lifecycle.restart_each(h.host, [0, 1, 2], 0, check=True)
    assert [d["id"] for d in dry["done"]] == [0, 2] and dry["left"] == [{"id": 1, "holder": "run-a"}]


def test_a_rolling_restart_waits_for_a_holder_up_to_its_bound_and_restarts_what_was_given_back():
    h = ScriptedHost(2)
    lifecycle.lend(h.host, 0, "session-olga")
    waited = []

    def sleep(s):
        waited.append(s)
        h.clock += s
        if len(waited) == 5:  # given back (restarted, then free) 5 s into the wait
            assert lifecycle.give_back(h.host, 0, "session-olga") is None

    h.host.sleep = sleep
    result = lifecycle.restart_each(h.host, [0, 1], 0, held_wait=30)
    assert [d["id"] for d in result["done"]] == [0, 1] and result["left"] == [] and len(waited) == 5
    # held past the bound: waited for it, then left
    lifecycle.lend(h.host, 1, "session-piet")
    waited.clear()
    result = lifecycle.restart_each(h.host, [0, 1], 0, held_wait=3)
    assert result["left"] == [{"id": 1, "holder": "session-piet"}] and sum(waited) == 3


def sleeps(h, then=None) -> list:
    """The host's sleeps pass on its clock at once, each written down (then: called after each)."""
    waited = []

    def sleep(s):
        waited.append(s)
        h.clock += s
        if then is not None:
            then()

    h.host.sleep = sleep
    return waited


def test_a_controller_gone_while_a_rollout_waits_for_a_holder_ends_the_wait_and_the_rollout():
    h = ScriptedHost(3)
    lifecycle.lend(h.host, 0, "session-olga")
    waited = sleeps(h)
    h.host.interrupted = lambda: "the controller is gone" if len(waited) >= 2 else ""
    result = lifecycle.restart_each(h.host, [0, 1, 2], 0, held_wait=600)
    assert len(waited) == 2 and result["left"] == [{"id": 0, "holder": "session-olga"}]
    assert result["interrupted"] == "the controller is gone" and result["untouched"] == [1, 2]
    assert h.commands("restart") == []


def test_an_operator_s_end_sessions_warns_a_session_then_ends_its_claim_and_rolls_it_but_never_a_test_run_s():
    h = ScriptedHost(3)
    lifecycle.lend(h.host, 0, "session-olga")
    lifecycle.lend(h.host, 2, "run-a")
    notices = []
    waited = sleeps(h, lambda: notices.append(h.files.get(lifecycle.ending_marker(0), (None,))[0]))
    result = lifecycle.apply(h.host, want({i: NEW for i in range(3)}) | {"end_sessions": 120, "by": "olga"})
    # the session's marker said when and by whom the whole time it was warned, then its claim ended and it rolled
    assert json.loads(notices[0]) == {"at": round(1795000000 + 1000 + 120, 3), "by": "olga"}
    assert sum(waited) >= 120 and notices.count(notices[0]) == len(notices)
    assert [d["id"] for d in result["done"]] == [0, 1] and lifecycle.lent_to(h.host, 0) is None
    assert h.files[layout.env_file(0)][0] == NEW and lifecycle.ending_marker(0) not in h.files
    # a test run is left as always (held_wait 0)
    assert result["left"] == [{"id": 2, "holder": "run-a"}] and h.files[layout.env_file(2)][0] == OLD
    assert result["ended"] == [{"id": 0, "holder": "session-olga"}]
    assert "sessions ended for this rollout: h1: isaac-sim-0 (session-olga)" in lifecycle.summary(
        {"h1": result}, ["h1"]
    )


def test_a_controller_gone_while_a_session_is_warned_takes_the_warning_back_and_ends_nothing():
    h = ScriptedHost(2)
    lifecycle.lend(h.host, 0, "session-olga")
    waited = sleeps(h)
    h.host.interrupted = lambda: "the controller is gone" if len(waited) >= 3 else ""
    result = lifecycle.restart_each(h.host, [0, 1], 0, end_sessions=300)
    assert result["left"] == [{"id": 0, "holder": "session-olga"}] and result["interrupted"] == "the controller is gone"
    assert lifecycle.lent_to(h.host, 0) == "session-olga" and lifecycle.ending_marker(0) not in h.files
    assert h.commands("restart") == []


def test_a_deploy_leaves_an_instance_lent_to_a_run_as_it_was_and_rolls_the_others():
    h = ScriptedHost(3)
    lifecycle.lend(h.host, 1, "run-a")
    result = lifecycle.apply(h.host, want({i: NEW for i in range(3)}))
    assert result["failed"] is None and result["left"] == [{"id": 1, "holder": "run-a"}]
    assert [d["id"] for d in result["done"]] == [0, 2] and result["untouched"] == []
    # its settings too: the next deploy finds it changed and rolls it
    assert h.files[layout.env_file(1)][0] == OLD and h.units[1]["ActiveState"] == "active"
    assert f"systemctl restart {layout.unit(1)}" not in h.log
    assert lifecycle.apply(h.host, want({i: NEW for i in range(3)}), check=True)["plan"]["held"] == {1: "run-a"}
    # while it is held, a deploy again has nothing else to do: no change
    kept = lifecycle.apply(h.host, want({i: NEW for i in range(3)}))
    assert kept["changed"] is False and kept["left"] == [{"id": 1, "holder": "run-a"}] and kept["done"] == []
    lifecycle.unlend(h.host, 1, "run-a")
    again = lifecycle.apply(h.host, want({i: NEW for i in range(3)}))
    assert [d["id"] for d in again["done"]] == [1] and h.files[layout.env_file(1)][0] == NEW


def test_the_summary_lists_what_was_left_for_its_holder_and_is_no_failure():
    lines = lifecycle.summary(
        {"h1": {"done": [{"id": 0, "action": "restart"}], "left": [{"id": 1, "holder": "session-olga"}]}},
        ["h1"],
    )
    assert "left for their holders: h1: isaac-sim-1 (held by session-olga)" in lines
    assert lines[-1] == "completed: every host rolled"


def test_a_loan_whose_runner_died_is_ended_as_its_runner_would_have_before_the_next_run_gets_it():
    h = ScriptedHost(2)
    assert lifecycle.lend(h.host, 0, "run-a", pid=4242) is None  # /proc/4242 does not exist here
    assert h.files[f"{layout.lent_marker(0)}/run"][0] == "run-a\n4242\n"
    assert lifecycle.lend(h.host, 0, "run-b", pid=77) is None and lifecycle.lent_to(h.host, 0) == "run-b"
    # restarted clean on the dead run's behalf, before run-b got it
    assert h.commands("restart") == [f"systemctl restart {layout.unit(0)}"]
    # a live runner's loan is waited for, not taken
    live = lifecycle.Host(
        *[getattr(h.host, k) for k in ("run", "read", "write", "remove", "mode")],
        lambda p: p == "/proc/77" or h.host.exists(p),
        h.host.sleep,
        h.host.now,
        h.host.wall,
    )
    assert lifecycle.lend(live, 0, "run-c", pid=78) == "run-b"


@pytest.mark.parametrize(
    ("holder", "words"),
    [
        (
            "run-a",
            "it is lent to test run run-a, which it serves until the run ends. Fix: run again once the run is over",
        ),
        (
            "session-0123456789ab",
            "it is held by session 0123456789ab, which it serves until the session ends. "
            "Fix: run again once the session is over",
        ),
    ],
)
def test_a_scale_down_never_removes_an_instance_lent_to_a_run_or_held_by_a_session(holder, words):
    h = ScriptedHost(3)
    lifecycle.lend(h.host, 2, holder)
    result = lifecycle.apply(h.host, want({i: OLD for i in range(2)}, remove=[2]))
    assert result["failed"]["id"] == 2 and words in result["failed"]["reason"], result["failed"]["reason"]
    assert layout.env_file(2) in h.files and h.units[2]["ActiveState"] == "active"
    assert [line for line in h.log if line.startswith(("systemctl stop", "systemctl disable"))] == []


def test_a_process_finds_its_command_off_a_service_s_path_and_says_127_for_none(monkeypatch, tmp_path):
    monkeypatch.setenv("PATH", str(tmp_path))  # a service's PATH, without /usr/bin
    assert lifecycle.command_path("true") == shutil.which("true", path=lifecycle.SYSTEM_PATH)
    assert lifecycle.run_process(["printf", "a\\r\\nb"]) == (0, "a\nb", "")
    assert lifecycle.run_process(["no-such-command-here"]) == (127, "", "no-such-command-here: not found")


# --- a session's files: moved aside, whole, at its end (take_files)

FILE_COMMANDS = ("mv", "stat", "install", "rmdir")


def real_files(h, root, fail=None):
    """The scripted host with real files under `root`: mv, stat, install and rmdir run for real (each in
    its log), and exists looks there. fail: {command: (rc, out, err)} answered instead of running it."""
    scripted_run, scripted_exists = h.host.run, h.host.exists

    def run(argv):
        if argv[0] not in FILE_COMMANDS:
            return scripted_run(argv)
        h.log.append(" ".join(argv))
        if fail and argv[0] in fail:
            return fail[argv[0]]
        return lifecycle.run_process(argv)

    h.host.run = run
    h.host.exists = lambda p: os.path.exists(p) if p.startswith(str(root)) else scripted_exists(p)
    return h


def documents(root, i=0, mode=0o2751, files=None):
    """Instance i's Documents under root, with `files` {relative path: text} and a link to /etc/passwd."""
    docs = layout.documents_dir(i, str(root))
    os.makedirs(docs)
    os.chmod(docs, mode)
    for rel, text in (files or {"notes.txt": "mine\n", "scenes/a.usd": "#usda 1.0\n"}).items():
        os.makedirs(os.path.dirname(os.path.join(docs, rel)), exist_ok=True)
        with open(os.path.join(docs, rel), "w") as fh:
            fh.write(text)
    os.symlink("/etc/passwd", os.path.join(docs, "passwd"))
    return docs


def owner(path) -> tuple:
    st = os.lstat(path)
    return st.st_uid, st.st_gid, st.st_mode & 0o7777


def test_take_files_moves_a_session_s_documents_aside_whole_and_leaves_an_empty_one_like_it(tmp_path):
    h = real_files(ScriptedHost(2), tmp_path)
    docs = documents(tmp_path, 1)
    before = owner(docs)
    assert before[:2] == (os.getuid(), os.getgid())
    stash = lifecycle.take_files(h.host, 1, "session-ab12", str(tmp_path))
    assert stash == layout.files_dir("session-ab12", str(tmp_path)) == str(tmp_path / "files" / "session-ab12")
    # the very directory, renamed: its content, its link left a link (nothing read or followed)
    assert sorted(os.listdir(stash)) == ["notes.txt", "passwd", "scenes"] and owner(stash) == before
    assert os.readlink(os.path.join(stash, "passwd")) == "/etc/passwd"
    assert Path(stash, "scenes/a.usd").read_text() == "#usda 1.0\n"
    # an empty Documents the container user can write, as the old one was; the stashes are root's alone
    assert os.listdir(docs) == [] and owner(docs) == before
    assert owner(str(tmp_path / "files"))[2] == 0o700
    assert f"mv -T {docs} {stash}" in h.log


def test_take_files_leaves_a_test_run_s_an_empty_and_a_missing_documents_as_they_are(tmp_path):
    h = real_files(ScriptedHost(2), tmp_path)
    docs = documents(tmp_path, 0)
    assert lifecycle.take_files(h.host, 0, "run-a", str(tmp_path)) is None
    assert lifecycle.take_files(h.host, 0, "session-AB", str(tmp_path)) is None  # not a session's name
    assert sorted(os.listdir(docs)) == ["notes.txt", "passwd", "scenes"] and h.log == []
    # nothing to move: no directory (a test run's host)
    assert lifecycle.take_files(h.host, 1, "session-ab12", str(tmp_path)) is None and h.log == []
    # or an empty one (a give-back done before): moved all the same (what the container writes meanwhile
    # goes with it), and no stash of nothing is left
    empty = layout.documents_dir(1, str(tmp_path))
    os.makedirs(empty, mode=0o750)
    assert lifecycle.take_files(h.host, 1, "session-ab12", str(tmp_path)) is None
    assert os.listdir(empty) == [] and owner(empty)[2] == 0o750 and os.listdir(tmp_path / "files") == []


def test_take_files_again_after_a_crash_between_its_two_steps_only_makes_the_empty_documents(tmp_path):
    h = real_files(ScriptedHost(1), tmp_path)
    docs = documents(tmp_path, 0, mode=0o750)
    stash = layout.files_dir("session-ab12", str(tmp_path))
    os.makedirs(os.path.dirname(stash), mode=0o700)
    os.rename(docs, stash)  # moved, then the crash: no Documents
    assert lifecycle.take_files(h.host, 0, "session-ab12", str(tmp_path)) == stash
    assert os.listdir(docs) == [] and owner(docs) == owner(stash) == (os.getuid(), os.getgid(), 0o750)
    assert sorted(os.listdir(stash)) == ["notes.txt", "passwd", "scenes"]
    # and once more, all done: nothing to move, the stash as it was
    assert lifecycle.take_files(h.host, 0, "session-ab12", str(tmp_path)) is None
    assert os.listdir(tmp_path / "files") == ["session-ab12"] and os.listdir(docs) == []
    assert sorted(os.listdir(stash)) == ["notes.txt", "passwd", "scenes"]


def test_a_stash_the_door_has_not_taken_yet_is_never_written_over(tmp_path):
    h = real_files(ScriptedHost(2), tmp_path)
    first = layout.files_dir("session-ab12", str(tmp_path))
    os.makedirs(first)
    (tmp_path / "files" / "session-ab12" / "old.txt").write_text("kept\n")
    documents(tmp_path, 0, files={"new.txt": "newer\n"})
    assert lifecycle.take_files(h.host, 0, "session-ab12", str(tmp_path)) == first + ".2"
    documents(tmp_path, 1, files={"third.txt": "3\n"})
    os.rmdir(layout.documents_dir(0, str(tmp_path)))
    assert lifecycle.take_files(h.host, 1, "session-ab12", str(tmp_path)) == first + ".3"
    assert os.listdir(first) == ["old.txt"] and Path(first, "old.txt").read_text() == "kept\n"
    assert "new.txt" in os.listdir(first + ".2") and "third.txt" in os.listdir(first + ".3")
    # another session's stash is its own name
    documents(tmp_path, 0, files={"x": "y"})
    assert lifecycle.take_files(h.host, 0, "session-cd34", str(tmp_path)) == layout.files_dir(
        "session-cd34", str(tmp_path)
    )


def test_documents_on_another_filesystem_than_the_stashes_are_not_moved_since_mv_would_copy_them(tmp_path):
    h = real_files(ScriptedHost(1), tmp_path)
    docs = documents(tmp_path, 0)
    run = h.host.run

    def elsewhere(argv):
        rc, out, err = run(argv)
        if argv[0] == "stat" and len(argv) == 5:  # Documents and the stashes' root: another mount for the first
            lines = out.split("\n")
            out = "\n".join([lines[0], "/mnt/other"] + lines[2:])
        return rc, out, err

    h.host.run = elsewhere
    with pytest.raises(lifecycle.FilesError, match="not on one filesystem.*Fix: keep"):
        lifecycle.take_files(h.host, 0, "session-ab12", str(tmp_path))
    assert sorted(os.listdir(docs)) == ["notes.txt", "passwd", "scenes"]
    assert not any(line.startswith("mv") for line in h.log)


def test_a_give_back_moves_the_session_s_files_before_the_restart_and_frees_the_instance_after(tmp_path):
    h = real_files(ScriptedHost(2), tmp_path)
    docs = documents(tmp_path, 1)
    assert lifecycle.lend(h.host, 1, "session-ab12") is None
    assert lifecycle.give_back(h.host, 1, "session-ab12", data_root=str(tmp_path)) is None
    stash = layout.files_dir("session-ab12", str(tmp_path))
    moved = h.log.index(f"mv -T {docs} {stash}")
    made = next(n for n, line in enumerate(h.log) if line.startswith("install -d -o"))
    assert (
        moved < made < h.log.index(f"systemctl restart {layout.unit(1)}") < h.log.index(f"rm {layout.lent_marker(1)}")
    )
    assert os.listdir(docs) == [] and "notes.txt" in os.listdir(stash) and lifecycle.lent_to(h.host, 1) is None
    # a test run's give-back moves nothing
    documents(tmp_path, 0)
    lifecycle.lend(h.host, 0, "run-a")
    assert lifecycle.give_back(h.host, 0, "run-a", data_root=str(tmp_path)) is None
    assert "notes.txt" in os.listdir(layout.documents_dir(0, str(tmp_path)))


def test_a_give_back_whose_files_cannot_be_moved_restarts_the_instance_but_lends_it_to_nobody_else(tmp_path):
    h = real_files(ScriptedHost(2), tmp_path, fail={"mv": (1, "", "mv: cannot move: No space left on device")})
    docs = documents(tmp_path, 1)
    lifecycle.lend(h.host, 1, "session-ab12")
    why = lifecycle.give_back(h.host, 1, "session-ab12", data_root=str(tmp_path))
    assert f"could not move {docs} to {layout.files_dir('session-ab12', str(tmp_path))}" in why
    assert "No space left on device" in why and "Fix:" in why and why.endswith("isaac-sim-1 stays lent to session-ab12")
    # the person's container ended, their files where they were, and nobody else gets the instance
    assert h.commands("restart") == [f"systemctl restart {layout.unit(1)}"]
    assert "notes.txt" in os.listdir(docs) and lifecycle.lent_to(h.host, 1) == "session-ab12"
    assert lifecycle.lend(h.host, 1, "session-cd34") == "session-ab12"
    assert any(line.startswith("logger -t isaac-sim-lifecycle isaac-sim-1 stays lent") for line in h.log)
    # fixed, the same give-back again finishes it
    real_files(h, tmp_path)
    assert lifecycle.give_back(h.host, 1, "session-ab12", data_root=str(tmp_path)) is None
    assert lifecycle.lent_to(h.host, 1) is None and os.listdir(docs) == []


def test_a_rollout_that_ends_a_session_moves_its_files_aside_before_the_claim_ends_and_the_instance_rolls(tmp_path):
    h = real_files(ScriptedHost(2), tmp_path)
    docs = documents(tmp_path, 0)
    lifecycle.lend(h.host, 0, "session-olga")
    sleeps(h)
    result = lifecycle.restart_each(h.host, [0, 1], 0, end_sessions=60, data_root=str(tmp_path))
    assert result["ended"] == [{"id": 0, "holder": "session-olga"}] and [d["id"] for d in result["done"]] == [0, 1]
    stash = layout.files_dir("session-olga", str(tmp_path))
    assert (
        h.log.index(f"mv -T {docs} {stash}")
        < h.log.index(f"rm {layout.lent_marker(0)}")
        < h.log.index(f"systemctl restart {layout.unit(0)}")
    )
    assert os.listdir(docs) == [] and "notes.txt" in os.listdir(stash)
    # a deploy's rollout (apply) takes the data root from its plan
    docs = documents(tmp_path, 1)
    lifecycle.lend(h.host, 1, "session-piet")
    result = lifecycle.apply(h.host, want({0: NEW, 1: NEW}, data_root=str(tmp_path), end_sessions=30))
    assert result["ended"] == [{"id": 1, "holder": "session-piet"}] and os.listdir(docs) == []
    assert "notes.txt" in os.listdir(layout.files_dir("session-piet", str(tmp_path)))


def test_a_rollout_whose_session_files_cannot_be_moved_leaves_the_instance_to_the_session(tmp_path):
    h = real_files(ScriptedHost(2), tmp_path, fail={"mv": (1, "", "mv: Read-only file system")})
    docs = documents(tmp_path, 0)
    lifecycle.lend(h.host, 0, "session-olga")
    sleeps(h)
    result = lifecycle.restart_each(h.host, [0, 1], 0, end_sessions=60, data_root=str(tmp_path))
    assert result["left"] == [{"id": 0, "holder": "session-olga"}] and result["ended"] == []
    assert [d["id"] for d in result["done"]] == [1] and f"systemctl restart {layout.unit(0)}" not in h.log
    # the warning taken back: the session goes on, its files where they were
    assert lifecycle.lent_to(h.host, 0) == "session-olga" and lifecycle.ending_marker(0) not in h.files
    assert "notes.txt" in os.listdir(docs)
    assert any("isaac-sim-0 left for session-olga: could not move" in line for line in h.log)
