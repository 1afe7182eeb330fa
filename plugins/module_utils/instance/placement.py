# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""Which GPU each instance runs on: by the GPU memory each needs, streaming ones only where a video
encoder is.

An instance needs its GPU memory (isaac_sim_gpu_memory, per release NVIDIA's minimum, more with
isaac_sim_instance_gpu_memory, plus what its GPU companions name); a GPU offers its memory less
what the driver reserves and what processes that are not the collection's hold. Instances keep the
GPU they run on while it still serves them (a re-plan moves nothing for nothing); the others go,
in instance order, to the GPU with the most memory left (on equal GPUs: round-robin, as before).
A plan that does not fit is refused with the numbers. A streaming instance never goes to a GPU
whose driver says it has no encoder (nvenc.py); where the driver could not be asked, it may, with a
warning.
"""

from __future__ import annotations

# NVIDIA's driver limits concurrent encode sessions on its consumer GPUs, per system and summed
# over all of them (NVENC licensing policy); the count has changed with drivers (2, 3, 5, then 8
# since early 2024): isaac_sim_gpu_consumer_encode_sessions follows the hosts' drivers
CONSUMER_BRANDS = ("geforce", "titan")  # nvidia-smi's product_brand, as a prefix ("GeForce RTX", "Titan")


def capacity(gpu: dict):
    """MiB this GPU offers the collection's instances, None where its memory is not known."""
    total = gpu.get("memory_total_mib")
    if total is None:
        return None
    return max(total - (gpu.get("memory_reserved_mib") or 0) - (gpu.get("others_mib") or 0), 0)


def _describe(gpu: dict) -> str:
    return f"GPU {gpu['index']} ({gpu.get('name') or 'unknown model'})"


def _memory_line(gpu: dict, used: int, on: list) -> str:
    total = gpu.get("memory_total_mib")
    parts = [f"{total} MiB" if total is not None else "memory not known"]
    if gpu.get("memory_reserved_mib"):
        parts.append(f"{gpu['memory_reserved_mib']} reserved by the driver")
    if gpu.get("others_mib"):
        parts.append(f"{gpu['others_mib']} held by other processes")
    if on:
        parts.append(f"{used} taken by instance{'s' if len(on) > 1 else ''} {', '.join(map(str, on))}")
    free = capacity(gpu)
    mute = " without a video encoder" if gpu.get("encoder") is False else ""
    return f"{_describe(gpu)}{mute}: {', '.join(parts)}, {free - used if free is not None else '?'} MiB left"


def place(
    gpus: list, needs: dict, gpu_map: dict, current: dict, exclusive: bool, consumer_limit=8, why_none=""
) -> tuple:
    """({instance: GPU index}, errors, warnings).

    gpus: [{index, name, brand, memory_total_mib, memory_reserved_mib, others_mib, encoder}]
    (encoder True, False or None: not known); needs: {instance: {"mib": int, "streams": bool}};
    gpu_map: {instance: GPU index} the user fixed; current: {instance: GPU index} where each runs now;
    consumer_limit: the encode sessions NVIDIA's driver allows on a system's consumer GPUs;
    why_none: what nvidia-smi said when it listed no GPU.
    """
    errors, warnings = [], []
    by_index = {g["index"]: g for g in gpus}
    placed, used, on = {}, {g["index"]: 0 for g in gpus}, {g["index"]: [] for g in gpus}

    def fits(inst, gpu):
        room = capacity(gpu)
        if exclusive and on[gpu["index"]]:
            return False
        return room is None or used[gpu["index"]] + needs[inst]["mib"] <= room

    def allowed(inst, gpu):
        return not (needs[inst]["streams"] and gpu.get("encoder") is False)

    def put(inst, index):
        placed[inst] = index
        used[index] += needs[inst]["mib"]
        on[index].append(inst)

    if not gpus:
        said = f"nvidia-smi answered: {why_none}" if why_none else "nvidia-smi lists none"
        return (
            {},
            [
                f"isaac_sim_gpu_enabled: true, but this host shows no NVIDIA GPU ({said}). "
                "Fix: install the driver, or set isaac_sim_gpu_enabled: false to run without GPUs."
            ],
            [],
        )
    if exclusive and len(needs) > len(gpus):
        return (
            {},
            [
                f"isaac_sim_instance_count: {len(needs)} instances with isaac_sim_gpu_exclusive: true need "
                f"{len(needs)} GPUs, this host has {len(gpus)}. Fix: lower isaac_sim_instance_count to "
                f"{len(gpus)} or set isaac_sim_gpu_exclusive: false to share GPUs."
            ],
            [],
        )
    last = max(by_index)
    for inst, index in sorted(gpu_map.items()):
        if inst not in needs:
            errors.append(
                f"isaac_sim_gpu_map: instance {inst} does not exist (instances are 0..{len(needs) - 1}). "
                "Fix: remove it from isaac_sim_gpu_map."
            )
        elif index not in by_index:
            errors.append(
                f"isaac_sim_gpu_map: instance {inst} is mapped to GPU {index}, this host has GPUs 0..{last}. "
                "Fix: map it to one of those."
            )
        elif not allowed(inst, by_index[index]):
            encoders = [str(g["index"]) for g in gpus if g.get("encoder") is not False]
            errors.append(
                f"isaac_sim_gpu_map: instance {inst} streams, and {_describe(by_index[index])} has no video encoder "
                f"(the driver's encode API says so). Fix: map it to a GPU with one"
                f"{' (' + ', '.join(encoders) + ')' if encoders else ''}, or run it without a stream "
                f"(isaac_sim_instance_profiles: {{{inst}: headless}})."
            )
        elif exclusive and on[index]:
            errors.append(
                f"isaac_sim_gpu_map: instances {on[index][0]} and {inst} share GPU {index} but "
                "isaac_sim_gpu_exclusive is true. Fix: give each instance its own GPU."
            )
        else:
            put(inst, index)
    # a wrong map entry is said; the others are still placed, so every problem is said at once
    wrong = {inst for inst in gpu_map if inst in needs and inst not in placed}
    # where each runs now, while that GPU still serves it: a re-plan moves nothing for nothing
    for inst in sorted(needs):
        gpu = by_index.get(current.get(inst))
        if inst not in placed and inst not in wrong and gpu is not None and allowed(inst, gpu) and fits(inst, gpu):
            put(inst, gpu["index"])
    unplaced = []
    for inst in sorted(needs):
        if inst in placed or inst in wrong:
            continue
        candidates = [g for g in gpus if allowed(inst, g) and fits(inst, g)]
        if candidates:
            # the most memory left first; GPUs of unknown memory by how many they carry
            best = min(
                candidates,
                key=lambda g: (
                    -(capacity(g) - used[g["index"]]) if capacity(g) is not None else 0,
                    len(on[g["index"]]),
                    g["index"],
                ),
            )
            put(inst, best["index"])
        else:
            unplaced.append(inst)
    if unplaced:
        errors += _refusals(unplaced, needs, gpus, used, on, exclusive)
    if errors:
        return {}, errors, warnings
    warnings += _encoder_warnings(gpus, needs, on) + consumer_sessions(gpus, placed, needs, consumer_limit)
    unknown = [g for g in gpus if capacity(g) is None and on[g["index"]]]
    if unknown and any(needs[i]["mib"] for i in needs):
        warnings.append(
            f"{', '.join(_describe(g) for g in unknown)}: memory not known (nvidia-smi gave none), so instances "
            "were placed there by count, not by the GPU memory they need."
        )
    return placed, errors, warnings


def _refusals(unplaced, needs, gpus, used, on, exclusive) -> list:
    """One error per reason, naming every instance it leaves without a GPU and the GPUs' memory."""
    lines = "; ".join(_memory_line(g, used[g["index"]], on[g["index"]]) for g in gpus)
    encoders = [g for g in gpus if g.get("encoder") is not False]
    mute = [i for i in unplaced if needs[i]["streams"] and not encoders]
    rest = [i for i in unplaced if i not in mute]
    errors = []
    if mute:
        models = ", ".join(sorted({g.get("name") or "unknown model" for g in gpus}))
        errors.append(
            f"isaac_sim_profile: {_instances(mute)} stream{'s' if len(mute) == 1 else ''}, and no GPU of this host "
            f"has a video encoder ({models}: the driver's encode API says so; NVIDIA's data-centre GPUs such as the "
            "A100, H100 and H200 have none). Fix: run them without a stream (isaac_sim_profile: headless, or "
            f"isaac_sim_instance_profiles: {{{mute[0]}: headless}}), or put streaming instances on hosts whose "
            "GPUs encode."
        )
    if not rest:
        return errors
    asked = sorted({needs[i]["mib"] for i in rest})
    each = f"{asked[0]} MiB" if len(asked) == 1 else " to ".join(f"{m} MiB" for m in (asked[0], asked[-1]))
    streams = any(needs[i]["streams"] for i in rest) and len(encoders) < len(gpus)
    where = "GPUs with a video encoder" if streams else "GPUs"
    if exclusive:
        errors.append(
            f"isaac_sim_gpu_exclusive: {_instances(rest)} need{'s' if len(rest) == 1 else ''} a GPU of its own "
            f"with {each} of GPU memory, and none of this host's {where} is free and large enough ({lines}). "
            "Fix: fewer instances (isaac_sim_instance_count), or share GPUs (isaac_sim_gpu_exclusive: false)."
        )
    else:
        errors.append(
            f"isaac_sim_gpu_memory: {_instances(rest)} need{'s' if len(rest) == 1 else ''} {each} of GPU memory"
            f"{' each' if len(rest) > 1 else ''}, and none of this host's {where} has that much left ({lines}). "
            "Fix: fewer instances (isaac_sim_instance_count), less GPU memory each (isaac_sim_gpu_memory, "
            "isaac_sim_instance_gpu_memory) if your scenes allow it, or stop what else holds GPU memory."
        )
    return errors


def _instances(ids) -> str:
    return f"instance{'s' if len(ids) > 1 else ''} {', '.join(map(str, ids))}"


def _encoder_warnings(gpus, needs, on) -> list:
    warnings = []
    for gpu in gpus:
        streams = [i for i in on[gpu["index"]] if needs[i]["streams"]]
        if streams and gpu.get("encoder") is None:
            why = gpu.get("encoder_why") or "the driver could not be asked"
            warnings.append(
                f"{_describe(gpu)} carries streaming instance{'s' if len(streams) > 1 else ''} "
                f"{', '.join(map(str, streams))}, and whether it has a video encoder is not known ({why}). "
                "Without one they start but never stream."
            )
    return warnings


def consumer_sessions(gpus, placed, needs, limit) -> list:
    """A warning when more streams than NVIDIA's driver allows are placed on this host's consumer GPUs."""
    consumer = {g["index"] for g in gpus if (g.get("brand") or "").lower().startswith(CONSUMER_BRANDS)}
    streams = sorted(i for i, index in placed.items() if index in consumer and needs[i]["streams"])
    if not limit or len(streams) <= limit:
        return []
    return [
        f"isaac_sim_gpu_consumer_encode_sessions: {len(streams)} streaming instances ({', '.join(map(str, streams))}) "
        f"run on this host's GeForce GPUs, and NVIDIA's driver allows {limit} encode sessions at once on all of a "
        f"system's consumer GPUs together: the streams beyond {limit} fail to open. Fix: at most {limit} streaming "
        "instances on them (the others headless), or GPUs of NVIDIA's professional lines."
    ]
