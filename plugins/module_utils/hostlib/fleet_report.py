# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""The fleet view of isaac_sim_info results: one report, a text table, Prometheus text.

Pure functions, used by the status playbook's filters (on the controller)
and by the metrics timer (on each host).
"""

from __future__ import annotations

import datetime
import re

TABLE_COLUMNS = ("HOST", "INSTANCE", "STATE", "READY", "UPTIME", "RESTARTS", "GPU", "URL")


def duration(seconds) -> str:
    """3d4h, 2h05m, 7m03s, 42s; "-" for none."""
    if seconds is None:
        return "-"
    s = max(0, int(seconds))
    days, rest = divmod(s, 86400)
    hours, rest = divmod(rest, 3600)
    minutes, secs = divmod(rest, 60)
    if days:
        return f"{days}d{hours}h"
    if hours:
        return f"{hours}h{minutes:02d}m"
    if minutes:
        return f"{minutes}m{secs:02d}s"
    return f"{secs}s"


def primary_url(inst: dict) -> str:
    """What a person points a client at: the browser client where the release serves one, else the signal address."""
    urls = inst.get("urls") or {}
    for key in ("webrtc_client", "signal", "native", "web_viewer"):
        if urls.get(key):
            return urls[key]
    return "-"


def gpu_text(inst: dict) -> str:
    if inst.get("gpu") is None:
        return "-"
    mem = inst.get("gpu_memory_used_mib")
    return f"{inst['gpu']}" if mem is None else f"{inst['gpu']} ({mem} MiB)"


def restarts_text(inst: dict) -> str:
    """systemd's count, and the last day's ends from the journal where there were any: NRestarts
    is reset by every session end and every deliberate start."""
    day = inst.get("last_day") or {}
    said = [
        f"{day[k]} {word}"
        for k, word in (("crashes", "crashed"), ("unhealthy_restarts", "unhealthy"), ("session_ends", "sessions ended"))
        if day.get(k)
    ]
    return str(inst.get("restarts") or 0) + (f" (24h: {', '.join(said)})" if said else "")


def build(
    results: dict, targets: list, generated_at: str = "", compare: bool = True, mirrors=None, front_doors=None
) -> dict:
    """One report over the hosts asked for; a host without a result is unreachable or failed.

    results: {host: isaac_sim_info result, or {"failed": True, "msg": ...}}
    compare: mark instances whose digest differs from the fleet's (fleet_drift); a host's status
    endpoint answers for itself alone and leaves that to the page, which compares its hosts.
    mirrors: {mirror host: isaac_sim_mirror_info result}, the fleet's registry mirrors.
    front_doors: {front door host: {door: its front-door.json, relay: its relay unit's state}}: each
    door gets a line, and each instance behind one its entrance.
    """
    hosts, totals = [], {"hosts": 0, "reachable": 0, "instances": 0, "running": 0, "ready": 0, "failed": 0, "stray": 0}
    for host in targets:
        res = results.get(host)
        totals["hosts"] += 1
        if not res or res.get("failed") or res.get("unreachable") or "instances" not in res:
            detail = (res or {}).get("msg") or "no answer (unreachable, or the status task failed)"
            short = detail.strip().splitlines()[0] if detail.strip() else detail
            short = short if len(short) <= 160 else short[:157] + "..."
            hosts.append(
                {
                    "host": host,
                    "reachable": False,
                    "error": short,
                    "error_detail": detail,
                    "instances": [],
                    "summary": {},
                }
            )
            continue
        totals["reachable"] += 1
        instances = []
        for inst in res["instances"]:
            view = dict(inst)
            view["uptime"] = duration(inst.get("uptime_s"))
            view["ready_in"] = ready_in(inst)
            view["gpu_text"] = gpu_text(inst)
            view["restarts_text"] = restarts_text(inst)
            view["primary_url"] = primary_url(inst)
            view["digest_short"] = (inst.get("digest") or inst.get("image_id") or "")[7:19] or "-"
            # what the dashboard can show inline: a page served by the instance itself
            view["embed_url"] = (inst.get("urls") or {}).get("webrtc_client") if inst.get("ready") else None
            instances.append(view)
        summary = res.get("summary", {})
        totals["instances"] += len(instances)
        for key in ("running", "ready", "failed", "stray"):
            totals[key] += summary.get(key, 0)
        hosts.append(
            {
                "host": host,
                "reachable": True,
                "deployed": res.get("deployed", False),
                "drained": res.get("drained"),
                "error": "; ".join(res.get("errors") or []) or None,
                "public_address": res.get("public_address"),
                "status_url": res.get("status_url"),
                "gpu": res.get("gpu", {}),
                "instances": instances,
                "summary": summary,
            }
        )
    totals["drift"] = (
        fleet_drift(hosts) if compare else sum(bool(i.get("drift")) for h in hosts for i in h["instances"])
    )
    report = {"generated_at": generated_at, "summary": totals, "hosts": hosts}
    if mirrors:
        report["mirrors"] = [mirror_view(host, mirrors[host]) for host in sorted(mirrors)]
    if front_doors:
        report["front_doors"] = [door_view(host, front_doors[host], generated_at) for host in sorted(front_doors)]
        for h in hosts:
            for inst in h["instances"]:
                found = [d["entrances"].get(h["host"], {}).get(str(inst["id"])) for d in report["front_doors"]]
                inst["entrance"] = next((url for url in found if url), None)
    return report


# a certificate this close to its end marks its front door's line
EXPIRES_SOON_DAYS = 14


def door_view(host: str, res: dict, generated_at: str = "") -> dict:
    """A front door's line of the report: its address, its certificate's expiry, its relay's state;
    healthy unless the certificate ends within EXPIRES_SOON_DAYS or a relay it has is down."""
    said = (res or {}).get("door")
    if not isinstance(said, dict):
        why = (res or {}).get("error") or "it says nothing of itself (no front-door.json)"
        text = (
            f"UNREADABLE: {why}. Fix: run playbooks/front_door.yml, or take the host out of group "
            "isaac_sim_front_door where it is no front door"
        )
        return {"host": host, "healthy": False, "text": text, "entrances": {}}
    ends = (said.get("certificate") or {}).get("not_after") or ""
    days = _days_between(generated_at, ends)
    relay = said.get("relay")
    state = str(res.get("relay") or "unknown") if relay else "off"
    text = f"{said.get('url')}, certificate until {ends or 'unknown'}" + (f" ({days} days)" if days is not None else "")
    text += f", relay {state}" + (f" ({relay.get('url')}, relay ports {relay.get('ports')})" if relay else "")
    soon = days is not None and days < EXPIRES_SOON_DAYS
    if soon:
        text += ": the certificate expires soon. Fix: your own (front_door_tls_cert), or remove the issued one"
        text += " (front_door_ca_dir/door-NAME.*) and run playbooks/front_door.yml again"
    view = {
        "host": host,
        "url": said.get("url"),
        "certificate_not_after": ends or None,
        "certificate_days_left": days,
        "relay": state,
        "relay_url": (relay or {}).get("url"),
        "entrances": said.get("entrances") or {},
        "healthy": not soon and state in ("active", "off"),
        "text": text,
    }
    return view


def _days_between(generated_at: str, iso_end: str):
    """Whole days from the report's time stamp to an ISO 8601 UTC end; None if either is unreadable."""
    try:
        start = datetime.datetime.strptime(generated_at, "%Y-%m-%d %H:%M:%S UTC")
        end = datetime.datetime.strptime(iso_end, "%Y-%m-%dT%H:%M:%SZ")
    except ValueError:
        return None
    return (end - start).days


def size_text(count) -> str:
    """1536 -> "1.5 KiB"."""
    if count is None:
        return "-"
    value = float(count)
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if value < 1024 or unit == "TiB":
            return f"{value:.0f} {unit}" if unit == "B" else f"{value:.1f} {unit}"
        value /= 1024
    return "-"


def mirror_view(host: str, res: dict) -> dict:
    """A registry mirror's line of the report: serving or not (and why), what its storage holds."""
    state = (res or {}).get("mirror")
    if not state:
        detail = (res or {}).get("msg") or "no answer (unreachable, or the status task failed)"
        return {"host": host, "reachable": False, "healthy": False, "text": f"UNREACHABLE: {detail.strip()[:160]}"}
    view = dict(state, host=host, reachable=True)
    repos = len(state.get("repositories") or {})
    holds = (
        f"{size_text(state.get('used_bytes'))} held ({state.get('images', 0)} images in {repos} repositories), "
        f"{size_text(state.get('free_bytes'))} free of {size_text(state.get('size_bytes'))}"
    )
    answered = f"HTTP {state['http_status']}" if state.get("http_status") else "no answer"
    view["text"] = ("serving" if state.get("healthy") else "DOWN") + f" ({answered}), {holds}"
    if state.get("errors"):
        view["text"] += ": " + "; ".join(state["errors"])
    if state.get("warnings"):
        view["text"] += "; " + "; ".join(state["warnings"])
    return view


def ready_in(inst: dict):
    """How long the running container took to its ready line, e.g. "12s (warm caches)"; None if not ready."""
    after = inst.get("ready_after_s")
    if after is None:
        return None
    cache = inst.get("cache_at_start")
    return f"{duration(after)}" + (f" ({cache} caches)" if cache else "")


def fleet_drift(hosts: list) -> int:
    """Mark (fleet_drift) every instance that runs another digest than most instances of the same
    image across the fleet (a host a deploy left out, an image changed by hand); an instance off its
    own deploy's digest says so in drift (fleet_status.drift). The dashboard's page compares its
    live answers the same way (status.html.j2, fleetDigests). Returns how many drift either way."""
    seen = {}
    for h in hosts:
        for inst in h["instances"]:
            if inst.get("configured") and inst.get("image") and inst.get("digest"):
                counts = seen.setdefault(inst["image"], {})
                counts[inst["digest"]] = counts.get(inst["digest"], 0) + 1
    # the digest most instances of the image run (on a tie, the first in name order: stable between reads)
    fleet = {image: max(sorted(counts), key=counts.get) for image, counts in seen.items()}
    drifting = 0
    for h in hosts:
        for inst in h["instances"]:
            theirs = fleet.get(inst.get("image"))
            if inst.get("configured") and theirs and inst.get("digest") not in (None, theirs):
                inst["fleet_drift"] = f"runs {inst['digest'][:19]} where the fleet runs {theirs[:19]}"
            drifting += bool(inst.get("drift") or inst.get("fleet_drift"))
    return drifting


def table(report: dict) -> list:
    """The compact table, as lines (aligned columns)."""
    rows = [TABLE_COLUMNS]
    for h in report["hosts"]:
        if not h["reachable"]:
            rows.append((h["host"], "-", "UNREACHABLE", "-", "-", "-", "-", h["error"]))
            continue
        if not h["instances"]:
            rows.append(
                (h["host"], "-", "no instances" if h.get("deployed") else "not deployed", "-", "-", "-", "-", "-")
            )
        for i in h["instances"]:
            rows.append(
                (
                    h["host"],
                    str(i["id"]) if i["id"] is not None else i["name"],
                    i["state"]
                    + (" (stray)" if i.get("stray") else "")
                    + (" (drift)" if i.get("drift") or i.get("fleet_drift") else ""),
                    "yes" if i["ready"] else "no",
                    i["uptime"],
                    i.get("restarts_text") or str(i["restarts"]),
                    i["gpu_text"],
                    f"{i['entrance']} (direct: {i['primary_url']})" if i.get("entrance") else i["primary_url"],
                )
            )
            # why a configured instance is down (a crash loop, a port held, the container policy, a stop),
            # in status.yml's table and status.txt as in status.json and the dashboard
            if i.get("down_reason"):
                rows.append((h["host"], str(i["id"]), "", "", "", "", "", f"why: {i['down_reason']}"))
            # its one claim: nothing but its borrower restarts it until the run gives it back
            if i.get("lent_to"):
                held = i["lent_to"]
                who = f"session {held[8:]}" if held.startswith("session-") else f"test run {held}"
                rows.append((h["host"], str(i["id"]), "", "", "", "", "", f"held by: {who}"))
            # each companion on a line of its own under its instance: 2/ros-bridge
            for c in i.get("companions") or []:
                rows.append(
                    (
                        h["host"],
                        f"{i['id']}/{c['name']}",
                        c["state"] + ("" if c.get("configured") else " (stray)"),
                        "yes" if c["ready"] else "no",
                        duration(c.get("uptime_s")),
                        str(c.get("restarts", 0)),
                        "-",
                        " ".join(f"{p['port']}/{p['proto']}" for p in c.get("ports") or []) or "-",
                    )
                )
    widths = [max(len(r[c]) for r in rows) for c in range(len(TABLE_COLUMNS) - 1)]
    lines = ["  ".join(cell.ljust(widths[c]) for c, cell in enumerate(r[:-1])) + "  " + r[-1] for r in rows]
    s = report["summary"]
    lines.append(
        f"{s['hosts']} hosts ({s['reachable']} answered), {s['instances']} instances: "
        f"{s['running']} running, {s['ready']} ready, {s['failed']} failed, {s['stray']} stray"
        + (f", {s['drift']} on another digest than the fleet's" if s.get("drift") else "")
    )
    lines += [f"mirror {m['host']}: {m['text']}" for m in report.get("mirrors") or []]
    lines += [f"front door {d['host']}: {d['text']}" for d in report.get("front_doors") or []]
    return lines


_METRICS = (
    ("isaac_sim_up", "Whether the instance's container is running (1) or not (0).", "gauge"),
    ("isaac_sim_ready", "Whether the instance printed its ready line since it started (1) or not (0).", "gauge"),
    (
        "isaac_sim_restarts",
        "Automatic restarts by systemd since the unit's counter was last reset (NRestarts).",
        "gauge",
    ),
    ("isaac_sim_uptime_seconds", "Seconds the instance's container has been running.", "gauge"),
    (
        "isaac_sim_ready_seconds",
        "Seconds the running container took from its start to its ready line; cache: warm or cold at the start.",
        "gauge",
    ),
    ("isaac_sim_crashes_last_day", "Crashes and failed starts in the last 24 h (the journal).", "gauge"),
    ("isaac_sim_session_ends_last_day", "Stream sessions that ended (clean exits) in the last 24 h.", "gauge"),
    ("isaac_sim_gpu_memory_used_bytes", "GPU memory held by the instance's processes.", "gauge"),
    ("isaac_sim_info", "Release, image and GPU of the instance (always 1).", "gauge"),
)


def _label(value) -> str:
    return re.sub(r'(["\\])', r"\\\1", str(value)).replace("\n", "\\n")


def prometheus(result: dict) -> str:
    """node_exporter textfile lines for one host's isaac_sim_info result.

    The instance label is isaac_sim_instance: Prometheus reserves `instance`
    for the scrape target.
    """
    samples = {metric[0]: [] for metric in _METRICS}
    for inst in result.get("instances", []):
        lab = f'isaac_sim_instance="{_label(inst["id"] if inst["id"] is not None else inst["name"])}"'
        if inst.get("stray"):
            lab += ',stray="true"'
        container = inst.get("container") or {}
        samples["isaac_sim_up"].append((lab, 1 if container.get("state") == "running" else 0))
        samples["isaac_sim_ready"].append((lab, 1 if inst.get("ready") else 0))
        samples["isaac_sim_restarts"].append((lab, inst.get("restarts") or 0))
        samples["isaac_sim_uptime_seconds"].append((lab, inst.get("uptime_s") or 0))
        if inst.get("ready_after_s") is not None:
            cache = f',cache="{_label(inst.get("cache_at_start") or "unknown")}"'
            samples["isaac_sim_ready_seconds"].append((lab + cache, inst["ready_after_s"]))
        if inst.get("last_day") is not None:
            samples["isaac_sim_crashes_last_day"].append((lab, inst["last_day"]["crashes"]))
            samples["isaac_sim_session_ends_last_day"].append((lab, inst["last_day"]["session_ends"]))
        if inst.get("gpu_memory_used_mib") is not None:
            samples["isaac_sim_gpu_memory_used_bytes"].append((lab, inst["gpu_memory_used_mib"] * 1024 * 1024))
        gpu = "" if inst.get("gpu") is None else inst["gpu"]
        info = (
            f'{lab},release="{_label(inst.get("release") or "")}",image="{_label(inst.get("image") or "")}",'
            f'digest="{_label(inst.get("digest") or "")}",gpu="{_label(gpu)}"'
        )
        samples["isaac_sim_info"].append((info, 1))
    out = []
    for name, help_text, kind in _METRICS:
        out.append(f"# HELP {name} {help_text}")
        out.append(f"# TYPE {name} {kind}")
        out += [f"{name}{{{lab}}} {value}" for lab, value in samples[name]]
    return "\n".join(out) + "\n"
