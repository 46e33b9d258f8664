"""The server's advice to the engine (server/prediction.py): the epsilon to use next, from the
proxy's speed, the engine's period and the engine tool's distance; bounded by the granted epsilon."""
import math

import numpy as np
import pytest

from hapticproxy.server.prediction import EPSILON_FLOOR_M, EPSILON_MARGIN, LEAD_MAX_S, EngineAdvice, tool_radius_m

IDENT = (1.0, 0.0, 0.0, 0.0)


def _pose(x, y=0.0, theta=0.0):
    return np.array([x, y, 0.0, math.cos(theta / 2), 0.0, 0.0, math.sin(theta / 2)])


def _feed(adv, *, v, period, lag, steps=30, touching=False, follow_lead=False):
    """Free motion along +x at ``v``; updates every ``period``; the engine's tool ``lag`` s behind
    the proxy (less the lead it is told, when it follows it)."""
    for k in range(steps):
        t = k * period
        x = v * t
        behind = lag - (adv.lead_s if follow_lead else 0.0)
        adv.on_update(t, _pose(x), np.array([v, 0, 0, 0, 0, 0.0]), _pose(x - v * behind), touching)
    return adv


def test_tool_radius_is_exact_for_a_rod_and_a_rectangle():
    m, length, width = 0.25, 0.08, 0.02
    assert tool_radius_m(m, (m * length ** 2 / 12,)) == pytest.approx(length / 2)
    assert tool_radius_m(m, (m * (length ** 2 + width ** 2) / 12,)) == pytest.approx(math.hypot(length, width) / 2)
    assert tool_radius_m(1.0, (0.0, 0.0, 0.0)) == 0.0


def test_until_measured_the_granted_epsilon_is_used():
    adv = EngineAdvice(0.01)
    assert adv.epsilon_m == 0.01 and adv.lead_s == 0.0


def test_a_slow_tool_gets_the_floor_a_fast_one_the_travel_and_the_distance():
    slow = _feed(EngineAdvice(0.04, lead=False), v=0.001, period=0.02, lag=0.0)
    assert slow.epsilon_m == pytest.approx(EPSILON_FLOOR_M)
    fast = _feed(EngineAdvice(0.04, lead=False), v=0.2, period=0.02, lag=0.03)
    # margin x v x T plus the engine tool's distance from the proxy (v x lag)
    assert fast.epsilon_m == pytest.approx(EPSILON_MARGIN * 0.2 * 0.02 + 0.2 * 0.03, rel=1e-6)
    assert fast.distance_m == pytest.approx(0.2 * 0.03)
    assert fast.period_s == pytest.approx(0.02)


def test_the_granted_epsilon_caps_it_and_zero_turns_it_off():
    capped = _feed(EngineAdvice(0.005, lead=False), v=1.0, period=0.03, lag=0.03)
    assert capped.epsilon_m == 0.005
    lm0 = _feed(EngineAdvice(0.0), v=1.0, period=0.03, lag=0.03)
    assert lm0.epsilon_m == 0.0
    fixed = _feed(EngineAdvice(0.01, predict=False, lead=False), v=1.0, period=0.03, lag=0.03)
    assert fixed.epsilon_m == 0.01 and fixed.lead_s == 0.0


def test_the_longest_recent_engine_step_and_speed_are_remembered():
    adv = EngineAdvice(0.1, lead=False)
    _feed(adv, v=0.3, period=0.033, lag=0.0, steps=5)
    e_fast = adv.epsilon_m
    # two quick updates at a lower speed: the long step and the high speed decay, not vanish
    t0 = 4 * 0.033                   # the last update of _feed
    for k in range(2):
        t = t0 + 0.017 * (k + 1)
        adv.on_update(t, _pose(0.0), np.array([0.1, 0, 0, 0, 0, 0.0]), _pose(0.0), False)
    assert adv.period_s > 0.017
    assert adv.epsilon_m > EPSILON_MARGIN * 0.1 * 0.017
    assert adv.epsilon_m < e_fast


def test_rotation_counts_at_the_tools_reach():
    adv = EngineAdvice(0.1, tool_radius_m=0.04, lead=False)
    for k in range(10):
        t = 0.02 * k
        adv.on_update(t, _pose(0.0, theta=2.0 * t), np.array([0, 0, 0, 0, 0, 2.0]), _pose(0.0, theta=2.0 * t - 0.1),
                      False)
    # 2 rad/s at 40 mm: 80 mm/s; the engine's tool 0.1 rad behind: 4 mm
    assert adv.epsilon_m == pytest.approx(EPSILON_MARGIN * 0.08 * 0.02 + 0.1 * 0.04, rel=1e-3)


def test_bad_arguments_are_refused_by_name():
    for kw, name in (({"epsilon_cap_m": -1.0}, "epsilon_cap_m"), ({"epsilon_cap_m": math.nan}, "epsilon_cap_m"),
                     ({"epsilon_cap_m": 0.01, "tool_radius_m": -1}, "tool_radius_m"),
                     ({"epsilon_cap_m": 0.01, "margin": 0.5}, "margin")):
        with pytest.raises(ValueError, match=name):
            EngineAdvice(**kw)


def test_a_non_finite_input_changes_nothing():
    adv = _feed(EngineAdvice(0.04, lead=False), v=0.2, period=0.02, lag=0.01)
    before = adv.epsilon_m
    adv.on_update(1.0, _pose(math.nan), np.array([math.nan, 0, 0, 0, 0, 0.0]), _pose(0.0), False)
    assert adv.epsilon_m == before


# ------------------------------------------------------------------------------ the lead
def test_the_lag_of_an_engine_that_ignores_the_lead_is_measured():
    adv = _feed(EngineAdvice(0.04), v=0.2, period=0.02, lag=0.03)
    assert adv.lag_s == pytest.approx(0.03, rel=1e-6)
    assert adv.lead_s == pytest.approx(LEAD_MAX_S)          # it keeps asking for more, within its bound


def test_an_engine_that_follows_the_lead_ends_on_the_proxy():
    adv = _feed(EngineAdvice(0.04), v=0.2, period=0.02, lag=0.035, steps=40, follow_lead=True)
    assert adv.lead_s == pytest.approx(0.035, rel=1e-3)
    assert abs(adv.lag_s) < 1e-4
    # and the epsilon no longer has to cover the lag: the travel of one engine step
    assert adv.epsilon_m == pytest.approx(EPSILON_MARGIN * 0.2 * 0.02, rel=2e-2)


def test_a_tool_held_by_a_wall_is_not_lag():
    adv = _feed(EngineAdvice(0.04), v=0.2, period=0.02, lag=0.03, touching=True)
    assert adv.lag_samples == 0 and adv.lead_s == 0.0


def test_the_lead_can_be_switched_off():
    adv = _feed(EngineAdvice(0.04, lead=False), v=0.2, period=0.02, lag=0.03)
    assert adv.lead_s == 0.0 and adv.lag_s == pytest.approx(0.03, rel=1e-6)


def test_arrays_and_plain_sequences_give_the_same_advice():
    """The loop passes numpy views, other callers tuples: one advice, bit for bit."""
    a, b = EngineAdvice(0.04, tool_radius_m=0.05), EngineAdvice(0.04, tool_radius_m=0.05)
    rng = np.random.default_rng(3)
    for k in range(40):
        pose, twist, eng = _pose(0.01 * k, 0.002 * k, 0.1 * k), rng.normal(size=6) * 0.1, _pose(0.01 * k - 0.003)
        a.on_update(k / 60, pose, twist, eng, k % 7 == 0)
        b.on_update(k / 60, tuple(pose.tolist()), tuple(twist.tolist()), list(eng.tolist()), k % 7 == 0)
        assert (a.epsilon_m, a.lead_s, a.lag_s, a.distance_m) == (b.epsilon_m, b.lead_s, b.lag_s, b.distance_m)
    assert a.lag_samples > 0


def test_a_contact_at_or_below_zero_separation_counts_as_touching():
    """The loop hands the update's separations to the kernel instead of a flag: any <= 0 is the
    engine's tool touching something (no lag measured), all > 0 is free motion."""
    touching = _feed(EngineAdvice(0.04), v=0.2, period=0.02, lag=0.03, touching=True)
    for seps, like in (([0.003, 0.0, 0.01], touching), ([0.003, 0.001], None)):
        adv = EngineAdvice(0.04)
        sep = np.array(seps)
        for k in range(30):
            t, x = k * 0.02, 0.2 * k * 0.02
            adv.on_update(t, _pose(x), np.array([0.2, 0, 0, 0, 0, 0.0]), _pose(x - 0.2 * 0.03), False, sep)
        if like is None:
            assert adv.lag_samples == 30 and adv.lead_s > 0
        else:
            assert (adv.lag_samples, adv.lead_s, adv.epsilon_m) == (like.lag_samples, like.lead_s, like.epsilon_m)

