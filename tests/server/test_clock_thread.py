"""``[loop] protocol_thread``: the tick in a clock thread of its own (``servo.run_clock``), the
protocol, the lifecycle and housekeeping on the Python thread beside it, sharing the tick's arrays
through one lock word.

The clock thread's period (``servo.clock_tick``) is a pure function of the words and arrays it is
given, so its contract is tested by calling it on a real loop's arrays with a chosen ``now``:
nothing here asserts a time. What it promises: with the lock free it ticks and counts the tick;
with the lock held by Python it ticks nothing, counts the tick held and keeps the periods it
missed for the next tick run; the environment's silence starts the fade in the tick itself and
the rows say "fading" from that tick; a gap between ticks longer than the stall gap is reported
to Python with its end, and the environment's silence counts from that end; a gap as long as the
device's watchdog cuts the output at once. Python's side: a fade the tick started is a transition
before an update that arrived meanwhile resumes from it. The whole server with a clock thread runs
the fault and lifecycle cases of ``tests/faults/test_bench_faults.py`` (``clock-thread``).
"""
from __future__ import annotations

import threading
import time
from contextlib import contextmanager

import numpy as np
import pytest
from server_harness import Rig, WatchdogDevice, make_settings, receive_update, tick_once

from hapticproxy.server import control as ctl
from hapticproxy.server import safety as sf
from hapticproxy.server import servo, tick
from hapticproxy.server.clock import MonotonicClock, SimClock
from hapticproxy.server.lifecycle import LS, Fault, Reason
from hapticproxy.server.loop import HapticLoop
from hapticproxy.server.shm import ST, TEL
from hapticproxy.testing.cleanup import made_then_ended



@pytest.fixture
def armed():
    """A real loop on the monotonic clock (started, idle), bound to a clock thread's block that no
    thread runs: the test calls ``clock_tick`` itself."""
    lp = HapticLoop.build(make_settings(loop={"protocol_thread": True}), clock=MonotonicClock(spin_ns=20_000))
    try:
        lp.warm_up()
        lp.start()
        b = servo.ServoBinding(lp.period_ns)
        b.block[servo.SB_TK] = lp.tk.ctypes.data
        b.block[servo.SB_CMD] = lp._wcmd.ctypes.data
        b.bind(lp._T)
        lp.tk[tick.TK_DEV_WD_NS] = 2 * int(lp.tk[tick.TK_STALL_GAP_NS])  # the device's watchdog
        # each tick ends at its wake-up (the wake-ups the tests choose, not the wall clock's)
        lp.tk[tick.TK_SIMULATED] = 1
        lp.tk[tick.TK_SIM_COST_NS] = 0
        yield lp, b
    finally:
        lp.close()


def _now(lp, after_ns=0):
    """A wake-up one period after the loop's last tick (plus ``after_ns``)."""
    return int(lp.tk[tick.TK_LAST_WRITE_NS]) + lp.period_ns + after_ns


def test_the_lock_free_it_ticks_and_counts_the_tick(armed):
    lp, b = armed
    tk = lp.tk
    n0, ticks0 = int(b.block[servo.SB_TICKS]), int(tk[tick.TK_TICKS])
    last = int(tk[tick.TK_LAST_WRITE_NS])
    now = _now(lp)
    servo.clock_tick(b.block, tk, now, 0, 0)
    assert int(b.block[servo.SB_TICKS]) == n0 + 1 and int(tk[tick.TK_TICKS]) == ticks0 + 1
    assert int(b.block[servo.SB_HELD]) == 0
    # the tick wrote the device (its end; the one before moved back)
    assert int(tk[tick.TK_PREV_WRITE_NS]) == last and int(tk[tick.TK_LAST_WRITE_NS]) == now
    assert int(tk[tick.TK_LOCK]) == 0  # and let the lock go
    assert int(tk[tick.TK_STALL_SEEN]) == 0


def test_the_lock_held_by_python_nothing_ticks_and_missed_periods_wait(armed):
    lp, b = armed
    tk = lp.tk
    ticks0 = int(tk[tick.TK_TICKS])
    last = int(tk[tick.TK_LAST_WRITE_NS])
    missed0 = float(lp.shared.status[ST["missed_deadlines"]])
    skipped0 = float(lp.ctrl.cs[ctl.CS_SKIPPED])
    tk[tick.TK_LOCK] = 2  # Python has it
    servo.clock_tick(b.block, tk, _now(lp), 0, 2)
    servo.clock_tick(b.block, tk, _now(lp), 0, 1)
    assert int(b.block[servo.SB_HELD]) == 2 and int(tk[tick.TK_TICKS]) == ticks0
    assert int(tk[tick.TK_LAST_WRITE_NS]) == last  # the device was not ticked
    assert int(tk[tick.TK_LOCK]) == 2  # the lock is Python's still
    assert int(b.block[servo.SB_MISSED]) == 3
    assert float(lp.ctrl.cs[ctl.CS_SKIPPED]) == skipped0  # not counted while held
    tk[tick.TK_LOCK] = 0
    servo.clock_tick(b.block, tk, _now(lp), 0, 1)
    # the next tick run counts them: the safety filter's gain moves on over every skipped period
    assert int(b.block[servo.SB_MISSED]) == 0
    assert int(tk[tick.TK_TICKS]) == ticks0 + 1
    assert float(lp.shared.status[ST["missed_deadlines"]]) == missed0 + 4
    assert float(lp.ctrl.cs[ctl.CS_SKIPPED]) in (0.0, skipped0 + 4)  # (the tick's filter consumes it)


def test_silence_starts_the_fade_in_the_tick_and_the_rows_say_fading(armed):
    lp, b = armed
    tk, cs = lp.tk, lp.ctrl.cs
    tk[tick.TK_STATE] = LS["engaged"]  # as if a session had engaged
    cs[ctl.CS_TARGET] = 1.0
    now = _now(lp)
    tk[tick.TK_QUIET_SINCE_NS] = now - int(tk[tick.TK_WATCHDOG_NS])  # exactly the watchdog: not yet
    servo.clock_tick(b.block, tk, now, 0, 0)
    assert int(tk[tick.TK_STATE]) == LS["engaged"] and cs[ctl.CS_TARGET] == 1.0
    now = _now(lp)
    tk[tick.TK_QUIET_SINCE_NS] = now - int(tk[tick.TK_WATCHDOG_NS]) - 1
    servo.clock_tick(b.block, tk, now, 0, 0)
    assert int(tk[tick.TK_STATE]) == LS["fading"] and cs[ctl.CS_TARGET] == 0.0
    head = int(lp.shared.head[0])
    assert lp.shared.ring[(head - 1) % lp.shared.ring_rows, TEL["loop_state"]] == LS["fading"]


def test_a_gap_longer_than_the_stall_gap_is_reported_with_its_end(armed):
    lp, b = armed
    tk, cs = lp.tk, lp.ctrl.cs
    gap = int(tk[tick.TK_STALL_GAP_NS])
    last = int(tk[tick.TK_LAST_WRITE_NS])
    tk[tick.TK_QUIET_SINCE_NS] = last
    now = last + gap  # not longer: no stall
    servo.clock_tick(b.block, tk, now, 0, 0)
    assert int(tk[tick.TK_STALL_SEEN]) == 0
    last = int(tk[tick.TK_LAST_WRITE_NS])
    cs[ctl.CS_SAFETY + sf.SS_GAIN] = 1.0
    cs[ctl.CS_TARGET] = 1.0
    now = last + gap + 1  # longer, but shorter than the device's watchdog
    assert gap + 1 < int(tk[tick.TK_DEV_WD_NS])
    servo.clock_tick(b.block, tk, now, 0, 0)
    assert int(tk[tick.TK_STALL_SEEN]) == 1
    assert int(tk[tick.TK_STALL_WAKE_NS]) == now and int(tk[tick.TK_STALL_FROM_NS]) == last
    assert int(tk[tick.TK_QUIET_SINCE_NS]) == now  # the silence counts from the stall's end
    assert cs[ctl.CS_TARGET] == 1.0  # not cut: the device's watchdog did not trip


def test_a_gap_as_long_as_the_device_watchdog_cuts_at_once(armed):
    lp, b = armed
    tk, cs = lp.tk, lp.ctrl.cs
    last = int(tk[tick.TK_LAST_WRITE_NS])
    cs[ctl.CS_SAFETY + sf.SS_GAIN] = 1.0
    cs[ctl.CS_SAFETY + sf.SS_TARGET] = 1.0
    cs[ctl.CS_TARGET] = 1.0
    servo.clock_tick(b.block, tk, last + int(tk[tick.TK_DEV_WD_NS]), 0, 0)
    assert int(tk[tick.TK_STALL_SEEN]) == 1
    # the safety filter starts again from zero gain, and nothing ramps it back in by itself
    assert cs[ctl.CS_TARGET] == 0.0 and cs[ctl.CS_SAFETY + sf.SS_TARGET] == 0.0
    assert cs[ctl.CS_SAFETY + sf.SS_GAIN] == 0.0
    assert not np.any(lp.ctrl.cmd)


def test_python_takes_the_lock_in_the_gap_after_a_tick(armed):
    lp, b = armed
    tk, blk = lp.tk, b.block
    period = lp.period_ns
    # after a tick: the next one is due more than the room Python asks for away: taken at once
    blk[servo.SB_NEXT_NS] = MonotonicClock().now_ns() + 100 * period
    waited = servo.lock_between_ticks(tk, blk, period // 2, 10**9)
    assert int(tk[tick.TK_LOCK]) == 2 and waited < 10**9
    servo.unlock(tk)
    # the next tick is due sooner than that (or is under way: due already): Python waits, here
    # until its patience ends
    for ahead in (period // 4, -period // 10):
        blk[servo.SB_NEXT_NS] = MonotonicClock().now_ns() + ahead
        waited = servo.lock_between_ticks(tk, blk, period // 2, 2 * period)
        assert waited > 2 * period and int(tk[tick.TK_LOCK]) == 2
        servo.unlock(tk)


def test_each_tick_says_when_the_next_is_due(armed):
    """What ``lock_between_ticks`` reads: after a run tick and after a held one alike, the next
    deadline (the clock thread moved it on as it woke)."""
    lp, b = armed
    tk, blk = lp.tk, b.block
    for lock_word in (0, 2):
        tk[tick.TK_LOCK] = lock_word
        now = _now(lp)
        tk[tick.TK_DEADLINE_NS] = now + lp.period_ns // 3  # the thread woke 2/3 of a period late
        servo.clock_tick(blk, tk, now, 0, 0)
        assert int(blk[servo.SB_NEXT_NS]) == int(tk[tick.TK_DEADLINE_NS])
    tk[tick.TK_LOCK] = 0


def test_a_fade_the_tick_started_is_a_transition_before_an_update_resumes(rig_factory):
    """Simulated time: the loop engaged, the clock thread has started the silence fade (target
    zero, rows fading) and an update arrives before Python's next pass. It is staged and applied
    without the lock, but taking it waits for a pass with the lock, which makes the fade the
    transition it is, then the update resumes it: engaged, target 1. Without the first, the loop
    would stay "engaged" with its target at zero, the force fading out for good."""
    r = rig_factory()
    r.run(1.0)
    lp = r.loop
    proto = lp.proto
    assert lp.state_name == "engaged"
    lp.tk[tick.TK_STATE] = LS["fading"]  # what servo._locked_tick does on silence
    lp.ctrl.cs[ctl.CS_TARGET] = 0.0
    upd = receive_update(r)
    now = r.clock.now_ns()
    assert proto.exchange(now, locked=False) is True and proto._staged is upd  # staged, no lock
    tick_once(lp, now)
    assert proto.exchange(now, locked=False) is False and proto.needs_lock  # taking it: the lock's
    assert proto._staged is upd and lp.state_name == "engaged"
    lp.threaded_pass(now, False)
    reasons = [Reason(t[4]) for t in lp.shared.transitions_since(0)]
    assert reasons[-2:] == [Reason.SILENT, Reason.RESUMED]
    assert lp.state_name == "engaged" and lp.ctrl.cs[ctl.CS_TARGET] == 1.0
    assert int(lp.tk[tick.TK_STATE]) == LS["engaged"]
    assert proto._staged is None


def test_an_update_waits_in_the_decoder_while_the_slot_is_the_ticks(rig_factory):
    """Simulated time, beside a ticking thread: an update is staged in the model's slot without
    the lock; one received while the tick has not applied it waits (staging it would overwrite
    the slot the tick reads); the pass after the tick applied the first takes it, sends its
    acknowledgement (from the state the tick left in the slot) and stages the second."""
    r = rig_factory()
    r.run(1.0)
    lp, proto = r.loop, r.loop.proto
    tk = lp.tk
    first = receive_update(r)
    heard = r.clock.now_ns()
    assert proto.exchange(heard, locked=False) and proto._staged is first and proto._pending is None
    seq = int(tk[tick.TK_UPD_SEQ])
    assert seq == int(tk[tick.TK_UPD_DONE]) + 1
    second = receive_update(r)
    assert second is not first
    now = r.clock.now_ns()
    assert proto.exchange(now, locked=False) is False  # the slot is the tick's: nothing changes
    assert proto._staged is first and proto._pending is second and not proto.needs_lock
    updates, acks = proto.updates, proto.acks
    tick_once(lp, now)
    assert int(tk[tick.TK_UPD_DONE]) == seq and int(tk[tick.TK_UPD_CODE]) == 0
    # applied: counted by the tick, the silence counted from when it was received
    assert int(tk[tick.TK_UPDATES]) == updates + 1 and int(tk[tick.TK_QUIET_SINCE_NS]) >= heard
    assert proto.exchange(now, locked=False) is True
    assert proto.updates == updates + 1 and proto.acks == acks + 1 and proto.last_update_ns == heard
    assert proto._staged is second and proto._pending is None and int(tk[tick.TK_UPD_SEQ]) == seq + 1


@pytest.fixture
def pushing_rig():
    def make():
        clock = SimClock(start_ns=1_000_000_000)
        settings = make_settings()
        dev = WatchdogDevice(clock, hand=lambda t: (0.0, -0.5, 0.0), period_s=settings.period_ns * 1e-9)
        return Rig(settings, dev, {"start_pose": (0.0, 0.012, 0.0)}, clock=clock)

    yield from made_then_ended(make)


def _engaged_clock(pushing_rig):
    """An engaged loop in simulated time (a session, a hand pushing the tool onto the floor),
    bound to a clock thread's block that no thread runs: the test calls ``clock_tick`` with
    chosen wake-ups."""
    r = pushing_rig()
    r.run(1.0)
    lp = r.loop
    assert lp.state_name == "engaged" and lp.ctrl.cs[ctl.CS_SAFETY + sf.SS_GAIN] == 1.0
    assert np.abs(lp.ctrl.cmd).max() > 0.1  # pushing on the floor
    b = servo.ServoBinding(lp.period_ns)
    b.block[servo.SB_TK] = lp.tk.ctypes.data
    b.block[servo.SB_CMD] = lp._wcmd.ctypes.data
    b.bind(lp._T)
    lp.tk[tick.TK_DEV_WD_NS] = 2 * int(lp.tk[tick.TK_STALL_GAP_NS])
    lp.tk[tick.TK_QUIET_SINCE_NS] = 1 << 62  # the environment is not what this test is about
    return r, b


def test_a_stall_as_long_as_the_device_watchdog_cuts_and_nothing_comes_back_by_itself(pushing_rig):
    r, b = _engaged_clock(pushing_rig)
    lp = r.loop
    tk, cs = lp.tk, lp.ctrl.cs
    last = int(tk[tick.TK_LAST_WRITE_NS])
    wd = int(tk[tick.TK_DEV_WD_NS])
    servo.clock_tick(b.block, tk, last + wd - 1, 0, 0)  # a stall, shorter than the watchdog: no cut
    assert int(tk[tick.TK_STALL_SEEN]) == 1 and cs[ctl.CS_SAFETY + sf.SS_GAIN] > 0.9
    last = int(tk[tick.TK_LAST_WRITE_NS])
    servo.clock_tick(b.block, tk, last + wd, 0, 0)  # as long as the watchdog: cut at once
    assert int(tk[tick.TK_STALL_SEEN]) == 2
    assert cs[ctl.CS_SAFETY + sf.SS_GAIN] == 0.0 and not np.any(lp.ctrl.cmd)
    for _ in range(200):  # and it stays cut until Python's stall recovery ramps it in
        now = int(tk[tick.TK_LAST_WRITE_NS]) + lp.period_ns
        servo.clock_tick(b.block, tk, now, 0, 0)
    assert cs[ctl.CS_SAFETY + sf.SS_GAIN] == 0.0 and not np.any(lp.ctrl.cmd)


_WARM_PROBE = """
import json, sys
sys.path.insert(0, sys.argv[1])
from server_harness import make_settings
from hapticproxy.server import servo
from hapticproxy.server.clock import MonotonicClock
from hapticproxy.server.loop import HapticLoop
lp = HapticLoop.build(make_settings(loop={"protocol_thread": True}), clock=MonotonicClock())
lp.warm_up()
print(json.dumps({n: len(getattr(servo, n).overloads) for n in ("run_clock", "lock", "unlock", "lock_between_ticks")}))
lp.close()
"""


def test_warm_up_compiles_what_the_clock_thread_and_its_python_side_call():
    """A fresh interpreter (nothing compiled or loaded yet): after ``warm_up`` every kernel the
    clock thread's start, its Python side and its stop call has its signature. A cold-cache
    fresh clone once compiled ``servo.lock`` as the thread started: the demo's loop faulted."""
    import json
    import subprocess
    import sys
    from pathlib import Path

    out = subprocess.run([sys.executable, "-c", _WARM_PROBE, str(Path(__file__).parent)], capture_output=True,
                         text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    counts = json.loads(out.stdout.strip().splitlines()[-1])
    assert all(n >= 1 for n in counts.values()), counts


def test_a_stall_inside_a_tick_is_reported_and_cut_like_one_between_ticks(pushing_rig):
    """The process stopped between the tick's device read and its write (simulated: the tick's
    own cost as long as the device's watchdog): the next tick's device read reports the device's
    watchdog with no gap between ticks, so the tick itself reports the stall (its read and its
    end) and cuts; Python then classifies it as a stall trip, which recovers by itself, not as a
    device fault, which latches. Python's pass runs before the clock thread has reported it
    first: it must not take the stall for the engine's silence."""
    r, b = _engaged_clock(pushing_rig)
    lp = r.loop
    tk, cs = lp.tk, lp.ctrl.cs
    wd = int(tk[tick.TK_DEV_WD_NS])
    lp.tk[tick.TK_QUIET_SINCE_NS] = int(tk[tick.TK_LAST_WRITE_NS])
    lp.proto.last_update_ns = int(tk[tick.TK_LAST_WRITE_NS])
    now = int(tk[tick.TK_LAST_WRITE_NS]) + lp.period_ns
    stall = max(wd, int(tk[tick.TK_WATCHDOG_NS])) + lp.period_ns  # past the engine's watchdog too
    tk[tick.TK_SIM_COST_NS] = stall  # the stall, inside the tick
    servo.clock_tick(b.block, tk, now, 0, 0)
    tk[tick.TK_SIM_COST_NS] = 0
    assert int(tk[tick.TK_STALL_SEEN]) == 1
    assert int(tk[tick.TK_STALL_FROM_NS]) == now and int(tk[tick.TK_STALL_WAKE_NS]) == now + stall
    assert int(tk[tick.TK_QUIET_SINCE_NS]) == now + stall
    assert cs[ctl.CS_SAFETY + sf.SS_GAIN] == 0.0
    # Python's pass, longer after the engine's last update than its watchdog (the stall): a stall
    # trip, no fading
    lp.threaded_pass(now + stall + lp.period_ns, False)
    assert lp.state_name == "fault" and lp.fault == Fault.STALL and lp.stall_trips == 1
    assert Reason.SILENT not in [Reason(t[4]) for t in lp.shared.transitions_since(0)]


def test_python_before_the_clock_thread_after_a_stall_does_not_take_it_for_silence(pushing_rig):
    """Both threads stopped 110 ms (longer than the engine's watchdog); Python's pass runs first,
    before the clock thread's first tick has reported the stall: the engine was not silent, the
    loop was stopped, so no fade; the tick then reports it, and it is a stall trip."""
    r, b = _engaged_clock(pushing_rig)
    lp = r.loop
    tk = lp.tk
    last = int(tk[tick.TK_LAST_WRITE_NS])
    lp.tk[tick.TK_QUIET_SINCE_NS] = last
    lp.proto.last_update_ns = last
    end = last + int(tk[tick.TK_WATCHDOG_NS]) + 10_000_000
    lp.threaded_pass(end, False)
    assert lp.state_name == "engaged"
    servo.clock_tick(b.block, tk, end + 1000, 0, 0)
    lp.threaded_pass(end + 2000, False)
    assert lp.state_name == "fault" and lp.fault == Fault.STALL
    assert Reason.SILENT not in [Reason(t[4]) for t in lp.shared.transitions_since(0)]


@contextmanager
def _loop_thread(url, duration_s, no_housekeeping=False):
    """The real loop with a clock thread on the monotonic clock, run by a thread of its own for
    ``duration_s`` (stopped and closed at the end whatever happened): ``(loop, thread)``."""
    lp = HapticLoop.build(make_settings(loop={"protocol_thread": True}, transport={"url": url}),
                          clock=MonotonicClock())
    th = None
    try:
        lp.warm_up()
        lp.start()
        if no_housekeeping:
            lp.tk[tick.TK_HK_EVERY] = 1 << 40
        th = threading.Thread(target=lp.run, kwargs={"duration_s": duration_s}, daemon=True)
        th.start()
        yield lp, th
    finally:
        if th is not None and th.is_alive():
            lp.request_stop()
            th.join(10)
        lp.close()


def _engine(url, seed):
    from hapticproxy.clients.runner import ClientRunner
    from hapticproxy.clients.stub_engine import StubEngine

    return ClientRunner(StubEngine(seed=seed), url, scene="testbed", realtime=True, connect_timeout_s=10.0)


def _pump(runner, until, seconds=10.0):
    """Run the engine (real time) until ``until()`` or ``seconds``; ``until()``."""
    end = time.monotonic() + seconds
    while not until() and time.monotonic() < end:
        wait = runner.poll()
        if wait > 0:
            time.sleep(min(wait, 0.002))
    return until()


def _wait_for(cond, seconds=10.0):
    end = time.monotonic() + seconds
    while not cond() and time.monotonic() < end:
        time.sleep(0.01)
    return cond()


def test_updates_and_housekeeping_with_nothing_to_do_take_no_lock():
    """The real loop with a clock thread on the monotonic clock, housekeeping every 10 ms: an
    engine's session engages and its updates are applied and acknowledged through the update
    slot; the Python thread takes the tick's lock for far fewer passes than there are updates
    (before the slot: one per update and one per housekeeping, 100 a second). Counts only."""
    url = "mem://clock-thread-no-lock"
    with _loop_thread(url, 3.0) as (lp, th):
        runner = _engine(url, 2)
        try:
            _pump(runner, lambda: runner.stats()["steps"] >= 20, 60.0)  # engaged by now
            p0, u0 = lp.lock_passes, lp.updates
            _pump(runner, lambda: runner.stats()["steps"] >= 80, 60.0)
            passes = (lp.lock_passes - p0, lp.updates - u0, lp.state_name)
        finally:
            runner.close()
        th.join(20)
        assert not th.is_alive()
        n_passes, n_updates, state = passes
        assert state == "engaged" and n_updates >= 30, passes
        assert n_passes < n_updates / 4, passes


def test_an_update_brings_python_to_the_lock_by_itself():
    """The real loop with a clock thread on the monotonic clock and housekeeping switched off: only
    the session's first update brings the Python thread to the tick's lock (an engagement:
    ``TK_NEEDS_PYTHON`` through ``python_has_work``); the others go through the update slot. An
    engine's session engages, and its updates are applied and acknowledged (counts, no time
    asserted)."""
    url = "mem://clock-thread-updates"
    with _loop_thread(url, 3.0, no_housekeeping=True) as (lp, th):
        st = _engine(url, 1).run(max_steps=60)
        th.join(20)
        assert not th.is_alive()
        assert lp.servo is not None and lp.engagements == 1, (st, lp.counters())
        assert lp.updates >= 10 and lp.acks >= lp.updates - 1, (lp.updates, lp.acks)
        assert st["proxy_states"] >= 10


@pytest.mark.parametrize("stop_by", ["signal", "supervisor"])
def test_beside_the_clock_thread_housekeeping_takes_the_lock_when_it_has_something_to_do(stop_by):
    """Housekeeping takes the tick's lock only when it has something to do, and then it does it:
    a stall trip's fault recovers once the loop has been on time; a session that ended (Bye)
    fades it and the loop goes idle for the session's end, not the engine's silence; a
    supervisor's re-arm request is acknowledged at once even when there is nothing to re-arm (a
    request left pending would re-arm a later fault); a stop requested by a signal
    (``_stop_flag``) or by the supervisor (its control word) stops the loop. The real loop on the
    monotonic clock; counts and states only."""
    from hapticproxy.server.servo import lock, unlock
    from hapticproxy.server.shm import CT

    url = "mem://clock-thread-housekeeping"
    with _loop_thread(url, 60.0) as (lp, th):
        runner = _engine(url, 3)
        try:
            assert _pump(runner, lambda: runner.stats()["steps"] >= 30 and lp.state_name == "engaged"), lp.state_name
            # a stall trip (as the loop's own stall of the device's watchdog makes it): in fault,
            # recovered by housekeeping once the loop has been on time for stall_recover_s
            lock(lp.tk)
            try:
                lp.life.stall_ns = 80_000_000
                lp.life.on_stall_trip(lp.clock.now_ns(), own=True)
                lp.life.ontime_since = lp.clock.now_ns()
            finally:
                unlock(lp.tk)
            assert lp.state_name == "fault"
            assert _pump(runner, lambda: lp.state_name == "engaged" and lp.stall_recoveries == 1), lp.state_name
        finally:
            runner.close()  # Bye
        assert _wait_for(lambda: lp.state_name == "idle"), lp.state_name
        reasons = [Reason(t[4]) for t in lp.shared.transitions_since(0)]
        assert Reason.SESSION_ENDED in reasons and Reason.SILENT not in reasons, reasons
        ctrl = lp.shared.control
        ctrl[CT["rearm"]] += 1
        assert _wait_for(lambda: ctrl[CT["rearm_ack"]] == ctrl[CT["rearm"]])
        if stop_by == "signal":
            lp._stop_flag = True
        else:
            ctrl[CT["stop"]] += 1
        th.join(10)
        assert not th.is_alive() and lp.state_name == "stopped"
