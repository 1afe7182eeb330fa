"""Which GPU each instance runs on (module_utils/instance/placement.py): GPU memory and video encoders."""

from __future__ import annotations

from ansible_collections.isaacsim.fleet.plugins.module_utils.instance import placement


def gpu(index, name="NVIDIA L4", mib=23034, encoder=True, brand="NVIDIA", others=0, reserved=522):
    return {
        "index": index,
        "name": name,
        "brand": brand,
        "memory_total_mib": mib,
        "memory_reserved_mib": reserved,
        "others_mib": others,
        "encoder": encoder,
    }


def h100(index, others=0):
    return gpu(index, "NVIDIA H100 80GB HBM3", 81559, encoder=False, others=others, reserved=480)


def needs(count, mib=16384, headless=()):
    return {i: {"mib": mib, "streams": i not in headless} for i in range(count)}


def place(gpus, want, gpu_map=None, current=None, exclusive=False, limit=8):
    return placement.place(gpus, want, gpu_map or {}, current or {}, exclusive, limit)


def test_equal_gpus_take_instances_in_turn():
    placed, errors, warnings = place([gpu(0, mib=46068), gpu(1, mib=46068)], needs(4))
    assert (placed, errors, warnings) == ({0: 0, 1: 1, 2: 0, 3: 1}, [], [])


def test_the_gpu_with_the_most_memory_left_comes_first():
    """Several per large GPU: a 48 GB GPU takes three 12 GiB instances before a 24 GB one takes its first."""
    gpus = [gpu(0), gpu(1, "NVIDIA RTX 6000 Ada Generation", 49140)]
    placed, errors, _warnings = place(gpus, needs(4, mib=12288))
    assert errors == [] and placed == {0: 1, 1: 1, 2: 1, 3: 0}
    # memory other processes hold is not free
    placed, _errors, _warnings = place([gpu(0), gpu(1, mib=49140, others=30000)], needs(2, mib=12288))
    assert placed == {0: 0, 1: 1}


def test_streams_only_where_an_encoder_is_and_headless_anywhere():
    gpus = [h100(0), h100(1), gpu(2), gpu(3), gpu(4), gpu(5)]
    placed, errors, warnings = place(gpus, needs(6, headless=(4, 5)))
    assert errors == [] and warnings == []
    assert placed == {0: 2, 1: 3, 2: 4, 3: 5, 4: 0, 5: 1}


def test_instances_stay_where_they_run_while_that_still_serves_them():
    gpus = [gpu(0, mib=46068), gpu(1, mib=46068)]
    placed, _errors, _warnings = place(gpus, needs(2), current={0: 1, 1: 1})
    assert placed == {0: 1, 1: 1}
    # a stream on a GPU found to have no encoder moves; one that no longer fits moves
    placed, _e, _w = place([h100(0), gpu(1)], needs(2, headless=(1,)), current={0: 0, 1: 0})
    assert placed == {0: 1, 1: 0}
    placed, _e, _w = place([gpu(0), gpu(1)], needs(2), current={0: 0, 1: 0})
    assert placed == {0: 0, 1: 1}
    # a GPU that is gone
    assert place([gpu(0)], needs(1), current={0: 3})[0] == {0: 0}


def test_a_host_without_an_encoder_refuses_streams_naming_them_and_the_model():
    placed, errors, _warnings = place([h100(0)], needs(3, headless=(2,)))
    assert placed == {}
    assert errors == [
        "isaac_sim_profile: instances 0, 1 stream, and no GPU of this host has a video encoder (NVIDIA H100 80GB "
        "HBM3: the driver's encode API says so; NVIDIA's data-centre GPUs such as the A100, H100 and H200 have "
        "none). Fix: run them without a stream (isaac_sim_profile: headless, or isaac_sim_instance_profiles: "
        "{0: headless}), or put streaming instances on hosts whose GPUs encode."
    ]


def test_what_does_not_fit_is_refused_with_the_numbers():
    placed, errors, _warnings = place([gpu(0), gpu(1, others=10000)], needs(3, mib=20480))
    assert placed == {}
    assert errors == [
        "isaac_sim_gpu_memory: instances 1, 2 need 20480 MiB of GPU memory each, and none of this host's GPUs has "
        "that much left (GPU 0 (NVIDIA L4): 23034 MiB, 522 reserved by the driver, 20480 taken by instance 0, "
        "2032 MiB left; GPU 1 (NVIDIA L4): 23034 MiB, 522 reserved by the driver, 10000 held by other processes, "
        "12512 MiB left). Fix: fewer instances (isaac_sim_instance_count), less GPU memory each "
        "(isaac_sim_gpu_memory, isaac_sim_instance_gpu_memory) if your scenes allow it, or stop what else holds "
        "GPU memory."
    ]


def test_the_map_is_obeyed_and_every_problem_said_at_once():
    gpus = [h100(0), gpu(1)]
    placed, errors, _warnings = place(gpus, needs(2, mib=20480, headless=(0,)), gpu_map={0: 0})
    assert errors == [] and placed == {0: 0, 1: 1}
    placed, errors, _warnings = place(gpus, needs(3, mib=20480), gpu_map={0: 0, 7: 1, 2: 9})
    assert placed == {}
    assert errors[0].startswith(
        "isaac_sim_gpu_map: instance 0 streams, and GPU 0 (NVIDIA H100 80GB HBM3) has no video encoder (the "
        "driver's encode API says so). Fix: map it to a GPU with one (1), or run it without a stream"
    )
    assert (
        errors[1]
        == "isaac_sim_gpu_map: instance 2 is mapped to GPU 9, this host has GPUs 0..1. Fix: map it to one of those."
    )
    assert errors[2].startswith("isaac_sim_gpu_map: instance 7 does not exist (instances are 0..2).")
    # instance 1 fits on the L4 alone: only the map's mistakes are said
    assert len(errors) == 3


def test_exclusive_gives_each_instance_a_gpu_of_its_own():
    gpus = [gpu(0), gpu(1), gpu(2)]
    assert place(gpus, needs(3, mib=1024), exclusive=True)[0] == {0: 0, 1: 1, 2: 2}
    errors = place(gpus, needs(4), exclusive=True)[1]
    assert errors[0].startswith("isaac_sim_instance_count: 4 instances with isaac_sim_gpu_exclusive: true need 4 GPUs")
    errors = place([h100(0), gpu(1)], needs(2), exclusive=True)[1]
    assert errors[0].startswith(
        "isaac_sim_gpu_exclusive: instance 1 needs a GPU of its own with 16384 MiB of GPU memory, and none of this "
        "host's GPUs with a video encoder is free and large enough"
    )


def test_an_encoder_not_known_is_said_not_refused():
    unknown = dict(gpu(0), encoder=None, encoder_why="libnvidia-encode.so.1 could not be loaded")
    placed, errors, warnings = place([unknown], needs(1))
    assert placed == {0: 0} and errors == []
    assert warnings == [
        "GPU 0 (NVIDIA L4) carries streaming instance 0, and whether it has a video encoder is not known "
        "(libnvidia-encode.so.1 could not be loaded). Without one they start but never stream."
    ]


def test_gpus_of_unknown_memory_take_instances_in_turn():
    placed, errors, _warnings = place([{"index": 0}, {"index": 1}], needs(3))
    assert errors == [] and placed == {0: 0, 1: 1, 2: 0}


def test_more_streams_than_a_consumer_gpu_allows_are_warned_about():
    gpus = [
        gpu(0, "NVIDIA GeForce RTX 4090", 24564, brand="GeForce"),
        gpu(1, "NVIDIA GeForce RTX 4090", 24564, brand="GeForce"),
    ]
    placed, errors, warnings = place(gpus, needs(3, mib=4096), limit=2)
    assert errors == [] and len(placed) == 3
    assert warnings == [
        "isaac_sim_gpu_consumer_encode_sessions: 3 streaming instances (0, 1, 2) run on this host's GeForce GPUs, "
        "and NVIDIA's driver allows 2 encode sessions at once on all of a system's consumer GPUs together: the "
        "streams beyond 2 fail to open. Fix: at most 2 streaming instances on them (the others headless), or GPUs "
        "of NVIDIA's professional lines."
    ]
    assert place(gpus, needs(3, mib=4096, headless=(2,)), limit=2)[2] == []
    assert place(gpus, needs(3, mib=4096))[2] == []


def test_no_gpu_says_what_nvidia_smi_said_and_unknown_memory_is_warned_about():
    errors = placement.place(
        [], needs(1), {}, {}, False, 8, "Failed to initialize NVML: Driver/library version mismatch"
    )[1]
    assert "(nvidia-smi answered: Failed to initialize NVML: Driver/library version mismatch)" in errors[0]
    warnings = place([{"index": 0, "encoder": True}], needs(1))[2]
    assert warnings == [
        "GPU 0 (unknown model): memory not known (nvidia-smi gave none), so instances were placed there by count, "
        "not by the GPU memory they need."
    ]


def test_every_geforce_and_titan_brand_is_a_consumer_gpu():
    gpus = [
        gpu(0, "NVIDIA GeForce RTX 4090", 24564, brand="GeForce RTX"),
        gpu(1, "NVIDIA TITAN RTX", 24576, brand="Titan RTX"),
    ]
    assert len(place(gpus, needs(3, mib=4096), limit=2)[2]) == 1
