"""Each equation of the local model against a hand-computed case."""
import math

import numpy as np
import pytest

from hapticproxy.server.model.layout import S_Q


def test_eq1_rigid_policy_puts_the_contact_at_the_reported_separation(make_model, cs):
    m = make_model("planar", policy="rigid")
    m.reset(q=[0.1, 0.2, 0.3])
    cp, n, d = [0.15, 0.18, 0.0], [0.0, 1.0, 0.0], -0.002
    m.update(*cs([(1, cp, n, d)]))
    c, s = math.cos(0.3), math.sin(0.3)
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    expected = R.T @ (np.array(cp) + d * np.array(n) - np.array([0.1, 0.2, 0.0]))    # eq. 1
    np.testing.assert_allclose(m.contacts().local_point_body_m[0], expected, atol=1e-15)
    np.testing.assert_allclose(m.proxy_separations(), [d], atol=1e-15)


def test_eq3_separation_follows_the_proxy(make_model, cs):
    m = make_model("1dof")
    m.reset(q=[0.0], qd=[0.5])
    m.update(*cs([(1, [0.02, 0, 0], [-1, 0, 0], 0.01)]))          # right wall, 10 mm ahead
    for _ in range(5):
        m.step([0.0])
    # eq. 3 by hand: s = n . (c + p - c_p), p = c_p + d n - c0 at the update (c0 = 0)
    p = np.array([0.02 - 0.01, 0, 0])
    s_now = np.dot([-1, 0, 0], np.array([m.q[0], 0, 0]) + p - np.array([0.02, 0, 0]))
    np.testing.assert_allclose(m.proxy_separations(), [s_now], atol=1e-15)
    np.testing.assert_allclose(s_now, 0.01 - 5 * 1e-3 * 0.5, atol=1e-15)


def test_eq2_constraint_moves_with_its_normal_velocity(make_model, cs):
    m = make_model("1dof")
    m.update(*cs([(1, [0.02, 0, 0], [-1, 0, 0], 0.01, 0.5)]))      # wall approaching at 0.5 m/s
    seps = []
    for _ in range(4):
        m.step([0.0])
        seps.append(m.contacts().separation_m[0])
    # the separation seen at step i (time i dt) is d - v_constr * i dt, proxy at rest
    np.testing.assert_allclose(seps, [0.01 - 0.5 * i * 1e-3 for i in range(4)], atol=1e-15)


# --- the update rule table of the notes (eqs. 4, 5, 6) -------------------------------------
def _existing(make_model, cs, s_p):
    """A right-wall contact whose proxy separation is s_p at the next update."""
    m = make_model("1dof")
    m.update(*cs([(1, [0.0, 0, 0], [-1, 0, 0], 0.005)]))           # true geometry, s = 5 mm
    par, st, *_ = m.arrays()
    st[S_Q] = 0.005 - s_p                                           # move the proxy by hand
    np.testing.assert_allclose(m.proxy_separations(), [s_p], atol=1e-15)
    return m


@pytest.mark.parametrize("d, expected, deformed", [
    (0.003, 0.003, 0),      # new, d > 0: eq. 6, true geometry (predicted contact)
    (-0.004, 0.0, 1),       # new, d <= 0: eq. 4, proxy deformed to just touch
    (0.0, 0.0, 1),
])
def test_new_contact_rules(make_model, cs, d, expected, deformed):
    m = make_model("1dof")
    m.update(*cs([(7, [0.0, 0, 0], [-1, 0, 0], d)]))
    np.testing.assert_allclose(m.proxy_separations(), [expected], atol=1e-15)
    assert m.counters()["deformed"] == deformed
    assert m.counters()["new"] == 1


@pytest.mark.parametrize("s_p, d, expected, deformed", [
    (-0.002, 0.003, 0.003, 0),    # existing, d > 0: true geometry (eq. 6)
    (0.001, 0.003, 0.003, 0),
    (-0.004, -0.001, -0.001, 0),  # existing, s_p < d <= 0: true geometry, penetration shrinks
    (-0.001, -0.004, -0.001, 1),  # existing, d < s_p <= 0: keep the proxy's penetration (eq. 5)
    (0.002, -0.003, 0.0, 1),      # existing, d <= 0 < s_p: just touch (eq. 4)
])
def test_existing_contact_rules(make_model, cs, s_p, d, expected, deformed):
    m = _existing(make_model, cs, s_p)
    m.update(*cs([(1, [0.0, 0, 0], [-1, 0, 0], d)]))
    np.testing.assert_allclose(m.proxy_separations(), [expected], atol=1e-15)
    assert m.counters()["deformed"] == deformed
    assert m.counters()["new"] == 1 and m.contacts().age_updates[0] == 1


@pytest.mark.parametrize("s_p, d", [(-0.001, -0.004), (0.002, -0.003), (-0.004, -0.001)])
def test_rigid_policy_always_uses_eq1(make_model, cs, s_p, d):
    m = make_model("1dof", policy="rigid")
    m.update(*cs([(1, [0.0, 0, 0], [-1, 0, 0], 0.005)]))
    m.arrays()[1][S_Q] = 0.005 - s_p
    m.update(*cs([(1, [0.0, 0, 0], [-1, 0, 0], d)]))
    np.testing.assert_allclose(m.proxy_separations(), [d], atol=1e-15)
    assert m.counters()["deformed"] == 0


def test_contacts_missing_from_an_update_leave_the_model(make_model, cs):
    m = make_model("planar")
    m.update(*cs([(1, [0, -0.01, 0], [0, 1, 0], 0.001), (2, [0.01, 0, 0], [-1, 0, 0], 0.001)]))
    m.update(*cs([(2, [0.01, 0, 0], [-1, 0, 0], 0.002)]))
    snap = m.contacts()
    assert snap.keys[:, 1].tolist() == [2]
    assert m.counters()["left"] == 1


# --- eq. 7: proxy dynamics -------------------------------------------------------------------
def test_eq7_free_planar_acceleration(make_model):
    m = make_model("planar", mass=2.0, inertia=0.05)
    m.step([4.0, -2.0, 0.1])
    np.testing.assert_allclose(m.qd, [4.0 / 2 * 1e-3, -2.0 / 2 * 1e-3, 0.1 / 0.05 * 1e-3], rtol=1e-14)
    # semi-implicit Euler: the position uses the new velocity
    np.testing.assert_allclose(m.q, m.qd * 1e-3, rtol=1e-14)


def test_eq7_hand_offset_makes_a_torque(make_model):
    m = make_model("spatial", mass=1.0, inertia=(0.1, 0.2, 0.3), hand=(0.0, 0.1, 0.0))
    m.step([2.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    # tau = r x f = (0, 0.1, 0) x (2, 0, 0) = (0, 0, -0.2); I_zz = 0.3
    np.testing.assert_allclose(m.qd, [2e-3, 0, 0, 0, 0, -0.2 / 0.3 * 1e-3], atol=1e-15)


def test_gravity_is_optional(make_model):
    m = make_model("1dof", gravity=(0.0, 0.0, -9.81), axis=(0.0, 0.0, 1.0))
    m.step([0.0])
    np.testing.assert_allclose(m.qd, [-9.81e-3], rtol=1e-14)
    assert make_model("1dof").step([0.0])[0] == 0.0


# --- resting contact: unilateral penalty -----------------------------------------------------
@pytest.mark.parametrize("integrator", ["explicit", "implicit"])
def test_penalty_force_is_k_s_plus_b_v_and_never_pulls(make_model, cs, integrator):
    m = make_model("1dof", k=1000.0, b=10.0, integrator=integrator)
    m.update(*cs([(1, [0.0, 0, 0], [1, 0, 0], 0.0)]))      # left wall touching (eq. 4 touch)
    m.arrays()[1][S_Q] = -0.002                            # 2 mm in
    m.step([0.0])                                          # first step: colliding, v = 0
    m.arrays()[1][S_Q] = -0.002
    m.arrays()[1][8] = -0.01                               # moving further in at 1 cm/s
    f = m.step([0.0])[0]
    f0 = 1000 * 0.002 + 10 * 0.01
    if integrator == "explicit":
        assert f == pytest.approx(f0, rel=1e-12)
    else:
        # the force at the step's end, linearised: f0 - (b + dt k) dv with (m + dt b + dt^2 k) dv
        # = dt f0, i.e. f0 m / (m + dt b + dt^2 k); and it is the force that moved the proxy
        dt = 1e-3
        assert f == pytest.approx(f0 * 1.0 / (1.0 + dt * 10.0 + dt * dt * 1000.0), rel=1e-12)
        assert m.qd[0] == pytest.approx(-0.01 + dt * f / 1.0, rel=1e-12)
    m.arrays()[1][S_Q] = -0.0001
    m.arrays()[1][8] = 1.0                                 # leaving fast: -k s - b v < 0
    assert m.step([0.0])[0] == 0.0
    assert m.contacts().state == ["separating"]


# --- eq. 8: force to the hand through the dynamically consistent inverse ---------------------
@pytest.mark.parametrize("integrator", ["explicit", "implicit"])
def test_eq8_rendered_wrench_at_an_offset_hand(make_model, cs, integrator):
    hx = 0.05
    m = make_model("planar", k=1000.0, mass=1.0, inertia=0.01, hand=(hx, 0.0), integrator=integrator)
    # a floor contact under a body point r = (0.02, -0.01), penetrating 1 mm, at rest
    m.update(*cs([(1, [0.02, -0.01, 0], [0, 1, 0], 0.0)]))
    m.step([0.0, 0.0, 0.0])                               # collision step at zero velocity
    m.arrays()[1][S_Q + 1] = -0.001
    m.arrays()[1][8:11] = 0.0
    f_env = m.step([0.0, 0.0, 0.0]).copy()
    fy = 1000 * 0.001
    if integrator == "implicit":
        fy = m.contacts().normal_force_n[0]               # the step's force, at its end
        assert fy == pytest.approx(1000 * 0.001, rel=2e-3)
    # generalized force (0, fy, r_x fy); wrench at the hand: T = tau_z - h_x F_y
    np.testing.assert_allclose(f_env, [0.0, fy, 0.02 * fy - hx * fy], atol=1e-12)


# --- eqs. 11-12: collision impulse ------------------------------------------------------------
@pytest.mark.parametrize("e", [0.0, 0.5, 1.0])
def test_eq11_eq12_single_contact(make_model, cs, e):
    m = make_model("1dof", mass=2.0, k=1000.0, b=5.0, e=e)
    m.reset(qd=[-0.2])
    m.update(*cs([(1, [0.0, 0, 0], [1, 0, 0], -0.001)]))  # arrives late: touch (eq. 4)
    f = m.step([0.0])[0]
    p = (1 + e) * 2.0 * 0.2                                # -(1+e) m v_n
    assert m.contacts().impulse_n_s[0] == pytest.approx(p, rel=1e-12)
    assert m.impulsive_wrench[0] == pytest.approx(p / 1e-3, rel=1e-12)   # eq. 12
    assert m.contacts().state == ["colliding"] and m.proxy_state == "colliding"
    ke0, ke1 = m.collision_energy_j
    assert ke1 == pytest.approx(e * e * ke0, rel=1e-12, abs=1e-18)
    assert f == pytest.approx(p / 1e-3 + m.penalty_wrench[0], rel=1e-12)


# --- contact and proxy states (section IV-A) ------------------------------------------------
def test_contact_state_sequence(make_model, cs):
    m = make_model("1dof", k=2000.0, b=0.0, e=0.0)
    m.reset(qd=[0.1])
    m.update(*cs([(1, [0.0015, 0, 0], [-1, 0, 0], 0.0015)]))   # predicted, 1.5 mm ahead
    states, proxy = [], []
    for i in range(40):
        m.step([2.0 if i < 25 else -20.0])
        states.append(m.contacts().state[0])
        proxy.append(m.proxy_state)
    first = {s: states.index(s) for s in set(states)}
    assert first["impending"] < first["colliding"] < first["penetrating"] < first["separating"]
    assert states.count("colliding") == 1
    assert proxy[first["impending"]] == "free"
    assert proxy[first["colliding"]] == "colliding"
    assert proxy[first["penetrating"]] == "resting"


# --- dry friction, from local information only -----------------------------------------------
def _on_floor(make_model, cs, mus, muk, integrator="implicit"):
    m = make_model("planar", k=5000.0, b=50.0, mus=mus, muk=muk, mass=1.0, inertia=0.01, integrator=integrator)
    m.update(*cs([(1, [-0.01, -0.01, 0], [0, 1, 0], 0.0), (2, [0.01, -0.01, 0], [0, 1, 0], 0.0)]))
    for _ in range(600):
        m.step([0.0, -10.0, 0.0])                      # press down with 10 N
    return m


def test_friction_sticks_below_mu_s_normal_force(make_model, cs):
    m = _on_floor(make_model, cs, 0.5, 0.3)
    x0 = m.q[0]
    for _ in range(1500):
        # 2.5 N < 0.5 * 10 N, with the torque that cancels the tipping moment of the floor friction
        m.step([2.5, -10.0, 0.025])
    snap = m.contacts()
    assert not snap.slipping.any()
    assert snap.friction_force_n[:, 0].sum() == pytest.approx(-2.5, rel=1e-3)
    assert abs(m.q[0] - x0) < 2.5 / 5000.0            # only the stick spring's deflection
    assert abs(m.qd[0]) < 1e-4                        # at rest but for a lightly damped rocking mode


@pytest.mark.parametrize("integrator", ["explicit", "implicit"])
def test_friction_slips_above_mu_s_at_the_kinetic_level(make_model, cs, integrator):
    m = _on_floor(make_model, cs, 0.5, 0.3, integrator)
    for _ in range(500):
        m.step([6.0, -10.0, 0.0])                      # 6 N > 0.5 * 10 N
    snap = m.contacts()
    assert snap.slipping.all()
    fn = snap.normal_force_n.sum()
    assert fn == pytest.approx(10.0, rel=2e-2)
    # the kinetic force is mu_k times the normal force at the step's start; the implicit step
    # reports the normal force at its end, which differs by what the step's motion changed
    assert np.linalg.norm(snap.friction_force_n, axis=1).sum() == pytest.approx(
        0.3 * fn, rel=1e-9 if integrator == "explicit" else 1e-4)
    assert m.qd[0] > 0.1                               # accelerating at (6 - 3) / 1 m/s^2


@pytest.mark.parametrize("policy, eps", [("lm0", 0.0), ("lm", 0.005), ("deformation", 0.0)])
def test_lm_policies_share_the_deformation_rules(make_model, cs, policy, eps):
    from hapticproxy.server.model import ContactParams, LocalModel, ToolSpec
    m = LocalModel(ToolSpec.one_dof(1.0), ContactParams(), policy=policy, epsilon_m=eps)
    m.update(*cs([(1, [0.0, 0, 0], [-1, 0, 0], -0.004)]))
    np.testing.assert_allclose(m.proxy_separations(), [0.0], atol=1e-15)     # eq. 4, not eq. 1
