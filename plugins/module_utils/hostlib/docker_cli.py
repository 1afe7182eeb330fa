# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""docker run's arguments read the way Docker's own client reads them.

The container policy (container_policy.py) judges what Docker makes of the arguments, so this
reads them by Docker's rules, not by ours: the flags of `docker run`/`docker create` (docker/cli,
cli/command/container/opts.go, run.go) as spf13/pflag parses them (`--flag=v`, `--flag v`, short
flags run together as in `-Pv SRC:DST`, `-v=SRC:DST`, `-vSRC:DST`), booleans as Go's
strconv.ParseBool takes them (`0`, `f`, `False` ...), a single-valued flag given twice keeping the
last, `--mount` and `--gpus` as Go's encoding/csv reads one record (a quoted field, `""` for a
quote), `-v` as docker/cli's volumespec, and security options as the client and the daemon
(daemon/daemon_unix.go, parseSecurityOpt) resolve them. Its answer, config(), has the shape of
`docker inspect`'s HostConfig and Config, so the policy reads a planned container and a created
one alike. A word Docker would refuse is refused here too, with Docker's reason; a word that is no
flag would be taken by Docker as the image, and is refused.

It imports nothing but the standard library (the host library is copied flat to hosts).
"""

from __future__ import annotations

import posixpath
import re

# flags that take no value ("--flag", or "--flag=BOOL"); every other flag takes one
BOOLS = {
    "detach": "d", "disable-content-trust": "", "help": "", "init": "", "interactive": "i", "no-healthcheck": "",
    "oom-kill-disable": "", "privileged": "", "publish-all": "P", "quiet": "q", "read-only": "", "rm": "",
    "sig-proxy": "", "tty": "t", "use-api-socket": "",
}  # fmt: skip
VALUED = {
    "add-host": "", "annotation": "", "attach": "a", "blkio-weight": "", "blkio-weight-device": "", "cap-add": "",
    "cap-drop": "", "cgroup-parent": "", "cgroupns": "", "cidfile": "", "cpu-count": "", "cpu-percent": "",
    "cpu-period": "", "cpu-quota": "", "cpu-rt-period": "", "cpu-rt-runtime": "", "cpu-shares": "c", "cpus": "",
    "cpuset-cpus": "", "cpuset-mems": "", "detach-keys": "", "device": "", "device-cgroup-rule": "",
    "device-read-bps": "", "device-read-iops": "", "device-write-bps": "", "device-write-iops": "", "dns": "",
    "dns-opt": "", "dns-option": "", "dns-search": "", "domainname": "", "entrypoint": "", "env": "e",
    "env-file": "", "expose": "", "gpus": "", "group-add": "", "health-cmd": "", "health-interval": "",
    "health-retries": "", "health-start-interval": "", "health-start-period": "", "health-timeout": "",
    "hostname": "h", "io-maxbandwidth": "", "io-maxiops": "", "ip": "", "ip6": "", "ipc": "", "isolation": "",
    "kernel-memory": "", "label": "l", "label-file": "", "link": "", "link-local-ip": "", "log-driver": "",
    "log-opt": "", "mac-address": "", "memory": "m", "memory-reservation": "", "memory-swap": "",
    "memory-swappiness": "", "mount": "", "name": "", "net": "", "net-alias": "", "network": "",
    "network-alias": "", "oom-score-adj": "", "pid": "", "pids-limit": "", "platform": "", "publish": "p",
    "pull": "", "restart": "", "runtime": "", "security-opt": "", "shm-size": "", "stop-signal": "",
    "stop-timeout": "", "storage-opt": "", "sysctl": "", "tmpfs": "", "ulimit": "", "user": "u", "userns": "",
    "uts": "", "volume": "v", "volume-driver": "", "volumes-from": "", "workdir": "w",
}  # fmt: skip
# hidden spellings of the same option
ALIASES = {"net": "network", "net-alias": "network-alias", "dns-opt": "dns-option"}
SHORT = {short: name for table in (BOOLS, VALUED) for name, short in table.items() if short}
_TRUE = {"1", "t", "T", "TRUE", "true", "True"}
_FALSE = {"0", "f", "F", "FALSE", "false", "False"}
# docker/cli's Unix socket, which --use-api-socket binds into the container
API_SOCKET = "/var/run/docker.sock"
# where the unit runs docker (systemd's WorkingDirectory): a source "./x" is made absolute against it
WORKDIR = "/"


class DockerArgError(ValueError):
    """An argument Docker's client would refuse, or read other than as written."""


def parse_bool(text: str, flag: str) -> bool:
    """Go's strconv.ParseBool, as pflag applies it to a boolean flag."""
    if text in _TRUE:
        return True
    if text in _FALSE:
        return False
    raise DockerArgError(f'invalid argument "{text}" for "--{flag}" flag: Docker takes only 1, t, true, 0, f, false')


def parse(args) -> list:
    """[(flag's long name, value)] in order, as pflag reads them (a boolean's value is "true" or as
    given after "="). Refuses what Docker refuses, and any word Docker would take as the image."""
    words = [str(a) for a in args or []]
    out, i = [], 0
    while i < len(words):
        word = words[i]
        i += 1
        if word == "--" or len(word) < 2 or word[0] != "-":
            raise DockerArgError(
                f"{word!r} is not an option: Docker stops reading options there and takes it as the image "
                "(and the real image as its command)"
            )
        if word[1] == "-":
            name, eq, value = word[2:].partition("=")
            if not name or name[0] in "-=":
                raise DockerArgError(f"bad flag syntax: {word}")
            if name in BOOLS:
                out.append((name, value if eq else "true"))
            elif name in VALUED:
                if not eq:
                    if i >= len(words):
                        raise DockerArgError(f"flag needs an argument: {word}")
                    value, i = words[i], i + 1
                out.append((ALIASES.get(name, name), value))
            else:
                raise DockerArgError(f"unknown flag: --{name}")
            continue
        shorts = word[1:]
        while shorts:
            char, rest = shorts[0], shorts[1:]
            name = SHORT.get(char)
            if name is None:
                raise DockerArgError(f"unknown shorthand flag: {char!r} in {word}")
            if len(rest) > 1 and rest[0] == "=":  # -f=value
                value, shorts = rest[1:], ""
            elif name in BOOLS:
                value, shorts = "true", rest
            elif rest:  # -fvalue
                value, shorts = rest, ""
            elif i < len(words):  # -f value
                value, shorts, i = words[i], "", i + 1
            else:
                raise DockerArgError(f"flag needs an argument: {char!r} in {word}")
            out.append((name, value))
    for name, value in out:
        if name in BOOLS:
            parse_bool(value, name)
    return out


def csv_record(text: str) -> list:
    """The first record of Go's encoding/csv reader (comma-separated, "..." quoting, "" for a quote),
    which docker/cli reads --mount and --gpus with; a bare quote in an unquoted field is an error."""
    fields, field, i, n = [], [], 0, len(text)
    while True:
        if i < n and text[i] == '"':
            i += 1
            while True:
                if i >= n:
                    raise DockerArgError(f'extraneous or missing " in quoted-field: {text}')
                if text[i] == '"':
                    if i + 1 < n and text[i + 1] == '"':
                        field.append('"')
                        i += 2
                        continue
                    i += 1
                    break
                field.append(text[i])
                i += 1
            if i < n and text[i] not in ",\n" and text[i : i + 2] != "\r\n":
                raise DockerArgError(f'extraneous or missing " in quoted-field: {text}')
        else:
            # a record ends at a newline (\r\n or \n); a lone \r is data, as Go's reader keeps it
            while i < n and text[i] != "," and text[i] != "\n" and text[i : i + 2] != "\r\n":
                if text[i] == '"':
                    raise DockerArgError(f'bare " in non-quoted-field: {text}')
                field.append(text[i])
                i += 1
        fields.append("".join(field))
        field = []
        if i < n and text[i] == ",":
            i += 1
            continue
        return fields


def _absolute(source: str) -> str:
    """docker/cli makes a source starting with "." absolute against its working directory."""
    if source.startswith(".") and not source.startswith("/"):
        return posixpath.normpath(posixpath.join(WORKDIR, source))
    return source


def volume_spec(spec: str) -> dict:
    """-v as docker/cli's volumespec.Parse reads it on Linux: {"Type", "Source", "Target", "ReadOnly"}."""
    if not spec:
        raise DockerArgError("invalid empty volume spec")
    parts = spec.split(":")
    if any(p == "" for p in parts) and len(spec) > 2:
        raise DockerArgError(f"invalid spec: {spec}: empty section between colons")
    if len(parts) > 3:
        raise DockerArgError(f"invalid spec: {spec}: too many colons")
    if len(parts) == 1 or len(spec) <= 2:
        return {"Type": "volume", "Source": "", "Target": spec, "ReadOnly": False}
    source, target = parts[0], parts[1]
    read_only = False
    for option in (parts[2] if len(parts) == 3 else "").split(","):
        read_only = True if option == "ro" else False if option == "rw" else read_only
    bind = source[0] in "./~"
    return {"Type": "bind" if bind else "volume", "Source": _absolute(source) if bind else source,
            "Target": target, "ReadOnly": read_only}  # fmt: skip


def mount_spec(value: str) -> dict:
    """--mount as docker/cli's MountOpt.Set reads it: {"Type", "Source", "Target", "ReadOnly",
    "VolumeOptions": {"DriverConfig": {"Name", "Options"}}}; the type is "volume" unless given."""
    value = value.strip()
    if not value:
        raise DockerArgError("value is empty")
    mount = {"Type": "volume", "Source": "", "Target": "", "ReadOnly": False}
    for field in csv_record(value):
        key, has_value, val = field.partition("=")
        if key.strip() != key or (has_value and val.strip() != val):
            raise DockerArgError(f"invalid option in '{field}': it should not have whitespace")
        if has_value and not val:
            raise DockerArgError(f"invalid value for '{key}': value is empty")
        key = key.lower()
        if not has_value and key not in ("readonly", "ro", "volume-nocopy", "bind-nonrecursive", "bind-create-src"):
            raise DockerArgError(f"invalid field '{field}' must be a key=value pair")
        if key == "type":
            mount["Type"] = val.lower()
        elif key in ("source", "src"):
            mount["Source"] = _absolute(val)
        elif key in ("target", "dst", "destination"):
            mount["Target"] = val
        elif key in ("readonly", "ro"):
            mount["ReadOnly"] = parse_bool(val, f"mount {key}") if has_value else True
        elif key == "volume-driver":
            mount.setdefault("VolumeOptions", {}).setdefault("DriverConfig", {})["Name"] = val
        elif key == "volume-opt":
            opt_key, _eq, opt_value = val.partition("=")
            config = mount.setdefault("VolumeOptions", {}).setdefault("DriverConfig", {})
            config.setdefault("Options", {})[opt_key] = opt_value
        elif key not in (
            "consistency", "bind-propagation", "bind-recursive", "bind-create-src", "bind-nonrecursive",
            "volume-subpath", "volume-nocopy", "volume-label", "image-subpath", "tmpfs-size", "tmpfs-mode",
        ):  # fmt: skip
            raise DockerArgError(f"unknown option '{key}' in '{field}'")
    return mount


def gpu_request(value: str) -> dict:
    """--gpus as docker/cli's GpuOpts.Set reads it: {"Count", "DeviceIDs"} (Count -1: every GPU)."""
    request, seen = {"Count": 0, "DeviceIDs": None}, set()
    for field in csv_record(value):
        key, has_value, val = field.partition("=")
        if key in seen:
            raise DockerArgError(f"gpu request key '{key}' can be specified only once")
        seen.add(key)
        if not has_value or key == "count":
            seen.add("count")
            text = val if has_value else key
            if text == "all":
                request["Count"] = -1
            elif re.fullmatch(r"[+-]?[0-9]+", text):  # Go's Atoi
                request["Count"] = int(text)
            else:
                raise DockerArgError(f"invalid count ({text}): give a number or all")
        elif key == "device":
            request["DeviceIDs"] = val.split(",")
        elif key not in ("driver", "capabilities", "options"):
            raise DockerArgError(f"unexpected key '{key}' in '{field}'")
    if "count" not in seen and request["DeviceIDs"] is None:
        request["Count"] = 1
    return request


def security_opts(values) -> tuple:
    """(SecurityOpt as the client sends it, MaskedPaths): docker/cli's parseSecurityOpts and
    parseSystemPaths; MaskedPaths [] where systempaths=unconfined unmasks /proc and /sys, else None.
    A seccomp profile file is sent as its contents; here it stays "seccomp=PATH" (a custom profile)."""
    sent, masked = [], None
    for opt in values:
        key, eq, value = opt.partition("=")
        if not eq and key != "no-new-privileges":
            key, eq, value = opt.partition(":")
        if (not eq or not value) and key != "no-new-privileges":
            raise DockerArgError(f"invalid --security-opt: {opt!r}")
        if opt == "systempaths=unconfined":
            masked = []
            continue
        sent.append(opt)
    return sent, masked


def _device(value: str) -> dict:
    parts = value.split(":", 3)
    if len(parts) > 3:
        raise DockerArgError(f"invalid device specification: {value}")
    return {"PathOnHost": parts[0], "PathInContainer": parts[1] if len(parts) > 1 else parts[0]}


def config(args) -> dict:
    """What Docker makes of docker run arguments, shaped as `docker inspect` shows a container:
    {"HostConfig": {...}, "Config": {"User"}}. Only what the container policy reads."""
    last, many = {}, {}
    for name, value in parse(args):
        last[name] = value
        many.setdefault(name, []).append(value)
    # a set in docker/cli: the same -v twice is one; an anonymous volume is no bind
    binds = [spec for spec in dict.fromkeys(many.get("volume", [])) if volume_spec(spec)["Source"]]
    mounts = [mount_spec(m) for m in many.get("mount", [])]
    if parse_bool(last.get("use-api-socket", "false"), "use-api-socket"):
        mounts.append({"Type": "bind", "Source": API_SOCKET, "Target": API_SOCKET, "ReadOnly": False})
    security, masked = security_opts(many.get("security-opt", []))
    networks = many.get("network", [])
    host = {
        "Privileged": parse_bool(last.get("privileged", "false"), "privileged"),
        "CapAdd": many.get("cap-add", []),
        "CapDrop": many.get("cap-drop", []),
        "NetworkMode": networks[0] if networks else "",
        "PidMode": last.get("pid", ""),
        "IpcMode": last.get("ipc", ""),
        "UTSMode": last.get("uts", ""),
        "UsernsMode": last.get("userns", ""),
        "CgroupnsMode": last.get("cgroupns", ""),
        "SecurityOpt": security,
        "Devices": [_device(d) for d in many.get("device", [])],
        "DeviceCgroupRules": many.get("device-cgroup-rule", []),
        "DeviceRequests": [gpu_request(g) for g in many.get("gpus", [])],
        "Binds": binds,
        "Mounts": mounts,
        "VolumesFrom": many.get("volumes-from", []),
        # read by the client on the host: not in docker inspect, judged from the arguments only
        "EnvFiles": many.get("env-file", []) + many.get("label-file", []),
        "Runtime": last.get("runtime", ""),
    }
    if masked is not None:
        host["MaskedPaths"] = masked
    return {"HostConfig": host, "Config": {"User": last.get("user", "")}}
