# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""Simulators for whoever asks: the front door's sessions, handed out from the one pool of instances
that test runs share, with a fair queue (isaac-sim-front-door-api.service runs it).

A person (or a program with a token of the `use` scope) asks; the request joins the queue, and the
queue is served in arrival order from the ready instances nobody holds, on the least loaded host
that fits. An instance is taken with the host agent's claim, the same marker a test run's loan
takes (lifecycle.lend): the agent refuses an instance that a run, another session or a deploy has,
so nothing is ever given twice, whatever this file believes. A session ends when its holder or an
operator ends it, or at its maximum duration (a warning shown first); its instance is then given
back through the agent (restarted clean, ready, only then free) and goes to the head of the queue.

What is here is kept in SQLite beside the login service's sessions (door_store): a restart of the
service or of the front door host keeps every session and place in the queue. A host that does not
answer for `host_gone_s` has its sessions ended (their holders see why); its claims are given back
once it answers again.

Each person's files follow them. A give-back (and a rollout that ends a session) moves the instance's
Documents aside on its host, into a stash named after the session's holder; the door then takes that
stash (the agent's GET /files/HOLDER, at most `files_mib`), keeps it as the person's one tar in
`files_dir` (named by a hash of the user name, root's alone), and removes it from the host. At the
person's next session, on whichever instance, the door puts the tar back into its Documents (PUT
/files/HOLDER?instance=N, which the agent takes only for the instance that holder holds). A tar that
could not be put back is never lost: a session that did not start from the person's latest tar has
its files merged over that tar at its end, not put in its place. With `files_mib` 0, files do not
follow: the host's stash is removed unread.

The standard library alone, as the rest of the door's services.
"""

from __future__ import annotations

import hashlib
import ipaddress
import json
import os
import re
import secrets
import socket
import tarfile
import tempfile
import threading
import time

try:
    from ansible_collections.isaacsim.fleet.plugins.module_utils.front import door_store
except ImportError:  # on the front door host, beside the service's script
    import isaac_sim_door_store as door_store  # type: ignore[no-redef]

# the holder an instance's claim names (the agent's HOLDER_RE)
HOLDER = "session-{}"
# what a request may ask for (each matched against the instance's status; gpu: the model of its GPU, as
# the host's driver names it, "NVIDIA " left out or not)
WANTS = ("release", "profile", "gpu")
# an instance status's key for a field not named as the field (gpu_model: the fleet's read adds it)
STATUS_KEY = {"gpu": "gpu_model"}
# a GPU model as the driver names it: "NVIDIA L40S", "NVIDIA RTX 6000 Ada Generation"
GPU_MODEL_RE = re.compile(r"\A[A-Za-z0-9][A-Za-z0-9 ._()-]{0,63}\Z")
# the defaults of the role's settings (front_door_sim_*); files_dir '': `files` beside the store
RULES = {
    "per_person": 1,
    "idle_minutes": 30,
    "max_minutes": 240,
    "warn_minutes": 5,
    "queue_grace_s": 120,
    "host_gone_s": 120,
    "files_mib": 1024,
    "files_dir": "",
}
MIB = 1024 * 1024
# how long a move of a person's files that failed (the agent did not answer, the door's disk) waits before
# it is tried again
FILES_RETRY_S = 30.0
# the agent judges a stash's files against the door's limit; their tar is larger (a 512-byte header a member,
# each padded to 512 bytes), so the door reads up to twice the limit and this, never more
TAR_SLACK = 16 * MIB
# how many times a person's files are tried to be put into a session's instance (an agent that cuts the
# transfer each time is refusing it): then the session goes on without them, which stay kept
PUT_TRIES = 3
# sim_sessions.files_due: what is still to be done with an ended session's files on its host: take them
# (then remove them there), or only remove them there
FETCH, REMOVE = "fetch", "remove"
# sim_sessions.files_in while the person's tar waits to be put into the session's instance
PUT_PENDING = "pending"
# sim_sessions.files of a session that ended while files did not follow people (files_mib 0)
NOT_FOLLOWED = "not kept: files do not follow people here (front_door_sim_files_mib: 0)"
# how long an instance its give-back just freed (restarted, ready, free: the agent said so) is offered to the
# queue before the hosts' status shows it free (the host and the door each reuse a status read for 2 s): the
# claim through the agent is what decides, so an instance taken meanwhile is only refused
FREED_S = 10.0
# how long before a give-back the host could not finish (the session's files not moved aside: it kept the
# instance for the session) is asked again: each try restarts the instance
GIVE_BACK_RETRY_S = 60.0
# a guess at a reset's length until one was seen (seconds)
RESET_GUESS_S = 60.0
# node_exporter's textfile the API writes (in the directory the role gives it)
METRICS_FILE = "isaac_sim_sessions.prom"
METRICS_EVERY_S = 15.0
# the warnings a session's holder is given (sim_sessions.warned): for want of a client, for its maximum duration
IDLE, MAXIMUM, ROLLOUT = 1, 2, 3
# _claim's status where the request left the queue while its instance was claimed (given back at once)
LEFT = 410
# how often the door looks for a client on each session's stream
CLIENTS_EVERY_S = 5.0
# how often the door asks the hosts afresh whether each session still holds its instance there, and
# how old a claim must be for a host's status to show it (the host and the door each reuse a status
# read for 2 s)
VERIFY_EVERY_S, SETTLE_S = 10.0, 10.0
_SCHEMA = (
    "CREATE TABLE IF NOT EXISTS sim_sessions (id TEXT PRIMARY KEY, user TEXT NOT NULL, wants TEXT NOT NULL,"
    " host TEXT NOT NULL, instance INTEGER NOT NULL, state TEXT NOT NULL, created REAL NOT NULL,"
    " started REAL NOT NULL, expires REAL NOT NULL, warned INTEGER NOT NULL DEFAULT 0, ended REAL,"
    " why TEXT, action TEXT, client_seen REAL, files TEXT, files_due TEXT, files_in TEXT, files_from TEXT)",
    "CREATE TABLE IF NOT EXISTS sim_queue (seq INTEGER PRIMARY KEY AUTOINCREMENT, id TEXT UNIQUE NOT NULL,"
    " user TEXT NOT NULL, wants TEXT NOT NULL, created REAL NOT NULL, seen REAL NOT NULL)",
    # each person's tar in files_dir: which one it is (a new version at each write), its size and members
    "CREATE TABLE IF NOT EXISTS sim_files (user TEXT PRIMARY KEY, version TEXT NOT NULL, bytes INTEGER NOT NULL,"
    " members INTEGER NOT NULL, kept REAL NOT NULL)",
)
# sim_sessions' columns added since the file was first made (0.4.0's first sessions had none of them): a
# session's files at its end (files: what became of them; files_due: what is left to do on its host), at its
# start (files_in: put back or why not; files_from: the version of the person's tar put back)
_ADDED = (("files", "TEXT"), ("files_due", "TEXT"), ("files_in", "TEXT"), ("files_from", "TEXT"))


class RefusedError(Exception):
    """A request the pool does not take: (HTTP status, answer)."""


def wants_errors(body) -> list:
    """What is wrong with a request's body, each naming the field."""
    if not isinstance(body, dict):
        return ['the body: not a JSON object. Fix: {} or {"release": "5.0"}.']
    errors = [
        f"{k}: not a field of a session request; the fields are {', '.join(WANTS)}" for k in body if k not in WANTS
    ]
    for k in WANTS:
        v = body.get(k)
        if k == "gpu":
            if v is not None and (not isinstance(v, str) or not GPU_MODEL_RE.match(v)):
                errors.append(f'gpu: {v!r} is not a GPU model (1-64 of A-Z a-z 0-9 space . _ ( ) -), e.g. "L40S"')
        elif v is not None and (not isinstance(v, str) or not door_store.NAME_RE.match(v)):
            errors.append(f"{k}: {v!r} is not a name (1-64 of A-Z a-z 0-9 . _ @ -)")
    return errors


class Store(door_store.Store):
    """The sessions and the queue, in the login service's file."""

    def __init__(self, path: str, clock=time.time):
        super().__init__(path, clock)
        with self._db() as db:
            for statement in _SCHEMA:
                db.execute(statement)
            # a file of the version before: its sessions' table gets the columns it lacks
            have = {r["name"] for r in db.execute("PRAGMA table_info(sim_sessions)").fetchall()}
            for name, kind in _ADDED:
                if name not in have:
                    db.execute(f"ALTER TABLE sim_sessions ADD COLUMN {name} {kind}")

    def enqueue(self, user: str, wants: dict, limit: int) -> str:
        """A new place at the end of the queue; RefusedError(409) where the user has `limit` already."""
        with self._db() as db:
            now = self.clock()  # in the write lock: the queue's order is its times' order
            held = db.execute(
                "SELECT id FROM sim_sessions WHERE user = ? AND state = 'active' UNION ALL "
                "SELECT id FROM sim_queue WHERE user = ?",
                (user, user),
            ).fetchall()
            if len(held) >= limit:
                ids = [r["id"] for r in held]
                raise RefusedError(
                    409,
                    {
                        "error": f"{user} has {len(ids)} session(s) or place(s) in the queue, the most allowed "
                        f"({limit}): {', '.join(ids)}. End one first (DELETE /api/sessions/ID).",
                        "sessions": ids,
                    },
                )
            ident = secrets.token_hex(6)
            db.execute(
                "INSERT INTO sim_queue (id, user, wants, created, seen) VALUES (?, ?, ?, ?, ?)",
                (ident, user, json.dumps(wants, sort_keys=True), now, now),
            )
        return ident

    def queue(self) -> list:
        with self._db(write=False) as db:
            rows = db.execute("SELECT * FROM sim_queue ORDER BY seq").fetchall()
        return [dict(r, wants=json.loads(r["wants"])) for r in rows]

    def grant(self, entry: dict, host: str, n: int, expires: float, files_in=None) -> bool:
        """The queued entry becomes a session on host's instance n; False where it left the queue meanwhile
        (its claim is then given back by the caller). files_in: PUT_PENDING where the person's files go in."""
        now = self.clock()
        with self._db() as db:
            gone = db.execute("DELETE FROM sim_queue WHERE id = ?", (entry["id"],)).rowcount
            if gone:
                db.execute(
                    "INSERT INTO sim_sessions (id, user, wants, host, instance, state, created, started, expires,"
                    " files_in) VALUES (?, ?, ?, ?, ?, 'active', ?, ?, ?, ?)",
                    (entry["id"], entry["user"], json.dumps(entry["wants"]), host, n, entry["created"], now, expires,
                     files_in),
                )  # fmt: skip
        return bool(gone)

    def leave(self, ident: str) -> bool:
        with self._db() as db:
            return bool(db.execute("DELETE FROM sim_queue WHERE id = ?", (ident,)).rowcount)

    def seen(self, ident: str) -> None:
        with self._db() as db:
            db.execute("UPDATE sim_queue SET seen = ? WHERE id = ?", (self.clock(), ident))

    def sim_sessions(self, states=("active", "ending")) -> list:
        marks = ", ".join("?" * len(states))
        with self._db(write=False) as db:
            rows = db.execute(f"SELECT * FROM sim_sessions WHERE state IN ({marks}) ORDER BY started", states)
            return [dict(r, wants=json.loads(r["wants"])) for r in rows.fetchall()]

    def get(self, ident: str):
        """The session or queued entry of that id (a queued one with state 'queued'); else None."""
        with self._db(write=False) as db:
            row = db.execute("SELECT * FROM sim_sessions WHERE id = ?", (ident,)).fetchone()
            if row:
                return dict(row, wants=json.loads(row["wants"]))
            row = db.execute("SELECT * FROM sim_queue WHERE id = ?", (ident,)).fetchone()
        return dict(row, wants=json.loads(row["wants"]), state="queued") if row else None

    def update(self, ident: str, only_if=None, **fields) -> bool:
        """Set fields of a session; only_if: its state must be one of these. Whether it changed."""
        sets = ", ".join(f"{k} = ?" for k in fields)
        where, args = "id = ?", [*fields.values(), ident]
        if only_if:
            where += f" AND state IN ({', '.join('?' * len(only_if))})"
            args += list(only_if)
        with self._db() as db:
            return bool(db.execute(f"UPDATE sim_sessions SET {sets} WHERE {where}", args).rowcount)

    def files_due(self) -> list:
        """The sessions with files to move: ended ones whose files are still on their host, active ones whose
        person's files wait to be put in; oldest first."""
        with self._db(write=False) as db:
            rows = db.execute(
                "SELECT * FROM sim_sessions WHERE files_due IS NOT NULL OR (state = 'active' AND files_in = ?)"
                " ORDER BY started",
                (PUT_PENDING,),
            ).fetchall()
        return [dict(r, wants=json.loads(r["wants"])) for r in rows]

    def kept(self, user: str):
        """{version, bytes, members, kept} of the person's tar as last written; None: none was."""
        with self._db(write=False) as db:
            row = db.execute("SELECT * FROM sim_files WHERE user = ?", (user,)).fetchone()
        return dict(row) if row else None

    def keep(self, user: str, version: str, size: int, members: int) -> None:
        with self._db() as db:
            db.execute(
                "INSERT OR REPLACE INTO sim_files (user, version, bytes, members, kept) VALUES (?, ?, ?, ?, ?)",
                (user, version, size, members, self.clock()),
            )

    def figures(self, now: float) -> dict:
        """What the metrics say, from the file (so a restart of the service keeps their sums)."""
        with self._db(write=False) as db:
            states = dict(db.execute("SELECT state, COUNT(*) FROM sim_sessions GROUP BY state").fetchall())
            queued, oldest = db.execute("SELECT COUNT(*), MIN(created) FROM sim_queue").fetchone()
            waited = db.execute("SELECT COUNT(*), COALESCE(SUM(started - created), 0) FROM sim_sessions").fetchone()
            lasted = db.execute(
                "SELECT COUNT(*), COALESCE(SUM(ended - started), 0) FROM sim_sessions WHERE ended IS NOT NULL"
            ).fetchone()
        return {
            "active": states.get("active", 0),
            "ending": states.get("ending", 0),
            "queued": queued,
            "oldest_wait_s": now - oldest if oldest is not None else 0,
            "waits": tuple(waited),
            "lengths": tuple(lasted),
        }

    def recent(self, limit: int = 50) -> list:
        with self._db(write=False) as db:
            rows = db.execute("SELECT * FROM sim_sessions ORDER BY started DESC LIMIT ?", (limit,)).fetchall()
        return [dict(r, wants=json.loads(r["wants"])) for r in rows]


def peers(texts) -> set:
    """{(address, port)} at the far end of each established TCP connection in /proc/net/tcp and tcp6
    texts (an IPv4 address mapped into IPv6 as plain IPv4)."""
    out = set()
    for text in texts:
        for line in (text or "").splitlines()[1:]:
            parts = line.split()
            if len(parts) < 4 or parts[3] != "01":  # 01: ESTABLISHED
                continue
            address, _sep, port = parts[2].partition(":")
            raw = bytes.fromhex(address)
            # the kernel writes each 32-bit word in the host's order (little-endian here)
            raw = b"".join(raw[k : k + 4][::-1] for k in range(0, len(raw), 4))
            ip = ipaddress.ip_address(raw)
            if isinstance(ip, ipaddress.IPv6Address) and ip.ipv4_mapped:
                ip = ip.ipv4_mapped
            out.add((str(ip), int(port, 16)))
    return out


def proc_peers() -> set:
    """peers() of this host's network (the door's nginx relays each stream's signalling from here)."""
    texts = []
    for name in ("/proc/net/tcp", "/proc/net/tcp6"):
        try:
            with open(name, encoding="ascii") as fh:
                texts.append(fh.read())
        except OSError:
            pass
    return peers(texts)


def address_of(signal: str):
    """(address, port) of ADDRESS:PORT as a status endpoint reports it (a name resolved); None if it cannot be."""
    host, _sep, port = str(signal).rpartition(":")
    try:
        return socket.getaddrinfo(host.strip("[]"), int(port), type=socket.SOCK_STREAM)[0][4][0], int(port)
    except (OSError, ValueError):
        return None


def fits(wants: dict, inst: dict) -> bool:
    return all(not wants.get(k) or _offers(inst, k) == _wanted(k, wants[k]) for k in WANTS)


def _offers(inst: dict, k: str) -> str:
    """What the instance has of a wanted field, as a request's value is compared."""
    return _wanted(k, str(inst.get(STATUS_KEY.get(k, k)) or ""))


def _wanted(k: str, v: str) -> str:
    # a GPU model is matched whole, in any case, with or without the driver's "NVIDIA " (L40S is not L40)
    return v.lower().removeprefix("nvidia ").strip() if k == "gpu" else v


def files_name(user: str) -> str:
    """The file of a person's tar: a hash of the name, never the name (".", ".." and "a/b" name no path)."""
    return hashlib.sha256(user.encode("utf-8")).hexdigest() + ".tar"


def tar_members(path: str) -> int:
    """How many files (regular members) the tar holds; tarfile.TarError where it is not a tar."""
    with tarfile.open(path) as tar:
        return sum(1 for m in tar if m.isreg())


def _member_name(name: str) -> str:
    return os.path.normpath(name.removeprefix("./")).rstrip("/")


def merge_tars(newer: str, older: str, out: str) -> int:
    """Into out: every member of newer, then those of older that newer lacks (by path); how many files.
    Copied member by member, never unpacked on the door."""
    seen, count = set(), 0
    with tarfile.open(out, "w", format=tarfile.PAX_FORMAT) as merged:
        for source, skip in ((newer, False), (older, True)):
            with tarfile.open(source) as tar:
                for member in tar:
                    name = _member_name(member.name)
                    if skip and name in seen:
                        continue
                    seen.add(name)
                    merged.addfile(member, tar.extractfile(member) if member.isreg() else None)
                    count += member.isreg()
    return count


def _size(n) -> str:
    return f"{n / MIB:.1f} MiB" if isinstance(n, int) else "more"


def _sync_replace(tmp: str, path: str) -> None:
    """tmp becomes path whole or not at all, on disk before it is."""
    with open(tmp, "rb") as fh:
        os.fsync(fh.fileno())
    os.replace(tmp, path)


class Pool:
    """The queue served from the fleet's free instances through the hosts' agents.

    fleet: the API's Fleet (hosts' status, read at most once per its ttl); agents: its Agents;
    config: api.json (entrances); rules: RULES, as the role set them; log: the journal."""

    def __init__(self, store: Store, fleet, agents, rules=None, *, log, clock=time.time, clients=proc_peers):
        """clients(): {(address, port)} of the established connections the door holds (proc_peers)."""
        self.store, self.fleet, self.agents, self.log, self.clock = store, fleet, agents, log, clock
        self.rules = dict(RULES, **(rules or {}))
        # one dispatcher at a time: the queue is served in its order
        self._lock = threading.Lock()
        # the sessions whose give-back is being asked for now (a request's end and a tick never ask twice)
        self._asking, self._asking_lock = set(), threading.Lock()
        # host -> when it last answered (since this service started: a host gone across a restart still times out)
        self._seen_up, self._since = {}, clock()
        self._resets = []  # seconds the last give-backs took
        self.clients, self._looked, self._verified = clients, None, None
        # (host, instance) -> {at, by, holder}: a rollout ends the session there (the host's status says so);
        # session id -> by: sessions a rollout was seen to end, for the why of their end
        self._endings, self._rollouts = {}, {}
        # session id -> when a move of its files last failed (tried again FILES_RETRY_S later); how many
        # put-backs failed
        self._files_failed, self._put_failures = {}, {}
        # (host, instance) -> when its give-back freed it; session id -> when its give-back left it held
        self._freed, self._held_at = {}, {}

    # --- what a person sees

    def view(self, row: dict, operator: bool = False) -> dict:
        now = self.clock()
        out = {
            "id": row["id"],
            "user": row["user"],
            "state": row["state"],
            "wants": row["wants"],
            "created": row["created"],
            "url": f"/api/sessions/{row['id']}",
        }
        if row["state"] == "queued":
            queue = self.store.queue()
            place = next((k for k, e in enumerate(queue, 1) if e["id"] == row["id"]), None)
            out.update(place=place, waiting=len(queue), estimate_s=self.estimate(place))
            return out
        entrances = (self.fleet.config.get("entrances") or {}).get(row["host"]) or {}
        out.update(
            host=row["host"],
            instance=row["instance"],
            holder=HOLDER.format(row["id"]),
            entrance=entrances.get(str(row["instance"])),
            started=row["started"],
            expires=row["expires"],
            seconds_left=max(0, round(row["expires"] - now)) if row["state"] == "active" else 0,
            warning=(self._warning(row, now) or (None, None))[1] if row["state"] == "active" else None,
            ended=row["ended"],
            why=row["why"],
            files=self._files_said(row),
        )
        if operator:
            out["files_moves"] = {"in": row.get("files_in"), "out": row.get("files")}
        return out

    def _files_said(self, row: dict):
        """One sentence for the person about their files (Documents), where there is something to say."""
        files, into = row.get("files"), row.get("files_in")
        if row["state"] == "active":
            if into == PUT_PENDING:
                return "Your files from your last session are being put back into Documents."
            if into and into.startswith("put back"):
                return "Your files from your last session are in Documents."
            if into:
                return (
                    f"Your files could not be put back ({into.removeprefix('not put back: ')}); they are kept for "
                    "your next session."
                )
            return None
        if files is None:  # ending: its instance is being given back
            return "Your files (Documents) will be kept for your next session." if self.rules["files_mib"] else None
        if files == "pending" or files.startswith("kept"):
            return f"Your files (Documents) {'are being' if files == 'pending' else 'are'} kept for your next session."
        if files.startswith("none"):
            return "Documents was empty at this session's end: the files kept before (if any) stay kept."
        if files.startswith("over the limit"):
            return (
                f"Your files were not kept, {files}: they are still on {row['host']}, where an operator can get them."
            )
        if files == NOT_FOLLOWED:
            return "Files do not follow people here: what was in Documents went with this session."
        return f"Your files could not be kept ({files.removeprefix('not kept: ')})."

    def _signal(self, row: dict):
        """(address, port) of the session's stream's signalling as the door reaches it; None where the
        door relays none (no web viewer behind it: its idleness is not known, so it never ends idle)."""
        signal = ((self.fleet.config.get("signals") or {}).get(row["host"]) or {}).get(str(row["instance"]))
        return address_of(signal) if signal else None

    def _idle_end(self, row: dict):
        """When the session ends for want of a client on its stream; None: it does not."""
        if not self.rules["idle_minutes"] or self._signal(row) is None:
            return None
        return max(row["started"], row.get("client_seen") or 0) + self.rules["idle_minutes"] * 60

    def _warning(self, row: dict, now: float):
        """(IDLE, MAXIMUM or ROLLOUT, what the page says) while the session's end is near; else None."""
        ending = self._endings.get((row["host"], row["instance"]))
        if ending and ending.get("holder") == HOLDER.format(row["id"]):
            at = time.strftime("%H:%M:%S UTC", time.gmtime(ending["at"]))
            return ROLLOUT, (
                f"A rollout by {ending['by']} restarts this simulator at {at}, in "
                f"{max(0, round((ending['at'] - now) / 60))} minute(s): save your work where it is kept. This "
                "session ends then."
            )
        warn = self.rules["warn_minutes"] * 60
        idle = self._idle_end(row)
        if idle is not None and idle < row["expires"] and idle - now <= warn:
            quiet = round((now - idle) / 60 + self.rules["idle_minutes"])
            return IDLE, (
                f"Nobody has been on this simulator's stream for {quiet} minute(s): it ends in "
                f"{max(0, round((idle - now) / 60))} minute(s) unless you open it."
            )
        if row["expires"] - now <= warn:
            return MAXIMUM, (
                f"This session ends in {max(0, round((row['expires'] - now) / 60))} minute(s), at its maximum "
                "duration. Save your work where it is kept."
            )
        return None

    def estimate(self, place) -> float | None:
        """An upper bound in seconds before the place-th in the queue is served: the active sessions'
        ends in order (their maximum duration), plus a reset."""
        if not place:
            return None
        ends = sorted(s["expires"] for s in self.store.sim_sessions(("active",)))
        if len(ends) < place:
            return None
        reset = sum(self._resets) / len(self._resets) if self._resets else RESET_GUESS_S
        return round(max(0.0, ends[place - 1] - self.clock()) + reset)

    # --- asking, looking, ending

    def limit(self, user: str, role: str = "") -> int:
        """How many sessions and places the user may hold at once: the user's own number, else the role's,
        else per_person."""
        given = self.rules.get("limits") or {}
        return int(given.get(f"user:{user}", given.get(f"role:{role}", self.rules["per_person"])))

    def request(self, user: str, body, role: str = "") -> tuple:
        """(201, the session) where an instance was free; (202, the place in the queue) where not."""
        errors = wants_errors(body)
        if errors:
            raise RefusedError(400, {"error": "; ".join(errors)})
        wants = {k: body[k] for k in WANTS if body.get(k)}
        if wants:
            self._offered(wants)
        ident = self.store.enqueue(user, wants, self.limit(user, role))
        self.log(
            f"session {ident} asked by user={user}" + (f" wants={json.dumps(wants, sort_keys=True)}" if wants else "")
        )
        self.dispatch()
        row = self.store.get(ident)
        return (201 if row["state"] == "active" else 202), self.view(row)

    def _offered(self, wants: dict) -> None:
        """RefusedError(409) where no instance of the fleet, held or not, fits: the request would wait for ever."""
        insts = [i for r in self._read() for i in r["status"].get("instances") or [] if i.get("configured")]
        if not any(fits(wants, i) for i in insts):
            keys = {k: STATUS_KEY.get(k, k) for k in wants}
            offered = {k: sorted({str(i[key]) for i in insts if i.get(key)}) for k, key in keys.items()}
            raise RefusedError(
                409,
                {
                    "error": "; ".join(
                        f"{k}: no instance of the fleet runs {v!r}. Fix: one of {', '.join(offered[k]) or 'none'}."
                        for k, v in wants.items()
                    )
                },
            )

    def look(self, ident: str, user: str, operator: bool) -> dict:
        """The session or place of that id (its holder or an operator); a queued one's holder is
        still there (its place is kept while it looks)."""
        row = self.store.get(ident)
        if row is None or (row["user"] != user and not operator):
            raise RefusedError(404, {"error": f"no session {ident} of yours"})
        if row["state"] == "queued" and row["user"] == user:
            self.store.seen(ident)
        return self.view(row, operator)

    def mine(self, user: str) -> list:
        """The user's sessions and places; the user is looking, so the places are kept."""
        rows = [r for r in self.store.sim_sessions(("active", "ending")) if r["user"] == user]
        for e in self.store.queue():
            if e["user"] == user:
                self.store.seen(e["id"])
                rows.append(dict(e, state="queued"))
        return [self.view(r) for r in rows]

    def everything(self) -> dict:
        return {
            "sessions": [self.view(r, True) for r in self.store.sim_sessions(("active", "ending"))],
            "queue": [self.view(dict(e, state="queued"), True) for e in self.store.queue()],
        }

    def end(self, ident: str, user: str, operator: bool, why: str = "") -> dict:
        row = self.store.get(ident)
        if row is None or (row["user"] != user and not operator):
            raise RefusedError(404, {"error": f"no session {ident} of yours"})
        by = why or ("ended by its holder" if row["user"] == user else f"ended by the operator {user}")
        if row["state"] == "queued":
            if self.store.leave(ident):
                self.log(f"session {ident} of user={row['user']} left the queue ({by})")
            return {"id": ident, "state": "ended", "why": by}
        if row["state"] == "active":
            self._end(row, by)
        return self.view(self.store.get(ident), operator)

    def _end(self, row: dict, why: str) -> None:
        """An active session ends for its holder now; its instance is given back (restarted) behind."""
        if not self.store.update(row["id"], ("active",), state="ending", ended=self.clock(), why=why):
            return
        self.log(f"session {row['id']} of user={row['user']} on {row['host']}/{row['instance']} ends: {why}")
        self._give_back(self.store.get(row["id"]))

    def _give_back(self, row: dict) -> None:
        """Ask the host's agent to give the instance back; where it cannot be reached, the next tick asks again."""
        with self._asking_lock:
            if row["id"] in self._asking:
                return
            self._asking.add(row["id"])
        try:
            self._ask_give_back(row)
        finally:
            with self._asking_lock:
                self._asking.discard(row["id"])

    def _ask_give_back(self, row: dict) -> None:
        request = {
            "host": row["host"],
            "action": "give_back",
            "user": row["user"],
            "ids": [row["instance"]],
            "holder": HOLDER.format(row["id"]),
        }
        try:
            code, answer = self.agents.ask(row["host"], "POST", "/actions", request)
        except OSError as exc:
            self.log(f"session {row['id']}: {row['host']} did not take the give-back ({exc}); asking again")
            return
        if code == 202:
            self.store.update(row["id"], action=answer["id"])
        else:  # 200: held by nobody already; 409: by another now (a deploy's cleanup): ours is gone either way
            self._ended(row, answer.get("error") or (answer.get("result") or {}).get("message") or str(code))

    def _at_end(self, row: dict) -> dict:
        """The fields of a session that ends on its host: what is to become of its files there."""
        if self.rules["files_mib"]:
            fields = {"files": "pending", "files_due": FETCH}
        else:
            fields = {"files": NOT_FOLLOWED, "files_due": REMOVE}
        if row.get("files_in") == PUT_PENDING:
            fields["files_in"] = "not put back: the session ended first"
        return fields

    def _ended(self, row: dict, said: str) -> None:
        if self.store.update(row["id"], ("ending",), state="ended", **self._at_end(row)):
            # the instance is free on its host now: the next read shows it to the queue (one its give-back freed
            # is offered already, without waiting for a read of every host)
            if (row["host"], row["instance"]) not in self._freed:
                self.fleet.refresh()
            took = self.clock() - (row["ended"] or self.clock())
            self._resets = [*self._resets[-9:], took]
            self.log(
                f"session {row['id']} of user={row['user']} ended ({row['why']}); {row['host']}/{row['instance']} "
                f"given back after {took:.1f} s: {said}"
            )

    # --- serving the queue

    def free(self) -> list:
        """[(host, instance status)] ready, held by nobody, on reachable hosts with an agent that are
        not drained, least loaded host first."""
        ours = {(s["host"], s["instance"]) for s in self.store.sim_sessions()}
        now = self.clock()
        self._freed = {k: at for k, at in self._freed.items() if now - at < FREED_S}
        out = []
        for read in self._read():
            status = read["status"]
            if not read["reachable"] or status.get("drained") or not self.agents.url(read["name"]):
                continue
            insts = [i for i in status.get("instances") or [] if i.get("configured") and i.get("id") is not None]
            held = sum(1 for i in insts if i.get("lent_to") or (read["name"], i["id"]) in ours)
            load = held / len(insts) if insts else 1.0
            for i in insts:
                where = (read["name"], i["id"])
                if where not in ours and ((i.get("ready") and not i.get("lent_to")) or where in self._freed):
                    out.append((load, read["name"], i["id"], i))
        return [(h, i) for _load, h, _n, i in sorted(out, key=lambda t: t[:3])]

    def dispatch(self) -> int:
        """Serve the queue in its order; how many it granted."""
        with self._lock:
            queue = self.store.queue()
            if not queue:
                return 0
            free, granted = self.free(), 0
            for entry in queue:
                for host, inst in [(h, i) for h, i in free if fits(entry["wants"], i)]:
                    if not any(h == host and i is inst for h, i in free):
                        continue  # its host was left out meanwhile
                    code, answer = self._claim(entry, host, inst["id"])
                    self._freed.pop((host, inst["id"]), None)  # the agent has said what it is now
                    if code == LEFT:
                        break  # it left the queue meanwhile: nothing more for it
                    if code == 200:
                        free = [(h, i) for h, i in free if (h, i["id"]) != (host, inst["id"])]
                        granted += 1
                        break
                    if code is None or "holder" in answer or answer.get("drained"):
                        # the host did not answer, is held (a deploy, an action: the refusal names its holder) or
                        # drained: none of it this time
                        free = [(h, i) for h, i in free if h != host]
                        continue
                    # this instance was taken meanwhile (a test run), or is not ready: the next one
                    free = [(h, i) for h, i in free if (h, i["id"]) != (host, inst["id"])]
            return granted

    def _claim(self, entry: dict, host: str, n: int) -> tuple:
        """(the agent's status, its answer) of a claim for the entry; (None, None) where it did not answer."""
        request = {
            "host": host,
            "action": "claim",
            "user": entry["user"],
            "ids": [n],
            "holder": HOLDER.format(entry["id"]),
        }
        try:
            code, answer = self.agents.ask(host, "POST", "/actions", request)
        except OSError as exc:
            self.log(f"session {entry['id']}: {host} did not answer the claim of instance {n} ({exc})")
            return None, None
        if code != 200:
            return code, answer
        expires = self.clock() + self.rules["max_minutes"] * 60
        # the person's files go in at the next tick (a transfer never holds up the queue)
        files_in = PUT_PENDING if self.rules["files_mib"] and self.store.kept(entry["user"]) else None
        if not self.store.grant(entry, host, n, expires, files_in):
            # it left the queue while its claim was made: the instance goes back at once
            self._give_back({"id": entry["id"], "user": entry["user"], "host": host, "instance": n})
            return LEFT, {}
        waited = self.clock() - entry["created"]
        self.log(
            f"session {entry['id']} of user={entry['user']} started on {host}/{n} after {waited:.1f} s in the queue"
        )
        return code, answer

    def _read(self) -> list:
        """The fleet's hosts as last read, noting when each answered."""
        reads, now = self.fleet.hosts(), self.clock()
        for read in reads:
            if read["reachable"]:
                self._seen_up[read["name"]] = now
                for inst in read["status"].get("instances") or []:
                    where = (read["name"], inst.get("id"))
                    if inst.get("lent_ending"):
                        self._endings[where] = dict(inst["lent_ending"], holder=inst.get("lent_to"))
                        self._rollouts[str(inst.get("lent_to")).removeprefix("session-")] = inst["lent_ending"]["by"]
                    else:
                        self._endings.pop(where, None)
        return reads

    # --- time passing

    def tick(self) -> None:
        """Warnings, maximum durations, give-backs that ended, hosts gone, places given up; then the queue."""
        now, rules = self.clock(), self.rules
        if self._verified is None or now - self._verified >= VERIFY_EVERY_S:
            self._verified = now
            self.fleet.refresh()
            self._verify(now)
        up = {r["name"] for r in self._read() if r["reachable"]}
        if self._looked is None or now - self._looked >= CLIENTS_EVERY_S:
            self._looked = now
            self._see_clients(now)
        for e in self.store.queue():
            if now - e["seen"] > rules["queue_grace_s"] and self.store.leave(e["id"]):
                self.log(
                    f"session {e['id']} of user={e['user']} left the queue: "
                    f"not looked at for {rules['queue_grace_s']} s"
                )
        for row in self.store.sim_sessions():
            gone_for = now - self._seen_up.get(row["host"], self._since)
            if row["state"] == "active":
                if gone_for > rules["host_gone_s"]:
                    why = f"{row['host']} did not answer for {round(gone_for)} s; the session is over"
                    self.store.update(row["id"], ("active",), state="ending", ended=now, why=why)
                    self.log(
                        f"session {row['id']} of user={row['user']} on {row['host']}/{row['instance']} ends: {why}"
                    )
                elif row["expires"] <= now:
                    self._end(row, f"its maximum duration ({rules['max_minutes']} minutes)")
                elif (self._idle_end(row) or now + 1) <= now:
                    self._end(row, f"nobody on its stream for {rules['idle_minutes']} minutes")
                elif (warning := self._warning(row, now)) and row["warned"] != warning[0]:
                    self.store.update(row["id"], warned=warning[0])
                    self.log(f"session {row['id']} of user={row['user']} warned: {warning[1]}")
            elif row["host"] not in up:
                continue  # asked again once it answers
            elif row["action"]:
                self._follow(row)
            elif now - self._held_at.get(row["id"], float("-inf")) >= GIVE_BACK_RETRY_S:
                self._give_back(row)
        # files out of ended sessions before the queue is served: a person's next session gets their latest
        self._files_out(up)
        self.dispatch()
        self._files_back(up)

    def _verify(self, now: float) -> None:
        """A session whose instance its host no longer holds for it (given back there by a rollout that
        ended sessions, an operator, or lost with the host's /run at a reboot) ended there: it is over."""
        reads = {r["name"]: r for r in self._read() if r["reachable"]}
        for row in self.store.sim_sessions(("active",)):
            if row["host"] not in reads or row["started"] > now - SETTLE_S:
                continue
            insts = reads[row["host"]]["status"].get("instances") or []
            inst = next((i for i in insts if i.get("id") == row["instance"] and i.get("configured")), None)
            holder = inst.get("lent_to") if inst else None
            if holder == HOLDER.format(row["id"]):
                continue
            by = self._rollouts.pop(row["id"], None)
            why = f"ended for a rollout by {by}" if by and not holder else None
            why = why or f"{row['host']} no longer holds instance {row['instance']} for it" + (
                f" (held by {holder})" if holder else " (given back there, or lost with a reboot of the host)"
            )
            if self.store.update(row["id"], ("active",), state="ended", ended=now, why=why, **self._at_end(row)):
                self.fleet.refresh()
                self.log(f"session {row['id']} of user={row['user']} on {row['host']}/{row['instance']} ended: {why}")

    # --- each person's files

    def _files_dir(self) -> str:
        """Where the people's tars are kept (made, root's alone, when missing)."""
        beside = os.path.join(os.path.dirname(os.path.abspath(self.store.path)), "files")
        directory = self.rules.get("files_dir") or beside
        os.makedirs(directory, mode=0o700, exist_ok=True)
        if os.stat(directory).st_mode & 0o077:
            os.chmod(directory, 0o700)
        return directory

    def _files_out(self, up: set) -> None:
        """Ended sessions' files taken from their hosts that answer (or only removed there)."""
        for row in self.store.files_due():
            if row["files_due"] and self._files_may_try(row, up):
                if row["files_due"] == FETCH:
                    self._files_try(row, self._take_files, f"{row['host']} did not give them")
                else:
                    self._files_try(row, self._remove_files, f"{row['host']} did not remove its copy")

    def _files_back(self, up: set) -> None:
        """The people's files put into their new sessions' instances, on hosts that answer."""
        for row in self.store.files_due():
            if row["state"] == "active" and row["files_in"] == PUT_PENDING and self._files_may_try(row, up):
                self._files_try(row, self._put_files, f"not put into {row['host']}/{row['instance']} yet")
                if row["id"] not in self._files_failed:
                    self._put_failures.pop(row["id"], None)
                    continue
                self._put_failures[row["id"]] = self._put_failures.get(row["id"], 0) + 1
                if self._put_failures[row["id"]] >= PUT_TRIES:
                    self._put_failures.pop(row["id"])
                    self._files_failed.pop(row["id"])
                    self.store.update(row["id"], files_in=f"not put back: {PUT_TRIES} tries failed")
                    self.log(
                        f"session {row['id']} of user={row['user']}: files not put back ({PUT_TRIES} tries failed); "
                        "they stay kept for the next session"
                    )

    def _files_may_try(self, row: dict, up: set) -> bool:
        """Its host answers and has an agent, and the last try failed long enough ago."""
        if row["host"] not in up or not self.agents.url(row["host"]):
            return False
        return self.clock() - self._files_failed.get(row["id"], float("-inf")) >= FILES_RETRY_S

    def _files_try(self, row: dict, move, what: str) -> None:
        self._files_failed.pop(row["id"], None)
        try:
            move(row)
        except OSError as exc:  # the agent did not answer, or the door's disk: the same again later
            self._files_failed[row["id"]] = self.clock()
            self.log(
                f"session {row['id']} of user={row['user']}: files {what} ({exc}); trying again in {FILES_RETRY_S:g} s"
            )

    def _take_files(self, row: dict) -> None:
        """The session's files from its host, kept as the person's tar (merged over it where the session did
        not start from it), then removed there; where there were none, or too many, the tar kept stays."""
        limit = self.rules["files_mib"] * MIB
        if not limit:  # files stopped following people since it ended (the rules changed)
            self.store.update(row["id"], files=NOT_FOLLOWED, files_due=REMOVE)
            self._files_try(dict(row, files=NOT_FOLLOWED), self._remove_files, f"{row['host']} did not remove them")
            return
        directory, holder, user = self._files_dir(), HOLDER.format(row["id"]), row["user"]
        path = os.path.join(directory, files_name(user))
        fd, tmp = tempfile.mkstemp(dir=directory, prefix=".in-", suffix=".tmp")  # 0600
        merged_tmp = None
        try:
            with os.fdopen(fd, "wb") as fh:
                code, answer = self.agents.fetch(row["host"], f"/files/{holder}?max={limit}", 2 * limit + TAR_SLACK, fh)
            if code == 200:
                try:
                    members = tar_members(tmp)
                except (tarfile.TarError, EOFError) as exc:
                    # not what the agent gives: its copy stays there for an operator to look at
                    self._files_final(row, f"not kept: what {row['host']} gave is not a tar ({exc})", keep=True)
                    return
                kept = self.store.kept(user) if os.path.exists(path) else None
                # a session that did not start from the tar kept now (its files were not put back, or another
                # session of the person ended meanwhile) adds to it: nothing kept is lost
                merged = kept is not None and row["files_from"] != kept["version"]
                if merged:
                    fd2, merged_tmp = tempfile.mkstemp(dir=directory, prefix=".in-", suffix=".tmp")
                    os.close(fd2)
                    members = merge_tars(tmp, path, merged_tmp)
                    os.replace(merged_tmp, tmp)
                _sync_replace(tmp, path)
                size = os.path.getsize(path)
                self.store.keep(user, secrets.token_hex(8), size, members)
                said = f"kept ({size} bytes, {members} files)"
                self.store.update(row["id"], files=said, files_due=REMOVE)
                self.log(
                    f"session {row['id']} of user={user}: files {said}"
                    + (", merged over the ones kept before (the session did not start from them)" if merged else "")
                )
                self._files_try(dict(row, files=said), self._remove_files, f"{row['host']} did not remove its copy")
            elif code == 404:
                self._files_final(
                    row, f"none: {row['host']} had no files of it (Documents empty or absent); those kept before stay"
                )
            elif code == 413:
                self._files_final(
                    row, f"over the limit ({_size(answer.get('bytes'))} > {self.rules['files_mib']} MiB)", keep=True
                )
            elif code >= 500:
                raise OSError(f"HTTP {code}: {answer.get('error')}")
            else:
                self._files_final(row, f"not kept: {row['host']} said {code}: {answer.get('error')}", keep=True)
        finally:
            for name in (tmp, merged_tmp):
                if name and os.path.exists(name):
                    os.unlink(name)

    def _files_final(self, row: dict, said: str, keep: bool = False) -> None:
        """An end's files settled without a tar kept; keep: they stay on the host (an operator can get them)."""
        self.store.update(row["id"], files=said, files_due=None)
        self.log(
            f"session {row['id']} of user={row['user']}: files {said}"
            + (f"; left on {row['host']} ({HOLDER.format(row['id'])})" if keep else "")
        )

    def _remove_files(self, row: dict) -> None:
        """The host's copy of the session's files removed (kept on the door, or not following people)."""
        code, answer = self.agents.ask(row["host"], "DELETE", f"/files/{HOLDER.format(row['id'])}")
        if code >= 500:
            raise OSError(f"HTTP {code}: {answer.get('error')}")
        self.store.update(row["id"], files_due=None)
        if code != 200:
            self.log(
                f"session {row['id']} of user={row['user']}: {row['host']} did not remove its copy of the files "
                f"({code}: {answer.get('error')}); it stays there"
            )
        elif row["files"] == NOT_FOLLOWED:
            self.log(f"session {row['id']} of user={row['user']}: files {row['files']}; removed on {row['host']}")

    def _put_files(self, row: dict) -> None:
        """The person's tar put into the session's instance (Documents); a refusal leaves it kept, untouched."""
        kept = self.store.kept(row["user"]) if self.rules["files_mib"] else None
        path = os.path.join(self._files_dir(), files_name(row["user"]))
        if kept is None or not os.path.exists(path):
            self.store.update(row["id"], files_in=None)  # nothing (any more) to put back
            return
        where = f"{row['host']}/{row['instance']}"
        with open(path, "rb") as fh:
            code, answer = self.agents.send(
                row["host"], f"/files/{HOLDER.format(row['id'])}?instance={row['instance']}", fh
            )
        if code == 200:
            said = f"put back ({answer.get('put')} files)"
            self.store.update(row["id"], files_in=said, files_from=kept["version"])
            self.log(
                f"session {row['id']} of user={row['user']}: files put back into {where} ({answer.get('put')} files)"
            )
        elif code >= 500 and code != 502:  # 502: the agent tried, and unpacking failed in the instance
            raise OSError(f"HTTP {code}: {answer.get('error')}")
        else:
            why = answer.get("error") or f"HTTP {code}"
            self.store.update(row["id"], files_in=f"not put back: {why}")
            self.log(
                f"session {row['id']} of user={row['user']}: files could not be put back into {where} ({code}: "
                f"{why}); they stay kept for the next session"
            )

    def _see_clients(self, now: float) -> None:
        """Each active session whose stream the door relays to someone now was seen in use now."""
        active = [(r, self._signal(r)) for r in self.store.sim_sessions(("active",))]
        if not any(signal for _r, signal in active):
            return
        connected = self.clients()
        for row, signal in active:
            if signal is not None and signal in connected:
                # someone is on it: an idle warning given is over (one for its maximum duration stands)
                self.store.update(row["id"], client_seen=now, **({"warned": 0} if row["warned"] == IDLE else {}))

    def _follow(self, row: dict) -> None:
        try:
            code, answer = self.agents.ask(row["host"], "GET", f"/actions/{row['action']}")
        except OSError:
            return
        if code == 404:  # the agent forgot it (its state lost): ask again
            self.store.update(row["id"], action=None)
        elif answer.get("ended_at"):
            result = answer.get("result") or {}
            if result.get("held"):
                # the host kept the instance for the session (its files could not be moved aside): the session
                # is still ending; its give-back is asked again later, never at once (each try restarts it)
                self._held_at[row["id"]] = self.clock()
                self.store.update(row["id"], action=None)
                self.log(
                    f"session {row['id']}: {row['host']} kept {row['host']}/{row['instance']} for it: "
                    f"{result.get('message') or '?'}; asking again in {GIVE_BACK_RETRY_S:g} s"
                )
                return
            self._held_at.pop(row["id"], None)
            if result.get("ok"):
                self._freed[(row["host"], row["instance"])] = self.clock()
            self._ended(row, result.get("message") or answer.get("state", "?"))

    def metrics(self) -> str:
        """node_exporter textfile lines: sessions active and ending, the queue, waits and lengths."""
        f = self.store.figures(self.clock())
        lines = []
        for name, kind, help_text, value in (
            ("isaac_sim_door_sessions_active", "gauge", "Simulator sessions holding an instance", f["active"]),
            ("isaac_sim_door_sessions_ending", "gauge", "Sessions whose instance is being reset", f["ending"]),
            ("isaac_sim_door_queue_length", "gauge", "People waiting for a simulator", f["queued"]),
            ("isaac_sim_door_queue_oldest_wait_seconds", "gauge", "How long the first in the queue has waited",
             round(f["oldest_wait_s"], 3)),
        ):  # fmt: skip
            lines += [f"# HELP {name} {help_text}", f"# TYPE {name} {kind}", f"{name} {value}"]
        for name, help_text, (count, total) in (
            ("isaac_sim_door_session_wait_seconds", "From the request to the instance, per session", f["waits"]),
            ("isaac_sim_door_session_length_seconds", "From the instance to the end, per ended session", f["lengths"]),
        ):
            lines += [
                f"# HELP {name} {help_text}",
                f"# TYPE {name} summary",
                f"{name}_sum {round(total, 3)}",
                f"{name}_count {count}",
            ]
        return "\n".join(lines) + "\n"

    def write_metrics(self, directory: str) -> None:
        """The textfile, whole or not at all (node_exporter never reads half of one)."""
        path = os.path.join(directory, METRICS_FILE)
        tmp = f"{path}.{os.getpid()}.tmp"
        with open(tmp, "w", encoding="utf-8") as fh:
            fh.write(self.metrics())
        os.replace(tmp, path)

    def end_all(self, why: str, wait_s: float = 120.0, sleep=time.sleep) -> dict:
        """The door goes away: every place in the queue left and every session ended as any end is (each
        instance given back on its host, reset, then free; each person's files kept on the door), waiting up
        to wait_s for the hosts. {ended, left, unfinished}: unfinished names HOST/N whose give-back or files
        did not finish in time (that claim or those files stay on the host)."""
        left = [e for e in self.store.queue() if self.store.leave(e["id"])]
        for e in left:
            self.log(f"session {e['id']} of user={e['user']} left the queue ({why})")
        active = self.store.sim_sessions(("active",))
        for row in active:
            self._end(row, why)
        deadline = self.clock() + wait_s
        while self._unfinished() and self.clock() < deadline:
            sleep(0.5)
            self.tick()
        return {"ended": len(active), "left": len(left), "unfinished": self._unfinished()}

    def _unfinished(self) -> list:
        """HOST/N of the sessions whose give-back, or whose files' move off their host, is still to come."""
        rows = self.store.sim_sessions(("ending",)) + [r for r in self.store.files_due() if r["files_due"]]
        return sorted({f"{r['host']}/{r['instance']}" for r in rows})

    def run(self, stop: threading.Event, every: float = 0.5, metrics_dir: str = "") -> None:
        written = None
        while not stop.wait(every):
            try:
                self.tick()
                if metrics_dir and (written is None or self.clock() - written >= METRICS_EVERY_S):
                    written = self.clock()
                    self.write_metrics(metrics_dir)
            except Exception as exc:  # pylint: disable=broad-exception-caught
                self.log(f"pool: {type(exc).__name__}: {exc}")
