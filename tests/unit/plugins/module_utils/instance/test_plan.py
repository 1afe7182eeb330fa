import pytest
from ansible_collections.isaacsim.fleet.plugins.module_utils.instance import plan, unit_files
from ansible_collections.isaacsim.fleet.plugins.module_utils.instance.releases import RELEASES, release_of_tag
from ansible_collections.isaacsim.fleet.tests.unit.helpers import plan_config

GIB = 1024**3


def cfg(**over):
    return plan_config(**over)


HOST = {"memory_bytes": 64 * GIB, "gpu_count": 0, "ports_held": [], "image_present": True}


def errors_of(c, host=None):
    host = HOST if host is None else host
    with pytest.raises(plan.PlanError) as exc:
        plan.build(c, host)
    return exc.value.errors


def test_2023_1_reproduces_the_known_port_table():
    result = plan.build(cfg(release="2023.1", image="nvcr.io/nvidia/isaac-sim:2023.1.1"), HOST)
    assert [i["ports"] for i in result["instances"]] == [
        {"http": 8211 + i, "webrtc": 8011 + i, "native": 48010 + i} for i in range(4)
    ]
    first = result["instances"][0]
    assert "--/exts/omni.services.transport.server.http/port=8211" in first["app_args"]
    assert "--user=0:0" in first["docker_args"]
    assert "--entrypoint=/isaac-sim/runheadless.webrtc.sh" in first["docker_args"]
    # one streaming method per instance: the WebRTC client's, the native port kept in the block only
    assert first["listens"] == ["http", "webrtc"] and first["profile"] == "streaming"
    assert not any(a.startswith("--/app/livestream/port") for a in first["app_args"])


def test_profiles_per_instance_decide_launch_ports_health_and_the_viewer():
    c = cfg(profile="streaming", instance_profiles={"3": "headless"}, web_viewer_image="reg.lab/viewer:1")
    result = plan.build(c, HOST)
    streaming, headless = result["instances"][0], result["instances"][3]
    assert streaming["profile"] == "streaming" and headless["profile"] == "headless"
    assert "--entrypoint=/isaac-sim/isaac-sim.sh" in headless["docker_args"]
    assert headless["app_args"][:1] == ["--no-window"] and "--allow-root" not in headless["app_args"]
    # the block is kept (a later switch back does not move ports), but nothing is opened or set
    assert headless["ports"] == {"signal": 49103, "stream": 48001, "web_viewer": 8213}
    assert headless["listens"] == []
    assert not {"ISAACSIM_SIGNAL_PORT", "ISAACSIM_STREAM_PORT", "ISAACSIM_HOST"} & set(headless["container_env"])
    [health] = [a for a in headless["docker_args"] if a.startswith("--health-cmd=")]
    assert "AppReady" in health and "/dev/tcp/" not in health
    # the web viewer only beside the streaming instances
    assert [c["name"] for c in streaming["companions"]] == ["viewer"]
    assert headless["companions"] == []
    # every instance headless: no viewer at all
    quiet = plan.build(cfg(profile="headless", web_viewer_image="reg.lab/viewer:1"), HOST)
    assert all(i["companions"] == [] for i in quiet["instances"])


def test_2023_1_native_opens_only_the_native_port():
    c = cfg(release="2023.1", image="nvcr.io/nvidia/isaac-sim:2023.1.1", instance_profiles={1: "native"})
    native = plan.build(c, HOST)["instances"][1]
    assert "--entrypoint=/isaac-sim/runheadless.native.sh" in native["docker_args"]
    assert native["listens"] == ["native"]
    assert [a for a in native["app_args"] if a.startswith("--/")] == [
        "--/app/livestream/port=48011",
        "--/app/livestream/publicEndpointAddress=10.0.0.5",
    ]
    headless = plan.build(dict(c, instance_profiles={1: "headless"}), HOST)["instances"][1]
    assert headless["app_args"] == ["--no-window", "--allow-root"]


@pytest.mark.parametrize(
    "settings, wanted",
    [
        ({"profile": "native"}, ["isaac_sim_profile: 'native' is not a profile of Isaac Sim 6.x", "2023.1 only"]),
        ({"profile": "batch"}, ["isaac_sim_profile: 'batch'", "Fix: choose one of streaming, headless"]),
        ({"instance_profiles": {"7": "headless"}}, ["isaac_sim_instance_profiles: instance 7 does not exist"]),
        ({"instance_profiles": {"x": "headless"}}, ["isaac_sim_instance_profiles: 'x' is not an instance number"]),
        ({"instance_profiles": {"1": "native"}}, ["isaac_sim_instance_profiles[1]: 'native'"]),
    ],
)
def test_unknown_profiles_are_refused_naming_the_variable(settings, wanted):
    text = "\n".join(errors_of(cfg(**settings)))
    for part in wanted:
        assert part in text, text


def test_6x_ports_go_through_isaacsim_variables():
    inst = plan.build(cfg(), HOST)["instances"][2]
    assert inst["ports"] == {"signal": 49102, "stream": 48000, "web_viewer": 8212}
    assert inst["container_env"]["ISAACSIM_SIGNAL_PORT"] == "49102"
    assert inst["container_env"]["ISAACSIM_STREAM_PORT"] == "48000"
    assert inst["container_env"]["ISAACSIM_HOST"] == "10.0.0.5"
    assert "--env=ISAACSIM_SIGNAL_PORT" in inst["docker_args"]
    assert "--user=1234:1234" in inst["docker_args"]
    assert not any(a.startswith("--/app/livestream") for a in inst["app_args"])


def test_5x_ports_go_through_kit_flags():
    inst = plan.build(cfg(release="5.x", image="nvcr.io/nvidia/isaac-sim:5.1.0"), HOST)["instances"][1]
    assert "--/app/livestream/port=49101" in inst["app_args"]
    assert "--/app/livestream/fixedHostPort=47999" in inst["app_args"]
    assert "--/exts/omni.services.transport.server.http/port=8012" in inst["app_args"]
    assert "--/app/livestream/publicEndpointAddress=10.0.0.5" in inst["app_args"]


def test_stride_and_bases():
    result = plan.build(cfg(port_bases={"signal": 50000}, port_stride=10), HOST)
    assert [i["ports"]["signal"] for i in result["instances"]] == [50000, 50010, 50020, 50030]


def test_every_instance_and_companion_port_on_the_hosts_network_is_kept_from_outgoing_connections():
    comp = [{"name": "bridge", "image": "reg/bridge:1", "ports": {"dds": 7400}}]
    result = plan.build(cfg(port_bases={"signal": 50000}, port_stride=10, companions=comp), HOST)
    every = {port for inst in result["instances"] for port in inst["ports"].values()}
    assert set(result["reserved_ports"]) == every | {7400, 7410, 7420, 7430}
    assert result["reserved_ports"] == sorted(result["reserved_ports"])


def test_empty_image_means_the_release_image():
    assert plan.build(cfg(image="", release="5.x"), HOST)["image"] == "nvcr.io/nvidia/isaac-sim:5.1.0"


@pytest.mark.parametrize(
    "over, needle",
    [
        ({"port_bases": {"signal": 47999}}, "overlaps instance"),
        ({"port_bases": {"web_viewer": 65534}}, "outside 1024-65535"),
        ({"port_bases": {"web_viewer": 80}}, "outside 1024-65535"),
        ({"port_bases": {"http": 9000}}, "http is not a port of Isaac Sim 6.x"),
        ({"instance_count": 9}, "above isaac_sim_max_instances"),
        ({"image": "NVCR.io/Bad Image"}, "not a valid image reference"),
        ({"image": "nvcr.io/nvidia/isaac-sim:5.1.0"}, "is an Isaac Sim 5.x image but isaac_sim_release is 6.x"),
        ({"memory_limit": "eight gigs"}, "isaac_sim_memory_limit: 'eight gigs' is not a size"),
        ({"shm_size": "2x"}, "isaac_sim_shm_size: '2x' is not a size"),
        ({"memory_limit": "32g"}, "more than this host's 64.0 GiB"),
        ({"accept_eula": False}, "isaac_sim_accept_eula"),
        ({"port_stride": 0}, "isaac_sim_port_stride"),
        ({"data_root": "relative/path"}, "isaac_sim_data_root"),
        ({"env": {"ISAAC_SIM_IMAGE": "x"}}, "usable variable name"),
        ({"gpu_map": {"0": 1}}, "isaac_sim_gpu_enabled is false"),
    ],
)
def test_bad_input_names_the_variable(over, needle):
    errors = errors_of(cfg(**over))
    assert any(needle in e for e in errors), errors
    assert all("Fix:" in e or "must be" in e for e in errors), errors


def test_all_errors_are_reported_at_once():
    errors = errors_of(cfg(memory_limit="x", shm_size="y", instance_count=20))
    assert len(errors) >= 3


def test_port_held_by_a_foreign_process_is_refused_but_ours_is_not():
    foreign = {"proto": "tcp", "port": 49101, "process": "nginx (pid 77)", "ours": False}
    errors = errors_of(cfg(), dict(HOST, ports_held=[foreign]))
    assert "49101/tcp is already held on this host by nginx (pid 77)" in errors[0]
    ours = dict(foreign, ours=True)
    plan.build(cfg(), dict(HOST, ports_held=[ours]))
    # a UDP socket does not block a TCP port of the same number
    plan.build(cfg(), dict(HOST, ports_held=[dict(foreign, proto="udp")]))
    # held twice (our viewer on the host's address, another process on 0.0.0.0): refused, in either order
    for both in ([foreign, ours], [ours, foreign]):
        assert "held on this host by nginx" in errors_of(cfg(), dict(HOST, ports_held=both))[0]


def test_gpus_round_robin_and_map():
    host = dict(HOST, gpu_count=2)
    result = plan.build(cfg(gpu_enabled=True), host)
    assert [i["gpu"] for i in result["instances"]] == [0, 1, 0, 1]
    assert "--gpus=device=1" in result["instances"][1]["docker_args"]
    assert "--runtime=nvidia" in result["instances"][1]["docker_args"]
    # the others go where the least is taken: GPU 0, which the map left empty
    mapped = plan.build(cfg(gpu_enabled=True, gpu_map={"0": 1, "1": 1}), host)
    assert [i["gpu"] for i in mapped["instances"]] == [1, 1, 0, 0]
    # where they run now, they stay (an upgrade moves no instance)
    kept = plan.build(cfg(gpu_enabled=True, gpu_map={"0": 1, "1": 1}), dict(host, gpu_current={"3": 1, "2": 0}))
    assert [i["gpu"] for i in kept["instances"]] == [1, 1, 0, 1]


@pytest.mark.parametrize(
    "over, gpu_count, needle",
    [
        ({"gpu_exclusive": True}, 2, "need 4 GPUs, this host has 2"),
        ({}, 0, "shows no NVIDIA GPU"),
        ({"gpu_map": {"1": 5}}, 2, "mapped to GPU 5"),
        ({"gpu_map": {"7": 0}}, 2, "instance 7 does not exist"),
        ({"gpu_exclusive": True, "instance_count": 2, "gpu_map": {"0": 0, "1": 0}}, 2, "share GPU 0"),
    ],
)
def test_gpu_errors(over, gpu_count, needle):
    errors = errors_of(cfg(gpu_enabled=True, **over), dict(HOST, gpu_count=gpu_count))
    assert any(needle in e for e in errors), errors


def test_no_gpu_arguments_without_gpus():
    inst = plan.build(cfg(), HOST)["instances"][0]
    assert inst["gpu"] is None
    assert not any(a.startswith("--gpus") or a.startswith("--runtime") for a in inst["docker_args"])


def test_instances_keep_their_own_directories():
    result = plan.build(cfg(), HOST)
    roots = [i["root"] for i in result["instances"]]
    assert roots == [f"/var/lib/isaac-sim/instance-{i}" for i in range(4)]
    volume = "--volume=/var/lib/isaac-sim/instance-3/cache/main:/isaac-sim/.cache:rw"
    assert volume in result["instances"][3]["docker_args"]


def test_release_of_tag():
    assert release_of_tag("6.0.1") == "6.x"
    assert release_of_tag("2023.1.1") == "2023.1"
    assert release_of_tag("4.5.0") == "4.x"
    assert release_of_tag("latest") is None
    assert set(RELEASES) == {"2023.1", "4.x", "5.x", "6.x"}


def test_values_given_on_the_command_line_are_numbers_in_the_plan():
    result = plan.build(cfg(ready_timeout="20", stop_timeout="20", restart_sec="5", start_limit_burst="3"), HOST)
    assert result["settings"] == {
        "ready_timeout": 20,
        "stop_timeout": 20,
        "restart_sec": 5,
        "start_limit_burst": 3,
        "health_interval": 30,
        "health_retries": 3,
        "unhealthy_restart": 300,
    }


def test_sizes_become_one_docker_word():
    inst = plan.build(cfg(memory_limit="1 gb", shm_size="256 MiB"), HOST)["instances"][0]
    assert "--memory=1g" in inst["docker_args"] and "--shm-size=256m" in inst["docker_args"]


@pytest.mark.parametrize(
    "over, needle",
    [
        ({"release": "7.x"}, "isaac_sim_release: '7.x' is not a release this collection knows"),
        ({"port_bases": {"signal": "abc"}}, "isaac_sim_port_bases.signal: 'abc' is not a port number"),
        ({"gpu_enabled": True, "gpu_map": {"x": 1}}, "isaac_sim_gpu_map: 'x': 1 is not instance number: GPU index"),
        ({"ready_timeout": "soon"}, "isaac_sim_ready_timeout: 'soon' is not a valid number"),
        ({"start_limit_burst": 0}, "isaac_sim_start_limit_burst: 0 is not a valid number"),
    ],
)
def test_raw_errors_become_plan_errors(over, needle):
    errors = errors_of(cfg(**over))
    assert any(needle in e for e in errors), errors
    assert len(errors) == 1 and len(errors[0]) < 300


def test_gpus_on_a_host_without_nvidia_smi_is_a_plan_error():
    errors = errors_of(cfg(gpu_enabled=True), dict(HOST, nvidia_smi=False))
    assert errors == [
        "isaac_sim_gpu_enabled: true, but this host has no nvidia-smi (no NVIDIA driver installed). "
        "Fix: install the NVIDIA driver, or set isaac_sim_gpu_enabled: false to run without GPUs."
    ]


def test_an_ngc_image_to_pull_needs_the_registry_key():
    errors = errors_of(cfg(), dict(HOST, image_present=False))
    assert any(e.startswith("isaac_sim_registry_password: empty, but nvcr.io/nvidia/isaac-sim:6.0.1") for e in errors)
    assert plan.build(cfg(registry_login=True), HOST)
    assert plan.build(cfg(), HOST)
    assert plan.build(cfg(image_pull="never"), dict(HOST, image_present=False))
    assert plan.build(cfg(image="registry.local/isaac-sim:6.0.1"), dict(HOST, image_present=False))


def test_containers_follow_nvidias_recipe():
    inst = plan.build(cfg(), HOST)["instances"][0]
    assert "--security-opt=no-new-privileges" in inst["docker_args"]
    mounts = [a for a in inst["docker_args"] if a.startswith("--volume=")]
    # 6.x keeps the kit cache and the Hub cache too, per instance
    assert "--volume=/var/lib/isaac-sim/instance-0/cache/kit:/isaac-sim/kit/cache:rw" in mounts
    assert "--volume=/var/lib/isaac-sim/instance-0/cache/hub:/var/cache/hub:rw" in mounts
    # no consent: PRIVACY_CONSENT is not set at all (NVIDIA: opting out is not setting it)
    assert "PRIVACY_CONSENT" not in inst["container_env"] and "--env=PRIVACY_CONSENT" not in inst["docker_args"]
    consenting = plan.build(cfg(privacy_consent=True), HOST)["instances"][0]
    assert consenting["container_env"]["PRIVACY_CONSENT"] == "Y"


def test_settings_below_the_release_needs_are_said():
    big = dict(HOST, memory_bytes=512 * GIB, gpu_count=1, gpus=[H100])
    quiet = plan.build(cfg(memory_limit="32g", gpu_enabled=True, profile="headless"), big)
    assert quiet["warnings"] == []
    small = plan.build(cfg(memory_limit="8g", gpu_enabled=True, profile="headless"), big)
    assert small["warnings"] == [
        "isaac_sim_memory_limit: 8.0 GiB per instance is below the 32.0 GiB NVIDIA names as Isaac Sim's minimum; "
        "a real instance may be killed for memory while it loads or compiles shaders. Fix: raise "
        "isaac_sim_memory_limit (fewer instances per host if the sum does not fit)."
    ]


def test_gpu_memory_is_placed_not_only_warned_about():
    """Six instances at NVIDIA's 16 GiB minimum on one 80 GB GPU: four fit, the fifth is refused."""
    big = dict(HOST, memory_bytes=512 * GIB, gpu_count=1, gpus=[H100])
    errors = errors_of(cfg(memory_limit="32g", instance_count=6, gpu_enabled=True, profile="headless"), big)
    assert errors == [
        "isaac_sim_gpu_memory: instances 4, 5 need 16384 MiB of GPU memory each, and none of this host's GPUs has "
        "that much left (GPU 0 (NVIDIA H100 80GB HBM3) without a video encoder: 81559 MiB, 480 reserved by the "
        "driver, 65536 taken by instances 0, 1, 2, 3, 15543 MiB left). Fix: fewer instances "
        "(isaac_sim_instance_count), less GPU memory each (isaac_sim_gpu_memory, isaac_sim_instance_gpu_memory) "
        "if your scenes allow it, or stop what else holds GPU memory."
    ]
    # less memory each: all six fit
    fits = plan.build(
        cfg(memory_limit="32g", instance_count=6, gpu_enabled=True, profile="headless", gpu_memory="12g"), big
    )
    assert [i["gpu"] for i in fits["instances"]] == [0] * 6


H100 = {
    "index": 0,
    "name": "NVIDIA H100 80GB HBM3",
    "brand": "NVIDIA",
    "memory_total_mib": 81559,
    "memory_reserved_mib": 480,
    "others_mib": 0,
    "encoder": False,
}


def test_the_healthcheck_is_nvidias_plus_the_port_answering():
    inst = plan.build(cfg(health_interval="5", health_retries=2), HOST)["instances"][1]
    cmd = next(a for a in inst["docker_args"] if a.startswith("--health-cmd="))
    assert "ls -t /isaac-sim/.nvidia-omniverse/logs/Kit/*/*/kit_*.log" in cmd and "grep -q AppReady" in cmd
    # the port asked at the address clients use, the instance's public one (ISAACSIM_HOST)
    assert "/dev/tcp/10.0.0.5/49101" in cmd and "--env=ISAACSIM_HOST" in inst["docker_args"]
    assert {"--health-interval=5s", "--health-retries=2", "--health-start-period=300s"} <= set(inst["docker_args"])
    old = plan.build(cfg(release="2023.1", image="nvcr.io/nvidia/isaac-sim:2023.1.1"), HOST)["instances"][0]
    assert "/root/.nvidia-omniverse/logs/Kit" in next(a for a in old["docker_args"] if a.startswith("--health-cmd="))
    assert "/dev/tcp/10.0.0.5/8211" in next(a for a in old["docker_args"] if a.startswith("--health-cmd="))


STATUS = {"enabled": True, "port": 8290, "address": "", "allow": ["10.0.0.0/8"], "origins": ["null"]}


def test_the_status_endpoint_listens_on_every_address_and_says_its_url_at_the_public_one():
    result = plan.build(cfg(status_server=STATUS), HOST)
    assert result["status_server"] == {
        "enabled": True,
        "address": "0.0.0.0",
        "port": 8290,
        "allow": ["10.0.0.0/8"],
        "logs_allow": [],
        "origins": ["null"],
        "url": "http://10.0.0.5:8290/status",
    }
    # the instances' logs to the front door alone, where asked
    door = plan.build(cfg(status_server=dict(STATUS, logs_allow=["10.0.0.9"])), HOST)["status_server"]
    assert door["logs_allow"] == ["10.0.0.9/32"]
    # the public address may be a name: only the URL uses it
    named = plan.build(cfg(public_address="gpu-1.lab", status_server=STATUS), HOST)["status_server"]
    assert named["url"] == "http://gpu-1.lab:8290/status"
    one = plan.build(cfg(status_server=dict(STATUS, address="10.0.0.5")), HOST)["status_server"]
    assert one["address"] == "10.0.0.5" and one["url"] == "http://10.0.0.5:8290/status"
    assert plan.build(cfg(), HOST)["status_server"] == {"enabled": False}


AGENT = {"enabled": True, "port": 8291, "allow": ["10.0.0.9"], "soak": "30"}


def test_the_action_agent_answers_the_front_door_alone_at_the_public_address():
    result = plan.build(cfg(agent=AGENT, status_server=STATUS), HOST)
    assert result["agent"] == {
        "enabled": True,
        "port": 8291,
        "allow": ["10.0.0.9/32"],
        "soak": 30.0,
        "address": "10.0.0.5",
        "url": "https://10.0.0.5:8291",
    }
    # the firewall lets the front door's address alone reach it, whatever the other ports allow
    fw = result["firewall"]
    assert ["host", "tcp", 8291, "agent", ""] in fw["ports"] and fw["by_kind"]["agent"] == ["10.0.0.9/32"]
    assert fw["default"] == ["10.0.0.0/8"]
    assert plan.build(cfg(), HOST)["agent"] == {"enabled": False}
    assert "agent" not in plan.build(cfg(), HOST)["firewall"]["by_kind"]


@pytest.mark.parametrize(
    "settings, wanted",
    [
        ({"allow": []}, "isaac_sim_agent_allow: empty, so the front door could not reach the agent"),
        ({"allow": ["door"]}, "isaac_sim_agent_allow: 'door' is not a network"),
        ({"port": 8290}, "isaac_sim_agent_port: 8290 is also the status endpoint's port"),
        ({"port": 49101}, "isaac_sim_agent_port: 49101 is also instance 1 signal's port"),
        ({"port": 99}, "isaac_sim_agent_port: 99 is not a port in 1024-65535"),
        ({"soak": "long"}, "isaac_sim_rollout_soak: 'long' is not a number of seconds"),
    ],
)
def test_bad_agent_settings_are_refused_before_any_change(settings, wanted):
    text = "\n".join(errors_of(cfg(agent=dict(AGENT, **settings), status_server=STATUS), HOST))
    assert wanted in text and "Fix:" in text, text


@pytest.mark.parametrize(
    "settings, host, wanted",
    [
        ({"port": 49101}, HOST, "isaac_sim_status_server_port: 49101 is also instance 1 signal's port"),
        ({"port": 80}, HOST, "isaac_sim_status_server_port: 80 is not a port in 1024-65535"),
        (
            {},
            dict(HOST, ports_held=[{"proto": "tcp", "port": 8290, "process": "nginx (pid 7)", "ours": False}]),
            "isaac_sim_status_server_port: 8290/tcp is already held on this host by nginx (pid 7)",
        ),
        ({"address": "gpu-1.lab"}, HOST, "isaac_sim_status_server_address: 'gpu-1.lab' is not an IP address"),
        ({"allow": ["lab-net"]}, HOST, "isaac_sim_status_server_allow: 'lab-net' is not a network"),
        ({"allow": []}, HOST, "isaac_sim_status_server_allow: empty, so nobody could read the status"),
        ({"logs_allow": ["door"]}, HOST, "isaac_sim_status_server_logs_allow: 'door' is not a network"),
    ],
)
def test_bad_status_endpoint_settings_are_refused_before_any_change(settings, host, wanted):
    text = "\n".join(errors_of(cfg(status_server=dict(STATUS, **settings)), host))
    assert wanted in text and "Fix:" in text, text


def test_a_companion_on_the_status_endpoints_port_is_named_itself():
    bridge = {"name": "bridge", "image": "reg.lab/bridge:1", "ports": {"ws": 8290}}
    text = "\n".join(errors_of(cfg(status_server=STATUS, companions=[bridge])))
    assert "isaac_sim_companions[bridge].ports.ws: 8290 (instance 0's) is the status endpoint's port" in text, text
    assert "isaac_sim_status_server_port: 8290 is also" not in text


def test_a_negative_count_says_what_to_give():
    text = "\n".join(errors_of(cfg(instance_count=-1)))
    assert "isaac_sim_instance_count: -1 is below 0. Fix: " in text, text


def test_a_count_of_0_on_a_serving_host_asks_for_a_confirmation():
    serving = dict(HOST, serving=4)
    text = "\n".join(errors_of(cfg(instance_count=0), serving))
    assert "isaac_sim_instance_count: 0 stops and removes every instance of this host, and 4 serve now" in text
    assert "Fix: set isaac_sim_scale_to_zero: true" in text
    assert plan.build(cfg(instance_count=0, scale_to_zero=True), serving)["ids"] == []
    # nothing serves: nothing to confirm
    assert plan.build(cfg(instance_count=0), HOST)["ids"] == []


HUB = {"enabled": True, "image": "nvcr.io/nvidia/omniverse/hub_workstation_cache:2.0.0", "dir": ""}


def test_the_hub_cache_is_one_directory_shared_by_every_6x_instance():
    result = plan.build(cfg(hub_cache=HUB), HOST)
    hub = result["hub_cache"]
    assert hub["dir"] == "/var/lib/isaac-sim/hub-cache" and hub["port"] == 14090
    for inst in result["instances"]:
        assert "--volume=/var/lib/isaac-sim/hub-cache:/var/cache/hub:rw" in inst["docker_args"]
        assert "/var/lib/isaac-sim/hub-cache" in inst["dirs"]
        assert not any("/cache/hub:" in a for a in inst["docker_args"] if "hub-cache" not in a)
    assert "--user=1234:1234" in hub["unit"] and "--network=host" in hub["unit"]
    assert "ExecStartPost=" in hub["unit"] and "14090" in hub["unit"]
    assert hub["dropin"].endswith("Wants=isaac-sim-hub.service\nAfter=isaac-sim-hub.service\n")
    # off: each instance keeps its own Hub cache, as NVIDIA's compose recipe does
    inst = plan.build(cfg(), HOST)["instances"][1]
    assert "--volume=/var/lib/isaac-sim/instance-1/cache/hub:/var/cache/hub:rw" in inst["docker_args"]


@pytest.mark.parametrize(
    "over, host, wanted",
    [
        (
            {"release": "5.x", "image": "nvcr.io/nvidia/isaac-sim:5.1.0"},
            HOST,
            "isaac_sim_hub_cache_enabled: Isaac Sim 5.x has no Hub client",
        ),
        ({"hub_cache": dict(HUB, image="Hub Cache")}, HOST, "isaac_sim_hub_cache_image: 'Hub Cache' is not a valid"),
        ({"hub_cache": dict(HUB, dir="hub")}, HOST, "isaac_sim_hub_cache_dir: 'hub' must be a directory of its own"),
        ({"hub_cache": dict(HUB, dir="/etc")}, HOST, "isaac_sim_hub_cache_dir: '/etc' must be a directory of its own"),
        ({"hub_cache": dict(HUB, dir="/srv/a/../b")}, HOST, "'/srv/a/../b' must be a directory of its own"),
        ({"hub_cache": dict(HUB, dir="/var/lib/isaac-sim")}, HOST, "'/var/lib/isaac-sim' must be a directory"),
        ({"hub_cache": dict(HUB, dir="/var/lib/isaac-sim/instance-0/hub")}, HOST, "instance-0/hub' must be"),
        (
            {"status_server": {"enabled": True, "port": 14090, "allow": ["10.0.0.0/8"]}},
            HOST,
            "isaac_sim_status_server_port: 14090 is also the Hub cache's port",
        ),
        (
            {},
            dict(HOST, ports_held=[{"proto": "tcp", "port": 14090, "process": "hub (pid 9)", "ours": False}]),
            "isaac_sim_hub_cache_enabled: 14090/tcp, the Hub cache's port, is already held on this host by hub (pid 9)",
        ),
    ],
)
def test_bad_hub_cache_settings_are_refused(over, host, wanted):
    text = "\n".join(errors_of(cfg(**dict({"hub_cache": HUB}, **over)), host))
    assert wanted in text and "Fix:" in text, text


# a host on 10.0.0.0/24 whose default route is on eth0, as the plan module finds it
LAN_HOST = dict(
    HOST,
    interfaces=["lo", "eth0"],
    links={"lo": [("127.0.0.1", 8)], "eth0": [("10.0.0.5", 24)]},
    default_route={"dev": "eth0", "gateway": "10.0.0.1"},
    network=None,
    # a foreign process on the first block's signal port does not matter at the instances' own addresses
    ports_held=[{"proto": "tcp", "port": 49100, "process": "nginx (pid 7)", "ours": False}],
)
OWN = {"network_mode": "macvlan", "address_pool": ["10.0.0.50-10.0.0.60"]}


def test_own_addresses_keep_the_release_ports_and_companions_share_the_instance_s_namespace():
    c = cfg(
        release="5.x",
        image="nvcr.io/nvidia/isaac-sim:5.1.0",
        companions=[{"name": "bridge", "image": "reg/bridge:1", "ports": {"dds": 7400}, "env": {"SIM": "{host}"}}],
        **OWN,
    )
    result = plan.build(c, LAN_HOST)
    assert result["network"]["parent"] == "eth0" and result["network"]["subnet"] == "10.0.0.0/24"
    # each binds in a namespace of its own: the host's outgoing connections cannot take its ports
    assert result["reserved_ports"] == []
    for i, inst in enumerate(result["instances"]):
        address = f"10.0.0.{50 + i}"
        assert inst["address"] == address
        assert inst["ports"] == {"signal": 49100, "stream": 47998, "http": 8011}
        assert inst["docker_args"][:2] == ["--network=isaac-sim-macvlan", f"--ip={address}"]
        assert "--network=host" not in inst["docker_args"]
        # the stream's public address is the instance's own
        assert f"--/app/livestream/publicEndpointAddress={address}" in inst["app_args"]
        bridge = inst["companions"][0]
        assert bridge["docker_args"][0] == f"--network=container:isaac-sim-{i}"
        assert bridge["ports"] == {"dds": 7400} and bridge["container_env"]["SIM"] == address
    env = unit_files.render_env(result["instances"][2], result, "sha256:x", {}, "managed")
    assert 'ISAAC_SIM_ADDRESS="10.0.0.52"' in env and 'ISAAC_SIM_PUBLIC_ADDRESS="10.0.0.52"' in env
    # on the host's network the env file has no address line: deployed hosts keep their files
    shared = plan.build(cfg(), HOST)
    assert "ISAAC_SIM_ADDRESS" not in unit_files.render_env(shared["instances"][0], shared, "sha256:x", {}, "m")
    assert shared["network"] == {"mode": "host", "found": False}


def test_the_6x_viewer_is_told_its_instance_s_address_and_the_hub_cache_is_refused():
    c = cfg(web_viewer_image="reg.lab/viewer:1", **OWN)
    viewer = plan.build(c, LAN_HOST)["instances"][1]["companions"][0]
    assert viewer["container_env"]["ISAACSIM_HOST"] == "10.0.0.51"
    assert viewer["ports"] == {"http": 8210} and viewer["docker_args"][0] == "--network=container:isaac-sim-1"
    errors = errors_of(cfg(hub_cache=HUB, **OWN), LAN_HOST)
    assert any(e.startswith("isaac_sim_hub_cache_enabled: the instances have addresses of their own") for e in errors)


def test_own_addresses_still_check_ports_inside_one_block_and_the_pool():
    errors = errors_of(cfg(port_bases={"signal": 47998}, **OWN), LAN_HOST)
    assert errors == [
        "isaac_sim_port_bases: instance 0 stream port 47998 overlaps instance 0 signal port. Fix: give each port kind "
        "a base of its own (each instance has every port at its address)."
    ]
    errors = errors_of(cfg(network_mode="macvlan", address_pool=["10.0.0.50"]), LAN_HOST)
    assert errors == [
        "isaac_sim_address_pool: 1 usable address(es) for the 4 instance(s) that need one from the pool "
        "(0, 1, 2, 3). Fix: add addresses of 10.0.0.0/24 that no machine uses, or give instances "
        "isaac_sim_instance_addresses."
    ]


def test_companions_of_instances_with_own_addresses_check_no_host_port_and_take_no_network_options():
    c = cfg(web_viewer_image="reg.lab/viewer:1", **OWN)
    result = plan.build(c, LAN_HOST)
    viewer = result["instances"][0]["companions"][0]
    assert 'ISAAC_SIM_ADDRESS="10.0.0.50"' in unit_files.render_companion_env(viewer, result, "m")
    shared = plan.build(cfg(web_viewer_image="reg.lab/viewer:1"), HOST)
    assert "ISAAC_SIM_ADDRESS" not in unit_files.render_companion_env(
        shared["instances"][0]["companions"][0], shared, "m"
    )
    bad = [{"name": "bridge", "image": "reg/bridge:1", "docker_args": ["-p", "7400:7400", "--hostname=robot"]}]
    errors = errors_of(cfg(companions=bad, **OWN), LAN_HOST)
    assert [e.split(":")[0] for e in errors] == ["isaac_sim_companions[bridge].docker_args"] * 2
    assert "-p cannot be given to a companion of an instance with its own address" in errors[0]
    assert plan.build(cfg(companions=bad), HOST)["instances"][0]["companions"][0]["docker_args"][-1] == (
        "--hostname=robot"
    )


def test_a_way_out_of_the_container_is_refused_for_instances_and_companions_unless_allowed():
    bridge = {
        "name": "bridge",
        "image": "reg/bridge:1",
        "instances": [1],
        "docker_args": ["--cap-add=NET_ADMIN"],
        "volumes": ["maps:/maps", "/var/run/docker.sock:/var/run/docker.sock"],
    }
    c = cfg(instance_count=2, docker_args=["--privileged", "--cpus=8"], companions=[bridge])
    errors = errors_of(c)
    assert [e.split(" (")[0] for e in errors if "isaac_sim_allowed_docker_args" in e] == [
        "isaac_sim_extra_docker_args: --privileged gives the container every capability and device",
        "isaac_sim_companions[bridge].docker_args: --cap-add=NET_ADMIN adds the capability NET_ADMIN to the container",
        "isaac_sim_companions[bridge].volumes: --volume=/var/run/docker.sock:/var/run/docker.sock binds host path "
        "/run/docker.sock into it: Docker's socket, which controls every container and the host",
    ]
    assert any("(on isaac-sim-0, isaac-sim-1)" in e for e in errors)
    assert any("(the companion of isaac-sim-1)" in e for e in errors)
    # allowed, each by what Docker makes of it: the plan takes them, as given
    allow = ["--privileged=1", "--cap-add", "net_admin", "-v/run/docker.sock:/elsewhere"]
    allowed = plan.build(dict(c, allowed_docker_args=allow), HOST)
    assert "--privileged" in allowed["instances"][0]["docker_args"]


def test_binds_come_from_the_data_root_and_the_declared_roots_and_root_is_refused_where_the_release_has_a_user():
    c = cfg(docker_args=["-v", "/srv/maps:/maps:ro", "-u0"], companions=[{"name": "rec", "image": "r:1", "user": "0"}])
    errors = [e.split(" (on ")[0].split(" (the companion")[0] for e in errors_of(c)]
    assert errors == [
        "isaac_sim_extra_docker_args: --volume=/srv/maps:/maps:ro binds host path /srv/maps into it, outside the paths "
        "this host allows bind mounts from (/var/lib/isaac-sim; more with isaac_sim_allowed_bind_roots)",
        "isaac_sim_extra_docker_args: --user=0 runs the container as root, where its release runs as a user",
        "isaac_sim_companions[rec].user: --user=0 runs the container as root, where its release runs as a user",
    ]
    ok = plan.build(cfg(docker_args=["-v", "/srv/maps:/maps:ro"], allowed_bind_roots=["/srv/maps"]), HOST)
    assert "/srv/maps:/maps:ro" in ok["instances"][0]["docker_args"]
    # 4.x's container runs as root itself: --user=0 takes nothing away there
    assert plan.build(cfg(release="4.x", image="nvcr.io/nvidia/isaac-sim:4.5.0", docker_args=["--user=0"]), HOST)
    errors = errors_of(cfg(allowed_bind_roots=["/var"], allowed_docker_args=["--bogus"]))
    assert errors[0].startswith("isaac_sim_allowed_bind_roots: '/var' holds or is Docker's own state")
    assert errors[1].startswith("isaac_sim_allowed_docker_args: unknown flag: --bogus. Fix:")


L4 = {"name": "NVIDIA L4", "brand": "NVIDIA", "memory_total_mib": 23034, "memory_reserved_mib": 522, "encoder": True}


def test_gpu_memory_per_instance_and_companion_is_what_placement_weighs():
    host = dict(HOST, gpu_count=2, gpus=[dict(L4, index=0), dict(L4, index=1)])
    # 2 x 16 GiB fit two L4s; instance 1 asking 20g still fits its own, 24g does not fit any
    two = plan.build(cfg(gpu_enabled=True, instance_count=2, instance_gpu_memory={"1": "20g"}), host)
    assert [i["gpu"] for i in two["instances"]] == [0, 1]
    errors = errors_of(cfg(gpu_enabled=True, instance_count=2, instance_gpu_memory={1: "24g"}), host)
    assert errors[0].startswith("isaac_sim_gpu_memory: instance 1 needs 24576 MiB of GPU memory, and none of")
    # a companion on the instance's GPU adds what it names
    bridge = {"name": "bridge", "image": "reg/bridge:1", "gpu": True, "gpu_memory": "8g"}
    errors = errors_of(cfg(gpu_enabled=True, instance_count=2, companions=[bridge]), host)
    assert "instances 0, 1 need 24576 MiB of GPU memory each" in errors[0]
    fits = plan.build(cfg(gpu_enabled=True, instance_count=2, gpu_memory="12g", companions=[bridge]), host)
    assert [i["gpu"] for i in fits["instances"]] == [0, 1]


@pytest.mark.parametrize(
    "over, needle",
    [
        (
            {"gpu_memory": "16384"},
            "isaac_sim_gpu_memory: '16384' is not a size with its unit. Fix: write it as e.g. 16g",
        ),
        ({"gpu_memory": "lots"}, "isaac_sim_gpu_memory: 'lots' is not a size with its unit"),
        ({"instance_gpu_memory": {"9": "8g"}}, "isaac_sim_instance_gpu_memory: '9': '8g' is not instance number: size"),
        ({"instance_gpu_memory": {"1": "8"}}, "isaac_sim_instance_gpu_memory: '1': '8' is not instance number: size"),
        (
            {"companions": [{"name": "b", "image": "r/b:1", "gpu": True, "gpu_memory": "big"}]},
            "isaac_sim_companions[b].gpu_memory: 'big' is not a size with its unit. Fix: e.g. 4g or 2048m.",
        ),
        (
            {"companions": [{"name": "b", "image": "r/b:1", "gpu_memory": "2g"}]},
            "isaac_sim_companions[b].gpu_memory: '2g', but the companion has no GPU (gpu: false). Fix: set gpu: true",
        ),
    ],
)
def test_gpu_memory_settings_that_do_not_parse_are_named(over, needle):
    host = dict(HOST, gpu_count=1, gpus=[dict(L4, index=0)])
    errors = errors_of(cfg(gpu_enabled=True, instance_count=1, **over), host)
    assert any(needle in e for e in errors), errors


def test_gpu_memory_for_instances_without_gpus_is_a_mistake():
    errors = errors_of(cfg(instance_gpu_memory={"0": "20g"}), HOST)
    assert errors == [
        "isaac_sim_instance_gpu_memory: set while isaac_sim_gpu_enabled is false. Fix: enable GPUs or remove it."
    ]


def test_an_ngc_image_pulled_through_a_mirror_needs_no_key_on_the_host():
    ngc = cfg(image="nvcr.io/nvidia/isaac-sim:6.0.1", image_pull="missing", registry_login=False)
    absent = dict(HOST, image_present=False)
    assert any(e.startswith("isaac_sim_registry_password: empty") for e in errors_of(ngc, absent))
    plan.build(dict(ngc, registry_mirror="m.lab:5443", registry_mirror_upstream="https://nvcr.io"), absent)
    # a mirror of another registry does not carry NGC's images
    other = dict(ngc, registry_mirror="m.lab:5443", registry_mirror_upstream="https://reg.lab")
    assert any(e.startswith("isaac_sim_registry_password: empty") for e in errors_of(other, absent))


def test_a_mirror_needs_the_pin_and_a_companion_s_ngc_image_needs_the_key():
    mirrored = cfg(
        image="nvcr.io/nvidia/isaac-sim:6.0.1", registry_mirror="m.lab:5443", registry_mirror_upstream="nvcr.io"
    )
    errors = errors_of(dict(mirrored, image_pin=False), HOST)
    assert errors[0].startswith("isaac_sim_registry_mirror: set while isaac_sim_image_pin is false")
    # the Hub cache's image on NGC, not on the host, no key: it is pulled straight from NGC
    hub = "nvcr.io/nvidia/omniverse/hub_workstation_cache:2.0.0"
    errors = errors_of(mirrored, dict(HOST, companion_images_missing=[hub]))
    assert errors == [
        f"isaac_sim_registry_password: empty, but {hub} (a companion's image or the Hub cache's) is on NGC "
        "(nvcr.io), which refuses pulls without an API key, is not on this host and is pulled straight from NGC "
        "(only the instances' image goes through a mirror). Fix: set isaac_sim_registry_password, or put that "
        "image in the fleet's own registry."
    ]
    plan.build(dict(mirrored, registry_login=True), dict(HOST, companion_images_missing=[hub]))
