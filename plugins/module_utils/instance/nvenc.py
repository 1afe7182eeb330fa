# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""Which GPUs have a video encoder, asked of the driver's own encode API (NVENC).

Isaac Sim streams through the GPU's video encoder, and data-centre GPUs such as the A100, H100
and H200 have none. Neither NVML nor nvidia-smi says so: on an H100 (driver 580.159.04) NVML's
encoder capacity answered 100 % for H.264 and HEVC, and nvidia-smi's encoder fields read 0 as
on any idle GPU (tests/unit/recorded/h100-nvml.json). The one answer the driver gives is the
encode API's: opening an encode session on a GPU without an encoder returns
NV_ENC_ERR_NO_ENCODE_DEVICE or NV_ENC_ERR_UNSUPPORTED_DEVICE (nvEncodeAPI.h, NVIDIA's Video
Codec SDK header). The probe opens one session per GPU and closes it at once, in a child
process (a driver that crashes the probe never takes the module with it), through ctypes and the
libraries the driver installs: libcuda.so.1 and libnvidia-encode.so.1.

Every answer is one of: True (a session opened), False (the API said there is no encode device),
None (it could not be asked: a library missing, a context that could not be made, any other
status); None never refuses an instance.
"""

from __future__ import annotations

import json

# NVENCSTATUS values (nvEncodeAPI.h): the two that mean "this GPU cannot encode"
NO_ENCODE_DEVICE = 1
UNSUPPORTED_DEVICE = 2

# the program run in the child; it prints one JSON object
PROGRAM = r"""
import ctypes, json, sys

def status_of(found):
    out = {"gpus": [], "error": None}
    try:
        cuda = ctypes.CDLL("libcuda.so.1")
    except OSError as exc:
        return dict(out, error="libcuda.so.1 could not be loaded: %s" % exc)
    try:
        enc = ctypes.CDLL("libnvidia-encode.so.1")
    except OSError as exc:
        return dict(out, error="libnvidia-encode.so.1 (the driver's encode library) could not be loaded: %s" % exc)
    byref, u32, ptr = ctypes.byref, ctypes.c_uint32, ctypes.c_void_p
    max_version = u32()
    rc = enc.NvEncodeAPIGetMaxSupportedVersion(byref(max_version))
    if rc:
        return dict(out, error="NvEncodeAPIGetMaxSupportedVersion returned %d" % rc)
    # the largest API the driver knows: major in the high bits, minor in the low 4
    api = (max_version.value >> 4) | ((max_version.value & 0xF) << 24)
    out["api"] = "%d.%d" % (max_version.value >> 4, max_version.value & 0xF)

    def struct_version(n):
        return api | (n << 16) | (0x7 << 28)

    # NV_ENCODE_API_FUNCTION_LIST: version, reserved, then the function pointers
    functions = (ctypes.c_uint8 * 4096)()
    u32.from_buffer(functions, 0).value = struct_version(2)
    rc = enc.NvEncodeAPICreateInstance(functions)
    if rc:
        return dict(out, error="NvEncodeAPICreateInstance returned %d" % rc)
    pointers = (ptr * 64).from_buffer(functions, 8)
    # positions in the list: nvEncDestroyEncoder 27, nvEncOpenEncodeSessionEx 29
    open_session = ctypes.CFUNCTYPE(ctypes.c_int, ptr, ctypes.POINTER(ptr))(pointers[29])
    destroy = ctypes.CFUNCTYPE(ctypes.c_int, ptr)(pointers[27])
    rc = cuda.cuInit(0)
    if rc:
        return dict(out, error="cuInit returned %d" % rc)
    count = ctypes.c_int()
    cuda.cuDeviceGetCount(byref(count))
    for ordinal in range(count.value):
        gpu = {"ordinal": ordinal}
        out["gpus"].append(gpu)
        device = ctypes.c_int()
        raw = (ctypes.c_ubyte * 16)()
        if cuda.cuDeviceGet(byref(device), ordinal) or cuda.cuDeviceGetUuid(raw, device):
            gpu["error"] = "the device could not be named"
            continue
        hexed = bytes(raw).hex()
        gpu["uuid"] = "GPU-%s-%s-%s-%s-%s" % (hexed[:8], hexed[8:12], hexed[12:16], hexed[16:20], hexed[20:])
        context = ptr()
        rc = cuda.cuDevicePrimaryCtxRetain(byref(context), device)
        if rc:
            gpu["error"] = "cuDevicePrimaryCtxRetain returned %d" % rc
            continue
        try:
            cuda.cuCtxPushCurrent_v2(context)
            # NV_ENC_OPEN_ENCODE_SESSION_EX_PARAMS: version, deviceType (1: CUDA), device, reserved, apiVersion
            params = (ctypes.c_uint8 * 4096)()
            u32.from_buffer(params, 0).value = struct_version(1)
            u32.from_buffer(params, 4).value = 1
            ptr.from_buffer(params, 8).value = context.value
            u32.from_buffer(params, 24).value = api
            encoder = ptr()
            gpu["status"] = open_session(params, byref(encoder))
            if gpu["status"] == 0 and encoder.value:
                destroy(encoder)
        finally:
            popped = ptr()
            cuda.cuCtxPopCurrent_v2(byref(popped))
            cuda.cuDevicePrimaryCtxRelease_v2(device)
    return out

print(json.dumps(status_of(None)))
"""


def read(text: str) -> tuple:
    """({GPU uuid: True | False | None}, why the probe could not ask, or None) from its output."""
    try:
        answer = json.loads(text.strip().splitlines()[-1]) if text.strip() else {}
    except ValueError:
        return {}, f"the encoder probe printed no answer: {text.strip()[-200:]!r}"
    if not isinstance(answer, dict) or (not answer.get("gpus") and not answer.get("error")):
        return {}, "the encoder probe printed no answer"
    found = {}
    for gpu in answer.get("gpus") or []:
        if not gpu.get("uuid"):
            continue
        status = gpu.get("status")
        if status == 0:
            found[gpu["uuid"]] = True
        elif status in (NO_ENCODE_DEVICE, UNSUPPORTED_DEVICE):
            found[gpu["uuid"]] = False
        else:
            found[gpu["uuid"]] = None
    return found, answer.get("error")


# a driver that hangs in cuInit stalls no plan: the probe is ended after this many seconds
TIMEOUT_S = 60


def probe(run, python: str, timeout=None) -> tuple:
    """Ask the driver (run(argv) -> (rc, out, err); python: the interpreter to run the child;
    timeout: the path of coreutils' timeout, which ends a probe that hangs)."""
    argv = [python, "-c", PROGRAM]
    rc, out, err = run([timeout, "-k", "5", str(TIMEOUT_S)] + argv if timeout else argv)
    if timeout and rc in (124, 137):
        return {}, f"the encoder probe did not answer within {TIMEOUT_S} s (the driver hangs)"
    if rc != 0:
        return {}, f"the encoder probe exited {rc}: {(err or out).strip()[-300:]}"
    return read(out)
