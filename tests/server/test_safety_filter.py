"""The safety filter's contract (``server/safety.py``'s docstring), promise by promise, over random
sequences of commands, gains, skipped periods and resets, for every device kind's components.

Each promise is checked on every call of a sequence; hypothesis shrinks a broken one to the
shortest sequence that breaks it. The parameters differ between force and torque (caps, rates,
per-axis caps), so a filter that mixes them up (a torque bounded by the force's numbers) breaks
a promise. The property tests are derandomized: the same examples on every run and machine,
so CI and a mutation run agree."""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

from hapticproxy.server import safety as sf
from hapticproxy.server.devices.base import KIND_WRENCH_MASK

TOL = 1e-9
KINDS = sorted(KIND_WRENCH_MASK)

finite = st.floats(-1e4, 1e4, allow_nan=False, allow_infinity=False)
small = st.floats(-5.0, 5.0, allow_nan=False, allow_infinity=False)
component = st.one_of(finite, small, st.just(0.0), st.sampled_from([1e-300, -1e-300, 1e6, -1e6]))
wrench = st.lists(component, min_size=6, max_size=6)


@st.composite
def params(draw):
    fmax = draw(st.floats(0.1, 20.0))
    tmax = draw(st.floats(0.01, 2.0))
    return dict(
        max_force_n=fmax, max_torque_n_m=tmax,
        # a motor's own limit, at times tighter than the norm cap
        max_force_axis_n=draw(st.one_of(st.none(), st.floats(0.05, 25.0))),
        max_torque_axis_n_m=draw(st.one_of(st.none(), st.floats(0.005, 3.0))),
        force_rate_n_per_step=draw(st.floats(0.001, 2.0)),
        torque_rate_n_m_per_step=draw(st.floats(0.0001, 0.2)),
        fade_per_step=draw(st.floats(1e-4, 0.5)),
        ramp_per_step=draw(st.floats(1e-4, 0.5)),
        mask=KIND_WRENCH_MASK[draw(st.sampled_from(KINDS))],
    )


#: one call: (command, new target or None, periods skipped before it, reset before it)
ops = st.lists(st.tuples(wrench, st.one_of(st.none(), st.sampled_from([0.0, 1.0]), st.floats(0.0, 1.0)),
                         st.one_of(st.just(0), st.integers(0, 3), st.integers(0, 2000)),
                         st.sampled_from([False] * 15 + [True])),
               min_size=1, max_size=60)


def _n(v) -> float:
    return float(math.sqrt(float(np.dot(v, v))))


class Filter:
    """The filter's arrays and one call, with the state before it kept for the checks."""

    def __init__(self, p: dict) -> None:
        self.p = p
        self.sp = sf.parameters(**p)
        self.ss = np.zeros(sf.NSS)
        self.sc = np.zeros(sf.NSC, dtype=np.int64)
        self.cmd = np.zeros(6)

    def call(self, w, skipped: int = 0):
        ss = self.ss
        ss[sf.SS_SKIPPED] = skipped
        before = ss.copy()
        self.cmd[:] = w
        rc = sf.safety_filter(self.sp, ss, self.sc, self.cmd)
        return rc, before, self.cmd.copy()


def check_promises(f: Filter, w, skipped: int, rc: int, before: np.ndarray, out: np.ndarray) -> None:
    sp, ss = f.sp, f.ss
    F, T = sp[sf.SP_FMAX], sp[sf.SP_TMAX]
    Fa, Ta = sp[sf.SP_FAXIS], sp[sf.SP_TAXIS]
    g0, g1, target = before[sf.SS_GAIN], ss[sf.SS_GAIN], before[sf.SS_TARGET]
    p = before[sf.SS_PREV:sf.SS_PREV + 6]
    # 1. finite
    if not np.all(np.isfinite(w)):
        assert rc == sf.RC_NONFINITE
        assert np.all(out == 0.0) and g1 == 0.0 and ss[sf.SS_TARGET] == 0.0
        assert np.all(ss[sf.SS_PREV:sf.SS_PREV + 6] == 0.0)
        return
    assert rc == sf.RC_OK
    assert np.all(np.isfinite(out))
    assert np.array_equal(ss[sf.SS_PREV:sf.SS_PREV + 6], out), "the state keeps what was written"
    assert ss[sf.SS_SKIPPED] == 0.0
    # 2. gain
    n = 1 + skipped
    assert 0.0 <= g1 <= 1.0
    if target > g0:
        assert g0 <= g1 <= target + TOL and g1 - g0 <= n * sp[sf.SP_RAMP] + TOL
        assert g1 == pytest.approx(min(target, g0 + n * sp[sf.SP_RAMP]), abs=1e-12)
    elif target < g0:
        assert target - TOL <= g1 <= g0 and g0 - g1 <= n * sp[sf.SP_FADE] + TOL
        assert g1 == pytest.approx(max(target, g0 - n * sp[sf.SP_FADE]), abs=1e-12)
    else:
        assert g1 == g0
    # 3. components
    mask = sp[sf.SP_MASK:sf.SP_MASK + 6]
    assert np.all(out[mask == 0.0] == 0.0)
    # 4. caps on the norm and per axis, scaled by the gain
    wf, wt, pf, pt = out[:3], out[3:], p[:3], p[3:]
    assert _n(wf) <= g1 * F + TOL and _n(wt) <= g1 * T + TOL
    assert np.all(np.abs(wf) <= g1 * Fa + TOL) and np.all(np.abs(wt) <= g1 * Ta + TOL)
    # 5. rate, whenever the gain does not fall
    if g1 >= g0:
        assert _n(wf - pf) <= sp[sf.SP_FRATE] + TOL
        assert _n(wt - pt) <= sp[sf.SP_TRATE] + TOL
    # 6. ramp envelope
    if g1 > g0:
        assert _n(wf) <= _n(pf) + F * sp[sf.SP_RAMP] + TOL
        assert _n(wt) <= _n(pt) + T * sp[sf.SP_RAMP] + TOL
        assert np.all(np.abs(wf) <= np.abs(pf) + Fa * sp[sf.SP_RAMP] + TOL)
        assert np.all(np.abs(wt) <= np.abs(pt) + Ta * sp[sf.SP_RAMP] + TOL)
    # 7. fade envelope
    if g1 < g0:
        s = g1 / g0
        for j in range(6):
            assert out[j] == 0.0 or np.sign(out[j]) == np.sign(p[j]), (j, out[j], p[j])  # never crosses zero
            assert abs(out[j]) <= abs(p[j]) * s + TOL, (j, out[j], p[j], s)
        assert _n(wf - pf) <= sp[sf.SP_FRATE] + (1 - s) * _n(pf) + TOL
        assert _n(wt - pt) <= sp[sf.SP_TRATE] + (1 - s) * _n(pt) + TOL
    # 8. zero gain, zero force
    if g1 == 0.0:
        assert np.all(out == 0.0)


@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow], derandomize=True, database=None)
@given(params(), ops)
def test_every_promise_holds_over_random_sequences(p, seq):
    f = Filter(p)
    for w, target, skipped, reset in seq:
        if reset:
            sf.reset(f.ss)
        if target is not None:
            f.ss[sf.SS_TARGET] = target
        rc, before, out = f.call(w, skipped)
        check_promises(f, w, skipped, rc, before, out)


@settings(max_examples=200, deadline=None, derandomize=True, database=None)
@given(params(), st.lists(wrench, min_size=1, max_size=40), st.integers(0, 50))
def test_non_finite_anywhere_cuts_to_zero(p, seq, where):
    f = Filter(p)
    f.ss[sf.SS_TARGET] = 1.0
    for w in seq:
        f.call(w)
    bad = list(seq[where % len(seq)])
    bad[where % 6] = [math.nan, math.inf, -math.inf][where % 3]
    rc, before, out = f.call(bad)
    check_promises(f, bad, 0, rc, before, out)
    assert f.sc[sf.SC_NONFINITE] == 1


def _ramped(p: dict, w, steps: int = 20000) -> Filter:
    """A filter whose gain has reached 1 and whose output has settled on what ``w`` gives."""
    f = Filter(p)
    f.ss[sf.SS_TARGET] = 1.0
    last = None
    for _ in range(steps):
        rc, before, out = f.call(w)
        if f.ss[sf.SS_GAIN] == 1.0 and last is not None and np.array_equal(out, last):
            return f
        last = out
    raise AssertionError(f"the output did not settle in {steps} calls")


BASE = dict(max_force_n=10.0, max_torque_n_m=0.5, force_rate_n_per_step=1.0, torque_rate_n_m_per_step=0.05,
            fade_per_step=0.005, ramp_per_step=0.002, mask=(1, 1, 1, 1, 1, 1))


def test_the_norm_is_capped_on_a_diagonal():
    """A spatial command along a diagonal, and a 1-DOF device whose axis is diagonal, get the cap
    on the norm: not sqrt(3) x 10 N, not sqrt(2) x 10 N."""
    f = _ramped(BASE, [20.0, 20.0, 20.0, 2.0, 2.0, 2.0])
    assert _n(f.cmd[:3]) == pytest.approx(10.0, rel=1e-12)
    assert _n(f.cmd[3:]) == pytest.approx(0.5, rel=1e-12)
    assert f.cmd[0] == pytest.approx(10.0 / math.sqrt(3))
    f1 = _ramped(dict(BASE, mask=KIND_WRENCH_MASK["1dof"]), [15.0, 15.0, 0.0, 1.0, 1.0, 1.0])
    assert _n(f1.cmd[:3]) == pytest.approx(10.0, rel=1e-12) and np.all(f1.cmd[3:] == 0.0)
    # every component within the cap, the norm over it (8, 8: 11.3 N)
    for kind, w in (("spatial", [8.0, 8.0, 0.0, 0.4, 0.4, 0.0]), ("1dof", [8.0, 8.0, 0.0, 0.0, 0.0, 0.0]),
                    ("planar", [8.0, 8.0, 0.0, 0.0, 0.0, 0.4])):
        f2 = _ramped(dict(BASE, mask=KIND_WRENCH_MASK[kind]), w)
        assert _n(f2.cmd[:3]) == pytest.approx(10.0, rel=1e-12), kind
        assert f2.cmd[0] == pytest.approx(10.0 / math.sqrt(2))


def test_a_motor_limit_caps_its_axis_below_the_norm():
    f = _ramped(dict(BASE, max_force_axis_n=4.0), [0.0, 0.0, 9.0, 0.0, 0.0, 0.0])
    assert f.cmd[2] == pytest.approx(4.0)


def test_torque_has_its_own_cap_and_rate():
    """The review's mutations: the torque capped or rate-limited with the force's numbers."""
    f = Filter(BASE)
    f.ss[sf.SS_GAIN] = 1.0
    f.ss[sf.SS_TARGET] = 1.0
    rc, before, out = f.call([0.0, 0.0, 0.0, 5.0, 0.0, 0.0])
    assert out[3] == pytest.approx(0.05)  # the torque's rate, not the force's 1 N
    for _ in range(100):
        f.call([0.0, 0.0, 0.0, 5.0, 0.0, 0.0])
    assert f.cmd[3] == pytest.approx(0.5)  # the torque's cap, not the force's 10 N


def test_a_fade_under_a_pushing_hand_stays_inside_its_envelope():
    """A hand that keeps pushing during a fade raises the command (the coupling stretches); the
    output still falls at least as fast as the gain (3 N at gain 1 is at most 3 g N)."""
    f = _ramped(BASE, [0.0, 3.0, 0.0, 0.0, 0.0, 0.0])
    assert f.cmd[1] == pytest.approx(3.0)
    f.ss[sf.SS_TARGET] = 0.0
    push = 3.0
    for k in range(1, 202):  # 0.2 s of fade at 1 kHz, and a step
        push += 0.05
        rc, before, out = f.call([0.0, push, 0.0, 0.0, 0.0, 0.0])
        g = f.ss[sf.SS_GAIN]
        assert out[1] <= 3.0 * g + 1e-9, (k, out[1], g)
    assert f.ss[sf.SS_GAIN] == 0.0 and np.all(f.cmd == 0.0)


def test_a_stall_skips_the_gain_but_not_the_rate():
    """After 300 skipped periods the ramp-in's gain is whole, yet the output grows by at most the
    rate limit and the ramp's step per written command: force never comes back as a step."""
    f = Filter(BASE)
    f.ss[sf.SS_TARGET] = 1.0
    rc, before, out = f.call([0.0, 8.0, 0.0, 0.0, 0.0, 0.0], skipped=1000)
    assert f.ss[sf.SS_GAIN] == 1.0
    assert _n(out[:3]) <= 10.0 * BASE["ramp_per_step"] + 1e-12


def test_reset_means_the_device_renders_nothing():
    f = _ramped(BASE, [0.0, 5.0, 0.0, 0.0, 0.0, 0.0])
    sf.reset(f.ss)
    f.ss[sf.SS_TARGET] = 1.0
    rc, before, out = f.call([0.0, 5.0, 0.0, 0.0, 0.0, 0.0])
    assert _n(out) <= 10.0 * BASE["ramp_per_step"] + 1e-12  # ramps from zero, not from 5 N


def test_counters_count_what_changed_the_command():
    f = Filter(BASE)
    f.ss[sf.SS_GAIN] = 1.0
    f.ss[sf.SS_TARGET] = 1.0
    f.call([0.0, 0.5, 0.0, 0.0, 0.0, 0.0])
    assert list(f.sc) == [0, 0, 0]
    f.call([0.0, 5.0, 0.0, 0.0, 0.0, 0.0])
    assert list(f.sc) == [0, 1, 0]
    f.call([0.0, 50.0, 0.0, 0.0, 0.0, 0.0])
    assert list(f.sc) == [1, 2, 0]


@pytest.mark.parametrize("bad", [dict(max_force_n=-1.0), dict(force_rate_n_per_step=math.nan),
                                 dict(fade_per_step=math.inf)])
def test_bad_parameters_are_refused_by_name(bad):
    name = next(iter(bad))
    with pytest.raises(ValueError, match=name):
        sf.parameters(**dict(BASE, **bad))
