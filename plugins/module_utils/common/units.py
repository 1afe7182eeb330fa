# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""The one way the collection writes a systemd unit file.

Every unit (the instances' template, the companions', the target, the Hub cache, the status
endpoint, the metrics exporter, a test run's services) is a list of sections given to render();
layout.py and runs/testrun.py say what goes in them.
"""

from __future__ import annotations


def render(sections, header=()) -> str:
    """The unit's text.

    header: comment lines above the first section ("# " is added).
    sections: [(name, entries)]; an entry is a (key, value) pair, a comment line ("# ..."), or
    "" for a blank line; a pair whose value is None is left out. Sections are a blank line apart.
    """
    head = "".join(f"# {line}\n" for line in header)
    return head + "\n".join(_section(name, entries) for name, entries in sections)


def _section(name: str, entries) -> str:
    lines = [f"[{name}]"]
    for entry in entries:
        if isinstance(entry, str):
            lines.append(entry)
        elif entry[1] is not None:
            lines.append(f"{entry[0]}={entry[1]}")
    return "\n".join(lines) + "\n"
