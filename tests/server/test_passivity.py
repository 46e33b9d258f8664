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
v3 = st.lists(st.floats(-20.0, 20.0), min_size=3, max_size=3).map(np.array)
vel3 = st.lists(st.floats(-0.5, 0.5), min_size=3, max_size=3).map(np.array)
hand3 = st.lists(st.floats(-3.0, 3.0), min_size=3, max_size=3).map(np.array)
level = st.floats(-0.02, 0.06)
M, I, T, RATE, TRATE = 0.4, 1e-3, 1e-3, 1.0, 0.05


def _tp(enabled=True, h0=0.01, hmax=0.05, low=0.005, m=M, i=I, b=0.0, br=0.0, period=T, credit=1.0):
    tp = np.zeros(pv.NTP)
    pv.set_parameters(tp, enabled=enabled, initial_budget_j=h0, max_tank_j=hmax, low_level_j=low,
                      moving_mass_kg=m, moving_inertia_kg_m2=i,
                      device_damping_n_s_per_m=b, device_rot_damping_n_m_s_per_rad=br, period_s=period,
                      input_credit=credit)
    return tp


def _limited(tp, h, f, v, t=None, w=None, hand=None, prev=None):
    ts = np.zeros(pv.NTS)
    ts[pv.TS_TANK] = h
    tc = np.zeros(pv.NTC, dtype=np.int64)
    cmd = np.concatenate([f, np.zeros(3) if t is None else t])
    tw = np.concatenate([v, np.zeros(3) if w is None else w])
    hd = np.zeros(6) if hand is None else hand
    pr = np.zeros(6) if prev is None else prev
    pv.limit(tp, ts, tc, cmd, tw, hd, pr, RATE, TRATE)
    return cmd, ts, tc


def _p(g, v, h, m=M, period=T):
    """The contract's prediction P(g), in numpy."""
    return float(period * g @ v + period ** 2 / m * g @ (g + np.where(np.isfinite(h), h, 0.0)))


def _left(tp, h, v, w, hand, prev):
    """H' of the contract (the level less both reserves), in numpy."""
    out = h
    for o, rate, m in ((0, RATE, tp[pv.TP_MASS]), (3, TRATE, tp[pv.TP_INERTIA])):
        p, vv, hh = prev[o:o + 3], np.concatenate([v, w])[o:o + 3], hand[o:o + 3]
        n = float(np.linalg.norm(p))
        if n == 0.0:
            continue
        tau = n * T / rate
        out -= max(0.0, tau * float(p @ vv) / 2 + tau ** 2 * (n ** 2 / 8 + float(p @ hh) / 6) / m)
    return out


@settings(**SET)
@given(v3, vel3, hand3, st.floats(0.0, 0.05), st.booleans())
def test_l1_off_or_a_full_tank_and_an_affordable_command_change_nothing(f, v, hand, h, on):
    tp = _tp(enabled=on)
    hd = np.concatenate([hand, np.zeros(3)])
    if on:
        assume(h >= 0.005 and _p(f, v, hand) <= h / 2)
    cmd, _, tc = _limited(tp, h, f, v, hand=hd)
    assert np.array_equal(cmd[:3], f) and tc[pv.TC_LIMITED] == 0


@settings(**SET)
@given(level, level)
def test_l2_the_allowance_is_a_c1_function_of_the_level(h1, h2):
    tp = _tp()
    a1, a2 = pv.allowance(tp, h1), pv.allowance(tp, h2)
    b1 = pv.beta_of(tp, h1)
    assert 0.0 <= b1 <= 1.0 and (b1 == 1.0 if h1 <= 0.0 else True) and (b1 == 0.0) == (h1 >= 0.005)
    assert a1 == (0.0 if h1 <= 0.0 else (1.0 - b1) * h1)
    assert (a1 == h1) if h1 >= 0.005 else (0.0 <= a1 <= max(h1, 0.0))
    if h1 <= h2:
        assert a1 <= a2  # a fuller tank allows more
    assert abs(a1 - a2) <= 27.0 / 16.0 * abs(h1 - h2) + 1e-15  # the largest slope, 27/16 at H = 3 L / 4


@pytest.mark.parametrize("h", [0.0, 0.005])
def test_l2_the_allowance_has_no_kink_where_the_limiting_begins_or_ends(h):
    tp = _tp()
    d = 1e-7
    left = (pv.allowance(tp, h) - pv.allowance(tp, h - d)) / d
    right = (pv.allowance(tp, h + d) - pv.allowance(tp, h)) / d
    assert left == pytest.approx(right, abs=1e-4)  # slope 0 at the empty tank, 1 at L


@settings(**SET)
@given(v3, vel3, v3.map(lambda x: x / 100), vel3.map(lambda x: 10 * x), hand3, v3, level)
def test_l3_the_output_is_the_nearest_point_of_the_affordable_ball(f, v, t, w, hand, prev, h):
    tp = _tp()
    hd = np.concatenate([hand, hand / 100])
    pr = np.concatenate([prev / 2, prev / 400])
    cmd, ts, tc = _limited(tp, h, f, v, t, w, hd, pr)
    left = _left(tp, h, v, w, hd, pr)
    assert ts[pv.TS_BETA] == pytest.approx(pv.beta_of(tp, left), abs=1e-9)
    allow = pv.allowance(tp, left) / 2
    for o, g0, vv, m in ((0, f, v, M), (3, t, w, I)):
        g = cmd[o:o + 3]
        hh = hd[o:o + 3]
        scale = 1e-9 * (1.0 + float(np.abs(g0).max()) ** 2)
        if _p(g0, vv, hh, m) <= allow:
            assert np.array_equal(g, g0)  # affordable: unchanged
            continue
        assert _p(g, vv, hh, m) <= allow + scale * T ** 2 / m * 10  # in the ball (on its surface)
        # the nearest point: every point of the ball is on the far side of the plane through it
        c = -(m * vv / T + hh) / 2
        r = math.sqrt(allow * m / T ** 2 + c @ c)
        rng = np.random.default_rng(0)
        for _ in range(20):
            u = rng.normal(size=3)
            q = c + r * rng.random() * u / np.linalg.norm(u)
            assert (g0 - g) @ (q - g) <= 1e-9 * (1.0 + np.linalg.norm(g0 - g) * (r + np.linalg.norm(q)))
    assert tc[pv.TC_LIMITED] == int(not np.array_equal(cmd, np.concatenate([f, t])))


@settings(**SET)
@given(v3, v3, vel3, hand3, v3, level)
def test_l4_the_output_is_1_lipschitz_in_the_command(f1, f2, v, hand, prev, h):
    tp = _tp()
    hd = np.concatenate([hand, np.zeros(3)])
    pr = np.concatenate([prev / 2, np.zeros(3)])
    c1, _, _ = _limited(tp, h, f1, v, hand=hd, prev=pr)
    c2, _, _ = _limited(tp, h, f2, v, hand=hd, prev=pr)
    assert np.linalg.norm(c1[:3] - c2[:3]) <= np.linalg.norm(f1 - f2) * (1 + 1e-12) + 1e-12


@settings(**SET)
@given(v3, vel3, vel3, hand3, hand3, st.floats(0.0, 1.0), v3, level)
def test_l4_the_output_is_continuous_in_velocity_hand_and_level(f, v, dv, hand, dh, k, prev, h):
    """A small change of the velocity, the hand or the level moves the output by little (no switch
    anywhere: a step here would be chatter the safety filter has to hide)."""
    tp = _tp()
    eps = 1e-6 * k
    pr = np.concatenate([prev / 2, np.zeros(3)])
    c1, _, _ = _limited(tp, h, f, v, hand=np.concatenate([hand, np.zeros(3)]), prev=pr)
    c2, _, _ = _limited(tp, h + eps * 1e-3, f, v + eps * dv, hand=np.concatenate([hand + eps * dh, np.zeros(3)]),
                        prev=pr)
    # bound: the ball's centre moves by m |dv| / (2 T) + |dh| / 2, its radius as much plus the level's share
    assert np.linalg.norm(c1[:3] - c2[:3]) <= 1e-3 + 2e3 * eps


@settings(**SET)
@given(v3, vel3, v3.map(lambda x: x / 100), vel3.map(lambda x: 10 * x), hand3, v3, st.floats(-0.02, 0.0))
def test_l5_an_empty_tank_gives_nothing_by_the_prediction(f, v, t, w, hand, prev, h):
    tp = _tp()
    hd = np.concatenate([hand, hand / 100])
    cmd, _, tc = _limited(tp, h, f, v, t, w, hd, np.concatenate([prev / 2, np.zeros(3)]))
    assert _p(cmd[:3], v, hand) <= 1e-9 * T ** 2 / M * (1 + f @ f)
    assert _p(cmd[3:], w, hand / 100, I) <= 1e-9 * T ** 2 / I * (1 + t @ t)
    assert tc[pv.TC_EMPTY] == int(h <= 0.0)


@settings(**SET)
@given(hand3, st.floats(-0.02, 0.0))
def test_l3_a_hand_held_still_by_a_wall_keeps_its_wall_at_an_empty_tank(hand, h):
    cmd, _, tc = _limited(_tp(), h, -hand, np.zeros(3), hand=np.concatenate([hand, np.zeros(3)]))
    assert np.allclose(cmd[:3], -hand, atol=1e-12)


@pytest.mark.parametrize("f, v, want_cut", [(-2.0, 0.01, False), (-6.0, 0.01, True), (1.0, 0.0, True)])
def test_l3_a_damper_beyond_m_over_t_and_a_pull_at_rest_are_cut(f, v, want_cut):
    """At an empty tank a force against the motion stays while it takes energy over the period:
    up to m v / T (4 N at 10 mm/s on 0.4 kg at 1 kHz); beyond that it would turn the handle
    within the period and give energy back, as a force at rest always would."""
    cmd, _, _ = _limited(_tp(), 0.0, np.array([f, 0.0, 0.0]), np.array([v, 0.0, 0.0]))
    if want_cut:
        assert cmd[0] == pytest.approx(max(f, -M * v / T) if v else 0.0, abs=1e-12)
    else:
        assert cmd[0] == f


def test_the_reserve_is_the_work_of_withdrawing_the_rendered_force():
    """``reserve`` against a fine simulation of a free 0.4 kg handle at 0.3 m/s while a 6 N force
    along the motion ramps to 0 at 1 N per period, with a 1 N hand across it (and none when the
    rendered force takes energy)."""
    p, v, hand = np.array([6.0, 0.0, 0.0]), np.array([0.3, 0.0, 0.0]), np.array([0.5, 1.0, 0.0])
    r = pv.reserve(p, 0, v, hand, 1.0, T, M)
    tau, n = 6.0 * T, 60000
    dt = tau / n
    x = np.zeros(3)
    vel = v.copy()
    work = 0.0
    for k in range(n):
        f = p * (1 - (k + 0.5) / n)
        vel = vel + (f + hand) / M * dt
        work += f @ vel * dt
    assert r == pytest.approx(work, rel=1e-3)
    assert pv.reserve(-p, 0, v, np.zeros(3), 1.0, T, M) == 0.0  # it takes energy: nothing reserved
    assert pv.reserve(np.zeros(3), 0, v, hand, 1.0, T, M) == 0.0
    assert pv.reserve(p, 0, v, hand, 0.0, T, M) == 0.0  # no rate limit: withdrawn at once


def test_the_reserve_lowers_the_level_the_allowance_sees():
    tp = _tp()
    f, v = np.array([5.0, 0.0, 0.0]), np.array([0.2, 0.0, 0.0])
    full, ts_full, _ = _limited(tp, 0.007, f, v)
    held, ts_held, _ = _limited(tp, 0.007, f, v, prev=np.array([8.0, 0, 0, 0, 0, 0]))
    assert ts_full[pv.TS_BETA] == 0.0 and np.array_equal(full[:3], f)
    # 8 N rendered along 0.2 m/s: withdrawing it gives 6.4 + 1.28 mJ, more than the tank's 7 mJ
    assert ts_held[pv.TS_BETA] == 1.0 and abs(held[0]) < 1e-9


@settings(**SET)
@given(v3, vel3, level, st.sampled_from([math.nan, math.inf]), st.integers(0, 2))
def test_l6_finite_in_finite_out_a_bad_input_limits_nothing(f, v, h, bad, which):
    cmd, _, _ = _limited(_tp(), h, f, v)
    assert np.all(np.isfinite(cmd))
    v = v.copy()
    prev = np.zeros(6)
    if which == 0:
        v[1] = bad
    elif which == 1:
        prev[2] = bad
    hand = np.zeros(6)
    if which == 2:
        hand[:] = bad  # no sensor: read as no hand
        cmd2, _, _ = _limited(_tp(), h, f, v, hand=hand)
        assert np.array_equal(cmd2, cmd)
        return
    cmd, _, tc = _limited(_tp(), h, f, v, prev=prev)
    assert np.array_equal(cmd[:3], f) and tc[pv.TC_LIMITED] == 0


def test_moving_figures_config_then_device_then_fallback():
    class Info:
        moving_mass_kg = 0.3
        moving_inertia_kg_m2 = None
    assert pv.moving_figures(0.5, 2e-3, Info()) == (0.5, 2e-3)
    assert pv.moving_figures(0.0, 0.0, Info()) == (0.3, pv.FALLBACK_INERTIA_KG_M2)
    assert pv.moving_figures(0.0, 0.0, None) == (pv.FALLBACK_MASS_KG, pv.FALLBACK_INERTIA_KG_M2)


def test_damping_figures_config_then_device_then_nothing():
    class Info:
        damping_n_s_per_m = 2.0
        rot_damping_n_m_s_per_rad = None
    assert pv.damping_figures(3.0, 1e-3, Info()) == (3.0, 1e-3)
    assert pv.damping_figures(0.0, 0.0, Info()) == (2.0, 0.0)
    assert pv.damping_figures(0.0, 0.0, None) == (0.0, 0.0)
    # the share the config credits (``damping_credit``), of either figure
    assert pv.damping_figures(3.0, 1e-3, Info(), share=0.5) == (1.5, 5e-4)
    assert pv.damping_figures(0.0, 0.0, Info(), share=0.25) == (0.5, 0.0)
    assert pv.damping_figures(0.0, 0.0, Info(), share=0.0) == (0.0, 0.0)
    for bad in (-0.1, 1.5, math.nan):
        with pytest.raises(ValueError, match="damping_credit"):
            pv.damping_figures(3.0, 1e-3, Info(), share=bad)


@settings(**SET)
@given(st.floats(0.0, 0.05), st.floats(-0.05, 0.05), st.floats(0.0, 1e-4), st.floats(0.0, 1e-2), st.floats(0, 5),
       st.floats(0, 0.1), st.sampled_from([1.0, 0.5, 0.1]))
def test_a2_the_tank_is_the_ports_balance_with_the_declared_damping_capped(h0, w, dx2, dr2, b, br, k):
    tp = _tp(h0=0.0, b=b, br=br, credit=k)
    ts = np.zeros(pv.NTS)
    pv.reset(tp, ts)
    ts[pv.TS_TANK] = h0
    pv.account(tp, ts, w, dx2, dr2)
    want = min(0.05, h0 - max(w, 0.0) + k * max(-w, 0.0) + (b * dx2 + br * dr2) / 1e-3)
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
                                 dict(moving_mass_kg=math.nan), dict(moving_inertia_kg_m2=0.0),
                                 dict(input_credit=0.0), dict(input_credit=1.5)])
def test_parameters_are_checked_by_name(bad):
    kw = dict(enabled=True, initial_budget_j=0.01, max_tank_j=0.05, low_level_j=0.005, moving_mass_kg=0.4,
              moving_inertia_kg_m2=1e-3, device_damping_n_s_per_m=0.0,
              device_rot_damping_n_m_s_per_rad=0.0, period_s=1e-3)
    kw.update(bad)
    with pytest.raises(ValueError, match=f"passivity.{next(iter(bad))}"):
        pv.set_parameters(np.zeros(pv.NTP), **kw)


def _active_device(enabled: bool, seconds: float = 3.0, hand_n: float = -0.5, grip: bool = False):
    """A 0.1 kg 1-DOF device (no physical damping, integrated by semi-implicit Euler) under a
    controller that is a negative damper (+4 N s/m: it pushes the way the handle moves) plus a
    spring to a set-point that rises 20 mm at t = 0.5 s (an engine moving a surface into the
    user), behind a 10 N cap and a 1 N-per-step rate limit (the safety filter's); the hand pushes
    with ``hand_n`` (or grips: a 300 N/m, 5 N s/m spring-damper to where it started), measured.
    Returns the largest net energy the port gave the hand (the ledger), the layer's counters and
    state, and the largest step of the command over the last second."""
    dt = 1e-3
    m = 0.1
    tp = _tp(enabled=enabled, m=m)
    ts = np.zeros(pv.NTS)
    tc = np.zeros(pv.NTC, dtype=np.int64)
    pv.reset(tp, ts)
    x, v, held = 0.0, 0.0, 0.0
    e = e_max = 0.0
    late_steps = []
    for k in range(int(seconds / dt)):
        t = k * dt
        x_set = 0.02 if t >= 0.5 else 0.0
        fh = -300.0 * x - 5.0 * v if grip else hand_n
        cmd = np.zeros(6)
        cmd[0] = 4.0 * v + 200.0 * (x_set - x)
        twist = np.zeros(6)
        twist[0] = v
        hand = np.zeros(6)
        hand[0] = fh
        prev = np.zeros(6)
        prev[0] = held
        pv.limit(tp, ts, tc, cmd, twist, hand, prev, 1.0, 0.05)
        held = held + max(-1.0, min(1.0, max(-10.0, min(10.0, cmd[0])) - held))
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


@pytest.mark.parametrize("credit", [1.0, 0.5])
def test_a_lossless_bounce_keeps_bouncing_on_a_full_credit_and_dies_on_half(credit):
    """A free 0.4 kg handle under a constant 1 N push onto an undamped 10 N-capped wall
    (10 kN/m, no damping anywhere, rate-limited 1 N per step): passive and lossless, so with the
    whole of the hand's input credited the layer lets it bounce on; with half, each bounce drains
    the tank and the bounce dies out."""
    dt, m = 1e-3, 0.4
    tp = _tp(m=m, h0=0.001, credit=credit)
    ts = np.zeros(pv.NTS)
    tc = np.zeros(pv.NTC, dtype=np.int64)
    pv.reset(tp, ts)
    x, v, held = 0.002, 0.0, 0.0
    xs = []
    for k in range(4000):
        cmd = np.zeros(6)
        cmd[0] = max(0.0, -10000.0 * x)
        twist = np.zeros(6)
        twist[0] = v
        hand = np.zeros(6)
        hand[0] = -1.0
        prev = np.zeros(6)
        prev[0] = held
        pv.limit(tp, ts, tc, cmd, twist, hand, prev, 1.0, 0.05)
        held = held + max(-1.0, min(1.0, min(10.0, cmd[0]) - held))
        x_old = x
        for _ in range(16):  # a continuous handle behind the hold
            v += (held - 1.0) / m * dt / 16
            x += v * dt / 16
        pv.account(tp, ts, held * (x - x_old), (x - x_old) ** 2, 0.0)
        xs.append(x)
    late = np.ptp(xs[-1000:])
    if credit == 1.0:
        assert late > 1e-3, late  # still bouncing millimetres high after 3 s
    else:
        assert late < 1e-4, late


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
    with pytest.raises(cfg.ConfigError, match="passivity.moving_mass_kg"):
        cfg.load({"passivity": {"moving_mass_kg": -1.0}})
    s = cfg.load({"passivity": {"enabled": True, "initial_budget_j": 0.02, "device_damping_n_s_per_m": 3.0}})
    c = ctl.Controller(s, "planar")
    assert c.tank_j == 0.02 and c.tp[pv.TP_ON] == 1.0 and c.tp[pv.TP_BDEV] == 3.0
    assert c.tp[pv.TP_PERIOD] == pytest.approx(1e-3)
    assert cfg.load().data["passivity"]["enabled"]  # on by default: transparency, EXPERIMENTS.md
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


@pytest.mark.parametrize("share", [0.0, 0.4, 1.0])
def test_the_damping_credit_is_the_share_of_the_devices_damping_the_tank_is_fed(share):
    """``[passivity] damping_credit``: the share of the config's damping figure the tank credits
    from the start (the device's figures alike: the loop's test below)."""
    from hapticproxy.server import config as cfg
    from hapticproxy.server import control as ctl

    s = cfg.load({"device": {"driver": "sim", "kind": "planar"},
                  "passivity": {"damping_credit": share, "device_damping_n_s_per_m": 3.0}})
    assert ctl.Controller(s, "planar").tp[pv.TP_BDEV] == pytest.approx(share * 3.0, rel=1e-12)
    with pytest.raises(Exception, match="damping_credit"):
        cfg.load({"passivity": {"damping_credit": 1.5}})


@pytest.mark.parametrize("vy, hand, want", [(-0.5, 0.0, 0.5), (0.5, 0.0, 0.0), (0.0, 0.0, 0.0), (0.0, -0.5, 0.5),
                                             (0.0, math.nan, 0.0)])
def test_the_controller_limits_its_command_by_the_handles_twist_and_hand(vy, hand, want):
    """``control._command_out`` with the tank empty: a 0.5 N command against the handle's
    motion (it takes energy) stays; along it (it gives energy) and at rest it goes, unless the
    hand's measured force (``dev[13:19]``; NaN: no sensor) holds it there."""
    from hapticproxy.server import config as cfg
    from hapticproxy.server import control as ctl

    c = ctl.Controller(cfg.load({"passivity": {"enabled": True}}), "planar")
    c.set_moving_figures(None)
    assert c.tp[pv.TP_MASS] == pv.FALLBACK_MASS_KG
    c.ts[pv.TS_TANK] = 0.0
    c.cs[ctl.CS_GAIN] = c.cs[ctl.CS_TARGET] = 1.0
    c.cs[ctl.CS_ENV + 1] = 0.5  # the command (no controller: the environment's wrench)
    dev = np.zeros(20)
    dev[3] = 1.0
    dev[0:3] = [0.03, 0.04, 0.0]  # a pose that is no velocity
    dev[8] = vy
    dev[14] = hand
    assert ctl._command_out(c.cp, c.cs, c.cc, c.cmd, -1, ctl.RC_OK, dev) == ctl.RC_OK
    assert c.cmd[1] == pytest.approx(want, rel=1e-9, abs=1e-12)
    assert c.counters()["passivity_limited"] == int(want != 0.5)


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


@pytest.mark.parametrize("kind, mass, inertia", [("planar", 0.4, 1e-3), ("spatial", 0.3, None), ("1dof", 0.2, None)])
def test_the_loop_gives_the_layer_the_devices_moving_mass_inertia_and_damping(kind, mass, inertia):
    """``HapticLoop`` sets the prediction's mass and smallest moment, and the damping that feeds
    the tank, from the device's ``DeviceInfo`` (the simulated device states them; a 1-DOF one no
    rotation: the fallback inertia, no rotational damping), the config's values first."""
    from hapticproxy.server import config as cfg
    from hapticproxy.server.clock import SimClock
    from hapticproxy.server.loop import HapticLoop

    dev_b = {"1dof": 1.0, "planar": 2.0, "spatial": 1.0}[kind]          # the sim's defaults (devices/sim.py)
    dev_br = {"1dof": 0.0, "planar": 2e-3, "spatial": 1e-3}[kind]
    for over, want_m, want_b in (({}, mass, (dev_b, dev_br)), ({"moving_mass_kg": 0.05}, 0.05, (dev_b, dev_br)),
                                 ({"device_damping_n_s_per_m": 0.5, "device_rot_damping_n_m_s_per_rad": 1e-4}, mass,
                                  (0.5, 1e-4 if kind != "1dof" else 1e-4)),
                                 # the share credited (``damping_credit``) of the device's own figures
                                 ({"damping_credit": 0.25, "moving_mass_kg": 0.0}, mass, (0.25 * dev_b, 0.25 * dev_br))):
        s = cfg.load({"transport": {"url": f"mem://passivity-figures-{kind}-{len(over)}"},
                      "status": {"address": "127.0.0.1:1"}, "device": {"driver": "sim", "kind": kind},
                      "passivity": over})
        loop = HapticLoop.build(s, clock=SimClock(start_ns=1_000_000_000))
        try:
            info = loop.device.info
            assert loop.ctrl.tp[pv.TP_MASS] == want_m == (over.get("moving_mass_kg") or info.moving_mass_kg)
            # the damping that feeds the tank: the config's, else the device's own (the sim states it)
            assert (loop.ctrl.tp[pv.TP_BDEV], loop.ctrl.tp[pv.TP_BRDEV]) == pytest.approx(want_b)
            assert info.damping_n_s_per_m == dev_b
            want_i = info.moving_inertia_kg_m2 or pv.FALLBACK_INERTIA_KG_M2
            assert loop.ctrl.tp[pv.TP_INERTIA] == want_i
            if inertia is not None:
                assert want_i == inertia
            elif kind == "spatial":
                assert 0.0 < want_i < 1.0
            else:
                assert want_i == pv.FALLBACK_INERTIA_KG_M2
        finally:
            loop.close()


@settings(max_examples=40, deadline=None, derandomize=True, database=None)
@given(st.lists(st.tuples(st.floats(-1.0, 1.0), st.floats(-1.0, 1.0), st.floats(-2e-3, 2e-3), st.integers(1, 20)),
                min_size=1, max_size=20), st.floats(0.0, 5.0), st.floats(0.0, 5e-3))
def test_the_damping_a_simulated_device_states_dissipates_at_least_what_the_tank_credits(forces, b, br):
    """The credit the tank takes for the device's stated damping (``damping_figures``, contract
    A2: ``b |dx|^2 / T`` per period) never exceeds what the simulated device dissipated: the
    command's work less the change of the handle's kinetic energy, measured from its readings."""
    from hapticproxy.server.devices.sim import make_sim_device

    now = [1_000_000_000]
    dev = make_sim_device({"kind": "planar", "hand": {"type": "none"}, "damping_n_s_per_m": b,
                           "rot_damping_n_m_s_per_rad": br, "workspace_min_m": [-1.0, -1.0],
                           "workspace_max_m": [1.0, 1.0]}, period_s=T, clock_ns=lambda: now[0])
    bd, brd = pv.damping_figures(0.0, 0.0, dev.info)
    m, izz = dev.info.moving_mass_kg, dev.info.moving_inertia_kg_m2
    from hapticproxy.server.devices.base import DEV_NSTATE

    row = np.zeros(DEV_NSTATE)
    dev.enable()
    dev.read(row)

    def pose(r):
        return np.array([r[0], r[1], 2.0 * math.atan2(r[6], r[3])])

    def kinetic(r):
        return 0.5 * m * (r[7] ** 2 + r[8] ** 2) + 0.5 * izz * r[12] ** 2

    p0, k0 = pose(row), kinetic(row)
    work = credit = 0.0
    for fx, fy, tz, held in forces:                 # each force held over ``held`` periods
        for _ in range(held):
            assert dev.write(np.array([fx, fy, 0.0, 0.0, 0.0, tz])) == 0
            now[0] += int(T * 1e9)
            dev.read(row)
            p1 = pose(row)
            d = p1 - p0
            work += fx * d[0] + fy * d[1] + tz * d[2]
            credit += (bd * (d[0] ** 2 + d[1] ** 2) + brd * d[2] ** 2) / T
            p0 = p1
    assert np.all(np.abs(row[:2]) < 0.9)            # never on an end-stop (it stores energy of its own)
    dissipated = work - (kinetic(row) - k0)
    assert credit <= dissipated + 1e-12
    assert (bd, brd) == (b, br)                     # the device states its own figures
