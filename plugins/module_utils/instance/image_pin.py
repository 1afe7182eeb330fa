# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""One image digest for the whole fleet: the tag is resolved once, before any host pulls.

A tag can move between the first host's pull and the last one's (NGC republishes tags; a team
pushes a new :latest). The deploy asks the registry once, through one host's Docker daemon (its
registry settings, mirrors and certificates are the ones its pulls use), what digest the tag
names now; every host then pulls and runs REPOSITORY@DIGEST, so a tag moved in the middle of a
run changes nothing, and the reports keep naming the tag the user wrote.
"""

from __future__ import annotations

import base64
import json
import os
import re
import ssl
from http.client import HTTPSConnection

from ansible_collections.isaacsim.fleet.plugins.module_utils.common.parse import parse_image
from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib.docker_socket import DockerError

DOCKER_HUB = "docker.io"
REFUSED = re.compile(r"unauthorized|authentication required|denied", re.IGNORECASE)
# what Docker accepts of a registry, so the digest is the one Docker itself would pin (an index's, for
# a multi-platform image)
MANIFEST_TYPES = ", ".join(
    (
        "application/vnd.docker.distribution.manifest.list.v2+json",
        "application/vnd.oci.image.index.v1+json",
        "application/vnd.docker.distribution.manifest.v2+json",
        "application/vnd.oci.image.manifest.v1+json",
    )
)


def registry_of(repository: str) -> str:
    """The registry a repository lives on, as Docker decides it: a first component with a dot, a
    port or 'localhost' is a registry; anything else is Docker Hub."""
    first, _slash, rest = repository.partition("/")
    if rest and ("." in first or ":" in first or first == "localhost"):
        return first
    return DOCKER_HUB


def auth_header(username: str, password: str, server: str) -> str:
    """Docker's X-Registry-Auth value: the credentials as base64url JSON."""
    raw = json.dumps({"username": username, "password": password, "serveraddress": server}).encode()
    return base64.urlsafe_b64encode(raw).decode("ascii")


def digest_of(answer) -> str:
    """The manifest digest in a /distribution answer (Descriptor.digest; 'Digest' on older engines)."""
    descriptor = (answer or {}).get("Descriptor") or {}
    digest = descriptor.get("digest") or descriptor.get("Digest") or ""
    return digest if digest.startswith("sha256:") and len(digest) == 71 else ""


class PinError(Exception):
    """The module fails with this message."""


def resolve(docker, image: str, username: str = "", password: str = "", asked_from: str = "") -> dict:
    """{"image": the reference as written, "pinned": REPOSITORY@DIGEST, "digest": DIGEST}.

    docker: the Engine API (DockerSocket). An image already named by digest is pinned as written,
    without asking. Raises PinError with what went wrong and the fix; the password is never in it.
    """
    repository, _tag, digest = _parsed(image)
    if digest:
        return _pin(image, repository, digest)
    server = registry_of(repository)
    auth = auth_header(username, password, server) if password else ""
    try:
        answer = docker.distribution(image, auth)
    except DockerError as exc:
        why = str(exc).replace(password, "********") if password else str(exc)
        # Docker 20.10 passes the registry's 401 on as its own 500, with the registry's word in it
        if exc.status == 404 or (exc.status != 401 and WITHDRAWN.search(str(exc)) and not REFUSED.search(str(exc))):
            raise _withdrawn(image, server, why) from exc
        if exc.status in (401, 403) or REFUSED.search(str(exc)):
            raise PinError(
                f"{server} refused the login of user {username or '(none)'} from {asked_from or 'this host'} when "
                f"asked which digest {image} names ({why[:300]}). Fix: check isaac_sim_registry_username and "
                "isaac_sim_registry_password (for NGC, user $oauthtoken and a current NGC API key), and that the "
                "image and tag exist."
            ) from exc
        raise PinError(
            f"could not ask {server} which digest {image} names: {why[:300]}. Fix: check that the host reaches "
            "the registry and that the image and tag exist, or name the image by its digest "
            "(REPOSITORY@sha256:...), or set isaac_sim_image_pin: false."
        ) from exc
    found = digest_of(answer)
    if not found:
        raise PinError(f"{server} answered without a digest for {image}: {json.dumps(answer)[:300]}")
    return _pin(image, repository, found)


def ask_mirror(reference: str, certs_dir: str = "/etc/docker/certs.d", timeout: float = 60.0, connect=None) -> dict:
    """Resolve MIRROR/NAME:TAG on the fleet's mirror with a HEAD of its manifest (Docker-Content-Digest).

    Not through Docker's /distribution: to tell an image's platform Docker fetches its config blob,
    and a proxy asked for a blob it does not hold fetches it from the upstream twice, before the
    deploy has copied the image in (host/mirror_seed.py). Trusts what Docker trusts for the mirror:
    the system's CAs and certs.d/MIRROR/ca.crt."""
    repository, tag, digest = _parsed(reference)
    if digest:
        return _pin(reference, repository, digest)
    host, _slash, name = repository.partition("/")
    tag = tag or "latest"
    context = ssl.create_default_context()
    ca = os.path.join(certs_dir, host, "ca.crt")
    if os.path.exists(ca):
        context.load_verify_locations(ca)
    conn = (connect or HTTPSConnection)(host, context=context, timeout=timeout)
    try:
        conn.request("HEAD", f"/v2/{name}/manifests/{tag}", headers={"Accept": MANIFEST_TYPES})
        answer = conn.getresponse()
        status, digest = answer.status, answer.getheader("Docker-Content-Digest") or ""
    except (OSError, ssl.SSLError) as exc:
        raise PinError(
            f"could not ask the registry mirror {host} which digest {reference} names: {exc}. Fix: check that "
            "the mirror runs (status.yml reports it) and that this host reaches it and trusts its certificate."
        ) from exc
    finally:
        conn.close()
    if status != 200 or not re.match(r"^sha256:[0-9a-f]{64}\Z", digest):
        raise PinError(
            f"the registry mirror {host} answered HTTP {status}{' with no digest' if status == 200 else ''} when "
            f"asked which digest {reference} names. Fix: check that the image and tag exist upstream and that the "
            "mirror reaches its upstream (its journal: journalctl -u isaac-sim-mirror.service)."
        )
    return _pin(reference, repository, digest)


def _parsed(image: str) -> tuple:
    """(repository, tag, digest) of a reference, or PinError naming the variable."""
    parsed = parse_image(image)
    if parsed is None:
        raise PinError(f"isaac_sim_image: {image!r} is not a valid image reference.")
    return parsed


def _pin(image: str, repository: str, digest: str) -> dict:
    return {"image": image, "pinned": f"{repository}@{digest}", "digest": digest}


WITHDRAWN = re.compile(r"manifest unknown|not found|\b404\b|name unknown", re.IGNORECASE)
OFFLINE_VAR = "isaac_sim_pin_offline"


def _withdrawn(image: str, where: str, said: str, mirror_note: str = "") -> PinError:
    return PinError(
        f"{where} no longer has {image} (…{said.strip()[-160:]}): the tag was withdrawn (or never existed)"
        f"{mirror_note}. "
        "A withdrawn image is not rolled out; nothing was changed. Fix: choose a tag the registry has "
        "(isaac_sim_image), or name the image by its digest (REPOSITORY@sha256:...) to run a copy on purpose."
    )


def _through_mirror(image, through, answer, offline, ask, docker, username, password, asked_from) -> dict:
    """The pin of an image the hosts pull through the mirror: the digest the upstream itself names now
    (answer: what the mirror's host asked it, None where no host of the inventory runs the mirror: then
    asked through this host's Docker). The mirror's own answer (it falls back to its cached copy when its
    upstream says the tag is gone) counts only with isaac_sim_pin_offline, and says so."""
    repository, _tag, digest = _parsed(through)
    if digest:
        return dict(ask(through), image=image)
    if answer is None:
        try:
            found = resolve(docker, image, username, password, asked_from)
            return dict(_pin(image, repository, found["digest"]), image=image)
        except PinError as exc:
            answer = {"cause": "missing" if WITHDRAWN.search(str(exc)) else "unreachable", "said": str(exc), "url": ""}
    if answer.get("digest"):
        return dict(_pin(image, repository, answer["digest"]), image=image)
    where = f"the upstream {answer.get('url') or registry_of(image.split('@', 1)[0])}"
    if answer.get("cause") == "missing":
        raise _withdrawn(image, where, answer.get("said", ""), " though the mirror may still hold a copy of it")
    if not offline:
        raise PinError(
            f"could not ask {where} which digest {image} names ({answer.get('cause') or 'failed'}: "
            f"{answer.get('said', '')[:300].strip()}), so whether the tag is still there is unknown; nothing was "
            f"changed. Fix: check that the mirror's host reaches its upstream and holds its key, or set {OFFLINE_VAR}: "
            "true to run the mirror's copy of the tag (the deploy says which digest)."
        )
    pin = dict(ask(through), image=image)
    pin["note"] = (
        f"{where} could not be asked ({answer.get('cause') or 'failed'}); {OFFLINE_VAR}: the mirror's copy "
        f"{pin['digest']} is used"
    )
    return pin


def pin_fleet(
    docker,
    images: dict,
    configured: dict,
    username: str = "",
    password: str = "",
    asked_from: str = "",
    mirror: str = "",
    upstream: str = "",
    ask=ask_mirror,
    upstream_answers: dict | None = None,
    offline: bool = False,
) -> dict:
    """Each distinct image of the play resolved once; what every host will run and which it moves.

    images: {host: the plan's image}; configured: {host: [what its instances run now]}; mirror:
    HOST:PORT of a pull-through mirror of `upstream` (host/registry_mirror.py): an image of that
    registry is pinned to the digest the upstream itself names (upstream_answers: the mirror host's
    answers, isaac_sim_mirror_seed's `upstream`), on the mirror's reference, so the hosts pull it
    from there; a tag the upstream no longer has stops the deploy.
    Returns {"pinned": {host: REPOSITORY@DIGEST}, "digests": {image: DIGEST}, "summary": [lines]}.
    """
    from ansible_collections.isaacsim.fleet.plugins.module_utils.host import registry_mirror

    wanted = sorted(set(images.values()) - {"", None})
    found = {}
    for image in wanted:
        through = registry_mirror.mirror_reference(image, mirror, upstream) if mirror else None
        if through:
            # the mirror serves anonymously to the fleet: no credentials leave the controller for it
            answer = (upstream_answers or {}).get(image) if upstream_answers is not None else None
            found[image] = _through_mirror(image, through, answer, offline, ask, docker, username, password, asked_from)
        else:
            found[image] = resolve(docker, image, username, password, asked_from)
    pinned = {host: found[image]["pinned"] for host, image in images.items() if image in found}
    summary = []
    for image, pin in found.items():
        mine = sorted(host for host, wanted in images.items() if wanted == image)
        now = {host: configured.get(host) or [] for host in mine}
        moving = [host for host in mine if now[host] and pin["pinned"] not in now[host]]
        first = [host for host in mine if not now[host]]
        runs = [host for host in mine if host not in moving and host not in first]
        parts = [f"{image} is {pin['digest']} now"] + ([pin["note"]] if pin.get("note") else [])
        if moving:
            parts.append(
                "this deploy moves "
                + ", ".join(f"{host} (from {', '.join(_digest(ref) for ref in now[host])})" for host in moving)
            )
        if runs:
            parts.append(f"{', '.join(runs)} run{'s' if len(runs) == 1 else ''} it already")
        if first:
            parts.append(f"{', '.join(first)} get{'s' if len(first) == 1 else ''} it first")
        summary.append("; ".join(parts))
    return {"pinned": pinned, "digests": {image: pin["digest"] for image, pin in found.items()}, "summary": summary}


def _digest(ref: str) -> str:
    """A configured reference as a reader compares them: its digest, or the tag an older deploy ran."""
    return ref.rsplit("@", 1)[1][:19] if "@" in ref else ref
