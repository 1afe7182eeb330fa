# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""Where a person or a client points to reach an instance, per release."""

from __future__ import annotations


def endpoints(release: str, ports: dict, host: str, served=()) -> dict:
    """{name: address} for one instance's port block.

    served: the ports of the block a companion listens on; a port kept for a companion (the 6.x
    web viewer's) is reported only when one does, so no URL names a port nothing listens on.
    """
    out = {}
    if release == "2023.1":
        out["webrtc_client"] = f"http://{host}:{ports['http']}/streaming/webrtc-client?server={host}"
        out["native"] = f"{host}:{ports['native']}"
    else:
        # what the Isaac Sim WebRTC Streaming Client asks for
        out["signal"] = f"{host}:{ports['signal']}"
        out["stream"] = f"{host}:{ports['stream']}/udp"
        if "web_viewer" in ports and ports["web_viewer"] in set(served):
            out["web_viewer"] = f"http://{host}:{ports['web_viewer']}/"
        if "http" in ports:
            out["api"] = f"http://{host}:{ports['http']}/"
    return out


def summary_lines(plan: dict, host: str) -> list:
    lines = []
    for inst in plan["instances"]:
        served = [port for c in inst.get("companions", []) for port in c["ports"].values()]
        eps = endpoints(plan["release"], inst["ports"], host, served)
        gpu = "-" if inst.get("gpu") is None else inst["gpu"]
        lines.append(f"{inst['name']} gpu={gpu} " + " ".join(f"{k}={v}" for k, v in eps.items()))
    return lines
