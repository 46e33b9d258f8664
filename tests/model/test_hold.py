"""Set-position modulation: a constraint the engine moves into the tool (``v_constr > 0``) advances
only as far as the passivity layer's budget allows (``P_REC_CUT``, the layer's limiting factor);
the part held back becomes deformation, which the recovery completes once the budget is back.
Receding and separated constraints are never held. The numpy reference agrees step for step."""
import numpy as np
import pytest
from hypothesis import given, strategies as st

from hapticproxy.server.model import ContactParams, LocalModel, ToolSpec
from hapticproxy.server.model.kernels import _plane_speed
from hapticproxy.server.model.layout import C_DEF, C_S, C_REC, C_VN, K_HELD, P_REC_CUT, TOUCH_TOL_M
from hapticproxy.server.model.reference import reference_step

K = 4000.0
KEYS = np.array([[0, 1, 10], [0, 1, 11]])
CP = np.array([[-0.04, 0.0, 0.0], [0.04, 0.0, 0.0]])
NRM = np.array([[0.0, 1.0, 0.0], [0.0, 1.0, 0.0]])
HALF_HEIGHT = 0.010
PUSH = np.array([0.0, -0.5, 0.0])


def _resting(vc, **kw):
    """A planar 0.25 kg box resting on the floor y = 0 under a 0.5 N push, the floor then moving
    along +y (into the tool) at ``vc`` m/s: the engine's update says so (``v_constr``)."""
    m = LocalModel(ToolSpec.planar(0.25, 1.4e-4), ContactParams(K, 30.0), period_s=1e-3,
                   recovery_min_age_updates=0, **kw)
    m.reset([0.0, HALF_HEIGHT, 0.0])
    m.update(KEYS, CP, NRM, np.zeros(2), tool_q=[0.0, HALF_HEIGHT, 0.0])
    for _ in range(300):                       # settle on the still floor
        m.step(PUSH)
    # the engine reports its tool where the proxy is, pressed into the floor as far as the proxy
    s_m = m.arrays()[2][:2, C_S].copy()
    m.update(KEYS, CP, NRM, s_m, np.full(2, vc), tool_q=list(m.q))
    return m


@pytest.mark.parametrize("cut", [0.0, 0.5, 1.0])
def test_the_cut_holds_back_the_share_of_an_advancing_constraint_and_the_reference_agrees(cut):
    vc = 0.02
    m = _resting(vc, recovery_speed_m_per_s=0.0)   # nothing completes it: the hold alone
    y0 = float(m.q[1])
    m.arrays()[0][P_REC_CUT] = cut
    for i in range(200):
        par, st_, C, CI, cnt = m.arrays()
        rst, rC, rCI, rcnt = reference_step(m.kind, par, st_, C, CI, cnt, PUSH)
        m.step(PUSH)
        np.testing.assert_allclose(C[:2], rC[:2], rtol=1e-9, atol=1e-12)
        np.testing.assert_array_equal(CI[:2], rCI[:2])      # the states, from the held plane's speed
        np.testing.assert_allclose(m.q, rst[1:4], rtol=1e-9, atol=1e-12)
        # nothing has advanced yet at the update's own step
        assert cnt[K_HELD] == rcnt[K_HELD] == (2 if cut > 0 and i > 0 else 0)
    # the proxy rides on the floor at the share (1 - cut) of its speed; the rest is deformation
    assert float(m.q[1]) - y0 == pytest.approx((1.0 - cut) * vc * 0.2, abs=2e-4)
    C = m.arrays()[2]
    np.testing.assert_allclose(C[:2, C_DEF], cut * vc * 0.199, rtol=1e-9)
    np.testing.assert_allclose(C[:2, C_REC], -cut * vc * 0.199, rtol=1e-9)
    if cut == 1.0:
        # the proxy's normal speed is against the held plane, which stands still: no damper push
        np.testing.assert_allclose(C[:2, C_VN], 0.0, atol=1e-6)
    assert m.held == (2 if cut > 0 else 0)


def test_a_held_advance_is_completed_by_the_recovery_once_the_budget_is_back():
    vc = 0.02
    m = _resting(vc)
    y0 = float(m.q[1])
    m.arrays()[0][P_REC_CUT] = 1.0
    for _ in range(200):
        m.step(PUSH)
    assert float(m.q[1]) == pytest.approx(y0, abs=1e-5)           # held: the floor did not push
    assert m.arrays()[2][0, C_DEF] == pytest.approx(vc * 0.199, rel=1e-6)
    # the engine's next update: its floor and tool have moved up by what was held; the rules
    # turn the held part into this contact's deformation, the recovery completes it
    m.arrays()[0][P_REC_CUT] = 0.0
    up = np.array([0.0, vc * 0.2, 0.0])
    m.update(KEYS, CP + up, NRM, np.zeros(2), np.zeros(2), tool_q=[m.q[0], HALF_HEIGHT + up[1], m.q[2]])
    for _ in range(3000):
        m.step(PUSH)
    # the floor is where the engine moved it: the proxy rests on it (pushed 0.5 N into k)
    assert float(m.q[1]) == pytest.approx(y0 + vc * 0.2, abs=1e-4)
    assert m.arrays()[2][0, C_DEF] == pytest.approx(0.0, abs=1e-9)


@pytest.mark.parametrize("vc", [-0.02, 0.02])
def test_a_receding_or_separated_constraint_is_never_held(vc):
    m = _resting(vc)
    if vc > 0:
        m.reset([0.0, HALF_HEIGHT + 0.05, 0.0])      # 50 mm above the floor: it approaches on time
    m.arrays()[0][P_REC_CUT] = 1.0
    for _ in range(100):
        m.step(np.zeros(3))
        assert m.held == 0
    assert m.arrays()[2][0, C_DEF] == 0.0


_speeds = st.floats(-10.0, 10.0, allow_nan=False)
_cuts = st.floats(-1.0, 2.0, allow_nan=False) | st.just(float("nan"))
_seps = st.floats(-0.01, 0.01, allow_nan=False) | st.just(TOUCH_TOL_M) | st.just(float("inf"))


@given(_speeds, _seps, _cuts)
def test_plane_speed_contract(vc, sprev, cut):
    v = _plane_speed(vc, sprev, cut)
    if vc > 0 and sprev <= TOUCH_TOL_M and cut > 0:
        assert 0.0 <= v <= vc
        assert v == (0.0 if cut >= 1 else vc * (1.0 - cut))
    else:
        assert v == vc


@given(st.floats(0.001, 10.0), st.floats(0.0, 1.0), st.floats(0.0, 1.0))
def test_plane_speed_is_monotone_in_the_cut(vc, c1, c2):
    lo, hi = min(c1, c2), max(c1, c2)
    assert _plane_speed(vc, 0.0, hi) <= _plane_speed(vc, 0.0, lo)


@pytest.mark.parametrize("cut", [0.0, 0.5, 1.0])
def test_the_rigid_policy_takes_the_share_of_a_jump_the_layer_allows(cut):
    """The rigid policy takes an update's depth at once (eq. 1, the paper's baseline): a floor
    that jumps 2 mm into the resting tool (the same contact: within ``2 REKEY_DISTANCE_M``) is
    2 mm deeper at once, a force step of 8 N per contact. With the layer short, only ``1 - cut`` of the jump is taken; the rest is
    deformation (``C_DEF``), completed when the budget is back."""
    jump = 0.002
    m = LocalModel(ToolSpec.planar(0.25, 1.4e-4), ContactParams(K, 30.0), period_s=1e-3, policy="rigid",
                   recovery_speed_m_per_s=0.0)
    m.reset([0.0, HALF_HEIGHT, 0.0])
    m.update(KEYS, CP, NRM, np.zeros(2), tool_q=[0.0, HALF_HEIGHT, 0.0])
    for _ in range(300):
        m.step(PUSH)
    s0 = m.proxy_separations()[:2]
    m.arrays()[0][P_REC_CUT] = cut
    deformed = m.counters()["deformed"]
    up = np.array([0.0, jump, 0.0])
    m.update(KEYS, CP + up, NRM, s0 - jump, tool_q=list(m.q))
    C = m.arrays()[2]
    np.testing.assert_allclose(C[:2, C_DEF], cut * jump, rtol=1e-9, atol=1e-15)
    assert m.counters()["deformed"] - deformed == (2 if cut > 0 else 0)
    np.testing.assert_allclose(m.proxy_separations()[:2], s0 - (1.0 - cut) * jump, rtol=1e-9, atol=1e-15)
    # a new contact that arrives penetrating: the same share
    m2 = LocalModel(ToolSpec.planar(0.25, 1.4e-4), ContactParams(K, 30.0), period_s=1e-3, policy="rigid")
    m2.reset([0.0, HALF_HEIGHT - jump, 0.0])
    m2.arrays()[0][P_REC_CUT] = cut
    m2.update(KEYS, CP, NRM, np.full(2, -jump), tool_q=list(m2.q))
    np.testing.assert_allclose(m2.arrays()[2][:2, C_DEF], cut * jump, rtol=1e-9, atol=1e-15)


@given(st.floats(-0.1, 0.1), st.floats(-0.1, 0.0), _cuts)
def test_held_depth_contract(dr, now, cut):
    from hapticproxy.server.model.kernels import _held_depth
    off = _held_depth(dr, now, cut)
    if cut > 0 and dr < now:
        assert dr <= off <= now
        assert off == (now if cut >= 1 else dr + cut * (now - dr))
    else:
        assert off == dr


@given(st.floats(-0.1, -1e-6), st.floats(0.0, 1.0), st.floats(0.0, 1.0))
def test_held_depth_is_monotone_in_the_cut(dr, c1, c2):
    from hapticproxy.server.model.kernels import _held_depth
    lo, hi = min(c1, c2), max(c1, c2)
    assert _held_depth(dr, 0.0, lo) <= _held_depth(dr, 0.0, hi)


def test_an_approaching_constraint_arrives_on_time_and_is_held_from_the_step_after_it_touches():
    """A floor rising at 50 mm/s towards a box 1 mm above it with the layer half short: it is not
    held while apart (it arrives when the engine says), and from the step after the first touch
    it is (the step that first touches saw an advance made while apart: its damper sees the full
    speed). The numpy reference agrees at every step, the touching one included."""
    m = LocalModel(ToolSpec.planar(0.25, 1.4e-4), ContactParams(K, 30.0), period_s=1e-3,
                   recovery_speed_m_per_s=0.0)
    m.reset([0.0, HALF_HEIGHT + 0.001, 0.0])
    m.update(KEYS, CP, NRM, np.full(2, 0.001), np.full(2, 0.05), tool_q=list(m.q))
    m.arrays()[0][P_REC_CUT] = 0.5
    touched = None
    for i in range(60):
        par, st_, C, CI, cnt = m.arrays()
        rst, rC, rCI, rcnt = reference_step(m.kind, par, st_, C, CI, cnt, np.zeros(3))
        m.step(np.zeros(3))
        np.testing.assert_allclose(C[:2], rC[:2], rtol=1e-9, atol=1e-12)
        np.testing.assert_array_equal(CI[:2], rCI[:2])
        assert cnt[K_HELD] == rcnt[K_HELD]
        if touched is None and C[0, C_S] <= TOUCH_TOL_M:
            touched = i
            assert cnt[K_HELD] == 0                              # apart until now: nothing held
    assert touched is not None and 18 <= touched <= 22           # 1 mm at 50 mm/s: on time
    assert m.held == 2
