"""Numba kernels of the local model for a linkage tool: a kinematic tree held by one of its links.

The paper (section IV-B): when the user holds one link of a linkage, the virtual tool is the whole
linkage; its proxy dynamics are eq. 7 in configuration space, where the bilateral joint
constraints are implicit in the coordinates. This module supplies only the linkage's kinematics
and integrator; the contact detection, contact states, collision impulses (eq. 11), penalty and
friction forces, the dynamics solve and the rendering to the hand (eq. 8, eq. 12) are the rigid
tools' ``kernels._core`` and ``kernels.apply_update``, unchanged. Rigid tools never call
anything here (their step is ``kernels.step_rigid``), so they pay nothing for linkages.

Coordinates (the protocol's ``Hello.links``): link 0 is the root, a floating base whose frame is
the tool frame; each other link hangs from an earlier one by a revolute or prismatic joint.
Link k's frame at configuration q is ``T_k = T_parent * T_origin_k * J_k(q_k)`` (URDF
convention: the joint acts at the child's frame origin about / along the axis given in the child
frame). q = (root pose, q_1 .. q_{L-1}); qd = (velocity of the root frame's origin and the root's
angular velocity, both world, then the joint rates). Planar linkages live in the world x-y plane:
root (x, y, theta), revolute joints about +-z, prismatic joints along in-plane axes; d = 3 + J,
hand space (fx, fy, tau_z). Spatial: root (x, y, z, quaternion), d = 6 + J, hand space 6.

Per step (``step_linkage``): forward kinematics; D(q) = sum_k J_k^T M_k J_k over the links'
COM Jacobians (only the columns of the root and the link's ancestor joints are non-zero: the
``LI_CHAIN`` list); the generalized gravity; the point Jacobian of every contact on its link
(key column 0); the hand Jacobian of the held link's frame origin.

Velocity-product terms (``LM_COR``). The paper neglects Coriolis and centripetal terms (its
footnote 2: linkages are not moved fast). Without them the proxy is not energy-consistent:
d/dt(qd^T D qd / 2) = qd^T tau + qd^T Ddot qd / 2, and the extra term is cubic in speed. A
free link of a held chain swings fast even when the hand moves slowly (measured: a 3-bar chain
of 80 g bars pushed at a pivot with 0.5 N gains three times the work the hand did within
0.15 s). So by default (``LM_COR`` = 1) they are included, as the bias force
h(q, qd) = sum_k J_k^T (M_k Jdot_k qd + [0; w_k x I_k w_k]) from one forward recursion of link
velocities and velocity-product accelerations (Newton-Euler with qdd = 0), and eq. 7 becomes
D qdd + h + G = sum J_i^T f_i + J_h^T F_h; ``LM_COR`` = 0 is the paper's eq. 7 as written.
"""
from __future__ import annotations

import math

from numba import njit

from .kernels import (
    _V_QD, _V_TAUG, _core, _views, apply_update, check_update, end_step, hand_to_world, take_hand,
    turn_quat,
)
from .layout import (
    C_P, CI_KEY, E_HAND_NONFINITE, E_OK, JT_PRISMATIC, JT_REVOLUTE, K_M,
    LI_CHAIN, LI_NCHAIN, LI_PARENT, LI_TYPE, LK_AXIS, LK_COM, LK_I, LK_MASS, LK_OP, LK_OR,
    LM_COR, LM_D, LM_H, LM_HELD, LM_NLINKS, LM_NQR, LM_PLANAR, LM_R,
    LW_A, LW_AC, LW_AL, LW_C, LW_IW, LW_JV, LW_JW, LW_P, LW_R, LW_V, LW_W,
    P_DT, P_GRAV, S_LQ, S_QD, TOOL_PLANAR, TOOL_SPATIAL,
)

_JIT = dict(cache=True, nogil=True, error_model="numpy")


@njit(**_JIT)
def forward_kinematics(lmeta, lk, lki, q, lw):
    """Link frame poses (``LW_R``, ``LW_P``) and world joint axes (``LW_A``) at configuration q
    (root pose coordinates, then one value per joint), world frame."""
    nl = lmeta[LM_NLINKS]
    nqr = lmeta[LM_NQR]
    if lmeta[LM_PLANAR]:
        th = q[2]
        ct = math.cos(th)
        sn = math.sin(th)
        for a in range(9):
            lw[0, LW_R + a] = 0.0
        lw[0, LW_R + 0] = ct
        lw[0, LW_R + 1] = -sn
        lw[0, LW_R + 3] = sn
        lw[0, LW_R + 4] = ct
        lw[0, LW_R + 8] = 1.0
        lw[0, LW_P] = q[0]
        lw[0, LW_P + 1] = q[1]
        lw[0, LW_P + 2] = 0.0
    else:
        qw = q[3]; qx = q[4]; qy = q[5]; qz = q[6]
        # an engine's or a caller's quaternion may be off unit by rounding: normalise here so
        # every link frame is a rotation
        nrm = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
        qw /= nrm; qx /= nrm; qy /= nrm; qz /= nrm
        lw[0, LW_R + 0] = 1.0 - 2.0 * (qy * qy + qz * qz)
        lw[0, LW_R + 1] = 2.0 * (qx * qy - qw * qz)
        lw[0, LW_R + 2] = 2.0 * (qx * qz + qw * qy)
        lw[0, LW_R + 3] = 2.0 * (qx * qy + qw * qz)
        lw[0, LW_R + 4] = 1.0 - 2.0 * (qx * qx + qz * qz)
        lw[0, LW_R + 5] = 2.0 * (qy * qz - qw * qx)
        lw[0, LW_R + 6] = 2.0 * (qx * qz - qw * qy)
        lw[0, LW_R + 7] = 2.0 * (qy * qz + qw * qx)
        lw[0, LW_R + 8] = 1.0 - 2.0 * (qx * qx + qy * qy)
        lw[0, LW_P] = q[0]
        lw[0, LW_P + 1] = q[1]
        lw[0, LW_P + 2] = q[2]
    for a in range(3):
        lw[0, LW_A + a] = 0.0
    for k in range(1, nl):
        par = lki[k, LI_PARENT]
        qk = q[nqr + k - 1]
        # Rp = R_parent R_origin (this link's frame at q_k = 0), its origin p_parent + R_parent o
        o0 = lk[k, LK_OP]; o1 = lk[k, LK_OP + 1]; o2 = lk[k, LK_OP + 2]
        for a in range(3):
            lw[k, LW_P + a] = _world_point(lw, par, a, o0, o1, o2)
            for c in range(3):
                s = 0.0
                for b in range(3):
                    s += lw[par, LW_R + 3 * a + b] * lk[k, LK_OR + 3 * b + c]
                lw[k, LW_R + 3 * a + c] = s
        ax = lk[k, LK_AXIS]; ay = lk[k, LK_AXIS + 1]; az = lk[k, LK_AXIS + 2]
        # world axis = Rp axis (the joint's own motion leaves its axis where it is)
        for a in range(3):
            lw[k, LW_A + a] = (lw[k, LW_R + 3 * a] * ax + lw[k, LW_R + 3 * a + 1] * ay
                               + lw[k, LW_R + 3 * a + 2] * az)
        if lki[k, LI_TYPE] == JT_PRISMATIC:
            for a in range(3):
                lw[k, LW_P + a] += qk * lw[k, LW_A + a]
        elif lki[k, LI_TYPE] == JT_REVOLUTE:
            # R = Rp Rot(axis, q_k), Rot by Rodrigues: c I + s [a]x + (1 - c) a a^T
            c = math.cos(qk)
            s_ = math.sin(qk)
            t = 1.0 - c
            r00 = c + t * ax * ax; r01 = t * ax * ay - s_ * az; r02 = t * ax * az + s_ * ay
            r10 = t * ax * ay + s_ * az; r11 = c + t * ay * ay; r12 = t * ay * az - s_ * ax
            r20 = t * ax * az - s_ * ay; r21 = t * ay * az + s_ * ax; r22 = c + t * az * az
            for a in range(3):
                p0 = lw[k, LW_R + 3 * a]; p1 = lw[k, LW_R + 3 * a + 1]; p2 = lw[k, LW_R + 3 * a + 2]
                lw[k, LW_R + 3 * a] = p0 * r00 + p1 * r10 + p2 * r20
                lw[k, LW_R + 3 * a + 1] = p0 * r01 + p1 * r11 + p2 * r21
                lw[k, LW_R + 3 * a + 2] = p0 * r02 + p1 * r12 + p2 * r22


@njit(inline="always", **_JIT)
def _world_point(lw, k, a, p0, p1, p2):
    """World coordinate ``a`` of the point p (p0, p1, p2) given in link k's frame: origin + R p
    (summed in this order, as every caller did before it was shared)."""
    return (lw[k, LW_P + a] + lw[k, LW_R + 3 * a] * p0 + lw[k, LW_R + 3 * a + 1] * p1
            + lw[k, LW_R + 3 * a + 2] * p2)


@njit(inline="always", **_JIT)
def _column(planar, r, lki, lw, col, x0, x1, x2):
    """(v0, v1, v2, w0, w1, w2): world velocity v of the world point x and angular velocity w of
    its body for a unit rate of configuration column ``col`` (the body being any link that column
    moves). Root columns: planar vx, vy, wz (about the root frame's origin); spatial v, w. Joint
    columns: revolute a x (x - p_j), a; prismatic a, 0. Returns scalars (no arrays per call: it
    runs for every chain column of every contact)."""
    if col < r:
        if planar:
            if col == 0:
                return 1.0, 0.0, 0.0, 0.0, 0.0, 0.0
            if col == 1:
                return 0.0, 1.0, 0.0, 0.0, 0.0, 0.0
            return -(x1 - lw[0, LW_P + 1]), x0 - lw[0, LW_P], 0.0, 0.0, 0.0, 1.0
        if col == 0:
            return 1.0, 0.0, 0.0, 0.0, 0.0, 0.0
        if col == 1:
            return 0.0, 1.0, 0.0, 0.0, 0.0, 0.0
        if col == 2:
            return 0.0, 0.0, 1.0, 0.0, 0.0, 0.0
        # v = e x (x - p_root)
        d0 = x0 - lw[0, LW_P]; d1 = x1 - lw[0, LW_P + 1]; d2 = x2 - lw[0, LW_P + 2]
        if col == 3:
            return 0.0, -d2, d1, 1.0, 0.0, 0.0
        if col == 4:
            return d2, 0.0, -d0, 0.0, 1.0, 0.0
        return -d1, d0, 0.0, 0.0, 0.0, 1.0
    j = col - r + 1  # the link whose joint this column drives
    a0 = lw[j, LW_A]; a1 = lw[j, LW_A + 1]; a2 = lw[j, LW_A + 2]
    if lki[j, LI_TYPE] == JT_PRISMATIC:
        return a0, a1, a2, 0.0, 0.0, 0.0
    d0 = x0 - lw[j, LW_P]; d1 = x1 - lw[j, LW_P + 1]; d2 = x2 - lw[j, LW_P + 2]
    return a1 * d2 - a2 * d1, a2 * d0 - a0 * d2, a0 * d1 - a1 * d0, a0, a1, a2


@njit(**_JIT)
def _kin_linkage(lmeta, lk, lki, par, st, C, CI, m, lw, D, taug, Jpt, X, Jh):
    """Fill D(q) (d x d), generalized gravity and velocity-product forces taug = -G(q) - h(q, qd),
    the contact points X_i (world) on their links with their Jacobians J_i(q) (3 x d), and J_h(q)
    (h x d) of the held link's frame origin."""
    nl = lmeta[LM_NLINKS]
    d = lmeta[LM_D]
    r = lmeta[LM_R]
    planar = lmeta[LM_PLANAR] == 1
    q = st[S_LQ:]
    forward_kinematics(lmeta, lk, lki, q, lw)
    for a in range(d):
        taug[a] = 0.0
        for b in range(d):
            D[a, b] = 0.0
    g0 = par[P_GRAV]; g1 = par[P_GRAV + 1]; g2 = par[P_GRAV + 2]
    for k in range(nl):
        mass = lk[k, LK_MASS]
        # COM and inertia in the world
        m0 = lk[k, LK_COM]; m1 = lk[k, LK_COM + 1]; m2 = lk[k, LK_COM + 2]
        for a in range(3):
            lw[k, LW_C + a] = _world_point(lw, k, a, m0, m1, m2)
        for a in range(3):
            for b in range(3):
                s = 0.0
                for e in range(3):
                    for f in range(3):
                        s += lw[k, LW_R + 3 * a + e] * lk[k, LK_I + 3 * e + f] * lw[k, LW_R + 3 * b + f]
                lw[k, LW_IW + 3 * a + b] = s
        c0 = lw[k, LW_C]; c1 = lw[k, LW_C + 1]; c2 = lw[k, LW_C + 2]
        nc = lki[k, LI_NCHAIN]
        for t in range(nc):
            v0, v1, v2, w0, w1, w2 = _column(planar, r, lki, lw, lki[k, LI_CHAIN + t], c0, c1, c2)
            o = 3 * t
            lw[k, LW_JV + o] = v0; lw[k, LW_JV + o + 1] = v1; lw[k, LW_JV + o + 2] = v2
            lw[k, LW_JW + o] = w0; lw[k, LW_JW + o + 1] = w1; lw[k, LW_JW + o + 2] = w2
        # D += J_k^T M_k J_k over the chain columns (lower triangle), taug += J_v^T m g
        for t1 in range(nc):
            ca = lki[k, LI_CHAIN + t1]
            o1 = 3 * t1
            mv0 = mass * lw[k, LW_JV + o1]
            mv1 = mass * lw[k, LW_JV + o1 + 1]
            mv2 = mass * lw[k, LW_JV + o1 + 2]
            wa0 = lw[k, LW_JW + o1]; wa1 = lw[k, LW_JW + o1 + 1]; wa2 = lw[k, LW_JW + o1 + 2]
            iw0 = lw[k, LW_IW] * wa0 + lw[k, LW_IW + 1] * wa1 + lw[k, LW_IW + 2] * wa2
            iw1 = lw[k, LW_IW + 3] * wa0 + lw[k, LW_IW + 4] * wa1 + lw[k, LW_IW + 5] * wa2
            iw2 = lw[k, LW_IW + 6] * wa0 + lw[k, LW_IW + 7] * wa1 + lw[k, LW_IW + 8] * wa2
            taug[ca] += mv0 * g0 + mv1 * g1 + mv2 * g2
            for t2 in range(t1 + 1):
                cb = lki[k, LI_CHAIN + t2]
                o2 = 3 * t2
                D[ca, cb] += (lw[k, LW_JV + o2] * mv0 + lw[k, LW_JV + o2 + 1] * mv1
                              + lw[k, LW_JV + o2 + 2] * mv2 + lw[k, LW_JW + o2] * iw0
                              + lw[k, LW_JW + o2 + 1] * iw1 + lw[k, LW_JW + o2 + 2] * iw2)
    for a in range(d):
        for b in range(a):
            D[b, a] = D[a, b]
    if lmeta[LM_COR]:
        _bias_forces(lmeta, lk, lki, st, lw, taug)
    # contact points on their links
    for i in range(m):
        k = CI[i, CI_KEY]
        px = C[i, C_P]; py = C[i, C_P + 1]; pz = C[i, C_P + 2]
        for a in range(3):
            X[i, a] = _world_point(lw, k, a, px, py, pz)
            for b in range(d):
                Jpt[i, a, b] = 0.0
        x0 = X[i, 0]; x1 = X[i, 1]; x2 = X[i, 2]
        for t in range(lki[k, LI_NCHAIN]):
            col = lki[k, LI_CHAIN + t]
            v0, v1, v2, w0, w1, w2 = _column(planar, r, lki, lw, col, x0, x1, x2)
            Jpt[i, 0, col] = v0
            Jpt[i, 1, col] = v1
            Jpt[i, 2, col] = v2
    # hand: the held link's frame origin; planar rows (vx, vy, wz), spatial (v, w)
    hk = lmeta[LM_HELD]
    h = lmeta[LM_H]
    for a in range(h):
        for b in range(d):
            Jh[a, b] = 0.0
    x0 = lw[hk, LW_P]; x1 = lw[hk, LW_P + 1]; x2 = lw[hk, LW_P + 2]
    for t in range(lki[hk, LI_NCHAIN]):
        col = lki[hk, LI_CHAIN + t]
        v0, v1, v2, w0, w1, w2 = _column(planar, r, lki, lw, col, x0, x1, x2)
        if planar:
            Jh[0, col] = v0
            Jh[1, col] = v1
            Jh[2, col] = w2
        else:
            Jh[0, col] = v0; Jh[1, col] = v1; Jh[2, col] = v2
            Jh[3, col] = w0; Jh[4, col] = w1; Jh[5, col] = w2


@njit(inline="always", **_JIT)
def _cross_add(a0, a1, a2, b0, b1, b2, lw, k, o, scale):
    """lw[k, o:o+3] += scale * (a x b)."""
    lw[k, o] += scale * (a1 * b2 - a2 * b1)
    lw[k, o + 1] += scale * (a2 * b0 - a0 * b2)
    lw[k, o + 2] += scale * (a0 * b1 - a1 * b0)


@njit(**_JIT)
def _bias_forces(lmeta, lk, lki, st, lw, taug):
    """taug -= h(q, qd): the generalized velocity-product forces (Coriolis, centripetal,
    gyroscopic) by one forward recursion of the link velocities and of their accelerations at
    qdd = 0, then h = sum_k J_k^T (m_k a_c,k ; I_k alpha_k + w_k x I_k w_k). Needs the COM
    Jacobian columns, COMs and world inertias that ``_kin_linkage`` has just filled."""
    nl = lmeta[LM_NLINKS]
    r = lmeta[LM_R]
    planar = lmeta[LM_PLANAR]
    for a in range(3):
        lw[0, LW_AL + a] = 0.0
        lw[0, LW_AC + a] = 0.0
    if planar:
        lw[0, LW_W] = 0.0; lw[0, LW_W + 1] = 0.0; lw[0, LW_W + 2] = st[S_QD + 2]
        lw[0, LW_V] = st[S_QD]; lw[0, LW_V + 1] = st[S_QD + 1]; lw[0, LW_V + 2] = 0.0
    else:
        for a in range(3):
            lw[0, LW_V + a] = st[S_QD + a]
            lw[0, LW_W + a] = st[S_QD + 3 + a]
    for k in range(1, nl):
        p = lki[k, LI_PARENT]
        u = st[S_QD + r + k - 1]
        w0 = lw[p, LW_W]; w1 = lw[p, LW_W + 1]; w2 = lw[p, LW_W + 2]
        x0 = lw[k, LW_P] - lw[p, LW_P]; x1 = lw[k, LW_P + 1] - lw[p, LW_P + 1]; x2 = lw[k, LW_P + 2] - lw[p, LW_P + 2]
        a0 = lw[k, LW_A]; a1 = lw[k, LW_A + 1]; a2 = lw[k, LW_A + 2]
        for c in range(3):
            lw[k, LW_W + c] = lw[p, LW_W + c]
            lw[k, LW_V + c] = lw[p, LW_V + c]
            lw[k, LW_AL + c] = lw[p, LW_AL + c]
            lw[k, LW_AC + c] = lw[p, LW_AC + c]
        # v = v_p + w_p x r; acc = acc_p + alpha_p x r + w_p x (w_p x r)
        _cross_add(w0, w1, w2, x0, x1, x2, lw, k, LW_V, 1.0)
        _cross_add(lw[p, LW_AL], lw[p, LW_AL + 1], lw[p, LW_AL + 2], x0, x1, x2, lw, k, LW_AC, 1.0)
        wx0 = w1 * x2 - w2 * x1; wx1 = w2 * x0 - w0 * x2; wx2 = w0 * x1 - w1 * x0
        _cross_add(w0, w1, w2, wx0, wx1, wx2, lw, k, LW_AC, 1.0)
        if lki[k, LI_TYPE] == JT_PRISMATIC:
            # the axis turns with the parent: Coriolis 2 w_p x a u
            for c in range(3):
                lw[k, LW_V + c] += u * lw[k, LW_A + c]
            _cross_add(w0, w1, w2, a0, a1, a2, lw, k, LW_AC, 2.0 * u)
        else:
            for c in range(3):
                lw[k, LW_W + c] += u * lw[k, LW_A + c]
            _cross_add(w0, w1, w2, a0, a1, a2, lw, k, LW_AL, u)
    for k in range(nl):
        mass = lk[k, LK_MASS]
        w0 = lw[k, LW_W]; w1 = lw[k, LW_W + 1]; w2 = lw[k, LW_W + 2]
        s0 = lw[k, LW_C] - lw[k, LW_P]; s1 = lw[k, LW_C + 1] - lw[k, LW_P + 1]; s2 = lw[k, LW_C + 2] - lw[k, LW_P + 2]
        al0 = lw[k, LW_AL]; al1 = lw[k, LW_AL + 1]; al2 = lw[k, LW_AL + 2]
        # COM acceleration at qdd = 0: acc + alpha x s + w x (w x s)
        ws0 = w1 * s2 - w2 * s1; ws1 = w2 * s0 - w0 * s2; ws2 = w0 * s1 - w1 * s0
        f0 = lw[k, LW_AC] + (al1 * s2 - al2 * s1) + (w1 * ws2 - w2 * ws1)
        f1 = lw[k, LW_AC + 1] + (al2 * s0 - al0 * s2) + (w2 * ws0 - w0 * ws2)
        f2 = lw[k, LW_AC + 2] + (al0 * s1 - al1 * s0) + (w0 * ws1 - w1 * ws0)
        f0 *= mass; f1 *= mass; f2 *= mass
        # I alpha + w x I w
        iw0 = lw[k, LW_IW] * w0 + lw[k, LW_IW + 1] * w1 + lw[k, LW_IW + 2] * w2
        iw1 = lw[k, LW_IW + 3] * w0 + lw[k, LW_IW + 4] * w1 + lw[k, LW_IW + 5] * w2
        iw2 = lw[k, LW_IW + 6] * w0 + lw[k, LW_IW + 7] * w1 + lw[k, LW_IW + 8] * w2
        t0 = lw[k, LW_IW] * al0 + lw[k, LW_IW + 1] * al1 + lw[k, LW_IW + 2] * al2 + (w1 * iw2 - w2 * iw1)
        t1 = lw[k, LW_IW + 3] * al0 + lw[k, LW_IW + 4] * al1 + lw[k, LW_IW + 5] * al2 + (w2 * iw0 - w0 * iw2)
        t2 = lw[k, LW_IW + 6] * al0 + lw[k, LW_IW + 7] * al1 + lw[k, LW_IW + 8] * al2 + (w0 * iw1 - w1 * iw0)
        for t in range(lki[k, LI_NCHAIN]):
            col = lki[k, LI_CHAIN + t]
            o = 3 * t
            taug[col] -= (lw[k, LW_JV + o] * f0 + lw[k, LW_JV + o + 1] * f1 + lw[k, LW_JV + o + 2] * f2
                          + lw[k, LW_JW + o] * t0 + lw[k, LW_JW + o + 1] * t1 + lw[k, LW_JW + o + 2] * t2)


@njit(**_JIT)
def integrate_linkage(lmeta, st, qd, dt):
    """Semi-implicit Euler position update with the already-updated velocity qd."""
    d = lmeta[LM_D]
    r = lmeta[LM_R]
    nqr = lmeta[LM_NQR]
    for a in range(3):
        st[S_LQ + a] += dt * qd[a]
    if not lmeta[LM_PLANAR]:
        turn_quat(st, S_LQ + 3, qd, dt)
    for j in range(d - r):
        st[S_LQ + nqr + j] += dt * qd[r + j]


@njit(**_JIT)
def step_linkage(par, lmeta, lk, lki, st, C, CI, cnt, wk, lw, hand):
    """One haptic step of a linkage. ``hand``: wrench on the proxy at the held link's frame
    origin, world (planar: fx, fy, tau_z; spatial: f (3), tau (3)). Returns an E_* code; on a
    non-finite result the state is kept, the rendered wrench is zero and K_NONFINITE counts it."""
    d = lmeta[LM_D]
    h = lmeta[LM_H]
    if not take_hand(h, st, hand):
        return E_HAND_NONFINITE
    cap = C.shape[0]
    m = cnt[K_M]
    D, L, U, G, Y, Jh, Jpt, Jn, Bm, Cm, X, Zn, V = _views(wk, cap)
    _kin_linkage(lmeta, lk, lki, par, st, C, CI, m, lw, D, V[_V_TAUG], Jpt, X, Jh)
    ok = _core(d, h, par, st, C, CI, cnt, D, L, U, G, Y, Jh, Jpt, Jn, Bm, Cm, X, Zn, V, m)
    if end_step(ok, d, par, st, C, cnt, D, Zn, V, m):
        integrate_linkage(lmeta, st, V[_V_QD], par[P_DT])
    return E_OK


@njit(**_JIT)
def update_linkage(par, lmeta, lk, lki, st, C, CI, cnt, wk, lw, keys, cp, nrm, dsep, vc, n_in, sel,
                   newF, newI, qe, use_qe, lw_e):
    """Replace the local contact set by the engine's, as ``kernels.update_rigid`` does, with each
    contact's feature located on its own link (key column 0, checked < L). ``use_qe`` = 1:
    ``qe`` (root pose then joints, like q) is the engine's configuration at which the contacts
    were computed; its link poses go to ``lw_e``. The proxy's q and qd are never touched."""
    planar = lmeta[LM_PLANAR]
    cap = C.shape[0]
    code, nk = check_update(TOOL_PLANAR if planar else TOOL_SPATIAL, lmeta[LM_NLINKS], keys, cp, nrm,
                            dsep, vc, n_in, cap, sel)
    if code != E_OK:
        return code
    D, L, U, G, Y, Jh, Jpt, Jn, Bm, Cm, X, Zn, V = _views(wk, cap)
    forward_kinematics(lmeta, lk, lki, st[S_LQ:], lw)
    link_velocities(lmeta, lki, st, lw)
    if use_qe:
        forward_kinematics(lmeta, lk, lki, qe, lw_e)
    apply_update(planar == 1, par, st, C, CI, cnt, X, Cm, keys, cp, nrm, dsep, vc, n_in, nk, sel,
                 newF, newI, lw, lw_e, use_qe, lw[:, LW_W:LW_W + 6])
    return E_OK


@njit(**_JIT)
def link_velocities(lmeta, lki, st, lw):
    """Each link's angular velocity (``LW_W``) and its frame origin's velocity (``LW_V``), world,
    from qd (``st``) and the poses and joint axes ``forward_kinematics`` left in ``lw``: what the
    update's rules read (a contact's normal speed where they put it)."""
    nl = lmeta[LM_NLINKS]
    r = lmeta[LM_R]
    if lmeta[LM_PLANAR]:
        lw[0, LW_W] = 0.0; lw[0, LW_W + 1] = 0.0; lw[0, LW_W + 2] = st[S_QD + 2]
        lw[0, LW_V] = st[S_QD]; lw[0, LW_V + 1] = st[S_QD + 1]; lw[0, LW_V + 2] = 0.0
    else:
        for a in range(3):
            lw[0, LW_V + a] = st[S_QD + a]
            lw[0, LW_W + a] = st[S_QD + 3 + a]
    for k in range(1, nl):
        p = lki[k, LI_PARENT]
        u = st[S_QD + r + k - 1]
        w0 = lw[p, LW_W]; w1 = lw[p, LW_W + 1]; w2 = lw[p, LW_W + 2]
        x0 = lw[k, LW_P] - lw[p, LW_P]; x1 = lw[k, LW_P + 1] - lw[p, LW_P + 1]; x2 = lw[k, LW_P + 2] - lw[p, LW_P + 2]
        for c in range(3):
            lw[k, LW_W + c] = lw[p, LW_W + c]
            lw[k, LW_V + c] = lw[p, LW_V + c]
        _cross_add(w0, w1, w2, x0, x1, x2, lw, k, LW_V, 1.0)
        if lki[k, LI_TYPE] == JT_PRISMATIC:
            for c in range(3):
                lw[k, LW_V + c] += u * lw[k, LW_A + c]
        else:
            for c in range(3):
                lw[k, LW_W + c] += u * lw[k, LW_A + c]


@njit(**_JIT)
def hand_state_linkage(lmeta, lk, lki, st, lw, out, o):
    """Pose (7: x y z qw qx qy qz) of the held link's frame at out[o:o+7] and its twist (6: origin
    velocity, angular velocity) at out[o+7:o+13], world, at the current q and qd."""
    forward_kinematics(lmeta, lk, lki, st[S_LQ:], lw)
    hk = lmeta[LM_HELD]
    _link_pose(lw, hk, out, o)
    x0 = lw[hk, LW_P]; x1 = lw[hk, LW_P + 1]; x2 = lw[hk, LW_P + 2]
    for a in range(6):
        out[o + 7 + a] = 0.0
    planar = lmeta[LM_PLANAR] == 1
    r = lmeta[LM_R]
    for t in range(lki[hk, LI_NCHAIN]):
        col = lki[hk, LI_CHAIN + t]
        v0, v1, v2, w0, w1, w2 = _column(planar, r, lki, lw, col, x0, x1, x2)
        qdc = st[S_QD + col]
        out[o + 7] += v0 * qdc; out[o + 8] += v1 * qdc; out[o + 9] += v2 * qdc
        out[o + 10] += w0 * qdc; out[o + 11] += w1 * qdc; out[o + 12] += w2 * qdc


@njit(**_JIT)
def _link_pose(lw, k, out, o):
    """Pose (7) of link k's frame from its rotation rows: position, unit quaternion (w x y z)."""
    for a in range(3):
        out[o + a] = lw[k, LW_P + a]
    r00 = lw[k, LW_R]; r01 = lw[k, LW_R + 1]; r02 = lw[k, LW_R + 2]
    r10 = lw[k, LW_R + 3]; r11 = lw[k, LW_R + 4]; r12 = lw[k, LW_R + 5]
    r20 = lw[k, LW_R + 6]; r21 = lw[k, LW_R + 7]; r22 = lw[k, LW_R + 8]
    tr = r00 + r11 + r22
    # Shepperd's method: the largest of the four candidates keeps the division well conditioned
    if tr > 0.0:
        s = math.sqrt(tr + 1.0) * 2.0
        qw = 0.25 * s; qx = (r21 - r12) / s; qy = (r02 - r20) / s; qz = (r10 - r01) / s
    elif r00 > r11 and r00 > r22:
        s = math.sqrt(1.0 + r00 - r11 - r22) * 2.0
        qw = (r21 - r12) / s; qx = 0.25 * s; qy = (r01 + r10) / s; qz = (r02 + r20) / s
    elif r11 > r22:
        s = math.sqrt(1.0 + r11 - r00 - r22) * 2.0
        qw = (r02 - r20) / s; qx = (r01 + r10) / s; qy = 0.25 * s; qz = (r12 + r21) / s
    else:
        s = math.sqrt(1.0 + r22 - r00 - r11) * 2.0
        qw = (r10 - r01) / s; qx = (r02 + r20) / s; qy = (r12 + r21) / s; qz = 0.25 * s
    if qw < 0.0:
        qw = -qw; qx = -qx; qy = -qy; qz = -qz
    nrm = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
    out[o + 3] = qw / nrm
    out[o + 4] = qx / nrm
    out[o + 5] = qy / nrm
    out[o + 6] = qz / nrm


@njit(**_JIT)
def joint_state(lmeta, lk, lki, st, lw, wrench_hand, out_pose, out_twist, out_wrench, out_effort, out_q, out_qd,
                q_end, qd_end):
    """``root_state_and_efforts`` and the joint positions and rates (the last ``len(out_q)``
    coordinates before ``st[q_end]`` / ``st[qd_end]``), in one call: the linkage's ProxyState."""
    root_state_and_efforts(lmeta, lk, lki, st, lw, wrench_hand, out_pose, out_twist, out_wrench, out_effort)
    nj = out_q.shape[0]
    for j in range(nj):
        out_q[j] = st[q_end - nj + j]
        out_qd[j] = st[qd_end - nj + j]


@njit(**_JIT)
def root_state_and_efforts(lmeta, lk, lki, st, lw, wrench_hand, out_pose, out_twist, out_wrench,
                           out_effort):
    """What a ProxyState says about a linkage: the root frame's pose (7) and twist (6), world; and
    the hand wrench (6, world, at the held link's origin; planar uses fx, fy, tau_z) as the
    generalized force J_h^T F_h split into the wrench on the root frame origin (6, world) and
    one effort per joint (N m or N, positive along +q)."""
    d = lmeta[LM_D]
    r = lmeta[LM_R]
    planar = lmeta[LM_PLANAR] == 1
    forward_kinematics(lmeta, lk, lki, st[S_LQ:], lw)
    _link_pose(lw, 0, out_pose, 0)
    for a in range(6):
        out_twist[a] = 0.0
        out_wrench[a] = 0.0
    hand_to_world(planar, st, S_QD, out_twist, 0)
    hk = lmeta[LM_HELD]
    x0 = lw[hk, LW_P]; x1 = lw[hk, LW_P + 1]; x2 = lw[hk, LW_P + 2]
    for col in range(d):
        # generalized force of column col: v . f + w . tau (planar: tau about +z only)
        g = 0.0
        isin = False
        for t in range(lki[hk, LI_NCHAIN]):
            if lki[hk, LI_CHAIN + t] == col:
                isin = True
        if isin:
            v0, v1, v2, w0, w1, w2 = _column(planar, r, lki, lw, col, x0, x1, x2)
            if planar:
                g = v0 * wrench_hand[0] + v1 * wrench_hand[1] + w2 * wrench_hand[5]
            else:
                g = (v0 * wrench_hand[0] + v1 * wrench_hand[1] + v2 * wrench_hand[2]
                     + w0 * wrench_hand[3] + w1 * wrench_hand[4] + w2 * wrench_hand[5])
        if col < r:
            if planar:
                out_wrench[0 if col == 0 else (1 if col == 1 else 5)] = g
            else:
                out_wrench[col] = g
        else:
            out_effort[col - r] = g
    return d - r
