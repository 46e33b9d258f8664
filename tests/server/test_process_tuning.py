"""The loop process's tuning on the real clock (``server/clock.py``): the idle CPUs' wake-up
latency request, held while its file stays open and withdrawn when it closes; where the clock
thread ticks and where the loop's Python thread runs."""
from __future__ import annotations

import os
import struct

import pytest
from hypothesis import given
from hypothesis import strategies as st

from hapticproxy.server.clock import CPU_DMA_LATENCY, HeldCpuLatency, clock_cpus, hold_cpu_latency, parse_cpu_latency


def test_the_request_is_the_value_as_a_native_int_and_lasts_while_the_file_is_open(tmp_path):
    path = tmp_path / "qos"
    path.write_bytes(b"")
    fd, why = hold_cpu_latency(7, str(path))
    assert fd is not None and why == ""
    try:
        os.fstat(fd)  # still open: the request stands
        assert struct.unpack("i", path.read_bytes()) == (7,)
    finally:
        os.close(fd)


def test_a_request_that_cannot_be_made_says_why_and_holds_nothing(tmp_path):
    fd, why = hold_cpu_latency(0, str(tmp_path / "missing"))
    assert fd is None and "missing" in why and "No such file" in why
    ro = tmp_path / "ro"
    ro.write_bytes(b"")
    os.chmod(ro, 0o400)
    if os.geteuid() != 0:  # root writes a read-only file anyway
        fd, why = hold_cpu_latency(0, str(ro))
        assert fd is None and "ro" in why


@pytest.mark.skipif(not os.access(CPU_DMA_LATENCY, os.R_OK | os.W_OK), reason="no PM QoS device to ask")
def test_the_kernel_keeps_the_request_until_it_is_closed():
    """The device reads back the latency in force: the smallest request any process holds."""
    def in_force() -> int:
        with open(CPU_DMA_LATENCY, "rb") as f:
            return struct.unpack("i", f.read(4))[0]

    before = in_force()
    fd, why = hold_cpu_latency(0)
    assert fd is not None, why
    try:
        assert in_force() == 0
    finally:
        os.close(fd)
    assert in_force() == before


@given(allowed=st.frozensets(st.integers(0, 63), min_size=1, max_size=8),
       setting=st.one_of(st.just("auto"), st.just(-1), st.integers(0, 63)))
def test_the_clock_cpu_contract(allowed, setting):
    cpu, others, why = clock_cpus(setting, allowed)
    if cpu is None:
        assert others is None
        # nothing pinned: asked for, one CPU only, or a CPU the process may not use (said why)
        assert (setting == -1 or len(allowed) < 2) == (why == "")
        if why:
            assert setting not in allowed and str(setting) in why
    else:
        assert len(allowed) >= 2 and setting != -1
        assert cpu in allowed and others == allowed - {cpu} and others and cpu not in others
        assert cpu == (max(allowed) if setting == "auto" else setting) and why == ""


def test_auto_takes_the_highest_cpu_and_leaves_python_the_rest():
    assert clock_cpus("auto", {0, 1}) == (1, frozenset({0}), "")
    assert clock_cpus("auto", {2, 5, 7}) == (7, frozenset({2, 5}), "")
    assert clock_cpus(0, {0, 1}) == (0, frozenset({1}), "")
    assert clock_cpus("auto", {3}) == (None, None, "")


def test_a_command_lines_latency_is_off_or_whole_us_up_to_1000():
    assert parse_cpu_latency("off") is None and parse_cpu_latency("0") == 0 and parse_cpu_latency("1000") == 1000
    for bad in ("-1", "1001", "x", "2.5", ""):
        with pytest.raises(ValueError, match="off or a whole number"):
            parse_cpu_latency(bad)


def test_nothing_asked_holds_nothing():
    with HeldCpuLatency(None) as q:
        assert q.held is None and q.fd is None and q.why == ""


def test_a_refused_request_holds_nothing_and_says_why(tmp_path):
    with HeldCpuLatency(0, str(tmp_path / "missing")) as q:
        assert q.held is None and q.fd is None and "missing" in q.why
    path = tmp_path / "qos"
    path.write_bytes(b"")
    with HeldCpuLatency(5, str(path)) as q:
        assert q.held == 5 and q.why == "" and struct.unpack("i", path.read_bytes()) == (5,)
    assert q.fd is None


@pytest.mark.skipif(not os.access(CPU_DMA_LATENCY, os.R_OK | os.W_OK), reason="no PM QoS device to ask")
def test_the_with_block_holds_the_request_and_withdraws_it():
    def in_force() -> int:
        with open(CPU_DMA_LATENCY, "rb") as f:
            return struct.unpack("i", f.read(4))[0]

    before = in_force()
    with HeldCpuLatency(0) as q:
        assert q.held == 0 and in_force() == 0
    assert q.fd is None and in_force() == before
