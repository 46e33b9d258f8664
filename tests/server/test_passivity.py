"""The passivity layer (``server/passivity.py``): its contract, promise by promise, over random
commands, velocities and tank levels (hypothesis), and a 1-DOF device in simulated time whose
controller is an active element (a negative damper): with the layer the energy given to the hand
stays within the initial budget plus the leak the contract allows; without it, it grows."""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import assume, given, settings, strategies as st

from hapticproxy.server import passivity as pv

SET = dict(max_examples=300, deadline=None, derandomize=True, database=None)
v3 = st.lists(st.floats(-5.0, 5.0), min_size=3, max_size=3).map(np.array)
small3 = st.lists(st.floats(-0.05, 0.05), min_size=3, max_size=3).map(np.array)
level = st.floats(-0.02, 0.02)


def _tp(enabled=True, h0=0.01, hmax=0.05, low=0.005, v0=0.02, w0=0.2, b=0.0, br=0.0, period=1e-3):
    tp = np.zeros(pv.NTP)
    pv.set_parameters(tp, enabled=enabled, initial_budget_j=h0, max_tank_j=hmax, low_level_j=low,
                      velocity_threshold_m_per_s=v0, angular_velocity_threshold_rad_per_s=w0,
                      device_damping_n_s_per_m=b, device_rot_damping_n_m_s_per_rad=br, period_s=period)
    return tp


def _limited(tp, h, f, v, t=None, w=None):
    ts = np.zeros(pv.NTS)
    ts[pv.TS_TANK] = h
    tc = np.zeros(pv.NTC, dtype=np.int64)
    cmd = np.concatenate([f, np.zeros(3) if t is None else t])
    tw = np.concatenate([v, np.zeros(3) if w is None else w])
    pv.limit(tp, ts, tc, cmd, tw)
    return cmd, ts, tc


@settings(**SET)
@given(v3, small3, st.floats(0.005, 1.0), st.booleans())
def test_l1_off_or_a_full_tank_changes_nothing(f, v, h, on):
    cmd, _, tc = _limited(_tp(enabled=on), h if on else h - 1.0, f, v)
    assert np.array_equal(cmd[:3], f) and tc[pv.TC_LIMITED] == 0


@settings(**SET)
@given(level, level)
def test_l2_the_factor_is_a_smooth_function_of_the_level(h1, h2):
    tp = _tp()
    b1, b2 = pv.beta_of(tp, h1), pv.beta_of(tp, h2)
    assert 0.0 <= b1 <= 1.0
    assert (b1 == 1.0) if h1 <= 0.0 else True
    assert (b1 == 0.0) if h1 >= 0.005 else True
    if h1 <= h2:
        assert b1 >= b2  # fuller tank, less limiting
    assert abs(b1 - b2) <= 1.5 * abs(h1 - h2) / 0.005 + 1e-12  # smoothstep's largest slope


def _check_l3(f, v, fo, beta, v0):
    p, po = float(f @ v), float(fo @ v)
    assert np.linalg.norm(fo - f) <= beta * np.linalg.norm(f) + 1e-12
    vn = np.linalg.norm(v)
    r = vn ** 2 / (vn ** 2 + v0 ** 2)  # moving: 1, at rest: 0
    if p > 0.0:
        assert po == pytest.approx((1.0 - beta) * p, rel=1e-9, abs=1e-15) and po >= -1e-15
    else:  # a force that takes energy: only the at-rest share shrinks
        assert po == pytest.approx((1.0 - beta * (1.0 - r)) * p, rel=1e-9, abs=1e-15)
        assert p - 1e-15 <= po <= 1e-15
    if vn > 0.0:  # across the velocity: only the at-rest share shrinks
        u = v / vn
        assert np.allclose(fo - (fo @ u) * u, (1.0 - beta * (1.0 - r)) * (f - (f @ u) * u), atol=1e-12)


@settings(**SET)
@given(v3, small3, v3, st.lists(st.floats(-0.5, 0.5), min_size=3, max_size=3).map(np.array), level)
def test_l3_moving_the_power_giving_part_shrinks_at_rest_the_whole_force_never_a_pull(f, v, t, w, h):
    tp = _tp()
    cmd, ts, _ = _limited(tp, h, f, v, t, w)
    beta = pv.beta_of(tp, h)
    assert ts[pv.TS_BETA] == beta
    _check_l3(f, v, cmd[:3], beta, 0.02)   # force against the velocity, v0
    _check_l3(t, w, cmd[3:], beta, 0.2)    # torque against the angular velocity, w0


@settings(**SET)
@given(v3, small3, v3, small3, st.floats(-0.02, 0.0))
def test_l5_an_empty_tank_gives_no_power_at_the_sampled_velocity(f, v, t, w, h):
    cmd, _, tc = _limited(_tp(), h, f, v, t, w)
    assert float(cmd[:3] @ v) <= 1e-15 and float(cmd[3:] @ w) <= 1e-15
    assert tc[pv.TC_EMPTY] == 1


@settings(**SET)
@given(v3, small3, level, st.sampled_from([math.nan, math.inf]))
def test_l6_finite_in_finite_out_a_bad_twist_limits_nothing(f, v, h, bad):
    cmd, _, _ = _limited(_tp(), h, f, v)
    assert np.all(np.isfinite(cmd))
    v = v.copy()
    v[1] = bad
    cmd, _, tc = _limited(_tp(), h, f, v)
    assert np.array_equal(cmd[:3], f) and tc[pv.TC_LIMITED] == 0


@settings(**SET)
@given(st.floats(0.0, 0.05), st.floats(-0.05, 0.05), st.floats(0.0, 1e-4), st.floats(0.0, 1e-2), st.floats(0, 5),
       st.floats(0, 0.1))
def test_a2_the_tank_is_the_ports_balance_with_the_declared_damping_capped(h0, w, dx2, dr2, b, br):
    tp = _tp(h0=0.0, b=b, br=br)
    ts = np.zeros(pv.NTS)
    pv.reset(tp, ts)
    ts[pv.TS_TANK] = h0
    pv.account(tp, ts, w, dx2, dr2)
    want = min(0.05, h0 - w + (b * dx2 + br * dr2) / 1e-3)
    assert ts[pv.TS_TANK] == pytest.approx(want, abs=1e-15)
    assert ts[pv.TS_GIVEN] == max(w, 0.0) and ts[pv.TS_TAKEN] == max(-w, 0.0)
    assert ts[pv.TS_LOW] == min(0.0, ts[pv.TS_TANK])
    pv.account(tp, ts, math.nan, dx2, dr2)
    assert ts[pv.TS_TANK] == pytest.approx(want, abs=1e-15) and ts[pv.TS_BAD] == 1.0


def test_grants_feed_the_tank_up_to_its_cap_and_bad_ones_nothing():
    tp = _tp()
    ts = np.zeros(pv.NTS)
    pv.reset(tp, ts)
    assert pv.grant(tp, ts, 0.02) == pytest.approx(0.02) and ts[pv.TS_TANK] == pytest.approx(0.03)
    assert pv.grant(tp, ts, 1.0) == pytest.approx(0.02) and ts[pv.TS_TANK] == pytest.approx(0.05)
    for bad in (-0.01, math.nan, math.inf):
        assert pv.grant(tp, ts, bad) == 0.0
    assert ts[pv.TS_GRANTED] == pytest.approx(0.04)
    off = _tp()
    off[pv.TP_GRANTS] = 0.0
    pv.reset(off, ts)
    assert pv.grant(off, ts, 0.01) == 0.0 and ts[pv.TS_TANK] == 0.01


@pytest.mark.parametrize("bad", [dict(initial_budget_j=0.1), dict(low_level_j=0.0), dict(period_s=-1.0),
                                 dict(velocity_threshold_m_per_s=math.nan)])
def test_parameters_are_checked_by_name(bad):
    kw = dict(enabled=True, initial_budget_j=0.01, max_tank_j=0.05, low_level_j=0.005, velocity_threshold_m_per_s=1e-3,
              angular_velocity_threshold_rad_per_s=1e-2, device_damping_n_s_per_m=0.0,
              device_rot_damping_n_m_s_per_rad=0.0, period_s=1e-3)
    kw.update(bad)
    with pytest.raises(ValueError, match=f"passivity.{next(iter(bad))}"):
        pv.set_parameters(np.zeros(pv.NTP), **kw)


def _active_device(enabled: bool, seconds: float = 3.0, hand_n: float = -0.5, grip: bool = False):
    """A 0.1 kg 1-DOF device (no physical damping) under a controller that is a negative damper
    (+4 N s/m: it pushes the way the handle moves) plus a spring to a set-point that rises 20 mm
    at t = 0.5 s (an engine moving a surface into the user); the hand pushes with ``hand_n``
    (or grips: a 300 N/m, 5 N s/m spring-damper to where it started). Returns the largest net
    energy the port gave the hand (the ledger), the layer's counters and state, and the
    largest step of the command over the last second."""
    dt = 1e-3
    tp = _tp(enabled=enabled)
    ts = np.zeros(pv.NTS)
    tc = np.zeros(pv.NTC, dtype=np.int64)
    pv.reset(tp, ts)
    m, x, v, held = 0.1, 0.0, 0.0, 0.0
    e = e_max = 0.0
    late_steps = []
    for k in range(int(seconds / dt)):
        t = k * dt
        x_set = 0.02 if t >= 0.5 else 0.0
        cmd = np.zeros(6)
        cmd[0] = 4.0 * v + 200.0 * (x_set - x)
        cmd[0] = max(-10.0, min(10.0, cmd[0]))
        twist = np.zeros(6)
        twist[0] = v
        pv.limit(tp, ts, tc, cmd, twist)
        held = cmd[0]
        fh = -300.0 * x - 5.0 * v if grip else hand_n
        v += (held + fh) / m * dt
        x_new = x + v * dt
        w = held * (x_new - x)
        e += w
        e_max = max(e_max, e)
        pv.account(tp, ts, w, (x_new - x) ** 2, 0.0)
        x = x_new
        if t >= seconds - 1.0:
            late_steps.append(held)
    tc = tc.copy()
    return e_max, tc, ts, float(np.max(np.abs(np.diff(late_steps))))


@pytest.mark.parametrize("grip", [False, True])
def test_an_active_controller_gives_the_hand_its_budget_and_no_more(grip):
    on, tc, ts, chatter = _active_device(True, grip=grip)
    off, _, _, _ = _active_device(False, grip=grip)
    assert off > 5 * 0.01  # the active element gives the hand far more than the budget
    assert on <= 0.01 + 1e-3  # with the layer: the initial budget plus at most 1 mJ
    assert tc[pv.TC_LIMITED] > 0
    assert chatter < 0.01  # the last second's command changes by under 10 mN a step: no chatter


def test_the_config_table_is_checked_by_name_and_reaches_the_controller():
    from hapticproxy.server import config as cfg
    from hapticproxy.server import control as ctl

    with pytest.raises(cfg.ConfigError, match="passivity.initial_budget_j"):
        cfg.load({"passivity": {"initial_budget_j": 0.2, "max_tank_j": 0.1}})
    with pytest.raises(cfg.ConfigError, match="passivity.low_level_j"):
        cfg.load({"passivity": {"low_level_j": 0.2, "max_tank_j": 0.1}})
    with pytest.raises(cfg.ConfigError, match="passivity.velocity_threshold_m_per_s"):
        cfg.load({"passivity": {"velocity_threshold_m_per_s": 0.0}})
    s = cfg.load({"passivity": {"enabled": True, "initial_budget_j": 0.02, "device_damping_n_s_per_m": 3.0}})
    c = ctl.Controller(s, "planar")
    assert c.tank_j == 0.02 and c.tp[pv.TP_ON] == 1.0 and c.tp[pv.TP_BDEV] == 3.0
    assert c.tp[pv.TP_PERIOD] == pytest.approx(1e-3)
    assert not cfg.load().data["passivity"]["enabled"]  # off by default: see EXPERIMENTS.md
    assert c.grant(0.01) == pytest.approx(0.01) and c.tank_j == pytest.approx(0.03)


def test_the_declared_device_damping_feeds_the_tank_through_the_controllers_ledger():
    """``control._port_in``: the ledger's period (here no force held: nothing given) and the
    handle's displacement and rotation during it reach the tank as b |dx|^2 / T + b_r |dr|^2 / T."""
    from hapticproxy.server import config as cfg
    from hapticproxy.server import control as ctl

    s = cfg.load({"device": {"driver": "sim", "kind": "spatial"},
                  "passivity": {"initial_budget_j": 0.0, "device_damping_n_s_per_m": 3.0,
                                "device_rot_damping_n_m_s_per_rad": 0.02}})
    c = ctl.Controller(s, "spatial")
    dev = np.zeros(20)
    dev[3] = 1.0
    ctl._port_in(c.cp, c.cs, dev)  # the first sample: nothing to pair
    dev[0:3] = [0.001, -0.002, 0.0005]
    dev[3:7] = [math.cos(0.005), 0.0, 0.0, math.sin(0.005)]  # 0.01 rad about z
    ctl._port_in(c.cp, c.cs, dev)
    want = (3.0 * (0.001 ** 2 + 0.002 ** 2 + 0.0005 ** 2) + 0.02 * 0.01 ** 2) / 1e-3
    assert c.tank_j == pytest.approx(want, rel=1e-9)
    assert c.ts[pv.TS_DAMPED] == pytest.approx(want, rel=1e-9) and c.cs[ctl.CS_EHAND] == 0.0


@pytest.mark.parametrize("vy, want", [(-0.5, 0.5 * (1 - 0.02 ** 2 / (0.25 + 0.02 ** 2))), (0.5, 0.0), (0.0, 0.0)])
def test_the_controller_limits_its_command_by_the_handles_twist(vy, want):
    """``control._command_out`` with the tank empty: a 0.5 N command against the handle's
    motion (it takes energy) stays; along it (it gives energy) and at rest it goes."""
    from hapticproxy.server import config as cfg
    from hapticproxy.server import control as ctl

    c = ctl.Controller(cfg.load({"passivity": {"enabled": True}}), "planar")
    c.ts[pv.TS_TANK] = 0.0
    c.cs[ctl.CS_GAIN] = c.cs[ctl.CS_TARGET] = 1.0
    c.cs[ctl.CS_ENV + 1] = 0.5  # the command (no controller: the environment's wrench)
    dev = np.zeros(20)
    dev[3] = 1.0
    dev[0:3] = [0.03, 0.04, 0.0]  # a pose that is no velocity
    dev[8] = vy
    assert ctl._command_out(c.cp, c.cs, c.cc, c.cmd, -1, ctl.RC_OK, dev) == ctl.RC_OK
    assert c.cmd[1] == pytest.approx(want, rel=1e-9, abs=1e-12)
    assert c.counters()["passivity_limited"] == 1


@pytest.mark.parametrize("enabled, tank, want", [(True, 0.0, 1.0), (True, 0.0025, 0.5), (True, 0.01, 0.0),
                                                 (False, 0.0, 0.0)])
def test_the_recovery_slows_with_the_tank(enabled, tank, want):
    """Each step the controller drives the proxy, the model's ``P_REC_CUT`` is the layer's last
    limiting factor: the deformation recovery (an active element) stops at an empty tank."""
    from hapticproxy.server import config as cfg
    from hapticproxy.server import control as ctl
    from hapticproxy.server.model import ContactParams, LocalModel, ToolSpec
    from hapticproxy.server.model.layout import P_REC_CUT

    c = ctl.Controller(cfg.load({"passivity": {"enabled": enabled}}), "planar")
    m = LocalModel(ToolSpec.planar(0.2, 1e-4), ContactParams(4000.0, 30.0), period_s=1e-3)
    m.reset([0.0, 0.05, 0.0])
    dev = np.zeros(20)
    dev[3] = 1.0
    dev[13:19] = np.nan
    for _ in range(2):  # the first step's limiting factor reaches the model at the second
        c.ts[pv.TS_TANK] = tank
        ctl.haptic_step(c.cp, c.cs, c.cc, dev, c.cmd, 1, *m.kernel_args(), c.hand, c.R, c.c)
    assert m.arrays()[0][P_REC_CUT] == pytest.approx(want)
