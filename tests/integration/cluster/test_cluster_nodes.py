"""The slurm_node role's cluster (molecule/cluster): a controller and two compute nodes with
stand-in GPUs (device files with NVIDIA's major number, a stand-in nvidia-smi: test fixtures),
checked from outside through Slurm itself: what sinfo shows, where srun puts steps, what a
step's device cgroup lets it open, and what the role refuses.
"""

from __future__ import annotations

import json
import re
import shlex
import subprocess

import pytest
import testbed
from clusterhosts import CONTROLLER, MANAGED, NODES, PLAIN, playbook, sh, squash
from testbed import ROOT, client


def test_inventory_is_the_cluster():
    out = subprocess.run(
        ["ansible-inventory", "-i", testbed.inventory(), "--list"], capture_output=True, text=True, check=True, cwd=ROOT
    )
    groups = json.loads(out.stdout)
    assert groups["slurm_controller"]["hosts"] == [CONTROLLER]
    assert sorted(groups["slurm_compute"]["hosts"]) == sorted(NODES)


def test_sinfo_shows_both_nodes_idle_with_their_gpus():
    lines = sh(CONTROLLER, "sinfo -N -h -o '%N|%T|%G|%P'").split()
    found = {fields[0]: fields[1:] for fields in (line.split("|") for line in lines)}
    assert found == {name: ["idle", f"gpu:{gpus}", "gpu*"] for name, gpus in NODES.items()}
    assert "is UP" in sh(CONTROLLER, "scontrol ping")


def test_one_munge_key_for_the_cluster():
    keys = {host: sh(host, "sha256sum /etc/munge/munge.key").split()[0] for host in [CONTROLLER, *NODES]}
    assert len(set(keys.values())) == 1, keys
    for host in [CONTROLLER, *NODES]:
        owner, mode = sh(host, "stat -c '%U:%G %a' /etc/munge/munge.key").split()
        assert owner == "munge:munge" and mode in ("400", "600"), (host, owner, mode)
    # a credential made on a compute node decodes on the controller
    credential = sh("slurm-node-2", "munge -n").strip()
    assert "STATUS:          Success" in sh(CONTROLLER, f"echo '{credential}' | unmunge")


def test_steps_land_on_the_node_asked_for_or_the_one_with_enough_gpus():
    assert sh(CONTROLLER, "srun -w slurm-node-2 hostname").strip() == "slurm-node-2"
    # three tries: node-2 is free too, and never chosen
    landed = {sh(CONTROLLER, "srun --gpus-per-node=2 hostname").strip() for _try in range(3)}
    assert landed == {"slurm-node-1"}
    # two nodes of two GPUs: the cluster has one
    out = sh(CONTROLLER, "srun -N2 --gpus-per-node=2 hostname", check=False)
    assert "Requested node configuration is not available" in out


def test_a_step_opens_its_gpu_and_not_the_other():
    script = (
        'echo "gpus=$SLURM_STEP_GPUS"; '
        "for i in 0 1; do printf 'nvidia%s: ' $i; cat /dev/nvidia$i 2>&1 | sed 's/.*: //'; done"
    )
    out = sh(CONTROLLER, f"srun -w slurm-node-1 --gpus=1 sh -c {shlex.quote(script)}")
    given = int(re.search(r"gpus=(\d+)", out).group(1))
    other = 1 - given
    # no driver behind the device: the one the cgroup allows answers ENXIO, the other EPERM
    assert f"nvidia{given}: No such device or address" in out, out
    assert f"nvidia{other}: Operation not permitted" in out, out


def test_generated_files_are_stamped_and_the_same_everywhere():
    for name in ("slurm.conf", "cgroup.conf", "gres.conf"):
        sums = set()
        for host in [CONTROLLER, *NODES]:
            text = sh(host, f"cat /etc/slurm/{name}")
            assert text.startswith(MANAGED), (host, name, text[:200])
            sums.add(sh(host, f"sha256sum /etc/slurm/{name}").split()[0])
        assert len(sums) == 1, name
    gres = sh(CONTROLLER, "grep -v '^#' /etc/slurm/gres.conf").split("\n")
    assert [line for line in gres if line] == [
        "NodeName=slurm-node-1 Name=gpu File=/dev/nvidia0",
        "NodeName=slurm-node-1 Name=gpu File=/dev/nvidia1",
        "NodeName=slurm-node-2 Name=gpu File=/dev/nvidia0",
    ]
    conf = sh(CONTROLLER, "cat /etc/slurm/slurm.conf")
    address = client().containers.get(CONTROLLER).attrs["NetworkSettings"]["IPAddress"]
    assert f"SlurmctldHost={CONTROLLER}({address})" in conf
    assert re.search(r"^NodeName=slurm-node-1 NodeAddr=\S+ CPUs=\d+ .*RealMemory=\d+ Gres=gpu:2 ", conf, re.M)


def test_node_local_cache_and_shared_directory():
    for host in NODES:
        assert sh(host, "stat -c '%U %a' /var/tmp/isaac-sim-cache").split() == ["root", "1777"]
    assert sh(CONTROLLER, "stat -c '%a' /shared/isaaclab").strip() == "1777"
    # one file system for all: what the controller writes there, a node reads
    sh(CONTROLLER, "echo shared > /shared/isaaclab/.probe")
    assert sh("slurm-node-2", "cat /shared/isaaclab/.probe").strip() == "shared"
    sh(CONTROLLER, "rm -f /shared/isaaclab/.probe")


def run_check(tmp_path, host: str) -> subprocess.CompletedProcess:
    """The role's read-only node check (tasks_from: check) on one host, as an operator runs it."""
    book = tmp_path / "check.yml"
    book.write_text(
        "- hosts: all\n  become: true\n  gather_facts: false\n  tasks:\n"
        "    - ansible.builtin.include_role:\n        name: isaacsim.fleet.slurm_node\n        tasks_from: check\n"
    )
    cmd = ["ansible-playbook", "-i", testbed.inventory(), "--limit", host, str(book)]
    return subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, timeout=300, check=False, env=PLAIN)


@pytest.fixture
def standin_conf():
    """Change slurm-node-2's stand-in nvidia-smi for a test, then put it back."""
    before = sh("slurm-node-2", "cat /etc/standin-nvidia-smi.conf")
    yield lambda text: sh("slurm-node-2", f"printf '%s\\n' '{text}' > /etc/standin-nvidia-smi.conf")
    sh("slurm-node-2", f"printf '%s' '{before}' > /etc/standin-nvidia-smi.conf")


def test_check_passes_on_a_good_node(tmp_path):
    result = run_check(tmp_path, "slurm-node-2")
    assert result.returncode == 0, result.stdout[-3000:]
    assert re.search(r"slurm-node-2\s*:.*changed=0 .*failed=0", result.stdout)


def test_a_node_with_an_old_driver_fails_the_check(tmp_path, standin_conf):
    standin_conf("STANDIN_GPUS=1\nSTANDIN_DRIVER=470.82.01")
    result = run_check(tmp_path, "slurm-node-2")
    out = squash(result.stdout + result.stderr)
    assert result.returncode != 0, out[-2000:]
    assert "NVIDIA driver 470.82.01 is older than" in out, out[-2000:]
    assert "Fix: upgrade the driver" in out


def test_a_node_whose_gpus_and_device_files_disagree_fails_the_check(tmp_path, standin_conf):
    standin_conf("STANDIN_GPUS=2")
    result = run_check(tmp_path, "slurm-node-2")
    out = squash(result.stdout + result.stderr)
    assert result.returncode != 0, out[-2000:]
    assert "nvidia-smi lists 2 GPU(s) on slurm-node-2, and /dev has 1 GPU device file(s) (/dev/nvidia0)" in out, out[
        -2000:
    ]


def test_a_site_that_runs_its_own_slurm_keeps_its_configuration_and_gets_the_lines_it_needs():
    """slurm_node_manage_config: false, on a cluster whose files the site has edited: the role
    touches no Slurm file and no munge key, restarts nothing, and prints each node's lines."""
    owned = "/etc/slurm/slurm.conf /etc/slurm/cgroup.conf /etc/slurm/gres.conf /etc/munge/munge.key"
    hosts = [CONTROLLER, *NODES]
    for host in hosts:
        sh(host, "echo '# the site s own line' >> /etc/slurm/slurm.conf")
    before = {h: sh(h, f"md5sum {owned}; systemctl show -p ActiveEnterTimestamp munge slurmd slurmctld") for h in hosts}
    try:
        done = playbook("cluster.yml", {"slurm_node_manage_config": False})
        assert done.returncode == 0, done.stdout[-3000:] + done.stderr
        assert {
            h: sh(h, f"md5sum {owned}; systemctl show -p ActiveEnterTimestamp munge slurmd slurmctld") for h in hosts
        } == before
        text = squash(done.stdout)
        for node, gpus in NODES.items():
            assert re.search(rf"NodeName={node} NodeAddr=\S+ CPUs=\d+ .*Gres=gpu:{gpus}", text), text[-3000:]
            assert f"NodeName={node} Name=gpu File=/dev/nvidia{gpus - 1}" in text
    finally:
        for host in hosts:
            sh(host, "sed -i '/# the site s own line/d' /etc/slurm/slurm.conf")
