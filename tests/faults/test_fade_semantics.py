"""Fades and ramp-ins in simulated time, in the situations where the command itself moves while
the gain changes: a fade never pushes harder than the force it started from (whatever the user
does meanwhile), and a session that engages while the previous one is still fading ramps in from
zero like any other engagement."""
from __future__ import annotations

import numpy as np
from server_harness import PointDevice, WallEnv

from hapticproxy.server.config import FIRST_COMMAND_MAX_N
from hapticproxy.server.shm import ST, TEL

PUSH = lambda t: (0.0, -0.5, 0.0)  # noqa: E731 - the paper's static-contact push, N


def _grew_while_fading(rows: np.ndarray, cmds: np.ndarray) -> int:
    """Steps in which the gain went down and some force component grew in magnitude."""
    g = rows[:, TEL["gain"]]
    c = np.abs(cmds)
    down = g[1:] < g[:-1]
    grew = (c[1:] > c[:-1] + 1e-12).any(axis=1)
    return int((down & grew).sum())


def _resting(rig_factory):
    """A rig and its device 2 s into a resting contact: the handle pushed onto the floor by PUSH."""
    dev = PointDevice(hand=PUSH)
    r = rig_factory(device=dev)
    r.run(2.0)
    return r, dev


def test_a_speed_trip_fade_never_pushes_harder_than_where_it_started(rig_factory):
    # resting on the wall with 0.5 N, then the hand yanks the handle away at 30 N: the speed
    # trips a fade while the device flies away from the proxy, stretching the coupling spring
    yank_at = 2.0
    # (the fade alone, without the passivity layer: with input_credit 0.45 and a 2 mJ budget the
    # layer holds the pull-back at the trip to 0.58 N, and the fade has less to show)
    dev = PointDevice(hand=lambda t: (0.0, -0.5, 0.0) if t < yank_at else (0.0, 30.0, 0.0))
    r = rig_factory(device=dev, safety={"max_speed_m_per_s": 0.5}, passivity={"enabled": False})
    rows = r.run(3.0)
    cmds = np.array(dev.commands)
    assert r.loop.ctrl.counters()["speed_trips"] > 0 and r.loop.state_name == "fault"
    g = rows[:, TEL["gain"]]
    y0 = int(yank_at * 1000)
    trip = y0 + 1 + int(np.argmax(g[y0 + 1:] < g[y0:-1]))  # the first step of the fade
    at_trip = np.abs(cmds[trip - 1])
    # the coupling pulled back as the handle flew off (up to the trip); from the trip on, no
    # component grows: the force never exceeds where the fade began, and it ends at zero
    assert at_trip.max() > 1.0
    assert _grew_while_fading(rows, cmds) == 0
    assert np.all(np.abs(cmds[trip:]) <= at_trip + 1e-9)
    fade_steps = int(r.settings["safety"]["fade_s"] * 1000)
    assert np.all(cmds[trip + fade_steps:] == 0.0)


def test_a_watchdog_fade_is_monotone_while_the_user_keeps_pushing(rig_factory):
    r, dev = _resting(rig_factory)
    r.env.alive = False
    n0 = len(dev.commands)
    rows = r.run(0.6)
    cmds = np.array(dev.commands[n0 - 1:])
    assert _grew_while_fading(np.vstack([rows[:1], rows]), cmds) == 0
    fy = np.abs(cmds[:, 1])
    assert np.all(np.diff(fy[100:]) <= 1e-12)  # from the watchdog on: only down
    assert fy[-1] == 0.0


def test_a_new_session_engaging_during_a_fade_ramps_in_from_zero(rig_factory):
    r, dev = _resting(rig_factory)
    r.env.bye()  # session A ends mid-contact: its force fades
    r.run(0.05)
    assert 0.0 < r.loop.ctrl.gain < 1.0  # still fading
    # client B connects at once, its tool 5 mm inside the floor (a large penalty force)
    b = WallEnv(r.settings["transport"]["url"], r.clock, start_pose=(0.0, 0.005, 0.0), seed=2)
    r.env.close()
    r.env = b
    n0 = len(dev.commands)
    rows = r.run(1.0)
    cmds = np.array(dev.commands[n0:])
    g = rows[:, TEL["gain"]]
    eng = int(np.argmax(rows[:, TEL["updates"]] > rows[0, TEL["updates"]]))  # B's first update
    assert r.loop.engagements == 2
    # from B's engagement on, the force ramps in from zero: the first command is tiny and the
    # output stays within gain * cap while the gain climbs
    nz = np.nonzero(np.abs(cmds[eng:]).max(axis=1) > 0)[0]
    assert len(nz)
    assert np.abs(cmds[eng + nz[0]]).max() <= FIRST_COMMAND_MAX_N
    cap = r.loop.ctrl.force_cap_n
    assert np.all(np.abs(cmds[eng:, :2]).max(axis=1) <= g[eng:] * cap + 1e-9)
    assert g[eng] <= r.settings.period_ns * 1e-9 / r.settings["safety"]["ramp_in_s"] + 1e-12


def test_force_comes_back_at_the_ramp_slope_after_an_interrupted_fade(rig_factory):
    # the environment falls silent long enough for the watchdog to start a fade, then comes back
    # half-way through it: the gain climbs again from where it was, and the force must climb back
    # gradually (no component growing faster than cap * dt / ramp_in_s per step), not snap back
    r, dev = _resting(rig_factory)
    r.env.alive = False
    n0 = len(dev.commands)
    rows = r.run(0.2)  # watchdog at 0.1 s, then half of the 0.2 s fade
    g = rows[:, TEL["gain"]]
    assert 0.0 < g[-1] < 1.0
    r.env.alive = True
    rows = np.vstack([rows, r.run(1.0)])
    cmds = np.array(dev.commands[n0 - 1:])
    g = np.concatenate([[1.0], rows[:, TEL["gain"]]])
    up = g[1:] > g[:-1]
    assert up.any()
    growth = np.abs(cmds[1:]).max(axis=1) - np.abs(cmds[:-1]).max(axis=1)
    s = r.settings["safety"]
    slope = r.loop.ctrl.force_cap_n * r.settings.period_ns * 1e-9 / s["ramp_in_s"]
    assert growth[up].max() <= slope + 1e-12
    assert _grew_while_fading(np.vstack([rows[:1], rows]), cmds) == 0
    assert abs(cmds[-1][1] - 0.5) < 0.05  # and it does come back


def test_a_fade_keeps_its_time_when_the_loop_skips_periods(rig_factory):
    # the loop wakes 50 ms late in the middle of a watchdog fade (a loaded machine, a stopped
    # process): the skipped periods count towards the fade, which still ends fade_s after it began
    r, dev = _resting(rig_factory)
    r.env.alive = False
    rows = r.run(0.15)  # the watchdog (0.1 s) started the fade ~50 ms ago
    assert rows[-1, TEL["gain"]] < 1.0
    t_fade = rows[np.argmax(rows[:, TEL["gain"]] < 1.0), TEL["t_s"]]
    r.clock.stall(50_000_000)  # the next wake-up is 50 ms late
    rows = r.run(0.2)
    t = rows[:, TEL["t_s"]]
    fy = rows[:, TEL["cmd_fy"]]
    zero = t[np.argmax((fy == 0.0) & (rows[:, TEL["gain"]] == 0.0))]
    s = r.settings["safety"]
    assert zero - t_fade <= s["fade_s"] + 0.002
    assert r.loop.shared.status[ST["missed_deadlines"]] >= 50
