# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""Where a person or a client points to reach an instance, per release."""

from __future__ import annotations


def endpoints(release: str, ports: dict, host: str, served=(), listens=None) -> dict:
    """{name: address} for one instance's port block: only what listens.

    listens: the kinds of the block the instance itself opens (its profile's; None: all of them).
    served: the ports of the block a companion listens on; a port kept for a companion (the 6.x
    web viewer's) is reported only when one does, so no URL names a port nothing listens on.
    """
    opened = set(ports) if listens is None else set(listens)
    out = {}
    if release == "2023.1":
        if "http" in opened:
            out["webrtc_client"] = f"http://{host}:{ports['http']}/streaming/webrtc-client?server={host}"
        if "native" in opened:
            out["native"] = f"{host}:{ports['native']}"
        return out
    # what the Isaac Sim WebRTC Streaming Client asks for
    if "signal" in opened:
        out["signal"] = f"{host}:{ports['signal']}"
    if "stream" in opened:
        out["stream"] = f"{host}:{ports['stream']}/udp"
    if "web_viewer" in ports and ports["web_viewer"] in set(served):
        out["web_viewer"] = f"http://{host}:{ports['web_viewer']}/"
    if "http" in opened and "http" in ports:
        out["api"] = f"http://{host}:{ports['http']}/"
    return out


def summary_lines(plan: dict, host: str) -> list:
    lines = []
    for inst in plan["instances"]:
        served = [port for c in inst.get("companions", []) for port in c["ports"].values()]
        eps = endpoints(plan["release"], inst["ports"], inst.get("address") or host, served, inst.get("listens"))
        gpu = "-" if inst.get("gpu") is None else inst["gpu"]
        mode = "" if inst.get("profile", "streaming") == "streaming" else f" profile={inst['profile']}"
        lines.append(f"{inst['name']} gpu={gpu}{mode} " + " ".join(f"{k}={v}" for k, v in eps.items()))
    return lines
