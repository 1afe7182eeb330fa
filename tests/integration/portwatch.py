"""What clients see of the hosts' ports, from outside the hosts: a watcher and a port scan.

The watcher: the fleet tests and the rollout benchmark see how many instances
of each host answer at each moment of a rollout. The scan: every TCP port of a
host that accepts a connection.
"""

from __future__ import annotations

import errno
import select
import socket
import threading
import time


def answers(address: str, port: int) -> bool:
    """Whether the stand-in answers on the port with its banner."""
    try:
        with socket.create_connection((address, port), timeout=0.5) as conn:
            conn.settimeout(0.5)
            # the stand-in's hook for tests: it names itself (a real signalling server sends nothing unasked)
            conn.sendall(b"hello\n")
            return conn.recv(64).startswith(b"isaac-sim-standin")
    except OSError:
        return False


def listening(address: str, ports, batch: int = 2000, timeout: float = 2.0) -> set:
    """The TCP ports that accept a connection, tried from here: every port of a host in seconds.

    Non-blocking connects, a batch at a time (asyncio took eight times as long on two cores).
    """
    found, ports = set(), list(ports)
    for start in range(0, len(ports), batch):
        poller, pending = select.epoll(), {}
        for port in ports[start : start + batch]:
            sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            sock.setblocking(False)
            if sock.connect_ex((address, port)) in (0, errno.EINPROGRESS):
                pending[sock.fileno()] = (sock, port)
                poller.register(sock.fileno(), select.EPOLLOUT | select.EPOLLERR | select.EPOLLHUP)
            else:
                sock.close()
        deadline = time.monotonic() + timeout
        while pending and time.monotonic() < deadline:
            for fd, _event in poller.poll(max(0.0, deadline - time.monotonic())):
                sock, port = pending.pop(fd)
                poller.unregister(fd)
                if sock.getsockopt(socket.SOL_SOCKET, socket.SO_ERROR) == 0:
                    found.add(port)
                sock.close()
        for sock, _port in pending.values():  # no answer in time: filtered, not listening
            sock.close()
        poller.close()
    return found


class Watcher(threading.Thread):
    """samples: [(monotonic time, {host: instances answering})], one per interval.

    The stand-in's port is closed for under a second while systemd replaces its
    container; sampled once a second, a host's four gaps were all missed once.
    """

    def __init__(self, addresses: dict, ports: list, interval: float = 0.25):
        super().__init__(daemon=True)
        self.addresses, self.ports, self.interval = addresses, ports, interval
        self.samples = []
        self.done = threading.Event()

    def run(self):
        while not self.done.is_set():
            start = time.monotonic()
            self.samples.append((start, {h: sum(answers(a, p) for p in self.ports) for h, a in self.addresses.items()}))
            self.done.wait(max(0.0, self.interval - (time.monotonic() - start)))

    def stop(self):
        self.done.set()
        self.join()

    def lowest(self) -> dict:
        """The fewest instances seen answering on each host."""
        return {h: min(s[h] for _key, s in self.samples) for h in self.addresses}

    def most_disturbed_at_once(self, full: int) -> int:
        """The most hosts seen with fewer than `full` instances answering in one sample."""
        return max(sum(1 for v in s.values() if v < full) for _key, s in self.samples)
