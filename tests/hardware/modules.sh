#!/usr/bin/env bash
# Run the GPU-facing modules through Ansible on this host (a GPU host): the driver check, and
# isaac_sim_info with each GPU source. Run from the repository root, with ansible on PATH.
set -u
work=$(mktemp -d)
printf '[defaults]\n' >"$work/ansible.cfg"
mkdir -p "$work/ansible_collections/isaacsim" && ln -s "$PWD" "$work/ansible_collections/isaacsim/fleet"
export ANSIBLE_COLLECTIONS_PATH=$work ANSIBLE_CONFIG=$work/ansible.cfg ANSIBLE_CALLBACK_RESULT_FORMAT=yaml \
  ANSIBLE_LOCALHOST_WARNING=false ANSIBLE_INVENTORY_UNPARSED_WARNING=false
adhoc() { ansible localhost -c local -i localhost, -e "ansible_python_interpreter=$(command -v python3)" "$@"; }
echo "== driver check, Isaac Sim 5.x"; adhoc -m isaacsim.fleet.nvidia_driver_check -a release=5.x
echo "== driver check, a minimum above the driver"; adhoc -m isaacsim.fleet.nvidia_driver_check -a min_version=999.1
echo "== isaac_sim_info, NVML"; adhoc -m isaacsim.fleet.isaac_sim_info -a gpu_source=nvml
echo "== isaac_sim_info, nvidia-smi"; adhoc -m isaacsim.fleet.isaac_sim_info -a gpu_source=nvidia-smi
rm -rf "$work"
