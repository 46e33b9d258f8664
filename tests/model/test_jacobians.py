"""Contact-point and hand Jacobians of the kernels against finite differences of the pose."""
import numpy as np
import pytest

from hapticproxy.server.model import kernels as K
from hapticproxy.server.model.layout import (C_P, MAX_DOF, NCOLS_F, NSTATE, S_Q, TOOL_KIND_NAMES)
from hapticproxy.server.model.reference import integrate, rigid_pose


def _kernel_kinematics(model, q, points):
    par = model.arrays()[0]
    st = np.zeros(NSTATE)
    st[S_Q:S_Q + model.nq] = q
    m = len(points)
    C = np.zeros((m, NCOLS_F))
    C[:, C_P:C_P + 3] = points
    R = np.zeros((MAX_DOF, MAX_DOF)); c = np.zeros(MAX_DOF)
    D = np.zeros((MAX_DOF, MAX_DOF)); taug = np.zeros(MAX_DOF)
    Jpt = np.zeros((m, 3, MAX_DOF)); X = np.zeros((m, 3)); Jh = np.zeros((6, MAX_DOF))
    K._kin_rigid(model.kind, par, st, C, m, R, c, D, taug, Jpt, X, Jh)
    d, h = model.dof, model.hand_dim
    return D[:d, :d], X, Jpt[:, :, :d], Jh[:h, :d]


def _hand_point(model, q):
    R, c = rigid_pose(model.kind, model.arrays()[0], q)
    return c + R @ np.asarray(model.tool.hand_point_m)


@pytest.mark.parametrize("kind", ["1dof", "planar", "spatial"])
def test_point_and_hand_jacobians_match_finite_differences(make_model, kind):
    rng = np.random.default_rng(7)
    hand = (0.03, -0.02) if kind == "planar" else ((0.01, 0.03, -0.02) if kind == "spatial" else None)
    model = make_model(kind, hand=hand, axis=(0.6, 0.0, 0.8)) if kind == "1dof" else make_model(kind, hand=hand)
    for _ in range(20):
        if kind == "spatial":
            quat = rng.normal(size=4)
            q = np.r_[rng.normal(size=3) * 0.1, quat / np.linalg.norm(quat)]
        else:
            q = rng.normal(size=model.nq)
        points = rng.normal(size=(5, 3)) * 0.05
        if kind == "planar":
            points[:, 2] = 0.0
        qd = rng.normal(size=model.dof)
        D, X, J, Jh = _kernel_kinematics(model, q, points)
        h = 1e-6
        _, Xp, _, _ = _kernel_kinematics(model, integrate(model.kind, q, qd, h), points)
        _, Xm, _, _ = _kernel_kinematics(model, integrate(model.kind, q, qd, -h), points)
        fd = (Xp - Xm) / (2 * h)
        np.testing.assert_allclose(np.einsum("ijk,k->ij", J, qd), fd, atol=1e-7)
        hp = _hand_point(model, integrate(model.kind, q, qd, h))
        hm = _hand_point(model, integrate(model.kind, q, qd, -h))
        v_hand_fd = (hp - hm) / (2 * h)                     # world velocity of the hand point
        v_hand = Jh @ qd
        if kind == "1dof":
            np.testing.assert_allclose(v_hand, [v_hand_fd @ np.array([0.6, 0.0, 0.8])], atol=1e-7)
        elif kind == "planar":
            np.testing.assert_allclose(v_hand[:2], v_hand_fd[:2], atol=1e-7)
            assert v_hand[2] == qd[2]
        else:
            np.testing.assert_allclose(v_hand[:3], v_hand_fd, atol=1e-7)
        # D is the kinetic-energy metric: symmetric positive definite
        np.testing.assert_allclose(D, D.T, atol=1e-15)
        assert np.all(np.linalg.eigvalsh(D) > 0)


def test_spatial_angular_rows_of_the_hand_jacobian(make_model):
    m = make_model("spatial", hand=(0.02, 0.0, 0.05))
    q = np.r_[0.0, 0.0, 0.0, 0.9, 0.1, -0.3, 0.2]
    q[3:] /= np.linalg.norm(q[3:])
    _, _, _, Jh = _kernel_kinematics(m, q, np.zeros((1, 3)))
    qd = np.array([0.1, 0.2, 0.3, -1.0, 0.5, 2.0])
    np.testing.assert_allclose((Jh @ qd)[3:], qd[3:], atol=1e-15)   # omega passes through
    assert TOOL_KIND_NAMES["spatial"] == m.kind
