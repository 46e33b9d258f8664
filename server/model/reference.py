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
    C_CP, C_DEF, C_FN, C_FT, C_IMP, C_N, C_P, C_REC, C_S, C_SPREV, C_TU, C_VC, C_VN, C_Z,
    CI_AGE, CI_SLIP, CI_STATE, CST_COLLIDING, CST_IMPENDING, CST_PENETRATING, CST_SEPARATING,
    K_COLLISIONS, K_M, K_N_COLLIDING, K_N_IMPENDING, K_N_PENETRATING, K_N_SEPARATING,
    K_HELD, K_NONFINITE, K_PROXY, K_RANK, K_RECOVERING, K_SLIPPING, K_STEPS,
    P_AXIS, P_B, P_BT, P_DT, P_E, P_GRAV, P_HAND, P_INERTIA, P_K, P_KT, P_MASS, P_MUK, P_MUS,
    P_ORIGIN, P_REC_AGE, P_REC_CUT, P_REC_FRATE, P_REC_TAU, P_REC_V, P_REC_VN, PS_COLLIDING, PS_FREE, PS_RESTING,
    S_EREC, S_RECF, S_FENV, S_FH, S_FIMP, S_FPEN, S_GIMP, S_KE, S_KE_POST, S_KE_PRE, S_LQ, S_Q, S_QD, S_T,
    TOOL_1DOF, TOOL_DIMS, TOOL_PLANAR, TOUCH_TOL_M, CI_KEY,
    DIVERGE_DECAY, DIVERGE_SPEED, DIVERGE_STEPS, INTEG_IMPLICIT, S_FCPL, S_QDP, K_DIVERGED, K_OSC_RUN, P_CPL_BR, P_CPL_BT, P_CPL_KR, P_CPL_KT,
    P_INTEG,
)

#: Most solves of the implicit step (``kernels.IMPLICIT_MAX_SOLVES``, written again here).
IMPLICIT_MAX_SOLVES = 8

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


def _rot_axis(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rotation by ``angle`` about the unit ``axis`` (matrix exponential of the skew matrix)."""
    K = _skew(axis)
    return np.eye(3) + np.sin(angle) * K + (1.0 - np.cos(angle)) * (K @ K)


def _quat_rot(q) -> np.ndarray:
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


class LinkageReference:
    """A linkage's kinematics in plain numpy, from its ``LinkSpec`` list with 4 x 4 homogeneous
    transforms (written independently of ``linkage.py``): the oracle of the linkage kernels.

    Coordinates as the kernels': q = (root pose, joints), qd = (root origin velocity, root
    angular velocity (world), joint rates); planar roots are (x, y, theta)."""

    def __init__(self, links, held_link: int, planar: bool, velocity_terms: bool = True) -> None:
        self.velocity_terms = bool(velocity_terms)
        self.links = tuple(links)
        self.held = int(held_link)
        self.planar = bool(planar)
        self.nl = len(self.links)
        self.r = 3 if planar else 6
        self.nqr = 3 if planar else 7
        self.d = self.r + self.nl - 1
        self.h = 3 if planar else 6
        # ancestors[k]: the links whose joints move link k (k itself included, the root excluded)
        self.ancestors = []
        for k in range(self.nl):
            chain, j = [], k
            while j > 0:
                chain.append(j)
                j = self.links[j].parent
            self.ancestors.append(set(chain))

    @classmethod
    def of(cls, tool, linkage_dynamics: str = "full") -> "LinkageReference":
        return cls(tool.links, tool.held_link, tool.planar, linkage_dynamics == "full")

    def bias(self, q: np.ndarray, qd: np.ndarray) -> np.ndarray:
        """Velocity-product generalized forces h(q, qd) = sum_k J_k^T (m_k Jdot_v qd ;
        I_k Jdot_w qd + w_k x I_k w_k), with Jdot qd by central differences of the COM Jacobians
        along the motion (q moved by +-eps qd on the manifold): accurate to ~1e-9 relative."""
        eps = 1e-6
        qp, qm = self.integrate(q, qd, eps), self.integrate(q, qd, -eps)
        T, Tp, Tm = self.frames(q), self.frames(qp), self.frames(qm)
        h = np.zeros(self.d)
        for k, ln in enumerate(self.links):
            com = np.asarray(ln.com_m, dtype=np.float64)
            c, cp, cm = (F[k][:3, 3] + F[k][:3, :3] @ com for F in (T, Tp, Tm))
            Jv, Jw = self.jacobian(q, k, c, T)
            Jvp, Jwp = self.jacobian(qp, k, cp, Tp)
            Jvm, Jwm = self.jacobian(qm, k, cm, Tm)
            acc = (Jvp - Jvm) @ qd / (2 * eps)
            alpha = (Jwp - Jwm) @ qd / (2 * eps)
            w = Jw @ qd
            R = T[k][:3, :3]
            Iw = R @ ln.inertia_matrix() @ R.T
            h += Jv.T @ (ln.mass_kg * acc) + Jw.T @ (Iw @ alpha + np.cross(w, Iw @ w))
        return h

    def frames(self, q: np.ndarray) -> list[np.ndarray]:
        """4 x 4 link-to-world transforms at q."""
        T0 = np.eye(4)
        if self.planar:
            T0[:3, :3] = _rot_axis(np.array([0.0, 0.0, 1.0]), q[2])
            T0[:2, 3] = q[:2]
        else:
            T0[:3, :3] = _quat_rot(q[3:7])
            T0[:3, 3] = q[:3]
        out = [T0]
        for k in range(1, self.nl):
            ln = self.links[k]
            To = np.eye(4)
            To[:3, :3] = _quat_rot(ln.origin_quat)
            To[:3, 3] = ln.origin_m
            if self.planar:
                To[2, 3] = 0.0
            Tj = np.eye(4)
            axis = np.asarray(ln.axis, dtype=np.float64)
            qk = q[self.nqr + k - 1]
            if ln.joint == "revolute":
                Tj[:3, :3] = _rot_axis(axis, qk)
            else:
                Tj[:3, 3] = axis * qk
            out.append(out[ln.parent] @ To @ Tj)
        return out

    def jacobian(self, q: np.ndarray, link: int, x: np.ndarray, frames=None) -> tuple[np.ndarray, np.ndarray]:
        """(Jv (3 x d) of the world point x on ``link``, Jw (3 x d) of the link)."""
        T = self.frames(q) if frames is None else frames
        Jv = np.zeros((3, self.d))
        Jw = np.zeros((3, self.d))
        p0 = T[0][:3, 3]
        if self.planar:
            Jv[:2, :2] = np.eye(2)
            Jv[:, 2] = np.cross([0.0, 0.0, 1.0], x - p0)
            Jw[2, 2] = 1.0
        else:
            Jv[:, :3] = np.eye(3)
            Jv[:, 3:6] = -_skew(x - p0)
            Jw[:, 3:6] = np.eye(3)
        for j in self.ancestors[link]:
            ln = self.links[j]
            a = T[j][:3, :3] @ np.asarray(ln.axis, dtype=np.float64)
            col = self.r + j - 1
            if ln.joint == "revolute":
                Jv[:, col] = np.cross(a, x - T[j][:3, 3])
                Jw[:, col] = a
            else:
                Jv[:, col] = a
        return Jv, Jw

    def kinematics(self, q, grav, links_of_points, local_points):
        """D (d x d), generalized gravity (d), world points X (m x 3), point Jacobians (m x 3 x d),
        hand Jacobian (h x d)."""
        T = self.frames(q)
        D = np.zeros((self.d, self.d))
        taug = np.zeros(self.d)
        for k, ln in enumerate(self.links):
            R = T[k][:3, :3]
            c = T[k][:3, 3] + R @ np.asarray(ln.com_m, dtype=np.float64)
            Jv, Jw = self.jacobian(q, k, c, T)
            Iw = R @ ln.inertia_matrix() @ R.T
            if self.planar:
                Iw = np.diag([0.0, 0.0, Iw[2, 2]])
            D += ln.mass_kg * Jv.T @ Jv + Jw.T @ Iw @ Jw
            taug += ln.mass_kg * Jv.T @ grav
        m = len(links_of_points)
        X = np.zeros((m, 3))
        J = np.zeros((m, 3, self.d))
        for i in range(m):
            k = int(links_of_points[i])
            X[i] = T[k][:3, 3] + T[k][:3, :3] @ local_points[i]
            J[i] = self.jacobian(q, k, X[i], T)[0]
        Jv, Jw = self.jacobian(q, self.held, T[self.held][:3, 3], T)
        Jh = np.vstack([Jv[:2], Jw[2:3]]) if self.planar else np.vstack([Jv, Jw])
        return D, taug, X, J, Jh

    def integrate(self, q: np.ndarray, qd: np.ndarray, dt: float) -> np.ndarray:
        q = q.copy()
        if self.planar:
            q[:3] += dt * qd[:3]
        else:
            q[:7] = integrate(2, q[:7], qd[:6], dt)
        q[self.nqr:] += dt * qd[self.r:]
        return q


def recover(par, st, C, CI, cnt, m: int) -> None:
    """Deformation recovery, in place (see ``kernels._recover``): every deformed contact that has
    persisted ``P_REC_AGE`` updates and touched at the last step takes back at most
    min(v, F_rate / (k n), remaining / tau) dt of its deformation."""
    cnt[K_RECOVERING] = 0
    st[S_RECF] = 0.0
    v = par[P_REC_V] * (1.0 - par[P_REC_CUT])
    if not v > 0 or m == 0:
        return
    Cm = C[:m]
    elig = (Cm[:, C_DEF] > 0) & (CI[:m, CI_AGE] >= par[P_REC_AGE]) & (Cm[:, C_S] <= TOUCH_TOL_M)
    if par[P_REC_VN] > 0:
        elig &= np.abs(Cm[:, C_VN]) <= par[P_REC_VN]
    n_r = int(np.count_nonzero(elig))
    cnt[K_RECOVERING] = n_r
    if not n_r:
        return
    dt, k = par[P_DT], par[P_K]
    if par[P_REC_FRATE] > 0 and k > 0:
        v = min(v, par[P_REC_FRATE] / (k * n_r))
    left = Cm[elig, C_DEF]
    step = np.full(n_r, v * dt)
    if par[P_REC_TAU] > 0:
        step = np.minimum(step, left * dt / par[P_REC_TAU])
    step = np.where((step > left) | (left < 1e-9), left, step)
    st[S_EREC] += float(np.sum(Cm[elig, C_FN] * step))
    st[S_RECF] = float(k * np.sum(step))
    Cm[elig, C_DEF] = left - step
    Cm[elig, C_REC] += step


def plane_speed(vc, sprev, cut):
    """``kernels._plane_speed`` over arrays: the constraint's speed along n, held back by the share
    ``cut`` where it advances into the tool at a contact touching at the last step."""
    vc = np.asarray(vc, dtype=float)
    if not cut > 0:
        return vc
    held = (vc > 0) & (np.asarray(sprev) <= TOUCH_TOL_M)
    return np.where(held, vc * max(1.0 - cut, 0.0), vc)


def hold(par, st, C, cnt, m: int) -> None:
    """``kernels._hold``: the held part of each constraint's advance since the last step moves
    from ``C_REC`` into ``C_DEF``."""
    Cm = C[:m]
    span = np.minimum(st[S_T] - Cm[:, C_TU], par[P_DT])
    held = (Cm[:, C_VC] - plane_speed(Cm[:, C_VC], Cm[:, C_S], par[P_REC_CUT])) * span
    on = held > 0
    Cm[on, C_REC] -= held[on]
    Cm[on, C_DEF] += held[on]
    cnt[K_HELD] = int(np.count_nonzero(on))


def implicit_velocity(par, h, D, J, Jh, n, s, vn, touching, fn, ft, slip, z_prev, base, qd):
    """The implicit step's velocity (``kernels._implicit_step``) from its definition: with the
    contacts S that push at the step's end, (D + dt B + dt^2 K) dv = dt (base + sum_S J^T (f_0 n
    + t)), B = J_h^T diag(b_c) J_h + sum_S (b n n^T + b_t (I - n n^T) [sticking]) through J, K
    alike. A touching contact is in S when f_e = f_0 - (b + dt k) n^T J dv > 0 (f_0 = -k s -
    b v_n); with friction, t is its stick force t_0 = -k_t z - b_t v_t now (z the bristle
    stretched by dt v_t) while t_0 - (b_t + dt k_t) (I - n n^T) J dv stays within mu_s f_e, else
    mu_k f_0 along that force (-mu_k f_0 z / |z| where the friction pass found it slipping, turned
    by dt (I - n n^T - s s^T) J dv with the stiffness mu_k f_0 / |z| across its slip s; a
    slipping one whose stick force would be inside sticks); the guess is the friction pass's (``fn`` > 0, ``slip``,
    its kinetic forces ``ft``). Returns (qd + dv, the generalized contact force, fn, ft, bristles,
    slip flags)."""
    dt, k, b, kt, bt = par[P_DT], par[P_K], par[P_B], par[P_KT], par[P_BT]
    mus, muk = par[P_MUS], par[P_MUK]
    m = len(s)
    rot = np.arange(h) >= (2 if h == 3 else (3 if h == 6 else h))
    c_hand = np.where(rot, dt * par[P_CPL_BR] + dt * dt * par[P_CPL_KR], dt * par[P_CPL_BT] + dt * dt * par[P_CPL_KT])
    a_hand = D + Jh.T @ (c_hand[:, None] * Jh)
    Jn = np.einsum("ij,ijk->ik", n, J)
    proj_t = np.eye(3)[None] - n[:, :, None] * n[:, None, :]
    Jt = np.einsum("iab,ibk->iak", proj_t, J)                                # tangential point Jacobian
    cn = dt * b + dt * dt * k
    ctan = dt * bt + dt * dt * kt
    f0 = np.where(touching, -k * s - b * vn, 0.0)
    friction = touching & ((mus > 0) | (muk > 0))
    v = np.einsum("ijk,k->ij", J, qd)
    v_t = v - np.einsum("ij,ij->i", v, n)[:, None] * n
    zs = z_prev + dt * v_t - np.einsum("ij,ij->i", z_prev, n)[:, None] * n
    t0 = -kt * zs - bt * v_t
    zn = np.linalg.norm(zs, axis=1)
    # the kinetic force: the bristle held at mu_k f_0, as the friction pass's breakaway
    t_slip = np.where(((zn > 0) & (kt > 0))[:, None],
                      -(muk * np.maximum(f0, 0.0) / np.where(zn > 0, zn, 1.0))[:, None] * zs, 0.0)
    slipping = friction & (fn > 0) & (slip != 0)
    mode = np.where(slipping, 2, np.where(friction, 1, 0))
    # a slipping contact's kinetic force turns with its bristle: k_s = mu_k f_0 / |z| across the
    # slip direction s in the tangent plane (Jx: that part of the point Jacobian)
    tsn = np.linalg.norm(t_slip, axis=1)
    ks = np.where((tsn > 0) & (zn > 0), tsn / np.where(zn > 0, zn, 1.0), 0.0)
    sdir = t_slip / np.where(tsn > 0, tsn, 1.0)[:, None]
    Jx = Jt - np.einsum("ia,ib,ibk->iak", sdir, sdir, Jt)
    inS = fn > 0.0
    for _ in range(IMPLICIT_MAX_SOLVES):
        stick = inS & ((mode == 1) | (mode == 4))
        turn = inS & (mode == 2)
        A = (a_hand + cn * np.einsum("i,ia,ib->ab", inS * 1.0, Jn, Jn)
             + ctan * np.einsum("i,iqa,iqb->ab", stick * 1.0, Jt, Jt)
             + dt * dt * np.einsum("i,iqa,iqb->ab", turn * ks, Jx, Jx))
        t = np.where(((mode == 1) | (mode == 4))[:, None], t0, t_slip)
        f_s = np.where(inS[:, None], f0[:, None] * n + t, 0.0)
        dv = dt * np.linalg.solve(A, base + np.einsum("ijk,ij->k", J, f_s))
        f_end = f0 - (b + dt * k) * (Jn @ dv)
        pushes = touching & (f_end > 0.0)
        moved = pushes != inS
        t_end = t0 - (bt + dt * kt) * np.einsum("iak,k->ia", Jt, dv)
        tn = np.linalg.norm(t_end, axis=1)
        # modes: 1 stick, 2 slip (the friction pass's), 3 slip after breaking away (final), 4 stick
        # after slipping (may break away once more)
        brk = ~moved & pushes & ((mode == 1) | (mode == 4)) & (tn > mus * f_end)
        holds = ~moved & pushes & (mode == 2) & (tn <= mus * f_end)
        t_slip = np.where(brk[:, None], (muk * np.maximum(f0, 0.0) / np.where(brk, tn, 1.0))[:, None] * t_end, t_slip)
        mode = np.where(brk, 3, np.where(holds, 4, mode))
        inS = pushes
        if not (np.any(moved) or np.any(brk) or np.any(holds)):
            break
    fn1 = np.where(inS, np.maximum(f0 - (b + dt * k) * (Jn @ dv), 0.0), 0.0)
    u = np.einsum("iak,k->ia", Jt, dv)                                       # tangential velocity change
    stick = (inS & ((mode == 1) | (mode == 4)))[:, None]
    slid = (inS & ((mode == 2) | (mode == 3)))[:, None]
    t_end = t0 - (bt + dt * kt) * u
    tn = np.linalg.norm(t_end, axis=1)
    t_end *= np.where(tn > mus * fn1, mus * fn1 / np.where(tn > 0, tn, 1.0), 1.0)[:, None]   # within the cone
    turned = t_slip - (dt * ks)[:, None] * np.einsum("iak,k->ia", Jx, dv)
    gn = np.linalg.norm(turned, axis=1)
    turned *= (tsn / np.where(gn > 0, gn, 1.0))[:, None]
    t_slip = np.where(((mode == 2) & (ks > 0) & (gn > 0))[:, None], turned, t_slip)
    ft1 = np.where(stick, t_end, np.where(slid, t_slip, 0.0))
    z1 = np.where(stick, zs + dt * u, np.where(slid, -t_slip / kt if kt > 0 else 0.0, 0.0))
    slip1 = slid[:, 0].astype(np.int64)
    tau = np.einsum("ijk,ij->k", J, fn1[:, None] * n + ft1) if m else np.zeros(len(qd))
    return qd + dv, tau, fn1, ft1, z1, slip1


def reference_step(kind, par, st, C, CI, cnt, hand, linkage: LinkageReference | None = None):
    """One haptic step in numpy. Returns new (st, C, CI, cnt); inputs are not modified.
    ``linkage``: the tool's ``LinkageReference`` for a linkage model (its q is at ``S_LQ``)."""
    st = st.copy(); C = C.copy(); CI = CI.copy(); cnt = cnt.copy()
    hold(par, st, C, cnt, int(cnt[K_M]))
    recover(par, st, C, CI, cnt, int(cnt[K_M]))
    if linkage is not None:
        d, h, nq, q_at = linkage.d, linkage.h, linkage.nqr + linkage.nl - 1, S_LQ
    else:
        (d, h, nq), q_at = TOOL_DIMS[kind], S_Q
    dt, k, b, e = par[P_DT], par[P_K], par[P_B], par[P_E]
    mus, muk, kt, bt = par[P_MUS], par[P_MUK], par[P_KT], par[P_BT]
    hand = np.asarray(hand, dtype=np.float64)[:h]
    st[S_FH:S_FH + h] = hand
    m = int(cnt[K_M])
    t = st[S_T]
    q = st[q_at:q_at + nq].copy()
    qd0 = st[S_QD:S_QD + d].copy()
    Cm = C[:m]
    if linkage is not None:
        D, taug, X, J, Jh = linkage.kinematics(q, par[P_GRAV:P_GRAV + 3], CI[:m, CI_KEY], Cm[:, C_P:C_P + 3])
        if linkage.velocity_terms:
            taug = taug - linkage.bias(q, qd0)
    else:
        D, taug, X, J, Jh = rigid_kinematics(kind, par, q, Cm[:, C_P:C_P + 3])
    Dinv = np.linalg.inv(D)

    n = Cm[:, C_N:C_N + 3]
    vc = Cm[:, C_VC]
    s = (np.einsum("ij,ij->i", n, X - Cm[:, C_CP:C_CP + 3]) - vc * (t - Cm[:, C_TU])   # eq. 3 + eq. 2
         - Cm[:, C_REC])                                                                 # + recovery
    Jn = np.einsum("ij,ijk->ik", n, J)
    sprev = Cm[:, C_S].copy()
    vc_now = plane_speed(vc, sprev, par[P_REC_CUT])
    vn = Jn @ qd0 - vc_now
    state = np.select([s > TOUCH_TOL_M, vn > 0, sprev > 0], [CST_IMPENDING, CST_SEPARATING, CST_COLLIDING], CST_PENETRATING)
    Cm[:, C_SPREV] = sprev
    Cm[:, C_S] = s
    Cm[:, C_VN] = vn
    Cm[:, C_IMP] = 0.0
    CI[:m, CI_STATE] = state
    n_col = int(np.sum(state == CST_COLLIDING))
    cnt[K_N_IMPENDING] = int(np.sum(state == CST_IMPENDING))
    cnt[K_N_COLLIDING] = n_col
    cnt[K_N_PENETRATING] = int(np.sum(state == CST_PENETRATING))
    cnt[K_N_SEPARATING] = int(np.sum(state == CST_SEPARATING))
    cnt[K_PROXY] = PS_COLLIDING if n_col else (PS_FREE if cnt[K_N_IMPENDING] == m else PS_RESTING)

    ke0 = 0.5 * qd0 @ D @ qd0
    st[S_KE_PRE] = ke0
    st[S_KE_POST] = ke0
    qd = qd0.copy()
    gimp = np.zeros(d)
    if n_col:
        sel = (state == CST_COLLIDING) | (state == CST_PENETRATING)
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
    vn1 = Jn @ qd - vc_now
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

    if par[P_INTEG] == INTEG_IMPLICIT:
        rot = np.arange(h) >= (2 if h == 3 else (3 if h == 6 else h))
        b_c = np.where(rot, par[P_CPL_BR], par[P_CPL_BT])
        bk = np.where(rot, par[P_CPL_BR] + dt * par[P_CPL_KR], par[P_CPL_BT] + dt * par[P_CPL_KT])
        # the coupling's damper at the velocity the impulse left, then its change over the step
        f_imp = -b_c * (Jh @ (qd - qd0))
        qd1, tau, fn, ft, z_new, slip = implicit_velocity(par, h, D, J, Jh, n, s, vn1, touching, fn, ft, slip,
                                                          Cm[:, C_Z:C_Z + 3], Jh.T @ (hand + f_imp) + taug, qd)
        Cm[:, C_FN] = fn
        Cm[:, C_FT:C_FT + 3] = ft
        CI[:m, CI_SLIP] = slip
        cnt[K_SLIPPING] = int(slip.sum())
        st[S_FCPL:S_FCPL + h] = f_imp - bk * (Jh @ (qd1 - qd))                 # the coupling's change
        qd = qd1
    else:
        qdd = np.linalg.solve(D, tau + Jh.T @ hand + taug)                      # eq. 7
        qd = qd + dt * qdd
        st[S_FCPL:S_FCPL + h] = 0.0
    jbar_t = np.linalg.inv(Jh @ Dinv @ Jh.T) @ Jh @ Dinv                        # eq. 8
    fpen = jbar_t @ tau
    fimp = jbar_t @ (gimp / dt)                                                 # eq. 12
    st[S_FPEN:S_FPEN + h] = fpen
    st[S_FIMP:S_FIMP + h] = fimp
    st[S_FENV:S_FENV + h] = fpen + fimp
    if np.all(np.isfinite(qd)) and np.all(np.isfinite(fpen + fimp)):
        prev = st[S_QDP:S_QDP + d].copy()
        osc = np.any((qd0 * prev < 0.0) & (np.abs(qd0) >= (1.0 - DIVERGE_DECAY) * np.abs(prev))
                     & (np.abs(qd0) > DIVERGE_SPEED))
        st[S_QDP:S_QDP + d] = qd0
        cnt[K_OSC_RUN] = cnt[K_OSC_RUN] + 1 if osc else 0
        if osc and cnt[K_OSC_RUN] == DIVERGE_STEPS:
            cnt[K_DIVERGED] += 1
        st[S_QD:S_QD + d] = qd
        Cm[:, C_Z:C_Z + 3] = z_new
        st[q_at:q_at + nq] = linkage.integrate(q, qd, dt) if linkage is not None else integrate(kind, q, qd, dt)
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
