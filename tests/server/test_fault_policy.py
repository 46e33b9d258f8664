"""``lifecycle.FAULT_POLICY``, one row at a time, in simulated time.

Every row of the table has a scenario here: a pushing hand holds the tool on a floor, the trouble
happens, and the test checks what the row promises: the output (``cut``: zero from the next
command on and the device disabled; ``fade``: the device stays on and the force falls to zero
within ``fade_s`` without a step beyond the rate limit; ``none``: nothing was rendered, nothing
is), the fault code and reason, and how force comes back (by itself, or only after a re-arm, then
ramped in without a kick)."""
from __future__ import annotations

import math

import numpy as np
import pytest
from server_harness import Rig, WatchdogDevice, make_settings

from hapticproxy.server.clock import SimClock
from hapticproxy.server.devices.base import (
    DEV_FAULT_DISABLED, DEV_FAULT_FROZEN, DEV_FAULT_HARDWARE, DEV_FAULT_LINK, DEV_FAULT_WATCHDOG, DEV_OK,
)
from hapticproxy.server.status import format_status
from hapticproxy.server.lifecycle import FAULT_POLICY, STALL_EXPLAINS_S, Fault, Reason
from hapticproxy.server.model.layout import DIVERGE_STEPS, K_OSC_RUN, S_QD, S_QDP
from hapticproxy.testing.cleanup import made_then_ended

PUSH_N = 0.5
PUSH = lambda t: (0.0, -PUSH_N, 0.0)  # noqa: E731 - a pure force hand pushing onto the floor
FAST = 3.0  # m/s: over the default 2 m/s limit


class FaultyDevice(WatchdogDevice):
    """A ``WatchdogDevice`` whose driver reports a fault code from ``fault_at_ns`` on (latched until
    ``enable``, as the contract says), and, if ``link_up_ns`` is set, reports a link that is not up
    (``DEV_FAULT_LINK``, not cleared by ``enable``) before then. ``speed`` adds a handle speed."""

    def __init__(self, clock, **kw):
        super().__init__(clock, **kw)
        self.fault_at_ns = None
        self.fault_code = DEV_OK
        self.link_up_ns = None
        self.speed = 0.0
        self.nan_at_ns = None
        self.frozen = None  # a position row: read reports it from now on (a sensor that stopped)

    def _injected(self):
        now = self.clock.now_ns()
        if self.link_up_ns is not None and now < self.link_up_ns:
            self._fault = DEV_FAULT_LINK
        elif self.fault_at_ns is not None and now >= self.fault_at_ns:
            self._fault = self.fault_code
            self.fault_at_ns = None
            if self.fault_code == DEV_FAULT_DISABLED:
                self._enabled = False
        return now

    def enable(self):
        super().enable()
        self._injected()

    def read(self, s):
        now = self._injected()
        rc = super().read(s)
        s[7] += self.speed
        if self.nan_at_ns is not None and now >= self.nan_at_ns:
            s[1] = math.nan
            self.nan_at_ns = None
        if self.frozen is not None:
            s[0:3] = self.frozen
            s[7:10] = 0.0
        return rc or self._fault

    def write(self, w):
        self._injected()
        return super().write(w) or self._fault


def _rig(link_up_s=None, **sections):
    clock = SimClock(start_ns=1_000_000_000)
    settings = make_settings(**sections)
    dev = FaultyDevice(clock, hand=PUSH, period_s=settings.period_ns * 1e-9)
    if link_up_s is not None:
        dev.link_up_ns = clock.now_ns() + int(link_up_s * 1e9)
    return Rig(settings, dev, {"start_pose": (0.0, 0.012, 0.0)}, clock=clock)


@pytest.fixture
def rig():
    yield from made_then_ended(_rig)


def _reasons(loop):
    return [Reason(r[4]) for r in loop.shared.transitions_since(0)]


def _engaged(r):
    r.run(3.0)
    assert r.loop.state_name == "engaged"
    assert abs(r.device.commands[-1][1] - PUSH_N) < 0.02
    return len(r.device.commands)


def _cut(r, n0, within=2):
    """The trouble came at step n0 (or within ``within`` steps of it): the next command is zero
    and so is every one while it lasts."""
    fy = np.array(r.device.commands[n0:])[:, 1]
    k = int(np.argmax(fy == 0.0))
    assert k <= within and np.all(fy[k:] == 0.0), fy[:5]
    assert not r.device.enabled


def _faded(r, n0, within=2):
    """The trouble came at step n0 (seen within ``within`` steps): the force fell to zero within
    fade_s, never by more than the rate limit per step, never above where it began; the device
    stayed on."""
    fy = np.array(r.device.commands[n0 - 1:])[:, 1]
    fade_steps = int(round(r.settings["safety"]["fade_s"] * r.settings.rate_hz)) + within
    assert np.all(np.abs(np.diff(fy)) <= r.loop.ctrl.force_rate_n_per_step + 1e-9)
    assert np.all(np.abs(fy) <= abs(fy[0]) + 1e-9)
    assert np.all(fy[fade_steps + 2:] == 0.0) and fy[1] != 0.0
    assert r.device.enabled


def _rearm_ramps_in(r):
    n1 = len(r.device.commands)
    assert r.loop.rearm()
    r.run(2.0)
    assert r.loop.state_name == "engaged"
    fy = np.array(r.device.commands[n1:])[:, 1]
    assert np.max(np.abs(np.diff(fy))) <= r.loop.ctrl.force_rate_n_per_step + 1e-9
    # the handle was free while the output was off (the hand pushed it on): stopping it takes more
    # than the push, at the ramp's slope, never more than the push and 1 N (as after a stall)
    assert np.max(np.abs(fy)) <= PUSH_N + 1.0 and abs(fy[-1] - PUSH_N) < 0.02


def _latched(r, fault, reason, seconds=5.0):
    r.run(seconds)
    assert r.loop.state_name == "fault" and r.loop.fault == fault
    assert reason in _reasons(r.loop)


def stall_explained(r):
    """A stall shorter than the watchdog the device declares (40 of 50 ms: not a trip of the
    loop's own) that the device's watchdog tripped on all the same (its program was late too)."""
    n0 = _engaged(r)
    r.device._check = lambda: r.clock.now_ns()
    r.device._last_ns = None
    r.clock.stall(40_000_000)
    r.device.fault_at_ns = r.clock.now_ns() + 40_000_000
    r.device.fault_code = DEV_FAULT_WATCHDOG
    r.run(0.1)
    _cut(r, n0)
    assert r.loop.fault == Fault.STALL and _reasons(r.loop)[-1] == Reason.STALL
    r.run(1.0)
    assert r.loop.state_name == "engaged" and _reasons(r.loop)[-1] == Reason.RECOVERED


def own_stall_engaged(r):
    n0 = _engaged(r)
    r.device._check = lambda: r.clock.now_ns()  # the device's watchdog does not see it
    r.device._last_ns = None
    r.clock.stall(80_000_000)
    r.run(0.1)
    assert r.device.trips == 0
    _cut(r, n0)
    assert r.loop.fault == Fault.STALL
    r.run(1.0)
    assert r.loop.state_name == "engaged" and _reasons(r.loop)[-1] == Reason.RECOVERED


def own_stall_idle(r):
    r.env.alive = False
    r.run(0.3)
    r.clock.stall(80_000_000)
    r.run(0.3)
    assert r.loop.state_name == "idle" and r.loop.fault == Fault.NONE and r.device.enabled
    assert Reason.STALL_IDLE in _reasons(r.loop)
    assert np.all(np.array(r.device.commands) == 0.0)


def watchdog_unexplained(r):
    """A device watchdog trip long after a stall the loop recovered from is the device's own."""
    _engaged(r)
    r.clock.stall(80_000_000)
    r.run(1.0)
    assert r.loop.state_name == "engaged" and r.loop.stall_recoveries == 1
    r.run(5.0)
    n0 = len(r.device.commands)
    r.device.fault_at_ns = r.clock.now_ns()
    r.device.fault_code = DEV_FAULT_WATCHDOG
    r.run(0.05)
    _cut(r, n0)
    _latched(r, Fault.DEVICE, Reason.DEVICE_FAULT, seconds=6.0)
    assert r.loop.stall_trips == 1 and r.loop.device_fault == DEV_FAULT_WATCHDOG
    _rearm_ramps_in(r)


def hardware(r):
    n0 = _engaged(r)
    r.device.fault_at_ns = r.clock.now_ns()
    r.device.fault_code = DEV_FAULT_HARDWARE
    r.run(0.05)
    _cut(r, n0)
    _latched(r, Fault.DEVICE, Reason.DEVICE_FAULT)
    _rearm_ramps_in(r)


def frozen(r):
    """The position stops changing while the hand pushes: cut after safety.frozen_s (not before),
    named; a sensor that moves again brings nothing back by itself; a re-arm ramps in."""
    _engaged(r)
    window = int(round(r.settings["safety"]["frozen_s"] * r.settings.rate_hz))
    r.device.frozen = r.loop.dev[0:3].copy()
    n0 = len(r.device.commands)
    r.run(window * 1e-3 - 0.01)
    assert r.loop.state_name == "engaged"  # a still handle under force is a sensor only after the window
    r.run(0.05)
    _cut(r, n0 + window, within=3)
    assert r.loop.device_fault == DEV_FAULT_FROZEN and r.loop.shared.get("device_fault") == DEV_FAULT_FROZEN
    assert "device fault: position frozen" in format_status(r.loop.shared.snapshot())  # what `status` prints
    r.device.frozen = None
    _latched(r, Fault.DEVICE, Reason.DEVICE_FAULT)
    _rearm_ramps_in(r)


def link_lost(r):
    n0 = _engaged(r)
    r.device.fault_at_ns = r.clock.now_ns()
    r.device.fault_code = DEV_FAULT_LINK
    r.run(0.05)
    _cut(r, n0)
    _latched(r, Fault.DEVICE, Reason.DEVICE_FAULT)
    _rearm_ramps_in(r)


def link_not_up(r):
    """Built with the link down for its first 1.5 s: no force was ever rendered, so the loop arms
    the device when the link comes up (not a force coming back by itself)."""
    r.run(1.0)
    assert r.loop.state_name == "fault" and r.loop.fault == Fault.DEVICE and r.loop.device_fault == DEV_FAULT_LINK
    assert np.all(np.array(r.device.commands) == 0.0)
    r.run(3.0)
    assert Reason.LINK_UP in _reasons(r.loop)
    assert r.loop.state_name == "engaged" and abs(r.device.commands[-1][1] - PUSH_N) < 0.02


def nonfinite(r):
    n0 = _engaged(r)
    r.device.nan_at_ns = r.clock.now_ns()
    r.run(0.05)
    _cut(r, n0)
    _latched(r, Fault.NONFINITE, Reason.NONFINITE)
    _rearm_ramps_in(r)


def update_error(r):
    n0 = _engaged(r)

    def boom(upd, now):
        raise ValueError("an update the model cannot take")

    r.loop._apply_stage = boom
    r.run(0.1)
    _cut(r, n0, within=int(r.settings.rate_hz / r.env.rate_hz) + 3)  # at the next update
    r.loop._apply_stage = r.loop._on_update
    _latched(r, Fault.NONFINITE, Reason.UPDATE_ERROR)
    _rearm_ramps_in(r)


def speed_engaged(r):
    n0 = _engaged(r)
    r.device.speed = FAST
    r.run(0.05)
    r.device.speed = 0.0
    r.run(0.3)
    _faded(r, n0)
    _latched(r, Fault.SPEED, Reason.SPEED)
    _rearm_ramps_in(r)


def speed_idle(r):
    r.env.alive = False
    r.run(0.2)
    r.device.speed = FAST
    r.run(0.2)
    r.device.speed = 0.0
    r.run(0.1)
    r.device.speed = FAST
    r.run(0.1)
    r.device.speed = 0.0
    assert r.loop.state_name == "idle" and r.loop.fault == Fault.NONE
    assert _reasons(r.loop).count(Reason.SPEED_IDLE) == 2  # once per fast spell, not per step
    assert r.loop.ctrl.counters()["speed_trips"] == 300
    r.env.alive = True  # a client that connects afterwards engages as usual
    r.run(3.0)
    assert r.loop.state_name == "engaged" and abs(r.device.commands[-1][1] - PUSH_N) < 0.02


def diverged(r):
    """The model's divergence watch fires (its signature injected: a velocity that reversed
    without decaying on the step before a run of DIVERGE_STEPS - 1): the force fades from that
    step with the device on, latched; a re-arm ramps it back in (the proxy no longer diverges)."""
    n0 = _engaged(r)
    _, st, _, _, cnt = r.loop.model.arrays()
    st[S_QD + 1] = 0.01
    st[S_QDP + 1] = -0.01
    cnt[K_OSC_RUN] = DIVERGE_STEPS - 1
    r.run(0.05)
    _faded(r, n0 + 1)
    _latched(r, Fault.DIVERGED, Reason.DIVERGED)
    assert r.loop.shared.get("diverged") == 1  # status says so
    _rearm_ramps_in(r)


def env_silent(r):
    n0 = _engaged(r)
    r.env.alive = False
    r.run(0.4)
    assert r.loop.state_name == "fading" and _reasons(r.loop)[-1] == Reason.SILENT
    _faded(r, n0 + int(r.settings["safety"]["watchdog_s"] * r.settings.rate_hz))
    r.env.alive = True
    r.run(2.0)
    assert r.loop.state_name == "engaged" and Reason.RESUMED in _reasons(r.loop)
    assert abs(r.device.commands[-1][1] - PUSH_N) < 0.02


def session_ended(r):
    n0 = _engaged(r)
    r.env.bye()
    r.run(0.5)
    assert Reason.SESSION_ENDED in _reasons(r.loop)
    _faded(r, n0, within=12)  # seen at the next housekeeping (10 ms)
    assert r.loop.state_name == "idle"


SCENARIOS = {f.__name__: f for f in (
    stall_explained, own_stall_engaged, own_stall_idle, watchdog_unexplained, hardware, frozen, link_lost, link_not_up,
    nonfinite, update_error, speed_engaged, speed_idle, diverged, env_silent, session_ended)}


def test_a_rearm_cannot_ramp_a_diverging_proxy_back_in(rig):
    """A re-arm restarts the proxy at rest: one still diverging is flagged again within
    DIVERGE_STEPS steps (its force barely starts to ramp in); once it no longer diverges, the
    re-arm ramps the force back in."""
    r = rig()
    _engaged(r)
    _, st, _, _, cnt = r.loop.model.arrays()

    def diverging(i):
        st[S_QD + 1] = 0.01 * (-1) ** i      # the signature, every step: a velocity flipping at full size
        st[S_QDP + 1] = -st[S_QD + 1]
        cnt[K_OSC_RUN] = max(cnt[K_OSC_RUN], DIVERGE_STEPS - 1)

    r.run(0.3, on_step=diverging)
    assert r.loop.state_name == "fault" and r.loop.fault == Fault.DIVERGED
    n1 = len(r.device.commands)
    assert r.loop.rearm()
    r.run(0.5, on_step=diverging)
    assert r.loop.state_name == "fault" and r.loop.fault == Fault.DIVERGED
    fy = np.abs(np.array(r.device.commands[n1:])[:, 1])
    assert fy.max() <= (DIVERGE_STEPS + 2) * r.loop.ctrl.force_rate_n_per_step and fy[-1] == 0.0
    _rearm_ramps_in(r)                       # no longer diverging


def test_every_row_has_a_scenario():
    assert sorted(p.key for p in FAULT_POLICY) == sorted(SCENARIOS)


@pytest.mark.parametrize("row", FAULT_POLICY, ids=lambda p: p.key)
def test_each_row_of_the_fault_policy(rig, row):
    r = rig(link_up_s=1.5) if row.key == "link_not_up" else rig()
    SCENARIOS[row.key](r)  # each checks the row's output, fault code and recovery
    assert row.reason in _reasons(r.loop)


@pytest.mark.parametrize("after_s, latches", [(STALL_EXPLAINS_S * 0.8, False), (STALL_EXPLAINS_S * 1.3, True),
                                              (6.0, True)])
def test_a_device_watchdog_is_the_stalls_only_shortly_after_it(rig, after_s, latches):
    """The border of "explained by a stall": a device watchdog trip reported ``after_s`` after the
    loop's own stall ended (the stall itself unseen by the device)."""
    r = rig()
    _engaged(r)
    r.device._check = lambda: r.clock.now_ns()
    r.device._last_ns = None
    r.clock.stall(40_000_000)  # below the device's 50 ms watchdog: not a trip by itself
    r.run(after_s)
    assert r.loop.state_name == "engaged"
    r.device.fault_at_ns = r.clock.now_ns()
    r.device.fault_code = DEV_FAULT_WATCHDOG
    r.run(0.05)
    if latches:
        assert r.loop.state_name == "fault" and r.loop.fault == Fault.DEVICE
    else:  # a stall trip, and on time long enough since the stall: it recovers at once
        assert _reasons(r.loop)[-2:] == [Reason.STALL, Reason.RECOVERED]


class ReadFaultDevice(FaultyDevice):
    """A driver whose ``read`` reports the fault and whose ``write`` does not (a link lost is seen
    when the state stops arriving)."""

    def write(self, w):
        self._injected()
        rc = WatchdogDevice.write(self, w)
        return DEV_OK if rc == self.fault_code else rc


def test_a_fault_only_the_read_reports_cuts_and_latches():
    clock = SimClock(start_ns=1_000_000_000)
    settings = make_settings()
    dev = ReadFaultDevice(clock, hand=PUSH, period_s=settings.period_ns * 1e-9)
    r = Rig(settings, dev, {"start_pose": (0.0, 0.012, 0.0)}, clock=clock)
    try:
        n0 = _engaged(r)
        r.device.fault_at_ns = r.clock.now_ns()
        r.device.fault_code = DEV_FAULT_HARDWARE
        r.run(0.05)
        _cut(r, n0)
        _latched(r, Fault.DEVICE, Reason.DEVICE_FAULT, seconds=1.0)
    finally:
        r.close()


def test_status_names_the_fault_with_the_state(rig):
    """The step that enters ``fault`` publishes why with it (the status publisher's pass is up
    to 10 ms later): a reader never sees ``fault`` with no fault named."""
    r = rig()
    _engaged(r)
    r.device.fault_at_ns = r.clock.now_ns()
    r.device.fault_code = DEV_FAULT_HARDWARE
    for _ in range(3):
        r.loop.step()
        if r.loop.state_name == "fault":
            break
    snap = r.loop.shared.snapshot()
    assert snap["loop_state"] == "fault" and snap["fault"] == int(Fault.DEVICE)
    assert snap["device_fault"] == DEV_FAULT_HARDWARE
