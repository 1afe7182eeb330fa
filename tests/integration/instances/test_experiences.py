"""Test runs (experiences) through playbooks/experience.yml on a real systemd host: a passing
run with its artefacts, a run against a borrowed instance, one with a simulator of its own, and
bad input refused before any container starts; every container, unit, network and volume of a run gone afterwards. The
other verdicts (an orchestrator's exit 3, a crash with and without restart, a late dependency,
a timeout) are the fleet scenario's suite test (tests/integration/fleet/test_suite.py), which
runs them all in one playbook."""

import hashlib
import json
import signal
import xml.etree.ElementTree as ET
from concurrent.futures import ThreadPoolExecutor

from testbed import (
    ROOT,
    RUN_LEFTOVERS,
    all_ready,
    assert_sandboxed,
    container_id,
    info,
    instance_ready,
    registry_image,
    run_playbook,
    sh,
    start_playbook,
    wait_for,
)

FIXTURES = ROOT / "tests" / "fixtures" / "experiences"


def run(host, tmp_path, name, timeout=60, **extra):
    env = {"IMAGE": registry_image(host, "6.0.1"), **extra.pop("env", {})}
    vars_ = {
        "experience_file": str(FIXTURES / f"{name}.yml"),
        "experience_environment": env,
        "experience_timeout": timeout,
        "experience_artefacts_dir": str(tmp_path),
        **extra,
    }
    result = run_playbook(host, vars_, playbook="playbooks/experience.yml")
    runs = sorted(p for p in tmp_path.iterdir() if p.is_dir()) if tmp_path.exists() else []
    outcome = json.loads((runs[-1] / "result.json").read_text()) if runs else None
    return result, outcome, runs[-1] if runs else None


def left_behind(host) -> str:
    """Anything of any run still on the host: containers, networks, volumes, units."""
    return sh(host, RUN_LEFTOVERS).stdout.strip()


def test_a_passing_run_stops_the_companion_still_running_and_brings_everything_back(host, tmp_path):
    result, outcome, directory = run(host, tmp_path, "pass")
    assert result.returncode == 0, result.stdout[-3000:]
    assert outcome["verdict"]["result"] == "passed", outcome["events"]
    services = outcome["services"]
    assert services["check"]["exit_code"] == 0
    assert services["robot"]["exit_code"] is None and services["robot"]["state_at_verdict"] == "running"
    # compose's order: check started only once robot was healthy
    starts = {svc: t for t, svc, what in outcome["events"] if what.startswith("started")}
    assert starts["check"] > starts["robot"]
    files = {p.name for p in directory.iterdir()}
    run_id = outcome["run"]
    assert {f"{run_id}-robot.log", f"{run_id}-check.log", "compose.yml", "metrics.csv", "junit.xml"} <= files
    # what the orchestrator wrote to $ISAAC_SIM_RUN_OUTPUTS came back too
    assert (directory / "outputs" / "report.txt").read_text() == f"judged by {run_id}\n"
    assert "check passed" in (directory / f"{run_id}-check.log").read_text()
    assert "robot up" in (directory / f"{run_id}-robot.log").read_text()
    junit = ET.parse(directory / "junit.xml").getroot()
    assert junit.get("tests") == "1" and junit.get("failures") == "0"
    # CPU and memory sampled over the run; the check burned CPU for a while
    assert outcome["metrics"]["robot"]["samples"] >= 2 and outcome["metrics"]["robot"]["memory_peak_bytes"] > 0
    assert "PASSED" in result.stdout and "robot" in result.stdout  # the summary table
    assert left_behind(host) == ""
    # the run's directory is on the controller, no longer on the host
    assert sh(host, f"test -e /var/lib/isaac-sim/runs/{run_id}", check=False).rc != 0


def test_two_runs_on_one_borrowed_instance_each_get_it_clean_one_after_the_other(host, tmp_path):
    # started together: one borrows instance 0, the other waits until it is back, restarted. The
    # timeout bounds the second run's wait too (the first run, its give-back and a restart to ready):
    # CI under load once took more than 60 s for that
    before = container_id(host, "isaac-sim-0")
    with ThreadPoolExecutor(2) as pool:
        done = list(pool.map(lambda d: run(host, tmp_path / d, "sim", timeout=240, experience_instance=0), ("a", "b")))
    seen = []
    for result, outcome, directory in done:
        assert result.returncode == 0, result.stdout[-3000:]
        assert outcome["verdict"]["result"] == "passed", outcome
        # the orchestrator reached instance 0 by the simulator's service name
        log = (directory / f"{outcome['run']}-check.log").read_text()
        assert "simulator says: isaac-sim-standin signal" in log
        banner = (directory / "outputs" / "banner.txt").read_text()
        assert banner.startswith("isaac-sim-standin signal")
        seen.append(banner.split()[-1])  # the container's host name: its short id
    all_ready(host, ids=[0])
    after = container_id(host, "isaac-sim-0")
    # three containers: the one before, the one the second run got, the one after it
    assert len({before[:12], *seen, after[:12]}) == 3, (before, seen, after)
    assert sh(host, "ls /run/isaac-sim").stdout.count(".lent") == 0
    assert left_behind(host) == ""


def killed_mid_run(host, tmp_path, hold_s, runner_too=False) -> str:
    """Start a run that borrows instance 1, SIGKILL its ansible-playbook once the instance is
    lent (and the run's own process on the host too, when runner_too). Returns the run's name."""
    vars_ = {
        "experience_file": str(FIXTURES / "sim.yml"),
        "experience_environment": {"IMAGE": registry_image(host, "6.0.1"), "HOLD_S": str(hold_s)},
        "experience_instance": 1,
        "experience_timeout": 120,
        "experience_artefacts_dir": str(tmp_path / "never"),
    }
    controller = start_playbook(host, vars_, playbook="playbooks/experience.yml")
    lent = "/run/isaac-sim/instance-1.lent/run"

    def borrower():
        return sh(host, f"cat {lent}", check=False).stdout.strip()

    wait_for(borrower, timeout=120, what="instance 1 lent")
    run = borrower().split()[0]
    # its services are up: the run is well under way
    wait_for(lambda: f"isaac-sim-run-{run}-check" in sh(host, "docker ps --format '{{.Names}}'").stdout, timeout=60)
    controller.send_signal(signal.SIGKILL)
    controller.wait()
    if runner_too:
        owner = json.loads(sh(host, f"cat /run/isaac-sim/runs/{run}.json").stdout)
        sh(host, f"kill -9 {owner['pid']}")
    return run


def test_runs_whose_controller_or_runner_was_killed_leave_the_instance_clean_and_come_back_with_the_next(
    host, tmp_path
):
    runs = "/var/lib/isaac-sim/runs"
    # a controller killed mid-run: the run ends on the host by itself, gives instance 1 back
    # restarted and ready, and keeps its directory for a controller
    during = container_id(host, "isaac-sim-1")
    ended = killed_mid_run(host, tmp_path, hold_s=8)
    wait_for(
        lambda: sh(host, "ls /run/isaac-sim", check=False).stdout.count(".lent") == 0,
        timeout=180,
        what="instance 1 given back by the run itself",
    )
    assert instance_ready(host, 1) and container_id(host, "isaac-sim-1") != during
    assert json.loads(sh(host, f"cat {runs}/{ended}/result.json").stdout)["verdict"]["result"] == "passed"
    # its runner killed too: the run is stuck, holding instance 1, until the next run on the host
    swept = killed_mid_run(host, tmp_path, hold_s=300, runner_too=True)
    held = container_id(host, "isaac-sim-1")
    # the host's status names the run that holds it, the others held by nobody
    holders = {i["id"]: i["lent_to"] for i in info(host)["instances"]}
    assert holders == {0: None, 1: swept, 2: None, 3: None}, holders
    # a rolling restart meanwhile restarts the others and leaves the held one as it is, and says so
    others = {i: container_id(host, f"isaac-sim-{i}") for i in (0, 2, 3)}
    rolled = run_playbook(host, playbook="playbooks/rolling_restart.yml")
    said = " ".join((rolled.stdout + rolled.stderr).split())
    assert rolled.returncode == 0, said[-3000:]
    assert f"left for their holders: {host.backend.get_hostname()}: isaac-sim-1 (held by {swept})" in said, said[-3000:]
    assert container_id(host, "isaac-sim-1") == held
    assert all(container_id(host, f"isaac-sim-{i}") not in ("", others[i]) for i in others)
    # a run's service runs its docker client in the sandbox the security guide lists
    assert_sandboxed(host, f"isaac-sim-run-{swept}-check.service", "isaac-sim-run-RUN-SERVICE.service")
    # a run nobody will fetch, older than the retention limit
    sh(host, f"mkdir -p {runs}/ancient-run && echo '{{}}' > {runs}/ancient-run/result.json")
    sh(host, f"touch -d '20 days ago' {runs}/ancient-run/result.json {runs}/ancient-run")

    result, outcome, _directory = run(
        host, tmp_path / "next", "sim", experience_instance=1, experience_unfetched_after=2, experience_keep_days=14
    )
    assert result.returncode == 0, result.stdout[-3000:]
    assert outcome is not None
    text = " ".join((result.stdout + result.stderr).split())
    # the next run swept the stuck one, gave instance 1 back clean before borrowing it, and
    # brought both earlier runs' directories back with its own
    back = {p.name: p for p in (tmp_path / "next").iterdir() if p.is_dir()}
    assert {ended, swept} <= set(back), sorted(back)
    first = json.loads((back[ended] / "result.json").read_text())
    assert first["verdict"]["result"] == "passed"
    assert "simulator says: isaac-sim-standin signal" in (back[ended] / f"{ended}-check.log").read_text()
    second = json.loads((back[swept] / "result.json").read_text())
    assert second["verdict"]["result"] == "error" and "ended before a verdict" in second["verdict"]["reason"]
    assert (back[swept] / f"{swept}-check.log").exists()
    assert "Also brought back" in text and ended in text and swept in text
    mine = next(b for n, b in back.items() if n not in (ended, swept))
    assert json.loads((mine / "result.json").read_text())["verdict"]["result"] == "passed"
    # the instance it borrowed was not the one the killed run left
    assert (mine / "outputs" / "banner.txt").read_text().split()[-1] != held[:12]
    # retention: the old run is gone, with a warning naming it; nothing else of any run is left
    assert "ancient-run" in text and "keep_days" in text
    assert sh(host, f"ls -A {runs}").stdout.split() == [".store.lock"]
    assert sh(host, "ls /run/isaac-sim").stdout.count(".lent") == 0
    assert left_behind(host) == ""
    all_ready(host, ids=[1])


def test_a_secret_substituted_into_a_variable_reaches_the_container_and_nothing_written_down(host, tmp_path):
    # what no file, unit, process or journal line may hold, with what shells, systemd and
    # Docker's env file would each take for their own
    token = "tok-9f1c2e7d5b $HOME 'sq' \"dq\" \\ %n `id` ;|&"
    pattern = "[t]ok-9f1c2e7d5b"  # matches the token, not the command line that looks for it
    digest = hashlib.sha256(token.encode()).hexdigest()
    with ThreadPoolExecutor(1) as pool:
        running = pool.submit(
            run, host, tmp_path, "secret", env={"TOKEN_SHA256": digest}, experience_secret_environment={"TOKEN": token}
        )
        seen = []
        while not running.done():
            # while the run's units exist: their files and the host's command lines
            seen.append(sh(host, f"ps -eo args | grep '{pattern}'", check=False).stdout.strip())
            seen.append(sh(host, f"grep -rl '{pattern}' /run/systemd/system /etc/systemd", check=False).stdout.strip())
        result, outcome, directory = running.result()
    assert result.returncode == 0, result.stdout[-3000:]
    assert outcome["verdict"]["result"] == "passed", outcome
    assert "secret arrived whole" in (directory / f"{outcome['run']}-check.log").read_text()
    assert [s for s in seen if s] == []
    # nothing on the controller: artefacts, the playbook's output
    assert token not in result.stdout + result.stderr and "tok-9f1c2e7d5b" not in result.stdout + result.stderr
    for path in directory.rglob("*"):
        assert not path.is_file() or b"tok-9f1c2e7d5b" not in path.read_bytes(), path
    # nothing on the host, and not in its journal
    files = sh(host, f"grep -rl '{pattern}' /etc /run /var/lib/isaac-sim /usr/local /root", check=False).stdout
    assert files.strip() == ""
    assert sh(host, f"journalctl --no-pager | grep '{pattern}'", check=False).stdout.strip() == ""
    assert left_behind(host) == ""


def test_a_dedicated_simulator_is_a_headless_isaac_sim_of_the_run_that_keeps_its_caches(host, tmp_path):
    fleet = {i: container_id(host, f"isaac-sim-{i}") for i in range(4)}
    result, outcome, directory = run(host, tmp_path, "dedicated", experience_simulator="dedicated")
    assert result.returncode == 0, result.stdout[-3000:]
    assert outcome["verdict"]["result"] == "passed", outcome["events"]
    # the fleet's image, run headless (the release's launch) as its user; the check started once it was healthy
    log = (directory / f"{outcome['run']}-isaac-sim.log").read_text()
    assert "Isaac Sim Full App starting as uid 1234 (script isaac-sim.sh, shader cache cold)" in log, log[-2000:]
    starts = {svc: t for t, svc, what in outcome["events"] if what.startswith("started")}
    healthy = min(t for t, svc, what in outcome["events"] if (svc, what) == ("isaac-sim", "healthy"))
    assert starts["check"] >= healthy > starts["isaac-sim"], outcome["events"]
    # found by its service name on the run's network, with the release's ports
    name, address, port = (directory / "outputs" / "simulator.txt").read_text().split()
    assert (name, port) == ("isaac-sim", "49100") and address.count(".") == 3
    # stopped with the run; its caches stay for the next run on the slot, owned by its user
    assert outcome["services"]["isaac-sim"]["state_at_verdict"] == "running"
    cache = sh(host, "stat -c '%u %s' /var/lib/isaac-sim/simulators/0/cache/main/ov/standin-shader-cache")
    assert cache.stdout.split()[0] == "1234"
    assert sh(host, "ls /run/isaac-sim").stdout.count(".lent") == 0
    # no instance of the fleet was lent or restarted
    assert {i: container_id(host, f"isaac-sim-{i}") for i in range(4)} == fleet
    assert left_behind(host) == ""


def test_bad_experiences_are_refused_before_any_container_starts(host, tmp_path):
    registry = registry_image(host, "x").split("/", 1)[0]
    result, outcome, _directory = run(host, tmp_path, "bad")
    text = " ".join((result.stdout + result.stderr).split())
    assert result.returncode != 0 and outcome is None
    assert "depends_on goes round in a cycle: a -> b -> a" in text
    assert "no test orchestrator" in text
    assert "./src is a path on the machine the file was written on" in text
    result, outcome, _directory = run(host, tmp_path, "missing", env={"REGISTRY": registry})
    text = " ".join((result.stdout + result.stderr).split())
    assert result.returncode != 0 and outcome is None
    assert f"image {registry}/fixtures/no-such-image:1 cannot be had" in text
    result, outcome, _directory = run(host, tmp_path, "sim", experience_instance=7)
    text = " ".join((result.stdout + result.stderr).split())
    assert "instance: 7 is not configured on this host" in text
    image = "registry.local/sim:v1"
    result, outcome, _directory = run(
        host, tmp_path, "dedicated", experience_simulator="dedicated", experience_simulator_image=image
    )
    text = " ".join((result.stdout + result.stderr).split())
    assert result.returncode != 0 and outcome is None
    assert "simulator_release: not given, and the tag of registry.local/sim:v1 names no release" in text
    assert left_behind(host) == ""


def test_an_added_capability_is_refused_until_the_operator_names_it_and_then_the_container_has_it(host, tmp_path):
    result, outcome, _directory = run(host, tmp_path, "caps")
    text = " ".join((result.stdout + result.stderr).split())
    assert result.returncode != 0 and outcome is None
    assert (
        "caps: services.check: --cap-add=NET_ADMIN adds the capability NET_ADMIN to the container (a test run's "
        "service). Fix: remove it; where this host must allow it, add '--cap-add=NET_ADMIN' to "
        "experience_allowed_docker_args"
    ) in text
    assert left_behind(host) == ""
    result, outcome, _directory = run(host, tmp_path, "caps", experience_allowed_docker_args=["--cap-add=NET_ADMIN"])
    assert result.returncode == 0, result.stdout[-3000:]
    assert outcome["verdict"]["result"] == "passed", outcome
    assert left_behind(host) == ""
