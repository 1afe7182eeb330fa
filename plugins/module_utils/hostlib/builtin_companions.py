# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""The built-in companions: containers the collection itself runs beside an instance, each turned on by one
variable that gives its image. One entry per companion, and everything that differs between them; the plan
reads it (which instances get one, its container, the errors naming its variable), the plan's host facts (its
image is pulled with the instance's, and a missing one is named by its variable), and the endpoints (where a
person reaches it). Here, in the host library, because each host's status endpoint reports those too.

Each entry:

- variable: the isaac_sim role's variable giving its image (empty: not run); the plan module's option is the
  same name without its isaac_sim_ prefix.
- port: the kind of port of the instance's block it serves; a release whose block has no such kind has no such
  companion (the release table keeps the port for it: releases.py, a kind the instance does not tell itself).
- profiles: the instance profiles it goes with (an instance that streams nothing gets no viewer).
- url: (the name it is reported by, its address with {host} and {port}).
- title, made_by, example: what the errors call it, and where its image comes from.
- container: as an entry of isaac_sim_companions gives one (instance/companions.py): user, env, ports,
  healthcheck; a healthcheck's interval is the instances' (isaac_sim_health_interval), at most 5 s.
"""

from __future__ import annotations

BUILT_IN = {
    # NVIDIA's web viewer (roles/web_viewer_image), told its instance's address and ports when it starts,
    # bound to that address on the block's web-viewer port, healthchecked as NVIDIA's recipe does (curl -f
    # on its page; NVIDIA checks every 30 s, the readiness gate waits for the first healthy check, which
    # Docker runs one interval after the start)
    "viewer": {
        "variable": "isaac_sim_web_viewer_image",
        "port": "web_viewer",
        "profiles": ("streaming",),
        "url": ("web_viewer", "http://{host}:{port}/"),
        "title": "web viewer",
        "made_by": "playbooks/web_viewer_image.yml",
        "example": "registry.lab:5000/isaac-sim/web-viewer:2.1.5",
        "container": {
            "user": "1234:1234",
            "env": {
                "ISAACSIM_HOST": "{host}",
                "ISAACSIM_SIGNAL_PORT": "{port.signal}",
                "ISAACSIM_STREAM_PORT": "{port.stream}",
                "WEB_VIEWER_PORT": "{port.web_viewer}",
            },
            "ports": {"http": "web_viewer"},
            "healthcheck": {
                "test": ["CMD", "curl", "-f", "http://{host}:{port.http}/"],
                "timeout": 5,
                "start_period": 10,
                "retries": 3,
            },
        },
    },
}


def option(name: str) -> str:
    """The plan module's option that gives the companion's image."""
    return BUILT_IN[name]["variable"][len("isaac_sim_") :]


def given(params: dict) -> dict:
    """{variable: image} of every built-in companion, from the plan module's options (empty: not run)."""
    return {entry["variable"]: params.get(option(name)) or "" for name, entry in BUILT_IN.items()}


def shapes() -> list:
    """The built-in companions' URL shapes, as endpoints.URLS gives a release's: (kind of port, name reported,
    address, who opens it), reported where a companion serves the port."""
    return [(entry["port"], entry["url"][0], entry["url"][1], "companion") for entry in BUILT_IN.values()]


def serving(release_ports, profiles: dict, given: dict):
    """(name, entry, instances) of each built-in companion the plan gives this host's instances: instances is
    None when every instance gets it, else the list of those that do. release_ports: the kinds of the
    release's block; profiles: {instance: its profile}; given: {variable: image}. A host without instances
    keeps its unit template."""
    out = []
    for name, entry in BUILT_IN.items():
        mine = [i for i, profile in profiles.items() if profile in entry["profiles"]]
        if given.get(entry["variable"]) and entry["port"] in release_ports and (mine or not profiles):
            out.append((name, entry, None if len(mine) == len(profiles) else mine))
    return out


def images(release_ports, profile_names, given: dict) -> list:
    """(image, variable) of the built-in companions some instance of these profiles runs (the plan's host facts
    pull them with the instance's); given: {variable: image}."""
    return [
        (given[entry["variable"]], entry["variable"])
        for entry in BUILT_IN.values()
        if given.get(entry["variable"])
        and entry["port"] in release_ports
        and any(profile in entry["profiles"] for profile in profile_names)
    ]
