# Copyright: isaacsim.fleet contributors
# SPDX-License-Identifier: Apache-2.0 (the collection's license, see galaxy.yml)
"""What every domain parses the same way: image references, Docker sizes, whole numbers given as
text (values given with -e are strings)."""

from __future__ import annotations

import ipaddress
import re

# https://github.com/distribution/reference grammar, condensed
_COMPONENT = r"[a-z0-9]+(?:(?:[._]|__|-+)[a-z0-9]+)*"
_DOMAIN = r"(?:[a-zA-Z0-9](?:[a-zA-Z0-9-]*[a-zA-Z0-9])?(?:\.[a-zA-Z0-9](?:[a-zA-Z0-9-]*[a-zA-Z0-9])?)*(?::[0-9]+)?)"
_TAG = r"[\w][\w.-]{0,127}"
_DIGEST = r"[A-Za-z][A-Za-z0-9]*(?:[-_+.][A-Za-z][A-Za-z0-9]*)*:[0-9a-fA-F]{32,}"
IMAGE_RE = re.compile(
    rf"^(?:(?P<domain>{_DOMAIN})/)?(?P<path>{_COMPONENT}(?:/{_COMPONENT})*)"
    rf"(?::(?P<tag>{_TAG}))?(?:@(?P<digest>{_DIGEST}))?$"
)
SIZE_RE = re.compile(r"^(\d+(?:\.\d+)?) ?([kmgtp])?(i?b)?\Z", re.IGNORECASE)
_UNITS = {None: 1, "k": 1024, "m": 1024**2, "g": 1024**3, "t": 1024**4, "p": 1024**5}


def is_ip(text: str) -> bool:
    """An IPv4 or IPv6 address written plainly: not a network, not a name, no IPv6 zone (%eth0),
    nothing around it (the callers write it into configuration files)."""
    if not isinstance(text, str) or re.fullmatch(r"[0-9A-Fa-f:.]+", text) is None:
        return False
    try:
        ipaddress.ip_address(text)
    except ValueError:
        return False
    return True


def parse_size(text) -> int | None:
    """Bytes in a Docker size ("8g", "512m", "2GiB"), or None if it does not parse."""
    match = SIZE_RE.match(str(text).strip())
    if not match:
        return None
    number, unit, _suffix = match.groups()
    return int(float(number) * _UNITS[unit.lower() if unit else None])


def mib_of(text) -> int | None:
    """MiB in a size that names its unit ("16g", "24576m", "80GiB"); None for a bare number, whose
    unit a reader could take for bytes or for MiB."""
    match = SIZE_RE.match(str(text).strip())
    if not match or not match.group(2):
        return None
    return parse_size(text) // 1024**2


def docker_size(text) -> str:
    """The size as Docker's flags want it, one word: "1 GB" -> "1g", "2GiB" -> "2g"."""
    number, unit, _suffix = SIZE_RE.match(str(text).strip()).groups()
    return f"{number}{unit.lower() if unit else ''}"


def as_int(value):
    """An int from an int or a string of digits (values given with -e are strings), else None."""
    if isinstance(value, bool):
        return None
    if isinstance(value, int):
        return value
    text = str(value).strip()
    return int(text) if re.fullmatch(r"-?\d+", text) else None


def parse_image(ref: str):
    """(repository, tag, digest) of an image reference, or None if malformed."""
    match = IMAGE_RE.match(ref or "")
    if not match or len(ref) > 255:
        return None
    repo = match.group("path")
    if match.group("domain"):
        repo = f"{match.group('domain')}/{repo}"
    return repo, match.group("tag"), match.group("digest")
