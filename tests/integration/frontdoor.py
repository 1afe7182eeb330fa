"""What the front door's tests share: the users, the requests a browser outside the fleet sends
(Python's own HTTP client, trusting the collection's CA the role made and nothing else), a login."""

import http.client
import importlib.util
import json
import os
import ssl
import urllib.parse
from pathlib import Path

from testbed import ROOT

# the login service's own code (the standard library alone) makes the users' hashes
_spec = importlib.util.spec_from_file_location("door_auth", ROOT / "plugins/module_utils/front/door_auth.py")
door_auth = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(door_auth)

UNITS = ("isaac-sim-front-door.service", "isaac-sim-front-door-auth.service", "isaac-sim-front-door-turn.service")
# hashed once: a new salt is a changed users file, which a re-run would rightly apply
USERS = [
    {"name": "olga", "role": "operator", "password_hash": door_auth.hash_password("op-secret", 10000)},
    {"name": "vic", "role": "viewer", "password_hash": door_auth.hash_password("view-secret", 10000)},
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


def request(address, method, path, body=None, cookie=None, tls=True, headers=None, port=None):
    if tls:
        context = ssl.create_default_context(cafile=str(ca_dir() / "ca.crt"))
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
