# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""docker run arguments that take a container out of its confinement, and the one way to allow one.

The plan refuses them in isaac_sim_extra_docker_args and in each companion's docker_args, before
anything on the host changes, unless isaac_sim_allowed_docker_args names that exact argument:
a privileged container, an added capability, the host's PID, IPC, UTS, user or cgroup namespace,
a confinement turned off (seccomp, AppArmor, SELinux labels, no-new-privileges), a host device
(an instance has the GPU the plan gives it, nothing else) and Docker's or containerd's socket
(or a directory that holds it) mounted into the container: each is a way from the container to
root on the host.
"""

from __future__ import annotations

import posixpath

ALLOW_VAR = "isaac_sim_allowed_docker_args"

# options that take a value; given as "--opt value" the value is the next word
_VALUED = {
    "--cap-add", "--pid", "--ipc", "--uts", "--userns", "--cgroupns", "--security-opt", "--device",
    "--device-cgroup-rule", "--gpus", "--volume", "-v", "--mount",
}  # fmt: skip
_NAMESPACES = {"--pid": "PID", "--ipc": "IPC", "--uts": "UTS", "--userns": "user", "--cgroupns": "cgroup"}
# security options that turn a confinement off (Docker takes "=" or ":" between key and value)
_LOOSENING = {
    "seccomp=unconfined": "turns off the seccomp filter",
    "apparmor=unconfined": "turns off the AppArmor profile",
    "label=disable": "turns off SELinux labels",
    "label=type:spc_t": "runs the container as a super-privileged SELinux type",
    "systempaths=unconfined": "unmasks /proc and /sys paths Docker hides",
    "no-new-privileges=false": "lets the container's processes gain privileges (setuid binaries)",
}
# sockets that hand whoever reaches them the host; a directory that holds one hands it too
_SOCKETS = ("/var/run/docker.sock", "/run/docker.sock", "/run/containerd/containerd.sock")


def _words(args) -> list:
    """(canonical --opt=value, option, value) per argument; a value given as the next word joins it."""
    out, words, i = [], [str(a) for a in args or []], 0
    while i < len(words):
        word = words[i]
        if word.startswith("--") and "=" in word:
            opt, value = word.split("=", 1)
        elif word.startswith("-v") and len(word) > 2 and not word.startswith("--"):
            opt, value = "-v", word[2:]
        elif word in _VALUED and i + 1 < len(words):
            opt, value, i = word, words[i + 1], i + 1
        else:
            opt, value = word, None
        opt = "--volume" if opt == "-v" else opt
        out.append((opt if value is None else f"{opt}={value}", opt, value))
        i += 1
    return out


def _mount_source(opt: str, value: str) -> str:
    if opt == "--volume":
        return value.split(":", 1)[0]
    fields = dict(f.split("=", 1) if "=" in f else (f, "") for f in value.split(","))
    return fields.get("source") or fields.get("src") or ""


def _holds_socket(source: str) -> bool:
    if not source.startswith("/"):  # a named volume
        return False
    path = posixpath.normpath(source)
    return any(sock == path or sock.startswith(path.rstrip("/") + "/") for sock in _SOCKETS)


def _why(opt: str, value) -> str:
    """Why the argument loosens the container's confinement; "" when it does not."""
    if opt == "--privileged":
        return "" if str(value).lower() in ("false", "0") else "gives the container every capability and device"
    if opt == "--cap-add":
        return f"adds the capability {value} to the container"
    if opt in _NAMESPACES:
        return f"shares the host's {_NAMESPACES[opt]} namespace with the container" if value == "host" else ""
    if opt == "--security-opt":
        key = str(value) if "=" in str(value) else str(value).replace(":", "=", 1)
        return _LOOSENING.get(key, "")
    if opt in ("--device", "--device-cgroup-rule", "--gpus"):
        return "gives the container a host device beyond the GPU the plan gives each instance (isaac_sim_gpu_map)"
    if opt in ("--volume", "--mount") and _holds_socket(_mount_source(opt, str(value))):
        return "mounts Docker's or containerd's socket into it, and that socket controls every container and the host"
    return ""


def canonical(args) -> set:
    """The arguments as the plan compares them (--opt=value), whichever way each was written."""
    return {text for text, _opt, _value in _words(args)}


def refused(args, allowed=()) -> list:
    """[(argument as --opt=value, why)] for each argument that loosens the container's confinement
    and that `allowed` (isaac_sim_allowed_docker_args) does not name."""
    allow = canonical(allowed)
    return [(text, why) for text, opt, value in _words(args) if (why := _why(opt, value)) and text not in allow]


def errors(where: str, whose: str, args, allowed=(), allow_var: str = ALLOW_VAR) -> list:
    """The plan's error for each refused argument: the variable, the argument, whose it is, the fix."""
    return [
        f"{where}: {text} {why} ({whose}). Fix: remove it; where this host must allow it, add {text!r} to "
        f"{allow_var} (the README's Security section says what that gives away)."
        for text, why in refused(args, allowed)
    ]
