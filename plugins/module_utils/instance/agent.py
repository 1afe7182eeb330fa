# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""The host's action agent (isaac-sim-agent.service): the front door's one way to act on this
host's instances, so the door holds no SSH key to the fleet and a host offers no shell.

It answers over TLS and only a client that shows a certificate of the collection's CA whose
name is the front door's (CLIENT_NAME, for client authentication) from an allowed network.
It offers a fixed list of actions: start, stop, restart and remove instances (the day-2 actions
of lifecycle_call.py, the same code a deploy runs) and drain or undrain the host; and a session's
files (/files/HOLDER): the Documents its give-back moved aside (lifecycle.take_files) read as a tar and
removed, and a tar put into the Documents of the instance the session holds now.

An action is acknowledged at once (202 and its id) and runs here, in this process, whoever
asked and whatever becomes of them: it holds the host's lock (runlock.py) as a playbook run
does, so a deploy and an action exclude each other (409 naming the holder), and it renews the
lock while it works. It never takes the host below N-1 serving instances unless the request
confirms it (the door lets operators alone confirm). Its progress is a list of events, kept on
disk with its outcome, so the door (or the door back after a crash) can read and follow it.

The standard library only, like the status endpoint: a host needs nothing from PyPI.
"""

from __future__ import annotations

import contextlib
import errno
import ipaddress
import json
import os
import re
import secrets
import shutil
import socket
import ssl
import stat
import subprocess
import sys
import tarfile
import tempfile
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib import layout

# the status endpoint's rule for a client's address, one for both host services
from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib.status_server import allowed
from ansible_collections.isaacsim.fleet.plugins.module_utils.instance import (
    hostprobe,
    lifecycle,
    lifecycle_call,
    runlock,
)

# the subject of the front door's client certificate (roles/front_door issues it from the CA)
CLIENT_NAME = "isaacsim.fleet front door"
INSTANCE_ACTIONS = tuple(lifecycle_call.DAY2)
# the host's own: drain, undrain, and cleanup (the old web service's "Cleanup All"): every instance of
# the host removed through the lifecycle, caches and logs kept, never without a confirmation
HOST_ACTIONS = ("drain", "undrain", "cleanup")
DRAINS = ("drain", "undrain")
# a session's claim of one ready instance (the lend marker test runs take) and its end: the instance
# restarted clean, ready, then free (lifecycle.give_back), as a test run gives one back
CLAIMS = ("claim", "give_back")
HOLDER_RE = layout.SESSION_RE
# actions that take serving instances out of service while they run
TAKES_DOWN = ("stop", "restart", "remove")
MAX_BODY = 4096
# clients served at once (a followed action holds one until it ends); the unit allows 64 tasks
MAX_CLIENTS = 32
# the lock is renewed this often while an action runs (runlock.HEARTBEAT_LIMIT_S is its limit)
RENEW_S = 5.0
# actions kept on disk, newest first
KEEP = 100
ACTION_ID_RE = re.compile(r"^[a-f0-9]{16}\Z")
NAME_RE = re.compile(r"^[A-Za-z0-9._@-]{1,64}\Z")
# a session's files (/files/HOLDER): the largest tar a PUT takes (--files-max-bytes), and what GET sends
# unless the door asks for less (?max=); a stash's directories deeper than this are left out of a GET (said)
FILES_MAX_BYTES = 1 << 30
FILES_DEPTH = 128
FILES_PATH_RE = re.compile(r"^/files/([^/]+)\Z")
# a put's tar runs inside the container; this long at most
PUT_TIMEOUT_S = 1800
# a refused body up to this size is read to its end first, so the client reads the answer
DRAIN_BYTES = 64 << 20
# host: the host the door means (this agent refuses a request for another, whatever its certificate said)
_FIELDS = {"host": str, "action": str, "ids": list, "confirm": bool, "user": str, "token": str, "holder": str}
_NEEDED = ("host", "action", "user")


class RefusedError(Exception):
    """A request the agent will not act on: its HTTP status and the answer's fields."""

    def __init__(self, code: int, error: str, **fields):
        super().__init__(error)
        self.code, self.body = code, dict(error=error, **fields)


def parse_request(body: bytes) -> dict:
    """The request of an action, checked field by field; RefusedError(400) naming the field."""
    if len(body) > MAX_BODY:
        raise RefusedError(413, f"the request is over {MAX_BODY} bytes")
    try:
        req = json.loads(body or b"{}")
    except (ValueError, RecursionError) as exc:
        raise RefusedError(400, f"the body is not JSON: {exc}") from exc
    if not isinstance(req, dict):
        raise RefusedError(400, "the body is not a JSON object")
    unknown = sorted(set(req) - set(_FIELDS))
    if unknown:
        raise RefusedError(400, f"{unknown[0]}: not a field of an action; the fields are {', '.join(_FIELDS)}")
    for name in _NEEDED:
        if name not in req:
            raise RefusedError(400, f"{name}: missing")
    for name, kind in _FIELDS.items():
        if name in req and (not isinstance(req[name], kind) or (kind is int and isinstance(req[name], bool))):
            raise RefusedError(400, f"{name}: {req[name]!r} is not a {kind.__name__}")
    known = INSTANCE_ACTIONS + HOST_ACTIONS + CLAIMS
    if req["action"] not in known:
        raise RefusedError(400, f"action: {req['action']!r} is not one of {', '.join(known)}")
    if not NAME_RE.match(req["user"]) or (req.get("token") and not NAME_RE.match(req["token"])):
        raise RefusedError(400, "user, token: names of 1-64 letters, digits and ._@-")
    ids = req.get("ids", [])
    if req["action"] in HOST_ACTIONS:
        if ids:
            raise RefusedError(400, f"ids: {req['action']} is the host's; it takes no instances")
    elif not ids or any(not isinstance(i, int) or isinstance(i, bool) or not 0 <= i <= 99 for i in ids):
        raise RefusedError(400, f"ids: {ids!r} is not a list of instance numbers 0-99")
    elif len(set(ids)) != len(ids):
        raise RefusedError(400, f"ids: {ids!r} names an instance twice")
    holder = req.get("holder", "")
    if req["action"] in CLAIMS:
        if len(ids) != 1:
            raise RefusedError(400, f"ids: {req['action']} takes one instance, not {len(ids)}")
        if not HOLDER_RE.match(holder):
            raise RefusedError(400, "holder: a session's name, session- and 1-32 lowercase letters and digits")
    elif holder:
        raise RefusedError(400, f"holder: only a claim or a give_back names one, not {req['action']}")
    return {
        "host": req["host"],
        "action": req["action"],
        "ids": list(ids),
        "confirm": bool(req.get("confirm")),
        "user": req["user"],
        "token": req.get("token") or "",
        "holder": holder,
    }


def below_n1(action: str, ids, states: dict) -> str:
    """Why `action` on `ids` would leave fewer than N-1 of the host's N instances serving while it
    runs ("" when it would not). A restart takes one at a time; a stop or a remove takes all of
    them; a start takes none."""
    if action not in TAKES_DOWN:
        return ""
    serving = {i for i, s in states.items() if lifecycle.serving(s)}
    targets = [i for i in ids if i in serving]
    if not targets:
        return ""
    least = len(serving) - (1 if action == "restart" else len(targets))
    n = len(states)
    if least >= max(1, n - 1):
        return ""
    down = sorted(set(states) - serving)
    said = f" ({', '.join(layout.container(i) for i in down)} not serving)" if down else ""
    # a host of one instance (N-1 = 0) is never emptied without a word either
    rule = f"below N-1 = {n - 1}" if least < n - 1 else "none at all"
    return (
        f"{action} of {', '.join(layout.container(i) for i in ids)} would leave {least} of this host's {n} "
        f"instances serving{said}, {rule}"
    )


def parse_query(query: str, names) -> dict:
    """{name: int} of a query string whose parameters are among `names`, each at most once, each a
    decimal number; RefusedError(400) naming the first one that is not."""
    out = {}
    for part in query.split("&") if query else ():
        key, sep, value = part.partition("=")
        if key not in names:
            said = ", ".join(names) or "none"
            raise RefusedError(400, f"{key or part!r}: not a parameter of this path (its parameters: {said})")
        if key in out:
            raise RefusedError(400, f"{key}: given twice")
        if not sep or not re.fullmatch(r"[0-9]{1,18}", value):
            raise RefusedError(400, f"{key}: {value!r} is not a number")
        out[key] = int(value)
    return out


def files_holder(path: str) -> str:
    """The session a /files/HOLDER path names; RefusedError 404 (another path) or 400 (not a session's name)."""
    m = FILES_PATH_RE.match(path)
    if not m:
        raise RefusedError(404, f"no such path: {path}")
    if not layout.SESSION_RE.match(m.group(1)):
        raise RefusedError(400, "holder: a session's name, session- and 1-32 lowercase letters and digits")
    return m.group(1)


def run_piped(argv, stdin, timeout: float = PUT_TIMEOUT_S) -> tuple:
    """(rc, stdout, stderr) of a command fed `stdin` (an open file), without a shell. Beside
    lifecycle.run_process, not through it: a put's tar is streamed from a file under a time limit, and
    what tar says is bytes, replaced where it is not UTF-8 (run_process reads text, strictly)."""
    path = lifecycle.command_path(argv[0])
    if not path:
        return 127, "", f"{argv[0]}: not found"
    try:
        done = subprocess.run([path] + list(argv[1:]), stdin=stdin, capture_output=True, check=False, timeout=timeout)
    except subprocess.TimeoutExpired:
        return 124, "", f"{argv[0]}: still running after {timeout:.0f} s; stopped"
    return done.returncode, done.stdout.decode(errors="replace"), done.stderr.decode(errors="replace")


# what opening a name with O_NOFOLLOW (and O_DIRECTORY) says when it is gone, a link or not a directory
_NOT_A_DIRECTORY = (errno.ENOENT, errno.ELOOP, errno.ENOTDIR)


def _tar_member(name: str, st, kind: bytes) -> tarfile.TarInfo:
    """A member with the entry's mode bits and time, and no owner: uid/gid 0, no names."""
    info = tarfile.TarInfo(name)
    info.type, info.mode, info.mtime = kind, stat.S_IMODE(st.st_mode) & 0o777, int(st.st_mtime)
    info.uid = info.gid = 0
    info.uname = info.gname = ""
    info.size = st.st_size if kind == tarfile.REGTYPE else 0
    return info


def tar_stashes(tops, out, max_bytes: int) -> dict:
    """Write into `out` (an open binary file) a tar of the directories `tops`, newest first, their paths
    relative to each: {"bytes": the regular files' total, "members", "skipped", "over": total > max_bytes;
    then nothing more is written, the total is still counted}.

    Root reads here what a person wrote: every name is opened relative to its directory's descriptor with
    O_NOFOLLOW, so no symbolic link is ever followed, whatever changes meanwhile. Only regular files and
    directories go in; left out, and counted: symbolic links, fifos, sockets, devices, a second name of a
    file already in (a hard link: its content is in once), directories deeper than FILES_DEPTH, and what an
    older stash has under a name a newer one has (the newer wins, file or directory)."""
    kept, inodes = {}, set()
    res = {"bytes": 0, "members": 0, "skipped": 0, "over": False}
    flags = os.O_RDONLY | os.O_NOFOLLOW | os.O_CLOEXEC
    with tarfile.open(fileobj=out, mode="w", format=tarfile.PAX_FORMAT) as tar:
        for top in tops:
            try:
                fd = os.open(top, flags | os.O_DIRECTORY)
            except OSError as exc:
                # gone meanwhile, or not a directory (a link): nothing of it is read. Any other error (no
                # right to read it) is raised: an empty answer would say there is nothing to keep
                if exc.errno in _NOT_A_DIRECTORY:
                    continue
                raise
            stack = [(fd, "", iter(sorted(os.listdir(fd))))]
            try:
                while stack:
                    dfd, rel, names = stack[-1]
                    name = next(names, None)
                    if name is None:
                        os.close(dfd)
                        stack.pop()
                        continue
                    arc = f"{rel}/{name}" if rel else name
                    try:
                        st = os.stat(name, dir_fd=dfd, follow_symlinks=False)
                    except FileNotFoundError:
                        continue
                    if stat.S_ISDIR(st.st_mode):
                        if kept.get(arc, "dir") != "dir" or len(stack) > FILES_DEPTH:
                            res["skipped"] += 1
                            continue
                        try:
                            sub = os.open(name, flags | os.O_DIRECTORY, dir_fd=dfd)
                        except OSError as exc:  # replaced by a link meanwhile; else raised, as above
                            if exc.errno not in _NOT_A_DIRECTORY:
                                raise
                            res["skipped"] += 1
                            continue
                        stack.append((sub, arc, iter(sorted(os.listdir(sub)))))
                        if arc not in kept:
                            kept[arc] = "dir"
                            res["members"] += 1
                            if not res["over"]:
                                tar.addfile(_tar_member(arc, st, tarfile.DIRTYPE))
                    elif stat.S_ISREG(st.st_mode) and arc not in kept and (st.st_dev, st.st_ino) not in inodes:
                        kept[arc] = "file"
                        inodes.add((st.st_dev, st.st_ino))
                        res["bytes"] += st.st_size
                        res["members"] += 1
                        res["over"] = res["over"] or res["bytes"] > max_bytes
                        if not res["over"]:
                            _add_file(tar, dfd, name, arc, st)
                    else:
                        res["skipped"] += 1
            finally:
                for dfd, _rel, _names in stack:
                    os.close(dfd)
    return res


def _add_file(tar: tarfile.TarFile, dfd: int, name: str, arc: str, st) -> None:
    """One regular file into the tar, opened without following a link (O_NONBLOCK: a fifo put in its
    place meanwhile does not hold the read); RefusedError(409) when it is not the file seen a moment ago."""
    try:
        fd = os.open(name, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC, dir_fd=dfd)
    except OSError as exc:
        if exc.errno not in _NOT_A_DIRECTORY + (errno.ENXIO,):
            raise
        raise RefusedError(409, f"{arc} changed while the stash was read ({exc.strerror}); ask again") from exc
    with os.fdopen(fd, "rb") as fh:
        now = os.fstat(fd)
        if not stat.S_ISREG(now.st_mode) or (now.st_dev, now.st_ino) != (st.st_dev, st.st_ino):
            raise RefusedError(409, f"{arc} changed while the stash was read; ask again")
        try:
            tar.addfile(_tar_member(arc, st, tarfile.REGTYPE), fh)
        except OSError as exc:
            if exc.errno is not None:  # the tar's own write (a full disk)
                raise
            # tarfile's "unexpected end of data": shorter than it was
            raise RefusedError(409, f"{arc} changed while the stash was read ({exc}); ask again") from exc


def check_tar(fh) -> int:
    """The number of members of the tar in `fh` (read from where it is, then put back there): only
    regular files and directories with relative names that stay below where they go; RefusedError(400)
    naming the first other one."""
    start = fh.tell()
    n = 0
    try:
        with tarfile.open(fileobj=fh, mode="r:") as tar:
            for member in tar:
                name = member.name
                parts = name.split("/")
                if not (member.isreg() or member.isdir()):
                    raise RefusedError(400, f"{name!r}: only regular files and directories are put")
                # "." only as a directory (tar -C DIR -cf - . makes one): the Documents itself
                if name.startswith("/") or ".." in parts or "\0" in name or not (name.strip("/.") or member.isdir()):
                    raise RefusedError(400, f"{name!r}: not a relative path below the Documents")
                n += 1
    except tarfile.TarError as exc:
        raise RefusedError(400, f"the body is not a tar: {exc}") from exc
    fh.seek(start)
    return n


class _Counted:
    """A body, and how much of it was read."""

    def __init__(self, raw):
        self.raw, self.n = raw, 0

    def read(self, size: int) -> bytes:
        data = self.raw.read(size)
        self.n += len(data)
        return data


def _unit_step(argv) -> tuple:
    """(verb, units) of a systemctl command that starts, stops or restarts instances; else (None, [])."""
    if len(argv) >= 3 and argv[0] == "systemctl" and argv[1] in ("start", "restart", "stop"):
        units = [u for u in argv[2:] if layout.UNIT_RE.match(u) or layout.COMPANION_UNIT_RE.match(u)]
        return argv[1], units
    return None, []


class Agent:
    """The actions of one host: taken, run in a thread each, kept on disk.

    host(): the lifecycle's Host (lifecycle.bind_local() on the real host, a scripted one in the
    tests); lock, guard, record: runlock's files; journal(line, unit): a line in the host's journal,
    in the named unit's own journal too."""

    def __init__(
        self,
        name: str,
        state_dir: str,
        host=lifecycle.bind_local,
        soak_seconds: float = 0.0,
        data_root: str = layout.DATA_ROOT,
        lock: str = runlock.LOCK,
        guard: str = "",
        record: str = runlock.RECORD,
        drained: str = layout.DRAINED,
        journal=None,
        renew_s: float = RENEW_S,
        files_max_bytes: int = FILES_MAX_BYTES,
        pipe=run_piped,
    ):
        self.name, self.state_dir, self.host = name, state_dir, host
        self.soak, self.data_root = soak_seconds, data_root
        # the guard beside the lock, as the lifecycle call's own marks of its job take it
        self.lock, self.guard, self.record, self.drained = lock, guard or runlock.guard_of(lock), record, drained
        self.journal = journal or say
        self.renew_s = renew_s
        # a put's tar goes to `pipe(argv, stdin)` (docker exec -i): run_piped, a fake in the tests
        self.files_max_bytes, self.pipe = files_max_bytes, pipe
        self.actions_dir = os.path.join(state_dir, "actions")
        os.makedirs(self.actions_dir, mode=0o700, exist_ok=True)
        # the tars of /files in and out, on disk rather than in memory; what a killed agent left goes
        self.tmp_dir = os.path.join(state_dir, "tmp")
        os.makedirs(self.tmp_dir, mode=0o700, exist_ok=True)
        for entry in os.listdir(self.tmp_dir):
            with contextlib.suppress(OSError):
                os.unlink(os.path.join(self.tmp_dir, entry))
        self._cv = threading.Condition()
        # one give-back of an instance at a time, however often it is asked for
        self._giving = threading.Lock()
        self._pruning = threading.Lock()
        self._live = {}
        self._threads = []
        self._recover()

    # --- what is kept

    def _path(self, action_id: str) -> str:
        return os.path.join(self.actions_dir, f"{action_id}.json")

    def _save(self, rec: dict) -> None:
        path = self._path(rec["id"])
        tmp = f"{path}.{threading.get_ident()}.tmp"
        with open(tmp, "w", encoding="utf-8") as fh:
            json.dump(rec, fh, sort_keys=True)
        os.replace(tmp, path)

    def _load(self, action_id: str):
        try:
            with open(self._path(action_id), encoding="utf-8") as fh:
                return json.load(fh)
        except (OSError, ValueError):
            return None

    def _recover(self) -> None:
        """Actions this process did not see end (the agent stopped or was killed while one ran): said
        so, and the lock such an action held given back, so the host is not held by nobody."""
        for entry in os.listdir(self.actions_dir):
            rec = self._load(entry[:-5]) if entry.endswith(".json") else None
            if rec and rec.get("state") in ("accepted", "running"):
                self._event(
                    rec,
                    "the agent stopped while this action ran; systemd finished or failed what it "
                    "was doing; the instances' journals say which",
                    state="interrupted",
                    save=False,
                )
                rec["ended_at"] = time.time()
                self._save(rec)
                runlock.release({"id": rec["id"]}, self.lock, self.guard)
        # a hold an agent process took and did not give back (killed before its action was even written
        # down): that process is gone, so is its action
        holder = runlock.read(self.lock)
        if isinstance(holder, dict) and holder.get("agent") and not self._alive(holder):
            runlock.release({"id": holder.get("id")}, self.lock, self.guard)
        self._prune()

    @staticmethod
    def _alive(holder: dict) -> bool:
        """Whether the agent process that took this hold still runs (its pid, and that pid's start time)."""
        pid = holder.get("pid")
        return bool(pid) and runlock.start_time(pid) == holder.get("started") != ""

    def _newest(self) -> list:
        """The actions' files, newest first (one removed meanwhile is left out)."""
        found = []
        for entry in os.listdir(self.actions_dir):
            if entry.endswith(".json"):
                with contextlib.suppress(FileNotFoundError):
                    found.append((os.path.getmtime(os.path.join(self.actions_dir, entry)), entry))
        return [entry for _mtime, entry in sorted(found, reverse=True)]

    def _prune(self) -> None:
        with self._pruning:
            for entry in self._newest()[KEEP:]:
                with contextlib.suppress(FileNotFoundError):
                    os.unlink(os.path.join(self.actions_dir, entry))

    def get(self, action_id: str):
        if not ACTION_ID_RE.match(action_id or ""):
            return None
        with self._cv:
            if action_id in self._live:
                return json.loads(json.dumps(self._live[action_id]))
        return self._load(action_id)

    def recent(self, limit: int = 20) -> list:
        """The last actions, newest first, without their events."""
        out = []
        for entry in self._newest()[:limit]:
            rec = self.get(entry[:-5])
            if rec:
                out.append({k: v for k, v in rec.items() if k != "events"})
        return out

    def events(self, action_id: str, start: int = 0, wait: float = 1.0):
        """(new events since `start`, whether the action has ended), waiting up to `wait` s for one."""
        with self._cv:
            rec = self._live.get(action_id)
            if rec is not None and len(rec["events"]) <= start and rec["state"] in ("accepted", "running"):
                self._cv.wait(wait)
                rec = self._live.get(action_id)
            if rec is not None:  # both read at once: the last event never goes without its end
                return list(rec["events"][start:]), rec["state"] not in ("accepted", "running")
        # not in hand: no thread of this process runs it, whatever its file last said
        rec = self._load(action_id) or {"events": []}
        return rec["events"][start:], True

    def _event(self, rec: dict, text: str, progress=None, state=None, save=True, **extra) -> None:
        with self._cv:
            if progress is not None:
                rec["progress"] = progress
            if state:
                rec["state"] = state
            rec["events"].append(
                dict(at=round(time.time(), 3), text=text, progress=rec["progress"], state=rec["state"], **extra)
            )
            self._cv.notify_all()
        if save:
            self._save(rec)

    # --- taking and running

    def drained_by(self):
        try:
            with open(self.drained, encoding="utf-8") as fh:
                return json.load(fh)
        except (OSError, ValueError):
            return None

    def submit(self, req: dict) -> tuple:
        """(HTTP status, answer) for a checked request (parse_request): 202 and the action once it is
        taken and holds the host; RefusedError otherwise, with nothing on the host changed."""
        if req["host"] != self.name:
            raise RefusedError(421, f"host: this is {self.name}, not {req['host']}; nothing was done")
        action_id = secrets.token_hex(8)
        who = req["user"] + (f" (token {req['token']})" if req["token"] else "")
        what = f"{req['action']} " + (", ".join(layout.container(i) for i in req["ids"]) or self.name)
        rec = {
            "id": action_id,
            "host": self.name,
            "action": req["action"],
            "ids": req["ids"],
            "user": req["user"],
            "token": req["token"],
            "confirmed": req["confirm"],
            "what": what,
            # the lifecycle's action (cleanup is every instance's remove)
            "day2": "remove" if req["action"] == "cleanup" else req["action"],
            "state": "accepted",
            "progress": 0,
            "accepted_at": round(time.time(), 3),
            "ended_at": None,
            "result": None,
            "events": [],
        }
        if req["action"] in DRAINS:
            return self._drain(rec, who)
        if req["action"] == "claim":
            return self._claim(rec, who, req["holder"])
        if req["action"] == "give_back":
            return self._give_back(rec, who, req["holder"])
        me = self._hold(rec, who)
        try:
            host = self.host()
            configured = _configured(host)
            if req["action"] == "cleanup":
                if not configured:
                    runlock.release(me, self.lock, self.guard)
                    return self._done(rec, who, f"cleanup: {self.name} runs no instance; nothing to remove")
                rec["ids"] = list(configured)
                rec["what"] = f"cleanup {self.name}: remove " + ", ".join(layout.container(i) for i in configured)
                what = rec["what"]
                if not req["confirm"]:
                    why = f"cleanup removes every instance of {self.name} ({len(configured)})"
                    self.journal(f"refused action {what} by {who}: not confirmed")
                    raise RefusedError(
                        412,
                        f"{why}. Nothing was done; an operator may confirm it (confirm: true).",
                        needs_confirm=True,
                        why=why,
                    )
            missing = [i for i in req["ids"] if i not in configured]
            if missing:
                raise RefusedError(
                    404,
                    f"ids: {', '.join(layout.container(i) for i in missing)} not on {self.name}, which runs "
                    f"{', '.join(layout.container(i) for i in configured) or 'none'}",
                )
            # a test run or a session has it: nothing of the API acts under it (its holder gives it back)
            held = lifecycle.holders(host, rec["ids"])
            if held:
                names = "; ".join(f"{layout.container(i)} is held by {h}" for i, h in held.items())
                self.journal(f"refused action {what} by {who}: {names}")
                raise RefusedError(
                    409,
                    f"{names}; nothing was done. Try again once it is given back.",
                    held=[{"id": i, "holder": h} for i, h in held.items()],
                )
            below = below_n1(rec["day2"], rec["ids"], lifecycle.states(host, configured))
            if below and not req["confirm"]:
                self.journal(f"refused action {what} by {who}: {below}; not confirmed")
                raise RefusedError(
                    412,
                    f"{below}. Nothing was done; an operator may confirm it (confirm: true).",
                    needs_confirm=True,
                    why=below,
                )
            self._event(rec, f"accepted: {what} by {who}" + (f"; confirmed: {below}" if below else ""), progress=0)
            answer = self._launch(rec, self._run, (rec, me, host, who))
        except BaseException as exc:
            runlock.release(me, self.lock, self.guard)
            with self._cv:
                taken = self._live.pop(action_id, None)
            if taken is not None:  # written down as accepted: say it ended there
                rec["ended_at"] = round(time.time(), 3)
                rec["result"] = {"ok": False, "message": f"not started: {type(exc).__name__}: {exc}"}
                with contextlib.suppress(OSError):
                    self._event(rec, rec["result"]["message"], progress=100, state="failed")
            raise
        self.journal(f"action {action_id} accepted: {what} by {who}" + (" (confirmed below N-1)" if below else ""))
        return 202, answer

    def _drain(self, rec: dict, who: str) -> tuple:
        if rec["action"] == "drain":
            tmp = f"{self.drained}.{threading.get_ident()}.tmp"
            with open(tmp, "w", encoding="utf-8") as fh:
                json.dump({"by": who, "at": time.time()}, fh)
            os.replace(tmp, self.drained)
            text = "drained: no new claim here; what runs goes on"
        else:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(self.drained)
            text = "undrained: claims are taken here again"
        return self._done(rec, who, text)

    def _claim(self, rec: dict, who: str, holder: str) -> tuple:
        """Lend one ready instance to a session, at once (200), or refuse with nothing changed. The host's
        lock is taken for the moment of the claim: a deploy or an action on the host makes it 409, so no
        instance is claimed while something restarts it."""
        i = rec["ids"][0]
        name = layout.container(i)
        rec["holder"] = holder
        me = self._hold(rec, who)
        try:
            host = self.host()
            if i not in _configured(host):
                raise RefusedError(404, f"ids: {name} not on {self.name}")
            if not host.exists(layout.marker(i)):
                raise RefusedError(409, f"{name} is not ready; nothing was claimed", ready=False)
            drained = self.drained_by()
            if drained:
                raise RefusedError(
                    409, f"{self.name} is drained (by {drained.get('by') or '?'}): it takes no new claim", drained=True
                )
            try:
                other = lifecycle.lend(host, i, holder, data_root=self.data_root)
            except lifecycle.DrainedError as exc:
                raise RefusedError(409, str(exc), drained=True) from exc
            if other is not None:
                raise RefusedError(409, f"{name} is held by {other}; nothing was claimed", held_by=other)
        except RefusedError as refused:
            self.journal(f"refused claim of {name} for {holder} by {who}: {refused}")
            raise
        finally:
            runlock.release(me, self.lock, self.guard)
        self.journal(f"{name} claimed for {holder} by {who}", layout.unit(i))
        return self._done(rec, who, f"{name} claimed for {holder}")

    def _hold(self, rec: dict, who: str) -> dict:
        """The host's lock for this action, or RefusedError(409) naming whoever holds it."""
        me = {
            "id": rec["id"],
            "user": who,
            "controller": f"the fleet API (isaac-sim-agent on {self.name})",
            "pid": os.getpid(),
            "started": runlock.start_time(os.getpid()),
            "play": rec["what"],
            "agent": rec["id"],
        }
        taken, holder, _note = runlock.acquire(me, time.time(), 0, path=self.lock, guard=self.guard, record_path="")
        if not taken:
            held = runlock.holder_text(holder or {}, time.time())
            self.journal(f"refused action {rec['what']} by {who}: the host is held by {held}")
            raise RefusedError(
                409, f"{self.name} is held by {held}; nothing was done. Try again once it ends.", holder=held
            )
        return me

    def _give_back(self, rec: dict, who: str, holder: str) -> tuple:
        """The end of a session's claim: 202, then the instance restarted clean and ready, and only then
        free (lifecycle.give_back), in a thread of its own. No host lock: a rollout that waits for the
        instance holds it (isaac_sim_rollout_held_wait)."""
        i = rec["ids"][0]
        rec["holder"] = holder
        host = self.host()
        now = lifecycle.lent_to(host, i)
        if now is None:
            return self._done(rec, who, f"{layout.container(i)} is held by nobody; nothing to give back")
        if now != holder:
            self.journal(f"refused give_back of {layout.container(i)} for {holder} by {who}: held by {now}")
            raise RefusedError(409, f"{layout.container(i)} is held by {now}, not {holder}; nothing was done")
        with self._giving:
            # asked again while it runs (the door asking twice): the same action, never a second restart
            with self._cv:
                running = next(
                    (
                        r
                        for r in self._live.values()
                        if r["action"] == "give_back" and r["ids"] == rec["ids"] and r.get("holder") == holder
                    ),
                    None,
                )
            if running is not None:
                return 202, {k: v for k, v in running.items() if k != "events"}
            self._event(rec, f"accepted: {rec['what']} by {who} (the end of {holder})", progress=0)
            answer = self._launch(rec, self._run_give_back, (rec, host, who, holder))
        self.journal(f"action {rec['id']} accepted: {rec['what']} for {holder} by {who}")
        return 202, answer

    def _run_give_back(self, rec: dict, host, who: str, holder: str) -> None:
        i = rec["ids"][0]
        self._event(rec, f"restart: {layout.container(i)} (a fresh container; waits for its ready line)", 10, "running")
        try:
            why = lifecycle.give_back(host, i, holder, data_root=self.data_root)
        except Exception as exc:  # pylint: disable=broad-exception-caught
            why = f"{type(exc).__name__}: {exc}"
        ok = why is None
        # its files could not be moved aside (lifecycle.give_back): it stays the session's; the door asks again
        held = not ok and lifecycle.lent_to(host, i) == holder
        if ok:
            message = f"{layout.container(i)} given back by {holder}: restarted and free"
        elif held:
            message = f"{layout.container(i)} not given back by {holder}: {why}"
        else:
            message = f"{layout.container(i)} given back by {holder}, but its restart failed: {why}"
        rec["result"] = {"ok": ok, "message": message, "held": held}
        self._end(rec, who, "succeeded" if ok else "failed")

    # --- a session's files (lifecycle.take_files moved them aside at its end)

    def stashes(self, holder: str) -> list:
        """The paths of the session's stashes, the newest first."""
        root = os.path.join(self.data_root, layout.FILES_DIR)
        try:
            entries = os.listdir(root)
        except FileNotFoundError:
            return []
        found = []
        for entry in entries:
            m = layout.FILES_STASH_RE.match(entry)
            if m and m.group(1) == holder:
                found.append(int(m.group(2) or 1))
        return [layout.files_stash(holder, n, self.data_root) for n in sorted(found, reverse=True)]

    def files_tar(self, holder: str, max_bytes: int) -> tuple:
        """(path of a temporary tar of the session's stashes, what tar_stashes said); the caller removes
        the file. RefusedError 404 without a stash, 413 (with "bytes") over max_bytes."""
        tops = self.stashes(holder)
        if not tops:
            raise RefusedError(404, f"no files of {holder} on {self.name}")
        fd, path = tempfile.mkstemp(prefix="get-", suffix=".tar", dir=self.tmp_dir)
        try:
            with os.fdopen(fd, "wb") as out:
                said = tar_stashes(tops, out, max_bytes)
            if said["over"]:
                self.journal(f"files of {holder}: {said['bytes']} bytes, over the {max_bytes} asked for; not sent")
                raise RefusedError(
                    413, f"the files of {holder} are {said['bytes']} bytes, over {max_bytes}", bytes=said["bytes"]
                )
        except BaseException:
            os.unlink(path)
            raise
        left = f", {said['skipped']} left out (links, devices, fifos, hard links, too deep)" if said["skipped"] else ""
        self.journal(f"files of {holder}: {said['members']} sent ({said['bytes']} bytes){left}")
        return path, said

    def files_remove(self, holder: str) -> bool:
        """Remove the session's stashes (rmtree works through descriptors: it follows no link inside);
        whether there was one."""
        tops = self.stashes(holder)
        for top in tops:
            if os.path.isdir(top) and not os.path.islink(top):
                shutil.rmtree(top)
            else:
                with contextlib.suppress(FileNotFoundError):
                    os.unlink(top)
        self.journal(f"files of {holder}: " + ("removed" if tops else "none to remove"))
        return bool(tops)

    def _documents(self, host, holder: str, i: int) -> dict:
        """Where a put goes, as Docker has it: instance i lent to `holder` and its container running with
        the instance's Documents directory bind-mounted read-write; {id, user, destination}. Else
        RefusedError (409: held by another or by none, not running, no such mount; 502: Docker failed)."""
        name = layout.container(i)
        now = lifecycle.lent_to(host, i)
        if now != holder:
            raise RefusedError(409, f"{name} is held by {now or 'nobody'}, not {holder}; nothing was put", held_by=now)
        rc, out, err = host.run(["docker", "inspect", "--type", "container", name])
        try:
            found = json.loads(out) if rc == 0 else None
            c = found[0]
            running, cid = c["State"]["Running"], c["Id"]
            user, mounts = c["Config"].get("User") or "", c.get("Mounts") or []
        except (ValueError, TypeError, KeyError, IndexError, AttributeError) as exc:
            raise RefusedError(502, f"docker inspect {name}: {(err or out).strip()[-300:] or exc}") from exc
        if not running:
            raise RefusedError(409, f"{name} is not running; nothing was put")
        docs = layout.documents_dir(i, self.data_root)
        sources = {os.path.normpath(docs), os.path.realpath(docs)}
        mount = next((m for m in mounts if m.get("Type") == "bind" and m.get("Source") in sources), None)
        if mount is None or not mount.get("RW") or not mount.get("Destination"):
            said = "is mounted read-only" if mount else "is not mounted"
            raise RefusedError(409, f"{docs} {said} in {name}: there is no Documents to put files into")
        return {"id": cid, "user": user, "destination": mount["Destination"]}

    def files_put_ready(self, holder: str, i: int, length: int) -> tuple:
        """(host, where) for a put of `length` bytes into instance i for `holder`, before a byte of it is
        read; RefusedError 413, 404 or 409 (as _documents) otherwise."""
        if length > self.files_max_bytes:
            raise RefusedError(413, f"the tar is {length} bytes, over {self.files_max_bytes}", bytes=length)
        host = self.host()
        if i not in _configured(host):
            raise RefusedError(404, f"instance: {layout.container(i)} not on {self.name}")
        return host, self._documents(host, holder, i)

    def files_put(self, holder: str, i: int, body, length: int, ready=None) -> dict:
        """Put the tar `body` (a file of `length` bytes) into the Documents of instance i, which `holder`
        holds: extracted by tar inside its running container, as the container's own user, in the
        directory the instance's Documents is mounted at, so it can reach nothing of the host but that
        directory. {"put": members, "bytes": length}; RefusedError: 404 (no such instance), 409, 400 (not
        a tar of regular files and directories), 413, 502 (Docker or tar failed: the door keeps the files).

        ready: what files_put_ready said of this very request (the handler asked it before 100 Continue);
        None: asked here. The image has a tar (Isaac Sim's are Ubuntu's)."""
        name = layout.container(i)
        host, where = ready or self.files_put_ready(holder, i, length)
        fd, path = tempfile.mkstemp(prefix="put-", suffix=".tar", dir=self.tmp_dir)
        try:
            with os.fdopen(fd, "w+b") as spool:
                left = length
                while left:
                    chunk = body.read(min(left, 1 << 20))
                    if not chunk:
                        raise RefusedError(400, f"the body ended after {length - left} of {length} bytes")
                    spool.write(chunk)
                    left -= len(chunk)
                spool.seek(0)
                members = check_tar(spool)
                # the claim may have ended while the body came: the container is the one inspected, by its id
                now = lifecycle.lent_to(host, i)
                if now != holder:
                    raise RefusedError(409, f"{name} is held by {now or 'nobody'} now, not {holder}; nothing was put")
            user = ["--user", where["user"]] if where["user"] else []
            argv = ["docker", "exec", "-i", *user, where["id"], "tar", "--no-same-owner", "-C"]
            # opened again: the command reads the descriptor from its start, whatever the buffer above it read
            with open(path, "rb") as tar:
                rc, out, err = self.pipe(argv + [where["destination"], "-xf", "-"], tar)
        finally:
            os.unlink(path)
        if rc != 0:
            last = " / ".join(line for line in (err or out).strip().splitlines()[-5:])
            self.journal(f"files of {holder}: put into {name} failed (exit {rc}): {last}", layout.unit(i))
            raise RefusedError(502, f"tar in {name} failed (exit {rc}): {last}", rc=rc, stderr=last)
        self.journal(f"files of {holder}: {members} put into {name} ({length} bytes)", layout.unit(i))
        return {"put": members, "bytes": length}

    def _done(self, rec: dict, who: str, text: str) -> tuple:
        """An action that needed no lifecycle call, written down as succeeded."""
        rec.update(ended_at=round(time.time(), 3), result={"ok": True, "message": text})
        self._event(rec, text, progress=100, state="succeeded")
        self.journal(f"action {rec['id']} {rec['action']} of {self.name} by {who}: succeeded")
        self._prune()
        return 200, {k: v for k, v in rec.items() if k != "events"}

    def _run(self, rec: dict, me: dict, host, who: str) -> None:
        stop = threading.Event()
        renewer = threading.Thread(target=self._renew, args=(me, stop), daemon=True)
        steps = {"n": 0}
        total = max(1, len(rec["ids"]))
        run = host.run

        def watched(argv):
            verb, units = _unit_step(argv)
            mine = [u for u in units if layout.UNIT_RE.match(u)]
            if mine:
                names = ", ".join(layout.container(layout.instance_id(layout.UNIT_RE, u)) for u in mine)
                self._event(rec, f"{verb}: {names}" + (" (waits for its ready line)" if verb != "stop" else ""))
            began = time.monotonic()
            rc, out, err = run(argv)
            if mine:
                steps["n"] = min(total, steps["n"] + len(mine))
                took = round(time.monotonic() - began, 1)
                said = "done" if rc == 0 else f"failed (exit {rc}): {(err or out).strip()[-300:]}"
                self._event(rec, f"{verb} of {names} {said} in {took} s", progress=10 + 80 * steps["n"] // total)
            return rc, out, err

        host.run = watched
        p = {
            "action": rec["day2"],
            "ids": rec["ids"],
            "soak_seconds": self.soak,
            "purge": False,
            "data_root": self.data_root,
            "managed": layout.MANAGED,
            "controller_run": me["id"],
        }
        try:
            renewer.start()
            self._event(rec, f"holds {self.name}; the lifecycle runs", progress=10, state="running")
            out = lifecycle_call.call(host, p, lock=self.lock, record=self.record)
            rec["result"] = {"ok": True, "message": f"{rec['what']}: done", "done": out["done"]}
            ended = "succeeded"
        except lifecycle_call.LifecycleError as exc:
            rec["result"] = {"ok": False, "message": exc.msg, **{k: v for k, v in exc.fields.items() if k != "diff"}}
            ended = "failed"
        except Exception as exc:  # pylint: disable=broad-exception-caught
            rec["result"] = {"ok": False, "message": f"{type(exc).__name__}: {exc}"}
            ended = "failed"
        finally:
            stop.set()
            if renewer.is_alive():
                renewer.join()
            runlock.release(me, self.lock, self.guard)
        self._end(rec, who, ended)

    def _launch(self, rec: dict, target, args: tuple) -> dict:
        """An accepted action in hand and its thread started; the answer to its request."""
        with self._cv:
            self._live[rec["id"]] = rec
            answer = {k: v for k, v in rec.items() if k != "events"}
        worker = threading.Thread(target=target, args=args, name=f"action-{rec['id']}", daemon=True)
        worker.start()
        self._threads = [t for t in self._threads if t.is_alive()] + [worker]
        return answer

    def _end(self, rec: dict, who: str, ended: str) -> None:
        """An action's outcome (rec["result"]) kept and said in the journal, in each instance's own too."""
        rec["ended_at"] = round(time.time(), 3)
        kept = True
        try:
            self._event(rec, rec["result"]["message"], progress=100, state=ended)
        except OSError as exc:  # the outcome could not be written down (a full disk): said, and kept in memory
            self.journal(f"action {rec['id']}: could not keep its outcome: {exc}")
            kept = False
        line = f"action {rec['id']} {rec['what']} by {who}: {ended}" + (
            "" if ended == "succeeded" else f": {rec['result']['message']}"
        )
        for i in rec["ids"]:  # in the instance's own journal too, beside the lifecycle's lines
            self.journal(line, layout.unit(i))
        if not rec["ids"]:
            self.journal(line)
        if kept:
            with self._cv:
                self._live.pop(rec["id"], None)
        self._prune()

    def _renew(self, me: dict, stop: threading.Event) -> None:
        while not stop.wait(self.renew_s):
            runlock.renew(me, time.time(), self.lock, self.guard)

    def wait(self, timeout: float = 30.0) -> None:
        """Until every action taken has ended (the tests)."""
        for worker in list(self._threads):
            worker.join(timeout)


def say(line: str, unit: str = "") -> None:
    """A line in the agent's journal; with `unit`, in that unit's journal too (journalctl -u shows a
    root process's entries that name it as OBJECT_SYSTEMD_UNIT)."""
    sys.stdout.write(line + "\n")
    sys.stdout.flush()
    if unit:
        with contextlib.suppress(OSError, subprocess.SubprocessError):
            subprocess.run(
                ["logger", "--journald"],
                input=f"MESSAGE=isaac-sim-agent: {line}\nSYSLOG_IDENTIFIER=isaac-sim-agent\n"
                f"OBJECT_SYSTEMD_UNIT={unit}\nPRIORITY=5\n",
                text=True,
                check=False,
                timeout=5,
            )


# --- the channel: TLS, the front door's certificate alone, from allowed networks


def tls_context(cert: str, key: str, ca: str) -> ssl.SSLContext:
    """The server side: TLS 1.2 or later, a client certificate of the CA required."""
    ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    ctx.minimum_version = ssl.TLSVersion.TLSv1_2
    ctx.verify_mode = ssl.CERT_REQUIRED
    ctx.load_verify_locations(cafile=ca)
    ctx.load_cert_chain(cert, key)
    return ctx


def peer_name(cert: dict) -> str:
    """The common name of a verified peer certificate (ssl's getpeercert())."""
    for rdn in (cert or {}).get("subject", ()):
        for key, value in rdn:
            if key == "commonName":
                return value
    return ""


class Server(ThreadingHTTPServer):
    daemon_threads = True
    # a client that does not finish its handshake holds only its own thread, this long
    handshake_s = 10.0

    def __init__(self, address, handler, ctx: ssl.SSLContext, networks, client_name=CLIENT_NAME, log=say):
        self.ctx, self.networks, self.client_name, self.log = ctx, networks, client_name, log
        self.address_family = socket.AF_INET6 if ":" in address[0] else socket.AF_INET
        # a thread per client, within the unit's TasksMax: more at once are closed at once
        self.slots = threading.BoundedSemaphore(MAX_CLIENTS)
        super().__init__(address, handler)

    def process_request(self, request, client_address):
        if not self.slots.acquire(blocking=False):
            self.log(f"refused {client_address[0]}: {MAX_CLIENTS} clients at once already")
            self.shutdown_request(request)
            return
        try:
            super().process_request(request, client_address)
        except BaseException:
            self.slots.release()
            raise

    def process_request_thread(self, request, client_address):
        try:
            super().process_request_thread(request, client_address)
        finally:
            self.slots.release()

    def finish_request(self, request, client_address):
        """In the request's own thread: the network, the handshake and the certificate's name checked
        before a byte of HTTP is read."""
        if not allowed(client_address[0], self.networks):
            self.log(f"refused {client_address[0]}: not in the allowed networks")
            return
        try:
            request.settimeout(self.handshake_s)
            conn = self.ctx.wrap_socket(request, server_side=True)
        except (OSError, ssl.SSLError) as exc:
            self.log(f"refused {client_address[0]}: TLS: {exc}")
            return
        name = peer_name(conn.getpeercert())
        if name != self.client_name:
            self.log(f"refused {client_address[0]}: certificate of {name!r}, not the front door's")
            conn.close()
            return
        self.RequestHandlerClass(conn, client_address, self)


def _configured(host) -> list:
    """The instances the host has set up (their env file and enabled unit)."""
    return hostprobe.existing_instances(
        layout.CONFIG_DIR, os.path.join(layout.UNIT_DIR, layout.TARGET + ".wants"), host.find
    )


def handler(agent: Agent):
    class Handler(BaseHTTPRequestHandler):
        server_version = "isaac-sim-agent"
        sys_version = ""
        timeout = 30
        # HTTP/1.1 for Expect: 100-continue (a put refused before its body is sent); one request a connection
        protocol_version = "HTTP/1.1"
        # files_put_ready's (host, where) of the request whose Expect: 100-continue was answered, so its
        # body's put does not ask Docker again
        put_ready = None

        def _send(self, code: int, body: dict) -> None:
            data = (json.dumps(body, sort_keys=True) + "\n").encode()
            self.send_response(code)
            self.send_header("Content-Type", "application/json")
            self.send_header("Content-Length", str(len(data)))
            self.send_header("Connection", "close")
            self.end_headers()
            self.wfile.write(data)

        def do_GET(self):  # noqa: N802 - http.server's naming
            path, _sep, query = self.path.partition("?")
            if path.startswith("/files/"):
                return self._files("GET", path, query)
            if path == "/health":
                return self._send(200, {"status": "ok", "host": agent.name, "drained": agent.drained_by()})
            if path == "/actions":
                return self._send(200, {"actions": agent.recent(), "drained": agent.drained_by()})
            m = re.match(r"^/actions/([a-f0-9]{16})(/events)?\Z", path)
            rec = agent.get(m.group(1)) if m else None
            if rec is None:
                return self._send(404, {"error": f"no such action: {path}"})
            if not m.group(2):
                return self._send(200, rec)
            return self._stream(m.group(1), "follow=1" in query.split("&"))

        def _stream(self, action_id: str, follow: bool) -> None:
            """The action's events, one JSON line each; with follow, each new one as it comes until the
            action ends (the connection's end is the stream's)."""
            self.send_response(200)
            self.send_header("Content-Type", "application/x-ndjson")
            self.send_header("Connection", "close")
            self.end_headers()
            seen = 0
            while True:
                new, ended = agent.events(action_id, seen, wait=1.0 if follow else 0)
                for event in new:
                    self.wfile.write((json.dumps(event, sort_keys=True) + "\n").encode())
                self.wfile.flush()
                seen += len(new)
                if ended or not follow:
                    break
            self.close_connection = True

        def do_POST(self):  # noqa: N802
            if self.path != "/actions":
                return self._send(404, {"error": f"no such path: {self.path}"})
            try:
                length = int(self.headers.get("Content-Length") or 0)
                if not 0 <= length <= MAX_BODY:
                    raise RefusedError(413, f"the request is not 0-{MAX_BODY} bytes")
                code, body = agent.submit(parse_request(self.rfile.read(length)))
            except RefusedError as refused:
                code, body = refused.code, refused.body
            except ValueError:
                code, body = 400, {"error": "Content-Length: not a number"}
            except Exception as exc:  # pylint: disable=broad-exception-caught
                agent.journal(f"error on POST /actions: {type(exc).__name__}: {exc}")
                code, body = 500, {"error": "the agent failed; its journal says why (nothing was started)"}
            return self._send(code, body)

        def do_DELETE(self):  # noqa: N802
            path, _sep, query = self.path.partition("?")
            return self._files("DELETE", path, query)

        def do_PUT(self):  # noqa: N802
            path, _sep, query = self.path.partition("?")
            return self._files("PUT", path, query)

        def _files(self, method: str, path: str, query: str) -> None:
            """A session's files: GET (?max=BYTES) the tar of its stashes, DELETE them, PUT (?instance=N)
            a tar into the Documents of the instance it holds."""
            ready, self.put_ready = self.put_ready, None  # this request's alone
            sent = _Counted(self.rfile)
            try:
                holder = files_holder(path)
                if method == "GET":
                    asked = parse_query(query, ("max",))
                    tar, _said = agent.files_tar(holder, asked.get("max", agent.files_max_bytes))
                    try:
                        self._send_file(tar)
                    except OSError as exc:  # the door went away while it was sent: nothing to answer
                        agent.journal(f"GET {path}: not sent whole: {exc}")
                    finally:
                        os.unlink(tar)
                    return None
                if method == "DELETE":
                    parse_query(query, ())
                    return self._send(200, {"removed": agent.files_remove(holder)})
                holder, i, length = self._put_request(query)
                code, body = 200, agent.files_put(holder, i, sent, length, ready)
            except RefusedError as refused:
                code, body = refused.code, refused.body
                if code != 404 or method != "GET":
                    agent.journal(f"refused {method} {path}: {refused}")
            except Exception as exc:  # pylint: disable=broad-exception-caught
                agent.journal(f"error on {method} {path}: {type(exc).__name__}: {exc}")
                code, body = 500, {"error": "the agent failed; its journal says why"}
            self._drain(sent)
            return self._send(code, body)

        def _put_request(self, query: str) -> tuple:
            """(holder, instance, length) of a PUT /files/HOLDER?instance=N; RefusedError otherwise."""
            holder = files_holder(self.path.partition("?")[0])
            asked = parse_query(query, ("instance",))
            if "instance" not in asked or not 0 <= asked["instance"] <= 99:
                raise RefusedError(400, "instance: the number (0-99) of the instance the session holds")
            length = self.headers.get("Content-Length")
            if self.headers.get("Transfer-Encoding") or length is None:
                raise RefusedError(411, "Content-Length: needed (the tar's size)")
            if not length.strip().isdigit():
                raise RefusedError(400, "Content-Length: not a number")
            return holder, asked["instance"], int(length)

        def handle_expect_100(self):
            """A put that will be refused is refused before its body is sent (the door waits for 100 Continue)."""
            if self.command == "PUT":
                path, _sep, query = self.path.partition("?")
                try:
                    holder, i, length = self._put_request(query)
                    self.put_ready = agent.files_put_ready(holder, i, length)
                except RefusedError as refused:
                    agent.journal(f"refused PUT {path}: {refused}")
                    self._send(refused.code, refused.body)
                    return False
                except Exception as exc:  # pylint: disable=broad-exception-caught
                    agent.journal(f"error on PUT {path}: {type(exc).__name__}: {exc}")
                    self._send(500, {"error": "the agent failed; its journal says why"})
                    return False
            return super().handle_expect_100()

        def _drain(self, sent) -> None:
            """A body refused before it was read is read to its end, up to DRAIN_BYTES, so the client gets
            the answer (a socket closed with bytes unread is reset, the answer lost); a larger one is not."""
            length = self.headers.get("Content-Length", "").strip()
            left = int(length) - sent.n if length.isdigit() else 0
            if left <= 0:
                return
            if left > DRAIN_BYTES:
                self.close_connection = True
                return
            with contextlib.suppress(OSError):
                while left > 0:
                    chunk = self.rfile.read(min(left, 1 << 16))
                    if not chunk:
                        break
                    left -= len(chunk)

        def _send_file(self, tar: str) -> None:
            self.send_response(200)
            self.send_header("Content-Type", "application/x-tar")
            self.send_header("Content-Length", str(os.path.getsize(tar)))
            self.send_header("Connection", "close")
            self.end_headers()
            with open(tar, "rb") as fh:
                shutil.copyfileobj(fh, self.wfile, 1 << 20)

        def log_message(self, *args):
            pass

    return Handler


def main(argv=None):
    import argparse

    parser = argparse.ArgumentParser(description="The host's action agent (isaacsim.fleet)")
    parser.add_argument("--name", required=True, help="the host's name in the inventory")
    parser.add_argument("--address", default="")
    parser.add_argument("--port", type=int, required=True)
    parser.add_argument("--allow", action="append", default=[], help="a network the front door reaches it from")
    parser.add_argument("--tls-dir", default=layout.AGENT_TLS_DIR, help="ca.crt, agent.crt and agent.key")
    parser.add_argument("--state-dir", default=layout.AGENT_STATE_DIR)
    parser.add_argument("--soak", type=float, default=0.0, help="seconds a restarted instance soaks")
    parser.add_argument("--data-root", default=layout.DATA_ROOT)
    parser.add_argument(
        "--files-max-bytes", type=int, default=FILES_MAX_BYTES, help="the largest tar of a session's files put"
    )
    args = parser.parse_args(argv)
    networks = [ipaddress.ip_network(n, strict=False) for n in args.allow]
    agent = Agent(
        args.name,
        args.state_dir,
        soak_seconds=args.soak,
        data_root=args.data_root,
        files_max_bytes=args.files_max_bytes,
    )
    ctx = tls_context(*(os.path.join(args.tls_dir, f) for f in ("agent.crt", "agent.key", "ca.crt")))
    server = Server((args.address or "0.0.0.0", args.port), handler(agent), ctx, networks)
    say(
        f"isaac-sim-agent of {args.name} on {args.address or '0.0.0.0'}:{args.port}, for {CLIENT_NAME!r} from "
        f"{', '.join(args.allow)}"
    )
    server.serve_forever()


if __name__ == "__main__":
    main()
