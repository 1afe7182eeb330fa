# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""The front door's login service (roles/front_door).

nginx asks it about every request before passing it on (auth_request: 204 passes, 401 goes to the
login page, 403 is refused), and it serves the login page itself. It listens on 127.0.0.1 only and
is copied to the front door host as this one file (the standard library alone), run by
isaac-sim-front-door-auth.service.

Users come from a JSON file of the role's ({name: {role, hash}}, root's alone): the hash is
PBKDF2-SHA256 in passlib's format ($pbkdf2-sha256$ROUNDS$SALT$SUM, as Ansible's
password_hash('pbkdf2_sha256') and the isaac_sim_password_hash filter write it), so no plain
password is ever on a host. Sessions are kept by the service (front/door_store.py): the cookie is a
random secret, so a logout ends the session everywhere at the next request, and a user removed,
given another role or a new password loses it too. Programs send an API token instead
(`Authorization: Bearer isf_...`, made with isaac_sim_door_token): it acts as its user, within its
scopes. Which role and scope a path needs is nginx's to say (its locations match the path as it
serves it; `need=` on the question), never a parse of the raw URI here. Every login, logout,
refused login and refused request is a line on stdout (the journal) with the user's name (and
token's) and the client's address. A logged-in user gets short-lived credentials of the front
door's TURN relay at /turn-credentials (coturn's shared-secret scheme), each handed out written
down.
"""

from __future__ import annotations

import base64
import contextlib
import hashlib
import hmac
import html
import json
import os
import sys
import time
import urllib.parse
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

try:
    from ansible_collections.isaacsim.fleet.plugins.module_utils.front import door_store
except ImportError:  # on the front door host, copied beside this script (front_door.files)
    import isaac_sim_door_store as door_store  # type: ignore[no-redef]

# __Host-: the browser keeps it for this host alone (Secure, Path=/, no Domain)
COOKIE = "__Host-fleet_session"
SCHEME = "$pbkdf2-sha256$"
ROLES = ("viewer", "operator")
# what nginx's question may need: (the role, and the scope of a token)
NEEDS = {
    "": ("viewer", "read"),
    "operator": ("operator", "read"),
    "act": ("operator", "act"),
    "operate": ("operator", "operate"),
}
MIN_ROUNDS = 10000


def _ab64_decode(text: str) -> bytes:
    """passlib's adapted base64: '.' for '+', no padding."""
    text = text.replace(".", "+")
    return base64.b64decode(text + "=" * (-len(text) % 4), validate=True)


def _ab64_encode(data: bytes) -> str:
    return base64.b64encode(data).decode().rstrip("=").replace("+", ".")


def hash_password(password: str, rounds: int = 29000, salt: bytes | None = None) -> str:
    """A hash in passlib's pbkdf2_sha256 format (its default rounds)."""
    salt = os.urandom(16) if salt is None else salt
    digest = hashlib.pbkdf2_hmac("sha256", password.encode(), salt, rounds)
    return f"{SCHEME}{rounds}${_ab64_encode(salt)}${_ab64_encode(digest)}"


def parse_hash(stored: str):
    """(rounds, salt, digest), or None for anything that is not a pbkdf2_sha256 hash."""
    if not isinstance(stored, str) or not stored.startswith(SCHEME):
        return None
    parts = stored[len(SCHEME) :].split("$")
    if len(parts) != 3 or not parts[0].isdigit():
        return None
    try:
        salt, digest = _ab64_decode(parts[1]), _ab64_decode(parts[2])
    except ValueError:
        return None
    if len(digest) != 32 or not salt:
        return None
    return int(parts[0]), salt, digest


def hash_error(stored) -> str | None:
    """What is wrong with a user's hash, or None (the role's check, before anything changes)."""
    parsed = parse_hash(stored)
    if parsed is None:
        return "is not a PBKDF2-SHA256 hash ($pbkdf2-sha256$ROUNDS$SALT$SUM)"
    if parsed[0] < MIN_ROUNDS:
        return f"has {parsed[0]} rounds, fewer than {MIN_ROUNDS}"
    return None


def verify_password(password: str, stored: str) -> bool:
    parsed = parse_hash(stored)
    if parsed is None:
        return False
    rounds, salt, digest = parsed
    return hmac.compare_digest(hashlib.pbkdf2_hmac("sha256", password.encode(), salt, rounds), digest)


def turn_credentials(user: str, secret: bytes, expires: int) -> tuple:
    """(user name, password) for the TURN relay, in coturn's shared-secret scheme (use-auth-secret):
    the name is EXPIRY:USER, the password base64(HMAC-SHA1(secret, name)); coturn refuses both
    after EXPIRY, so nothing is stored and nothing needs revoking."""
    name = f"{int(expires)}:{user}"
    return name, base64.b64encode(hmac.new(secret, name.encode(), hashlib.sha1).digest()).decode()


def cookie_value(header: str) -> str:
    for part in (header or "").split(";"):
        name, _eq, value = part.strip().partition("=")
        if name == COOKIE:
            return value
    return ""


def csrf_token(secret: str) -> str:
    """The session's CSRF token: derived from its secret, so it lives and ends with the session."""
    return hashlib.sha256(b"isaacsim.fleet csrf:" + secret.encode()).hexdigest()[:32]


def safe_next(target: str) -> str:
    """Where to go after login: a path on this front door only (never another site), printable
    ASCII (it goes into a Location header)."""
    target = target or "/"
    if not target.startswith("/") or target.startswith("//") or "\\" in target:
        return "/"
    if any(not " " < c <= "~" for c in target):
        return "/"
    return target


def may_open(role: str, need: str, scopes=None) -> bool:
    """Whether a user of that role (through a token: with those scopes) may open what needs need;
    a need nobody knows opens nothing."""
    if need not in NEEDS:
        return False
    role_needed, scope = NEEDS[need]
    return (role_needed == "viewer" or role == "operator") and (scopes is None or scope in scopes)


def bearer(header: str) -> str:
    scheme, _sp, value = (header or "").strip().partition(" ")
    return value.strip() if scheme.lower() == "bearer" else ""


def shown(name) -> str:
    """A user name as the journal gets it (never a forged line)."""
    return name if isinstance(name, str) and door_store.NAME_RE.match(name) else "<invalid>"


LOGIN_PAGE = """<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>Isaac Sim fleet: log in</title>
<meta name="viewport" content="width=device-width, initial-scale=1">
<style>body{{font-family:system-ui,sans-serif;max-width:22em;margin:4em auto}}
label,input,button{{display:block;width:100%;margin:.4em 0}}.error{{color:#b00020}}</style></head>
<body><h1>Isaac Sim fleet</h1>{message}
<form method="post" action="/login">
<input type="hidden" name="next" value="{next}">
<label>User <input name="user" autocomplete="username" required autofocus></label>
<label>Password <input name="password" type="password" autocomplete="current-password" required></label>
<button type="submit">Log in</button></form></body></html>
"""


def say(line: str) -> None:
    """A line for the journal (the unit's stdout), at once."""
    sys.stdout.write(line + "\n")
    sys.stdout.flush()


class Door:
    """The service's state: users (reloaded when their file changes), the store of sessions and
    tokens, the clock."""

    def __init__(self, users_file: str, store_file: str, hours: float, log=say, clock=time.time, turn=None):
        """turn: {url, secret_file, seconds} of the TURN relay whose credentials a session gets."""
        self.users_file, self.hours, self.log, self.clock = users_file, hours, log, clock
        self.store = door_store.Store(store_file, clock=clock)
        self.turn = turn
        self._users, self._mtime = {}, None
        # an unknown user's password is checked against this, so both answers take as long
        self._decoy = hash_password(os.urandom(8).hex())

    def users(self) -> dict:
        mtime = os.stat(self.users_file).st_mtime_ns
        if mtime != self._mtime:
            with open(self.users_file, encoding="utf-8") as f:
                self._users, self._mtime = json.load(f), mtime
        return self._users

    def identify(self, cookie_header: str, authorization: str = ""):
        """{user, role, token, scopes, expires} of the request's token (when it sends one) or
        session: the user still there with that role (and, for a session, that password); else None.
        A token acts with its user's role of now."""
        users = self.users()
        text = bearer(authorization)
        if text:
            token = self.store.token(text)
            record = users.get(token["user"]) if token else None
            if not token or not isinstance(record, dict) or record.get("role") not in ROLES:
                return None
            # made for this user as they are now: not for one removed and made again, or given a new password
            if not hmac.compare_digest(token["owner"], door_store.fingerprint(record.get("hash", ""))):
                return None
            return {
                "user": token["user"],
                "role": record["role"],
                "token": token["name"],
                "scopes": token["scopes"],
                "expires": token["expires"],
            }
        session = self.store.session(cookie_value(cookie_header))
        record = users.get(session["user"]) if session else None
        if not session or not isinstance(record, dict) or record.get("role") != session["role"]:
            return None
        if not hmac.compare_digest(session["fingerprint"], door_store.fingerprint(record.get("hash", ""))):
            return None
        return {
            "user": session["user"],
            "role": session["role"],
            "token": None,
            "scopes": None,
            "expires": session["expires"],
            # what the door's own pages send with a write (the fleet API's X-Fleet-CSRF): bound to this
            # session, which another site's page can never read
            "csrf": csrf_token(cookie_value(cookie_header)),
        }

    @staticmethod
    def _who(who) -> str:
        return f"user={who['user']}" + (f" token={who['token']}" if who and who.get("token") else "")

    def check(
        self, cookie_header: str, path: str, client: str, need: str = "", authorization: str = "", instance: str = ""
    ):
        """(status, identity) for nginx: 204 passes, 401 means log in, 403 refused for the role
        or the token's scopes. path: the request as sent (for the journal only); need: what nginx's
        location asks for; instance: HOST/N of a web viewer's port, which a session may hold."""
        who = self.identify(cookie_header, authorization)
        if who is None:
            what = "no valid token" if bearer(authorization) else "no valid session"
            self.log(f"refused user=- path={path!r} from={client} ({what})")
            return 401, None
        if not may_open(who["role"], need, who["scopes"]):
            wanted = "/".join(NEEDS.get(need, ("?", "?")))
            self.log(f"refused {self._who(who)} path={path!r} from={client} (role {who['role']}, needs {wanted})")
            return 403, who
        host, _sep, n = instance.rpartition("/")
        holder = self.store.session_holder(host, int(n)) if host and n.isdigit() and who["role"] != "operator" else None
        if holder is not None and holder != who["user"]:
            self.log(f"refused {self._who(who)} path={path!r} from={client} (instance {instance}: another's session)")
            return 403, who
        return 204, who

    def whoami(self, cookie_header: str, authorization: str = ""):
        """(status, {user, role, token, scopes}) of the session or token, for the pages behind the door
        (not logged: asked on each page load, and it opens nothing)."""
        who = self.identify(cookie_header, authorization)
        if who is None:
            return 401, None
        scopes = who["scopes"] if who["scopes"] is not None else list(door_store.ROLE_SCOPES[who["role"]])
        answer = {"user": who["user"], "role": who["role"], "token": who["token"], "scopes": scopes}
        if who.get("csrf"):
            answer["csrf"] = who["csrf"]
        return 200, answer

    def relay(self, cookie_header: str, client: str, authorization: str = ""):
        """(status, {iceServers, ttl}) for a logged-in user: short-lived TURN credentials, which
        never outlive the session (or token) they were handed to."""
        who = self.identify(cookie_header, authorization)
        if who is None:
            self.log(f"refused user=- path='/turn-credentials' from={client} (no valid session)")
            return 401, None
        if not may_open(who["role"], "", who["scopes"]):
            self.log(f"refused {self._who(who)} path='/turn-credentials' from={client} (needs the read scope)")
            return 403, None
        with open(self.turn["secret_file"], "rb") as f:
            secret = f.read().strip()
        now = int(self.clock())
        expires = min(now + int(self.turn["seconds"]), int(who["expires"]))
        seconds = expires - now
        name, password = turn_credentials(who["user"], secret, expires)
        self.log(f"turn credentials {self._who(who)} from={client} until={expires}")
        server = {"urls": [self.turn["url"]], "username": name, "credential": password}
        return 200, {"iceServers": [server], "ttl": seconds}

    def login(self, user: str, password: str, client: str):
        """The session cookie's value, or None for a refused login (logged either way)."""
        record = self.users().get(user) if isinstance(user, str) else None
        matches = verify_password(password or "", (record or {}).get("hash") or self._decoy)
        if not record or not matches:
            why = "wrong password" if record else "unknown user"
            self.log(f"login refused user={shown(user)} from={client} ({why})")
            return None
        self.log(f"login user={user} role={record['role']} from={client}")
        secret, _expires = self.store.open_session(user, record["role"], record.get("hash", ""), self.hours, client)
        return secret

    def _person(self, cookie_header: str, authorization: str = ""):
        """(200, identity) of a person logged in; (401, None) without a session, (403, why) for a
        token: a token does not manage tokens."""
        who = self.identify(cookie_header, authorization)
        if who is None:
            return 401, None
        if who["token"]:
            return 403, {"error": "a token does not manage tokens; log in"}
        return 200, who

    def own_tokens(self, cookie_header: str, authorization: str = ""):
        """(status, {user, role, scopes, tokens}) for the console's token page: a person's own
        tokens, with a session only."""
        code, who = self._person(cookie_header, authorization)
        if code != 200:
            return code, who
        mine = [t for t in self.store.tokens() if t["user"] == who["user"]]
        return 200, {
            "user": who["user"],
            "role": who["role"],
            "scopes": list(door_store.ROLE_SCOPES[who["role"]]),
            "tokens": mine,
        }

    def token_change(self, cookie_header: str, body: dict, client: str, revoke: bool = False):
        """(status, answer) for a person making (or revoking) a token of their own from the console."""
        code, who = self._person(cookie_header)
        if code != 200:
            return code, who
        user, name = who["user"], body.get("name")
        if revoke:
            if not isinstance(name, str) or not self.store.revoke(user, name):
                return 404, {"error": f"no live token {name!r} of {user}"}
            self.log(f"token revoked user={user} name={name} from={client}")
            return 200, {"revoked": name}
        scopes, days = body.get("scopes") or ["read"], body.get("days", 30)
        errors = door_store.token_errors(user, who["role"], name, scopes, days)
        if errors:
            return 400, {"errors": errors}
        record = self.users().get(user) or {}
        text, made = self.store.make_token(user, name, scopes, days, record.get("hash", ""))
        self.log(f"token made user={user} name={name} scopes={','.join(scopes)} days={days} from={client}")
        return 201, {"token": text, "record": made}

    def logout(self, cookie_header: str, client: str) -> None:
        """Ends the session the cookie names, here, so the cookie opens nothing anywhere after."""
        user = self.store.end_session(cookie_value(cookie_header))
        if user:
            self.log(f"logout user={user} from={client}")


def handler(door: Door, form_action: str = ""):
    """form_action: sources the login form may lead to besides its own origin (after the login, a
    redirect to a web viewer's port of the front door: Chrome holds each hop to form-action)."""
    sources = " ".join(["'self'", *form_action.split()])
    policy = f"default-src 'none'; style-src 'unsafe-inline'; form-action {sources}; frame-ancestors 'none'"

    class Handler(BaseHTTPRequestHandler):
        server_version = "isaac-sim-front-door"
        sys_version = ""
        timeout = 10  # a client that stops sending holds a thread this long at most

        def _client(self) -> str:
            return self.headers.get("X-Real-IP") or self.client_address[0]

        def _send(self, code: int, body: bytes = b"", headers=(), kind="text/html; charset=utf-8"):
            self.send_response(code)
            for name, value in headers:
                self.send_header(name, value)
            if body:
                self.send_header("Content-Type", kind)
                self.send_header("Content-Security-Policy", policy)
            self.send_header("Cache-Control", "no-store")
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)

        def _page(self, code: int, target: str, message: str = ""):
            text = LOGIN_PAGE.format(
                message=f'<p class="error">{html.escape(message)}</p>' if message else "",
                next=html.escape(safe_next(target), quote=True),
            )
            self._send(code, text.encode())

        def do_GET(self):  # noqa: N802 - http.server's naming
            try:
                self._get()
            except Exception as error:  # pylint: disable=broad-exception-caught
                # one bad request is one answer and one line, never a dead thread or server
                door.log(f"error path={self.path!r} from={self._client()}: {type(error).__name__}")
                self._send(500)

        def do_POST(self):  # noqa: N802
            try:
                self._post()
            except Exception as error:  # pylint: disable=broad-exception-caught
                door.log(f"error path={self.path!r} from={self._client()}: {type(error).__name__}")
                self._send(500)

        def _get(self):
            url = urllib.parse.urlsplit(self.path)
            if url.path == "/auth":
                code, who = door.check(
                    self.headers.get("Cookie", ""),
                    self.headers.get("X-Original-URI", "/"),
                    self._client(),
                    urllib.parse.parse_qs(url.query).get("need", [""])[0],
                    self.headers.get("Authorization", ""),
                    urllib.parse.parse_qs(url.query).get("instance", [""])[0],
                )
                said = [("X-Fleet-User", who["user"])] if who else []
                self._send(code, headers=said + ([("X-Fleet-Token", who["token"])] if who and who["token"] else []))
            elif url.path == "/session":
                code, answer = door.whoami(self.headers.get("Cookie", ""), self.headers.get("Authorization", ""))
                self._send(code, json.dumps(answer).encode() if answer else b"", kind="application/json")
            elif url.path == "/turn-credentials" and door.turn:
                code, answer = door.relay(
                    self.headers.get("Cookie", ""), self._client(), self.headers.get("Authorization", "")
                )
                body = json.dumps(answer).encode() if answer else b""
                self._send(code, body, kind="application/json")
            elif url.path == "/tokens":
                code, answer = door.own_tokens(self.headers.get("Cookie", ""), self.headers.get("Authorization", ""))
                self._send(code, json.dumps(answer).encode() if answer else b"", kind="application/json")
            elif url.path == "/login":
                self._page(200, urllib.parse.parse_qs(url.query).get("next", ["/"])[0])
            elif url.path == "/logout":
                door.logout(self.headers.get("Cookie", ""), self._client())
                self._send(
                    303,
                    headers=[
                        ("Location", "/login"),
                        ("Set-Cookie", f"{COOKIE}=; Path=/; Max-Age=0; Secure; HttpOnly; SameSite=Lax"),
                    ],
                )
            else:
                self._send(404)

        def _another_site(self) -> bool:
            """A request another site's page sent (CSRF): browsers say where it came from, in
            Sec-Fetch-Site or (older ones, and every POST of a page) in Origin, which must be the
            front door's own as nginx saw the browser reach it (X-Fleet-Origin); no Origin: no browser."""
            origin, own = self.headers.get("Origin"), self.headers.get("X-Fleet-Origin")
            return self.headers.get("Sec-Fetch-Site") in ("cross-site", "same-site") or (
                origin is not None and (not own or origin.rstrip("/").lower() != own.rstrip("/").lower())
            )

        def _post(self):
            path = urllib.parse.urlsplit(self.path).path
            if path not in ("/login", "/tokens", "/tokens/revoke"):
                self._send(404)
                return
            length = self.headers.get("Content-Length") or "0"
            if not length.isdigit() or int(length) > 8192:
                self._send(413 if length.isdigit() else 400)
                return
            if self._another_site():
                door.log(f"{path.strip('/').split('/')[0]} refused from={self._client()} (a form of another site)")
                self._send(403)
                return
            if path != "/login":
                self._tokens(path, self.rfile.read(int(length)))
                return
            form = urllib.parse.parse_qs(self.rfile.read(int(length)).decode("utf-8", "replace"))
            user, password = form.get("user", [""])[0], form.get("password", [""])[0]
            target = form.get("next", ["/"])[0]
            # over the address's rate (nginx's limit_req, in dry run so the attempt reaches here): refused
            # without a look at the password, and logged with the user name tried
            if self.headers.get("X-Fleet-Throttle") == "REJECTED_DRY_RUN":
                door.log(f"login throttled user={shown(user)} from={self._client()} (too many attempts)")
                self._page(429, target, "Too many login attempts from this address. Wait a minute and try again.")
                return
            token = door.login(user, password, self._client())
            if token is None:
                self._page(401, target, "Wrong user name or password.")
                return
            max_age = int(door.hours * 3600)
            cookie = f"{COOKIE}={token}; Path=/; Max-Age={max_age}; Secure; HttpOnly; SameSite=Lax"
            self._send(303, headers=[("Location", safe_next(target)), ("Set-Cookie", cookie)])

        def _tokens(self, path: str, raw: bytes):
            # JSON only: a form another site could post without asking is no JSON
            if (self.headers.get("Content-Type") or "").split(";")[0].strip() != "application/json":
                self._send(415, b'{"error": "send JSON"}', kind="application/json")
                return
            try:
                body = json.loads(raw or b"{}")
            except ValueError:
                body = None
            if not isinstance(body, dict):
                self._send(400, b'{"error": "a JSON object, please"}', kind="application/json")
                return
            code, answer = door.token_change(
                self.headers.get("Cookie", ""), body, self._client(), revoke=path == "/tokens/revoke"
            )
            self._send(code, json.dumps(answer).encode() if answer else b"", kind="application/json")

        def log_message(self, *args):
            pass  # the lines that matter are Door's

    return Handler


class Server(ThreadingHTTPServer):
    # a burst of requests at once (nginx passes them on as they come) waits in the kernel, never reset
    request_queue_size = 128
    daemon_threads = True


def main(argv=None):
    import argparse

    parser = argparse.ArgumentParser(description="The front door's login service (isaacsim.fleet)")
    parser.add_argument("--port", type=int, required=True)
    parser.add_argument("--users", required=True)
    parser.add_argument("--store", required=True, help="the SQLite file of sessions and tokens")
    parser.add_argument("--hours", type=float, default=8)
    parser.add_argument("--form-action", default="", help="sources the login may lead to besides itself")
    parser.add_argument("--turn-url", default="", help="the TURN relay (turns:NAME:PORT?transport=tcp)")
    parser.add_argument("--turn-secret", default="", help="the file of the relay's shared secret")
    parser.add_argument("--turn-seconds", type=int, default=3600, help="how long its credentials are good")
    args = parser.parse_args(argv)
    turn = {"url": args.turn_url, "secret_file": args.turn_secret, "seconds": args.turn_seconds}
    # the signing key of the sessions of releases before 0.4.0, which kept none: nothing reads it now
    with contextlib.suppress(FileNotFoundError):
        os.remove(os.path.join(os.path.dirname(args.store), "session.key"))
    door = Door(args.users, args.store, args.hours, turn=turn if args.turn_url else None)
    Server(("127.0.0.1", args.port), handler(door, args.form_action)).serve_forever()


if __name__ == "__main__":
    main()
