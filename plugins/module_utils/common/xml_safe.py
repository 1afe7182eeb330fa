# Copyright: isaacsim.fleet contributors
# SPDX-License-Identifier: Apache-2.0 (the collection's license, see galaxy.yml)
"""Text and attribute values for the JUnit files: escaped, and without the control characters
XML 1.0 forbids (a log's colours, a suite entry's name or parameters), which would make the
whole file unreadable to a CI server."""

from __future__ import annotations

import re
from xml.sax.saxutils import escape, quoteattr

_NOT_XML = re.compile("[\x00-\x08\x0b\x0c\x0e-\x1f\ufffe\uffff]")


def text(value) -> str:
    return escape(_NOT_XML.sub("", str(value or "")))


def attr(value) -> str:
    """A quoted attribute value."""
    return quoteattr(_NOT_XML.sub("", str(value if value is not None else "")))
