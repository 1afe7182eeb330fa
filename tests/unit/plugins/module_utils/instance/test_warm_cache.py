"""Warm before first start (module_utils/instance/warm_cache.py): the keys, which instances are cold, the
warm run's arguments, the archive's contents both ways, and who warms, fetches and is given what."""

from __future__ import annotations

import io
import json
import os
import tarfile

import pytest
from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib import docker_cli, layout
from ansible_collections.isaacsim.fleet.plugins.module_utils.instance import plan, warm_cache
from ansible_collections.isaacsim.fleet.tests.unit.helpers import plan_config

H100 = [{"index": 0, "name": "NVIDIA H100 80GB HBM3"}, {"index": 1, "name": "NVIDIA L40S"}]


def _plan(tmp_path, **over):
    cfg = plan_config(data_root=str(tmp_path / "data"), instance_count=2, secret_env_names=["NGC_KEY"], **over)
    host = {"memory_bytes": 64 * 1024**3, "image_present": True}
    if cfg["gpu_enabled"]:
        host.update(gpu_count=2, gpus=[dict(g, memory_total_mib=81559, encoder=True) for g in H100])
    p = plan.build(cfg, host)
    # the test runs as whoever it runs as: the "container user" is that user
    p["uid"], p["gid"] = os.getuid(), os.getgid()
    return p


def test_a_key_is_release_image_gpu_model_and_driver_and_an_instance_without_gpu_has_neither(tmp_path):
    p = _plan(tmp_path, gpu_enabled=True, gpu_map={0: 0, 1: 1})
    keys = warm_cache.instance_keys(p, "sha256:aa", H100, "580.65")
    assert keys[0][1] == {
        "release": "6.x",
        "image_id": "sha256:aa",
        "profile": "streaming",
        "gpu_model": "NVIDIA H100 80GB HBM3",
        "driver": "580.65",
    }
    assert keys[0][0] != keys[1][0] and len(keys[0][0]) == 16
    # one kind of GPU, one key, on any host
    assert warm_cache.instance_keys(p, "sha256:aa", H100, "580.65")[0][0] == keys[0][0]
    assert warm_cache.instance_keys(p, "sha256:aa", H100, "580.76")[0][0] != keys[0][0]
    bare = warm_cache.instance_keys(_plan(tmp_path), "sha256:aa", [], "580.65")
    assert bare[0][1]["gpu_model"] == "" and bare[0][1]["driver"] == "" and bare[0][0] == bare[1][0]
    # a headless instance runs another launch script: a cache of its own
    mixed = warm_cache.instance_keys(_plan(tmp_path, instance_profiles={1: "headless"}), "sha256:aa", [], "")
    assert mixed[0][0] != mixed[1][0] and mixed[1][1]["profile"] == "headless"


def test_cold_means_not_running_and_no_file_in_any_cache(tmp_path):
    p = _plan(tmp_path)
    found, keys = warm_cache.cold(p, "sha256:aa", [], "", active=set())
    assert list(found.values()) == [[0, 1]] and list(keys) == list(found)
    # a file anywhere under one cache of instance 1 makes it warm; instance 0 runs: neither is touched
    deep = os.path.join(p["instances"][1]["caches"][0], "a", "b")
    os.makedirs(deep)
    assert warm_cache.cold(p, "sha256:aa", [], "", active=set())[0] == {next(iter(found)): [0, 1]}
    # a link is no file (isaac-sim-cache-state's find -type f says so too)
    os.symlink("/etc/hostname", os.path.join(deep, "link"))
    assert warm_cache.cold(p, "sha256:aa", [], "", active=set())[0] == {next(iter(found)): [0, 1]}
    open(os.path.join(deep, "shader.bin"), "w").close()
    assert warm_cache.cold(p, "sha256:aa", [], "", active={0})[0] == {}
    # an image not known (check mode): nothing is cold
    assert warm_cache.cold(p, "unknown", [], "", active=set()) == ({}, {})


def test_the_running_units_are_read_from_systemctl_show():
    out = (
        "Id=isaac-sim@0.service\nActiveState=active\n\nId=isaac-sim@1.service\nActiveState=inactive\n\n"
        "Id=isaac-sim@2.service\nActiveState=activating\n"
    )
    assert warm_cache.active(out) == {0, 2}


def test_the_warm_run_is_the_instance_s_own_start_on_scratch_with_no_secret_and_its_own_network(tmp_path):
    user = [
        "--volume=/datasets:/datasets:rw",
        "--label",
        "team=a b",
        "-p",
        "8080:80",
        "--mount=type=bind,src=/m,dst=/m",
    ]
    p = _plan(
        tmp_path, gpu_enabled=True, gpu_map={0: 1, 1: 0}, docker_args=user, allowed_bind_roots=["/datasets", "/m"]
    )
    inst = p["instances"][0]
    argv, subdirs = warm_cache.run_argv(p, inst, "sha256:aa", "/scratch", "warm-isaac-sim-k", "k")
    joined = " ".join(argv)
    assert argv[:2] == ["docker", "run"] and "--network=bridge" in argv and "--network=host" not in argv
    assert f"--label={layout.LABEL_WARM}=k" in argv and f"--label={layout.LABEL_INSTANCE}=0" not in argv
    assert "--health-cmd" not in joined and "--gpus=device=1" in argv and "--runtime=nvidia" in argv
    # every mount of the instance on scratch, the user's own read-only; a two-word label and a published
    # port (host ports, on a bridge) dropped whole
    assert inst["root"] not in joined and "--volume=/datasets:/datasets:ro" in argv
    assert "--mount=type=bind,src=/m,dst=/m,readonly" in argv
    assert "team=a b" not in argv and "8080:80" not in joined and "-p" not in argv
    assert "--volume=/scratch/cache/main:/isaac-sim/.cache:rw" in argv and "cache/main" in subdirs
    # its environment by value, the host's address replaced by the warm run's own; no secret at all
    assert "--env=ACCEPT_EULA=Y" in argv and "--env=NGC_KEY" not in joined
    assert "--env=ISAACSIM_HOST=127.0.0.1" in argv and "10.0.0.5" not in joined
    image_at = argv.index("sha256:aa")
    assert argv[image_at + 1 :] == inst["app_args"]


class FakeDocker:
    """docker as the warm run sees it: create keeps what Docker makes of the arguments (docker inspect shows
    it, as docker_cli reads them, or `made` instead), start writes into the mounted scratch caches (a file, a
    link, a fifo); the ready line comes on the third look at the logs, or never. volumes: docker volume
    inspect's options of named volumes."""

    def __init__(self, ready_after=3, exits=False, made=None, volumes=None):
        self.calls = []
        self.looks = 0
        self.ready_after = ready_after
        self.exits = exits
        self.made = made
        self.volumes = volumes or {}
        self.created = []

    def __call__(self, argv):
        self.calls.append(argv)
        if argv[:2] == ["docker", "create"]:
            self.created = argv[2:]
            return 0, "cid\n", ""
        if argv[:3] == ["docker", "container", "inspect"]:
            options = [a for a in self.created if a.startswith("--")]
            inspected = dict(self.made or docker_cli.config(options))
            inspected["Mounts"] = [{"Type": "volume", "Name": n} for n in self.volumes]
            return 0, json.dumps([inspected]), ""
        if argv[:3] == ["docker", "volume", "inspect"]:
            return 0, json.dumps([{"Name": n, "Options": self.volumes[n]} for n in argv[3:]]), ""
        if argv[:2] == ["docker", "start"]:
            argv = self.created
            mounts = [a.split("=", 1)[1].split(":")[0] for a in argv if a.startswith("--volume=")]
            main = next(m for m in mounts if m.endswith("/cache/main"))
            os.makedirs(os.path.join(main, "ov", "shaders"))
            with open(os.path.join(main, "ov", "shaders", "s.bin"), "w") as fh:
                fh.write("compiled")
            os.link(os.path.join(main, "ov", "shaders", "s.bin"), os.path.join(main, "ov", "shaders", "hard.bin"))
            os.symlink("/etc/shadow", os.path.join(main, "ov", "link"))
            os.mkfifo(os.path.join(main, "fifo"))
            with open(os.path.join(next(m for m in mounts if m.endswith("/logs")), "kit.log"), "w") as fh:
                fh.write("not a cache")
            return 0, "cid\n", ""
        if argv[:2] == ["docker", "logs"]:
            self.looks += 1
            return 0, "Isaac Sim Full App is loaded.\n" if self.looks >= self.ready_after else "starting\n", ""
        if argv[:2] == ["docker", "inspect"]:
            return 0, "exited\n" if self.exits else "running\n", ""
        return 0, "", ""


def test_a_warm_run_keeps_only_files_of_the_cache_mounts_and_leaves_nothing_behind(tmp_path):
    p = _plan(tmp_path)
    store = layout.warm_dir(p["layout"]["data_root"])
    docker = FakeDocker()
    clock = iter(range(0, 100, 5))
    k = warm_cache.key("6.x", "sha256:aa", "", "")
    kid = warm_cache.key_id(k)
    out = warm_cache.Warmer(docker, sleep=lambda s: None, clock=lambda: next(clock)).warm(
        p, p["instances"][0], "sha256:aa", store, kid, k
    )
    assert out["ready_after_s"] == 15 and out["bytes"] > 0
    assert os.listdir(store) == [kid + ".tar"]
    with tarfile.open(os.path.join(store, kid + ".tar")) as tar:
        names = tar.getnames()
    assert names[0] == "key.json" and "cache/main/ov/shaders/s.bin" in names
    assert not any("link" in n or "fifo" in n or "logs" in n for n in names), names
    # a hard link goes in as a file of its own, with its content
    with tarfile.open(os.path.join(store, kid + ".tar")) as tar:
        hard = tar.getmember("cache/main/ov/shaders/hard.bin")
        assert hard.isfile() and tar.extractfile(hard).read() == b"compiled"
    # stopped cleanly (the plan's stop timeout), then removed
    assert ["docker", "stop", "-t", "60", layout.WARM_CONTAINER_PREFIX + kid] in docker.calls
    assert docker.calls[-1] == ["docker", "rm", "-f", layout.WARM_CONTAINER_PREFIX + kid]


@pytest.mark.parametrize(
    "docker, needle", [(FakeDocker(exits=True), "ended before"), (FakeDocker(ready_after=99), "no ready line in 300 s")]
)
def test_a_warm_run_that_fails_says_why_and_keeps_no_archive(tmp_path, docker, needle):
    p = _plan(tmp_path)
    store = layout.warm_dir(p["layout"]["data_root"])
    clock = iter(range(0, 10000, 50))
    with pytest.raises(warm_cache.WarmError, match=needle):
        warm_cache.Warmer(docker, sleep=lambda s: None, clock=lambda: next(clock)).warm(
            p, p["instances"][0], "sha256:aa", store, "0123456789abcdef", {}
        )
    assert os.listdir(store) == []
    assert docker.calls[-1][:3] == ["docker", "rm", "-f"]


@pytest.mark.parametrize(
    "docker, needle",
    [
        # a named volume the user gave that Docker makes a bind of the host's /etc of
        (FakeDocker(volumes={"maps": {"type": "none", "o": "bind", "device": "/etc"}}), "host path /etc"),
        # Docker's reading other than the plan's: the release's user became root
        (FakeDocker(made={"HostConfig": {}, "Config": {"User": "0"}}), "--user=0 runs the container as root"),
    ],
)
def test_a_warm_run_the_container_policy_refuses_never_starts(tmp_path, docker, needle):
    p = _plan(tmp_path, docker_args=["-v", "maps:/maps"])
    store = layout.warm_dir(p["layout"]["data_root"])
    with pytest.raises(warm_cache.WarmError, match="was not started: the container policy refuses") as raised:
        warm_cache.Warmer(docker, sleep=lambda s: None, clock=lambda: 0).warm(
            p, p["instances"][0], "sha256:aa", store, "0123456789abcdef", {}
        )
    assert needle in str(raised.value)
    assert not [c for c in docker.calls if c[:2] == ["docker", "start"]]
    assert docker.calls[-1][:3] == ["docker", "rm", "-f"] and os.listdir(store) == []


def _archive(path, k, members):
    with tarfile.open(path, "w") as tar:
        for name, data, kind in [("key.json", json.dumps(k).encode(), tarfile.REGTYPE)] + members:
            info = tarfile.TarInfo(name)
            info.type = kind
            info.size = len(data) if kind == tarfile.REGTYPE else 0
            if kind == tarfile.SYMTYPE:
                info.linkname = "/etc"
            tar.addfile(info, io.BytesIO(data) if kind == tarfile.REGTYPE else None)


def test_seeding_unpacks_files_under_the_cache_mounts_only(tmp_path):
    k = warm_cache.key("6.x", "sha256:aa", "", "")
    path = str(tmp_path / "k.tar")
    _archive(
        path,
        k,
        [
            ("cache/main/ov/s.bin", b"compiled", tarfile.REGTYPE),
            ("cache/computecache/c.bin", b"c", tarfile.REGTYPE),
            ("cache/main/evil", b"", tarfile.SYMTYPE),
            ("cache/main/../../escape", b"x", tarfile.REGTYPE),
            ("/abs", b"x", tarfile.REGTYPE),
            ("logs/kit.log", b"x", tarfile.REGTYPE),
            ("documents/x", b"x", tarfile.REGTYPE),
        ],
    )
    root = str(tmp_path / "data" / "instance-0")
    assert warm_cache.seed(path, root, os.getuid(), os.getgid(), k) == 2
    found = sorted(os.path.relpath(os.path.join(d, f), root) for d, _s, fs in os.walk(root) for f in fs)
    assert found == ["cache/computecache/c.bin", "cache/main/ov/s.bin"]
    assert not (tmp_path / "escape").exists() and not (tmp_path / "data" / "escape").exists()
    assert oct(os.stat(os.path.join(root, "cache", "main")).st_mode & 0o777) == "0o750"
    # an archive of another key is refused
    with pytest.raises(warm_cache.WarmError, match="not of"):
        warm_cache.seed(path, root, os.getuid(), os.getgid(), dict(k, driver="580"))


def test_the_module_call_warms_then_seeds_every_cold_instance_of_the_key(tmp_path):
    p = _plan(tmp_path)
    docker = FakeDocker(ready_after=1)

    def run(argv):
        if argv[0] == "systemctl":
            return (
                0,
                "Id=isaac-sim@0.service\nActiveState=inactive\n\nId=isaac-sim@1.service\nActiveState=inactive\n",
                "",
            )
        return docker(argv)

    params = {"plan": p, "image_id": "sha256:aa", "gpus": [], "driver": "", "key": None}
    probe = warm_cache.call(dict(params, state="probe"), False, run)
    [(kid, ids)] = list(probe["cold"].items())
    assert ids == [0, 1] and probe["held"] == [] and probe["changed"] is False
    with pytest.raises(warm_cache.WarmError, match="no instance"):
        warm_cache.call(dict(params, state="warm", key="0" * 16), False, run)
    warmed = warm_cache.call(dict(params, state="warm", key=kid), False, run)
    assert warmed["changed"] and warmed["held"] == [kid]
    assert warm_cache.call(dict(params, state="seed"), True, run)["seeded"] == {0: 0, 1: 0}
    seeded = warm_cache.call(dict(params, state="seed"), False, run)
    assert seeded["seeded"] == {0: 2, 1: 2} and seeded["changed"]
    # warm now: a second seed finds nothing cold, and changes nothing
    again = warm_cache.call(dict(params, state="seed"), False, run)
    assert again["cold"] == {} and again["changed"] is False


def test_systemd_not_answering_counts_every_instance_as_running(tmp_path):
    p = _plan(tmp_path)
    params = {"plan": p, "image_id": "sha256:aa", "gpus": [], "driver": "", "key": None, "state": "probe"}
    assert warm_cache.call(params, False, lambda argv: (1, "", "Failed to connect to bus"))["cold"] == {}


def test_the_fleet_warms_each_key_once_and_gives_it_to_the_others():
    hosts = [("h1", ["a"], []), ("h2", ["a", "b"], []), ("h3", ["b"], ["b"]), ("h4", ["c"], [])]
    out = warm_cache.fleet_plan(hosts, kept=["c"])
    # a: nobody keeps it, warmed on the first host needing it and kept by the controller; b: a host
    # keeps it, fetched from there; c: the controller has it
    assert out["h1"] == {"warm": ["a"], "fetch": ["a"], "copy": []}
    assert out["h2"] == {"warm": [], "fetch": [], "copy": ["a", "b"]}
    assert out["h3"] == {"warm": [], "fetch": ["b"], "copy": []}
    assert out["h4"] == {"warm": [], "fetch": [], "copy": ["c"]}
    assert warm_cache.fleet_plan([("h1", [], [])], kept=[]) == {"h1": {"warm": [], "fetch": [], "copy": []}}


def test_a_cache_that_holds_anything_or_is_a_link_is_left_and_a_broken_archive_changes_nothing(tmp_path):
    k = warm_cache.key("6.x", "sha256:aa", "", "")
    path = str(tmp_path / "k.tar")
    _archive(
        path, k, [("cache/main/ov/s.bin", b"compiled", tarfile.REGTYPE), ("cache/kit/k.bin", b"k", tarfile.REGTYPE)]
    )
    root = tmp_path / "instance-0"
    (root / "cache" / "main").mkdir(parents=True)
    (root / "cache" / "main" / "mine.txt").write_text("the user's")
    (tmp_path / "elsewhere").mkdir()
    (root / "cache" / "kit").symlink_to(tmp_path / "elsewhere")
    assert warm_cache.seed(path, str(root), os.getuid(), os.getgid(), k) == 2
    assert os.listdir(root / "cache" / "main") == ["mine.txt"] and os.listdir(tmp_path / "elsewhere") == []
    assert not [n for n in os.listdir(root) if n.startswith(".warm-seed")]
    broken = tmp_path / "broken.tar"
    with open(path, "rb") as f:
        broken.write_bytes(f.read()[:700])
    with pytest.raises(warm_cache.WarmError, match="cache archive"):
        warm_cache.seed(str(broken), str(tmp_path / "instance-1"), os.getuid(), os.getgid(), k)
    assert not (tmp_path / "instance-1" / "cache").exists()


def test_a_broken_archive_is_a_warning_the_instances_start_cold_and_it_is_removed(tmp_path):
    p = _plan(tmp_path)
    docker = FakeDocker()

    def run(argv):
        return (0, "", "") if argv[0] == "systemctl" else docker(argv)

    params = {"plan": p, "image_id": "sha256:aa", "gpus": [], "driver": "", "key": None}
    [kid] = list(warm_cache.call(dict(params, state="probe"), False, run)["cold"])
    store = layout.warm_dir(p["layout"]["data_root"])
    os.makedirs(store)
    with open(os.path.join(store, kid + ".tar"), "wb") as f:
        f.write(b"not a tar")
    out = warm_cache.call(dict(params, state="seed"), False, run)
    assert out["seeded"] == {} and out["changed"] is False and "instance 0 starts on empty caches" in out["warnings"][0]
    assert os.listdir(store) == []


def test_the_sweep_removes_a_killed_warm_run_and_its_scratch_and_nothing_else(tmp_path):
    asked = []

    def run(argv):
        asked.append(argv)
        return (0, "c0ffee\n", "") if argv[:2] == ["docker", "ps"] else (0, "", "")

    (tmp_path / ".k1.abc" / "cache").mkdir(parents=True)
    (tmp_path / "k1.tar.partial").write_text("x")
    (tmp_path / "k1.tar").write_text("x")
    (tmp_path / ".keep").write_text("a user's file")
    (tmp_path / ".linked").symlink_to(tmp_path / "k1.tar")
    warm_cache.Warmer(run).sweep(str(tmp_path))
    assert ["docker", "rm", "-f", "c0ffee"] in asked
    assert sorted(p.name for p in tmp_path.iterdir()) == [".keep", ".linked", "k1.tar"]
