"""The fleet's registry mirror (roles/registry_mirror) and one digest for the fleet, after the cold deploy.

Runs first of the fleet's modules (file order), right after converge: the three hosts were deployed
cold through the mirror (isaacsim-mirror-1, Debian's Distribution registry in proxy mode) from the
stand-in upstream (tests/fixtures/registry, login required as NGC's), the deploy having copied the
pinned image into the mirror's storage first (isaac_sim_mirror_seed). The upstream's own access log
says what it served to whom: every blob of the image to the mirror once, none to a host.
Every host runs the one digest the deploy pinned, from the mirror. A host without the registry key
still deploys (it pulls through the mirror, which holds the key).
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import tarfile
from datetime import datetime, timezone
from pathlib import Path

import pytest
import testbed
from fleethosts import all_ready, ip, playbook, ready_fleet, sh, squash
from testbed import ROOT, client

MIRROR = "isaacsim-mirror-1"
UPSTREAM_LOG = (
    Path(os.environ.get("ISAACSIM_FLEET_REGISTRY_STATE", "/var/lib/isaacsim-fleet/registry")) / "registry.log"
)
# the access log: 172.17.0.5 - - [26/Nov/2026:12:00:00 +0000] "GET /v2/... HTTP/1.1" 200 1234 "" "agent"
ACCESS = re.compile(
    r'^(?P<addr>\S+) \S+ \S+ \[(?P<when>[^\]]+)\] "(?P<method>\S+) (?P<path>\S+) [^"]*" (?P<status>\d+) (?P<size>\d+|-)'
)
BLOB = re.compile(r"^/v2/.+/blobs/(?P<digest>sha256:[0-9a-f]{64})$")


@pytest.fixture(scope="module")
def fleet():
    return ready_fleet()


def served_since(container: str) -> list:
    """(client address, blob digest, bytes) of every blob the upstream served since the container started."""
    started = client().containers.get(container).attrs["State"]["StartedAt"][:19]
    start = datetime.strptime(started, "%Y-%m-%dT%H:%M:%S").replace(tzinfo=timezone.utc)
    found = []
    for line in UPSTREAM_LOG.read_text(errors="replace").splitlines():
        hit = ACCESS.match(line)
        blob = hit and BLOB.match(hit["path"])
        fresh = blob and datetime.strptime(hit["when"], "%d/%b/%Y:%H:%M:%S %z") >= start
        if fresh and hit["method"] == "GET" and hit["status"] == "200":
            found.append((hit["addr"], blob["digest"], int(hit["size"]) if hit["size"].isdigit() else 0))
    return found


def pinned(host: str) -> str:
    return re.search(r'^ISAAC_SIM_IMAGE_PINNED="([^"]+)"', sh(host, "cat /etc/isaac-sim/instance-0.env"), re.M).group(1)


def test_a_cold_deploy_fetched_the_image_from_upstream_through_the_mirror_alone(fleet):
    mirror = f"{ip(MIRROR)}:5443"
    refs = {h: pinned(h) for h in fleet}
    # every host runs the one digest, from the mirror
    assert len(set(refs.values())) == 1 and all(r.startswith(f"{mirror}/") for r in refs.values()), refs
    repository, digest = refs[fleet[0]].split("/", 1)[1].split("@")
    for h in fleet:
        info = json.loads(sh(h, "docker inspect isaac-sim-0 isaac-sim-1 isaac-sim-2 isaac-sim-3"))
        assert {c["Config"]["Image"] for c in info} == {refs[h]}, h
    # the image's blobs as the registries store them (compressed), from the manifest the mirror serves
    manifest = json.loads(
        sh(
            fleet[0],
            f"curl -sf --cacert /etc/docker/certs.d/{mirror}/ca.crt "
            "-H 'Accept: application/vnd.docker.distribution.manifest.v2+json' "
            f"https://{mirror}/v2/{repository}/manifests/{digest}",
        )
    )
    blobs = {layer["digest"]: layer["size"] for layer in manifest["layers"]}
    blobs[manifest["config"]["digest"]] = manifest["config"]["size"]
    served = [(addr, d, size) for addr, d, size in served_since(MIRROR) if d in blobs]
    to_mirror = [d for addr, d, _size in served if addr == ip(MIRROR)]
    to_hosts = [d for addr, d, _size in served if addr in {ip(h) for h in fleet}]
    assert to_hosts == [], "a host pulled from the upstream itself"
    fetched, size = sum(bytes_ for addr, _d, bytes_ in served if addr == ip(MIRROR)), sum(blobs.values())
    print(f"upstream bytes / image size: {fetched / size:.2f} ({fetched} of {size} bytes, {len(fleet)} hosts)")
    # every blob once for the whole fleet: copied into the mirror before any host pulled, then served by
    # the proxy from its storage (a proxy asked first fetches a blob twice: once to keep, once to serve)
    assert set(to_mirror) == set(blobs), (to_mirror, blobs)
    assert max(to_mirror.count(d) for d in blobs) == 1, to_mirror
    assert fetched == size, (fetched, size)
    # the copy's writable registry is gone with it, and its key's file too
    assert sh(MIRROR, "systemctl is-active isaac-sim-mirror-seed.service; true").strip() != "active"
    assert sh(MIRROR, "ls /run | grep -c '^isaac-sim-seed' ; true").strip() == "0"


def test_every_instance_of_the_cold_fleet_started_warm_from_one_warm_run(fleet):
    """Warm before first start: one warm run for the fleet's one key (release, image; no GPU here), its
    archive kept by the controller and copied to the other hosts, every instance's very first start warm."""
    kept = sorted((Path(os.environ["MOLECULE_EPHEMERAL_DIRECTORY"]) / "warm-caches").glob("*.tar"))
    assert len(kept) == 1, kept
    controller = hashlib.sha256(kept[0].read_bytes()).hexdigest()
    with tarfile.open(kept[0]) as tar:
        key = json.load(tar.extractfile("key.json"))
        # the stand-in adds a line to its cache's marker at each start: the archive holds one start, the warm run
        marker = tar.extractfile("cache/main/ov/standin-shader-cache").read().decode().split()
    assert key["release"] == "6.x" and key["gpu_model"] == "" and len(marker) == 1, (key, marker)
    for h in fleet:
        # byte for byte the controller's archive on every host: made once, copied, never warmed again
        held = sh(h, f"sha256sum /var/lib/isaac-sim/warm-caches/{kept[0].name}").split()[0]
        assert held == controller, h
        image_id = json.loads(sh(h, "docker inspect isaac-sim-0"))[0]["Image"]
        assert key["image_id"] == image_id, (key, image_id)
        # the warm run left no container and no scratch directory
        assert sh(h, "docker ps -aq --filter label=org.isaacsim.fleet.warm").strip() == "", h
        assert sh(h, "ls -A /var/lib/isaac-sim/warm-caches").split() == [kept[0].name], h
        for i in range(4):
            first = sh(h, f"journalctl -u isaac-sim@{i} --no-pager | grep 'starting as' | head -n 1")
            assert "shader cache warm" in first, (h, i, first)
        # status says so, beside the time each took to its ready line
        for inst in testbed.info(h)["instances"]:
            assert inst["cache_at_start"] == "warm" and inst["ready_after_s"] is not None, (h, inst)


def test_status_says_whether_the_mirror_serves_and_what_its_storage_holds(fleet, tmp_path):
    repository = pinned(fleet[0]).split("/", 1)[1].split("@")[0]

    def status(where):
        run = playbook("status.yml", {"fleet_report_dir": str(where)})
        assert run.returncode == 0, squash(run.stdout + run.stderr)[-3000:]
        report = json.loads((where / "status.json").read_text())
        return report, (where / "status.txt").read_text(), (where / "status.html").read_text()

    report, text, page = status(tmp_path / "up")
    [mirror] = report["mirrors"]
    assert mirror["host"] == MIRROR and mirror["healthy"] and mirror["http_status"] == 200, mirror
    assert mirror["repositories"].get(repository, 0) >= 1 and mirror["images"] >= 1, mirror
    files = sh(MIRROR, "find /var/lib/docker-registry -type f -printf '%s\\n' | awk '{s += $1} END {print s}'")
    assert mirror["used_bytes"] == int(files) and 0 < mirror["free_bytes"] <= mirror["size_bytes"], mirror
    assert f"mirror {MIRROR}: serving (HTTP 200), " in text
    assert f'<p class="mirror" data-mirror="{MIRROR}">' in page
    # a stopped mirror is reported down with why; the status run itself still succeeds
    sh(MIRROR, "systemctl stop isaac-sim-mirror.service")
    try:
        report, text, page = status(tmp_path / "down")
        [mirror] = report["mirrors"]
        assert not mirror["healthy"] and mirror["active"] == "inactive" and mirror["http_status"] is None
        assert f"mirror {MIRROR}: DOWN (no answer), " in text and "isaac-sim-mirror.service is inactive" in text
        assert f'<p class="mirror bad" data-mirror="{MIRROR}">' in page
    finally:
        sh(MIRROR, "systemctl start isaac-sim-mirror.service")
        # the unit is started before the registry listens, and the next test pulls through it at once
        answer = f"curl -sk -o /dev/null -w '%{{http_code}}' --max-time 3 https://{ip(MIRROR)}:5443/v2/; true"
        testbed.wait_for(lambda: sh(fleet[0], answer).strip() == "200", timeout=60, what="the mirror to answer again")


STORE = "/var/lib/docker-registry/docker/registry/v2"


def revisions() -> set:
    """(repository, digest) of every manifest the mirror's storage holds."""
    listing = sh(MIRROR, f"cd {STORE}/repositories && find . -path '*/_manifests/revisions/sha256/*' -name link")
    found = set()
    for path in listing.split():
        head, _sep, tail = path[2:].partition("/_manifests/revisions/sha256/")
        found.add((head, "sha256:" + tail.split("/")[0]))
    return found


def blobs_of(digest: str) -> set:
    hexd = digest.split(":")[1]
    manifest = json.loads(sh(MIRROR, f"cat {STORE}/blobs/sha256/{hexd[:2]}/{hexd}/data"))
    return {layer["digest"] for layer in manifest["layers"]} | {manifest["config"]["digest"]}


def held_blobs() -> set:
    return {"sha256:" + p.split("/")[-2] for p in sh(MIRROR, f"find {STORE}/blobs -name data").split()}


def test_the_collection_keeps_what_the_fleet_runs_and_drops_the_rest(fleet):
    mirror = f"{ip(MIRROR)}:5443"
    repository, kept = pinned(fleet[0]).split("/", 1)[1].split("@")
    before = revisions()
    # an image no instance runs, pulled through the mirror by a host: the proxy keeps it
    sh(fleet[0], f"docker pull -q {mirror}/{repository}:6.0.1-crash")
    extra = revisions() - before
    assert len(extra) == 1, extra
    [(_name, unused)] = extra
    only_its = blobs_of(unused) - blobs_of(kept)
    assert only_its and only_its <= held_blobs() and blobs_of(unused) & blobs_of(kept), "no shared base layer"
    try:
        # a collection that does not hear from every host deletes nothing: their image may be on the mirror alone
        run = playbook("registry_mirror_gc.yml", limit=f"{MIRROR},{fleet[0]}")
        out = squash(run.stdout + run.stderr)
        assert run.returncode != 0 and f"Nothing was deleted: {fleet[1]}, {fleet[2]} did not say" in out, out[-2000:]
        assert revisions() == before | extra
        run = playbook("registry_mirror_gc.yml")
        out = squash(run.stdout + run.stderr)
        assert run.returncode == 0, out[-3000:]
        assert f"1 images dropped: {repository}@{unused}" in out
        assert revisions() == before and (repository, kept) in before
        # the layers only the dropped image used are gone; the kept image's, shared base included, stay
        assert not only_its & held_blobs() and blobs_of(kept) <= held_blobs()
        assert sh(MIRROR, "systemctl is-active isaac-sim-mirror.service; true").strip() == "active"
        again = squash(playbook("registry_mirror_gc.yml").stdout)
        assert "0 images dropped; 0.0 MiB freed" in again
        assert re.search(rf"{MIRROR} : ok=\d+ changed=0 ", again), again[-1500:]
    finally:
        sh(fleet[0], f"docker rmi -f {mirror}/{repository}:6.0.1-crash; true")


def test_only_the_mirror_holds_the_upstream_key_and_a_host_without_it_deploys(fleet):
    key = (ROOT / "tests" / "fixtures" / "registry" / "ngc-api-key").read_text().strip()
    # on the mirror: in its configuration alone, which only the registry's user reads
    assert sh(MIRROR, "stat -c '%a %U' /etc/isaac-sim/mirror/config.yml").split() == ["600", "docker-registry"]
    holding = sh(MIRROR, f"grep -rlsF -e '{key}' /etc /var/lib /root /tmp /run; true").split()
    assert holding == ["/etc/isaac-sim/mirror/config.yml"], holding
    assert set(sh(MIRROR, "ps -o user= -C docker-registry").split()) == {"docker-registry"}
    measured = testbed.exposure_of(lambda command: sh(MIRROR, command), "isaac-sim-mirror.service")
    assert measured == testbed.listed_exposure("isaac-sim-mirror.service"), measured
    # a host given no key at all, forced to pull again: it pulls through the mirror, never logs in
    last = fleet[-1]
    run = playbook("deploy.yml", {"isaac_sim_registry_password": "", "isaac_sim_image_pull": "always"}, limit=last)
    out = squash(run.stdout + run.stderr)
    assert run.returncode == 0, out[-3000:]
    assert re.search(r"TASK \[isaacsim\.fleet\.isaac_sim : Pull the Isaac Sim image[^\]]*\] \*+ (changed|ok): ", out)
    assert not re.search(r"Log in to the image's registry, into the pull's own config\] \*+ (changed|ok): ", out)
    testbed.wait_for(lambda: all_ready(last), timeout=240, what=f"{last} ready")
    assert sh(last, f"grep -rlsF -e '{key}' /etc /root /var/lib /run /tmp; true").strip() == ""


def test_the_mirror_answers_the_fleet_and_comes_back_after_a_reboot(fleet):
    mirror = f"{ip(MIRROR)}:5443"
    ask = f"curl -s -o /dev/null -w '%{{http_code}}' --max-time 5 --cacert /etc/docker/certs.d/{mirror}/ca.crt"
    ask += f" https://{mirror}/v2/; true"
    assert sh(fleet[0], ask) == "200"
    assert "tcp dport 5443 ip saddr 172.16.0.0/12 accept" in sh(MIRROR, "nft list table inet isaac_sim_mirror")
    # a power cut, as before: systemd (PID 1, no STOPSIGNAL) takes Docker's SIGTERM for a re-exec, so
    # any grace time only waited for the kill
    client().containers.get(MIRROR).restart(timeout=0)
    testbed.wait_for(
        lambda: sh(MIRROR, "systemctl is-active isaac-sim-mirror.service; true").strip() == "active",
        timeout=120,
        what="the mirror's unit after the reboot",
    )
    testbed.wait_for(lambda: sh(fleet[0], ask) == "200", timeout=60, what="the mirror answering again")
    assert "isaac_sim_mirror" in sh(MIRROR, "nft list tables")


def test_a_mirror_out_of_reach_in_the_middle_of_a_deploy_is_named_with_the_host_and_its_unit(fleet):
    # the mirror ran when the deploy checked it, and cannot be reached from the first host once it pulls: a
    # rule on that host refuses its connections to the mirror's port (as a mirror that went down does)
    first = fleet[0]
    mirror = f"{ip(MIRROR)}:5443"
    before = sh(first, "docker ps -q --no-trunc --filter name=isaac-sim- | sort")
    sh(
        first,
        "nft add table inet cut && nft add chain inet cut out '{ type filter hook output priority 0; }' && "
        f"nft add rule inet cut out ip daddr {ip(MIRROR)} tcp dport 5443 reject with tcp reset",
    )
    try:
        # the image the host runs, pulled again (as a host that lacks it would)
        run = playbook("deploy.yml", {"isaac_sim_image_pull": "always"}, limit=first)
    finally:
        sh(first, "nft delete table inet cut")
    said = squash(run.stdout + run.stderr)
    assert run.returncode != 0
    assert f"{first} could not pull {mirror}/fixtures/isaac-sim-standin@sha256:" in said, said[-3000:]
    assert f"through the fleet's registry mirror {mirror} (isaac-sim-mirror.service on {MIRROR}): Docker said" in said
    assert "connection refused" in said
    # no instance was touched
    assert sh(first, "docker ps -q --no-trunc --filter name=isaac-sim- | sort") == before
