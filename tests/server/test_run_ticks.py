"""The compiled loop that owns the clock (``tick.run_ticks``): it ticks by itself and hands back to
Python exactly when Python is needed, counted in ticks (the real clock paces it; nothing here
asserts a time). The loop is a real ``HapticLoop`` on the simulated device, armed and idle."""
from __future__ import annotations

import socket

import pytest
from server_harness import make_settings

from hapticproxy.server import tick
from hapticproxy.server.clock import MonotonicClock
from hapticproxy.server.devices.base import DEV_FAULT_WATCHDOG
from hapticproxy.server.devices.layout import DC_FAULT
from hapticproxy.server.loop import HapticLoop


def _loop(**sections):
    loop = HapticLoop.build(make_settings(**sections), clock=MonotonicClock(spin_ns=20_000))
    loop.warm_up()
    loop.start()
    loop.tk[tick.TK_HK_EVERY] = 1 << 40  # no housekeeping unless a test asks for it
    loop.tk[tick.TK_POLL_EVERY] = 1 << 40  # (the memory transport has no socket: polled by count)
    loop.tk[tick.TK_SPIN_NS] = 20_000
    loop.tk[tick.TK_DEADLINE_NS] = MonotonicClock().now_ns() + loop.period_ns
    loop.tk[tick.TK_LAST_WRITE_NS] = MonotonicClock().now_ns()
    return loop


@pytest.fixture
def loop():
    lp = _loop()
    try:
        yield lp
    finally:
        lp.close()


def _plain(lp, n_ticks):
    """Let the loop tick n_ticks times by itself: housekeeping due after that many."""
    tk = lp.tk
    tk[tick.TK_HK_COUNT] = 0
    tk[tick.TK_HK_EVERY] = n_ticks
    tk[tick.TK_LAST_WRITE_NS] = MonotonicClock().now_ns()
    tk[tick.TK_DEADLINE_NS] = MonotonicClock().now_ns() + lp.period_ns


def test_plain_ticks_run_without_python_until_housekeeping(loop):
    _plain(loop, 25)
    n0 = int(loop.tk[tick.TK_TICKS])
    head0 = int(loop.shared.head[0])
    assert tick.run_ticks_at(loop._desc_addr) == tick.EV_TICKED
    assert int(loop.tk[tick.TK_TICKS]) - n0 == 25
    assert int(loop.shared.head[0]) - head0 == 25  # each tick wrote its telemetry row
    assert loop.tk[tick.TK_RC] == 0


def test_a_step_with_python_work_is_handed_back_untouched(loop):
    _plain(loop, 1000)
    loop.tk[tick.TK_NEEDS_PYTHON] = 1
    n0 = int(loop.tk[tick.TK_TICKS])
    assert tick.run_ticks_at(loop._desc_addr) == tick.EV_STEP
    assert int(loop.tk[tick.TK_TICKS]) == n0  # not ticked: Python runs that step itself
    assert loop.tk[tick.TK_WAKE_NS] >= loop.tk[tick.TK_DEADLINE_NS] - loop.period_ns


def test_a_stall_is_handed_back_before_any_tick(loop):
    _plain(loop, 1000)
    loop.tk[tick.TK_LAST_WRITE_NS] -= 10 * loop.tk[tick.TK_STALL_GAP_NS]  # the loop did not run
    n0 = int(loop.tk[tick.TK_TICKS])
    assert tick.run_ticks_at(loop._desc_addr) == tick.EV_STEP
    assert int(loop.tk[tick.TK_TICKS]) == n0


def test_a_device_fault_is_handed_back_after_its_tick(loop):
    _plain(loop, 1000)
    loop.device._ctl[DC_FAULT] = DEV_FAULT_WATCHDOG
    n0 = int(loop.tk[tick.TK_TICKS])
    assert tick.run_ticks_at(loop._desc_addr) == tick.EV_TICKED
    assert int(loop.tk[tick.TK_TICKS]) == n0 + 1
    assert (int(loop.tk[tick.TK_RC]) >> 8) & 0xFF == DEV_FAULT_WATCHDOG


def test_a_waiting_datagram_is_handed_back_after_one_tick(loop):
    _plain(loop, 1000)
    a = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    a.bind(("127.0.0.1", 0))
    try:
        a.sendto(b"x", a.getsockname())
        loop.tk[tick.TK_FD] = a.fileno()
        n0 = int(loop.tk[tick.TK_TICKS])
        assert tick.run_ticks_at(loop._desc_addr) == tick.EV_TICKED
        assert int(loop.tk[tick.TK_TICKS]) == n0 + 1
        loop.tk[tick.TK_RX_PENDING] = 1  # a transport without a socket says so through this word
        loop.tk[tick.TK_FD] = -1
        assert tick.run_ticks_at(loop._desc_addr) == tick.EV_TICKED and int(loop.tk[tick.TK_TICKS]) == n0 + 2
    finally:
        loop.tk[tick.TK_FD] = -1
        a.close()


def test_environment_silence_while_engaged_is_handed_back(loop):
    _plain(loop, 1000)
    loop.tk[tick.TK_STATE] = tick.LS_ENGAGED
    loop.tk[tick.TK_QUIET_SINCE_NS] = int(loop.tk[tick.TK_DEADLINE_NS]) - 2 * int(loop.tk[tick.TK_WATCHDOG_NS])
    assert tick.run_ticks_at(loop._desc_addr) == tick.EV_STEP


def test_a_stop_request_returns_at_once(loop):
    loop.tk[tick.TK_STOP] = 1
    n0 = int(loop.tk[tick.TK_TICKS])
    assert tick.run_ticks_at(loop._desc_addr) == tick.EV_STOP and int(loop.tk[tick.TK_TICKS]) == n0


def test_the_spin_is_capped_at_its_share_of_the_period():
    """A calibrated spin longer than the period (276 us at 4 kHz on a loaded machine) would never
    let the thread sleep under SCHED_FIFO: the compiled loop caps it at ``SPIN_MAX_SHARE`` of the
    period (and the share leaves the thread asleep for a good part of every period)."""
    assert 0.25 <= tick.SPIN_MAX_SHARE <= 0.75
    lp = HapticLoop.build(make_settings(loop={"rate_hz": 4000.0}), clock=MonotonicClock(spin_ns=276_000))
    try:
        lp.warm_up()
        lp.start()
        lp.run(duration_s=0.02)
        assert int(lp.tk[tick.TK_SPIN_NS]) == int(lp.period_ns * tick.SPIN_MAX_SHARE) < 276_000
        assert int(lp.tk[tick.TK_TICKS]) > 0  # the compiled loop ticked
    finally:
        lp.close()


def test_a_transport_without_a_socket_is_polled_every_millisecond_of_ticks(loop):
    _plain(loop, 1000)
    loop.tk[tick.TK_FD] = -1
    loop.tk[tick.TK_POLL_COUNT] = 0
    loop.tk[tick.TK_POLL_EVERY] = 7
    n0 = int(loop.tk[tick.TK_TICKS])
    assert tick.run_ticks_at(loop._desc_addr) == tick.EV_TICKED
    assert int(loop.tk[tick.TK_TICKS]) - n0 == 7
    assert tick.new_words(250_000)[tick.TK_POLL_EVERY] == 4  # 4 kHz: every 4 ticks


def test_device_clocked_python_takes_the_lock_only_when_it_has_work():
    """The servo thread's ticks find the lock held only while Python has work: none of the
    reasons alone leaves it free, each reason alone takes it."""
    from hapticproxy.server.lifecycle import LS
    from hapticproxy.server.loop import python_has_work

    tk = tick.new_words(1_000_000)
    tk[tick.TK_STATE] = LS["engaged"]
    assert not python_has_work(tk, False, False)
    assert python_has_work(tk, True, False) and python_has_work(tk, False, True)
    for word, value in ((tick.TK_RC_STICKY, 1 << 8), (tick.TK_NEEDS_PYTHON, 1), (tick.TK_STATE, LS["fading"]),
                        (tick.TK_STATE, LS["stopping"]), (tick.TK_STALL_SEEN, 1)):
        w = tk.copy()
        w[word] = value
        assert python_has_work(w, False, False), word
    for quiet in ("idle", "fault", "engaged"):  # states that need nothing each millisecond
        w = tk.copy()
        w[tick.TK_STATE] = LS[quiet]
        assert not python_has_work(w, False, False), quiet
