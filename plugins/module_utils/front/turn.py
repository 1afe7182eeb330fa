# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""The front door's TURN relay: coturn of the distribution's packages, for people whose network
lets nothing but the front door's TCP ports through (WebRTC's media is UDP to the GPU host).

TURN over TLS only (no plain UDP, TCP or DTLS listener), with the front door's certificate; relay
ports from a fixed range; UDP relays only, and only to the addresses of the instances behind the
front door (every other address is a denied peer: the relay is no way into the rest of the LAN).
Credentials are coturn's shared-secret scheme: the login service hands a logged-in user a user
name EXPIRY:USER and its HMAC (front/door_auth.py, /turn-credentials); coturn refuses them after
the expiry. It runs as its own unit (isaac-sim-front-door-turn.service) as the package's user, so
a coturn the site runs (coturn.service, /etc/turnserver.conf) is left alone.
"""

from __future__ import annotations

from ansible_collections.isaacsim.fleet.plugins.module_utils.common import sandbox, units

UNIT = "isaac-sim-front-door-turn.service"
# coturn opens an SQLite user database at start even when only the shared secret is used: its
# own, writable (systemd's StateDirectory, owned by the package's user)
STATE = "isaac-sim-front-door-turn"
TURNSERVER = "/usr/bin/turnserver"
# the package's user (Debian's coturn makes it)
USER = "turnserver"


def url(name: str, port: int) -> str:
    """The relay as browsers and WebRTC libraries name it: TURN over TLS (TCP)."""
    return f"turns:{name}:{int(port)}?transport=tcp"


def peers_denied_but(addresses) -> list:
    """coturn's peer rules: every address denied, then the instances' own allowed (an address
    both denied and allowed is allowed)."""
    lines = ["denied-peer-ip=0.0.0.0-255.255.255.255", "denied-peer-ip=::-ffff:ffff:ffff:ffff:ffff:ffff:ffff:ffff"]
    return lines + [f"allowed-peer-ip={a}" for a in sorted(set(addresses))]


def conf(p: dict, config_dir: str, secret: str, ciphers: str, managed: str) -> str:
    """turnserver.conf. p: server_name, turn_port, turn_min_port, turn_max_port, peers, turn_address
    (the host's address on the LAN, where the relay relays from; empty: coturn's choice)."""
    lines = [
        f"# {managed}",
        "# The front door's TURN relay (isaac-sim-front-door-turn.service): TLS only, shared-secret credentials.",
        f"tls-listening-port={int(p['turn_port'])}",
        "no-udp",
        "no-tcp",
        "no-dtls",
        "no-tlsv1",
        "no-tlsv1_1",
        f'cipher-list="{ciphers}"',
        f"cert={config_dir}/turn.crt",
        f"pkey={config_dir}/turn.key",
        # relays from the address the LAN knows this host by (coturn would take every interface's in
        # turn, a container bridge's too)
        *([f"relay-ip={p['turn_address']}"] if p.get("turn_address") else []),
        f"min-port={int(p['turn_min_port'])}",
        f"max-port={int(p['turn_max_port'])}",
        # WebRTC relays UDP; a TCP relay would open TCP connections into the LAN
        "no-tcp-relay",
        "no-multicast-peers",
        *peers_denied_but(p.get("peers") or []),
        "use-auth-secret",
        f"static-auth-secret={secret}",
        f"realm={p['server_name']}",
        "fingerprint",
        "no-software-attribute",
        "no-cli",
        f"userdb=/var/lib/{STATE}/turndb",
        "log-file=stdout",
        "simple-log",
        # no second (RFC 5780 alternate) TLS port: the one port is all a firewall opens
        "no-rfc5780",
    ]
    return "\n".join(lines) + "\n"


def unit(config_dir: str, managed: str, low_port: bool = False) -> str:
    return units.render(
        [
            (
                "Unit",
                [
                    ("Description", "isaacsim.fleet front door TURN relay (coturn)"),
                    ("Wants", "network-online.target"),
                    ("After", "network-online.target"),
                ],
            ),
            (
                "Service",
                [
                    ("Type", "notify"),
                    # no pid file: systemd follows it (as Debian's own coturn.service)
                    ("ExecStart", f"{TURNSERVER} -c {config_dir}/turnserver.conf --pidfile="),
                    ("Restart", "on-failure"),
                    ("RestartSec", 5),
                    ("StateDirectory", STATE),
                    *sandbox.relay(USER, low_port),
                ],
            ),
            ("Install", [("WantedBy", "multi-user.target")]),
        ],
        header=[managed],
    )
