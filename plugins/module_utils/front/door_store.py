# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""What the front door's login service keeps on disk: its sessions and the API tokens (an SQLite
file in its state directory, root's alone).

A session is a random secret the browser holds in its cookie; the store keeps only its SHA-256,
with the user, the role and a fingerprint of the password hash it was opened with. So a logout
ends it everywhere at once (the next request nginx asks about finds nothing), and it survives a
restart of the service or a reboot of the host.

A token is `isf_ID_SECRET`: ID names it in lists and the journal, SECRET (32 random bytes) is kept
as its SHA-256 only and shown once, when it is made. Each has a name (one live token per user and
name), scopes, an expiry, and can be revoked; it remembers the password its user had when it was
made, so a user removed and made again (another person, perhaps) or given a new password does not
get the old tokens back. A random secret of 256 bits needs no slow hash: no
guess list reaches it.

The standard library alone: this file is copied beside the login service (door_auth.py) on the
front door host and read there by isaac_sim_door_token too.
"""

from __future__ import annotations

import contextlib
import hashlib
import hmac
import os
import re
import secrets
import sqlite3
import time

# what a token may be given: read the fleet; use a simulator (a session from the pool); act on
# instances; operate hosts
SCOPES = ("read", "use", "act", "operate")
# what a role may hold: a viewer reads and asks for simulators, an operator may be given all
ROLE_SCOPES = {"viewer": ("read", "use"), "operator": SCOPES}
PREFIX = "isf_"
MAX_DAYS = 365
# a user's or a token's name, as the journal may show it (never a forged line)
NAME_RE = re.compile(r"^[A-Za-z0-9._@-]{1,64}\Z")
_TOKEN_RE = re.compile(r"^isf_([0-9a-f]{12})_([A-Za-z0-9_-]{43})\Z")
_SCHEMA = (
    "CREATE TABLE IF NOT EXISTS sessions (digest TEXT PRIMARY KEY, user TEXT NOT NULL, role TEXT NOT NULL,"
    " fingerprint TEXT NOT NULL, created INTEGER NOT NULL, expires INTEGER NOT NULL, client TEXT NOT NULL)",
    "CREATE TABLE IF NOT EXISTS tokens (id TEXT PRIMARY KEY, user TEXT NOT NULL, name TEXT NOT NULL,"
    " scopes TEXT NOT NULL, digest TEXT NOT NULL, created INTEGER NOT NULL, expires INTEGER NOT NULL,"
    " revoked INTEGER, owner TEXT NOT NULL)",
)


def digest(secret: str) -> str:
    return hashlib.sha256(str(secret).encode()).hexdigest()


def fingerprint(password_hash: str) -> str:
    """What a session remembers of the password it was opened with: a new password ends it."""
    return digest("hash:" + str(password_hash))[:24]


def token_errors(user: str, role, name: str, scopes, days) -> list:
    """What is wrong with a token asked for, each naming the option and the fix."""
    errors = []
    if not isinstance(name, str) or not NAME_RE.match(name):
        errors.append(f"name: {name!r} is not a token name. Fix: 1-64 of A-Z a-z 0-9 . _ @ -, e.g. ci-restarts.")
    if role is None:
        errors.append(f"user: {user!r} is not a user of this front door. Fix: one of front_door_users.")
    scopes = list(scopes or [])
    unknown = [s for s in scopes if s not in SCOPES]
    if not scopes or unknown:
        errors.append(f"scopes: {unknown or scopes!r} is not a choice. Fix: one or more of {', '.join(SCOPES)}.")
    elif role is not None and any(s not in ROLE_SCOPES.get(role, ()) for s in scopes):
        errors.append(
            f"scopes: {user} is a {role}, who may hold {', '.join(ROLE_SCOPES.get(role, ()))} only. "
            "Fix: ask for those, or give the user the operator role first."
        )
    if isinstance(days, bool) or not isinstance(days, int) or not 1 <= days <= MAX_DAYS:
        errors.append(f"days: {days!r} is not 1-{MAX_DAYS}. Fix: how many days the token is good for.")
    return errors


class Store:
    """The SQLite file: one connection per call, so the service's threads and a module run on the
    host at the same moment each see the other's writes (SQLite's own locks, waited on up to 5 s)."""

    def __init__(self, path: str, clock=time.time):
        self.path, self.clock = path, clock
        with self._db() as db:
            for statement in _SCHEMA:
                db.execute(statement)

    @contextlib.contextmanager
    def _db(self, write=True):
        new = not os.path.exists(self.path)
        if new:
            # root's alone from its first byte: it holds every session's and token's digest
            os.close(os.open(self.path, os.O_WRONLY | os.O_CREAT, 0o600))
        db = sqlite3.connect(self.path, timeout=5, isolation_level=None)
        db.row_factory = sqlite3.Row
        try:
            # a writer takes the lock at once (never a deadlock of two readers turning writers)
            db.execute("BEGIN IMMEDIATE" if write else "BEGIN")
            yield db
            db.execute("COMMIT")
        except BaseException:
            if db.in_transaction:
                db.execute("ROLLBACK")
            raise
        finally:
            db.close()

    def _now(self) -> int:
        return int(self.clock())

    # sessions

    def open_session(self, user: str, role: str, password_hash: str, hours: float, client: str) -> tuple:
        """(the cookie's secret, its expiry); expired sessions of anyone are dropped meanwhile."""
        secret = secrets.token_urlsafe(32)
        now = self._now()
        expires = int(now + float(hours) * 3600)
        with self._db() as db:
            db.execute("DELETE FROM sessions WHERE expires <= ?", (now,))
            db.execute(
                "INSERT INTO sessions VALUES (?, ?, ?, ?, ?, ?, ?)",
                (digest(secret), user, role, fingerprint(password_hash), now, expires, client),
            )
        return secret, expires

    def session(self, secret: str):
        """{user, role, fingerprint, expires} of an open, unexpired session; else None."""
        if not secret:
            return None
        with self._db(write=False) as db:
            row = db.execute(
                "SELECT user, role, fingerprint, expires FROM sessions WHERE digest = ? AND expires > ?",
                (digest(secret), self._now()),
            ).fetchone()
        return dict(row) if row else None

    def end_session(self, secret: str):
        """The user whose session this was (now gone), or None."""
        if not secret:
            return None
        with self._db() as db:
            row = db.execute("SELECT user FROM sessions WHERE digest = ?", (digest(secret),)).fetchone()
            db.execute("DELETE FROM sessions WHERE digest = ?", (digest(secret),))
        return row["user"] if row else None

    def sessions(self) -> list:
        """[{user, role, created, expires, client}] of the open sessions."""
        with self._db(write=False) as db:
            rows = db.execute(
                "SELECT user, role, created, expires, client FROM sessions WHERE expires > ? ORDER BY created",
                (self._now(),),
            ).fetchall()
        return [dict(r) for r in rows]

    def session_holder(self, host: str, n: int):
        """The user whose simulator session (front/pool.py) holds that instance now; else None."""
        try:
            with self._db(write=False) as db:
                row = db.execute(
                    "SELECT user FROM sim_sessions WHERE host = ? AND instance = ? AND state = 'active'", (host, n)
                ).fetchone()
        except sqlite3.OperationalError:  # no session was ever asked for: the API made no table yet
            return None
        return row["user"] if row else None

    # tokens

    def make_token(self, user: str, name: str, scopes, days: int, password_hash: str) -> tuple:
        """(the token's text, shown once; its record). A live token of that user and name is
        revoked first (a new one replaces it). password_hash: the user's now (see owner)."""
        ident, secret = secrets.token_hex(6), secrets.token_urlsafe(32)
        now = self._now()
        with self._db() as db:
            db.execute(
                "UPDATE tokens SET revoked = ? WHERE user = ? AND name = ? AND revoked IS NULL", (now, user, name)
            )
            db.execute(
                "INSERT INTO tokens VALUES (?, ?, ?, ?, ?, ?, ?, NULL, ?)",
                (
                    ident,
                    user,
                    name,
                    ",".join(scopes),
                    digest(secret),
                    now,
                    now + int(days) * 86400,
                    fingerprint(password_hash),
                ),
            )
        return f"{PREFIX}{ident}_{secret}", self.find_token(user, name)

    def find_token(self, user: str, name: str):
        """The live (unrevoked) token of that user and name, expired or not; else None."""
        with self._db(write=False) as db:
            row = db.execute(
                "SELECT * FROM tokens WHERE user = ? AND name = ? AND revoked IS NULL", (user, name)
            ).fetchone()
        return _public(row, self._now()) if row else None

    def revoke(self, user: str, name: str) -> bool:
        now = self._now()
        with self._db() as db:
            gone = db.execute(
                "UPDATE tokens SET revoked = ? WHERE user = ? AND name = ? AND revoked IS NULL", (now, user, name)
            ).rowcount
        return bool(gone)

    def tokens(self) -> list:
        """Every token made, newest first, without its digest."""
        now = self._now()
        with self._db(write=False) as db:
            rows = db.execute("SELECT * FROM tokens ORDER BY created DESC, id").fetchall()
        return [_public(r, now) for r in rows]

    def token(self, text: str):
        """{id, user, name, scopes, expires, owner} of a good token (its secret matches, not revoked,
        not expired); else None. owner: the fingerprint of its user's password when it was made."""
        found = _TOKEN_RE.match(str(text or ""))
        if not found:
            return None
        ident, secret = found.groups()
        with self._db(write=False) as db:
            row = db.execute("SELECT * FROM tokens WHERE id = ?", (ident,)).fetchone()
        if row is None or not hmac.compare_digest(row["digest"], digest(secret)):
            return None
        record = _public(row, self._now())
        return dict(record, owner=row["owner"]) if record["state"] == "active" else None


def _public(row, now: int) -> dict:
    state = "revoked" if row["revoked"] is not None else "expired" if row["expires"] <= now else "active"
    return {
        "id": row["id"],
        "user": row["user"],
        "name": row["name"],
        "scopes": row["scopes"].split(","),
        "created": row["created"],
        "expires": row["expires"],
        "state": state,
    }
