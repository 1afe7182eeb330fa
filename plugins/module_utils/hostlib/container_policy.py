# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""The container policy: what an Isaac Sim container, a companion or a test run's service may be
given, judged on what Docker makes of its arguments (docker_cli.py) or on what Docker says a
created container has (`docker inspect`), never on the words as written.

Its shape is Kubernetes' Pod Security Standards, restricted profile, for one Docker container:
not privileged; none of the host's PID, IPC, UTS, user or cgroup namespaces (the host's network is
the collection's own choice, NVIDIA's WebRTC needs it); no added capability; no host device beyond
the GPU the plan gives; bind mounts only from the paths the site declares
(isaac_sim_allowed_bind_roots) and the collection's own data paths, a local volume whose options
bind a host path judged as that bind, no other container's volumes; not root where the release's
user is not; seccomp, AppArmor, SELinux labels, masked paths and no-new-privileges only added to,
never loosened. One exception is a named argument of isaac_sim_allowed_docker_args, matched on
what Docker makes of it, so `-Pv /var/run/docker.sock:/s` is allowed by
`--volume=/var/run/docker.sock:/x` and refused by nothing else.

The same code serves the plan (before any change: instances, companions, test runs), the unit's
check of the container Docker created, before it starts (isaac-sim-policy, which reads this file
copied beside it), and the audit (on `docker inspect`).
"""

from __future__ import annotations

import posixpath
import re

try:
    from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib import docker_cli
except ImportError:  # copied flat on a host
    import docker_cli

ALLOW_VAR = "isaac_sim_allowed_docker_args"
ROOTS_VAR = "isaac_sim_allowed_bind_roots"
DockerArgError = docker_cli.DockerArgError
# paths whose bind hands the container the host, and why; a bind of one of them, of a path under
# one, or of a directory above one (/, /var, /run) is that way out
HOST_PATHS = {
    "/run/docker.sock": "Docker's socket, which controls every container and the host",
    "/run/containerd": "containerd's socket, which controls every container and the host",
    "/var/lib/docker": "Docker's own state (every container's files and config)",
    "/var/lib/containerd": "containerd's own state",
    "/run/systemd": "systemd's private socket, which starts anything as root",
    "/etc": "the host's configuration (users, sudoers, units)",
    "/root": "root's home (its keys)",
    "/boot": "the host's kernel and boot loader",
    "/proc": "the host's processes",
    "/sys": "the host's kernel settings",
    "/dev": "the host's devices",
}
# the SELinux types the restricted Pod Security Standard allows
_CONTAINER_TYPES = ("container_t", "container_init_t", "container_kvm_t", "container_engine_t")
_NAMESPACES = (("PidMode", "pid", "PID"), ("IpcMode", "ipc", "IPC"), ("UTSMode", "uts", "UTS"),
               ("UsernsMode", "userns", "user"), ("CgroupnsMode", "cgroupns", "cgroup"))  # fmt: skip


def normal(path: str) -> str:
    """A host path as the policy compares it: normalised, /var/run read as /run (its symlink)."""
    path = posixpath.normpath(path or "/")
    path = "/" + path.lstrip("/")  # normpath keeps a leading "//"
    return "/run" + path[len("/var/run") :] if path == "/var/run" or path.startswith("/var/run/") else path


def under(path: str, root: str) -> bool:
    path, root = normal(path), normal(root)
    return root == "/" or path == root or path.startswith(root + "/")


def host_path_risk(path: str) -> str:
    """What of the host a bind of `path` hands the container; "" when nothing the policy knows of."""
    for host_path, what in HOST_PATHS.items():
        if under(host_path, path) or under(path, host_path):
            return what
    return ""


def mounts(host: dict) -> list:
    """Every mount of a HostConfig as {"Type", "Source", "Target", "Options"}: -v's Binds (read as
    docker/cli reads them) and --mount's Mounts; Options are a volume's local-driver options."""
    out = []
    for spec in host.get("Binds") or []:
        parsed = docker_cli.volume_spec(spec)
        out.append({"Type": parsed["Type"], "Source": parsed["Source"], "Target": parsed["Target"], "Options": {}})
    for mount in host.get("Mounts") or []:
        driver = (mount.get("VolumeOptions") or {}).get("DriverConfig") or {}
        options = driver.get("Options") or {} if driver.get("Name", "local") in ("", "local") else {}
        out.append({"Type": str(mount.get("Type") or "volume").lower(), "Source": mount.get("Source") or "",
                    "Target": mount.get("Target") or "", "Options": options})  # fmt: skip
    return out


# a local volume's file systems that reach no path of the host: a network share, memory
_NETWORK_FS = ("nfs", "nfs4", "cifs", "smb3", "tmpfs")
# mount options that name host directories (an overlay's layers)
_PATH_OPTIONS = ("lowerdir", "upperdir", "workdir")


def _local_volume_sources(options: dict) -> list:
    """[(kind, host path)] a local volume's driver options reach, as moby's local driver mounts them
    (mount(2) run by dockerd, whose working directory is /: a relative path is read from /):
    ("bind", PATH) with o=bind and for each directory an overlay's options name, ("device", PATH)
    for any other device; [] for none, a network file system or tmpfs."""
    device = str(options.get("device") or "")
    fs = str(options.get("type") or "")
    mount_options = [o for o in str(options.get("o") or "").split(",") if o]
    found = []
    for option in mount_options:
        key, eq, value = option.partition("=")
        if eq and key in _PATH_OPTIONS:
            found += [("bind", posixpath.join("/", p)) for p in value.split(":") if p]
    if not device or fs in _NETWORK_FS and not found:
        return found
    if "bind" in mount_options or "rbind" in mount_options:
        return found + [("bind", posixpath.join("/", device))]
    if fs == "overlay" and found:
        return found
    return found + [("device", posixpath.join("/", device))]


def _bind(source: str, text: str, roots, how: str = "binds host path", resolve=None) -> list:
    if not source.startswith("/"):
        return []
    if resolve:  # on the host: a symbolic link is judged by where it leads, the roots too
        source, roots = resolve(source), None if roots is None else [resolve(r) for r in roots]
    risk = host_path_risk(source)
    if roots is not None and any(under(source, root) for root in roots) and not risk:
        return []
    if roots is None and not risk:
        return []
    why = f"{how} {normal(source)} into it"
    if risk:
        why += f": {risk}"
    else:
        why += f", outside the paths this host allows bind mounts from ({', '.join(roots)}; more with {ROOTS_VAR})"
    return [(("bind", normal(source)), text, why)]


def _mount_findings(host: dict, roots, volumes: dict, resolve=None) -> list:
    out = []
    specs = list(host.get("Binds") or [])
    for index, mount in enumerate(mounts(host)):
        if index < len(specs):
            text = f"--volume={specs[index]}"
        else:
            text = f"--mount=type={mount['Type']},source={mount['Source']},target={mount['Target']}"
        if mount["Type"] == "bind":
            out += _bind(mount["Source"], text, roots, resolve=resolve)
            continue
        if mount["Type"] != "volume":
            continue
        # a named volume made before (docker volume create --opt): its options as Docker has them
        options = mount["Options"] or (volumes or {}).get(mount["Source"], {})
        for kind, path in _local_volume_sources(options):
            if kind == "bind":
                out += _bind(path, text, roots, "binds (a local volume's options) host path", resolve)
            else:
                out.append((("device", normal(path)), text, f"mounts the host's {path} into it (a local volume)"))
    return out


def _security(host: dict) -> list:
    out, nnp = [], None
    for opt in host.get("SecurityOpt") or []:
        if opt == "no-new-privileges":
            nnp = True
            continue
        if opt == "disable":  # the daemon's own spelling of label=disable
            key, value = "label", "disable"
        else:
            sep = "=" if "=" in opt else ":"
            key, _sep, value = opt.partition(sep)
        if key == "no-new-privileges":
            nnp = docker_cli.parse_bool(value, "security-opt no-new-privileges")
        elif key == "seccomp" and value == "unconfined":
            out.append((("seccomp", "unconfined"), "--security-opt=seccomp=unconfined", "turns off the seccomp filter"))
        elif key == "seccomp" and value not in ("builtin", ""):
            why = "replaces Docker's seccomp filter with a profile of its own, which may allow anything"
            out.append((("seccomp", "custom"), "--security-opt=seccomp=PROFILE", why))
        elif key == "apparmor" and value == "unconfined":
            out.append(
                (("apparmor", "unconfined"), "--security-opt=apparmor=unconfined", "turns off the AppArmor profile")
            )
        elif key == "label" and value == "disable":
            out.append((("label", "disable"), "--security-opt=label=disable", "turns off SELinux labels"))
        elif (
            key == "label"
            and value.split(":", 1)[0] in ("user", "role")
            or (key == "label" and value.startswith("type:") and value[5:] not in _CONTAINER_TYPES)
        ):
            # the restricted profile: a container type only, no SELinux user or role of its own
            why = "gives the container an SELinux label other than a container type"
            out.append((("label", value), f"--security-opt=label={value}", why))
    if nnp is False:
        out.append((("no-new-privileges", "false"), "--security-opt=no-new-privileges=false",
                    "lets the container's processes gain privileges (setuid binaries)"))  # fmt: skip
    if host.get("MaskedPaths") == [] or host.get("ReadonlyPaths") == []:
        out.append((("systempaths", "unconfined"), "--security-opt=systempaths=unconfined",
                    "unmasks /proc and /sys paths Docker hides"))  # fmt: skip
    return out


def _gpus(request: dict) -> str:
    if request.get("Count") == -1:
        return "--gpus=all"
    if request.get("DeviceIDs"):
        return "--gpus=device=" + ",".join(str(d) for d in request["DeviceIDs"])
    return f"--gpus={request.get('Count', 0)}"


def is_root(user: str) -> bool:
    """Whether a --user runs as uid 0, as moby reads it (Go's Atoi: 00, +0 and -0 are 0 too)."""
    name = str(user or "").split(":", 1)[0]
    return name == "root" or (re.fullmatch(r"[+-]?[0-9]+", name) is not None and int(name) == 0)


def judge(inspected: dict, rules: dict | None = None) -> list:
    """[(key, argument, why)] for what the container has that the policy refuses. inspected: the
    shape of `docker inspect` (docker_cli.config() gives it for arguments). rules:
      bind_roots: host paths binds may come from; None: any path but those that hand over the host
      gpus: the GPU ids the plan gives (--gpus=device=ID); None: GPU requests are not judged
      root_ok: the release itself runs as root (2023.1, 4.x), so a root user takes nothing away
      volumes: {name: local-driver options} of named volumes as Docker has them
      resolve: on the host, os.path.realpath: bind sources and roots judged where their links lead
      inspected: what Docker shows (docker inspect), not arguments: its daemon defaults are not judged
    The key names the effect, so an allowance matches however either was spelled."""
    rules = rules or {}
    host = inspected.get("HostConfig") or {}
    out = []
    if host.get("Privileged"):
        out.append((("privileged",), "--privileged", "gives the container every capability and device"))
    for cap in host.get("CapAdd") or []:
        name = str(cap).upper()
        name = name[4:] if name.startswith("CAP_") else name
        out.append((("cap-add", name), f"--cap-add={name}", f"adds the capability {name} to the container"))
    for key, flag, what in _NAMESPACES:
        # docker inspect shows the daemon's default cgroup namespace (host on cgroup v1): only the
        # arguments tell one asked for
        if key == "CgroupnsMode" and rules.get("inspected"):
            continue
        mode = str(host.get(key) or "")
        if mode == "host":
            out.append(((flag, "host"), f"--{flag}=host", f"shares the host's {what} namespace with the container"))
        elif flag in ("pid", "ipc") and mode.startswith("container:"):
            # another container's namespace is what that container has (the host's, where it was allowed)
            out.append(((flag, mode), f"--{flag}={mode}",
                        f"joins the {what} namespace of another container, which the policy cannot judge"))  # fmt: skip
    out += _security(host)
    for device in host.get("Devices") or []:
        path = device.get("PathOnHost", "")
        out.append((("device", normal(path)), f"--device={path}",
                    "gives the container a host device beyond the GPU the plan gives each instance"))  # fmt: skip
    for rule in host.get("DeviceCgroupRules") or []:
        out.append((("device-cgroup-rule", rule), f"--device-cgroup-rule={rule}",
                    "lets the container use host devices beyond the GPU the plan gives each instance"))  # fmt: skip
    gpus = rules.get("gpus")
    for request in host.get("DeviceRequests") or []:
        ids = [str(d) for d in request.get("DeviceIDs") or []]
        if gpus is not None and not (request.get("Count", 0) == 0 and ids and set(ids) <= {str(g) for g in gpus}):
            text = _gpus(request)
            out.append((("gpus", text), text, "gives the container GPUs beyond the one the plan gives it"))
    out += _mount_findings(host, rules.get("bind_roots"), rules.get("volumes"), rules.get("resolve"))
    for path in host.get("EnvFiles") or []:
        # the client reads it on the host, as the unit's root, into the container's environment
        why = "reads a file of the host into the container's environment (another instance's secrets)"
        out.append((("env-file", path), f"--env-file={path}", why))
    for source in host.get("VolumesFrom") or []:
        out.append((("volumes-from", source), f"--volumes-from={source}",
                    "mounts every volume of another container, which the policy cannot judge"))  # fmt: skip
    user = (inspected.get("Config") or {}).get("User", "")
    if is_root(user) and not rules.get("root_ok"):
        out.append((("user", "root"), f"--user={user}", "runs the container as root, where its release runs as a user"))
    return out


def beyond_plan(inspected: dict, planned_args, gpu="", volumes=None, resolve=None) -> list:
    """judge() of a container of ours against its own plan (the docker run arguments of its env file):
    its binds' sources are its only bind roots, its GPU its only GPU, its release's user its user, and
    what the plan itself gave it (allowed there by isaac_sim_allowed_docker_args) is not refused. What
    remains is what Docker made that the plan did not give: a reading of the arguments other than ours,
    a named volume that binds a host path, a container made by hand under the instance's name."""
    try:
        planned = docker_cli.config(planned_args)
    except DockerArgError:
        planned = {"HostConfig": {}, "Config": {}}
    roots = [m["Source"] for m in mounts(planned["HostConfig"]) if m["Type"] == "bind"]
    user = planned["Config"].get("User", "")
    rules = {"bind_roots": roots, "gpus": [str(gpu)] if str(gpu) else [], "root_ok": is_root(user)}
    # what the plan gave, as the plan saw it: not where a link leads, nor what a named volume's options bind
    given = {key for key, _text, _why in judge(planned, rules)}
    found = judge(inspected, dict(rules, volumes=volumes or {}, resolve=resolve, inspected=True))
    return [item for item in found if item[0] not in given]


def check_created(name: str, planned_args, gpu, docker_json, resolve=None) -> list:
    """beyond_plan() of the container `name` Docker created, read from Docker: docker_json(*args) runs
    `docker ARGS` and returns its JSON (raising when Docker does not answer). Its named volumes' options
    are asked too. isaac-sim-policy (every unit's start) and the warm-cache runs use it."""
    [inspected] = docker_json("container", "inspect", name)
    names = sorted({m["Name"] for m in inspected.get("Mounts") or [] if m.get("Type") == "volume" and m.get("Name")})
    volumes = {v["Name"]: v.get("Options") or {} for v in docker_json("volume", "inspect", *names)} if names else {}
    return beyond_plan(inspected, planned_args, "" if gpu is None else str(gpu), volumes, resolve)


def allowed_keys(allowed) -> set:
    """The effects isaac_sim_allowed_docker_args names, read as Docker reads them."""
    return {key for key, _text, _why in judge(docker_cli.config(allowed), {"bind_roots": [], "gpus": []})}


def refused(args, allowed=(), rules=None) -> list:
    """[(argument, why)] of docker run arguments the policy refuses and `allowed` does not name.
    Raises DockerArgError for an argument Docker's client would refuse or read as the image."""
    allow = allowed_keys(allowed)
    return [(text, why) for key, text, why in judge(docker_cli.config(args), rules) if key not in allow]


def errors(where: str, whose: str, args, allowed=(), rules=None, allow_var: str = ALLOW_VAR) -> list:
    """The plan's error for each refused argument: the variable, the argument, whose it is, the fix."""
    try:
        found = refused(args, allowed, rules)
    except (DockerArgError, ValueError) as exc:
        return [f"{where}: {exc} ({whose}). Fix: write the arguments as docker run takes them, one word per item."]
    return [
        f"{where}: {text} {why} ({whose}). Fix: remove it; where this host must allow it, add {text!r} to "
        f"{allow_var} (the security guide, docs/docsite/rst/security.rst, says what that gives away)."
        for text, why in found
    ]


def roots_errors(roots, var: str = ROOTS_VAR) -> list:
    """A declared bind root must be an absolute path that hands over nothing of the host."""
    out = []
    for root in roots or []:
        text = str(root)
        if not text.startswith("/"):
            out.append(f"{var}: {text!r} is not an absolute path. Fix: give the host directory from /.")
        elif host_path_risk(text):
            out.append(
                f"{var}: {text!r} holds or is {host_path_risk(text)}. Fix: name a directory of your data instead; "
                f"where a container must have such a path, name that one bind exactly in {ALLOW_VAR}."
            )
    return out
