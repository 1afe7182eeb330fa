"""The front door's login service (module_utils/front/door_auth.py) and its store (door_store.py):
hashes, sessions kept server-side, API tokens, the decisions nginx asks for, and the service itself
over a real socket."""

from __future__ import annotations

import base64
import hashlib
import hmac
import http.client
import json
import os
import threading
import urllib.parse
from http.server import ThreadingHTTPServer

import pytest
from ansible_collections.isaacsim.fleet.plugins.module_utils.front import door_auth, door_store

# made by passlib 1.7.4: pbkdf2_sha256.using(rounds=1000, salt=b"fleet-salt-16byt").hash("correct horse")
PASSLIB = "$pbkdf2-sha256$1000$ZmxlZXQtc2FsdC0xNmJ5dA$hSivT8ZpaXf5jhjMaT/bchS401SFqVLg0iXf9B.gPrs"
# and with its defaults: pbkdf2_sha256.hash("s3cret")
PASSLIB_DEFAULT = "$pbkdf2-sha256$29000$Yyzl3HsvZcy5lxLiHCMkhA$TM4W7r4uUYQ6eAe1Z5b5px2TMkOSLzNRdTOLxwrjqbY"


def test_hashes_are_passlib_s_both_ways():
    assert door_auth.verify_password("correct horse", PASSLIB)
    assert not door_auth.verify_password("correct horsE", PASSLIB)
    assert door_auth.verify_password("s3cret", PASSLIB_DEFAULT)
    assert door_auth.hash_password("correct horse", 1000, b"fleet-salt-16byt") == PASSLIB
    made = door_auth.hash_password("pw")
    assert made.startswith("$pbkdf2-sha256$29000$") and door_auth.verify_password("pw", made)
    assert made != door_auth.hash_password("pw")  # a new salt each time


@pytest.mark.parametrize(
    "stored, problem",
    [
        (PASSLIB_DEFAULT, None),
        (PASSLIB, "has 1000 rounds, fewer than 10000"),
        ("$6$salt$crypt", "is not a PBKDF2-SHA256 hash"),
        ("s3cret", "is not a PBKDF2-SHA256 hash"),
        ("$pbkdf2-sha256$29000$!!$??", "is not a PBKDF2-SHA256 hash"),
        (None, "is not a PBKDF2-SHA256 hash"),
    ],
)
def test_a_hash_the_service_cannot_use_is_named(stored, problem):
    found = door_auth.hash_error(stored)
    assert (found is None) if problem is None else found.startswith(problem)
    assert not door_auth.verify_password("x", stored if isinstance(stored, str) else "")


USERS = {"olga": {"role": "operator", "hash": PASSLIB_DEFAULT}, "vic": {"role": "viewer", "hash": PASSLIB_DEFAULT}}


def door(tmp_path, users=None, **kwargs):
    (tmp_path / "users.json").write_text(json.dumps(USERS if users is None else users))
    return door_auth.Door(str(tmp_path / "users.json"), str(tmp_path / "door.db"), 1, **kwargs)


def users_now(tmp_path, users):
    """A changed users file, as a re-run of the role writes it (another mtime)."""
    (tmp_path / "users.json").write_text(json.dumps(users))
    os.utime(tmp_path / "users.json", ns=(1, os.stat(tmp_path / "users.json").st_mtime_ns + 1))


def test_a_session_holds_until_logout_expiry_or_its_user_s_role_or_password_changes(tmp_path):
    now = [1000.0]
    d = door(tmp_path, log=lambda line: None, clock=lambda: now[0])
    cookie = f"{door_auth.COOKIE}=" + d.login("vic", "s3cret", "10.0.0.1")
    assert d.identify(cookie)["user"] == "vic"
    # only the digest of the cookie is kept: the file gives no session away
    assert cookie.split("=", 1)[1].encode() not in (tmp_path / "door.db").read_bytes()
    assert d.identify(cookie[:-1] + ("A" if cookie[-1] != "A" else "B")) is None
    # a restarted service (a new Door on the same file) keeps it
    again = door(tmp_path, log=lambda line: None, clock=lambda: now[0])
    assert again.identify(cookie)["role"] == "viewer"
    now[0] += 3600
    assert d.identify(cookie) is None  # expired
    now[0] = 1000.0
    users_now(tmp_path, {"vic": {"role": "operator", "hash": PASSLIB_DEFAULT}})
    assert d.identify(cookie) is None  # another role
    users_now(tmp_path, {"vic": {"role": "viewer", "hash": PASSLIB}})
    assert d.identify(cookie) is None  # a new password
    users_now(tmp_path, {})
    assert d.identify(cookie) is None  # removed
    users_now(tmp_path, USERS)
    assert d.identify(cookie)["user"] == "vic"
    # a logout ends it, wherever the cookie is sent from next
    d.logout(cookie, "10.0.0.1")
    assert d.identify(cookie) is None and again.identify(cookie) is None
    for junk in ("", "garbage", f"{door_auth.COOKIE}=", f"{door_auth.COOKIE}=\u0100", None):
        assert d.identify(junk) is None


def test_a_token_acts_as_its_user_within_its_scopes_until_revoked_or_expired(tmp_path):
    now = [1000.0]
    lines = []
    d = door(tmp_path, log=lines.append, clock=lambda: now[0])
    text, record = d.store.make_token("olga", "ci", ["read", "act"], 2, PASSLIB_DEFAULT)
    assert text.startswith("isf_") and record["state"] == "active" and record["expires"] == 1000 + 2 * 86400
    bearer = f"Bearer {text}"
    assert d.check("", "/api/fleet", "10.0.0.9", "", bearer)[0] == 204
    assert d.check("", "/api/x", "10.0.0.9", "act", bearer)[0] == 204
    code, who = d.check("", "/api/hosts/a/drain", "10.0.0.9", "operate", bearer)
    assert code == 403 and who["token"] == "ci"
    assert lines[-1] == (
        "refused user=olga token=ci path='/api/hosts/a/drain' from=10.0.0.9 (role operator, needs operator/operate)"
    )
    # the scheme's name in any case; a wrong secret, a made-up id or a cookie's value are no token
    assert d.check("", "/", "x", "", f"bearer {text}")[0] == 204
    assert d.check("", "/", "x", "", bearer[:-1] + ("A" if bearer[-1] != "A" else "B"))[0] == 401
    assert lines[-1] == "refused user=- path='/' from=x (no valid token)"
    assert d.check("", "/", "x", "", "Bearer isf_000000000000_" + "A" * 43)[0] == 401
    # a token with a bad Authorization never falls back to the cookie's session
    cookie = f"{door_auth.COOKIE}=" + d.login("olga", "s3cret", "x")
    assert d.check(cookie, "/", "x", "", "Bearer nonsense")[0] == 401
    assert d.check(cookie, "/", "x", "", "Basic b2xnYTpz")[0] == 204
    # the user's role of now: demoted, the token's act scope opens nothing
    users_now(tmp_path, {"olga": {"role": "viewer", "hash": PASSLIB_DEFAULT}})
    assert d.check("", "/", "x", "act", bearer)[0] == 403 and d.check("", "/", "x", "", bearer)[0] == 204
    users_now(tmp_path, {})
    assert d.check("", "/", "x", "", bearer)[0] == 401
    # made again (another person, perhaps) or given a new password: the old tokens stay dead
    users_now(tmp_path, {"olga": {"role": "operator", "hash": PASSLIB}})
    assert d.check("", "/", "x", "", bearer)[0] == 401
    users_now(tmp_path, USERS)
    assert d.check("", "/", "x", "", bearer)[0] == 204
    # revoked, or a new token of that name: the old one ends
    newer, _r = d.store.make_token("olga", "ci", ["read"], 1, PASSLIB_DEFAULT)
    assert d.check("", "/", "x", "", bearer)[0] == 401 and d.check("", "/", "x", "", f"Bearer {newer}")[0] == 204
    assert d.store.revoke("olga", "ci") and not d.store.revoke("olga", "ci")
    assert d.check("", "/", "x", "", f"Bearer {newer}")[0] == 401
    short, _r = d.store.make_token("vic", "look", ["read"], 1, PASSLIB_DEFAULT)
    now[0] += 86400
    assert d.check("", "/", "x", "", f"Bearer {short}")[0] == 401
    states = [(t["name"], t["state"]) for t in d.store.tokens()]
    assert sorted(states) == [("ci", "revoked"), ("ci", "revoked"), ("look", "expired")]
    assert all("digest" not in t for t in d.store.tokens())


@pytest.mark.parametrize(
    "user, role, name, scopes, days, problem",
    [
        ("olga", "operator", "ci", ["read", "act", "operate"], 365, None),
        ("vic", "viewer", "ci", ["read"], 1, None),
        ("vic", "viewer", "ci", ["read", "act"], 30, "scopes: vic is a viewer, who may hold read, use only."),
        ("ann", None, "ci", ["read"], 30, "user: 'ann' is not a user of this front door."),
        ("olga", "operator", "ci x", ["read"], 30, "name: 'ci x' is not a token name."),
        ("olga", "operator", "ci", [], 30, "scopes: [] is not a choice."),
        ("olga", "operator", "ci", ["write"], 30, "scopes: ['write'] is not a choice."),
        ("olga", "operator", "ci", ["read"], 0, "days: 0 is not 1-365."),
        ("olga", "operator", "ci", ["read"], 366, "days: 366 is not 1-365."),
        ("olga", "operator", "ci", ["read"], True, "days: True is not 1-365."),
    ],
)
def test_a_token_asked_for_wrongly_is_named(user, role, name, scopes, days, problem):
    errors = door_store.token_errors(user, role, name, scopes, days)
    assert (errors == []) if problem is None else (len(errors) == 1 and errors[0].startswith(problem)), errors


def test_the_store_is_root_s_alone_and_keeps_no_secret(tmp_path):
    store = door_store.Store(str(tmp_path / "door.db"))
    assert (tmp_path / "door.db").stat().st_mode & 0o777 == 0o600
    text, _r = store.make_token("olga", "ci", ["read"], 1, PASSLIB_DEFAULT)
    secret, _e = store.open_session("olga", "operator", PASSLIB_DEFAULT, 1, "x")
    data = (tmp_path / "door.db").read_bytes()
    # (the secret may hold "_" itself: the token's own pattern splits it)
    assert door_store._TOKEN_RE.match(text).group(2).encode() not in data and secret.encode() not in data
    assert [s["user"] for s in store.sessions()] == ["olga"]


@pytest.mark.parametrize(
    "target, expected",
    [
        ("/hosts/a/status", "/hosts/a/status"),
        ("", "/"),
        ("https://evil.example/", "/"),
        ("//evil.example/", "/"),
        ("/\\evil.example", "/"),
        ("/a\r\nSet-Cookie: x", "/"),
        ("/\u0100", "/"),
    ],
)
def test_after_login_only_a_path_of_the_front_door(target, expected):
    assert door_auth.safe_next(target) == expected


def test_operator_paths_and_names_in_the_journal():
    assert door_auth.may_open("viewer", "") and not door_auth.may_open("viewer", "operator")
    assert door_auth.may_open("operator", "operator") and not door_auth.may_open("operator", "root")
    # a token: its scopes too
    assert door_auth.may_open("operator", "act", ["read", "act"])
    assert not door_auth.may_open("operator", "act", ["read"])
    assert door_auth.may_open("viewer", "", ["read"]) and not door_auth.may_open("viewer", "act", ["act"])
    assert door_auth.bearer("Bearer  isf_x ") == "isf_x" and door_auth.bearer("Basic x") == ""
    assert door_auth.shown("olga") == "olga" and door_auth.shown("x\nlogin user=root") == "<invalid>"
    assert door_auth.cookie_value("a=1; __Host-fleet_session=T.S; b=2") == "T.S" and door_auth.cookie_value(None) == ""


@pytest.fixture
def service(tmp_path):
    users = tmp_path / "users.json"
    users.write_text(json.dumps(USERS))
    lines = []
    door = door_auth.Door(str(users), str(tmp_path / "door.db"), hours=1, log=lines.append)
    server = ThreadingHTTPServer(("127.0.0.1", 0), door_auth.handler(door, "https://fleet.lab:*"))
    threading.Thread(target=server.serve_forever, daemon=True).start()
    yield server.server_address[1], lines, tmp_path
    server.shutdown()
    server.server_close()


def call(port, method, path, body=None, headers=None):
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=5)
    conn.request(method, path, body=urllib.parse.urlencode(body) if body else None, headers=headers or {})
    response = conn.getresponse()
    data = response.read()
    conn.close()
    return response, data


def test_the_service_logs_in_decides_and_writes_each_refusal_down(service):
    port, lines, tmp_path = service
    response, page = call(port, "GET", "/login?next=/hosts/a/status")
    assert response.status == 200 and b'value="/hosts/a/status"' in page
    # the login may lead on to a web viewer's port of the front door, nowhere else
    assert "form-action 'self' https://fleet.lab:*;" in response.getheader("Content-Security-Policy")
    # no session: 401 for nginx, written down with the path and the client nginx names
    response, _body = call(port, "GET", "/auth", headers={"X-Original-URI": "/hosts/a/status", "X-Real-IP": "10.1.2.3"})
    assert (
        response.status == 401 and lines[-1] == "refused user=- path='/hosts/a/status' from=10.1.2.3 (no valid session)"
    )
    response, page = call(port, "POST", "/login", {"user": "vic", "password": "nope", "next": "/x"})
    assert (
        response.status == 401 and b"Wrong user name or password" in page and response.getheader("Set-Cookie") is None
    )
    assert lines[-1] == "login refused user=vic from=127.0.0.1 (wrong password)"
    call(port, "POST", "/login", {"user": "nobody\nlogin user=root", "password": "x"})
    assert lines[-1] == "login refused user=<invalid> from=127.0.0.1 (unknown user)"
    response, _body = call(port, "POST", "/login", {"user": "vic", "password": "s3cret", "next": "//evil.example/"})
    assert response.status == 303 and response.getheader("Location") == "/"
    cookie = response.getheader("Set-Cookie")
    assert cookie.endswith("; Path=/; Max-Age=3600; Secure; HttpOnly; SameSite=Lax")
    assert lines[-1] == "login user=vic role=viewer from=127.0.0.1"
    session = {"Cookie": cookie.split(";", 1)[0], "X-Original-URI": "/hosts/a/status"}
    response, _body = call(port, "GET", "/auth", headers=session)
    assert response.status == 204 and response.getheader("X-Fleet-User") == "vic"
    # who is logged in, for the pages behind the door; nothing for a request without a session
    response, body = call(port, "GET", "/session", headers=session)
    assert response.status == 200
    secret = session["Cookie"].split("=", 1)[1]
    assert json.loads(body) == {
        "user": "vic",
        "role": "viewer",
        "token": None,
        "scopes": ["read", "use"],
        # the session's CSRF token, for the door's own pages (the fleet API's writes)
        "csrf": door_auth.csrf_token(secret),
    }
    assert call(port, "GET", "/session")[0].status == 401
    assert call(port, "GET", "/session", headers={"Cookie": session["Cookie"][:-2] + "xx"})[0].status == 401
    # what a path needs is nginx's location's to say (need=), whatever the raw path looks like
    odd = dict(session, **{"X-Original-URI": "/%6Fperator/x"})
    response, _body = call(port, "GET", "/auth?need=operator", headers=odd)
    assert response.status == 403 and lines[-1].startswith("refused user=vic path='/%6Fperator/x'")
    # a logout ends the session here: the cookie, kept, opens nothing after
    response, _body = call(port, "GET", "/logout", headers=session)
    assert response.status == 303 and "Max-Age=0" in response.getheader("Set-Cookie")
    assert lines[-1] == "logout user=vic from=127.0.0.1"
    assert call(port, "GET", "/auth", headers=session)[0].status == 401
    assert call(port, "GET", "/session", headers=session)[0].status == 401
    # a token: its user and name for nginx's log
    text, _r = door_store.Store(str(tmp_path / "door.db")).make_token("olga", "ci", ["read"], 1, PASSLIB_DEFAULT)
    response, _body = call(port, "GET", "/auth", headers={"Authorization": f"Bearer {text}"})
    assert response.status == 204 and (response.getheader("X-Fleet-User"), response.getheader("X-Fleet-Token")) == (
        "olga",
        "ci",
    )
    response, body = call(port, "GET", "/session", headers={"Authorization": f"Bearer {text}"})
    assert json.loads(body) == {"user": "olga", "role": "operator", "token": "ci", "scopes": ["read"]}
    # a changed users file is read again: olga removed, her token opens nothing
    users_now(tmp_path, {"vic": USERS["vic"]})
    assert call(port, "GET", "/auth", headers={"Authorization": f"Bearer {text}"})[0].status == 401
    users_now(tmp_path, USERS)
    # bad requests: one answer each, and the service goes on
    assert call(port, "GET", "/auth", headers={"Cookie": "__Host-fleet_session=%C3.x"})[0].status == 401
    assert call(port, "POST", "/login", headers={"Content-Length": "abc"})[0].status == 400
    assert call(port, "POST", "/login", headers={"Content-Length": "99999"})[0].status == 413
    form = {"user": "olga", "password": "s3cret"}
    response, _body = call(port, "POST", "/login", form, {"Sec-Fetch-Site": "cross-site"})
    assert response.status == 403 and lines[-1] == "login refused from=127.0.0.1 (a form of another site)"
    # no Sec-Fetch-Site (an older browser): the Origin decides, against the door's own as nginx saw it
    own = {"X-Fleet-Origin": "https://fleet.lab:8443"}
    for origin in ("https://evil.example", "null", "https://fleet.lab"):
        response, _body = call(port, "POST", "/login", form, dict(own, Origin=origin))
        assert response.status == 403, origin
    # an Origin where the door's own is not known is refused too (fails closed)
    assert call(port, "POST", "/login", form, {"Origin": "https://fleet.lab:8443"})[0].status == 403
    response, _body = call(port, "POST", "/login", form, dict(own, Origin="https://FLEET.lab:8443"))
    assert response.status == 303
    response, _body = call(port, "POST", "/login", dict(form, next="/\u0100"))
    assert response.status == 303 and response.getheader("Location") == "/"
    # over nginx's rate (limit_req in dry run): refused here, good password or not, with the user tried logged
    for throttle, status in (("REJECTED_DRY_RUN", 429), ("PASSED", 303)):
        response, _body = call(port, "POST", "/login", form, {"X-Fleet-Throttle": throttle})
        assert response.status == status, throttle
    assert "login throttled user=olga from=127.0.0.1 (too many attempts)" in lines
    assert call(port, "GET", "/login")[0].status == 200


def test_turn_credentials_are_coturn_s_shared_secret_scheme():
    # coturn (use-auth-secret) recomputes the password from the name: base64(HMAC-SHA1(secret, name))
    name, password = door_auth.turn_credentials("vic", b"north", 1795000000)
    assert name == "1795000000:vic"
    assert password == base64.b64encode(hmac.new(b"north", b"1795000000:vic", hashlib.sha1).digest()).decode()


def test_a_logged_in_user_gets_relay_credentials_written_down_and_nobody_else(tmp_path):
    users = tmp_path / "users.json"
    users.write_text(json.dumps(USERS))
    (tmp_path / "turn.secret").write_text("north\n")
    lines, now = [], [1795000000.0]
    turn = {"url": "turns:fleet.lab:5349?transport=tcp", "secret_file": str(tmp_path / "turn.secret"), "seconds": 600}
    door = door_auth.Door(str(users), str(tmp_path / "door.db"), 1, log=lines.append, clock=lambda: now[0], turn=turn)
    server = ThreadingHTTPServer(("127.0.0.1", 0), door_auth.handler(door))
    threading.Thread(target=server.serve_forever, daemon=True).start()
    port = server.server_address[1]
    try:
        response, body = call(port, "GET", "/turn-credentials", headers={"X-Real-IP": "10.1.2.3"})
        assert response.status == 401 and body == b""
        assert lines[-1] == "refused user=- path='/turn-credentials' from=10.1.2.3 (no valid session)"
        cookie = call(port, "POST", "/login", {"user": "vic", "password": "s3cret"})[0].getheader("Set-Cookie")
        response, body = call(port, "GET", "/turn-credentials", headers={"Cookie": cookie.split(";", 1)[0]})
        assert response.status == 200 and response.getheader("Content-Type") == "application/json"
        answer = json.loads(body)
        name, password = door_auth.turn_credentials("vic", b"north", 1795000600)
        assert answer == {
            "iceServers": [{"urls": ["turns:fleet.lab:5349?transport=tcp"], "username": name, "credential": password}],
            "ttl": 600,
        }
        assert lines[-1] == "turn credentials user=vic from=127.0.0.1 until=1795000600"
        # a token must be allowed to read to get them
        acting, _r = door.store.make_token("olga", "act", ["act"], 1, PASSLIB_DEFAULT)
        response, _b = call(port, "GET", "/turn-credentials", headers={"Authorization": f"Bearer {acting}"})
        assert response.status == 403 and lines[-1].startswith("refused user=olga token=act path='/turn-credentials'")
        # never past the session's end (an hour after the login here)
        door.turn = dict(turn, seconds=7200)
        now[0] += 1800
        answer = json.loads(call(port, "GET", "/turn-credentials", headers={"Cookie": cookie.split(";", 1)[0]})[1])
        assert answer["ttl"] == 1800 and answer["iceServers"][0]["username"] == "1795003600:vic"
    finally:
        server.shutdown()
        server.server_close()
    # a service without a relay has no such path
    assert door_auth.Door(str(users), str(tmp_path / "door.db"), 1).turn is None


def post_json(port, path, body, headers=None):
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=5)
    conn.request("POST", path, body=json.dumps(body), headers={"Content-Type": "application/json", **(headers or {})})
    response = conn.getresponse()
    data = response.read()
    conn.close()
    return response.status, json.loads(data) if data else None


def test_a_person_makes_and_revokes_tokens_of_their_own_from_the_console(service):
    port, lines, tmp_path = service
    session = call(port, "POST", "/login", {"user": "vic", "password": "s3cret"})[0].getheader("Set-Cookie")
    own = {"Cookie": session.split(";", 1)[0], "X-Fleet-Origin": "https://fleet.lab", "Origin": "https://fleet.lab"}
    status, made = post_json(port, "/tokens", {"name": "laptop", "scopes": ["read"], "days": 7}, own)
    assert status == 201 and made["token"].startswith("isf_") and made["record"]["user"] == "vic"
    assert lines[-1] == "token made user=vic name=laptop scopes=read days=7 from=127.0.0.1"
    bearer = {"Authorization": f"Bearer {made['token']}", "X-Original-URI": "/"}
    assert call(port, "GET", "/auth", headers=bearer)[0].status == 204
    # listed for its own person only, never its secret; a token manages no tokens
    response, body = call(port, "GET", "/tokens", headers={"Cookie": own["Cookie"]})
    listed = json.loads(body)
    assert response.status == 200 and [t["name"] for t in listed["tokens"]] == ["laptop"]
    assert listed["scopes"] == ["read", "use"] and "token" not in listed["tokens"][0]
    assert call(port, "GET", "/tokens", headers=bearer)[0].status == 403
    assert post_json(port, "/tokens", {"name": "x"}, {"Authorization": bearer["Authorization"]})[0] == 401
    # a viewer asks for more than a viewer may hold: refused, each problem named
    status, refused = post_json(port, "/tokens", {"name": "ops", "scopes": ["act"], "days": 400}, own)
    assert status == 400 and [e.split(":")[0] for e in refused["errors"]] == ["scopes", "days"]
    # another site's page, a form (no JSON) or no session: refused before anything is made
    assert post_json(port, "/tokens", {"name": "evil"}, dict(own, Origin="https://evil.example"))[0] == 403
    assert post_json(port, "/tokens", {"name": "evil"}, dict(own, **{"Sec-Fetch-Site": "cross-site"}))[0] == 403
    assert call(port, "POST", "/tokens", {"name": "evil"}, {"Cookie": own["Cookie"]})[0].status == 415
    assert post_json(port, "/tokens", {"name": "evil"})[0] == 401
    assert [t["name"] for t in json.loads(call(port, "GET", "/tokens", headers=own)[1])["tokens"]] == ["laptop"]
    status, _a = post_json(port, "/tokens/revoke", {"name": "laptop"}, own)
    assert status == 200 and lines[-1] == "token revoked user=vic name=laptop from=127.0.0.1"
    assert call(port, "GET", "/auth", headers=bearer)[0].status == 401
    assert post_json(port, "/tokens/revoke", {"name": "laptop"}, own)[0] == 404
