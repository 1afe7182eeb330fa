"""Helpers for tests on the molecule test hosts (systemd + Docker inside a container).

Commands inside a host go through pytest-testinfra's ``host``; what happens
to the host container itself (a reboot) goes through the Docker SDK.
"""

from __future__ import annotations

import json
import os
import re
import resource
import shlex
import subprocess
import time
from pathlib import Path

import docker

ROOT = Path(__file__).resolve().parents[2]
CONVERGE = ROOT / "molecule" / "resources" / "converge.yml"
INSTANCES = 4


def client():
    return docker.from_env()


def sh(host, command: str, check=True):
    """Run a shell command inside a test host (a testinfra host)."""
    result = host.run(command)
    if check and result.rc != 0:
        raise AssertionError(f"{command!r} on {name(host)} failed ({result.rc}): {result.stdout}{result.stderr}")
    return result


def name(host) -> str:
    """A testinfra host's name; a name as it is (the fleet's tests name their hosts)."""
    return host if isinstance(host, str) else host.backend.get_hostname()


def host_ip(host) -> str:
    return client().containers.get(name(host)).attrs["NetworkSettings"]["IPAddress"]


# what a test run leaves on a host if it leaves anything: containers, networks, volumes, units, directories
RUN_LEFTOVERS = (
    "docker ps -aq --filter label=org.isaacsim.fleet.run; "
    "docker network ls -q --filter label=org.isaacsim.fleet.run; "
    "docker volume ls -q --filter label=org.isaacsim.fleet.run; "
    "ls /run/systemd/system | grep isaac-sim-run- || true; "
    "systemctl list-units --all --no-legend 'isaac-sim-run-*' | grep . || true; "
    "ls /var/lib/isaac-sim/runs 2>/dev/null || true"
)


def inventory() -> str:
    """Molecule's inventory directory: the scenario's hosts and group_vars, linked."""
    inv = os.environ.get("MOLECULE_INVENTORY_FILE")
    if not inv:
        raise RuntimeError("run these tests through molecule (molecule verify), which provides the inventory")
    return os.path.dirname(inv)


def converge_playbook() -> str:
    """The scenario's converge playbook (molecule exports the scenario's directory)."""
    own = Path(os.environ.get("MOLECULE_SCENARIO_DIRECTORY", "/nonexistent")) / "converge.yml"
    return str(own if own.exists() else CONVERGE)


def changed_count(result, host) -> int:
    match = re.search(rf"{re.escape(name(host))}\s*:.*changed=(\d+)", result.stdout)
    assert match, result.stdout[-2000:]
    return int(match.group(1))


def playbook_command(host, extra_vars=None, check=False, extra_inventory=None, playbook=None, raw_vars=()):
    """The ansible-playbook command line and environment of run_playbook."""
    book = str(ROOT / playbook) if playbook else converge_playbook()
    cmd = ["ansible-playbook", "-i", inventory(), "--limit", name(host), book]
    if extra_inventory:
        cmd += ["-i", str(extra_inventory)]
    if extra_vars:
        cmd += ["-e", json.dumps(extra_vars)]
    for raw in raw_vars:
        cmd += ["-e", raw]
    if check:
        cmd.append("--check")
    return cmd, dict(os.environ, ANSIBLE_FORCE_COLOR="0", ANSIBLE_NOCOLOR="1")


# each Ansible call of a test, its wall and CPU seconds: where a scenario's time goes (tools/test sums them)
CALLS = ROOT / "tests" / "output" / "ansible-calls.tsv"


def timed(kind: str, call):
    started, before = time.monotonic(), resource.getrusage(resource.RUSAGE_CHILDREN)
    try:
        return call()
    finally:
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        cpu = after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime
        test = os.environ.get("PYTEST_CURRENT_TEST", "?").split(" ", 1)[0]
        scenario = os.environ.get("MOLECULE_SCENARIO_NAME", "?")
        try:
            with CALLS.open("a") as out:
                out.write(f"{scenario}\t{test}\t{kind}\t{time.monotonic() - started:.2f}\t{cpu:.2f}\n")
        except OSError:
            pass


def start_playbook(host, extra_vars=None, playbook=None) -> subprocess.Popen:
    """run_playbook in the background: the caller waits for it (communicate)."""
    cmd, env = playbook_command(host, extra_vars, playbook=playbook)
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env, cwd=ROOT)


def run_playbook(
    host, extra_vars: dict | None = None, check=False, extra_inventory=None, playbook=None, raw_vars=()
) -> subprocess.CompletedProcess:
    """A playbook (the scenario's converge unless named, e.g. "playbooks/status.yml") on this host only.

    raw_vars: "name=value" strings given with -e as an operator types them (every value a string).
    """
    cmd, env = playbook_command(host, extra_vars, check, extra_inventory, playbook, raw_vars)
    book = Path(playbook or converge_playbook()).stem
    result = timed(
        f"playbook {book}",
        lambda: subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=900, cwd=ROOT, check=False),
    )
    if f"{name(host)} " not in result.stdout.split("PLAY RECAP", 1)[-1]:
        raise AssertionError(f"the playbook did not run on {name(host)}:\n{result.stdout[-2000:]}{result.stderr}")
    if " is held by " in result.stdout + result.stderr:
        # refused for another run's lock: which runs of this machine were alive then, for the failure's reader
        ps = subprocess.run(["ps", "-eo", "pid,ppid,lstart,args"], capture_output=True, text=True, check=False)
        alive = [line for line in ps.stdout.splitlines() if "ansible-playbook" in line or "PID" in line]
        result.stdout += "\n[testbed] ansible-playbook processes after the run:\n" + "\n".join(alive) + "\n"
    return result


def info(host, check=False, **params) -> dict:
    """The isaac_sim_info module's result on this host (an ad-hoc call, JSON callback)."""
    cmd = ["ansible", "-i", inventory(), name(host), "-m", "isaacsim.fleet.isaac_sim_info"]
    if params:
        cmd += ["-a", json.dumps(params)]
    if check:
        cmd.append("--check")
    env = dict(os.environ, ANSIBLE_LOAD_CALLBACK_PLUGINS="1", ANSIBLE_STDOUT_CALLBACK="json")
    out = timed(
        "info", lambda: subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=120, cwd=ROOT, check=False)
    )
    try:
        result = json.loads(out.stdout)["plays"][0]["tasks"][0]["hosts"][name(host)]
    except (ValueError, KeyError, IndexError) as exc:
        raise AssertionError(
            f"isaac_sim_info gave no result ({exc}): {out.stdout[-2000:]}{out.stderr[-2000:]}"
        ) from exc
    assert not result.get("failed"), result.get("msg")
    return result


def by_name(result: dict) -> dict:
    return {i["name"]: i for i in result["instances"]}


def unit_show(host, unit: str) -> dict:
    props = "ActiveState,SubState,NRestarts,UnitFileState,InvocationID"
    out = sh(host, f"systemctl show {shlex.quote(unit)} -p {props}").stdout
    return dict(line.split("=", 1) for line in out.strip().splitlines())


def exposure(host, unit: str) -> float:
    """systemd-analyze security's overall exposure of a loaded unit on the host."""
    return exposure_of(lambda command: sh(host, command).stdout, unit)


def exposure_of(run, unit: str) -> float:
    """The same, on a host reached by run(command) -> its output (the fleet's hosts are containers)."""
    out = run(f"systemd-analyze security --no-pager {shlex.quote(unit)}")
    found = re.search(r"Overall exposure level for \S+: (\d+\.\d+)", out)
    assert found, out[-2000:]
    return float(found.group(1))


# the security guide's sandbox table: an RST list-table whose last column is "Exposure"
SANDBOX_TABLE = ROOT / "docs" / "docsite" / "rst" / "security.rst"


def list_tables(text: str) -> list[list[list[str]]]:
    """The rows (lists of cells) of each RST list-table of a document, cells of one line each."""
    tables, rows, inside = [], None, False
    for line in text.splitlines():
        if line.strip().startswith(".. list-table::"):
            rows, inside = [], True
            tables.append(rows)
        elif inside and re.match(r"^\s*\* - ", line):
            rows.append([line.split("* - ", 1)[1].strip()])
        elif inside and rows and re.match(r"^\s+- ", line):
            rows[-1].append(line.split("- ", 1)[1].strip())
        elif inside and line.strip() and not line.startswith(" "):
            inside = False
    return tables


def listed_exposure(row: str) -> float:
    """The exposure the security guide's sandbox table lists for the unit named `row` (as the table names it)."""
    for rows in list_tables(SANDBOX_TABLE.read_text()):
        if rows and rows[0][-1] == "Exposure":
            for cells in rows[1:]:
                if cells[0] == f"``{row}``":
                    return float(cells[-1])
    raise AssertionError(f"{SANDBOX_TABLE.relative_to(ROOT)}'s sandbox table has no row for {row}")


def assert_sandboxed(host, unit: str, row: str | None = None):
    """The unit's exposure is the one the security guide lists (row: the table's name, default the unit)."""
    measured, listed = exposure(host, unit), listed_exposure(row or unit)
    print(f"systemd-analyze security {unit}: {measured}")
    assert measured == listed, f"{unit}: {measured}, {SANDBOX_TABLE.relative_to(ROOT)} lists {listed}"


def container_id(host, container: str) -> str:
    return sh(host, f"docker ps -q --no-trunc --filter name=^{container}$").stdout.strip()


def wait_for(predicate, timeout=120, interval=1.0, what="condition"):
    deadline = time.monotonic() + timeout
    last = None
    while time.monotonic() < deadline:
        try:
            last = predicate()
            if last:
                return last
        except (AssertionError, OSError, KeyError, ValueError, docker.errors.DockerException) as exc:
            last = exc  # keep polling through restarts
        time.sleep(interval)
    raise AssertionError(f"timed out after {timeout} s waiting for {what} (last: {last!r})")


def instance_ready(host, i: int) -> bool:
    show = unit_show(host, f"isaac-sim@{i}.service")
    marker = sh(host, f"test -f /run/isaac-sim/instance-{i}.ready", check=False).rc == 0
    return show["ActiveState"] == "active" and marker


def all_ready(host, ids=None, timeout=180):
    for i in range(INSTANCES) if ids is None else ids:
        wait_for(lambda i=i: instance_ready(host, i), timeout=timeout, what=f"isaac-sim@{i} ready")


def registry_image(host, tag: str) -> str:
    """The deployed image's repository (the local registry standing in for NGC) with another tag."""
    env = sh(host, "cat /etc/isaac-sim/instance-0.env").stdout
    current = next(line for line in env.splitlines() if line.startswith("ISAAC_SIM_IMAGE="))
    return current.split("=", 1)[1].strip('"').rsplit(":", 1)[0] + f":{tag}"


# everything our code could change on a host, as one text to compare
SNAPSHOT = (
    "sha256sum /etc/isaac-sim/* /etc/systemd/system/isaac-sim* /etc/docker/daemon.json "
    "/usr/local/libexec/isaac-sim/* /etc/apt/sources.list.d/* /etc/udev/rules.d/* 2>/dev/null; "
    "dpkg-query -W -f '${Package} ${Version}\\n' 2>/dev/null; "
    "ls -lnR /var/lib/isaac-sim 2>/dev/null | grep -v standin-shader-cache; "
    "docker ps -a --no-trunc --format '{{.ID}} {{.Names}} {{.Status}}' | sed 's/Up .*/Up/'; "
    "systemctl list-units --all --no-legend 'isaac-sim*' | awk '{print $1, $3, $4}'"
)


def snapshot(host) -> str:
    """Everything our code could change on a host (a testinfra host), as one text to compare."""
    return sh(host, SNAPSHOT, check=False).stdout


# the stand-in NGC registry as this machine reaches it, and its token realm (tests/fixtures/registry)
REGISTRY = "127.0.0.1:5555"
REGISTRY_REALM = "http://127.0.0.1:5557/token?service=isaacsim-fleet-fixture"
REGISTRY_KEY_FILE = ROOT / "tests" / "fixtures" / "registry" / "ngc-api-key"


def registry_status(
    path: str, scope: str, accept="application/vnd.docker.distribution.manifest.v2+json", method="GET"
) -> int:
    """The HTTP status the stand-in registry answers `method` path with, asked as a client does at a
    Bearer registry such as NGC: a token from its realm for scope, then the request with it."""
    import base64
    import urllib.error
    import urllib.request

    basic = base64.b64encode(f"$oauthtoken:{REGISTRY_KEY_FILE.read_text().strip()}".encode()).decode()
    ask = urllib.request.Request(f"{REGISTRY_REALM}&scope={scope}", headers={"Authorization": f"Basic {basic}"})
    with urllib.request.urlopen(ask, timeout=10) as answer:
        token = json.load(answer)["token"]
    request = urllib.request.Request(
        f"http://{REGISTRY}{path}", headers={"Authorization": f"Bearer {token}", "Accept": accept}, method=method
    )
    try:
        with urllib.request.urlopen(request, timeout=10) as answer:
            return answer.status
    except urllib.error.HTTPError as exc:
        return exc.code
