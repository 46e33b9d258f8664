"""Deformation recovery: a deformed contact that persists is brought back to the true geometry at
a bounded rate, so the surface is felt where it is; the force change it causes and the energy it
gives are bounded and measured; it never pulls, never makes a penetration jump and never starts
a collision."""
import numpy as np
import pytest

from hapticproxy.server.model import ContactParams, LocalModel, ToolSpec
from hapticproxy.server.model.layout import K_COLLISIONS
from hapticproxy.server.model.model import (RECOVERY_FORCE_RATE_N_PER_S, RECOVERY_MIN_AGE_UPDATES,
                                            RECOVERY_RESTING_SPEED_FACTOR, RECOVERY_SPEED_M_PER_S)
from hapticproxy.server.model.reference import reference_step

K = 4000.0
KEYS = np.array([[0, 1, 10], [0, 1, 11]])
CP = np.array([[-0.04, 0.0, 0.0], [0.04, 0.0, 0.0]])
NRM = np.array([[0.0, 1.0, 0.0], [0.0, 1.0, 0.0]])
HALF_HEIGHT = 0.010


def _deformed(mass=0.25, depth=0.004, **kw):
    """A planar box whose proxy is ``depth`` into the floor y = 0 while the engine's tool rests on
    it: the late contacts deform the proxy to just touch (eq. 4)."""
    m = LocalModel(ToolSpec.planar(mass, 1.4e-4 * mass / 0.25), ContactParams(K, 30.0), period_s=1e-3, **kw)
    m.reset([0.0, HALF_HEIGHT - depth, 0.0])
    return m


def _engine_update(m):
    """The engine's tool resting on the floor (it is held there), contacts at the true floor."""
    m.update(KEYS, CP, NRM, np.zeros(2), tool_q=[m.q[0], HALF_HEIGHT, m.q[2]])


def _run(m, seconds, push=0.5, every=20):
    f, pen, rec = [], [], []
    for i in range(int(round(seconds / m.period_s))):
        if i % every == 0:
            _engine_update(m)
        m.step([0.0, -push, 0.0])
        f.append(float(m.env_wrench[1]))
        pen.append(float(m.penalty_wrench[1]))
        rec.append(m.recovering)
    return np.array(f), np.array(pen), np.array(rec)


def test_defaults_are_documented_values():
    m = _deformed()
    assert m.recovery == {"speed_m_per_s": RECOVERY_SPEED_M_PER_S, "force_rate_n_per_s": RECOVERY_FORCE_RATE_N_PER_S,
                          "tau_s": pytest.approx(0.1), "min_age_updates": RECOVERY_MIN_AGE_UPDATES,
                          "normal_speed_max_m_per_s": pytest.approx(RECOVERY_RESTING_SPEED_FACTOR * RECOVERY_SPEED_M_PER_S)}


def test_without_recovery_the_deformation_is_kept_for_ever():
    m = _deformed(recovery_speed_m_per_s=0.0)
    _run(m, 3.0)
    assert m.q[1] == pytest.approx(HALF_HEIGHT - 0.004 - 0.5 / (2 * K), abs=1e-5)   # felt 4 mm too deep
    assert m.recovery_energy_j == 0.0


def test_recovery_brings_the_proxy_out_to_the_true_surface():
    m = _deformed()
    f, pen, rec = _run(m, 3.0)
    assert m.q[1] == pytest.approx(HALF_HEIGHT - 0.5 / (2 * K), abs=1e-6)     # on the floor, + the push's penetration
    snap = m.contacts()
    assert np.all(snap.deformation_m == 0.0)
    assert np.all(f >= 0.0)                                                    # never pulls
    assert abs(f[-1] - 0.5) < 1e-3
    assert m.counters()["collisions"] == 0     # the late contacts start resting; the recovery makes none
    # it started only once the contacts had persisted min_age updates (20 ms apart here)
    first = int(np.argmax(rec > 0))
    assert first >= RECOVERY_MIN_AGE_UPDATES * 20 - 20
    # the energy it gave: the push times the distance it moved the proxy out (quasi-static), and no more
    assert m.recovery_energy_j == pytest.approx(0.5 * 0.004, rel=0.15)


def test_recovery_force_rate_is_bounded_at_a_fixed_pose():
    # a tool too heavy to move in the time: the penalty force grows at the bound, shared by both contacts
    m = _deformed(mass=1e4, recovery_min_age_updates=0)
    _engine_update(m)
    f, pen, rec = _run(m, 0.2, push=0.0, every=10_000)
    growing = rec[1:] > 0
    dstep = np.diff(pen)[growing]
    assert np.max(dstep) <= RECOVERY_FORCE_RATE_N_PER_S * m.period_s * 1.001
    assert np.max(dstep) >= 0.95 * RECOVERY_FORCE_RATE_N_PER_S * m.period_s     # and at that rate
    assert np.all(pen >= 0.0)


def test_recovery_speed_is_bounded():
    m = _deformed(recovery_force_rate_n_per_s=1e6, recovery_tau_s=0.0, recovery_min_age_updates=0)
    _engine_update(m)
    m.step([0.0, -0.5, 0.0])
    r0 = m.contacts().recovered_m.copy()
    for _ in range(100):
        m.step([0.0, -0.5, 0.0])
    r1 = m.contacts().recovered_m
    np.testing.assert_allclose(r1 - r0, 100 * m.period_s * RECOVERY_SPEED_M_PER_S, rtol=1e-9)


def test_young_or_apart_contacts_are_not_recovered():
    m = _deformed(recovery_min_age_updates=5)
    for _ in range(4):                           # four updates: too young
        _engine_update(m)
        for _ in range(20):
            m.step([0.0, -0.5, 0.0])
    assert m.contacts().recovered_m.max() == 0.0
    # pulled off the floor: once the contacts are apart, nothing is recovered against them
    m2 = _deformed(recovery_min_age_updates=0)
    _engine_update(m2)
    for _ in range(300):
        m2.step([0.0, 3.0, 0.0])
    assert np.all(m2.proxy_separations() > 0)
    r = m2.contacts().recovered_m.copy()
    for _ in range(300):
        m2.step([0.0, 3.0, 0.0])
    np.testing.assert_array_equal(m2.contacts().recovered_m, r)
    assert m2.recovering == 0


def test_a_contact_moving_fast_along_its_normal_is_not_recovered():
    # the floor moving up into a heavy proxy at 0.1 m/s (a piston): the proxy does not rest on
    # it; pushing the constraint further would feed the motion (as a hand shaking the peg would)
    m = _deformed(mass=1e4, recovery_min_age_updates=0)
    m.update(KEYS, CP, NRM, np.zeros(2), np.full(2, 0.1), tool_q=[0.0, HALF_HEIGHT, 0.0])
    for _ in range(20):
        m.step([0.0, 0.0, 0.0])
    assert m.contacts().normal_velocity_m_per_s.max() < -RECOVERY_RESTING_SPEED_FACTOR * RECOVERY_SPEED_M_PER_S
    assert m.recovering == 0 and m.contacts().recovered_m.max() == 0.0
    # the same floor at rest: recovered
    m.update(KEYS, CP, NRM, np.zeros(2), np.zeros(2), tool_q=[0.0, HALF_HEIGHT, 0.0])
    for _ in range(20):
        m.step([0.0, 0.0, 0.0])
    assert m.recovering == 2 and m.contacts().recovered_m.min() > 0.0


def test_an_update_keeps_what_was_recovered():
    m = _deformed(recovery_min_age_updates=0)
    _engine_update(m)
    for _ in range(80):
        m.step([0.0, -0.5, 0.0])
    s_before = m.proxy_separations().copy()
    assert m.contacts().recovered_m.min() > 0.001
    _engine_update(m)                           # the same contacts again: eq. 5 keeps s_p, recovery included
    np.testing.assert_allclose(m.proxy_separations(), s_before, atol=1e-12)
    assert np.all(m.contacts().recovered_m == 0.0) and np.all(m.contacts().deformation_m > 0.0)


def test_recovery_never_makes_a_touching_contact_collide_again():
    m = _deformed(recovery_min_age_updates=0)
    _run(m, 1.0)
    assert m.counters()["collisions"] == 0     # the late contacts start resting (eq. 4 at rest)
    assert m.arrays()[4][K_COLLISIONS] == 0


def test_numpy_reference_recovers_the_same_way():
    m = _deformed(recovery_min_age_updates=0)
    _engine_update(m)
    for i in range(300):
        hand = np.array([0.0, -0.5, 0.01 * np.sin(i / 30.0)])
        par, st, C, CI, cnt = m.arrays()
        rst, rC, rCI, rcnt = reference_step(m.kind, par, st, C, CI, cnt, hand)
        m.step(hand)
        for got, want in ((st, rst), (C, rC)):
            g = np.where(np.isinf(got), 0.0, got)
            w = np.where(np.isinf(want), 0.0, want)
            np.testing.assert_allclose(g, w, rtol=1e-9, atol=1e-12)
        np.testing.assert_array_equal(cnt, rcnt)
    assert m.recovery_energy_j > 0


@pytest.mark.parametrize("cut", [0.0, 0.5, 1.0])
def test_the_passivity_layers_cut_slows_the_recovery_and_the_reference_agrees(cut):
    """``P_REC_CUT`` (the controller writes the passivity layer's limiting factor there): the
    recovery's speed is ``(1 - cut)`` of its own, none at an empty tank; the numpy reference the same."""
    from hapticproxy.server.model.layout import P_REC_CUT

    m = _deformed(recovery_force_rate_n_per_s=1e6, recovery_tau_s=0.0, recovery_min_age_updates=0)
    _engine_update(m)
    m.arrays()[0][P_REC_CUT] = cut
    m.step([0.0, -0.5, 0.0])
    r0 = m.contacts().recovered_m.copy()
    for _ in range(50):
        par, st, C, CI, cnt = m.arrays()
        _, rC, _, _ = reference_step(m.kind, par, st, C, CI, cnt, np.array([0.0, -0.5, 0.0]))
        m.step([0.0, -0.5, 0.0])
        np.testing.assert_allclose(C[:2], rC[:2], rtol=1e-9, atol=1e-12)
    r1 = m.contacts().recovered_m
    np.testing.assert_allclose(r1 - r0, (1.0 - cut) * 50 * m.period_s * RECOVERY_SPEED_M_PER_S, rtol=1e-9, atol=1e-15)


@pytest.mark.parametrize("field,value", [("recovery_speed_m_per_s", -0.01), ("recovery_speed_m_per_s", float("nan")),
                                         ("recovery_force_rate_n_per_s", 0.0), ("recovery_tau_s", -1.0),
                                         ("recovery_min_age_updates", -1), ("recovery_min_age_updates", 2.5),
                                         ("recovery_normal_speed_max_m_per_s", -0.1)])
def test_bad_recovery_settings_are_refused_by_name(field, value):
    with pytest.raises(ValueError, match=field):
        LocalModel(ToolSpec.planar(0.25, 1.4e-4), ContactParams(K, 30.0), period_s=1e-3, **{field: value})
    m = LocalModel(ToolSpec.planar(0.25, 1.4e-4), ContactParams(K, 30.0), period_s=1e-3)
    before = m.recovery
    kw = {"speed_m_per_s": RECOVERY_SPEED_M_PER_S}
    kw[field.removeprefix("recovery_")] = value
    with pytest.raises(ValueError, match=field):
        m.set_recovery(**kw)
    assert m.recovery == before


def test_without_the_engines_tool_pose_nothing_is_recovered():
    # the paper's eq. 1 (no tool_q): the reported separation is the engine tool's, the model does
    # not know where the true surface is relative to the proxy. The engine reports its tool 3 mm
    # in while the proxy is barely touching: eq. 5 keeps the proxy's penetration, as always, and
    # nothing is "recovered" towards the engine tool's 3 mm
    m = _deformed(recovery_min_age_updates=0)
    m.update(KEYS, CP, NRM, np.zeros(2))
    for i in range(600):
        if i % 20 == 0:
            m.update(KEYS, CP, NRM, np.full(2, -0.003))
        m.step([0.0, -0.5, 0.0])
    assert m.contacts().deformation_m.max() == 0.0 and m.recovery_energy_j == 0.0
    assert np.all(m.proxy_separations() > -0.001)
    # the same with the engine's tool pose: a deformation of about 3 mm, recovered
    e = _deformed(recovery_min_age_updates=0)
    e.update(KEYS, CP, NRM, np.zeros(2), tool_q=e.q.copy())
    for i in range(600):
        if i % 20 == 0:
            e.update(KEYS, CP, NRM, np.full(2, -0.003), tool_q=e.q.copy())
        e.step([0.0, -0.5, 0.0])
    assert e.recovery_energy_j > 0.0
