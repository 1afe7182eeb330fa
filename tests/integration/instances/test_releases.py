"""Each release profile reaches the container the way that release expects.

The stand-in image (a test fixture) opens exactly the ports its launch
script's kit flags or ISAACSIM_* variables ask for, so a port that answers
proves the settings were passed the release's way.
"""

import json
import re
import socket
import urllib.request

import pytest
import testbed
from dashboard import OUTPUT, check_dashboard, dashboard
from testbed import INSTANCES, registry_image, sh

# on the trixie scenario's host (molecule/trixie), not the default one: the CI lane with room for them
pytestmark = pytest.mark.trixie_host


@pytest.fixture(scope="module", autouse=True)
def restore_default(host):
    # once, after both tests: the release switch starts from the 2023.1 deployment (root, as 4.x)
    yield
    result = testbed.run_playbook(host)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr
    testbed.all_ready(host)


def refused(ip, port) -> bool:
    try:
        socket.create_connection((ip, port), timeout=2).close()
    except ConnectionRefusedError:
        return True
    return False


def test_2023_1_serves_one_streaming_method_per_instance_webrtc_or_native(host, tmp_path):
    # instances 0-2 the WebRTC browser client (the default profile), instance 3 the native livestream
    result = testbed.run_playbook(
        host,
        {
            "isaac_sim_release": "2023.1",
            "isaac_sim_image": registry_image(host, "2023.1.1"),
            "isaac_sim_instance_profiles": {3: "native"},
        },
    )
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr
    ip = testbed.host_ip(host)
    status = testbed.by_name(testbed.info(host))
    for i in range(INSTANCES):
        assert testbed.instance_ready(host, i)
        assert sh(host, f"docker inspect -f '{{{{.Config.User}}}}' isaac-sim-{i}").stdout.strip() == "0:0"
        urls = status[f"isaac-sim-{i}"]["urls"]
        if i < 3:
            url = f"http://{ip}:{8211 + i}/streaming/webrtc-client?server={ip}"
            assert url in result.stdout, "the deploy did not print the instance's address"
            with urllib.request.urlopen(url, timeout=5) as page:
                assert f"server={ip}" in page.read().decode()
            # NVIDIA: one streaming method per instance; the native port is kept, not opened
            assert urls == {"webrtc_client": url} and refused(ip, 48010 + i)
        else:
            assert status["isaac-sim-3"]["profile"] == "native"
            assert urls == {"native": f"{ip}:48013"} and f"native={ip}:48013" in result.stdout
            with socket.create_connection((ip, 48013), timeout=2) as conn:
                conn.sendall(b"hello\n")  # the stand-in's hook for tests
                assert conn.recv(64).startswith(b"isaac-sim-standin native")
            assert refused(ip, 8214) and refused(ip, 8014)
    # the dashboard embeds each WebRTC instance's own browser client and shows the native address
    _run, out = dashboard(host, tmp_path)
    expected = {i["id"]: i for i in testbed.info(host)["instances"]}
    found = check_dashboard(out / "status.html", expected, OUTPUT / "dashboard-2023.1.png")
    assert sorted(found["frames"]) == sorted(expected[i]["urls"]["webrtc_client"] for i in range(3))
    assert all(re.search(r"server=\d+\.\d+\.\d+\.\d+", src) for src in found["frames"])
    # the frames really loaded each instance's own client page
    assert len(found["frame_text"]) == 3 and all(found["frame_text"]), found["frame_text"]
    assert ("3", "native", f"{ip}:48013") in found["addresses"]


def test_a_release_switch_goes_through_the_lifecycle_and_a_failed_one_goes_back(host):
    four = testbed.run_playbook(host, {"isaac_sim_release": "4.x", "isaac_sim_image": registry_image(host, "4.5.0")})
    assert four.returncode == 0, four.stdout[-3000:] + four.stderr
    testbed.all_ready(host)
    root_ids = {i: testbed.container_id(host, f"isaac-sim-{i}") for i in range(INSTANCES)}
    # written as root by the 4.x instance (its ov cache and log)
    assert sh(host, "stat -c %u /var/lib/isaac-sim/instance-0/cache/ov/standin-shader-cache").stdout.strip() == "0"

    # the canary of a 4.x -> 5.x switch never gets ready: it goes back to a running 4.x instance
    bad = testbed.run_playbook(
        host,
        {
            "isaac_sim_release": "5.x",
            "isaac_sim_image": registry_image(host, "5.1.0-never-ready"),
            # the gate's deadline is all the canary waits for: short, it never gets ready
            "isaac_sim_ready_timeout": 5,
        },
    )
    out = " ".join((bad.stdout + bad.stderr).split())
    assert bad.returncode != 0
    assert f"Rollout stopped on {testbed.name(host)}: isaac-sim-0: isaac-sim-0 was not ready within 5 s" in out, out[
        -3000:
    ]
    testbed.all_ready(host)
    user, image = sh(host, "docker inspect -f '{{.Config.User}} {{.Config.Image}}' isaac-sim-0").stdout.split()
    # run by the digest its deploy pinned the 4.5.0 tag to (REPOSITORY@DIGEST, one of the tag's RepoDigests)
    digests = sh(host, f"docker image inspect -f '{{{{json .RepoDigests}}}}' {registry_image(host, '4.5.0')}").stdout
    assert user == "0:0" and image in json.loads(digests), (image, digests)
    assert {i: testbed.container_id(host, f"isaac-sim-{i}") for i in (1, 2, 3)} == {i: root_ids[i] for i in (1, 2, 3)}

    # the good switch: every instance runs as uid 1234 with its caches kept and handed over
    five = testbed.run_playbook(host, {"isaac_sim_release": "5.x", "isaac_sim_image": registry_image(host, "5.1.0")})
    assert five.returncode == 0, five.stdout[-3000:] + five.stderr
    testbed.all_ready(host)
    for i in range(INSTANCES):
        assert sh(host, f"docker inspect -f '{{{{.Config.User}}}}' isaac-sim-{i}").stdout.strip() == "1234:1234"
        # the 4.x cache is still there, and what 4.x wrote in the shared logs now belongs to uid 1234
        assert sh(host, f"test -s /var/lib/isaac-sim/instance-{i}/cache/ov/standin-shader-cache", check=False).rc == 0
        owners = sh(host, f"find /var/lib/isaac-sim/instance-{i}/logs -printf '%u\\n' | sort -u").stdout.split()
        assert owners == ["1234"], owners
    # 5.x takes its ports as kit flags: each one answers
    ip = testbed.host_ip(host)
    for i in range(INSTANCES):
        cmd = sh(host, f"docker inspect -f '{{{{json .Args}}}}' isaac-sim-{i}").stdout
        assert f"--/app/livestream/port={49100 + i}" in cmd
        assert f"--/app/livestream/fixedHostPort={47998 + i}" in cmd
        socket.create_connection((ip, 49100 + i), timeout=2).close()
        with urllib.request.urlopen(f"http://{ip}:{8011 + i}/health", timeout=5) as page:
            assert page.status == 200
