"""What of Docker is on a host, from the package query and systemctl show as a Debian 12 host
answered them (the molecule host: docker.io installed, docker-ce known to dpkg but not installed)."""

from __future__ import annotations

from ansible_collections.isaacsim.fleet.plugins.module_utils.host import docker_engine

QUERY = ["dpkg-query", "--show", "--showformat=${Package} ${db:Status-Abbrev}\n"]
# dpkg-query's answer for docker.io python3-requests docker-ce containerd.io (the last unknown to
# dpkg: it is left out, said on stderr, and the exit code is 1)
DPKG_OUT = "docker-ce un \ndocker.io ii \npython3-requests ii \n"
SHOWN = "ActiveState=active\nUnitFileState=enabled\n"


def answers(calls, query_out=DPKG_OUT, shown=SHOWN, show_rc=0):
    def run(argv):
        calls.append(argv)
        if argv[0] == "systemctl":
            return show_rc, shown, ""
        return 1, query_out, "dpkg-query: no packages found matching containerd.io\n"

    return run


def test_the_packages_not_installed_in_their_order_whatever_the_query_s_exit_code():
    calls = []
    found = docker_engine.probe(
        answers(calls), ["docker-ce", "docker.io", "containerd.io", "python3-requests"], QUERY, "docker.service"
    )
    assert found == {
        "missing": ["docker-ce", "containerd.io"],
        "service_state": {"ActiveState": "active", "UnitFileState": "enabled"},
    }
    assert calls == [
        QUERY + ["docker-ce", "docker.io", "containerd.io", "python3-requests"],
        ["systemctl", "show", "docker.service", "-p", "ActiveState", "-p", "UnitFileState"],
    ]


def test_an_installed_engine_misses_nothing_and_an_unknown_unit_reads_inactive():
    found = docker_engine.probe(
        answers([], shown="ActiveState=inactive\nUnitFileState=\n"), ["docker.io"], QUERY, "docker.service"
    )
    assert found == {"missing": [], "service_state": {"ActiveState": "inactive", "UnitFileState": ""}}


def test_no_packages_no_query_and_no_service_no_systemctl():
    calls = []
    assert docker_engine.probe(answers(calls), [], QUERY, "") == {"missing": []}
    assert calls == []


def test_systemctl_failing_leaves_the_state_empty():
    found = docker_engine.probe(answers([], show_rc=1), ["docker.io"], QUERY, "docker.service")
    assert found["service_state"] == {}


def test_the_redhat_query_s_lines_read_as_installed():
    # vars/RedHat.yml's query prints "NAME ii" for each installed package, "package X is not installed" else
    out = "moby-engine ii\npackage python3-requests is not installed\n"
    assert docker_engine.missing(["moby-engine", "python3-requests"], out) == ["python3-requests"]
