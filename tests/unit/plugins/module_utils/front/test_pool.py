"""Sessions from the one pool (module_utils/front/pool.py), end to end over real sockets: the login
service says who asks, the fleet API takes the request, the pool claims instances through two hosts'
real action agents (module_utils/instance/agent.py, mutual TLS) that run the lifecycle on scripted
hosts; each host's status is read from its scripted host, as its status endpoint reads the real one."""

from __future__ import annotations

import hashlib
import io
import json
import os
import socket
import sqlite3
import stat
import tarfile
import threading
import urllib.parse

import pytest
from ansible_collections.isaacsim.fleet.plugins.module_utils.front import door_auth, fleet_api, pool
from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib import layout
from ansible_collections.isaacsim.fleet.plugins.module_utils.instance import agent, lifecycle
from ansible_collections.isaacsim.fleet.tests.unit.helpers import issue, make_pki
from ansible_collections.isaacsim.fleet.tests.unit.plugins.module_utils.front.test_fleet_api import HASH
from ansible_collections.isaacsim.fleet.tests.unit.plugins.module_utils.front.test_fleet_api_actions import (
    ORIGIN,
    call,
)
from ansible_collections.isaacsim.fleet.tests.unit.plugins.module_utils.instance.test_lifecycle import ScriptedHost

HOSTS = ("gpu-1", "gpu-2")


def serve(handler_class):
    """A service as the door runs it (its backlog too)."""
    server = fleet_api.Server(("127.0.0.1", 0), handler_class)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    return server


@pytest.fixture(scope="module")
def pki(tmp_path_factory):
    d = make_pki(tmp_path_factory.mktemp("pki"), agent.CLIENT_NAME)
    issue(d, "ca", "gpu-2 agent", "serverAuth", "IP:127.0.0.1", 5, stem="agent2")
    return d


def tar_of(files: dict) -> bytes:
    """A tar of {name: bytes}, as a host's agent gives a stash of Documents."""
    out = io.BytesIO()
    with tarfile.open(fileobj=out, mode="w") as tar:
        for name, data in sorted(files.items()):
            info = tarfile.TarInfo(name)
            info.size = len(data)
            tar.addfile(info, io.BytesIO(data))
    return out.getvalue()


def files_of(data: bytes) -> dict:
    """{name: bytes} of a tar's files."""
    with tarfile.open(fileobj=io.BytesIO(data)) as tar:
        return {m.name: tar.extractfile(m).read() for m in tar if m.isreg()}


class HostFiles:
    """Each host's side of /files as its agent serves it, on the door's Agents: a give-back moves the instance's
    Documents (docs) aside into a stash named after its holder; GET /files/HOLDER?max= gives the stash as a tar
    (404 none, 413 over max), DELETE removes it, PUT ?instance=N unpacks a tar into the Documents of the
    instance the holder holds (409 otherwise). The rest goes to the hosts' real agents."""

    def __init__(self, fleet):
        self.fleet = fleet
        self.docs, self.stash, self.calls = {}, {}, []
        # hosts whose agent does not answer about files; the answer every PUT gets instead of one
        self.broken, self.put_answer = set(), None
        agents = fleet.pool.agents
        self._ask = agents.ask
        agents.ask, agents.fetch, agents.send = self.ask, self.fetch, self.send

    def _reach(self, host, method, path):
        if host in self.broken:
            raise OSError("connection refused")
        self.calls.append((method, host, path))
        address = urllib.parse.urlsplit(path)
        return address.path.split("/")[2], urllib.parse.parse_qs(address.query)

    def ask(self, host, method, path, body=None):
        if path.startswith("/files/"):
            holder, _query = self._reach(host, method, path)
            assert method == "DELETE"
            return 200, {"removed": self.stash.pop((host, holder), None) is not None}
        if body and body.get("action") == "give_back":
            docs = self.docs.pop((host, body["ids"][0]), None)
            if docs is not None:
                self.stash[(host, body["holder"])] = tar_of(docs)
        return self._ask(host, method, path, body)

    def fetch(self, host, path, max_bytes, into=None):
        holder, query = self._reach(host, "GET", path)
        limit = int(query["max"][0])
        # the door reads a tar somewhat larger than the files it holds, never much more
        assert max_bytes == 2 * limit + pool.TAR_SLACK
        data = self.stash.get((host, holder))
        if data is None:
            return 404, {"error": f"no files of {holder}"}
        total = sum(len(v) for v in files_of(data).values())
        if total > limit:
            return 413, {"error": "over max", "bytes": total}
        if into is None:
            return 200, data
        into.write(data)
        return 200, len(data)

    def send(self, host, path, data):
        holder, query = self._reach(host, "PUT", path)
        body = data if isinstance(data, bytes) else data.read()
        if self.put_answer:
            return self.put_answer
        n = int(query["instance"][0])
        if lifecycle.lent_to(self.fleet.scripted[host].host, n) != holder:
            return 409, {"error": f"instance {n} is not lent to {holder}"}
        files = files_of(body)
        self.docs.setdefault((host, n), {}).update(files)
        return 200, {"put": len(files), "bytes": len(body)}

    def moves(self, *methods):
        return [c for c in self.calls if c[0] in methods]


class Clock:
    def __init__(self):
        self.now = 1_800_000_000.0

    def __call__(self):
        return self.now


class Fleet:
    """2 hosts x 4 instances behind a door: the login service, the API with its pool, each host's agent."""

    def __init__(self, tmp_path, pki, rules=None):
        users = {name: {"role": "viewer", "hash": HASH} for name in ("vic", *(f"u{k}" for k in range(20)))}
        users["olga"] = {"role": "operator", "hash": HASH}
        (tmp_path / "users.json").write_text(json.dumps(users))
        self.db = str(tmp_path / "door.db")
        self.door = door_auth.Door(str(tmp_path / "users.json"), self.db, 1, log=lambda line: None)
        self.servers = [serve(door_auth.handler(self.door))]
        self.scripted, self.agents, self.down = {}, {}, set()
        config = {"door": ORIGIN + "/", "session_hours": 8, "hosts": [], "entrances": {}}
        for name, stem in zip(HOSTS, ("agent", "agent2")):
            scripted = ScriptedHost(4)
            a = agent.Agent(
                name,
                str(tmp_path / name),
                host=lambda s=scripted: s.host,
                lock=str(tmp_path / f"{name}.lock"),
                record=str(tmp_path / f"{name}.record"),
                drained=str(tmp_path / f"{name}.drained"),
                journal=lambda line, unit="": None,
                renew_s=0.05,
            )
            ctx = agent.tls_context(str(pki / f"{stem}.crt"), str(pki / f"{stem}.key"), str(pki / "ca.crt"))
            channel = agent.Server(
                ("127.0.0.1", 0), agent.handler(a), ctx, [agent.ipaddress.ip_network("127.0.0.0/8")],
                log=lambda line: None,
            )  # fmt: skip
            threading.Thread(target=channel.serve_forever, daemon=True).start()
            self.servers.append(channel)
            self.scripted[name], self.agents[name] = scripted, a
            config["hosts"].append(
                {"name": name, "status_url": f"http://{name}/status",
                 "agent_url": f"https://127.0.0.1:{channel.server_address[1]}"}
            )  # fmt: skip
            config["entrances"][name] = {str(i): f"{ORIGIN}:{8100 + i}/" for i in range(4)}
        self.config = config
        tls = {"ca": str(pki / "ca.crt"), "cert": str(pki / f"{agent.CLIENT_NAME}.crt"),
               "key": str(pki / f"{agent.CLIENT_NAME}.key")}  # fmt: skip
        self.fleet = fleet_api.Fleet(config, ttl=0, timeout=2, fetch=self.status)
        self.clock = Clock()
        self.lines = []
        self.pool = pool.Pool(
            pool.Store(self.db, clock=self.clock),
            self.fleet,
            fleet_api.Agents(config, tls, timeout=3),
            rules or {},
            log=self.lines.append,
            clock=self.clock,
        )
        service = fleet_api.Api(
            self.fleet,
            lambda cookie, auth: fleet_api.ask_identity(f"http://127.0.0.1:{self.servers[0].server_address[1]}",
                                                        cookie, auth),
            log=self.lines.append,
            agents=self.pool.agents,
            limiter=fleet_api.Limiter(1000),
            pool=self.pool,
        )  # fmt: skip
        self.servers.append(serve(fleet_api.handler(service)))
        self.port = self.servers[-1].server_address[1]
        self.files = HostFiles(self)
        # the people's files, beside the store as the pool keeps them by default
        self.files_dir = tmp_path / "files"

    def kept(self, user):
        """{name: bytes} of the person's tar on the door; None: there is none."""
        path = self.files_dir / pool.files_name(user)
        return files_of(path.read_bytes()) if path.exists() else None

    def status(self, url):
        """What the host's status endpoint gives of its instances: configured, ready, held by whom."""
        name = url.split("/")[2]
        if name in self.down:
            raise OSError("connection refused")
        scripted = self.scripted[name]
        instances = [
            {"id": i, "configured": True, "ready": i in scripted.markers, "release": "5.0",
             "lent_to": lifecycle.lent_to(scripted.host, i),
             "lent_ending": json.loads(scripted.files.get(lifecycle.ending_marker(i), ("null",))[0])}
            for i in range(4)
        ]  # fmt: skip
        return json.dumps({"instances": instances, "drained": self.agents[name].drained_by()}).encode()

    def answers_again(self, name):
        """The host's status answers again, and the door's reads have seen it: a host whose last read failed is
        listed from that failure while it is asked again, so the request after that read ends is the first
        to see it (fleet_api.Fleet)."""
        self.down.discard(name)
        for _read in range(100):
            if next(h for h in self.fleet.hosts() if h["name"] == name)["reachable"]:
                return
            threading.Event().wait(0.02)
        raise AssertionError(f"{name} never answered again")

    def token(self, user):
        return self.door.store.make_token(user, "s", ["read", "use"], 1, HASH)[0]

    def held(self):
        """{(host, instance): holder} as the hosts' own markers say."""
        return {
            (name, i): lifecycle.lent_to(s.host, i)
            for name, s in self.scripted.items()
            for i in range(4)
            if lifecycle.lent_to(s.host, i)
        }

    def settle(self, rounds=40):
        """Ticks until no give-back is pending."""
        for _round in range(rounds):
            self.pool.tick()
            if not self.pool.store.sim_sessions(("ending",)):
                return
            threading.Event().wait(0.05)
        raise AssertionError("a give-back never ended")

    def close(self):
        for s in self.servers:
            s.shutdown()
            s.server_close()


@pytest.fixture
def fleet(tmp_path, pki):
    f = Fleet(tmp_path, pki)
    yield f
    f.close()


def test_twenty_requests_at_once_for_eight_free_instances_grant_eight_and_queue_twelve_in_order(fleet):
    tokens = {f"u{k}": fleet.token(f"u{k}") for k in range(20)}
    answers = {}

    def ask(user):
        answers[user] = call(fleet.port, "/api/sessions", token=tokens[user], body={})

    threads = [threading.Thread(target=ask, args=(u,)) for u in tokens]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    granted = {u: a for u, (code, a) in answers.items() if code == 201}
    queued = {u: a for u, (code, a) in answers.items() if code == 202}
    assert len(granted) == 8 and len(queued) == 12, answers
    # nothing was restarted: each claim took a free instance, and none was taken and given back
    assert [fleet.scripted[h].commands("restart") for h in HOSTS] == [[], []]
    # eight different instances, four on each host (the least loaded first), and each host's own marker agrees
    places = {(a["host"], a["instance"]) for a in granted.values()}
    assert len(places) == 8
    assert fleet.held() == {(a["host"], a["instance"]): a["holder"] for a in granted.values()}
    assert all(a["entrance"] == f"{ORIGIN}:{8100 + a['instance']}/" for a in granted.values())
    # the queue is in the order the requests came: everyone granted came before everyone queued
    rows = {r["id"]: r for r in fleet.pool.store.sim_sessions()}
    queue = fleet.pool.store.queue()
    assert [e["user"] for e in queue] == sorted(queued, key=lambda u: queue[[e["user"] for e in queue].index(u)]["seq"])
    assert max(rows[a["id"]]["created"] for a in granted.values()) <= min(e["created"] for e in queue)
    assert [fleet.pool.look(e["id"], e["user"], False)["place"] for e in queue] == list(range(1, 13))
    # one each: asking again is refused, naming what the person has
    code, again = call(fleet.port, "/api/sessions", token=tokens["u0"], body={})
    assert code == 409 and "the most allowed (1)" in again["error"]


def test_an_ended_session_s_instance_is_reset_then_goes_to_the_head_of_the_queue(fleet):
    for k in range(9):
        fleet.pool.request(f"u{k}", {})
    first = next(s for s in fleet.pool.store.sim_sessions() if s["user"] == "u0")
    [waiting] = fleet.pool.store.queue()
    assert waiting["user"] == "u8"
    restarts = len(fleet.scripted[first["host"]].commands("restart"))
    ended = fleet.pool.end(first["id"], "u0", False)
    assert ended["state"] == "ending" and ended["why"] == "ended by its holder"
    fleet.settle()
    # the instance was restarted (a fresh container) before anyone else got it; then u8 had it
    assert fleet.scripted[first["host"]].commands("restart")[restarts:] == [
        f"systemctl restart {layout.unit(first['instance'])}"
    ]
    assert fleet.pool.store.get(first["id"])["state"] == "ended"
    mine = fleet.pool.mine("u8")
    assert [(m["state"], m["host"], m["instance"]) for m in mine] == [("active", first["host"], first["instance"])]
    assert fleet.held()[(first["host"], first["instance"])] == pool.HOLDER.format(mine[0]["id"])
    assert any("given back after" in line for line in fleet.lines)


def test_the_queue_gets_an_instance_its_give_back_freed_before_the_hosts_status_shows_it_free(fleet):
    for k in range(9):
        fleet.pool.request(f"u{k}", {})
    first = next(s for s in fleet.pool.store.sim_sessions() if s["user"] == "u0")
    where = (first["host"], first["instance"])
    # the hosts' status as read now, kept from here on: it shows the instance held by u0's session (a host
    # and the door each reuse a status read for 2 s, so a fresh one can say so after the give-back ended)
    seen = {name: fleet.status(f"http://{name}/status") for name in HOSTS}
    fleet.fleet.fetch = lambda url: seen[url.split("/")[2]]
    fleet.pool.end(first["id"], "u0", False)
    for _round in range(40):
        fleet.pool.tick()
        if fleet.pool.store.get(first["id"])["state"] == "ended":
            break
        threading.Event().wait(0.05)
    # in the tick that saw the give-back end, u8 got that instance, through the agent's claim
    [mine] = fleet.pool.mine("u8")
    assert (mine["state"], mine["host"], mine["instance"]) == ("active", *where)
    assert fleet.held()[where] == pool.HOLDER.format(mine["id"])
    assert where not in fleet.pool._freed  # pylint: disable=protected-access


def test_a_give_back_the_host_could_not_finish_is_asked_again_later_never_at_once(fleet):
    code, s = fleet.pool.request("vic", {})
    assert code == 201
    held_by = pool.HOLDER.format(s["id"])
    a = fleet.agents[s["host"]]
    real = a._run_give_back  # pylint: disable=protected-access

    def kept(rec, host, who, holder):
        # as when the session's Documents cannot be moved aside: restarted, still the session's
        rec["result"] = {"ok": False, "message": "Documents not moved aside", "held": True}
        a._end(rec, who, "failed")  # pylint: disable=protected-access

    a._run_give_back = kept  # pylint: disable=protected-access
    fleet.pool.end(s["id"], "vic", False)
    for _round in range(40):
        fleet.pool.tick()
        if any("kept" in line and "asking again" in line for line in fleet.lines):
            break
        threading.Event().wait(0.05)
    asked = [r for r in a.recent() if r["action"] == "give_back"]
    assert len(asked) == 1 and fleet.pool.store.get(s["id"])["state"] == "ending"
    # later ticks within the delay ask nothing more; after it, the give-back is asked again and ends
    for _round in range(5):
        fleet.pool.tick()
    assert len([r for r in a.recent() if r["action"] == "give_back"]) == 1
    a._run_give_back = real  # pylint: disable=protected-access
    fleet.clock.now += pool.GIVE_BACK_RETRY_S
    fleet.settle()
    assert fleet.pool.store.get(s["id"])["state"] == "ended"
    assert held_by not in fleet.held().values()


def test_instances_a_test_run_holds_are_never_granted_and_a_drained_host_gets_no_claim(fleet):
    s1 = fleet.scripted["gpu-1"]
    for i in range(4):
        assert lifecycle.lend(s1.host, i, f"run-{i}") is None
    fleet.agents["gpu-2"].submit({"host": "gpu-2", "action": "drain", "ids": [], "user": "olga", "token": "",
                                  "confirm": False, "holder": ""})  # fmt: skip
    code, answer = fleet.pool.request("vic", {})
    assert code == 202 and answer["place"] == 1
    assert set(fleet.held().values()) == {f"run-{i}" for i in range(4)}
    # the drained host undrained: the queue is served at the next tick
    fleet.agents["gpu-2"].submit({"host": "gpu-2", "action": "undrain", "ids": [], "user": "olga", "token": "",
                                  "confirm": False, "holder": ""})  # fmt: skip
    fleet.pool.tick()
    [mine] = fleet.pool.mine("vic")
    assert mine["state"] == "active" and mine["host"] == "gpu-2"
    # what a request asks for is matched: 5.0 runs on the instances left; 4.5 runs nowhere, so it would wait for ever
    code, other = fleet.pool.request("u1", {"release": "5.0"})
    assert code == 201 and other["host"] == "gpu-2" and other["wants"] == {"release": "5.0"}
    with pytest.raises(pool.RefusedError) as nowhere:
        fleet.pool.request("u3", {"release": "4.5"})
    assert nowhere.value.args == (409, {"error": "release: no instance of the fleet runs '4.5'. Fix: one of 5.0."})
    with pytest.raises(pool.RefusedError) as bad:
        fleet.pool.request("u2", {"release": "5.0\n", "colour": "red"})
    assert bad.value.args[0] == 400 and "colour: not a field" in bad.value.args[1]["error"]
    assert "release: '5.0\\n' is not a name" in bad.value.args[1]["error"]


def test_only_its_holder_and_operators_see_or_end_a_session_and_a_browser_needs_the_door_s_page(fleet):
    code, mine = call(fleet.port, "/api/sessions", token=fleet.token("vic"), body={})
    assert code == 201
    url = mine["url"]
    other = fleet.token("u1")
    # its viewer's port and signalling (nginx asks the login service with the instance) open for vic and operators
    held, free = f"{mine['host']}/{mine['instance']}", f"{mine['host']}/{(mine['instance'] + 1) % 4}"
    cookies = {u: f"{door_auth.COOKIE}=" + fleet.door.login(u, "s3cret", "x") for u in ("vic", "u1", "olga")}
    assert [fleet.door.check(cookies[u], "/", "x", "", "", held)[0] for u in ("vic", "u1", "olga")] == [204, 403, 204]
    assert fleet.door.check(cookies["u1"], "/", "x", "", "", free)[0] == 204
    assert call(fleet.port, url, method="GET", token=other)[0] == 404
    assert call(fleet.port, url, method="DELETE", token=other)[0] == 404
    # a token without the use scope reads but does not ask
    reader = fleet.door.store.make_token("u2", "r", ["read"], 1, HASH)[0]
    code, refused = call(fleet.port, "/api/sessions", token=reader, body={})
    assert code == 403 and "use scope" in refused["error"]
    # a person's cookie from another site's page is refused; the door's own page (CSRF token) is not
    cookie = f"{door_auth.COOKIE}=" + fleet.door.login("u3", "s3cret", "x")
    assert (
        call(fleet.port, "/api/sessions", cookie=cookie, body={}, headers={"Origin": "https://evil.example"})[0] == 403
    )
    csrf = door_auth.csrf_token(cookie.split("=", 1)[1])
    headers = {"Origin": ORIGIN, "X-Fleet-Origin": ORIGIN, "X-Fleet-CSRF": csrf}
    assert call(fleet.port, "/api/sessions", cookie=cookie, body={}, headers=headers)[0] == 201
    # the operator sees everyone's and ends vic's; vic is told who ended it
    op = fleet.door.store.make_token("olga", "o", ["read", "use", "operate"], 1, HASH)[0]
    code, everything = call(fleet.port, "/api/sessions", method="GET", token=op)
    assert code == 200 and {s["user"] for s in everything["sessions"]} == {"vic", "u3"}
    code, ended = call(fleet.port, url, method="DELETE", token=op)
    assert code == 200 and ended["why"] == "ended by the operator olga"
    fleet.settle()
    code, seen = call(fleet.port, url, method="GET", token=fleet.token("vic"))
    assert code == 200 and seen["state"] == "ended" and seen["why"] == "ended by the operator olga"
    assert fleet.door.check(cookies["u1"], "/", "x", "", "", held)[0] == 204
    # the fleet shows each instance's holder: a session by its id
    code, listing = call(fleet.port, "/api/fleet", method="GET", token=op)
    holders = [i["holder"] for h in listing["hosts"] for i in h["instances"] if i["holder"]]
    assert holders == [{"kind": "session", "id": everything["sessions"][1]["id"]}] or holders == [
        {"kind": "session", "id": everything["sessions"][0]["id"]}
    ]


def test_the_maximum_duration_warns_first_then_ends_and_a_queue_place_not_looked_at_is_given_up(tmp_path, pki):
    f = Fleet(tmp_path, pki, {"max_minutes": 30, "warn_minutes": 5, "queue_grace_s": 60})
    try:
        code, s = f.pool.request("vic", {})
        assert code == 201 and s["seconds_left"] == 1800 and s["warning"] is None
        f.clock.now += 25 * 60 + 1
        f.pool.tick()
        seen = f.pool.look(s["id"], "vic", False)
        assert "ends in 5 minute(s)" in seen["warning"] and any("warned" in line for line in f.lines)
        f.clock.now += 5 * 60
        f.settle()
        seen = f.pool.look(s["id"], "vic", False)
        assert seen["state"] == "ended" and seen["why"] == "its maximum duration (30 minutes)"
        assert not f.held()
        # the figures node_exporter reads: one session that waited nothing and lasted its 30 minutes (ended at the tick)
        f.pool.write_metrics(str(tmp_path))
        text = (tmp_path / pool.METRICS_FILE).read_text()
        assert "isaac_sim_door_sessions_active 0\n" in text and "isaac_sim_door_queue_length 0\n" in text
        assert "isaac_sim_door_session_length_seconds_sum 1801.0\n" in text
        assert "isaac_sim_door_session_length_seconds_count 1\n" in text
        assert "isaac_sim_door_session_wait_seconds_sum 0.0\n" in text
        # a queued person who stops looking loses the place; one who looks keeps it
        for k in range(8):
            f.pool.request(f"u{k}", {})
        _c, gone = f.pool.request("u8", {})
        _c, kept = f.pool.request("u9", {})
        f.clock.now += 45
        f.pool.look(kept["id"], "u9", False)
        f.clock.now += 30
        f.pool.tick()
        assert [e["user"] for e in f.pool.store.queue()] == ["u9"]
        assert f.pool.store.get(gone["id"]) is None
    finally:
        f.close()


def test_sessions_and_the_queue_survive_a_restart_and_a_host_gone_frees_its_claims_after_the_timeout(tmp_path, pki):
    f = Fleet(tmp_path, pki, {"host_gone_s": 120})
    try:
        for k in range(9):
            f.pool.request(f"u{k}", {})
        on_2 = [s for s in f.pool.store.sim_sessions() if s["host"] == "gpu-2"]
        # the API's service restarted: a new pool on the same file has every session and place
        again = pool.Pool(pool.Store(f.db, clock=f.clock), f.fleet, f.pool.agents, {"host_gone_s": 120},
                          log=f.lines.append, clock=f.clock)  # fmt: skip
        assert len(again.store.sim_sessions()) == 8 and [e["user"] for e in again.store.queue()] == ["u8"]
        f.pool = again
        f.down.add("gpu-2")
        f.pool.tick()
        f.clock.now += 121
        [queued] = f.pool.mine("u8")
        f.pool.look(queued["id"], "u8", False)  # its page is open: the place is kept
        f.pool.tick()
        told = [f.pool.look(s["id"], s["user"], False) for s in on_2]
        assert all(t["state"] == "ending" and t["why"].startswith("gpu-2 did not answer for 121 s") for t in told)
        assert {s["host"] for s in f.pool.store.sim_sessions(("active",))} == {"gpu-1"}
        # back: its claims are given back through its agent, and the queue is served from it
        f.down.discard("gpu-2")
        f.settle()
        assert all(f.pool.store.get(s["id"])["state"] == "ended" for s in on_2)
        [u8] = f.pool.mine("u8")
        assert u8["state"] == "active" and u8["host"] == "gpu-2"
        assert sorted(h for (h, _i) in f.held()) == ["gpu-1"] * 4 + ["gpu-2"]
    finally:
        f.close()


def test_layout_holder_is_what_the_agent_takes():
    assert agent.HOLDER_RE.match(pool.HOLDER.format("0123456789ab"))


def test_a_session_nobody_is_on_is_warned_then_ended_and_a_client_back_in_time_keeps_it(tmp_path, pki):
    """The door sees a session's stream in use by its own connections to the instance's signalling (read
    from this machine's /proc/net/tcp, as the door's API reads its host's)."""
    listeners = {}
    for name in HOSTS:
        for i in range(4):
            listeners[(name, i)] = socket.create_server(("127.0.0.1", 0))
    f = Fleet(tmp_path, pki, {"idle_minutes": 10, "warn_minutes": 5})
    try:
        f.fleet.config["signals"] = {
            name: {str(i): f"127.0.0.1:{listeners[(name, i)].getsockname()[1]}" for i in range(4)} for name in HOSTS
        }
        _code, s = f.pool.request("vic", {})
        signal = listeners[(s["host"], s["instance"])].getsockname()

        def later(minutes):
            f.clock.now += minutes * 60
            f.pool.tick()
            return f.pool.look(s["id"], "vic", False)

        viewer = socket.create_connection(signal)
        assert later(6)["warning"] is None  # on it all along
        viewer.close()
        seen = later(6)
        assert seen["state"] == "active" and seen["warning"].startswith("Nobody has been on this simulator's stream")
        assert "it ends in 4 minute(s) unless you open it" in seen["warning"]
        viewer = socket.create_connection(signal)  # back in time: the warning goes, the session stays
        assert later(1)["warning"] is None
        viewer.close()
        assert later(6)["warning"]
        f.clock.now += 5 * 60
        f.settle()
        ended = f.pool.look(s["id"], "vic", False)
        assert ended["state"] == "ended" and ended["why"] == "nobody on its stream for 10 minutes"
        assert any("warned: Nobody has been on" in line for line in f.lines)
    finally:
        f.close()
        for listener in listeners.values():
            listener.close()


def test_the_proc_net_tcp_reading_takes_established_connections_of_both_families():
    tcp = (
        "  sl  local_address rem_address   st\n"
        "   0: 0100007F:1F90 0100007F:C350 01 x\n"  # 127.0.0.1:8080 -> 127.0.0.1:50000, established
        "   1: 0100007F:1F91 00000000:0000 0A x\n"  # listening
    )
    tcp6 = (
        "  sl  local_address rem_address   st\n"
        "   0: 0000000000000000FFFF00000100007F:1F90 0000000000000000FFFF00000D00000A:C0A0 01 x\n"
        "   1: 00000000000000000000000001000000:1F90 B80D0120000000000000000001000000:01BB 01 x\n"
    )
    assert pool.peers([tcp, tcp6]) == {("127.0.0.1", 50000), ("10.0.0.13", 49312), ("2001:db8::1", 443)}


def test_a_session_whose_host_no_longer_holds_its_instance_is_over_once_the_host_says_so(fleet):
    _c, s = fleet.pool.request("vic", {})
    _c, t = fleet.pool.request("u1", {})
    scripted = fleet.scripted[s["host"]]
    # the host's /run lost with a reboot: its marker is gone (an operator's give-back on the host is the same)
    lifecycle.unlend(scripted.host, s["instance"], s["holder"])
    fleet.pool.tick()
    assert fleet.pool.look(s["id"], "vic", False)["state"] == "active"  # a claim this young is not judged yet
    fleet.clock.now += pool.SETTLE_S + pool.VERIFY_EVERY_S
    fleet.pool.tick()
    over = fleet.pool.look(s["id"], "vic", False)
    assert over["state"] == "ended" and over["why"] == (
        f"{s['host']} no longer holds instance {s['instance']} for it (given back there, or lost with a reboot of "
        "the host)"
    )
    # the other session is untouched, and the instance is free for the next request
    assert fleet.pool.look(t["id"], "u1", False)["state"] == "active"
    _c, again = fleet.pool.request("u2", {})
    assert (again["host"], again["instance"]) == (s["host"], s["instance"])


def test_a_rollout_that_ends_sessions_warns_the_holder_in_the_page_then_the_session_ends_for_it(fleet):
    fleet.clock.now = fleet.scripted["gpu-1"].host.wall()  # the door's and the hosts' clocks agree (NTP)
    _c, s = fleet.pool.request("vic", {})
    scripted, n = fleet.scripted[s["host"]], s["instance"]
    seen = []

    def sleep(seconds):
        scripted.clock += seconds
        if not seen:  # the door looks while the rollout waits out its warning
            fleet.pool.tick()
            seen.append(fleet.pool.look(s["id"], "vic", False))

    scripted.host.sleep = sleep
    rolled = lifecycle.restart_each(scripted.host, [n], 0, end_sessions=120, by="olga")
    assert [d["id"] for d in rolled["done"]] == [n] and rolled["left"] == []
    assert seen[0]["state"] == "active" and seen[0]["warning"].startswith(
        "A rollout by olga restarts this simulator at "
    )
    assert "in 2 minute(s): save your work" in seen[0]["warning"]
    assert any("warned: A rollout by olga" in line for line in fleet.lines)
    fleet.clock.now += pool.SETTLE_S + pool.VERIFY_EVERY_S
    fleet.pool.tick()
    over = fleet.pool.look(s["id"], "vic", False)
    assert over["state"] == "ended" and over["why"] == "ended for a rollout by olga"


def test_a_role_or_a_person_may_hold_another_number_of_sessions(tmp_path, pki):
    f = Fleet(tmp_path, pki, {"limits": {"role:operator": 3, "user:vic": 0, "user:olga": 2}})
    try:
        assert (f.pool.limit("u1", "viewer"), f.pool.limit("u2", "operator")) == (1, 3)
        assert (f.pool.limit("olga", "operator"), f.pool.limit("vic", "viewer")) == (2, 0)
        op = f.door.store.make_token("olga", "o", ["read", "use"], 1, HASH)[0]
        assert [call(f.port, "/api/sessions", token=op, body={})[0] for _k in range(3)] == [201, 201, 409]
        code, refused = call(f.port, "/api/sessions", token=f.token("vic"), body={})
        assert code == 409 and "the most allowed (0)" in refused["error"]
    finally:
        f.close()


def test_an_end_and_a_tick_at_the_same_moment_ask_for_one_give_back(fleet):
    _c, s = fleet.pool.request("vic", {})
    ask, asked = fleet.pool.agents.ask, []

    def counting(host, method, path, body=None):
        if body and body.get("action") == "give_back":
            asked.append(body["holder"])
            if len(asked) == 1:  # the service's tick comes while the end's own request is on its way
                fleet.pool.tick()
        return ask(host, method, path, body)

    fleet.pool.agents.ask = counting
    fleet.pool.end(s["id"], "vic", False)
    fleet.settle()
    assert asked == [s["holder"]] and fleet.scripted[s["host"]].commands("restart") == [
        f"systemctl restart {layout.unit(s['instance'])}"
    ]


# --- each person's files


def test_files_are_kept_at_the_end_removed_on_the_host_and_put_back_at_the_person_s_next_session_elsewhere(fleet):
    _c, first = fleet.pool.request("vic", {})
    assert (first["host"], first["instance"], first["files"]) == ("gpu-1", 0, None)
    fleet.files.docs[("gpu-1", 0)] = {"notes.txt": b"hello", "scenes/a.usda": b"#usda 1.0"}
    fleet.pool.end(first["id"], "vic", False)
    fleet.settle()
    holder = first["holder"]
    assert fleet.kept("vic") == {"notes.txt": b"hello", "scenes/a.usda": b"#usda 1.0"}
    # taken, then removed on the host: the next person on that instance finds no Documents of vic's
    assert fleet.files.moves("GET", "DELETE") == [
        ("GET", "gpu-1", f"/files/{holder}?max={1024 * pool.MIB}"),
        ("DELETE", "gpu-1", f"/files/{holder}"),
    ]
    assert fleet.files.stash == {} and ("gpu-1", 0) not in fleet.files.docs
    row = fleet.pool.store.get(first["id"])
    assert row["files"].startswith("kept (") and row["files"].endswith(" bytes, 2 files)") and not row["files_due"]
    assert (
        fleet.pool.look(first["id"], "vic", False)["files"] == "Your files (Documents) are kept for your next session."
    )
    assert any(line.startswith(f"session {first['id']} of user=vic: files kept (") for line in fleet.lines)
    # root's alone on the door
    assert stat.S_IMODE(os.stat(fleet.files_dir).st_mode) == 0o700
    assert stat.S_IMODE(os.stat(fleet.files_dir / pool.files_name("vic")).st_mode) == 0o600
    # another person takes that instance and gets nothing of vic's; vic's next session is on another host
    _c, other = fleet.pool.request("u1", {})
    assert (other["host"], other["instance"], other["files"]) == ("gpu-1", 0, None)
    _c, again = fleet.pool.request("vic", {})
    assert (again["host"], again["instance"]) == ("gpu-2", 0)
    assert again["files"] == "Your files from your last session are being put back into Documents."
    fleet.pool.tick()
    assert fleet.files.moves("PUT") == [("PUT", "gpu-2", f"/files/{again['holder']}?instance=0")]
    assert fleet.files.docs == {("gpu-2", 0): {"notes.txt": b"hello", "scenes/a.usda": b"#usda 1.0"}}
    assert fleet.pool.look(again["id"], "vic", False)["files"] == "Your files from your last session are in Documents."
    assert f"session {again['id']} of user=vic: files put back into gpu-2/0 (2 files)" in fleet.lines
    # u1's session, which had no files, ends with none kept; its next session gets no PUT
    fleet.pool.end(other["id"], "u1", False)
    fleet.settle()
    assert fleet.kept("u1") is None and fleet.pool.store.get(other["id"])["files"].startswith("none: gpu-1 had no")
    _c, other_again = fleet.pool.request("u1", {})
    fleet.pool.tick()
    assert other_again["files"] is None and [c[2] for c in fleet.files.moves("PUT")] == [
        f"/files/{again['holder']}?instance=0"
    ]
    # what vic's session ends with is what is kept: a file deleted in it is gone from the tar
    fleet.files.docs[("gpu-2", 0)] = {"scenes/a.usda": b"#usda 1.0 (edited)"}
    fleet.pool.end(again["id"], "vic", False)
    fleet.settle()
    assert fleet.kept("vic") == {"scenes/a.usda": b"#usda 1.0 (edited)"}
    assert sorted(os.listdir(fleet.files_dir)) == [pool.files_name("vic")]


def test_files_that_could_not_be_put_back_stay_kept_and_what_the_session_made_is_added_to_them(fleet):
    fleet.pool.store.keep("vic", "v1", 0, 1)
    fleet.files_dir.mkdir(mode=0o700)
    (fleet.files_dir / pool.files_name("vic")).write_bytes(tar_of({"old.txt": b"old", "both.txt": b"old"}))
    fleet.files.put_answer = (502, {"error": "tar failed in the container"})
    _c, s = fleet.pool.request("vic", {})
    fleet.pool.tick()
    assert fleet.pool.look(s["id"], "vic", False)["files"] == (
        "Your files could not be put back (tar failed in the container); they are kept for your next session."
    )
    assert fleet.kept("vic") == {"old.txt": b"old", "both.txt": b"old"}
    assert any("files could not be put back into gpu-1/0 (502: tar failed" in line for line in fleet.lines)
    fleet.files.docs[("gpu-1", 0)] = {"new.txt": b"new", "both.txt": b"new"}
    fleet.pool.end(s["id"], "vic", False)
    fleet.settle()
    # the session did not start from the tar: its files go over it, never in its place
    assert fleet.kept("vic") == {"old.txt": b"old", "both.txt": b"new", "new.txt": b"new"}
    assert any("merged over the ones kept before" in line for line in fleet.lines)


def test_files_that_cannot_be_put_back_are_tried_again_then_the_session_goes_on_without_them(fleet):
    fleet.pool.store.keep("vic", "v1", 0, 1)
    fleet.files_dir.mkdir(mode=0o700)
    (fleet.files_dir / pool.files_name("vic")).write_bytes(tar_of({"old.txt": b"old"}))
    fleet.files.broken.add("gpu-1")
    _c, s = fleet.pool.request("vic", {})
    for _try in range(pool.PUT_TRIES):
        fleet.pool.tick()
        fleet.pool.tick()  # not again before FILES_RETRY_S
        fleet.clock.now += pool.FILES_RETRY_S
    tried = f"session {s['id']} of user=vic: files not put into gpu-1/0 yet (connection refused); trying again in 30 s"
    assert fleet.lines.count(tried) == pool.PUT_TRIES
    assert fleet.pool.look(s["id"], "vic", False)["files"] == (
        "Your files could not be put back (3 tries failed); they are kept for your next session."
    )
    fleet.files.broken.discard("gpu-1")
    fleet.pool.tick()
    assert fleet.files.moves("PUT") == [] and fleet.kept("vic") == {"old.txt": b"old"}


def test_files_over_the_limit_stay_on_the_host_and_the_person_is_told(tmp_path, pki):
    f = Fleet(tmp_path, pki, {"files_mib": 1})
    try:
        _c, s = f.pool.request("vic", {})
        f.files.docs[("gpu-1", 0)] = {"big.bin": os.urandom(2 * pool.MIB)}
        f.pool.end(s["id"], "vic", False)
        f.settle()
        assert f.files.moves("GET", "DELETE") == [("GET", "gpu-1", f"/files/{s['holder']}?max={pool.MIB}")]
        assert ("gpu-1", s["holder"]) in f.files.stash and f.kept("vic") is None
        row = f.pool.store.get(s["id"])
        assert (row["files"], row["files_due"]) == ("over the limit (2.0 MiB > 1 MiB)", None)
        assert f.pool.look(s["id"], "vic", False)["files"] == (
            "Your files were not kept, over the limit (2.0 MiB > 1 MiB): they are still on gpu-1, where an operator "
            "can get them."
        )
        assert (
            f"session {s['id']} of user=vic: files over the limit (2.0 MiB > 1 MiB); left on gpu-1 ({s['holder']})"
            in (f.lines)
        )
        f.pool.tick()
        assert len(f.files.moves("GET")) == 1  # settled: not asked again
    finally:
        f.close()


def test_files_of_a_host_that_does_not_answer_are_taken_once_it_does(fleet):
    _c, s = fleet.pool.request("vic", {})
    fleet.files.docs[("gpu-1", 0)] = {"notes.txt": b"hello"}
    fleet.files.broken.add("gpu-1")
    fleet.pool.end(s["id"], "vic", False)
    fleet.settle()
    assert fleet.pool.store.get(s["id"])["files"] == "pending" and fleet.kept("vic") is None
    assert (
        f"session {s['id']} of user=vic: files gpu-1 did not give them (connection refused); trying again in 30 s"
        in (fleet.lines)
    )
    assert (
        fleet.pool.look(s["id"], "vic", False)["files"]
        == "Your files (Documents) are being kept for your next session."
    )
    fleet.files.broken.discard("gpu-1")
    fleet.pool.tick()
    assert fleet.files.moves("GET") == []  # not before FILES_RETRY_S
    fleet.down.add("gpu-1")  # nor while its status does not answer
    fleet.clock.now += pool.FILES_RETRY_S
    fleet.pool.tick()
    assert fleet.files.moves("GET") == []
    fleet.answers_again("gpu-1")
    fleet.pool.tick()
    assert fleet.kept("vic") == {"notes.txt": b"hello"} and fleet.files.stash == {}
    assert fleet.pool.store.get(s["id"])["files_due"] is None


def test_with_files_mib_0_files_do_not_follow_and_the_host_s_copy_is_removed_unread(tmp_path, pki):
    f = Fleet(tmp_path, pki, {"files_mib": 0})
    try:
        # a tar kept while files followed people is not put back
        f.pool.store.keep("vic", "v1", 0, 1)
        f.files_dir.mkdir(mode=0o700)
        (f.files_dir / pool.files_name("vic")).write_bytes(tar_of({"old.txt": b"old"}))
        _c, s = f.pool.request("vic", {})
        f.files.docs[("gpu-1", 0)] = {"notes.txt": b"hello"}
        f.pool.tick()
        f.pool.end(s["id"], "vic", False)
        f.settle()
        assert f.files.moves("GET", "PUT", "DELETE") == [("DELETE", "gpu-1", f"/files/{s['holder']}")]
        assert f.files.stash == {} and f.kept("vic") == {"old.txt": b"old"}
        assert f.pool.store.get(s["id"])["files"] == pool.NOT_FOLLOWED
        assert f.pool.look(s["id"], "vic", False)["files"] == (
            "Files do not follow people here: what was in Documents went with this session."
        )
        assert f"session {s['id']} of user=vic: files {pool.NOT_FOLLOWED}; removed on gpu-1" in f.lines
    finally:
        f.close()


def test_a_person_s_tar_is_named_by_a_hash_of_the_name_never_the_name(fleet):
    assert pool.files_name("..") == hashlib.sha256(b"..").hexdigest() + ".tar" != pool.files_name(".")
    _c, s = fleet.pool.request("..", {})
    fleet.files.docs[("gpu-1", 0)] = {"notes.txt": b"dots"}
    fleet.pool.end(s["id"], "..", False)
    fleet.settle()
    assert os.listdir(fleet.files_dir) == [pool.files_name("..")] and fleet.kept("..") == {"notes.txt": b"dots"}
    assert not (fleet.files_dir / "...tar").exists() and not (fleet.files_dir.parent / ".tar").exists()


def test_a_session_a_rollout_ended_on_its_host_has_its_files_kept(fleet):
    _c, s = fleet.pool.request("vic", {})
    scripted = fleet.scripted[s["host"]]
    # the host ended the claim (a rollout with isaac_sim_rollout_end_sessions), its Documents moved aside first
    lifecycle.unlend(scripted.host, s["instance"], s["holder"])
    fleet.files.stash[(s["host"], s["holder"])] = tar_of({"notes.txt": b"saved before the rollout"})
    fleet.clock.now += pool.SETTLE_S + pool.VERIFY_EVERY_S
    fleet.pool.tick()
    assert fleet.pool.store.get(s["id"])["state"] == "ended"
    assert fleet.kept("vic") == {"notes.txt": b"saved before the rollout"} and fleet.files.stash == {}


def test_a_store_of_the_version_before_gets_the_files_columns(tmp_path):
    path = str(tmp_path / "door.db")
    db = sqlite3.connect(path)
    db.execute(
        "CREATE TABLE sim_sessions (id TEXT PRIMARY KEY, user TEXT NOT NULL, wants TEXT NOT NULL,"
        " host TEXT NOT NULL, instance INTEGER NOT NULL, state TEXT NOT NULL, created REAL NOT NULL,"
        " started REAL NOT NULL, expires REAL NOT NULL, warned INTEGER NOT NULL DEFAULT 0, ended REAL,"
        " why TEXT, action TEXT, client_seen REAL)"
    )
    db.execute(
        "INSERT INTO sim_sessions (id, user, wants, host, instance, state, created, started, expires)"
        " VALUES ('0123456789ab', 'vic', '{}', 'gpu-1', 0, 'active', 1, 1, 2)"
    )
    db.commit()
    db.close()
    store = pool.Store(path)
    [row] = store.sim_sessions()
    assert (row["files"], row["files_due"], row["files_in"], row["files_from"]) == (None, None, None, None)
    pool.Store(path)  # and again: nothing added twice
    assert store.files_due() == [] and store.kept("vic") is None


def test_a_merge_keeps_the_newer_member_of_a_path_and_every_other_of_the_older(tmp_path):
    newer, older = tmp_path / "newer.tar", tmp_path / "older.tar"
    with tarfile.open(newer, "w") as tar:
        info = tarfile.TarInfo("./work/a.txt")
        info.size = 3
        tar.addfile(info, io.BytesIO(b"new"))
    with tarfile.open(older, "w") as tar:
        folder = tarfile.TarInfo("work")
        folder.type = tarfile.DIRTYPE
        tar.addfile(folder)
        for name, data in (("work/a.txt", b"old"), ("b.txt", b"old")):
            info = tarfile.TarInfo(name)
            info.size = len(data)
            tar.addfile(info, io.BytesIO(data))
    assert pool.merge_tars(str(newer), str(older), str(tmp_path / "out.tar")) == 2
    with tarfile.open(tmp_path / "out.tar") as tar:
        assert [(m.name, m.isdir()) for m in tar] == [("./work/a.txt", False), ("work", True), ("b.txt", False)]
        assert tar.extractfile("./work/a.txt").read() == b"new"
    assert pool.tar_members(str(tmp_path / "out.tar")) == 2


def test_the_door_s_removal_ends_every_session_and_place_and_gives_every_claim_back(fleet):
    for user in ("vic", *(f"u{k}" for k in range(8))):
        fleet.pool.request(user, {})
    [vics] = fleet.pool.mine("vic")
    fleet.files.docs[(vics["host"], vics["instance"])] = {"notes.txt": b"hello"}
    assert len(fleet.held()) == 8 and len(fleet.pool.store.queue()) == 1

    def sleep(seconds):
        fleet.clock.now += seconds

    said = fleet.pool.end_all("the front door was removed", 60, sleep=sleep)
    assert said == {"ended": 8, "left": 1, "unfinished": []}
    # every instance given back on its host (restarted, then free), nobody waiting, vic's files kept on the door
    assert fleet.held() == {} and fleet.pool.store.queue() == []
    assert {r["state"] for r in fleet.pool.store.recent()} == {"ended"}
    assert fleet.kept("vic") == {"notes.txt": b"hello"}
    assert sum(len(s.commands("restart")) for s in fleet.scripted.values()) == 8
    assert "session" in next(line for line in fleet.lines if "left the queue (the front door was removed)" in line)


def test_the_door_s_removal_says_which_claims_a_host_that_does_not_answer_keeps(fleet):
    for k in range(8):
        fleet.pool.request(f"u{k}", {})
    # gpu-2 gone: neither its status nor its agent answers
    fleet.down.add("gpu-2")
    ask = fleet.pool.agents.ask

    def unreachable(host, *args, **kwargs):
        if host == "gpu-2":
            raise OSError("no route to host")
        return ask(host, *args, **kwargs)

    fleet.pool.agents.ask = unreachable

    def sleep(seconds):
        fleet.clock.now += seconds

    said = fleet.pool.end_all("the front door was removed", 30, sleep=sleep)
    assert said["ended"] == 8 and said["unfinished"] == [f"gpu-2/{i}" for i in range(4)]
    assert sorted(fleet.held()) == [("gpu-2", i) for i in range(4)]


def test_a_request_may_name_the_gpu_model_its_instance_has(fleet):
    # gpu-1's instances 0 and 2 on an L40S, 1 and 3 on an L4; gpu-2's on an RTX 6000 Ada, as each driver names it
    models = {"gpu-1": ["NVIDIA L40S", "NVIDIA L4"], "gpu-2": ["NVIDIA RTX 6000 Ada Generation"]}
    status = fleet.status

    def with_gpus(url):
        name, read = url.split("/")[2], json.loads(status(url))
        gpus = models[name]
        for inst in read["instances"]:
            inst["gpu"] = inst["id"] % len(gpus)
        read["gpu"] = {"gpus": [{"index": k, "name": g} for k, g in enumerate(gpus)]}
        return json.dumps(read).encode()

    fleet.fleet.fetch = with_gpus
    # matched whole, in any case, with or without the driver's "NVIDIA ": L4 is not L40S
    code, l4 = fleet.pool.request("u1", {"gpu": "l4"})
    assert code == 201 and (l4["host"], l4["instance"] % 2) == ("gpu-1", 1) and l4["wants"] == {"gpu": "l4"}
    code, ada = fleet.pool.request("u2", {"gpu": "NVIDIA RTX 6000 Ada Generation"})
    assert code == 201 and ada["host"] == "gpu-2"
    code, l40s = fleet.pool.request("u3", {"gpu": "L40S", "release": "5.0"})
    assert code == 201 and (l40s["host"], l40s["instance"] % 2) == ("gpu-1", 0)
    with pytest.raises(pool.RefusedError) as nowhere:
        fleet.pool.request("u4", {"gpu": "L40"})
    assert nowhere.value.args == (
        409,
        {"error": "gpu: no instance of the fleet runs 'L40'. Fix: one of NVIDIA L4, NVIDIA L40S, "
                  "NVIDIA RTX 6000 Ada Generation."},
    )  # fmt: skip
    with pytest.raises(pool.RefusedError) as bad:
        fleet.pool.request("u4", {"gpu": "L40S; rm -rf /"})
    assert bad.value.args[0] == 400 and bad.value.args[1]["error"].startswith("gpu: 'L40S; rm -rf /' is not a GPU")
    # both L4 instances taken, the next L4 request waits for one, though L40S instances are free
    code, _second = fleet.pool.request("u5", {"gpu": "L4"})
    assert code == 201
    code, waits = fleet.pool.request("u6", {"gpu": "L4"})
    assert code == 202 and waits["place"] == 1
