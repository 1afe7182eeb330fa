# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""A host service of the collection that is not an instance (the status endpoint): its files
and its systemd unit, brought to the wanted state in one module call.

Pure decisions, and Service, which reads the host and applies them (the module isaac_sim_host_service
only adapts it). Instances never come here: they change only through the lifecycle
(module_utils/instance/lifecycle.py).
"""

from __future__ import annotations

import hashlib
import os
import shutil
import tempfile
from types import SimpleNamespace

UNIT_SUFFIXES = (".service", ".timer", ".socket")


def is_unit_file(path: str) -> bool:
    """A file systemd reads only on daemon-reload: a unit, or a drop-in (UNIT.d/NAME.conf)."""
    parent = os.path.basename(os.path.dirname(path))
    return path.endswith(UNIT_SUFFIXES) or (path.endswith(".conf") and parent.endswith(".d"))


def changed_files(files: dict, read) -> list:
    """The paths whose content, mode or (where wanted) owner differ from what is wanted.
    read(path) -> (content, mode[, uid, gid]) or None."""
    out = []
    for path, want in sorted(files.items()):
        have = read(path)
        owned = want.get("uid") is None or (have is not None and tuple(have[2:4]) == (want["uid"], want["gid"]))
        if have is None or have[0] != want["content"] or have[1] != int(str(want.get("mode", "0644")), 8) or not owned:
            out.append(path)
    return out


def directories_to_fix(directories: list, stat=os.stat) -> list:
    """The directories ({path, uid, gid, mode}) that are missing or owned or moded otherwise."""
    out = []
    for d in directories:
        try:
            st = stat(d["path"])
        except OSError:
            out.append(d)
            continue
        if (st.st_uid, st.st_gid, st.st_mode & 0o7777) != (int(d["uid"]), int(d["gid"]), int(str(d["mode"]), 8)):
            out.append(d)
    return out


def fix_directory(d: dict) -> None:
    """Created (with parents) or re-owned; what is inside is kept as it is."""
    os.makedirs(d["path"], mode=0o755, exist_ok=True)
    os.chown(d["path"], int(d["uid"]), int(d["gid"]))
    os.chmod(d["path"], int(str(d["mode"]), 8))


def actions(state: str, show: dict, files_changed: list, removable: list, directories: bool = False) -> list:
    """Steps, in order, for the unit as `show` describes it (ActiveState, UnitFileState, LoadState).

    started: its directories made first (they may be a container's mounts), enabled and running,
    restarted when one of its files or directories changed while it ran.
    absent: stopped and disabled, before its files go; a timer's service (Triggers) is stopped with
    it while files remain, or a run it started may write them again after they went. What it stopped
    mid-run (or what had failed) has its failed state reset: once its unit file is gone it would stay
    in `systemctl --failed` as "not-found failed" until a reboot.
    """
    units_changed = any(is_unit_file(p) for p in files_changed + (removable if state == "absent" else []))
    active = show.get("ActiveState") in ("active", "activating", "reloading")
    enabled = show.get("UnitFileState") == "enabled"
    verbs = []
    if state == "absent":
        if active or (show.get("Triggers") and removable):
            verbs.append("stop")
        if "stop" in verbs or show.get("ActiveState") == "failed":
            verbs.append("reset-failed")
        if enabled:
            verbs.append("disable")
        if removable:
            verbs.append("remove")
        if units_changed:
            verbs.append("daemon-reload")
        return verbs
    if directories:
        verbs.append("directories")
    if files_changed:
        verbs.append("write")
    if units_changed:
        verbs.append("daemon-reload")
    if not enabled:
        verbs.append("enable")
    if not active:
        verbs.append("start")
    elif files_changed or directories:
        verbs.append("restart")
    return verbs


def read_file(path):
    try:
        with open(path) as fh:
            content = fh.read()
        st = os.stat(path)
        return content, st.st_mode & 0o7777, st.st_uid, st.st_gid
    except (OSError, UnicodeDecodeError):
        return None


def write_file(path: str, content: str, mode, uid=None, gid=None) -> None:
    """Atomically: a reader never sees half a file (nor, with an owner of its own, another's)."""
    directory = os.path.dirname(path)
    os.makedirs(directory, mode=0o755, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=directory, prefix=".isaac-sim.")
    try:
        with os.fdopen(fd, "w") as fh:
            fh.write(content)
        if uid is not None:
            os.chown(tmp, int(uid), int(gid))
        os.chmod(tmp, int(str(mode), 8))
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def remove(path: str) -> bool:
    if os.path.isdir(path) and not os.path.islink(path):
        shutil.rmtree(path)
        return True
    if os.path.lexists(path):
        os.unlink(path)
        # a drop-in directory left empty goes too (one with other drop-ins stays)
        parent = os.path.dirname(path)
        if parent.endswith(".d") and not os.listdir(parent):
            os.rmdir(parent)
        return True
    return False


class ServiceError(Exception):
    """A step failed: msg says which and where to look; details go into the module's result."""

    def __init__(self, msg: str, **details):
        super().__init__(msg)
        self.msg = msg
        self.details = details


def wanted_files(params: dict) -> dict:
    """{path: {content, mode}} from the module's files, remove and directories; ServiceError on a bad one."""
    paths = list(params["files"]) + params["remove"] + [d.get("path", "") for d in params["directories"]]
    for path in paths:
        if not str(path).startswith("/"):
            raise ServiceError(f"{path!r} is not an absolute path. Fix: give every file and directory in full.")
    files = {}
    for path, spec in params["files"].items():
        spec = spec if isinstance(spec, dict) else {"content": spec}
        if "content" not in spec:
            raise ServiceError(f"files.{path}: no content. Fix: give content (and mode) for every file.")
        files[path] = {"content": str(spec["content"]), "mode": str(spec.get("mode", "0644"))}
        # an owner of its own: a service that runs as its own user reads its secrets (the registry mirror)
        if spec.get("uid") is not None:
            if not str(spec["uid"]).isdigit() or not str(spec.get("gid", "")).isdigit():
                raise ServiceError(
                    f"files.{path}: uid and gid must be numbers. Fix: give both, e.g. uid: 104, gid: 110."
                )
            files[path].update(uid=int(spec["uid"]), gid=int(spec["gid"]))
    return files


class Service:
    """One host service brought to params["state"] (the module's options: name, files, directories,
    remove, state). run(argv) -> (rc, out, err) runs systemctl, the only program it calls."""

    def __init__(self, params: dict, systemctl: str, run):
        self.p = params
        self.files = wanted_files(params)
        self.systemctl = systemctl
        self.run = run
        self.triggers = []

    def show(self) -> dict:
        rc, out, _err = self.run(
            [self.systemctl, "show", "-p", "ActiveState", "-p", "UnitFileState", "-p", "LoadState", "-p", "Triggers"]
            + [self.p["name"]]
        )
        return dict(line.split("=", 1) for line in out.splitlines() if "=" in line) if rc == 0 else {}

    def apply(self, check: bool) -> dict:
        """What changed (changed, actions, changed_files, diff); nothing is done in check mode."""
        p, show = self.p, self.show()
        self.triggers = show.get("Triggers", "").split()
        fix = []
        if p["state"] == "absent":
            changed = [path for path in list(self.files) + p["remove"] if os.path.lexists(path)]
            verbs = actions("absent", show, [], changed)
        else:
            changed = changed_files(self.files, read_file)
            fix = directories_to_fix(p["directories"])
            verbs = actions("started", show, changed, [], directories=bool(fix))
        diff = {
            "before": "".join(f"{path}\n" for path in changed if read_file(path) is not None),
            "after": "".join(f"{path}\n" for path in changed if p["state"] == "started"),
        }
        if not check:
            for verb in verbs:
                self._do(verb, changed, fix, verbs)
        return {"changed": bool(verbs), "actions": verbs, "changed_files": changed, "diff": diff}

    def _do(self, verb: str, changed: list, fix: list, verbs: list) -> None:
        if verb == "directories":
            for d in fix:
                fix_directory(d)
        elif verb == "write":
            for path in changed:
                want = self.files[path]
                write_file(path, want["content"], want["mode"], want.get("uid"), want.get("gid"))
        elif verb == "remove":
            for path in changed:
                remove(path)
        else:
            name = self.p["name"]
            units = {"daemon-reload": [], "stop": [name] + self.triggers}.get(verb, [name])
            if verb == "reset-failed":
                # tidying: a unit systemd no longer holds has no state to reset, and says so with rc 1
                for unit in [name] + self.triggers:
                    self.run([self.systemctl, verb, unit])
                return
            rc, out, err = self.run([self.systemctl, verb] + units)
            if rc != 0:
                raise ServiceError(
                    f"systemctl {verb} {name} failed: {(err or out).strip()}. "
                    f"See: systemctl status {name}; journalctl -u {name}",
                    actions=verbs,
                    changed_files=changed,
                )


def digest(content: str) -> str:
    return hashlib.sha256(content.encode("utf-8", "surrogateescape")).hexdigest()


def seen(files: list, directories: list, show: dict) -> dict:
    """What the plan reads of a host service, so in_place can tell on the controller whether the module
    would change anything: its unit's state, and each file's digest, mode and owner (null: none)."""
    out = {"ActiveState": show.get("ActiveState", ""), "UnitFileState": show.get("UnitFileState", "")}
    out["files"] = {}
    for path in files:
        have = read_file(path)
        out["files"][path] = None if have is None else [digest(have[0]), *have[1:]]
    out["directories"] = {}
    for path in directories:
        try:
            st = os.stat(path)
            out["directories"][path] = [st.st_mode & 0o7777, st.st_uid, st.st_gid]
        except OSError:
            out["directories"][path] = None
    return out


def in_place(params: dict, host: dict) -> bool:
    """Whether the module, given params (name, files, directories, state), would do nothing on the host
    as seen() read it: the same decision as Service.apply, on digests instead of contents. False for
    state absent, a bad parameter, or a file or directory the host was not asked about."""
    if params.get("state", "started") != "started" or not host:
        return False
    try:
        files = wanted_files(dict({"remove": [], "directories": []}, **params))
    except ServiceError:
        return False
    have_files, have_dirs = host.get("files", {}), host.get("directories", {})
    if not set(files) <= set(have_files):
        return False
    if any(d.get("path") not in have_dirs for d in params.get("directories", [])):
        return False
    digested = {path: dict(want, content=digest(want["content"])) for path, want in files.items()}

    def read(path):
        return None if have_files[path] is None else tuple(have_files[path])

    def stat(path):
        if have_dirs[path] is None:
            raise OSError(path)
        mode, uid, gid = have_dirs[path]
        return SimpleNamespace(st_mode=mode, st_uid=uid, st_gid=gid)

    fix = directories_to_fix(params.get("directories", []), stat)
    return not actions("started", host, changed_files(digested, read), [], directories=bool(fix))
