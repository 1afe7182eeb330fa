"""The isaac_sim_host_units filter: the host services' units, from the layout's names."""

from __future__ import annotations

import pytest
from ansible.errors import AnsibleFilterError
from ansible_collections.isaacsim.fleet.plugins.filter.isaac_sim_host_units import FilterModule, isaac_sim_host_units
from ansible_collections.isaacsim.fleet.plugins.module_utils.common import sandbox
from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib import layout

STATUS = {
    "name": "gpu host 1",
    "address": "0.0.0.0",
    "port": 8290,
    "allow": ["10.0.0.0/8", "127.0.0.1/32"],
    "logs_allow": ["10.0.0.9/32"],
    "origins": ["http://dash:8080"],
    "gpu_source": "auto",
}
METRICS = {"textfile_dir": "/var/lib/node-exporter", "interval": "15s", "gpu_source": "nvidia-smi"}


def lines(text: str) -> list:
    return text.splitlines()


def test_status_unit_runs_the_server_with_its_settings_sandboxed():
    units = isaac_sim_host_units(STATUS, "status")
    assert list(units) == [layout.STATUS_UNIT]
    text = lines(units[layout.STATUS_UNIT])
    assert text[0] == f"# {layout.MANAGED}" and text[1] == "[Unit]"
    [start] = [line for line in text if line.startswith("ExecStart=")]
    assert start == (
        f"ExecStart=/usr/bin/python3 {layout.LIBEXEC_DIR}/{layout.STATUS_SCRIPT} --lib {layout.LIB_DIR}"
        " --name 'gpu host 1' --address 0.0.0.0 --port 8290 --allow 10.0.0.0/8 --allow 127.0.0.1/32"
        " --logs-allow 10.0.0.9/32 --origin http://dash:8080 --gpu-source auto"
    )
    for key, value in sandbox.reader():
        assert f"{key}={value}" in text
    assert text[-2:] == ["[Install]", "WantedBy=multi-user.target"]


def test_metrics_are_a_oneshot_and_its_timer_writing_into_the_textfile_directory():
    units = isaac_sim_host_units(METRICS, "metrics")
    assert sorted(units) == sorted([layout.METRICS_UNIT, layout.METRICS_TIMER])
    service, timer = lines(units[layout.METRICS_UNIT]), lines(units[layout.METRICS_TIMER])
    assert "Type=oneshot" in service
    [start] = [line for line in service if line.startswith("ExecStart=")]
    assert start.endswith(f"--output /var/lib/node-exporter/{layout.METRICS_FILE} --gpu-source nvidia-smi")
    # the status endpoint's sandbox, no network, and only its directory writable
    assert "RestrictAddressFamilies=AF_UNIX AF_INET AF_INET6" in service and "IPAddressDeny=any" in service
    assert [line for line in service if line.startswith("ReadWritePaths=")] == ["ReadWritePaths=/var/lib/node-exporter"]
    assert "OnUnitActiveSec=15s" in timer and "Description=Write Isaac Sim instance metrics every 15s" in timer
    assert "[Install]" not in service and timer[-1] == "WantedBy=timers.target"


def test_the_agent_runs_from_its_copy_of_the_code_for_the_front_door_s_networks():
    agent = {"name": "gpu host 1", "port": 8291, "allow": ["10.0.0.9/32"], "soak": 30.0, "data_root": "/data/isaac"}
    units = isaac_sim_host_units(agent, "agent")
    text = lines(units[layout.AGENT_UNIT])
    assert f"Environment=PYTHONPATH={layout.AGENT_LIB}" in text
    [start] = [line for line in text if line.startswith("ExecStart=")]
    assert start == (
        "ExecStart=/usr/bin/python3 -m ansible_collections.isaacsim.fleet.plugins.module_utils.instance.agent"
        " --name 'gpu host 1' --port 8291 --allow 10.0.0.9/32 --soak 30.0 --data-root /data/isaac"
    )
    for key, value in sandbox.agent("/data/isaac"):
        assert f"{key}={value}" in text


@pytest.mark.parametrize(
    "settings, service, message",
    [
        (STATUS, "hub", "no host service 'hub'"),
        ({k: v for k, v in METRICS.items() if k != "interval"}, "metrics", "settings lack interval"),
    ],
)
def test_an_unknown_service_or_a_missing_setting_is_named(settings, service, message):
    with pytest.raises(AnsibleFilterError, match=message):
        isaac_sim_host_units(settings, service)


def test_the_filter_is_registered():
    assert FilterModule().filters()["isaac_sim_host_units"] is isaac_sim_host_units
