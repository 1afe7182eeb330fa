"""What the front door's tests share: the users, the requests a browser outside the fleet sends
(Python's own HTTP client, trusting the collection's CA the role made and nothing else), a login."""

import http.client
import importlib.util
import json
import os
import ssl
import subprocess
import sys
import urllib.parse
from pathlib import Path

from testbed import ROOT, client

# the login service's own code (the standard library alone) makes the users' hashes
_spec = importlib.util.spec_from_file_location("door_auth", ROOT / "plugins/module_utils/front/door_auth.py")
door_auth = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(door_auth)

PEER = ROOT / "tests" / "integration" / "webrtc_peer.py"
OUTSIDE_IMAGE = "isaacsim-fleet/standin-base:bookworm"
# a network namespace that reaches the front door's TLS port and nothing else
OUTSIDE_FIREWALL = (
    "-P INPUT DROP",
    "-P OUTPUT DROP",
    "-A INPUT -i lo -j ACCEPT",
    "-A INPUT -m conntrack --ctstate ESTABLISHED -j ACCEPT",
    "-A OUTPUT -o lo -j ACCEPT",
    "-A OUTPUT -m conntrack --ctstate ESTABLISHED -j ACCEPT",
    "-A OUTPUT -p tcp -d {door} --dport 5349 -j ACCEPT",
)
UNITS = (
    "isaac-sim-front-door.service",
    "isaac-sim-front-door-auth.service",
    "isaac-sim-front-door-turn.service",
    "isaac-sim-front-door-api.service",
)
# hashed once: a new salt is a changed users file, which a re-run would rightly apply
USERS = [
    {"name": "olga", "role": "operator", "password_hash": door_auth.hash_password("op-secret", 10000)},
    {"name": "vic", "role": "viewer", "password_hash": door_auth.hash_password("view-secret", 10000)},
    # more people, each asking for a simulator of their own (the sessions' tests; nine viewers for the
    # fleet's eight instances)
    *(
        {"name": name, "role": "viewer", "password_hash": door_auth.hash_password("view-secret", 10000)}
        for name in ("ana", "ben", "cy", "val", "dee", "eve", "fay", "gus")
    ),
]


def ca_dir() -> Path:
    return Path(os.environ["MOLECULE_EPHEMERAL_DIRECTORY"]) / "ca"


def settings(**over) -> dict:
    return {"front_door_users": USERS, "front_door_ca_dir": str(ca_dir()), "front_door_login_rate": "30r/m", **over}


def door_inventory(name: str) -> Path:
    """An inventory file that makes the named host the front door (group isaac_sim_front_door)."""
    inventory = Path(os.environ["MOLECULE_EPHEMERAL_DIRECTORY"]) / "front-door.yml"
    inventory.write_text(json.dumps({"isaac_sim_front_door": {"hosts": {name: {}}}}))
    return inventory


def request(address, method, path, body=None, cookie=None, tls=True, headers=None, port=None, client_cert=None):
    """client_cert: (certificate, key) files the client presents."""
    if tls:
        context = ssl.create_default_context(cafile=str(ca_dir() / "ca.crt"))
        if client_cert:
            context.load_cert_chain(*map(str, client_cert))
        conn = http.client.HTTPSConnection(address, port or 443, context=context, timeout=10)
    else:
        conn = http.client.HTTPConnection(address, port or 80, timeout=10)
    headers = dict(headers or {}, **({"Cookie": f"__Host-fleet_session={cookie}"} if cookie else {}))
    if body is not None:
        body = urllib.parse.urlencode(body)
        headers["Content-Type"] = "application/x-www-form-urlencoded"
    conn.request(method, path, body=body, headers=headers)
    response = conn.getresponse()
    data = response.read()
    version = conn.sock.version() if tls and conn.sock else None
    conn.close()
    return response, data, version


def login(address, user, password):
    response, _data, _v = request(address, "POST", "/login", {"user": user, "password": password, "next": "/"})
    return response


def session(address, user, password) -> str:
    """The session cookie's value after a login that must succeed."""
    response = login(address, user, password)
    assert response.status == 303, response.status
    return response.getheader("Set-Cookie").split(";", 1)[0].split("=", 1)[1]


def log_in(driver, user, password):
    """Fills the front door's login page in a browser and sends it."""
    driver.find_element("name", "user").send_keys(user)
    driver.find_element("name", "password").send_keys(password)
    driver.find_element("css selector", "button[type=submit]").click()


def as_person(address, method, path, cookie, body=None):
    """(status, answer) of the fleet API for a logged-in person, as the door's own page asks it (its
    Origin and the session's CSRF token)."""
    context = ssl.create_default_context(cafile=str(ca_dir() / "ca.crt"))
    headers = {"Cookie": f"__Host-fleet_session={cookie}"}
    conn = http.client.HTTPSConnection(address, 443, context=context, timeout=30)
    conn.request("GET", "/session", headers=headers)
    csrf = json.loads(conn.getresponse().read())["csrf"]
    headers.update({"Origin": f"https://{address}", "X-Fleet-CSRF": csrf, "Content-Type": "application/json"})
    conn.request(method, path, body=json.dumps(body) if body is not None else None, headers=headers)
    response = conn.getresponse()
    answer = json.loads(response.read() or b"{}")
    conn.close()
    return response.status, answer


def relay_credentials(address, cookie) -> dict:
    """What the front door hands a logged-in user for its TURN relay."""
    response, data, _v = request(address, "GET", "/turn-credentials", cookie=cookie)
    assert response.status == 200, response.status
    return json.loads(data)


def relayed_exchange(address, port, username, password, peer, payload=b"hello", timeout=5.0):
    """(relayed address, answer) of one UDP datagram sent to peer (host, port) through the front
    door's TURN relay, over TLS trusting the collection's CA alone: aioice (PyPI) as the TEST
    FIXTURE that stands in for a browser's WebRTC stack. Raises what the relay refused."""
    import asyncio

    from aioice import turn

    async def exchange():
        answers = asyncio.Queue()

        class Peer(asyncio.DatagramProtocol):
            def datagram_received(self, data, addr):
                answers.put_nowait((data, addr))

            def error_received(self, exc):
                # what the relay refused of a send (its permission or channel for the peer)
                answers.put_nowait((exc, None))

        context = ssl.create_default_context(cafile=str(ca_dir() / "ca.crt"))
        transport, _protocol = await asyncio.wait_for(
            turn.create_turn_endpoint(
                Peer, (address, port), username=username, password=password, ssl=context, transport="tcp"
            ),
            timeout,
        )
        try:
            relayed = transport.get_extra_info("sockname")
            transport.sendto(payload, peer)
            try:
                data, _addr = await asyncio.wait_for(answers.get(), timeout)
            except asyncio.TimeoutError:
                data = None
            if isinstance(data, Exception):
                raise data
            return relayed, data
        finally:
            transport.close()

    return asyncio.run(exchange())


def peer(pid: int, *args, env=None, **popen):
    """webrtc_peer.py (this machine's Python, with aiortc) in the network namespace of process pid:
    its last JSON line, or the process itself when given pipes."""
    command = ["nsenter", "-t", str(pid), "-n", sys.executable, str(PEER), *args]
    if popen:
        return subprocess.Popen(command, env=env, text=True, **popen)
    out = subprocess.run(command, env=env, text=True, capture_output=True, timeout=60, check=False)
    assert out.returncode == 0, out.stdout + out.stderr
    return json.loads(out.stdout.splitlines()[-1])


def check_a_stream_from_outside_the_lan(door: str, cookie: str, gpu_host: str, probe: tuple[str, int]):
    """A WebRTC stream relayed by the front door's TURN server: a receiver in a container whose
    firewall lets out only TCP to the door's TLS port (checked: a datagram to probe, a stream port
    that answers, goes unanswered) takes relay-only ICE with a login's credentials and gets the video
    a sender streams from the GPU host's network namespace (its host addresses only)."""
    turn = relay_credentials(door, cookie)["iceServers"]
    sender_ns = client().containers.get(gpu_host).attrs["State"]["Pid"]
    outside = client().containers.run(
        OUTSIDE_IMAGE, ["sleep", "600"], name="isaacsim-outside-the-lan", detach=True, remove=True
    )
    try:
        outside.reload()
        receiver_ns = outside.attrs["State"]["Pid"]
        to = f"{probe[0]}:{probe[1]}"
        assert peer(receiver_ns, "probe-udp", "--to", to)["answered"], "the probe's port must answer before"
        for rule in OUTSIDE_FIREWALL:
            argv = ["nsenter", "-t", str(receiver_ns), "-n", "iptables", *rule.format(door=door).split()]
            subprocess.run(argv, check=True)
        assert not peer(receiver_ns, "probe-udp", "--to", to)["answered"]
        assert not peer(receiver_ns, "probe-tcp", "--to", f"{door}:443")["connected"]
        assert peer(receiver_ns, "probe-tcp", "--to", f"{door}:5349")["connected"]

        env = dict(os.environ, SSL_CERT_FILE=str(ca_dir() / "ca.crt"))
        pipes = {"stdin": subprocess.PIPE, "stdout": subprocess.PIPE}
        receiver = peer(receiver_ns, "receive", "--turn", json.dumps(turn), env=env, **pipes)
        sender = peer(sender_ns, "send", **pipes)
        try:
            sender.stdin.write(receiver.stdout.readline())  # the offer: relay candidates only
            sender.stdin.flush()
            receiver.stdin.write(sender.stdout.readline())  # the answer: the GPU host's addresses
            receiver.stdin.flush()
            got = json.loads(receiver.stdout.readline() or "{}")
            sender.stdin.write("done\n")
            sender.stdin.flush()
            sent = json.loads(sender.stdout.readline() or "{}")
        finally:
            for process in (receiver, sender):
                process.kill()
                process.wait()
    finally:
        outside.remove(force=True)
    assert got.get("error") is None and got["frames"] >= 30 and got["sizes"] == [[320, 240]], got
    assert got["candidates"] and set(got["candidates"]) == {"relay"}, got
    # through the door's relay: the GPU host sent the stream to a relay port of the fixed range
    kind, relay_address, relay_port = sent["pair"]["remote"]
    assert (kind, relay_address) == ("relay", door) and 50000 <= relay_port <= 50199, sent


AGENT_PORT = 8291


def agent_answer(address, cert=None, netns=None) -> str:
    """What a TLS client with `cert` (certificate, key) gets of a host's action agent at GET /health, in
    the network namespace of process netns (None: this machine's): the status line, or the error."""
    script = (
        "import http.client, ssl, sys\n"
        "ctx = ssl.create_default_context(cafile=sys.argv[1])\n"
        "if len(sys.argv) > 3: ctx.load_cert_chain(sys.argv[3], sys.argv[4])\n"
        f"conn = http.client.HTTPSConnection(sys.argv[2], {AGENT_PORT}, context=ctx, timeout=5)\n"
        "try:\n    conn.request('GET', '/health'); print(conn.getresponse().status)\n"
        "except Exception as exc:\n    print(type(exc).__name__, exc)\n"
    )
    argv = [sys.executable, "-c", script, str(ca_dir() / "ca.crt"), address, *map(str, cert or ())]
    if netns:
        argv = ["nsenter", "-t", str(netns), "-n", *argv]
    return subprocess.run(argv, capture_output=True, text=True, timeout=30, check=True).stdout.strip()


def another_ca_door_cert(directory: Path) -> tuple:
    """(certificate, key) with the door's name, signed by a CA of its own: not the collection's."""
    other = directory / "other-ca"
    other.mkdir(exist_ok=True)
    for args in (
        ["req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "2", "-subj", "/CN=other CA",
         "-keyout", "ca.key", "-out", "ca.crt"],
        ["req", "-new", "-newkey", "rsa:2048", "-nodes", "-subj", "/CN=isaacsim.fleet front door",
         "-keyout", "door.key", "-out", "door.csr"],
        ["x509", "-req", "-in", "door.csr", "-CA", "ca.crt", "-CAkey", "ca.key", "-set_serial", "7", "-days", "2",
         "-out", "door.crt"],
    ):  # fmt: skip
        subprocess.run(["openssl", *args], cwd=other, check=True, capture_output=True)
    return other / "door.crt", other / "door.key"


def check_the_action_channel(agent: str, door: str, tmp: Path, elsewhere=None) -> None:
    """A host's action agent (at address `agent`) takes the door alone. From the door's container (its
    network namespace), the door's certificate gets an answer, and neither no certificate nor another
    CA's in the door's name does; from `elsewhere` (a container; None: this machine), nothing reaches
    the port, whatever certificate it shows."""

    def netns(name):
        return client().containers.get(name).attrs["State"]["Pid"]

    door_cert, other = (ca_dir() / "door-client.crt", ca_dir() / "door-client.key"), another_ca_door_cert(tmp)
    assert agent_answer(agent, door_cert, netns(door)) == "200"
    said = agent_answer(agent, None, netns(door))
    assert said.startswith(("SSLError", "ConnectionResetError", "SSLEOFError")), said
    said = agent_answer(agent, other, netns(door))
    assert not said.startswith("200"), said
    outside = netns(elsewhere) if elsewhere else None
    for cert in (None, other, door_cert):
        said = agent_answer(agent, cert, outside)
        assert said.startswith(("TimeoutError", "ConnectionRefusedError", "OSError")), (cert, said)
