# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""What of Docker is on a host: which of its packages are installed, and its service's state.

Asked by docker_daemon_config in the call that merges daemon.json, so the docker_engine role
learns both in one round trip; the package manager's query is the role's (vars/<OS family>.yml).
"""

from __future__ import annotations

# systemctl show's properties that say whether the service runs and starts at boot
SERVICE_PROPERTIES = ("ActiveState", "UnitFileState")


def missing(packages: list, query_out: str) -> list:
    """The packages not installed, in their order; query_out has a line "NAME ii" for each installed
    one (dpkg-query's Status-Abbrev, or the RedHat query written to print the same)."""
    installed = {line.split()[0] for line in query_out.splitlines() if line.split()[1:2] == ["ii"]}
    return [p for p in packages if p not in installed]


def service_state(show_out: str) -> dict:
    """systemctl show's KEY=value lines as a dict (an unknown unit reads inactive, UnitFileState empty)."""
    return dict(line.split("=", 1) for line in show_out.splitlines() if "=" in line)


def probe(run, packages: list, query: list, service: str) -> dict:
    """{"missing": [...], and with a service "service_state": {...}}; run(argv) -> (rc, out, err).
    The query's exit code is not read: dpkg-query exits 1 when one of the packages is unknown and
    still prints the others."""
    _rc, out, _err = run(list(query) + list(packages)) if packages and query else (0, "", "")
    found = {"missing": missing(packages, out)}
    if service:
        props = [arg for name in SERVICE_PROPERTIES for arg in ("-p", name)]
        rc, shown, _err = run(["systemctl", "show", service, *props])
        found["service_state"] = service_state(shown) if rc == 0 else {}
    return found
