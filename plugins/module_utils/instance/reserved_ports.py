# Copyright: isaacsim.fleet contributors
# SPDX-License-Identifier: Apache-2.0 (the collection's license, see galaxy.yml)
"""The instances' ports kept out of the host's ephemeral range.

Instances on the host's network bind fixed ports inside Linux's default ephemeral range
(32768-60999: NVIDIA's 49100 and 47998 are in it). Any outgoing connection from the host
(a health probe, a pull, a monitoring agent) may be given one of them as its source port,
and its TIME_WAIT holds it for 60 s after it closes: the instance's next bind fails with
"Address already in use" (SO_REUSEADDR does not help against a client's socket).
net.ipv4.ip_local_reserved_ports keeps the kernel from handing them out; explicit binds
still work. Pure functions: the lifecycle reads and writes the two places.
"""

from __future__ import annotations

from ansible_collections.isaacsim.fleet.plugins.module_utils.instance import hostprobe

PROC = "/proc/sys/net/ipv4/ip_local_reserved_ports"
# last in systemd-sysctl's order (after Debian's 99-sysctl.conf): it carries the value the host had, plus ours
CONF = "/etc/sysctl.d/99-zz-isaac-sim-reserved-ports.conf"
KEY = "net.ipv4.ip_local_reserved_ports"
MARK = "# added by isaacsim.fleet: "


def parse(text: str | None) -> set:
    """'8080,49100-49103' -> {8080, 49100, ..., 49103}; blank or malformed parts are skipped."""
    ports = set()
    for part in (text or "").replace("\n", ",").split(","):
        part = part.strip()
        low, _sep, high = part.partition("-")
        if not low.isdigit() or (high and not high.isdigit()):
            continue
        ports.update(range(int(low), int(high or low) + 1))
    return ports


def render(ports) -> str:
    """The kernel's own form: ascending, runs as ranges ('49100-49103,49200')."""
    out = []
    for port in sorted(set(ports)):
        if out and out[-1][1] == port - 1:
            out[-1][1] = port
        else:
            out.append([port, port])
    return ",".join(str(a) if a == b else f"{a}-{b}" for a, b in out)


def ours(conf_text: str | None) -> set:
    """The ports our file says we added (the rest of its value was the host's own)."""
    for line in (conf_text or "").splitlines():
        if line.startswith(MARK):
            return parse(line[len(MARK) :])
    return set()


def conf(value: set, added: set, managed: str) -> str | None:
    """Our sysctl.d file, or None when we add nothing (the host's own files say the rest)."""
    if not added:
        return None
    return (
        f"# {managed}\n"
        "# The Isaac Sim instances' ports, kept out of the ephemeral range: an outgoing connection\n"
        "# must never take one before its instance binds it. The value keeps the host's own ports.\n"
        f"{MARK}{render(added)}\n"
        f"{KEY} = {render(value)}\n"
    )


def wanted(runtime_text: str | None, conf_text: str | None, ports, grow: bool = False) -> tuple:
    """(value, added) for the kernel and our file.

    grow: while instances move, nothing is taken away (the old ports may still be bound);
    else the final state, where only ports that we added and no instance has any more leave.
    Ports reserved by the host itself (not in our file) are never taken away.
    """
    now = parse(runtime_text)
    mine = ours(conf_text) & now
    want = set(ports)
    if grow:
        return now | want, mine | (want - now)
    others = now - mine
    return others | want, want - others


# TIME_WAIT lasts 60 s on Linux (TCP_TIMEWAIT_LEN); a little more for the last ones to go
LINGER_LIMIT_S = 75


def _local_ports(texts, skip_state: str, wanted: set) -> set:
    return {
        port
        for text in texts
        for port, state, _inode in hostprobe.proc_net_entries(text)
        if state != skip_state and port in wanted
    }


def lingering(tcp_texts, ports, udp_texts=()) -> set:
    """The ports of `ports` that a socket other than a listener has as its local port
    (/proc/net/tcp, tcp6, udp, udp6 texts): an outgoing TCP connection given one before it was
    reserved, or the TIME_WAIT it leaves for 60 s; a connected UDP socket. Reserving a port keeps
    the kernel from handing it out again, not from the sockets that have it already."""
    wanted = set(ports)
    return _local_ports(tcp_texts, hostprobe.TCP_LISTEN, wanted) | _local_ports(
        udp_texts, hostprobe.UDP_UNCONNECTED, wanted
    )
