# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""systemd's sandbox for every unit the collection installs, one profile per kind of unit.

A unit that runs a container (an instance, a companion, the Hub cache, a test run's service)
sandboxes the host side only: the docker client, the scripts around it and their checks. The
container itself is Docker's, confined by hostlib/container_policy.py. Each profile is what its unit
needs and no more; `systemd-analyze security` rates them (docs/docsite/rst/security.rst, "Every host unit is
sandboxed").
"""

from __future__ import annotations

from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib import layout

# every unit: no capability it was not given, nothing written outside what it names, no new
# privileges, kernel and clock out of reach, the system calls of a service on the native ABI
_COMMON = (
    ("User", "root"),
    ("AmbientCapabilities", ""),
    ("NoNewPrivileges", "yes"),
    ("ProtectSystem", "strict"),
    ("ProtectKernelTunables", "yes"),
    ("ProtectKernelLogs", "yes"),
    ("ProtectControlGroups", "yes"),
    ("ProtectClock", "yes"),
    ("ProtectHostname", "yes"),
    ("RestrictNamespaces", "yes"),
    ("RestrictRealtime", "yes"),
    ("RestrictSUIDSGID", "yes"),
    ("LockPersonality", "yes"),
    ("MemoryDenyWriteExecute", "yes"),
    ("SystemCallArchitectures", "native"),
    ("SystemCallFilter", "@system-service"),
)

# The status endpoint and the metrics exporter: root only to read the env files they own (mode
# 0600), without any capability; no PrivateDevices, as nvidia-smi opens the GPUs' devices.
READER = (
    *_COMMON,
    ("CapabilityBoundingSet", ""),
    ("ProtectHome", "yes"),
    ("PrivateTmp", "yes"),
    ("ProtectKernelModules", "yes"),
    ("RestrictAddressFamilies", "AF_UNIX AF_INET AF_INET6"),
    ("UMask", "0077"),
)


def reader(writable=(), network=True) -> tuple:
    """The status endpoint's profile (network: it serves) or the metrics exporter's (no traffic;
    writable: the textfile directory it writes). The exporter keeps the IP socket families: it
    finds the host's address as the status endpoint does, by asking the kernel which source a UDP
    socket would use (fleet_status.default_ipv4, no packet sent); IPAddressDeny lets no packet
    through either way."""
    entries = list(READER)
    if not network:
        entries += [("IPAddressDeny", "any")]
    entries += [("ReadWritePaths", path) for path in writable]
    return tuple(entries)


def docker_client(localhost=False) -> tuple:
    """A unit that runs a container through Docker's socket: the docker client, a bash script
    around it (ready gate, health loop, ss for the ports of its block: netlink) and systemctl.
    Nothing of the host's is readable beyond the OS: an empty home (the docker client finds no
    config, so no registry key either), no devices, its own user namespace. It writes only
    RUN_DIR (ready markers, a test run's exit files). localhost: it may also reach 127.0.0.1
    (the Hub cache's unit waits until its cache listens there)."""
    families = "AF_UNIX AF_NETLINK AF_INET AF_INET6" if localhost else "AF_UNIX AF_NETLINK"
    return (
        *_COMMON,
        # without a capability, ss sees the ports but not who holds them (that would take
        # CAP_SYS_PTRACE, a root shell's worth): isaac-sim-ports says how to find out
        ("CapabilityBoundingSet", ""),
        ("ProtectHome", "tmpfs"),
        ("PrivateTmp", "yes"),
        ("PrivateDevices", "yes"),
        ("PrivateUsers", "yes"),
        ("ProtectKernelModules", "yes"),
        ("ProtectProc", "invisible"),
        ("RestrictAddressFamilies", families),
        ("IPAddressAllow", "localhost" if localhost else None),
        ("IPAddressDeny", "any"),
        ("SystemCallFilter", "~@privileged @resources"),
        # a denied call fails (the Go runtime of docker raises its open-files limit and goes
        # on without it) instead of killing the process
        ("SystemCallErrorNumber", "EPERM"),
        ("UMask", "0077"),
        # shared by every unit of the collection, kept when one stops
        ("RuntimeDirectory", layout.RUN_DIR[len("/run/") :]),
        ("RuntimeDirectoryPreserve", "yes"),
        ("RuntimeDirectoryMode", "0755"),
    )


def agent(data_root: str = layout.DATA_ROOT) -> tuple:
    """The host's action agent: the day-2 actions of the one lifecycle, as root (systemctl over D-Bus,
    Docker's socket, the env files root owns). It writes the instances' env files (a remove), the
    host's reserved ports (sysctl, with the last instance removed: CAP_NET_ADMIN, as for nft), the
    host's lock under /run, its own state, and under data_root a session's Documents moved aside at its
    end (lifecycle.take_files) and the empty one made in its place: the container user's directory,
    so CAP_DAC_OVERRIDE, CAP_CHOWN and CAP_FOWNER (it has Docker's socket, which is root already)."""
    return (
        *(entry for entry in _COMMON if entry[0] != "ProtectKernelTunables"),
        ("CapabilityBoundingSet", "CAP_NET_ADMIN CAP_DAC_OVERRIDE CAP_CHOWN CAP_FOWNER"),
        ("ProtectHome", "yes"),
        ("PrivateTmp", "yes"),
        ("PrivateDevices", "yes"),
        ("ProtectKernelModules", "yes"),
        ("RestrictAddressFamilies", "AF_UNIX AF_NETLINK AF_INET AF_INET6"),
        ("ReadWritePaths", f"{layout.CONFIG_DIR} /etc/sysctl.d /run /proc/sys/net/ipv4 {data_root}"),
        ("StateDirectory", layout.AGENT_STATE_DIR[len("/var/lib/") :]),
        ("StateDirectoryMode", "0700"),
        ("UMask", "0077"),
    )


def firewall() -> tuple:
    """isaac-sim-firewall.service: nft loads and deletes the collection's tables (netlink and
    CAP_NET_ADMIN), reading its rules file. Runs early at boot (DefaultDependencies=no): nothing
    that needs /tmp or /var mounted; the kernel may load nf_tables modules on its behalf."""
    return (
        *_COMMON,
        # no PrivateUsers: CAP_NET_ADMIN in a namespace of its own would not reach the host's tables
        ("CapabilityBoundingSet", "CAP_NET_ADMIN"),
        ("ProtectHome", "yes"),
        ("PrivateDevices", "yes"),
        ("ProtectProc", "invisible"),
        ("ProcSubset", "pid"),
        ("RestrictAddressFamilies", "AF_NETLINK"),
        ("IPAddressDeny", "any"),
        ("SystemCallFilter", "~@privileged @resources"),
        ("SystemCallErrorNumber", "EPERM"),
        ("UMask", "0077"),
    )


def server() -> tuple:
    """A network server that needs nothing of the host's (the registry mirror): as a system user of
    its own (set by its unit), no capability, no devices, its own user namespace, nothing writable
    but what its unit names (ReadWritePaths), IP and local sockets only."""
    return (
        ("AmbientCapabilities", ""),
        ("CapabilityBoundingSet", ""),
        ("NoNewPrivileges", "yes"),
        ("ProtectSystem", "strict"),
        ("ProtectHome", "yes"),
        ("PrivateTmp", "yes"),
        ("PrivateDevices", "yes"),
        ("PrivateUsers", "yes"),
        ("ProtectKernelTunables", "yes"),
        ("ProtectKernelModules", "yes"),
        ("ProtectKernelLogs", "yes"),
        ("ProtectControlGroups", "yes"),
        ("ProtectClock", "yes"),
        ("ProtectHostname", "yes"),
        ("ProtectProc", "invisible"),
        ("ProcSubset", "pid"),
        ("RestrictNamespaces", "yes"),
        ("RestrictRealtime", "yes"),
        ("RestrictSUIDSGID", "yes"),
        ("LockPersonality", "yes"),
        ("MemoryDenyWriteExecute", "yes"),
        ("RestrictAddressFamilies", "AF_UNIX AF_INET AF_INET6"),
        ("SystemCallArchitectures", "native"),
        ("SystemCallFilter", "@system-service"),
        ("SystemCallFilter", "~@privileged @resources"),
        ("SystemCallErrorNumber", "EPERM"),
        ("UMask", "0077"),
    )


def web_server() -> tuple:
    """The front door's nginx: its master binds the HTTP(S) ports, reads the certificate's key as
    root and drops its workers to the web user (setuid, and chown of its temporary directories);
    no PrivateUsers, as that user must exist inside. It writes only its runtime directory and
    reaches the hosts behind it over IP, the login service and the journal's socket."""
    return (
        *_COMMON,
        ("CapabilityBoundingSet", "CAP_NET_BIND_SERVICE CAP_SETUID CAP_SETGID CAP_CHOWN"),
        ("ProtectHome", "yes"),
        ("PrivateTmp", "yes"),
        ("PrivateDevices", "yes"),
        ("ProtectKernelModules", "yes"),
        ("RestrictAddressFamilies", "AF_UNIX AF_INET AF_INET6"),
        ("SystemCallErrorNumber", "EPERM"),
    )


def relay(user: str, low_port: bool = False) -> tuple:
    """The front door's TURN relay (coturn): the package's own user, no capability but binding a
    port below 1024 where its TLS port is one; it relays over IP and writes only its state
    directory (its SQLite user database)."""
    return (
        *(entry for entry in _COMMON if entry[0] not in ("User", "AmbientCapabilities")),
        ("User", user),
        ("Group", user),
        ("AmbientCapabilities", "CAP_NET_BIND_SERVICE" if low_port else ""),
        ("CapabilityBoundingSet", "CAP_NET_BIND_SERVICE" if low_port else ""),
        ("ProtectHome", "yes"),
        ("PrivateTmp", "yes"),
        ("PrivateDevices", "yes"),
        ("ProtectKernelModules", "yes"),
        ("ProtectProc", "invisible"),
        # netlink: coturn finds its listening and relay addresses with getifaddrs()
        ("RestrictAddressFamilies", "AF_UNIX AF_INET AF_INET6 AF_NETLINK"),
        ("UMask", "0077"),
    )
