"""A stalled loop (the OS did not run it for 50-250 ms) in simulated time.

The device keeps its own watchdog (50 ms) and keeps moving while the loop does not run, the hand
pushing on the dead handle (``WatchdogDevice``). Promises: a stall before anything is rendered
never faults; a stall while engaged cuts the output (the device's watchdog), holds the proxy
(nothing drags it into the floor meanwhile) and recovers by itself through the normal ramp-in
once the loop has been on time for ``safety.stall_recover_s``, without a kick; more than
``safety.stall_trips_max`` trips within ``safety.stall_window_s`` latch until a re-arm; every
transition is in the transition log with its reason.
"""
from __future__ import annotations

import numpy as np
import pytest
from server_harness import Rig, WatchdogDevice, make_settings

from hapticproxy.server import control as ctl
from hapticproxy.server.clock import SimClock
from hapticproxy.server.lifecycle import Fault, Reason
from hapticproxy.server.shm import LS, TEL
from hapticproxy.testing.cleanup import made_then_ended

PUSH = lambda t: (0.0, -0.5, 0.0)  # noqa: E731 - a pure force hand pushing onto the floor


def _rig(**sections):
    clock = SimClock(start_ns=1_000_000_000)
    settings = make_settings(**sections)
    dev = WatchdogDevice(clock, hand=PUSH, period_s=settings.period_ns * 1e-9)
    return Rig(settings, dev, {"start_pose": (0.0, 0.012, 0.0)}, clock=clock)


def _reasons(loop):
    return [Reason(r[4]) for r in loop.shared.transitions_since(0)]


@pytest.fixture
def rig():
    yield from made_then_ended(_rig)


@pytest.mark.parametrize("stall_ms", [60, 120, 250])
def test_a_stall_before_engagement_never_faults(rig, stall_ms):
    r = rig()
    r.env.alive = False
    r.run(0.2)
    r.clock.stall(stall_ms * 1_000_000)
    rows = r.run(0.3)
    assert r.device.trips == 1                      # the device's watchdog did cut it
    assert r.loop.stall_trips == 1
    assert not np.any(rows[:, TEL["loop_state"]] == LS["fault"])
    assert r.loop.state_name == "idle" and r.device.enabled
    assert Reason.STALL_IDLE in _reasons(r.loop)
    r.env.alive = True                              # a client then engages as usual
    r.run(2.0)
    assert r.loop.state_name == "engaged"
    assert abs(r.device.commands[-1][1] - 0.5) < 0.05


@pytest.mark.parametrize("stall_ms", [60, 120, 250])
def test_a_stall_while_engaged_recovers_by_itself_without_a_kick(rig, stall_ms):
    r = rig()
    r.run(3.0)
    assert abs(r.device.commands[-1][1] - 0.5) < 0.02
    proxy_y = r.loop.ctrl.cs[ctl.CS_PPOSE + 1]  # where the proxy rests on the floor
    n0 = len(r.device.commands)
    r.clock.stall(stall_ms * 1_000_000)
    rows = r.run(0.2)
    assert r.loop.state_name == "fault" and r.loop.fault == Fault.STALL
    assert r.loop.stall_trips == 1
    # held: the hand pushed the dead handle into the floor, the proxy did not follow
    assert np.all(np.abs(rows[:, TEL["proxy_y"]] - proxy_y) < 1e-6)
    assert rows[-1, TEL["dev_y"]] < proxy_y - 0.005
    r.run(0.5)                                      # on time for stall_recover_s (0.5 s) ...
    assert r.loop.state_name == "engaged"           # ... then the force ramps back in by itself
    assert r.loop.stall_recoveries == 1
    r.run(2.5)
    fy = np.array(r.device.commands[n0:])[:, 1]
    assert np.max(np.abs(fy)) <= 0.5 + 1.0          # never more than the steady force + 1 N
    assert abs(fy[-1] - 0.5) < 0.02                 # and the contact is rendered again
    steps = np.abs(np.diff(fy))
    assert np.max(steps) <= r.loop.ctrl.force_rate_n_per_step + 1e-12
    reasons = _reasons(r.loop)
    assert reasons[-2:] == [Reason.STALL, Reason.RECOVERED]


def test_the_stall_recovery_waits_until_the_loop_is_on_time(rig):
    r = rig(safety={"stall_recover_s": 0.3})
    r.run(2.0)
    r.clock.stall(80_000_000)
    r.run(0.2)
    for _ in range(3):                              # stalled again and again: no recovery yet
        r.clock.stall(30_000_000)                   # (each shorter than the device's watchdog)
        r.run(0.2)                                  # 0.2 s on time < 0.3 s
        assert r.loop.state_name == "fault"
    r.clock.stall(3_000_000)                        # a few missed deadlines are no stall: they do
    r.run(0.05)                                     # not restart the wait (0.25 s on time)
    assert r.loop.state_name == "fault"
    r.run(0.1)                                      # 0.35 s on time
    assert r.loop.state_name == "engaged"


class MidStepStallDevice(WatchdogDevice):
    """The loop process stopped inside a step, between its wake-up and the device read (where a
    SIGSTOP lands when steps are long, as on a loaded machine)."""

    stall_in_read_ns = 0

    def read(self, s):
        if self.stall_in_read_ns:
            self.clock.advance(self.stall_in_read_ns)
            self.stall_in_read_ns = 0
        return super().read(s)


def test_a_stall_inside_a_step_is_on_time_only_from_its_end():
    clock = SimClock(start_ns=1_000_000_000)
    settings = make_settings()
    dev = MidStepStallDevice(clock, hand=PUSH, period_s=settings.period_ns * 1e-9)
    r = Rig(settings, dev, {"start_pose": (0.0, 0.012, 0.0)}, clock=clock)
    try:
        r.run(2.0)
        assert r.loop.state_name == "engaged"
        dev.stall_in_read_ns = 120_000_000
        r.run(0.01)
        assert r.loop.state_name == "fault" and r.loop.fault == Fault.STALL
        r.run(0.47)                                 # 0.48 s after the stall's end: not yet
        assert r.loop.state_name == "fault"
        r.run(0.05)
        assert r.loop.state_name == "engaged" and r.loop.stall_recoveries == 1
    finally:
        r.close()


class LateDevice(WatchdogDevice):
    """A device program that was itself not running when the loop's stall ended: it finds the
    loop's new commands waiting and its watchdog never sees the gap (a remote device on a
    loaded machine)."""

    def _check(self):
        self._last_ns = self.clock.now_ns()
        return super()._check()


def _late_rig(**sections):
    clock = SimClock(start_ns=1_000_000_000)
    settings = make_settings(**sections)
    dev = LateDevice(clock, hand=PUSH, period_s=settings.period_ns * 1e-9)
    return Rig(settings, dev, {"start_pose": (0.0, 0.012, 0.0)}, clock=clock)


@pytest.fixture
def late_rig():
    yield from made_then_ended(_late_rig)


@pytest.mark.parametrize("device", ["watchdog", "late"])
def test_repeated_stalls_latch_until_rearmed(rig, late_rig, device):
    """Whether the device's watchdog saw the stalls or not (``LateDevice``)."""
    r = (rig if device == "watchdog" else late_rig)(safety={"stall_trips_max": 2, "stall_window_s": 10.0})
    r.run(2.0)
    for _ in range(2):
        r.clock.stall(70_000_000)
        r.run(1.5)
        assert r.loop.state_name == "engaged"
    r.clock.stall(70_000_000)
    r.run(2.0)
    assert r.loop.state_name == "fault" and r.loop.fault == Fault.STALLS_REPEATED and r.loop.stall_trips == 3
    assert np.all(np.array(r.device.commands[-1000:]) == 0.0)
    assert _reasons(r.loop)[-1] == Reason.STALLS_REPEATED
    assert r.loop.rearm()
    r.run(2.0)
    assert r.loop.state_name == "engaged"
    assert abs(r.device.commands[-1][1] - 0.5) < 0.02


def test_a_stall_the_device_did_not_see_trips_all_the_same(late_rig):
    r = late_rig()
    r.run(3.0)
    assert abs(r.device.commands[-1][1] - 0.5) < 0.02
    n0 = len(r.device.commands)
    r.clock.stall(80_000_000)
    r.run(0.2)
    assert r.device.trips == 0                      # the device's watchdog saw nothing
    assert r.loop.state_name == "fault" and r.loop.fault == Fault.STALL and r.loop.stall_trips == 1
    assert np.all(np.array(r.device.commands[-150:]) == 0.0)  # the loop cut it (as the device would have)
    r.run(3.0)
    assert r.loop.state_name == "engaged" and r.loop.stall_recoveries == 1
    fy = np.array(r.device.commands[n0:])[:, 1]
    assert np.max(np.abs(np.diff(fy))) <= 1.0 + 1e-9  # ramped back in: no step beyond the rate limit
    assert abs(fy[-1] - 0.5) < 0.02


def test_a_stall_while_the_last_one_recovers_counts(rig):
    """The device is off while a stall's recovery waits, so only the loop sees a new stall then:
    it is a trip of its own (and with stall_trips_max 1, the second latches)."""
    r = rig(safety={"stall_trips_max": 1, "stall_window_s": 60.0})
    r.run(2.0)
    r.clock.stall(80_000_000)
    r.run(0.2)
    assert r.loop.fault == Fault.STALL and r.loop.stall_trips == 1
    r.clock.stall(80_000_000)
    r.run(0.2)
    assert r.loop.state_name == "fault" and r.loop.fault == Fault.STALLS_REPEATED and r.loop.stall_trips == 2
    r.run(2.0)
    assert r.loop.state_name == "fault"             # latched until a re-arm


def test_stall_trips_outside_the_window_do_not_add_up(rig):
    r = rig(safety={"stall_trips_max": 1, "stall_window_s": 2.0})
    r.run(2.0)
    for _ in range(3):
        r.clock.stall(70_000_000)
        r.run(2.5)                                  # each trip older than the window by the next
        assert r.loop.state_name == "engaged"
    assert r.loop.stall_trips == 3 and r.loop.stall_recoveries == 3


def test_a_late_step_that_trips_nothing_is_not_a_fault(rig):
    r = rig()
    r.run(2.0)
    r.clock.stall(20_000_000)                       # shorter than the device's watchdog
    r.run(0.5)
    assert r.loop.state_name == "engaged" and r.loop.stall_trips == 0


def test_a_watchdog_trip_without_a_stall_latches(rig):
    """The device's watchdog tripping while the loop was on time is the device's (or its link's)
    fault, not the loop's: it latches as a device fault."""
    r = rig()
    r.run(2.0)
    r.device._fault = 2                             # DEV_FAULT_WATCHDOG, the loop on time
    r.run(1.0)
    assert r.loop.state_name == "fault" and r.loop.fault == Fault.DEVICE
    assert r.loop.stall_trips == 0


def test_the_engine_is_told_the_server_state_in_every_acknowledgement(rig):
    from hapticproxy.protocol.vocab import ServerState

    r = rig()
    seen = []

    def on_step(_):
        p = r.env.last_proxy
        if p is not None and (not seen or seen[-1] != p.server_state):
            seen.append(p.server_state)

    r.run(2.0, on_step=on_step)
    r.clock.stall(80_000_000)
    r.run(1.5, on_step=on_step)                     # fault, then recovered
    r.env.alive = False
    r.run(0.3, on_step=on_step)                     # silent: the acks stop with the updates
    assert seen == [ServerState.ENGAGED, ServerState.FAULT, ServerState.ENGAGED], seen
