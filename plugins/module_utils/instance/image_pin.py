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
import re

from ansible_collections.isaacsim.fleet.plugins.module_utils.common.parse import parse_image
from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib.docker_socket import DockerError

DOCKER_HUB = "docker.io"
REFUSED = re.compile(r"unauthorized|authentication required|denied", re.IGNORECASE)


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
    parsed = parse_image(image)
    if parsed is None:
        raise PinError(f"isaac_sim_image: {image!r} is not a valid image reference.")
    repository, _tag, digest = parsed
    if digest:
        return {"image": image, "pinned": f"{repository}@{digest}", "digest": digest}
    server = registry_of(repository)
    auth = auth_header(username, password, server) if password else ""
    try:
        answer = docker.distribution(image, auth)
    except DockerError as exc:
        why = str(exc).replace(password, "********") if password else str(exc)
        # Docker 20.10 passes the registry's 401 on as its own 500, with the registry's word in it
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
    return {"image": image, "pinned": f"{repository}@{found}", "digest": found}


def pin_fleet(
    docker,
    images: dict,
    configured: dict,
    username: str = "",
    password: str = "",
    asked_from: str = "",
    mirror: str = "",
    upstream: str = "",
) -> dict:
    """Each distinct image of the play resolved once; what every host will run and which it moves.

    images: {host: the plan's image}; configured: {host: [what its instances run now]}; mirror:
    HOST:PORT of a pull-through mirror of `upstream` (host/registry_mirror.py): an image of that
    registry is asked of the mirror (which holds the credentials) and pinned to the mirror's
    reference, so the hosts pull it from there.
    Returns {"pinned": {host: REPOSITORY@DIGEST}, "digests": {image: DIGEST}, "summary": [lines]}.
    """
    from ansible_collections.isaacsim.fleet.plugins.module_utils.host import registry_mirror

    wanted = sorted(set(images.values()) - {"", None})
    found = {}
    for image in wanted:
        through = registry_mirror.mirror_reference(image, mirror, upstream) if mirror else None
        if through:
            # the mirror serves anonymously to the fleet: no credentials leave the controller for it
            pin = resolve(docker, through, "", "", asked_from)
            found[image] = dict(pin, image=image)
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
        parts = [f"{image} is {pin['digest']} now"]
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
