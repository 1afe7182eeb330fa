# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""Warm before first start: one cache per (release, image, GPU model, driver), made once for the fleet.

A first start on empty caches compiles shaders for minutes. Before the lifecycle starts an instance
whose cache directories hold nothing (a new instance, a new host), the deploy gives it a copy of a
cache warmed for its key. The cache is made once for the fleet, on the first host that needs it, by
a one-off container: the instance's own image, launch script, arguments and GPU, on Docker's bridge
network (its ports are its own: nothing of the host's is taken) and with every mount on scratch
directories, started until the release's ready line and stopped cleanly. What its cache mounts
(releases.WARM_CACHES) then hold is the archive of that key.

No assumption about NVIDIA's warm-up script is made: the warm run is the instance's own first start.
Only regular files and directories under the cache mounts go in an archive and come out of it, and
only into the caches of an instance that is not running and whose caches are empty: nothing a user
keeps is overwritten. An instance of another key (another image, GPU model or driver) gets none.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import posixpath
import re
import shutil
import tarfile
import tempfile
import time

from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib import (
    container_policy,
    docker_cli,
    fleet_status,
    layout,
)
from ansible_collections.isaacsim.fleet.plugins.module_utils.instance.releases import WARM_CACHES

KEY_MEMBER = "key.json"
SUFFIX = ".tar"
# the warm run's ports are its own (bridge network): its address for a setting that must name one
WARM_ADDRESS = "127.0.0.1"


class WarmError(Exception):
    pass


class BrokenArchiveError(WarmError):
    """An archive that cannot be read: the host's copy is removed, so the next deploy copies it again."""


def key(release: str, image_id: str, gpu_model: str, driver: str, profile: str = "streaming") -> dict:
    """What a cache is valid for: the release, image and way of running (isaac_sim_profile: its launch script)
    that compiled it, the GPU model and driver it was compiled for (a driver or GPU of another kind recompiles)."""
    return {
        "release": str(release),
        "image_id": str(image_id),
        "profile": str(profile),
        "gpu_model": gpu_model or "",
        "driver": driver or "",
    }


def key_id(k: dict) -> str:
    return hashlib.sha256(json.dumps(k, sort_keys=True).encode()).hexdigest()[:16]


def instance_keys(plan: dict, image_id: str, gpus: list, driver: str) -> dict:
    """{instance id: (key id, key)} for the plan's instances; an instance without a GPU: no model, no driver."""
    models = {g.get("index"): g.get("name", "") for g in gpus or []}
    out = {}
    for inst in plan["instances"]:
        gpu = inst.get("gpu")
        model, drv = (models.get(gpu, ""), driver) if gpu is not None else ("", "")
        k = key(plan["release"], image_id, model, drv, inst.get("profile", "streaming"))
        out[inst["id"]] = (key_id(k), k)
    return out


def has_file(path: str) -> bool:
    """Whether a directory holds a regular file below it, as isaac-sim-cache-state's `find DIR -type f` tells
    a warm cache: links are not files, and a directory that is a link is not looked into."""
    if os.path.islink(path):
        return False
    for root, _dirs, files in os.walk(path):
        if any(os.path.isfile(os.path.join(root, f)) and not os.path.islink(os.path.join(root, f)) for f in files):
            return True
    return False


def cold(plan: dict, image_id: str, gpus: list, driver: str, active: set, holds=has_file) -> tuple[dict, dict]:
    """({key id: [instance ids]}, {key id: key}) of the instances that would start on empty caches: not
    running (active: ids whose unit is active) and no cache directory holding a file."""
    found, keys = {}, {}
    if not image_id or image_id == "unknown":
        return found, keys
    every = instance_keys(plan, image_id, gpus, driver)
    for inst in plan["instances"]:
        if inst["id"] in active or any(holds(path) for path in inst.get("caches") or []):
            continue
        kid, k = every[inst["id"]]
        found.setdefault(kid, []).append(inst["id"])
        keys[kid] = k
    return found, keys


def held(store: str, listdir=os.listdir) -> list:
    """The key ids whose archive the host keeps."""
    try:
        names = listdir(store)
    except FileNotFoundError:
        return []
    return sorted(n[: -len(SUFFIX)] for n in names if n.endswith(SUFFIX) and not n.startswith("."))


def archive(store: str, kid: str) -> str:
    if not re.fullmatch(r"[0-9a-f]{16}", kid or ""):
        raise WarmError(f"{kid!r} is not a cache key id (16 hex digits)")
    return os.path.join(store, kid + SUFFIX)


def _rel(inst: dict, source: str) -> str:
    """Where a mount's host directory goes under the warm run's scratch directory."""
    root = inst["root"].rstrip("/") + "/"
    return source[len(root) :] if source.startswith(root) else "shared/" + os.path.basename(source.rstrip("/"))


def words(args) -> list:
    """(argument as one word, option, value) of docker run arguments, read as Docker's client reads them
    (hostlib/docker_cli.py: -Pv SRC:DST is two options, --label a=b one): each option by its long name,
    its value joined (--label a=b: ("--label=a=b", "--label", "a=b")); a boolean flag has value None."""
    out = []
    for name, value in docker_cli.parse(args):
        opt = f"--{name}"
        if name in docker_cli.BOOLS:
            out.append((opt if value == "true" else f"{opt}={value}", opt, None))
        else:
            out.append((f"{opt}={value}", opt, value))
    return out


def _read_only(opt: str, value: str) -> str:
    """A mount of the user's own (not the instance's directories) for the warm run: read-only, so the
    one-off start writes nothing into the user's data."""
    if opt == "--volume":
        parts = value.split(":")
        if len(parts) == 2:
            return f"--volume={value}:ro"
        modes = [m for m in parts[2].split(",") if m not in ("rw", "ro")] + ["ro"]
        return f"--volume={':'.join(parts[:2])}:{','.join(modes)}"
    fields = [f for f in value.split(",") if f not in ("readonly", "ro", "readonly=false", "readonly=true")]
    return f"--mount={','.join(fields + ['readonly'])}"


def run_argv(plan: dict, inst: dict, image_id: str, scratch: str, name: str, kid: str) -> tuple[list, list]:
    """(docker run argv, scratch subdirectories) of the warm run of `inst`: its own arguments, environment
    (secrets left out) and GPU, its mounts on scratch and the user's read-only, Docker's bridge network with
    nothing published, no healthcheck."""
    public = inst.get("address") or plan.get("public_address") or ""
    env = dict(inst.get("container_env") or {})
    secret = set(inst.get("secret_env_names") or [])
    argv = ["docker", "run", "--detach", f"--name={name}", f"--label={layout.LABEL_WARM}={kid}", "--network=bridge"]
    subdirs = []
    dropped = ("--network", "--ip", "--ip6", "--label", "--publish", "--publish-all", "--name")
    for arg, opt, value in words(inst["docker_args"]):
        if opt in dropped or opt.startswith("--health-") or opt == "--no-healthcheck":
            continue
        if opt == "--volume" and value is not None:
            source, _sep, rest = value.partition(":")
            if source in inst.get("dirs", []):
                sub = _rel(inst, source)
                subdirs.append(sub)
                arg = f"--volume={scratch}/{sub}:{rest}"
            else:
                arg = _read_only(opt, value)
        elif opt == "--mount" and value is not None:
            arg = _read_only(opt, value)
        elif opt == "--env" and value is not None and "=" not in value:
            if value in secret:
                continue
            if value in env:
                arg = f"--env={value}={WARM_ADDRESS if public and env[value] == public else env[value]}"
        argv.append(arg)
    app = [
        f"{a.rsplit('=', 1)[0]}={WARM_ADDRESS}" if public and a.endswith("=" + public) else a for a in inst["app_args"]
    ]
    return argv + [image_id] + app, subdirs


def safe_member(member: tarfile.TarInfo) -> str | None:
    """The member's normalised name when it is a file or directory under a cache mount; None otherwise."""
    if not (member.isfile() or member.isdir()):
        return None
    name = posixpath.normpath(member.name)
    if name.startswith("/") or ".." in name.split("/"):
        return None
    if not any(name == sub or name.startswith(sub + "/") for sub in WARM_CACHES):
        return None
    return name


def pack(scratch: str, dest: str, k: dict) -> int:
    """Write the scratch directory's cache mounts and the key to `dest` (through a temporary name); its size.
    Every file goes in as a regular member, a hard link's too; links and special files stay out."""
    tmp = f"{dest}.partial"
    with tarfile.open(tmp, "w") as tar:
        data = json.dumps(k, sort_keys=True).encode()
        info = tarfile.TarInfo(KEY_MEMBER)
        info.size, info.mode, info.mtime = len(data), 0o644, int(time.time())
        tar.addfile(info, io.BytesIO(data))
        for sub in WARM_CACHES:
            top = os.path.join(scratch, sub)
            for root, dirs, files in os.walk(top):
                dirs.sort()
                for entry in sorted(files) + dirs:
                    path = os.path.join(root, entry)
                    if os.path.islink(path):
                        continue
                    arcname = os.path.relpath(path, scratch)
                    if os.path.isdir(path):
                        tar.add(path, arcname=arcname, recursive=False)
                    elif os.path.isfile(path):
                        info = tar.gettarinfo(path, arcname)
                        info.type, info.linkname, info.size = tarfile.REGTYPE, "", os.path.getsize(path)
                        with open(path, "rb") as f:
                            tar.addfile(info, f)
    # the caches are no secret (the warm run had none): readable, so the controller fetches it as itself
    os.chmod(tmp, 0o644)
    os.replace(tmp, dest)
    return os.path.getsize(dest)


def read_key(path: str) -> dict:
    with tarfile.open(path) as tar:
        member = tar.getmember(KEY_MEMBER)
        return json.loads(tar.extractfile(member).read())


def seed(path: str, root: str, uid: int, gid: int, want: dict) -> int:
    """Unpack the cache archive at `path` into an instance's directory `root` (its cache mounts only), owned
    by the container's user; the number of files. Refuses an archive of another key than `want`.

    Unpacked into a scratch directory beside them first, then each cache directory moved into place, where
    the instance has it empty (a directory with anything in it, or a link, is left as it is): a seed that
    fails half-way (a full disk, a broken archive) leaves the caches as they were."""
    try:
        found = read_key(path)
    except (tarfile.TarError, KeyError, ValueError, OSError) as exc:
        raise BrokenArchiveError(f"{path} is no cache archive ({exc})") from exc
    if found != want:
        raise WarmError(f"{path} holds the cache of {found}, not of {want}")
    if not os.path.isdir(root):
        os.makedirs(os.path.dirname(root), exist_ok=True)
        _dirs_to(root, os.path.dirname(root), uid, gid)
    scratch = tempfile.mkdtemp(prefix=".warm-seed.", dir=root)
    count = 0
    try:
        with tarfile.open(path) as tar:
            for member in tar:
                name = safe_member(member)
                if name is None:
                    continue
                target = os.path.join(scratch, name)
                _dirs_to(os.path.dirname(target) if member.isfile() else target, scratch, uid, gid)
                if member.isfile():
                    with tar.extractfile(member) as src, open(target, "xb") as dst:
                        shutil.copyfileobj(src, dst)
                    os.chown(target, uid, gid)
                    os.chmod(target, member.mode & 0o755 | 0o600)
                    os.utime(target, (member.mtime, member.mtime))
                    count += 1
        for sub in WARM_CACHES:
            made, place = os.path.join(scratch, sub), os.path.join(root, sub)
            if not os.path.isdir(made) or os.path.islink(place):
                continue
            if os.path.isdir(place):
                try:
                    os.rmdir(place)  # only an empty one: a cache with anything in it is kept as it is
                except OSError:
                    continue
            _dirs_to(os.path.dirname(place), root, uid, gid)
            os.rename(made, place)
    except tarfile.TarError as exc:
        raise BrokenArchiveError(f"{path} is a broken cache archive ({exc}); nothing was unpacked") from exc
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    return count


def _dirs_to(path: str, root: str, uid: int, gid: int):
    """Make the directories from `root` down to `path`, each owned by the container's user, mode 0750."""
    rel = os.path.relpath(path, root)
    current = root
    for part in [] if rel == "." else rel.split(os.sep):
        current = os.path.join(current, part)
        if os.path.islink(current):
            raise WarmError(f"{current} is a link: left alone, nothing unpacked through it")
        if not os.path.isdir(current):
            os.mkdir(current, 0o750)
            os.chown(current, uid, gid)


class Warmer:
    """Runs the warm run on a host. run(argv) -> (rc, out, err), as AnsibleModule.run_command."""

    def __init__(self, run, sleep=time.sleep, clock=time.monotonic):
        self.run = run
        self.sleep = sleep
        self.clock = clock

    def sweep(self, store: str):
        """Warm runs and scratch directories a killed run left (this run holds the host's lock)."""
        rc, out, _err = self.run(["docker", "ps", "-aq", "--filter", f"label={layout.LABEL_WARM}"])
        ids = out.split() if rc == 0 else []
        if ids:
            self.run(["docker", "rm", "-f"] + ids)
        for name in os.listdir(store) if os.path.isdir(store) else []:
            path = os.path.join(store, name)
            if not layout.warm_scratch(store, name):
                continue
            if os.path.isdir(path) and not os.path.islink(path):
                shutil.rmtree(path, ignore_errors=True)
            else:
                os.unlink(path)

    def warm(self, plan: dict, inst: dict, image_id: str, store: str, kid: str, k: dict) -> dict:
        """Start the warm run of `inst`, wait for the ready line, stop it cleanly, keep its caches in the store."""
        os.makedirs(store, mode=0o755, exist_ok=True)
        self.sweep(store)
        scratch = tempfile.mkdtemp(prefix=f".{kid}.", dir=store)
        name = layout.WARM_CONTAINER_PREFIX + kid
        settings = plan["settings"]
        try:
            os.chmod(scratch, 0o711)
            argv, subdirs = run_argv(plan, inst, image_id, scratch, name, kid)
            for sub in subdirs:
                _dirs_to(os.path.join(scratch, sub), scratch, plan["uid"], plan["gid"])
            started = self.clock()
            try:
                # made, judged by the container policy as an instance's unit judges its own, then started
                rc, _out, err = self.run(["docker", "create", *argv[3:]])
                if rc != 0:
                    raise WarmError(f"the warm run of instance {inst['id']} did not start: {err.strip()[-400:]}")
                options = argv[3 : len(argv) - len(inst["app_args"]) - 1]
                for _key, text, why in self._judged(name, options, inst.get("gpu")):
                    raise WarmError(
                        f"the warm run of instance {inst['id']} was not started: the container policy refuses what "
                        f"Docker made of its arguments: {text} {why}"
                    )
                rc, _out, err = self.run(["docker", "start", name])
                if rc != 0:
                    raise WarmError(f"the warm run of instance {inst['id']} did not start: {err.strip()[-400:]}")
                after = self._ready(name, plan["ready_pattern"], settings["ready_timeout"], started)
            finally:
                self.run(["docker", "stop", "-t", str(settings["stop_timeout"]), name])
                self.run(["docker", "rm", "-f", name])
            size = pack(scratch, archive(store, kid), k)
        finally:
            shutil.rmtree(scratch, ignore_errors=True)
        return {"ready_after_s": round(after, 1), "bytes": size}

    def _judged(self, name: str, options: list, gpu) -> list:
        """What the container policy refuses of the created warm run beyond its own arguments; Docker not
        answering is a refusal (fails closed)."""

        def docker_json(*args):
            rc, out, err = self.run(["docker", *args])
            if rc != 0:
                raise ValueError(err.strip()[-200:])
            return json.loads(out)

        try:
            return container_policy.check_created(name, options, gpu, docker_json, os.path.realpath)
        except (ValueError, KeyError, TypeError, AttributeError) as exc:
            return [(None, "(unknown)", f"could not be judged: Docker did not show it ({exc})")]

    def _ready(self, name: str, pattern: str, timeout: int, started: float) -> float:
        ready = re.compile(pattern)
        logs = ""
        while True:
            rc, out, err = self.run(["docker", "logs", name])
            logs = out + err
            if rc == 0 and ready.search(logs):
                return self.clock() - started
            rc, state, _err = self.run(["docker", "inspect", "-f", "{{.State.Status}}", name])
            if rc != 0 or state.strip() in ("exited", "dead"):
                raise WarmError(f"the warm run {name} ended before its ready line: {_tail(logs)}")
            if self.clock() - started > timeout:
                raise WarmError(f"the warm run {name} printed no ready line in {timeout} s: {_tail(logs)}")
            self.sleep(2)


def _tail(text: str) -> str:
    lines = [line for line in text.strip().splitlines() if line.strip()]
    return " | ".join(lines[-5:])[-600:] or "(it printed nothing)"


def active(systemctl_show: str) -> set:
    """The instance ids whose unit runs or starts, from `systemctl show -p Id -p ActiveState UNIT...`."""
    running = ("active", "activating", "reloading", "deactivating")
    return {
        i
        for i, props in fleet_status.parse_systemctl_show(systemctl_show).items()
        if props.get("ActiveState") in running
    }


def call(p: dict, check: bool, run) -> dict:
    """The module isaac_sim_warm_cache: probe, warm one key, or seed (see its documentation). A seed that
    fails for one instance is said in `warnings` and that instance starts cold; a broken archive is removed
    from the host, so the next deploy copies it again."""
    plan = p["plan"]
    store = layout.warm_dir(plan["layout"]["data_root"])
    running = set()
    if plan["instances"]:
        units = [layout.unit(i["id"]) for i in plan["instances"]]
        rc, out, _err = run(["systemctl", "show", "-p", "Id", "-p", "ActiveState", "--", *units])
        # systemd unreachable: every instance counts as running, so none is touched
        running = active(out) if rc == 0 else {i["id"] for i in plan["instances"]}
    found, keys = cold(plan, p["image_id"], p["gpus"], p["driver"], running)
    result = {"cold": found, "keys": keys, "held": held(store), "store": store, "changed": False, "warnings": []}
    by_id = {inst["id"]: inst for inst in plan["instances"]}
    warmer = Warmer(run)
    if p["state"] == "probe" and not check:
        # a warm run a killed deploy left (this run holds the host's lock): it must not keep a GPU
        warmer.sweep(store)
    elif p["state"] == "warm":
        if p["key"] not in found:
            raise WarmError(f"no instance of this host would start on empty caches with the cache key {p['key']}")
        if not check:
            inst = by_id[found[p["key"]][0]]
            result.update(warmer.warm(plan, inst, p["image_id"], store, p["key"], keys[p["key"]]))
            result["held"] = held(store)
        result["changed"] = True
    elif p["state"] == "seed":
        seeded = {}
        for kid, ids in found.items():
            if kid not in result["held"]:
                continue
            path = archive(store, kid)
            for i in ids:
                try:
                    seeded[i] = 0 if check else seed(path, by_id[i]["root"], plan["uid"], plan["gid"], keys[kid])
                except (WarmError, OSError) as exc:
                    result["warnings"].append(f"instance {i} starts on empty caches: {exc}")
                    if isinstance(exc, BrokenArchiveError) and os.path.exists(path):
                        os.unlink(path)
                        break
        result.update(seeded=seeded, changed=bool(seeded))
    return result


def fleet_plan(hosts: list, kept: list) -> dict:
    """Who does what for the fleet's caches. hosts: [(name, key ids its instances need, key ids it keeps)] in
    play order; kept: the key ids the controller keeps. {name: {"warm": [...], "fetch": [...], "copy": [...]}}:
    each key no one has is warmed on the first host needing it, and fetched from there to the controller; a
    key a host keeps but the controller lacks is fetched from the first such host; every other host needing a
    key it lacks is given the controller's copy."""
    out = {name: {"warm": [], "fetch": [], "copy": []} for name, _need, _have in hosts}
    needed = []
    for _name, need, _have in hosts:
        needed += [kid for kid in need if kid not in needed]
    for kid in needed:
        source = None
        if kid not in kept:
            source = next((name for name, _need, have in hosts if kid in have), None)
            if source is None:
                source = next(name for name, need, _have in hosts if kid in need)
                out[source]["warm"].append(kid)
            out[source]["fetch"].append(kid)
        for name, need, have in hosts:
            if kid in need and kid not in have and name != source:
                out[name]["copy"].append(kid)
    return out
