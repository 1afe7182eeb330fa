# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""Fill the registry mirror with the fleet's pinned images before any host pulls (module
isaac_sim_mirror_seed, run on the mirror host).

Why: asked for a blob it does not hold, Debian's Distribution 2.8 proxy fetches it from the upstream
twice (once to keep, once to serve its first client: registry/proxy/proxyblobstore.go at v2.8.2),
so a fleet pulling through it costs the upstream twice the image. Copied once by skopeo into the
mirror's own storage, the image is what the proxy then holds: it serves a manifest asked by digest
and every blob of it from its storage and asks the upstream nothing (measured with Debian's
docker-registry 2.8.2 and skopeo 1.9.3). The copy goes through a second registry process of the
same package, writable, on the loopback only, on the same storage, for the copy's time alone, as
the registry's own user and sandboxed as the mirror; the upstream's credentials are taken from the
mirror's own config and live, for the copy, in a root-only file on /run, removed after it.
Content the proxy did not fetch is not on its expiry schedule, so a seeded image stays.
"""

from __future__ import annotations

import base64
import hashlib
import json
import os
import re
import shutil
import socket
import tempfile
import time
from http.client import HTTPConnection
from urllib.parse import urlparse

from ansible_collections.isaacsim.fleet.plugins.module_utils.common import sandbox
from ansible_collections.isaacsim.fleet.plugins.module_utils.host import registry_mirror

UNIT = "isaac-sim-mirror-seed.service"
SKOPEO = "/usr/bin/skopeo"
STORE = f"{registry_mirror.DATA}/docker/registry/v2"  # the filesystem driver's layout under its root
RUN_PREFIX = "isaac-sim-seed."
_REF_RE = re.compile(r"^(?P<name>[a-z0-9]+(?:[._/-][a-z0-9]+)*)@(?P<digest>sha256:[0-9a-f]{64})\Z")


class SeedError(Exception):
    pass


# what skopeo says, and what it means (the first that matches)
_CAUSES = (
    (re.compile(r"no space left on device", re.I), "disk"),
    (re.compile(r"unauthorized|authentication required|requested access to the resource is denied|\b40[13]\b", re.I),
     "login"),
    (re.compile(r"manifest unknown|not found|\b404\b|name unknown", re.I), "missing"),
    (re.compile(r"connection refused|no such host|i/o timeout|timed out|network is unreachable|tls:|x509", re.I),
     "unreachable"),
)  # fmt: skip


def failure(where: str, name: str, digest: str, url: str, said: str, free_bytes=None) -> str:
    """The seed's error for a copy skopeo could not make: where (the mirror host and its unit), what
    was copied, the real cause as skopeo's words show it, and the fix for that cause."""
    cause = next((kind for pattern, kind in _CAUSES if pattern.search(said)), "")
    head = f"{where}: copying {name}@{digest} from {url} into the mirror failed"
    quoted = said.strip()[-600:]
    if cause == "disk":
        free = f" ({free_bytes / 1024**3:.1f} GiB free now)" if free_bytes is not None else ""
        return (
            f"{head}: the mirror's disk is full{free}; its partial upload was removed ({quoted}). Fix: free space "
            f"on the mirror's disk (playbooks/registry_mirror_gc.yml drops the images the fleet no longer runs) or "
            "give it a larger one, then deploy again."
        )
    if cause == "login":
        return (
            f"{head}: {url} refused the mirror's login ({quoted}). Fix: check registry_mirror_username and "
            "registry_mirror_password (for NGC, $oauthtoken and a current API key), then run the registry_mirror role."
        )
    if cause == "missing":
        return (
            f"{head}: {url} does not have it ({quoted}). Fix: check that the image and its tag still exist "
            "upstream (a withdrawn tag cannot be seeded)."
        )
    if cause == "unreachable":
        return (
            f"{head}: the mirror host does not reach {url} ({quoted}). Fix: check the mirror host's network, "
            "DNS and proxy towards the upstream."
        )
    return f"{head}: {quoted}. Fix: read skopeo's words above; the mirror host must reach {url} with its login."


def wanted(references: list, mirror: str) -> list:
    """[(repository, digest)] of the references a host pulls through the mirror (MIRROR/NAME@DIGEST),
    each once, in order."""
    found = []
    for ref in references:
        head, _slash, rest = str(ref).partition("/")
        hit = _REF_RE.match(rest) if head == mirror else None
        if not hit:
            raise SeedError(
                f"{ref!r} is not an image pinned on the mirror {mirror} (MIRROR/REPOSITORY@sha256:DIGEST). "
                "Fix: pass the references isaac_sim_image_pin answered."
            )
        if (hit["name"], hit["digest"]) not in found:
            found.append((hit["name"], hit["digest"]))
    return found


def blob_path(digest: str) -> str:
    algo, hexd = digest.split(":", 1)
    return f"blobs/{algo}/{hexd[:2]}/{hexd}/data"


def link_path(name: str, kind: str, digest: str) -> str:
    algo, hexd = digest.split(":", 1)
    return f"repositories/{name}/{kind}/{algo}/{hexd}/link"


def missing(read, name: str, digest: str) -> list:
    """What the mirror's storage lacks of NAME@DIGEST for the proxy to serve it all itself: the
    manifest, and each image's config and layers (an index's images each). read(path under STORE)
    answers the file's bytes, or None."""
    if read(link_path(name, "_manifests/revisions", digest)) is None or read(blob_path(digest)) is None:
        return [f"manifest {digest}"]
    manifest = json.loads(read(blob_path(digest)))
    lacking = []
    for child in manifest.get("manifests") or []:
        lacking += missing(read, name, child["digest"])
    for part in ([manifest["config"]] if manifest.get("config") else []) + (manifest.get("layers") or []):
        if read(link_path(name, "_layers", part["digest"])) is None or read(blob_path(part["digest"])) is None:
            lacking.append(f"blob {part['digest']}")
    return lacking


def upstream_of(config_text: str) -> dict:
    """The upstream and its credentials, from the mirror's config (JSON, registry_mirror.config)."""
    proxy = json.loads(config_text).get("proxy") or {}
    if not proxy.get("remoteurl"):
        raise SeedError("the mirror's config names no upstream (proxy.remoteurl). Fix: run the registry_mirror role.")
    return {"url": proxy["remoteurl"], "username": proxy.get("username", ""), "password": proxy.get("password", "")}


def auth_file(upstream: dict) -> str:
    """skopeo's auth file (containers-auth.json) for the upstream alone."""
    host = urlparse(upstream["url"]).netloc
    token = base64.b64encode(f"{upstream['username']}:{upstream['password']}".encode()).decode()
    return json.dumps({"auths": {host: {"auth": token}}}) + "\n"


def seed_config(port: int) -> str:
    """The writable registry on the loopback, on the mirror's storage: no proxy, no TLS (loopback)."""
    return (
        json.dumps(
            {
                "version": 0.1,
                "log": {"level": "warn", "fields": {"service": "isaac-sim-mirror-seed"}},
                "storage": {"filesystem": {"rootdirectory": registry_mirror.DATA}},
                "http": {"addr": f"127.0.0.1:{port}"},
            },
            indent=2,
        )
        + "\n"
    )


def registry_argv(config_path: str) -> list:
    """systemd-run of the writable registry: a transient unit as the registry's user, sandboxed as
    the mirror (common/sandbox.server), its storage the one thing writable, the loopback its only peer."""
    props = [
        ("User", registry_mirror.USER),
        ("Group", registry_mirror.USER),
        *sandbox.server(),
        ("ReadWritePaths", registry_mirror.DATA),
        ("IPAddressAllow", "localhost"),
        ("IPAddressDeny", "any"),
    ]
    argv = ["systemd-run", f"--unit={UNIT}", "--quiet", "--collect"]
    for key, value in props:
        argv.append(f"--property={key}={value}")
    return argv + [registry_mirror.REGISTRY, "serve", config_path]


def copy_argv(upstream: dict, name: str, digest: str, port: int, authfile: str) -> list:
    """skopeo copy of NAME@DIGEST from the upstream into the loopback registry, byte for byte (an
    index with all its images; --preserve-digests fails rather than convert)."""
    url = urlparse(upstream["url"])
    argv = [SKOPEO, "copy", "--all", "--preserve-digests", "--quiet", "--retry-times", "3"]
    argv += ["--src-authfile", authfile, "--dest-tls-verify=false"]
    if url.scheme == "http":
        argv.append("--src-tls-verify=false")
    return argv + [f"docker://{url.netloc}/{name}@{digest}", f"docker://127.0.0.1:{port}/{name}@{digest}"]


def inspect_argv(upstream: dict, name: str, tag: str, authfile: str) -> list:
    """skopeo inspect --raw of NAME:TAG on the upstream itself: its top-level manifest as the upstream
    serves it now (never the mirror's cached copy), whose sha256 is the digest Docker pins."""
    url = urlparse(upstream["url"])
    argv = [SKOPEO, "inspect", "--raw", "--retry-times", "2", "--authfile", authfile]
    if url.scheme == "http":
        argv.append("--tls-verify=false")
    return argv + [f"docker://{url.netloc}/{name}:{tag}"]


def upstream_answer(rc: int, out: bytes, err: bytes, password: str = "") -> dict:
    """{"digest"} of a manifest skopeo printed, or {"cause", "said"}: missing (the upstream has no
    such tag: withdrawn), login, unreachable, or "" (another failure)."""
    if rc == 0 and out.strip():
        return {"digest": "sha256:" + hashlib.sha256(out).hexdigest()}
    said = (out + err).decode(errors="replace").strip()
    if password:
        said = said.replace(password, "********")
    cause = next((kind for pattern, kind in _CAUSES if pattern.search(said)), "")
    return {"cause": "" if cause == "disk" else cause, "said": said[-400:]}


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def manifests(store: str) -> list:
    """[(repository, digest)] of every manifest revision in the storage."""
    found = []
    top = os.path.join(store, "repositories")
    for root, dirs, _files in os.walk(top):
        if "_manifests" in dirs:
            revisions = os.path.join(root, "_manifests", "revisions", "sha256")
            names = sorted(os.listdir(revisions)) if os.path.isdir(revisions) else []
            found += [(os.path.relpath(root, top), f"sha256:{hexd}") for hexd in names]
        dirs[:] = [d for d in dirs if not d.startswith("_")]
    return sorted(found)


def read_under(store: str, path: str):
    """The bytes of a file of the storage, or None."""
    try:
        with open(os.path.join(store, path), "rb") as f:
            return f.read()
    except (FileNotFoundError, NotADirectoryError):
        return None


class Seeder:
    """The I/O of a seed on the mirror host. run(argv) -> (rc, out, err), as AnsibleModule.run_command."""

    def __init__(self, run, store=STORE, config=f"{registry_mirror.CONFIG_DIR}/config.yml", scratch="/run", host=None):
        self.run = run
        self.store = store
        self.config = config
        self.scratch = scratch  # a tmpfs: the key's file never reaches a disk
        self.where = f"the registry mirror on {host or socket.gethostname()} ({registry_mirror.UNIT})"

    def read(self, path: str):
        return read_under(self.store, path)

    def lacking(self, images: list) -> dict:
        """{(name, digest): [what is missing]} of the images the storage does not hold whole."""
        found = {}
        for name, digest in images:
            gaps = missing(self.read, name, digest)
            if gaps:
                found[(name, digest)] = gaps
        return found

    def upstream(self) -> dict:
        try:
            with open(self.config, encoding="utf-8") as f:
                return upstream_of(f.read())
        except FileNotFoundError as exc:
            raise SeedError(
                f"{self.config} is missing: this host runs no mirror. Fix: run the registry_mirror role."
            ) from exc

    def ask(self, images: list, mirror: str, run_bytes) -> dict:
        """{image: upstream_answer() and "url"} for the images (as the user wrote them) that the hosts
        pull by tag through this mirror, asked of the upstream with the mirror's own credentials (in a
        root-only file on /run for the asking's time). run_bytes(argv) -> (rc, out, err) as bytes: the
        manifest is hashed as the upstream sent it. {} where this host runs no mirror yet (the pin then
        asks the upstream through its own host's Docker)."""
        if not os.path.exists(self.config):
            return {}
        upstream = self.upstream()
        wanted = {}
        for image in images:
            through = registry_mirror.mirror_reference(image, mirror, upstream["url"])
            path = (through or "").split("/", 1)[-1]
            if through and "@" not in path and ":" in path:
                wanted[image] = tuple(path.rsplit(":", 1))
        if not wanted:
            return {}
        scratch = tempfile.mkdtemp(prefix=RUN_PREFIX, dir=self.scratch)
        try:
            authfile = os.path.join(scratch, "auth.json")
            _write(authfile, auth_file(upstream), 0o600)
            out = {}
            for image, (name, tag) in wanted.items():
                rc, got, err = run_bytes(inspect_argv(upstream, name, tag, authfile))
                out[image] = dict(upstream_answer(rc, got, err, upstream["password"]), url=upstream["url"])
            return out
        finally:
            shutil.rmtree(scratch, ignore_errors=True)

    def sweep(self) -> None:
        """A run killed during its copy left its registry and the key's file: neither outlives it."""
        self.run(["systemctl", "stop", UNIT])
        for entry in os.listdir(self.scratch):
            if entry.startswith(RUN_PREFIX):
                shutil.rmtree(os.path.join(self.scratch, entry), ignore_errors=True)

    def copy(self, images: list, uid: int, gid: int, ready_timeout: float = 30.0) -> None:
        upstream = self.upstream()
        self.sweep()
        scratch = tempfile.mkdtemp(prefix=RUN_PREFIX, dir=self.scratch)
        try:
            os.chmod(scratch, 0o711)  # the registry's user reads its config by name, lists nothing
            port = _free_port()
            config = os.path.join(scratch, "seed.yml")
            _write(config, seed_config(port), 0o600)
            os.chown(config, uid, gid)
            authfile = os.path.join(scratch, "auth.json")
            _write(authfile, auth_file(upstream), 0o600)
            rc, out, err = self.run(registry_argv(config))
            if rc != 0:
                raise SeedError(f"the loopback registry did not start: {(out + err).strip()[-400:]}")
            self._wait(port, ready_timeout)
            for name, digest in images:
                began = time.time()
                rc, out, err = self.run(copy_argv(upstream, name, digest, port, authfile))
                if rc != 0:
                    said = (out + err).replace(upstream["password"], "********") if upstream["password"] else out + err
                    # a copy cut short (a full disk) leaves its upload behind, taking the space it took
                    self.drop_uploads(name, began)
                    raise SeedError(failure(self.where, name, digest, upstream["url"], said, self.free()))
        finally:
            self.run(["systemctl", "stop", UNIT])
            shutil.rmtree(scratch, ignore_errors=True)

    def drop_uploads(self, name: str, since: float) -> list:
        """Remove the uploads of repository `name` begun since `since` (this copy's): the registry keeps
        an upload cut short in its storage (repositories/NAME/_uploads/ID) until its own purge, days
        later. An older upload (another writer's) is left."""
        uploads = os.path.join(self.store, "repositories", name, "_uploads")
        removed = []
        for entry in os.listdir(uploads) if os.path.isdir(uploads) else []:
            path = os.path.join(uploads, entry)
            try:
                if os.path.isdir(path) and not os.path.islink(path) and os.stat(path).st_mtime >= since - 1:
                    shutil.rmtree(path, ignore_errors=True)
                    removed.append(entry)
            except OSError:
                continue
        return removed

    def free(self):
        try:
            disk = os.statvfs(self.store if os.path.isdir(self.store) else registry_mirror.DATA)
        except OSError:
            return None
        return disk.f_bavail * disk.f_frsize

    def _wait(self, port: int, timeout: float) -> None:
        deadline = time.monotonic() + timeout
        while True:
            conn = HTTPConnection("127.0.0.1", port, timeout=2)
            try:
                conn.request("GET", "/v2/")
                if conn.getresponse().status == 200:
                    return
            except OSError:
                pass
            finally:
                conn.close()
            if time.monotonic() > deadline:
                _rc, out, _err = self.run(["journalctl", "-u", UNIT, "--no-pager", "-n", "20"])
                raise SeedError(f"the loopback registry did not answer in {timeout:.0f} s: {out.strip()[-600:]}")
            time.sleep(0.3)


def _write(path: str, text: str, mode: int) -> None:
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, mode)
    with os.fdopen(fd, "w", encoding="utf-8") as f:
        f.write(text)
