"""Plain-numpy reference of one full haptic step of the local model: the test oracle for the
numba kernels, and the baseline of ``hapticproxy bench model``.

It is written independently of ``kernels.py`` and straight from the paper's formulas: eq. 11
with an explicit pseudo-inverse of the m x m matrix Jc D^-1 Jc^T, eq. 8 with an explicit
(J_h D^-1 J_h^T)^-1, vectorised over contacts. It works on copies of the model's arrays and
returns the new ones; it never touches the model.
"""
from __future__ import annotations

import numpy as np

from .layout import (
    C_CP, C_FN, C_FT, C_IMP, C_N, C_P, C_S, C_SPREV, C_TU, C_VC, C_VN, C_Z,
    CI_SLIP, CI_STATE, CS_COLLIDING, CS_IMPENDING, CS_PENETRATING, CS_SEPARATING,
    K_COLLISIONS, K_M, K_N_COLLIDING, K_N_IMPENDING, K_N_PENETRATING, K_N_SEPARATING,
    K_NONFINITE, K_PROXY, K_RANK, K_SLIPPING, K_STEPS,
    P_AXIS, P_B, P_BT, P_DT, P_E, P_GRAV, P_HAND, P_INERTIA, P_K, P_KT, P_MASS, P_MUK, P_MUS,
    P_ORIGIN, PS_COLLIDING, PS_FREE, PS_RESTING,
    S_FENV, S_FH, S_FIMP, S_FPEN, S_GIMP, S_KE, S_KE_POST, S_KE_PRE, S_Q, S_QD, S_T,
    TOOL_1DOF, TOOL_DIMS, TOOL_PLANAR, TOUCH_TOL_M,
)

#: Relative singular-value cut of the pseudo-inverse (rank decisions as in the kernels).
PINV_RCOND = 1e-12


def _skew(v: np.ndarray) -> np.ndarray:
    """[v]x for a stack of vectors (..., 3) -> (..., 3, 3)."""
    z = np.zeros(v.shape[:-1])
    return np.stack([
        np.stack([z, -v[..., 2], v[..., 1]], -1),
        np.stack([v[..., 2], z, -v[..., 0]], -1),
        np.stack([-v[..., 1], v[..., 0], z], -1),
    ], -2)


def rigid_pose(kind: int, par: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(R body-to-world, COM world) of a rigid tool at configuration q."""
    if kind == TOOL_1DOF:
        return np.eye(3), par[P_ORIGIN:P_ORIGIN + 3] + q[0] * par[P_AXIS:P_AXIS + 3]
    if kind == TOOL_PLANAR:
        c, s = np.cos(q[2]), np.sin(q[2])
        return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]), np.array([q[0], q[1], 0.0])
    w, x, y, z = q[3:7]
    R = np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])
    return R, q[0:3].copy()


def rigid_kinematics(kind: int, par: np.ndarray, q: np.ndarray, local_points: np.ndarray):
    """D (d x d), generalized gravity (d), world points X (m x 3), point Jacobians (m x 3 x d),
    hand Jacobian (h x d) of a rigid tool."""
    d, h, _ = TOOL_DIMS[kind]
    R, c = rigid_pose(kind, par, q)
    r = local_points @ R.T
    X = c + r
    m = local_points.shape[0]
    mass = par[P_MASS]
    grav = par[P_GRAV:P_GRAV + 3]
    hand_r = R @ par[P_HAND:P_HAND + 3]
    if kind == TOOL_1DOF:
        axis = par[P_AXIS:P_AXIS + 3]
        D = np.array([[mass]])
        taug = np.array([mass * grav @ axis])
        J = np.broadcast_to(axis[None, :, None], (m, 3, 1)).copy()
        Jh = np.array([[1.0]])
    elif kind == TOOL_PLANAR:
        D = np.diag([mass, mass, par[P_INERTIA + 8]])
        taug = np.array([mass * grav[0], mass * grav[1], 0.0])
        J = np.zeros((m, 3, 3))
        J[:, 0, 0] = 1.0
        J[:, 1, 1] = 1.0
        J[:, 0, 2] = -r[:, 1]
        J[:, 1, 2] = r[:, 0]
        Jh = np.array([[1.0, 0.0, -hand_r[1]], [0.0, 1.0, hand_r[0]], [0.0, 0.0, 1.0]])
    else:
        inertia = par[P_INERTIA:P_INERTIA + 9].reshape(3, 3)
        D = np.zeros((6, 6))
        D[:3, :3] = mass * np.eye(3)
        D[3:, 3:] = R @ inertia @ R.T
        taug = np.concatenate([mass * grav, np.zeros(3)])
        J = np.zeros((m, 3, 6))
        J[:, :, :3] = np.eye(3)
        J[:, :, 3:] = -_skew(r)
        Jh = np.eye(6)
        Jh[:3, 3:] = -_skew(hand_r)
    return D, taug, X, J, Jh


def integrate(kind: int, q: np.ndarray, qd: np.ndarray, dt: float) -> np.ndarray:
    q = q.copy()
    if kind != 2:
        q += dt * qd
        return q
    q[:3] += dt * qd[:3]
    w = qd[3:6]
    wn = np.linalg.norm(w)
    half = 0.5 * wn * dt
    v = (np.sin(half) / wn) * w if wn > 0 else 0.5 * dt * w
    dq = np.array([np.cos(half), *v])
    a = dq
    b = q[3:7]
    prod = np.array([
        a[0] * b[0] - a[1] * b[1] - a[2] * b[2] - a[3] * b[3],
        a[0] * b[1] + a[1] * b[0] + a[2] * b[3] - a[3] * b[2],
        a[0] * b[2] - a[1] * b[3] + a[2] * b[0] + a[3] * b[1],
        a[0] * b[3] + a[1] * b[2] - a[2] * b[1] + a[3] * b[0],
    ])
    q[3:7] = prod / np.linalg.norm(prod)
    return q


def reference_step(kind, par, st, C, CI, cnt, hand):
    """One haptic step in numpy. Returns new (st, C, CI, cnt); inputs are not modified."""
    st = st.copy(); C = C.copy(); CI = CI.copy(); cnt = cnt.copy()
    d, h, nq = TOOL_DIMS[kind]
    dt, k, b, e = par[P_DT], par[P_K], par[P_B], par[P_E]
    mus, muk, kt, bt = par[P_MUS], par[P_MUK], par[P_KT], par[P_BT]
    hand = np.asarray(hand, dtype=np.float64)[:h]
    st[S_FH:S_FH + h] = hand
    m = int(cnt[K_M])
    t = st[S_T]
    q = st[S_Q:S_Q + nq].copy()
    qd0 = st[S_QD:S_QD + d].copy()
    Cm = C[:m]
    D, taug, X, J, Jh = rigid_kinematics(kind, par, q, Cm[:, C_P:C_P + 3])
    Dinv = np.linalg.inv(D)

    n = Cm[:, C_N:C_N + 3]
    vc = Cm[:, C_VC]
    s = np.einsum("ij,ij->i", n, X - Cm[:, C_CP:C_CP + 3]) - vc * (t - Cm[:, C_TU])   # eq. 3 + eq. 2
    Jn = np.einsum("ij,ijk->ik", n, J)
    vn = Jn @ qd0 - vc
    sprev = Cm[:, C_S].copy()
    state = np.select([s > TOUCH_TOL_M, vn > 0, sprev > 0], [CS_IMPENDING, CS_SEPARATING, CS_COLLIDING], CS_PENETRATING)
    Cm[:, C_SPREV] = sprev
    Cm[:, C_S] = s
    Cm[:, C_VN] = vn
    Cm[:, C_IMP] = 0.0
    CI[:m, CI_STATE] = state
    n_col = int(np.sum(state == CS_COLLIDING))
    cnt[K_N_IMPENDING] = int(np.sum(state == CS_IMPENDING))
    cnt[K_N_COLLIDING] = n_col
    cnt[K_N_PENETRATING] = int(np.sum(state == CS_PENETRATING))
    cnt[K_N_SEPARATING] = int(np.sum(state == CS_SEPARATING))
    cnt[K_PROXY] = PS_COLLIDING if n_col else (PS_FREE if cnt[K_N_IMPENDING] == m else PS_RESTING)

    ke0 = 0.5 * qd0 @ D @ qd0
    st[S_KE_PRE] = ke0
    st[S_KE_POST] = ke0
    qd = qd0.copy()
    gimp = np.zeros(d)
    if n_col:
        sel = (state == CS_COLLIDING) | (state == CS_PENETRATING)
        Jc = Jn[sel]
        A = Jc @ Dinv @ Jc.T
        p = -(1.0 + e) * np.linalg.pinv(A, rcond=PINV_RCOND) @ (Jc @ qd0)      # eq. 11
        gimp = Jc.T @ p
        qd = qd0 + Dinv @ gimp                                                  # eq. 10
        Cm[sel, C_IMP] = p
        st[S_KE_POST] = 0.5 * qd @ D @ qd
        cnt[K_RANK] = np.linalg.matrix_rank(A, tol=PINV_RCOND * max(np.linalg.norm(A, 2), 1e-300))
        cnt[K_COLLISIONS] += 1
    st[S_GIMP:S_GIMP + d] = gimp

    # penalty + stick-slip friction at s <= 0 from the post-impulse velocity
    touching = s <= TOUCH_TOL_M
    vn1 = Jn @ qd - vc
    Cm[touching, C_VN] = vn1[touching]
    fn = np.where(touching, np.maximum(-k * s - b * vn1, 0.0), 0.0)
    Cm[:, C_FN] = fn
    ft = np.zeros((m, 3))
    z_new = np.zeros((m, 3))
    slip = np.zeros(m, dtype=np.int64)
    fric = touching & (fn > 0) & ((mus > 0) | (muk > 0))
    if np.any(fric):
        v = np.einsum("ijk,k->ij", J, qd)
        v_t = v - np.einsum("ij,ij->i", v, n)[:, None] * n
        z = Cm[:, C_Z:C_Z + 3]
        z = z + dt * v_t - np.einsum("ij,ij->i", z, n)[:, None] * n
        f_stick = -kt * z - bt * v_t
        mag = np.linalg.norm(f_stick, axis=1)
        slipping = fric & (mag > mus * fn)
        zn = np.linalg.norm(z, axis=1)
        ok = slipping & (zn > 0) & (kt > 0)
        scale = np.where(ok, muk * fn / np.where(ok, kt * zn, 1.0), 0.0)
        z_slip = z * scale[:, None]
        f_slip = -kt * z_slip
        ft = np.where(slipping[:, None], f_slip, f_stick)
        z_fin = np.where(slipping[:, None], z_slip, z)
        ft[~fric] = 0.0
        z_new[fric] = z_fin[fric]
        slip[slipping] = 1
    Cm[:, C_FT:C_FT + 3] = ft
    CI[:m, CI_SLIP] = slip
    cnt[K_SLIPPING] = int(slip.sum())
    f = fn[:, None] * n + ft
    tau = np.einsum("ijk,ij->k", J, f) if m else np.zeros(d)

    qdd = np.linalg.solve(D, tau + Jh.T @ hand + taug)                          # eq. 7
    qd = qd + dt * qdd
    jbar_t = np.linalg.inv(Jh @ Dinv @ Jh.T) @ Jh @ Dinv                        # eq. 8
    fpen = jbar_t @ tau
    fimp = jbar_t @ (gimp / dt)                                                 # eq. 12
    st[S_FPEN:S_FPEN + h] = fpen
    st[S_FIMP:S_FIMP + h] = fimp
    st[S_FENV:S_FENV + h] = fpen + fimp
    if np.all(np.isfinite(qd)) and np.all(np.isfinite(fpen + fimp)):
        st[S_QD:S_QD + d] = qd
        Cm[:, C_Z:C_Z + 3] = z_new
        st[S_Q:S_Q + nq] = integrate(kind, q, qd, dt)
        st[S_KE] = 0.5 * qd @ D @ qd
    else:
        st[S_FENV:S_FENV + 6] = 0.0
        st[S_FIMP:S_FIMP + 6] = 0.0
        st[S_FPEN:S_FPEN + 6] = 0.0
        cnt[K_NONFINITE] += 1
    st[S_T] += dt
    cnt[K_STEPS] += 1
    C[:m] = Cm
    return st, C, CI, cnt
