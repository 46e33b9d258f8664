"""Simultaneous collision impulses (eq. 11) in the tool's configuration space."""
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st
from linkage_helpers import random_normals

from hapticproxy.server.model import ContactParams, LocalModel, ToolSpec
from hapticproxy.server.model.reference import rigid_kinematics


def _touching_scene(kind, rng, n, e):
    """n new contacts that the proxy touches (they arrived late: eq. 4), proxy moving."""
    tool = {"planar": ToolSpec.planar(0.7, 2e-3), "spatial": ToolSpec.spatial(0.7, (1e-3, 2e-3, 2.5e-3)),
            "1dof": ToolSpec.one_dof(0.7)}[kind]
    m = LocalModel(tool, ContactParams(3000.0, 10.0, e), period_s=1e-3, capacity=64)
    m.reset(qd=rng.normal(size=m.dof) * 0.3)
    nrm = random_normals(rng, n, kind)
    pts = rng.normal(size=(n, 3)) * 0.02
    if kind == "planar":
        pts[:, 2] = 0.0
    keys = np.zeros((n, 3), dtype=np.int64)
    keys[:, 1] = np.arange(n)
    m.update(keys, pts, nrm, -rng.uniform(0, 0.003, n))
    return m


def _post_impulse_velocity(m, q0, qd0):
    """Velocity right after the impulse: qd0 + D(q0)^-1 Jc^T p (eq. 10)."""
    D = rigid_kinematics(m.kind, m.arrays()[0], q0, np.zeros((0, 3)))[0]
    return qd0 + np.linalg.solve(D, m.generalized_impulse)


@pytest.mark.parametrize("kind", ["1dof", "planar", "spatial"])
def test_plastic_impulse_removes_approaching_normal_velocity_everywhere(kind):
    rng = np.random.default_rng(3)
    checked = 0
    for _ in range(40):
        m = _touching_scene(kind, rng, int(rng.integers(1, 10)), e=0.0)
        qd0 = m.qd.copy()
        q0 = m.q.copy()
        m.step(np.zeros(m.hand_dim))
        snap = m.contacts()
        in_set = np.isin(snap.state, ["colliding", "penetrating"])
        if not np.any(np.array(snap.state) == "colliding"):
            continue
        qd1 = _post_impulse_velocity(m, q0, qd0)
        _, _, _, J, _ = rigid_kinematics(m.kind, m.arrays()[0], q0, snap.local_point_body_m)
        vn1 = np.einsum("ij,ijk,k->i", snap.normal, J, qd1)
        # Newton's law with e = 0 at every colliding and penetrating contact (eq. 9); contacts
        # outside the set (separating, impending) are not constrained by eq. 11
        np.testing.assert_allclose(vn1[in_set], 0.0, atol=1e-9)
        checked += 1
    assert checked >= 10


@pytest.mark.parametrize("kind", ["planar", "spatial"])
def test_elastic_impulse_keeps_kinetic_energy(kind):
    rng = np.random.default_rng(5)
    hits = 0
    for _ in range(30):
        m = _touching_scene(kind, rng, int(rng.integers(1, 8)), e=1.0)
        m.step(np.zeros(m.hand_dim))
        if m.counters()["collisions"]:
            ke0, ke1 = m.collision_energy_j
            assert ke1 == pytest.approx(ke0, rel=1e-12)
            hits += 1
    assert hits > 10


@settings(max_examples=200, deadline=None)
@given(kind=st.sampled_from(["1dof", "planar", "spatial"]), seed=st.integers(0, 2**32 - 1),
       n=st.integers(1, 40), e=st.floats(0.0, 1.0))
def test_kinetic_energy_never_increases_in_a_collision(kind, seed, n, e):
    m = _touching_scene(kind, np.random.default_rng(seed), n, e)
    m.step(np.zeros(m.hand_dim))
    ke0, ke1 = m.collision_energy_j
    assert ke1 <= ke0 * (1 + 1e-12) + 1e-15
    assert np.all(np.isfinite(m.contacts().impulse_n_s))


def test_coincident_constraints_share_the_impulse():
    # a face-face contact reported as two vertex-face contacts on the same line: singular matrix
    m = LocalModel(ToolSpec.one_dof(2.0), ContactParams(1000.0, 0.0, 0.0), period_s=1e-3)
    m.reset(qd=[0.4])
    m.update(np.array([[0, 1, 0], [0, 1, 1], [0, 2, 0]]),
             [[0.01, 0, 0], [0.01, 0, 0], [-0.01, 0, 0]], [[-1, 0, 0], [-1, 0, 0], [1, 0, 0]], [0.0, 0.0, 0.02])
    m.step([0.0])
    p = m.contacts().impulse_n_s
    np.testing.assert_allclose(p, [0.4, 0.4, 0.0], rtol=1e-12)     # m v split evenly (min-norm)
    assert m.counters()["rank"] == 1
    assert m.qd[0] == pytest.approx(0.0, abs=1e-15)


def test_peg_in_exact_hole_opposing_walls_give_finite_correct_impulses():
    # planar peg (half-width 5 mm) in a hole that fits exactly: left and right walls at the
    # same height (opposite normals: the rows of Jc are negatives, the matrix is singular),
    # plus the bottom. The peg falls onto the bottom sliding along both walls.
    m = LocalModel(ToolSpec.planar(0.5, 1e-3), ContactParams(4000.0, 30.0, 0.0), period_s=1e-3)
    m.reset(qd=[0.0, -0.2, 0.0])
    m.update(np.array([[0, 1, 0], [0, 2, 0], [0, 3, 0]]),
             [[-0.005, 0.0, 0], [0.005, 0.0, 0], [0.0, -0.02, 0]],
             [[1, 0, 0], [-1, 0, 0], [0, 1, 0]], [0.0, 0.0, -0.001])
    m.step([0.0, 0.0, 0.0])
    snap = m.contacts()
    # the walls, touched but not approached, start resting; the bottom, approached at 0.2 m/s, is
    # a collision; eq. 11 acts on the colliding and the penetrating ones alike
    assert snap.state == ["penetrating", "penetrating", "colliding"]
    assert np.all(np.isfinite(snap.impulse_n_s))
    np.testing.assert_allclose(snap.impulse_n_s, [0.0, 0.0, 0.5 * 0.2], atol=1e-12)
    assert m.counters()["rank"] == 2
    np.testing.assert_allclose(m.generalized_impulse, [0.0, 0.1, 0.0], atol=1e-12)


def test_walls_on_both_sides_at_rest_give_zero_finite_impulses():
    # the paper's model (no recovery, so no resting speed): a contact arising touching is a
    # collision even at rest
    m = LocalModel(ToolSpec.one_dof(1.0), ContactParams(1000.0, 0.0, 0.0), period_s=1e-3,
                   recovery_speed_m_per_s=0.0)
    m.update(np.array([[0, 1, 0], [0, 2, 0]]), [[0.01, 0, 0], [-0.01, 0, 0]], [[-1, 0, 0], [1, 0, 0]], [0.0, 0.0])
    f = m.step([3.0])
    assert m.counters()["collisions"] == 1
    np.testing.assert_array_equal(m.contacts().impulse_n_s, [0.0, 0.0])
    assert np.isfinite(f).all()
