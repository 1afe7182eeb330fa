# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""The verdict of a test run: the reference platform's container lifecycle rules.

systemd supervises the run's containers (one unit per service, restarts by its Restart=);
the judge only watches what they do and decides:
- a non-zero exit of any orchestrator fails the run; the run passes when every orchestrator
  has exited 0; orchestrators never restart;
- a non-orchestrator's exit before its dependencies are satisfied is ignored: here a service
  starts only once its depends_on conditions hold (compose's order), so it has no "before";
  after that, a non-zero exit fails the run unless the service has a restart policy (then
  systemd restarts it; it fails only when its retries are spent); a zero exit is ignored;
- the simulator (a borrowed fleet instance) going down fails the run;
- the run times out after `timeout` seconds;
- on any verdict the runner stops every other container.

It also says which services may start: a service starts when each of its depends_on
conditions holds (service_started, service_healthy, service_completed_successfully), as
docker compose starts them. Pure: observations in, decisions out.
"""

from __future__ import annotations

# what a service is doing, as the runner sees it through systemd and Docker
WAITING = "waiting"  # not started yet (its dependencies do not hold)
STARTING = "starting"  # its unit is starting, no container running yet
RUNNING = "running"
RESTARTING = "restarting"  # exited and systemd will start it again
EXITED = "exited"  # exited and stays down

PASSED, FAILED, TIMEOUT, ERROR = "passed", "failed", "timeout", "error"

# exit codes that are Docker's, not the container's (docker run's own failures)
DOCKER_CODES = {
    125: "docker could not run the container (see its log)",
    126: "the container's command could not be invoked",
    127: "the container's command was not found",
}


def observation(state=WAITING, exit_code=None, restarts=0, health=None, ran=False) -> dict:
    """One service as seen at one poll. ran: it has had a running container at some point."""
    return {"state": state, "exit_code": exit_code, "restarts": restarts, "health": health, "ran": ran}


def _exit_text(code) -> str:
    if code in DOCKER_CODES:
        return f"exited with {code}: {DOCKER_CODES[code]}"
    if code is not None and code > 128:
        return f"exited with {code} (killed by signal {code - 128})"
    return f"exited with {code}"


class Judge:
    """Decides one run. Call step(now, observations) at every poll until it returns a verdict."""

    def __init__(self, experience: dict, timeout: float, now: float):
        self.services = experience["services"]
        self.orchestrators = set(experience["orchestrators"])
        self.simulator = experience.get("simulator")
        self.timeout = timeout
        self.t0 = now
        self.started = {}  # service -> when its dependencies held and the runner was told to start it
        self.done = set()  # orchestrators that exited 0
        self.completed = set()  # non-orchestrators that exited 0
        self.seen_restarts = {}
        self.events = []  # [(seconds since start, service, what)]
        self.healthy = set()  # services seen healthy (an event the first time)
        self.verdict = None

    def _event(self, now, service, text):
        self.events.append((round(now - self.t0, 3), service, text))

    def _holds(self, condition: str, obs: dict, service: str) -> bool:
        if service == self.simulator:
            # the borrowed instance is ready before the run starts; it is its healthy state
            return obs["state"] == RUNNING
        if condition == "service_healthy":
            return obs["state"] == RUNNING and obs["health"] == "healthy"
        if condition == "service_completed_successfully":
            return obs["state"] == EXITED and obs["exit_code"] == 0
        # started: it has had a container, whatever it does now (compose starts dependents of a
        # service that ran and finished)
        return obs["ran"] or obs["state"] in (RUNNING, RESTARTING, EXITED)

    def startable(self, observations: dict) -> list:
        """Services not started yet whose depends_on conditions all hold now."""
        out = []
        for name, spec in self.services.items():
            if name in self.started or name == self.simulator:
                continue
            deps = spec["depends_on"]
            if all(self._holds(cond, observations.get(dep, observation()), dep) for dep, cond in deps.items()):
                out.append(name)
        return out

    def _decide(self, result, service, reason, now):
        self.verdict = {"result": result, "service": service, "reason": reason, "seconds": round(now - self.t0, 3)}
        self._event(now, service, f"verdict {result}: {reason}")

    def fail(self, now: float, service, reason: str):
        """The runner could not go on (systemd or Docker refused): an error, not the test's failure."""
        if not self.verdict:
            self._decide(ERROR, service, reason, now)

    def step(self, now: float, observations: dict) -> list:
        """Take one poll's observations; returns the services to start now ([] once decided)."""
        if self.verdict:
            return []
        for name in self.services:
            obs = observations.get(name, observation())
            if name == self.simulator:
                if obs["state"] != RUNNING:
                    self._decide(FAILED, name, "the simulator instance stopped during the run", now)
                    return []
                continue
            if name not in self.started:
                continue
            if obs["health"] == "healthy" and name not in self.healthy:
                self.healthy.add(name)
                self._event(now, name, "healthy")
            restarts = obs["restarts"]
            if restarts > self.seen_restarts.get(name, 0):
                self._event(now, name, f"restarted by its restart policy ({restarts} so far)")
                self.seen_restarts[name] = restarts
            if obs["state"] != EXITED:
                continue
            code = obs["exit_code"]
            if name in self.orchestrators:
                if name in self.done:
                    continue
                if code == 0:
                    self.done.add(name)
                    self._event(now, name, "orchestrator exited 0")
                    continue
                result = ERROR if code in DOCKER_CODES else FAILED
                self._decide(result, name, f"orchestrator {name} {_exit_text(code)}", now)
                return []
            if code == 0:
                if name not in self.completed:
                    self.completed.add(name)
                    self._event(now, name, "exited 0 (ignored: a service may finish at any time)")
                continue
            spent = f" after {restarts} restarts" if self.services[name]["restart"] != "no" else ""
            result = ERROR if code in DOCKER_CODES else FAILED
            self._decide(result, name, f"{name} {_exit_text(code)}{spent}", now)
            return []
        if self.orchestrators and self.done == self.orchestrators:
            names = ", ".join(sorted(self.orchestrators))
            self._decide(PASSED, None, f"every orchestrator exited 0 ({names})", now)
            return []
        for name, spec in self.services.items():
            if name in self.started or name == self.simulator:
                continue
            for dep, cond in spec["depends_on"].items():
                obs = observations.get(dep, observation())
                if dep != self.simulator and obs["state"] == EXITED and not self._holds(cond, obs, dep):
                    # it will not run again, so the condition will never hold (compose gives up too)
                    self._decide(
                        FAILED,
                        name,
                        f"{name} cannot start: {dep} {_exit_text(obs['exit_code'])} and {cond} will never hold",
                        now,
                    )
                    return []
        if now - self.t0 >= self.timeout:
            running = sorted(o for o in self.orchestrators if o not in self.done and o in self.started)
            waiting = sorted(s for s in self.services if s not in self.started and s != self.simulator)
            reason = f"timed out after {self.timeout:g} s"
            if running:
                reason += f" with {', '.join(running)} still running"
            if waiting:
                reason += (
                    f"{';' if running else ','} never started (their depends_on did not hold): {', '.join(waiting)}"
                )
            self._decide(TIMEOUT, (running or waiting or [None])[0], reason, now)
            return []
        starting = self.startable(observations)
        for name in starting:
            self.started[name] = now
            self._event(
                now, name, "started (its dependencies hold)" if self.services[name]["depends_on"] else "started"
            )
        return starting
