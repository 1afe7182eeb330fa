"""docker run's arguments read by Docker's own rules (module_utils/hostlib/docker_cli.py): pflag's
flags and shorthand clusters, Go's ParseBool and encoding/csv, docker/cli's volume spec."""

import pytest
from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib import docker_cli


@pytest.mark.parametrize(
    "args, parsed",
    [
        # a cluster of short flags: the booleans, then one that takes the rest of the word or the next word
        (["-Pv", "/a:/b"], [("publish-all", "true"), ("volume", "/a:/b")]),
        (["-itv/a:/b"], [("interactive", "true"), ("tty", "true"), ("volume", "/a:/b")]),
        (["-v=/a:/b"], [("volume", "/a:/b")]),
        (["-P=false"], [("publish-all", "false")]),
        (["-uroot"], [("user", "root")]),
        (["--volume", "/a:/b", "--volume=/c:/d"], [("volume", "/a:/b"), ("volume", "/c:/d")]),
        (["--privileged", "--privileged=f"], [("privileged", "true"), ("privileged", "f")]),
        # hidden spellings of the same option
        (["--net=host", "--dns-opt=ndots:1"], [("network", "host"), ("dns-option", "ndots:1")]),
        # a value that looks like a flag is still the value
        (["--entrypoint", "--help"], [("entrypoint", "--help")]),
    ],
)
def test_flags_are_read_as_pflag_reads_them(args, parsed):
    assert docker_cli.parse(args) == parsed


@pytest.mark.parametrize(
    "args, needle",
    [
        (["--privileged", "false"], "'false' is not an option: Docker stops reading options there"),
        (["--", "-v", "/:/h"], "'--' is not an option"),
        (["-"], "'-' is not an option"),
        (["--no-such-flag"], "unknown flag: --no-such-flag"),
        (["-Z"], "unknown shorthand flag: 'Z' in -Z"),
        (["--volume"], "flag needs an argument: --volume"),
        (["-Pv"], "flag needs an argument: 'v' in -Pv"),
        (["--privileged=maybe"], 'invalid argument "maybe" for "--privileged" flag'),
        (["---x"], "bad flag syntax: ---x"),
    ],
)
def test_what_docker_refuses_or_reads_as_the_image_is_refused(args, needle):
    with pytest.raises(docker_cli.DockerArgError, match=None) as raised:
        docker_cli.parse(args)
    assert needle in str(raised.value)


@pytest.mark.parametrize("text", ["1", "t", "T", "TRUE", "true", "True"])
def test_go_true(text):
    assert docker_cli.parse_bool(text, "x") is True


@pytest.mark.parametrize("text", ["0", "f", "F", "FALSE", "false", "False"])
def test_go_false(text):
    assert docker_cli.parse_bool(text, "x") is False


@pytest.mark.parametrize("text", ["yes", "no", "tRue", "", "2"])
def test_go_refuses_other_words(text):
    with pytest.raises(docker_cli.DockerArgError):
        docker_cli.parse_bool(text, "x")


@pytest.mark.parametrize(
    "text, fields",
    [
        ("a,b,c", ["a", "b", "c"]),
        ('type=bind,"source=/run/x.sock",target=/y', ["type=bind", "source=/run/x.sock", "target=/y"]),
        ('"a,b",c', ["a,b", "c"]),
        ('"say ""hi""",x', ['say "hi"', "x"]),
        ("a,,b", ["a", "", "b"]),
        # Go's reader returns the first record: what follows a newline is not read
        ("a,b\nsource=/etc", ["a", "b"]),
    ],
)
def test_csv_as_go_reads_one_record(text, fields):
    assert docker_cli.csv_record(text) == fields


@pytest.mark.parametrize("text", ['source="/etc",x', '"open', '"a"b'])
def test_csv_quotes_go_refuses(text):
    with pytest.raises(docker_cli.DockerArgError):
        docker_cli.csv_record(text)


@pytest.mark.parametrize(
    "spec, kind, source, target",
    [
        ("/a:/b", "bind", "/a", "/b"),
        ("/a:/b:ro,z", "bind", "/a", "/b"),
        ("./etc:/x", "bind", "/etc", "/x"),  # made absolute against the unit's working directory
        ("name:/x", "volume", "name", "/x"),
        ("/anonymous", "volume", "", "/anonymous"),
    ],
)
def test_volume_specs(spec, kind, source, target):
    parsed = docker_cli.volume_spec(spec)
    assert (parsed["Type"], parsed["Source"], parsed["Target"]) == (kind, source, target)


@pytest.mark.parametrize("spec", ["/a::/b", "/a:/b:ro:x", "/a:"])
def test_volume_specs_docker_refuses(spec):
    with pytest.raises(docker_cli.DockerArgError):
        docker_cli.volume_spec(spec)


def test_mounts_read_as_docker_reads_them():
    mount = docker_cli.mount_spec('Type=bind,"source=/run/containerd/containerd.sock",dst=/c,ro')
    assert (mount["Type"], mount["Source"], mount["Target"], mount["ReadOnly"]) == (
        "bind",
        "/run/containerd/containerd.sock",
        "/c",
        True,
    )
    volume = docker_cli.mount_spec("source=v,target=/h,volume-opt=type=none,volume-opt=o=bind,volume-opt=device=/")
    assert volume["Type"] == "volume"  # Docker's default type
    assert volume["VolumeOptions"]["DriverConfig"]["Options"] == {"type": "none", "o": "bind", "device": "/"}
    for bad in ("type=bind, source=/x", "source=", "color=red", "readonly=maybe", "   "):
        with pytest.raises(docker_cli.DockerArgError):
            docker_cli.mount_spec(bad)


def test_gpu_requests():
    assert docker_cli.gpu_request("all") == {"Count": -1, "DeviceIDs": None}
    assert docker_cli.gpu_request("device=0") == {"Count": 0, "DeviceIDs": ["0"]}
    assert docker_cli.gpu_request('"device=0,1"') == {"Count": 0, "DeviceIDs": ["0", "1"]}
    # unquoted, the second id is a field of its own: a count, as Docker reads it
    assert docker_cli.gpu_request("device=0,1") == {"Count": 1, "DeviceIDs": ["0"]}
    assert docker_cli.gpu_request("capabilities=compute") == {"Count": 1, "DeviceIDs": None}
    with pytest.raises(docker_cli.DockerArgError):
        docker_cli.gpu_request("count=2,count=3")


def test_security_options_as_the_client_sends_them():
    assert docker_cli.security_opts(["no-new-privileges", "seccomp:unconfined"]) == (
        ["no-new-privileges", "seccomp:unconfined"],
        None,
    )
    # systempaths=unconfined is the client's own: it becomes empty masked paths, not an option
    assert docker_cli.security_opts(["systempaths=unconfined"]) == ([], [])
    for bad in (["apparmor"], ["label="], ["seccomp:"]):
        with pytest.raises(docker_cli.DockerArgError):
            docker_cli.security_opts(bad)


def test_the_config_keeps_the_last_of_a_single_valued_option_and_every_list_item():
    config = docker_cli.config(
        ["--user=1234", "-u", "0", "--privileged=true", "--privileged=0", "--cap-add=A", "--cap-add", "B"]
        + ["-v", "/a:/b", "-v", "/a:/b", "-v", "/anon", "--use-api-socket", "--pid", "host", "--pid=private"]
    )
    host = config["HostConfig"]
    assert config["Config"]["User"] == "0"
    assert host["Privileged"] is False and host["CapAdd"] == ["A", "B"] and host["PidMode"] == "private"
    # the same -v twice is one bind (a set in docker/cli); an anonymous volume is no bind
    assert host["Binds"] == ["/a:/b"]
    assert host["Mounts"] == [
        {"Type": "bind", "Source": "/var/run/docker.sock", "Target": "/var/run/docker.sock", "ReadOnly": False}
    ]


def test_a_gpu_count_is_read_as_go_s_atoi_reads_it():
    assert docker_cli.gpu_request("+1")["Count"] == 1 and docker_cli.gpu_request("count=-1")["Count"] == -1
    # a digit Python takes and Go does not: Docker's refusal, not a crash of the plan
    with pytest.raises(docker_cli.DockerArgError):
        docker_cli.gpu_request("²")
