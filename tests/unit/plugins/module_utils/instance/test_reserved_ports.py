"""The instances' ports kept out of the ephemeral range: what the kernel and our sysctl.d file hold."""

from ansible_collections.isaacsim.fleet.plugins.module_utils.instance import reserved_ports as rp


def test_the_kernels_form_reads_and_writes_back_the_same():
    assert rp.parse("8080,49100-49103\n") == {8080, 49100, 49101, 49102, 49103}
    assert rp.render({49103, 49100, 49101, 49102, 8080, 47998}) == "8080,47998,49100-49103"
    assert rp.parse("") == set() and rp.render([]) == ""
    assert rp.parse("x,1-y,5") == {5}  # a malformed part is skipped, not guessed


def test_a_host_with_nothing_reserved_gets_the_instances_ports_and_a_file_that_says_they_are_ours():
    value, added = rp.wanted("\n", None, [49100, 49101, 47998])
    assert value == added == {49100, 49101, 47998}
    text = rp.conf(value, added, "managed")
    assert f"{rp.KEY} = 47998,49100-49101\n" in text and rp.ours(text) == added


def test_the_hosts_own_reservation_is_kept_and_never_claimed():
    value, added = rp.wanted("9000-9001,49100", None, [49100, 49101])
    assert value == {9000, 9001, 49100, 49101} and added == {49101}
    # later the instances leave: only what we added goes
    value, added = rp.wanted(rp.render(value), rp.conf(value, added, "m"), [])
    assert value == {9000, 9001, 49100} and added == set() and rp.conf(value, added, "m") is None


def test_a_port_layout_change_grows_first_and_lets_the_old_ports_go_at_the_end():
    first = rp.conf({49100, 49101}, {49100, 49101}, "m")
    value, added = rp.wanted("49100-49101", first, [49104, 49105], grow=True)
    assert value == added == {49100, 49101, 49104, 49105}
    value, added = rp.wanted(rp.render(value), rp.conf(value, added, "m"), [49104, 49105])
    assert value == added == {49104, 49105}


def test_a_rerun_changes_nothing():
    value, added = rp.wanted("9000", None, [49100])
    runtime, text = rp.render(value), rp.conf(value, added, "m")
    assert rp.wanted(runtime, text, [49100]) == (value, added)


def test_a_port_the_host_stopped_reserving_is_not_ours_to_keep():
    # someone cleared the kernel's value by hand: our file's record counts only what is still there
    value, added = rp.wanted("", rp.conf({49100}, {49100}, "m"), [])
    assert value == added == set()
