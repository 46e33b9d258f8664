"""Numba kernels of the local model of interaction (Constantinescu, Salcudean, Croft).

Two entry points per tool family, each one compiled call per haptic step / model update:

- ``step_rigid(kind, par, st, C, CI, cnt, wk, hand)``: local collision detection (eq. 3), the
  contact state machine (section IV-A), simultaneous collision impulses (eq. 11) rendered as the
  impulsive wrench (eq. 12), penalty + stick-slip friction (eq. 7), the force to the hand through
  the dynamically consistent inverse of the hand Jacobian (eq. 8), and one step of the proxy:
  by default (``P_INTEG`` = ``INTEG_IMPLICIT``) with its spring-dampers -- the controller's
  coupling at the hand point, the penalty contacts along their normals, sticking friction --
  linearised implicitly, (D + dt B + dt^2 K) dv = dt F (``_implicit_step``: stable for any
  mass, inertia, stiffness and damping; the forces rendered are the ones the proxy felt over the
  step), or the paper's semi-implicit Euler with every force explicit (``INTEG_EXPLICIT``).
  ``_watch_divergence`` counts a velocity that flips sign every step without decaying.
- ``update_rigid(kind, ..., keys, cp, n, d, vc, n_in, sel, newF, newI)``: validation, the
  capacity rule, and the update rule table of the notes (eqs. 1/4/5/6).

The tool-specific part is only the kinematics (``_kin_rigid``: D(q), gravity, the contact point
Jacobians J_i(q) and the hand Jacobian J_h(q)) and the integrator; ``_core`` works in the tool's
d-dimensional configuration space on whatever D, J_i and J_h it is given, so a linkage supplies
its own kinematics and reuses ``_core`` unchanged.

Eq. 11 without an m x m pseudo-inverse: with D = L L^T and B = Jc L^-T (m x d),
    D^-1 Jc^T (Jc D^-1 Jc^T)^+ Jc = L^-T (B^+ B) L^T,
and B^+ B is the orthogonal projector onto the row space of B, of rank r <= d. Gram-Schmidt of
the m rows b_i = L^-1 Jc_i^T gives an orthonormal basis U (r x d), so the velocity jump is
    w = L^T qd0,  dw = -(1 + e) U^T U w,  qd1 = qd0 + L^-T dw,
costing O(m d^2) instead of an O(m^3) SVD. Kinetic energy is |w|^2 / 2 and the projected part
of w is scaled by -e, so for e in [0, 1] it never increases (e = 1 keeps it). The per-contact
impulses p (the minimum-norm solution, which is what the pseudo-inverse returns) come from the
r x r system (C^T C) alpha = U dw with rows c_i = U b_i, p_i = c_i . alpha.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from ...protocol.quaternion import quat_to_matrix_into

from .layout import (
    C_CP, C_D, C_DEF, C_FN, C_FT, C_IMP, C_N, C_P, C_REC, C_S, C_SPREV, C_TU, C_VC, C_VN, C_Z,
    CI_AGE, CI_FLIPS, CI_KEY, CI_SLIP, CI_STATE,
    CST_COLLIDING, CST_IMPENDING, CST_PENETRATING, CST_SEPARATING,
    E_CONTACT_NONFINITE, E_DUPLICATE_KEY, E_HAND_NONFINITE, E_LINK_OUT_OF_RANGE,
    E_NORMAL_NOT_UNIT, E_NORMAL_OUT_OF_PLANE, E_OK, E_TOO_MANY,
    K_COLLISIONS, K_DEFORMED, K_DROPPED, K_LEFT, K_M, K_N_COLLIDING, K_N_IMPENDING,
    K_N_PENETRATING, K_N_SEPARATING, K_NEW, K_NONFINITE, K_PROXY, K_RANK, K_SLIPPING, K_STEPS,
    K_FLIPS, K_FLIPS_TAKEN, K_HELD, K_RECOVERING, K_REKEYED, K_UPDATES,
    FLIP_DOT, FLIP_REFUSE_MAX, KEY_SLIDE_FACTOR, MAX_DOF, NCOLS_F, NCOLS_I, REKEY_COS, REKEY_DISTANCE_M,
    P_AXIS, P_B, P_BT, P_DT, P_E, P_GRAV, P_HAND, P_INERTIA, P_K, P_KT, P_MASS, P_MUK, P_MUS,
    P_EPS, P_ORIGIN, P_POLICY, P_REC_AGE, P_REC_CUT, P_REC_FRATE, P_REC_TAU, P_REC_V, P_REC_VN,
    P_CPL_BR, P_CPL_BT, P_CPL_KR, P_CPL_KT, P_INTEG, INTEG_IMPLICIT, K_DIVERGED, K_OSC_RUN,
    DIVERGE_DECAY, DIVERGE_SPEED, DIVERGE_STEPS,
    POLICY_PAPER_LITERAL, POLICY_RIGID, PS_COLLIDING, PS_FREE, PS_RESTING,
    S_EREC, S_RECF, S_FCPL, S_FENV, S_FH, S_QDP, S_FIMP, S_FPEN, S_GIMP, S_KE, S_KE_POST, S_KE_PRE, S_Q, S_QD, S_T,
    TOOL_1DOF, TOOL_PLANAR, TOOL_SPATIAL, TOUCH_TOL_M, UNIT_TOL,
)

_JIT = dict(cache=True, nogil=True, error_model="numpy")

#: Relative Gram-Schmidt threshold: a constraint row whose component outside the span of the
#: previous rows is below this fraction of its own norm adds no rank (exactly opposing or
#: coincident normals give residuals ~1e-16).
RANK_TOL = 1e-9

# rows of the vector scratch block
_V_QD0 = 0     # velocity at the start of the step
_V_QD = 1      # velocity after the impulse
_V_W = 2       # L^T qd
_V_T1 = 3
_V_T2 = 4
_V_TAU = 5     # generalized penalty + friction force
_V_TAUG = 6    # generalized gravity force
_V_GIMP = 7    # generalized impulse
_V_TOT = 8     # total generalized force
_V_HV = 9      # hand-space temporaries
_V_DV = 10     # the implicit step's velocity change
_V_BASE = 11   # the implicit step's generalized force without the contacts
_NVEC = 12
#: Most solves of the implicit step per haptic step: the contacts that push at its end are found
#: by solving with a guess (those pushing at its start), then again while the set changes.
IMPLICIT_MAX_SOLVES = 8


def workspace_size(capacity: int) -> int:
    """Float64 elements of the scratch array for ``capacity`` contacts."""
    m = MAX_DOF
    return 5 * m * m + 6 * m + capacity * (3 * m + 3 * m + 3 + 3) + _NVEC * m


@njit(**_JIT)
def _views(wk, cap):
    m = MAX_DOF
    o = 0
    D = wk[o:o + m * m].reshape((m, m)); o += m * m
    L = wk[o:o + m * m].reshape((m, m)); o += m * m
    U = wk[o:o + m * m].reshape((m, m)); o += m * m
    G = wk[o:o + m * m].reshape((m, m)); o += m * m
    Y = wk[o:o + m * m].reshape((m, m)); o += m * m
    Jh = wk[o:o + 6 * m].reshape((6, m)); o += 6 * m
    Jpt = wk[o:o + cap * 3 * m].reshape((cap, 3, m)); o += cap * 3 * m
    Jn = wk[o:o + cap * m].reshape((cap, m)); o += cap * m
    Bm = wk[o:o + cap * m].reshape((cap, m)); o += cap * m
    Cm = wk[o:o + cap * m].reshape((cap, m)); o += cap * m
    X = wk[o:o + cap * 3].reshape((cap, 3)); o += cap * 3
    Zn = wk[o:o + cap * 3].reshape((cap, 3)); o += cap * 3
    V = wk[o:o + _NVEC * m].reshape((_NVEC, m)); o += _NVEC * m
    return D, L, U, G, Y, Jh, Jpt, Jn, Bm, Cm, X, Zn, V


# --------------------------------------------------------------------------------------------
# small dense linear algebra (d <= MAX_DOF), no allocation
# --------------------------------------------------------------------------------------------
@njit(**_JIT)
def _chol(A, L, n):
    """L L^T = A (lower); False if A is not positive definite."""
    for i in range(n):
        for j in range(i + 1):
            s = A[i, j]
            for k in range(j):
                s -= L[i, k] * L[j, k]
            if i == j:
                if not s > 0.0:
                    return False
                L[i, i] = math.sqrt(s)
            else:
                L[i, j] = s / L[j, j]
        for j in range(i + 1, n):
            L[i, j] = 0.0
    return True


@njit(**_JIT)
def _fwd(L, b, x, n):
    """Solve L x = b (x may alias b)."""
    for i in range(n):
        s = b[i]
        for k in range(i):
            s -= L[i, k] * x[k]
        x[i] = s / L[i, i]


@njit(**_JIT)
def _bwd(L, b, x, n):
    """Solve L^T x = b (x may alias b)."""
    for i in range(n - 1, -1, -1):
        s = b[i]
        for k in range(i + 1, n):
            s -= L[k, i] * x[k]
        x[i] = s / L[i, i]


#: the protocol's quaternion (w, x, y, z) -> rotation matrix, jitted here (the clients' narrow
#: phase jits the same function)
_quat_to_mat = njit(inline="always", error_model="numpy")(quat_to_matrix_into)


# --------------------------------------------------------------------------------------------
# rigid-tool kinematics: body <-> world points, D(q), gravity, J_i(q), J_h(q)
# --------------------------------------------------------------------------------------------
@njit(**_JIT)
def _rigid_pose(kind, par, st, R, c):
    """Body-to-world rotation R (3x3) and COM position c (3) of a rigid tool."""
    for i in range(3):
        for j in range(3):
            R[i, j] = 1.0 if i == j else 0.0
    if kind == TOOL_1DOF:
        x = st[S_Q]
        for j in range(3):
            c[j] = par[P_ORIGIN + j] + x * par[P_AXIS + j]
    elif kind == TOOL_PLANAR:
        th = st[S_Q + 2]
        ct = math.cos(th)
        sn = math.sin(th)
        R[0, 0] = ct; R[0, 1] = -sn
        R[1, 0] = sn; R[1, 1] = ct
        c[0] = st[S_Q]; c[1] = st[S_Q + 1]; c[2] = 0.0
    else:
        _quat_to_mat(st[S_Q + 3:S_Q + 7], R)
        c[0] = st[S_Q]; c[1] = st[S_Q + 1]; c[2] = st[S_Q + 2]


@njit(**_JIT)
def _kin_rigid(kind, par, st, C, m, R, c, D, taug, Jpt, X, Jh):
    """Fill D(q) (d x d), generalized gravity taug = -G(q), the world contact points X_i, the
    point Jacobians J_i(q) (3 x d, world velocity of the point) and J_h(q) (h x d)."""
    _rigid_pose(kind, par, st, R, c)
    mass = par[P_MASS]
    if kind == TOOL_1DOF:
        D[0, 0] = mass
        taug[0] = mass * (par[P_GRAV] * par[P_AXIS] + par[P_GRAV + 1] * par[P_AXIS + 1]
                          + par[P_GRAV + 2] * par[P_AXIS + 2])
        Jh[0, 0] = 1.0
        for i in range(m):
            for j in range(3):
                X[i, j] = c[j] + C[i, C_P + j]
                Jpt[i, j, 0] = par[P_AXIS + j]
    elif kind == TOOL_PLANAR:
        for a in range(3):
            for b in range(3):
                D[a, b] = 0.0
        D[0, 0] = mass
        D[1, 1] = mass
        D[2, 2] = par[P_INERTIA + 8]
        taug[0] = mass * par[P_GRAV]
        taug[1] = mass * par[P_GRAV + 1]
        taug[2] = 0.0
        hx = R[0, 0] * par[P_HAND] + R[0, 1] * par[P_HAND + 1]
        hy = R[1, 0] * par[P_HAND] + R[1, 1] * par[P_HAND + 1]
        Jh[0, 0] = 1.0; Jh[0, 1] = 0.0; Jh[0, 2] = -hy
        Jh[1, 0] = 0.0; Jh[1, 1] = 1.0; Jh[1, 2] = hx
        Jh[2, 0] = 0.0; Jh[2, 1] = 0.0; Jh[2, 2] = 1.0
        for i in range(m):
            rx = R[0, 0] * C[i, C_P] + R[0, 1] * C[i, C_P + 1]
            ry = R[1, 0] * C[i, C_P] + R[1, 1] * C[i, C_P + 1]
            X[i, 0] = c[0] + rx
            X[i, 1] = c[1] + ry
            X[i, 2] = 0.0
            Jpt[i, 0, 0] = 1.0; Jpt[i, 0, 1] = 0.0; Jpt[i, 0, 2] = -ry
            Jpt[i, 1, 0] = 0.0; Jpt[i, 1, 1] = 1.0; Jpt[i, 1, 2] = rx
            Jpt[i, 2, 0] = 0.0; Jpt[i, 2, 1] = 0.0; Jpt[i, 2, 2] = 0.0
    else:
        for a in range(6):
            for b in range(6):
                D[a, b] = 0.0
        D[0, 0] = mass
        D[1, 1] = mass
        D[2, 2] = mass
        # world inertia R I_body R^T
        for a in range(3):
            for b in range(3):
                s = 0.0
                for k in range(3):
                    for l in range(3):
                        s += R[a, k] * par[P_INERTIA + 3 * k + l] * R[b, l]
                D[3 + a, 3 + b] = s
        for a in range(3):
            taug[a] = mass * par[P_GRAV + a]
            taug[3 + a] = 0.0
        hx = R[0, 0] * par[P_HAND] + R[0, 1] * par[P_HAND + 1] + R[0, 2] * par[P_HAND + 2]
        hy = R[1, 0] * par[P_HAND] + R[1, 1] * par[P_HAND + 1] + R[1, 2] * par[P_HAND + 2]
        hz = R[2, 0] * par[P_HAND] + R[2, 1] * par[P_HAND + 1] + R[2, 2] * par[P_HAND + 2]
        for a in range(6):
            for b in range(6):
                Jh[a, b] = 1.0 if a == b else 0.0
        # v_hand = v + omega x r_h = v - [r_h]x omega
        Jh[0, 4] = hz; Jh[0, 5] = -hy
        Jh[1, 3] = -hz; Jh[1, 5] = hx
        Jh[2, 3] = hy; Jh[2, 4] = -hx
        for i in range(m):
            px = C[i, C_P]; py = C[i, C_P + 1]; pz = C[i, C_P + 2]
            rx = R[0, 0] * px + R[0, 1] * py + R[0, 2] * pz
            ry = R[1, 0] * px + R[1, 1] * py + R[1, 2] * pz
            rz = R[2, 0] * px + R[2, 1] * py + R[2, 2] * pz
            X[i, 0] = c[0] + rx
            X[i, 1] = c[1] + ry
            X[i, 2] = c[2] + rz
            for a in range(3):
                for b in range(3):
                    Jpt[i, a, b] = 1.0 if a == b else 0.0
            Jpt[i, 0, 3] = 0.0; Jpt[i, 0, 4] = rz; Jpt[i, 0, 5] = -ry
            Jpt[i, 1, 3] = -rz; Jpt[i, 1, 4] = 0.0; Jpt[i, 1, 5] = rx
            Jpt[i, 2, 3] = ry; Jpt[i, 2, 4] = -rx; Jpt[i, 2, 5] = 0.0


@njit(inline="always", **_JIT)
def turn_quat(st, o, qd, dt):
    """The unit quaternion (w x y z) at ``st[o:o + 4]`` turned by the world angular velocity
    ``qd[3:6]`` over ``dt`` (exact for a constant rate: q <- exp(w dt / 2) (x) q), renormalised."""
    wx = qd[3]; wy = qd[4]; wz = qd[5]
    wn = math.sqrt(wx * wx + wy * wy + wz * wz)
    half = 0.5 * wn * dt
    if wn > 0.0:
        sc = math.sin(half) / wn
    else:
        sc = 0.5 * dt
    dw = math.cos(half); dx = sc * wx; dy = sc * wy; dz = sc * wz
    qw = st[o]; qx = st[o + 1]; qy = st[o + 2]; qz = st[o + 3]
    # world-frame angular velocity: q <- dq (x) q
    nw = dw * qw - dx * qx - dy * qy - dz * qz
    nx = dw * qx + dx * qw + dy * qz - dz * qy
    ny = dw * qy - dx * qz + dy * qw + dz * qx
    nz = dw * qz + dx * qy - dy * qx + dz * qw
    inv = 1.0 / math.sqrt(nw * nw + nx * nx + ny * ny + nz * nz)
    st[o] = nw * inv
    st[o + 1] = nx * inv
    st[o + 2] = ny * inv
    st[o + 3] = nz * inv


@njit(**_JIT)
def _integrate_rigid(kind, st, qd, dt):
    """Semi-implicit Euler position update with the already-updated velocity qd."""
    if kind == TOOL_1DOF:
        st[S_Q] += dt * qd[0]
    elif kind == TOOL_PLANAR:
        st[S_Q] += dt * qd[0]
        st[S_Q + 1] += dt * qd[1]
        st[S_Q + 2] += dt * qd[2]
    else:
        st[S_Q] += dt * qd[0]
        st[S_Q + 1] += dt * qd[1]
        st[S_Q + 2] += dt * qd[2]
        turn_quat(st, S_Q + 3, qd, dt)


# --------------------------------------------------------------------------------------------
# the tool-independent step (configuration space, dimension d; hand space, dimension h)
# --------------------------------------------------------------------------------------------
@njit(**_JIT)
def _render(d, h, L, Jh, Y, G, tau, out, V):
    """out = Jbar_h^T tau = (J_h D^-1 J_h^T)^-1 J_h D^-1 tau (eq. 8, Khatib's inverse)."""
    u = V[_V_T1]
    _fwd(L, tau, u, d)                       # u = L^-1 tau
    for r in range(h):
        for a in range(d):
            Y[r, a] = Jh[r, a]
        _fwd(L, Y[r], Y[r], d)               # y_r = L^-1 J_h[r]^T
    hv = V[_V_HV]
    for r in range(h):
        s = 0.0
        for a in range(d):
            s += Y[r, a] * u[a]
        hv[r] = s                            # J_h D^-1 tau
        for c in range(r + 1):
            g = 0.0
            for a in range(d):
                g += Y[r, a] * Y[c, a]
            G[r, c] = g                      # J_h D^-1 J_h^T (lower part)
            G[c, r] = g
    Lh = Y  # reuse: Y is no longer needed once G is built
    if not _chol(G, Lh, h):
        return False
    _fwd(Lh, hv, hv, h)
    _bwd(Lh, hv, out, h)
    return True


@njit(**_JIT)
def _recovering(deformation_m, age_updates, s_m, vn_m_per_s, age, vg):
    """A contact is recovered this step: deformed, persisting (``age`` updates), touching at the
    last step, and the proxy resting on it (normal speed at most ``vg``; 0: any). Its columns
    come as numbers, not as the arrays: taking ``C`` and ``CI``, this call cost about 37 ns per
    contact (2.4 us a step at 64 contacts, none of them deformed; numba passes arrays to a
    kernel it does not inline with their reference counts); taking numbers it costs nothing
    measurable."""
    return (deformation_m > 0.0 and age_updates >= age and s_m <= TOUCH_TOL_M
            and (vg <= 0.0 or abs(vn_m_per_s) <= vg))


@njit(**_JIT)
def _recover(par, st, C, CI, cnt, m):
    """Deformation recovery: move each deformed, persisting, touching contact's constraint back
    towards the true geometry (its C_REC grows, its C_DEF shrinks), so the proxy is brought out
    to the real surface. Bounds: the speed ``P_REC_V`` per contact, the summed penalty force it
    adds at a fixed pose ``P_REC_FRATE`` (N/s, shared by the recovering contacts), an exponential
    landing (speed <= remaining / ``P_REC_TAU``). It only deepens contacts already touching (no
    new collision, no impulse) and never pulls: the penalty force stays one-sided. Its work on the
    proxy (normal force x recovered distance) accumulates in ``S_EREC``."""
    vmax = par[P_REC_V] * (1.0 - par[P_REC_CUT])
    st[S_RECF] = 0.0
    if not vmax > 0.0 or m == 0:
        cnt[K_RECOVERING] = 0
        return
    age = par[P_REC_AGE]
    vg = par[P_REC_VN]
    n_r = 0
    for i in range(m):
        if _recovering(C[i, C_DEF], CI[i, CI_AGE], C[i, C_S], C[i, C_VN], age, vg):
            n_r += 1
    cnt[K_RECOVERING] = n_r
    if n_r == 0:
        return
    dt = par[P_DT]
    k = par[P_K]
    v = vmax
    fr = par[P_REC_FRATE]
    if fr > 0.0 and k > 0.0 and fr / (k * n_r) < v:
        v = fr / (k * n_r)
    tau = par[P_REC_TAU]
    e = 0.0
    f = 0.0
    for i in range(m):
        dd = C[i, C_DEF]
        if not _recovering(C[i, C_DEF], CI[i, CI_AGE], C[i, C_S], C[i, C_VN], age, vg):
            continue
        step = v * dt
        if tau > 0.0 and dd * dt / tau < step:
            step = dd * dt / tau
        if step > dd or dd < 1e-9:
            step = dd                          # the last nanometre: done
        C[i, C_DEF] = dd - step
        C[i, C_REC] += step
        e += C[i, C_FN] * step
        f += k * step
    st[S_EREC] += e
    st[S_RECF] = f


@njit(**_JIT)
def _plane_speed(vc_m_per_s, sprev_m, cut):
    """The constraint's speed along its normal this step (set-position modulation).

    Contract: the engine's ``v_constr`` unchanged, except for a constraint that advances into
    the tool (``v_constr > 0``) at a contact touching at the last step (``sprev <= TOUCH_TOL_M``)
    while the passivity layer is short (``cut > 0``): then ``(1 - cut) v_constr``, 0 from
    ``cut >= 1``. Never faster than the engine's, never reversed, never changed for a receding
    or separated constraint: only the part of an update's motion that pushes into the proxy,
    and so stores energy in its penalty spring, waits for the budget. A non-finite cut holds
    nothing back (the layer's level is checked where it is made)."""
    if vc_m_per_s > 0.0 and cut > 0.0 and sprev_m <= TOUCH_TOL_M:
        if cut >= 1.0:
            return 0.0
        return vc_m_per_s * (1.0 - cut)
    return vc_m_per_s


@njit(**_JIT)
def _hold(par, st, C, cnt, m):
    """Set-position modulation of the model's moving geometry (Lee and Huang's PSPM, for the
    local model's constraints): the part of this step's constraint advance that ``_plane_speed``
    holds back is moved from the constraint (``C_REC`` down) into the deformation (``C_DEF`` up),
    so the proxy's separation grows by it and the rules' own recovery completes it later, at the
    recovery's bounded speed, itself slowed by the same cut. A geometry jump needs nothing
    here: the update rules (eqs. 4/5) never deepen a touching contact at an update; they deform
    it, and the recovery is what stores that energy. ``K_HELD`` counts the contacts held."""
    cut = par[P_REC_CUT]
    n_h = 0
    if cut > 0.0:
        dt = par[P_DT]
        t = st[S_T]
        for i in range(m):
            vc = C[i, C_VC]
            # the advance eq. 2 adds from the last step to this one: none yet at an update's step
            span = t - C[i, C_TU]
            if span > dt:
                span = dt
            held = (vc - _plane_speed(vc, C[i, C_S], cut)) * span
            if held > 0.0:
                C[i, C_REC] -= held
                C[i, C_DEF] += held
                n_h += 1
    cnt[K_HELD] = n_h


@njit(**_JIT)
def _core(d, h, par, st, C, CI, cnt, D, L, U, G, Y, Jh, Jpt, Jn, Bm, Cm, X, Zn, V, m):
    """Everything after the kinematics. Reads qd from st, leaves the new velocity in V[_V_QD]
    and the rendered wrenches in st; returns False when the result is not finite."""
    dt = par[P_DT]
    k = par[P_K]
    b = par[P_B]
    e = par[P_E]
    mus = par[P_MUS]
    muk = par[P_MUK]
    kt = par[P_KT]
    bt = par[P_BT]
    t = st[S_T]
    qd0 = V[_V_QD0]
    qd = V[_V_QD]
    for a in range(d):
        qd0[a] = st[S_QD + a]
        qd[a] = qd0[a]
    cut = par[P_REC_CUT]
    _hold(par, st, C, cnt, m)
    _recover(par, st, C, CI, cnt, m)
    if not _chol(D, L, d):
        return False

    # local collision detection (eq. 3) and contact states (section IV-A)
    n_imp = 0
    n_col = 0
    n_pen = 0
    n_sep = 0
    for i in range(m):
        n0 = C[i, C_N]; n1 = C[i, C_N + 1]; n2 = C[i, C_N + 2]
        # the constraint moves with v_constr along n since its update (eq. 2), and towards the
        # tool by what the recovery took back of the deformation (less what the layer held back)
        s = (n0 * (X[i, 0] - C[i, C_CP]) + n1 * (X[i, 1] - C[i, C_CP + 1])
             + n2 * (X[i, 2] - C[i, C_CP + 2]) - C[i, C_VC] * (t - C[i, C_TU]) - C[i, C_REC])
        vn = -_plane_speed(C[i, C_VC], C[i, C_S], cut)
        for a in range(d):
            jn = n0 * Jpt[i, 0, a] + n1 * Jpt[i, 1, a] + n2 * Jpt[i, 2, a]
            Jn[i, a] = jn
            vn += jn * qd0[a]
        sprev = C[i, C_S]
        C[i, C_SPREV] = sprev
        C[i, C_S] = s
        C[i, C_VN] = vn
        C[i, C_IMP] = 0.0
        if s > TOUCH_TOL_M:
            CI[i, CI_STATE] = CST_IMPENDING
            n_imp += 1
        elif vn > 0.0:
            CI[i, CI_STATE] = CST_SEPARATING
            n_sep += 1
        elif sprev > 0.0:
            CI[i, CI_STATE] = CST_COLLIDING
            n_col += 1
        else:
            CI[i, CI_STATE] = CST_PENETRATING
            n_pen += 1
    cnt[K_N_IMPENDING] = n_imp
    cnt[K_N_COLLIDING] = n_col
    cnt[K_N_PENETRATING] = n_pen
    cnt[K_N_SEPARATING] = n_sep
    if n_col > 0:
        cnt[K_PROXY] = PS_COLLIDING
    elif n_imp == m:
        cnt[K_PROXY] = PS_FREE
    else:
        cnt[K_PROXY] = PS_RESTING

    # simultaneous collision impulses at colliding + penetrating contacts (eqs. 10-12), with the
    # constraints momentarily static: v_n = n^T J qd
    gimp = V[_V_GIMP]
    for a in range(d):
        gimp[a] = 0.0
    w = V[_V_W]
    for a in range(d):
        s = 0.0
        for k2 in range(a, d):
            s += L[k2, a] * qd0[k2]
        w[a] = s                              # w = L^T qd0
    ke0 = 0.0
    for a in range(d):
        ke0 += w[a] * w[a]
    ke0 *= 0.5
    st[S_KE_PRE] = ke0
    st[S_KE_POST] = ke0
    if n_col > 0:
        r = 0
        tmp = V[_V_T1]
        for i in range(m):
            stt = CI[i, CI_STATE]
            if stt != CST_COLLIDING and stt != CST_PENETRATING:
                continue
            _fwd(L, Jn[i], Bm[i], d)          # b_i = L^-1 Jc_i^T
            nb = 0.0
            for a in range(d):
                tmp[a] = Bm[i, a]
                nb += tmp[a] * tmp[a]
            nb = math.sqrt(nb)
            if r >= d or not nb > 0.0:
                continue
            for _pass in range(2):            # re-orthogonalize once for accuracy
                for q_ in range(r):
                    c = 0.0
                    for a in range(d):
                        c += U[q_, a] * tmp[a]
                    for a in range(d):
                        tmp[a] -= c * U[q_, a]
            nr = 0.0
            for a in range(d):
                nr += tmp[a] * tmp[a]
            nr = math.sqrt(nr)
            if nr > RANK_TOL * nb:
                for a in range(d):
                    U[r, a] = tmp[a] / nr
                r += 1
        cnt[K_RANK] = r
        # dw = -(1 + e) U^T U w, in the r coordinates: beta = U w
        beta = V[_V_T2]
        for q_ in range(r):
            s = 0.0
            for a in range(d):
                s += U[q_, a] * w[a]
            beta[q_] = -(1.0 + e) * s
        dw = V[_V_TOT]
        for a in range(d):
            s = 0.0
            for q_ in range(r):
                s += U[q_, a] * beta[q_]
            dw[a] = s
        ke1 = 0.0
        for a in range(d):
            ke1 += (w[a] + dw[a]) * (w[a] + dw[a])
        st[S_KE_POST] = 0.5 * ke1
        # generalized impulse Jc^T p = D (qd1 - qd0) = L dw
        for a in range(d):
            s = 0.0
            for k2 in range(a + 1):
                s += L[a, k2] * dw[k2]
            gimp[a] = s
        _bwd(L, dw, tmp, d)                   # L^-T dw
        for a in range(d):
            qd[a] = qd0[a] + tmp[a]
        # per-contact impulses: minimum-norm p with Jc^T p = L dw (what the pseudo-inverse gives)
        if r > 0:
            for q_ in range(r):
                for c2 in range(r):
                    G[q_, c2] = 0.0
            for i in range(m):
                stt = CI[i, CI_STATE]
                if stt != CST_COLLIDING and stt != CST_PENETRATING:
                    continue
                for q_ in range(r):
                    s = 0.0
                    for a in range(d):
                        s += U[q_, a] * Bm[i, a]
                    Cm[i, q_] = s
                for q_ in range(r):
                    for c2 in range(q_ + 1):
                        G[q_, c2] += Cm[i, q_] * Cm[i, c2]
            for q_ in range(r):
                for c2 in range(q_ + 1, r):
                    G[q_, c2] = G[c2, q_]
            if _chol(G, Y, r):
                _fwd(Y, beta, beta, r)
                _bwd(Y, beta, beta, r)
                for i in range(m):
                    stt = CI[i, CI_STATE]
                    if stt != CST_COLLIDING and stt != CST_PENETRATING:
                        continue
                    s = 0.0
                    for q_ in range(r):
                        s += Cm[i, q_] * beta[q_]
                    C[i, C_IMP] = s
        cnt[K_COLLISIONS] += 1
    for a in range(d):
        st[S_GIMP + a] = gimp[a]

    # penalty (never pulling) and stick-slip friction at contacts with s <= 0, from the
    # post-impulse velocity
    tau = V[_V_TAU]
    for a in range(d):
        tau[a] = 0.0
    n_slip = 0
    for i in range(m):
        n0 = C[i, C_N]; n1 = C[i, C_N + 1]; n2 = C[i, C_N + 2]
        s = C[i, C_S]
        if s > TOUCH_TOL_M:
            C[i, C_FN] = 0.0
            for j in range(3):
                C[i, C_FT + j] = 0.0
                Zn[i, j] = 0.0
            CI[i, CI_SLIP] = 0
            continue
        vn = -_plane_speed(C[i, C_VC], C[i, C_SPREV], cut)
        for a in range(d):
            vn += Jn[i, a] * qd[a]
        C[i, C_VN] = vn
        fn = -k * s - b * vn
        if fn < 0.0:
            fn = 0.0
        C[i, C_FN] = fn
        f0 = fn * n0
        f1 = fn * n1
        f2 = fn * n2
        if (mus > 0.0 or muk > 0.0) and fn > 0.0:
            # tangential velocity of the proxy point (the engine reports no tangential
            # constraint velocity, so friction acts against the proxy's own sliding)
            v0, v1, v2 = _tangential(i, d, C, Jpt, qd)
            z0, z1, z2 = _bristle(i, C, v0, v1, v2, dt)
            t0 = -kt * z0 - bt * v0
            t1 = -kt * z1 - bt * v1
            t2 = -kt * z2 - bt * v2
            tn = math.sqrt(t0 * t0 + t1 * t1 + t2 * t2)
            if tn > mus * fn:
                # breakaway: the stick point jumps so the spring holds the kinetic force
                zn = math.sqrt(z0 * z0 + z1 * z1 + z2 * z2)
                if zn > 0.0 and kt > 0.0:
                    sc = muk * fn / (kt * zn)
                    z0 *= sc; z1 *= sc; z2 *= sc
                    t0 = -kt * z0; t1 = -kt * z1; t2 = -kt * z2
                else:
                    t0 = 0.0; t1 = 0.0; t2 = 0.0
                CI[i, CI_SLIP] = 1
                n_slip += 1
            else:
                CI[i, CI_SLIP] = 0
            Zn[i, 0] = z0; Zn[i, 1] = z1; Zn[i, 2] = z2
            C[i, C_FT] = t0; C[i, C_FT + 1] = t1; C[i, C_FT + 2] = t2
            f0 += t0; f1 += t1; f2 += t2
        else:
            for j in range(3):
                C[i, C_FT + j] = 0.0
                Zn[i, j] = 0.0
            CI[i, CI_SLIP] = 0
        for a in range(d):
            tau[a] += Jpt[i, 0, a] * f0 + Jpt[i, 1, a] * f1 + Jpt[i, 2, a] * f2
    cnt[K_SLIPPING] = n_slip

    # proxy dynamics (eq. 7, Coriolis neglected): D qdd = tau + J_h^T F_h - G
    tot = V[_V_TOT]
    taug = V[_V_TAUG]
    for a in range(d):
        s = tau[a] + taug[a]
        for r in range(h):
            s += Jh[r, a] * st[S_FH + r]
        tot[a] = s
    if par[P_INTEG] == INTEG_IMPLICIT:
        if not _implicit_step(d, h, par, st, C, CI, cnt, Jh, Jpt, Jn, D, G, Y, Cm, Zn, V, m):
            return False
    else:
        _fwd(L, tot, tot, d)
        _bwd(L, tot, tot, d)
        for a in range(d):
            qd[a] += dt * tot[a]
        for r in range(h):
            st[S_FCPL + r] = 0.0

    # what the hand feels: penalty + friction (eq. 8) and the impulsive wrench (eq. 12)
    fpen = V[_V_T2]
    if not _render(d, h, L, Jh, Y, G, tau, fpen, V):
        return False
    for r in range(h):
        st[S_FPEN + r] = fpen[r]
    for a in range(d):
        tot[a] = gimp[a] / dt
    if not _render(d, h, L, Jh, Y, G, tot, fpen, V):
        return False
    for r in range(h):
        st[S_FIMP + r] = fpen[r]
        st[S_FENV + r] = st[S_FPEN + r] + fpen[r]

    ok = True
    for a in range(d):
        if not math.isfinite(qd[a]):
            ok = False
    for r in range(h):
        if not math.isfinite(st[S_FENV + r]):
            ok = False
    return ok


@njit(**_JIT)
def _implicit_step(d, h, par, st, C, CI, cnt, Jh, Jpt, Jn, D, A, LA, W, Zn, V, m):
    """The proxy's velocity update with its stiff and damped terms linearised implicitly:
    (D + dt B + dt^2 K) dv = dt F, F the generalized force at the start of the step (``V[_V_TOT]``,
    as the explicit step has it), B and K the spring-dampers acting on the proxy: the controller's
    coupling at the hand point (``P_CPL_*``, hand space through J_h), each contact that pushes
    (k, b along its normal through J_n) and each sticking friction bristle (k_t, b_t in its
    tangent plane). As dt B + dt^2 K << D it is the explicit step; for any stiffness, damping and
    mass it neither flips nor grows (a spring alone keeps its energy, any damper dissipates): a
    gram-light tool on the coupling and the contacts of a kilogram one is stable.

    Contacts are one-sided and friction is bounded, both at the step's end: a touching contact is
    in the system when its linearised normal force there, f_e = f_0 - (b + dt k) J_n dv (f_0 =
    -k s - b v_n now, unclamped), pushes; with friction its bristle sticks, the stick force
    there t_0 - (b_t + dt k_t) (I - n n^T) J_i dv (t_0 the stick force now, as the friction
    pass has it), while that stays within mu_s f_e; once it leaves the cone it slips at mu_k f_0
    (the friction pass's kinetic level) against that stick force (and it sticks again if its
    stick force would be inside). The guess is the friction
    pass's (the contacts pushing now, its stick / slip); the step is solved again while a
    contact enters or leaves the system or its bristle changes between stick and slip (at most
    ``IMPLICIT_MAX_SOLVES`` solves; if they run out, a stick force is cut to the cone). Without that, a contact creeping out of
    an overdamped penetration (its force about zero) entered and left the system on alternate
    steps, and whether a contact had friction was decided by a rounding-sized force at the start.

    The hand wrench came with the velocity before the step's collision impulse: its coupling
    damper is taken at the velocity the impulse left (-B J_h (qd - qd0) more), as the contacts'
    dampers are.

    On return ``V[_V_QD]`` holds the new velocity, ``V[_V_TAU]`` the generalized contact force the
    proxy felt over the step (what eq. 8 renders), C_FN and C_FT that force per contact, CI_SLIP
    and the bristles (Zn) where the step left them, ``S_FCPL`` the coupling's change. ``W``
    (cap x MAX_DOF) is scratch: per contact 0: in the system; 1: f_0; 2: friction mode (0 none,
    1 stick, 2 slip as the friction pass found it, 3 slip after breaking away, 4 stick after
    slipping); 3..5: t_0; 6..8: the bristle the stick force t_0 stretches; 9..11: the
    kinetic force. False: not finite."""
    dt = par[P_DT]
    k = par[P_K]
    b = par[P_B]
    kt = par[P_KT]
    bt = par[P_BT]
    mus = par[P_MUS]
    muk = par[P_MUK]
    tot = V[_V_TOT]
    tau = V[_V_TAU]
    base = V[_V_BASE]
    dv = V[_V_DV]
    qd = V[_V_QD]
    rhs = V[_V_T1]
    for a in range(d):
        base[a] = tot[a] - tau[a]
    # the coupling's damper at the velocity the collision impulse left (the hand wrench came with
    # the velocity before it): -B J_h (qd - qd0), hand space, kept in S_FCPL for the controller
    qd0 = V[_V_QD0]
    b_t = par[P_CPL_BT]
    b_r = par[P_CPL_BR]
    for r in range(h):
        s = 0.0
        for a in range(d):
            s += Jh[r, a] * (qd[a] - qd0[a])
        s *= -(b_r if ((h == 3 and r == 2) or (h == 6 and r >= 3)) else b_t)
        st[S_FCPL + r] = s
        for a in range(d):
            base[a] += Jh[r, a] * s
    friction = mus > 0.0 or muk > 0.0
    for i in range(m):
        W[i, 0] = 1.0 if C[i, C_FN] > 0.0 else 0.0
        W[i, 1] = -k * C[i, C_S] - b * C[i, C_VN]
        W[i, 2] = 0.0
        for j in range(3, 12):
            W[i, j] = 0.0
        if friction and C[i, C_S] <= TOUCH_TOL_M:
            # the stick force now and its bristle, as the friction pass computes them
            v0, v1, v2 = _tangential(i, d, C, Jpt, qd)
            z0, z1, z2 = _bristle(i, C, v0, v1, v2, dt)
            W[i, 3] = -kt * z0 - bt * v0
            W[i, 4] = -kt * z1 - bt * v1
            W[i, 5] = -kt * z2 - bt * v2
            W[i, 6] = z0
            W[i, 7] = z1
            W[i, 8] = z2
            # its kinetic force if the friction pass found it slipping: the bristle held at
            # mu_k f_0, the friction pass's breakaway
            zn = math.sqrt(z0 * z0 + z1 * z1 + z2 * z2)
            f0 = W[i, 1] if W[i, 1] > 0.0 else 0.0
            sc = -muk * f0 / zn if (zn > 0.0 and kt > 0.0) else 0.0
            W[i, 9] = sc * z0
            W[i, 10] = sc * z1
            W[i, 11] = sc * z2
            W[i, 2] = 2.0 if (C[i, C_FN] > 0.0 and CI[i, CI_SLIP] != 0) else 1.0   # the friction pass's guess
    cn = dt * b + dt * dt * k
    ctan = dt * bt + dt * dt * kt
    for _solve in range(IMPLICIT_MAX_SOLVES):
        _implicit_matrix(d, h, par, Jh, Jpt, Jn, D, A, W, m)
        for a in range(d):
            rhs[a] = base[a]
        for i in range(m):
            if W[i, 0] != 0.0:
                f0 = W[i, 1]
                o = 3 if (W[i, 2] == 1.0 or W[i, 2] == 4.0) else 9  # mode 0: both are zero
                f_0 = f0 * C[i, C_N] + W[i, o]
                f_1 = f0 * C[i, C_N + 1] + W[i, o + 1]
                f_2 = f0 * C[i, C_N + 2] + W[i, o + 2]
                for a in range(d):
                    rhs[a] += Jpt[i, 0, a] * f_0 + Jpt[i, 1, a] * f_1 + Jpt[i, 2, a] * f_2
        if not _chol(A, LA, d):
            return False
        _fwd(LA, rhs, dv, d)
        _bwd(LA, dv, dv, d)
        for a in range(d):
            dv[a] *= dt
        changed = False
        for i in range(m):
            if C[i, C_S] > TOUCH_TOL_M:
                continue
            dn = 0.0
            for a in range(d):
                dn += Jn[i, a] * dv[a]
            fe = W[i, 1] - cn / dt * dn
            pushes = fe > 0.0
            if pushes != (W[i, 0] != 0.0):
                W[i, 0] = 1.0 if pushes else 0.0
                changed = True
            elif pushes and W[i, 2] != 0.0 and W[i, 2] != 3.0:
                # the stick force at the step's end: a sticking bristle whose force leaves the
                # friction cone breaks away (it slips at the kinetic level, for the rest of the
                # step); one the friction pass found slipping whose force would be inside it
                # sticks (once): no contact turns more than twice, the solves end
                u0, u1, u2 = _tangential(i, d, C, Jpt, dv)
                c = ctan / dt
                t0 = W[i, 3] - c * u0
                t1 = W[i, 4] - c * u1
                t2 = W[i, 5] - c * u2
                tn = math.sqrt(t0 * t0 + t1 * t1 + t2 * t2)
                sticking = W[i, 2] == 1.0 or W[i, 2] == 4.0
                if sticking and tn > mus * fe:
                    # against the motion that breaks it away, at mu_k f_0 (the friction pass's
                    # level: the start's normal force, whichever solve decides it)
                    f0 = W[i, 1] if W[i, 1] > 0.0 else 0.0
                    sc = muk * f0 / tn
                    W[i, 9] = sc * t0
                    W[i, 10] = sc * t1
                    W[i, 11] = sc * t2
                    W[i, 2] = 3.0
                    changed = True
                elif W[i, 2] == 2.0 and tn <= mus * fe:
                    W[i, 2] = 4.0
                    changed = True
        if not changed:
            break
    # the coupling's wrench at the step's end differs from the one handed in by -(B + dt K) J_h dv:
    # the controller renders that one to the device (equal and opposite coupling forces)
    bk_t = par[P_CPL_BT] + dt * par[P_CPL_KT]
    bk_r = par[P_CPL_BR] + dt * par[P_CPL_KR]
    for r in range(h):
        s = 0.0
        for a in range(d):
            s += Jh[r, a] * dv[a]
        st[S_FCPL + r] -= (bk_r if ((h == 3 and r == 2) or (h == 6 and r >= 3)) else bk_t) * s
    # what each contact gave over the step: its linearised force at the step's end
    for a in range(d):
        qd[a] += dv[a]
        tau[a] = 0.0
    n_slip = 0
    for i in range(m):
        CI[i, CI_SLIP] = 0
        if W[i, 0] == 0.0:
            C[i, C_FN] = 0.0
            for j in range(3):
                C[i, C_FT + j] = 0.0
                Zn[i, j] = 0.0
            continue
        n0 = C[i, C_N]; n1 = C[i, C_N + 1]; n2 = C[i, C_N + 2]
        dn = 0.0
        for a in range(d):
            dn += Jn[i, a] * dv[a]
        fn = W[i, 1] - cn / dt * dn
        if fn < 0.0:
            fn = 0.0                          # the set did not settle: never pulling
        C[i, C_FN] = fn
        if W[i, 2] == 1.0 or W[i, 2] == 4.0:
            # sticking: the bristle moved with the new tangential velocity (within the cone
            # unless the solves ran out first)
            u0, u1, u2 = _tangential(i, d, C, Jpt, dv)
            c = ctan / dt
            t0 = W[i, 3] - c * u0
            t1 = W[i, 4] - c * u1
            t2 = W[i, 5] - c * u2
            tn = math.sqrt(t0 * t0 + t1 * t1 + t2 * t2)
            sc = mus * fn / tn if tn > mus * fn else 1.0
            C[i, C_FT] = sc * t0
            C[i, C_FT + 1] = sc * t1
            C[i, C_FT + 2] = sc * t2
            Zn[i, 0] = W[i, 6] + dt * u0
            Zn[i, 1] = W[i, 7] + dt * u1
            Zn[i, 2] = W[i, 8] + dt * u2
        elif W[i, 2] != 0.0:
            # slipping: the bristle holds the kinetic force (as the friction pass leaves it), turned
            # by the step's tangential velocity across the slip (mode 2: the matrix has k_s there)
            for j in range(3):
                C[i, C_FT + j] = W[i, 9 + j]
            if W[i, 2] == 2.0:
                ks, s0, s1, s2 = _slip_turn(i, W)
                if ks > 0.0:
                    u0, u1, u2 = _tangential(i, d, C, Jpt, dv)
                    us = u0 * s0 + u1 * s1 + u2 * s2
                    c = ks * dt
                    g0 = W[i, 9] - c * (u0 - us * s0)
                    g1 = W[i, 10] - c * (u1 - us * s1)
                    g2 = W[i, 11] - c * (u2 - us * s2)
                    gn = math.sqrt(g0 * g0 + g1 * g1 + g2 * g2)
                    fk = math.sqrt(W[i, 9] * W[i, 9] + W[i, 10] * W[i, 10] + W[i, 11] * W[i, 11])
                    if gn > 0.0:
                        C[i, C_FT] = g0 * fk / gn
                        C[i, C_FT + 1] = g1 * fk / gn
                        C[i, C_FT + 2] = g2 * fk / gn
            for j in range(3):
                Zn[i, j] = -C[i, C_FT + j] / kt if kt > 0.0 else 0.0
            CI[i, CI_SLIP] = 1
            n_slip += 1
        else:
            for j in range(3):
                C[i, C_FT + j] = 0.0
                Zn[i, j] = 0.0
        f_0 = fn * n0 + C[i, C_FT]
        f_1 = fn * n1 + C[i, C_FT + 1]
        f_2 = fn * n2 + C[i, C_FT + 2]
        for a in range(d):
            tau[a] += Jpt[i, 0, a] * f_0 + Jpt[i, 1, a] * f_1 + Jpt[i, 2, a] * f_2
    cnt[K_SLIPPING] = n_slip
    for a in range(d):
        if not math.isfinite(qd[a]):
            return False
    return True


@njit(inline="always", **_JIT)
def _bristle(i, C, v0, v1, v2, dt):
    """Contact i's friction bristle after a period of tangential sliding (v0, v1, v2), kept in
    the contact's tangent plane (normals may turn at updates)."""
    n0 = C[i, C_N]; n1 = C[i, C_N + 1]; n2 = C[i, C_N + 2]
    z0 = C[i, C_Z]; z1 = C[i, C_Z + 1]; z2 = C[i, C_Z + 2]
    zdn = z0 * n0 + z1 * n1 + z2 * n2
    return z0 + (dt * v0 - zdn * n0), z1 + (dt * v1 - zdn * n1), z2 + (dt * v2 - zdn * n2)


@njit(inline="always", **_JIT)
def _tangential(i, d, C, Jpt, dv):
    """The change dv makes to contact i's tangential velocity, (I - n n^T) J_i dv (world)."""
    n0 = C[i, C_N]; n1 = C[i, C_N + 1]; n2 = C[i, C_N + 2]
    u0 = 0.0; u1 = 0.0; u2 = 0.0
    for a in range(d):
        u0 += Jpt[i, 0, a] * dv[a]
        u1 += Jpt[i, 1, a] * dv[a]
        u2 += Jpt[i, 2, a] * dv[a]
    un = u0 * n0 + u1 * n1 + u2 * n2
    return u0 - un * n0, u1 - un * n1, u2 - un * n2


@njit(**_JIT)
def _implicit_matrix(d, h, par, Jh, Jpt, Jn, D, A, W, m):
    """The lower triangle of A = D + dt B + dt^2 K (d x d) of ``_implicit_step``: the coupling in
    hand space (translational rows, then rotational ones), and each contact in the system
    (``W[:, 0]``): k, b along its normal, plus k_t, b_t in its tangent plane while its bristle
    sticks (``W[:, 2]`` = 1 or 4)."""
    dt = par[P_DT]
    dt2 = dt * dt
    for a in range(d):
        for b2 in range(a + 1):
            A[a, b2] = D[a, b2]
    ct_t = dt * par[P_CPL_BT] + dt2 * par[P_CPL_KT]
    ct_r = dt * par[P_CPL_BR] + dt2 * par[P_CPL_KR]
    for r in range(h):
        # hand space: 1 (the axis), 3 (x, y, about z) or 6 (x, y, z, about x, y, z)
        c = ct_r if ((h == 3 and r == 2) or (h == 6 and r >= 3)) else ct_t
        if c != 0.0:
            for a in range(d):
                ja = c * Jh[r, a]
                for b2 in range(a + 1):
                    A[a, b2] += ja * Jh[r, b2]
    cn = dt * par[P_B] + dt2 * par[P_K]
    ctan = dt * par[P_BT] + dt2 * par[P_KT]
    for i in range(m):
        if W[i, 0] == 0.0:
            continue
        cni = cn
        if (W[i, 2] == 1.0 or W[i, 2] == 4.0) and ctan != 0.0:
            # sticking: k_t, b_t on the tangential velocity (I - n n^T) J_i qd
            cni = cn - ctan
            for a in range(d):
                for b2 in range(a + 1):
                    A[a, b2] += ctan * (Jpt[i, 0, a] * Jpt[i, 0, b2] + Jpt[i, 1, a] * Jpt[i, 1, b2]
                                        + Jpt[i, 2, a] * Jpt[i, 2, b2])
        elif W[i, 2] == 2.0:
            # slipping (the friction pass's): the kinetic force -mu_k f_0 z / |z| turns with the
            # bristle z, which the tangential velocity moves by dt v across the slip: a stiffness
            # k_s = mu_k f_0 / |z| (about k_t: the bristle is held at mu_k f_0 / k_t) in the tangent
            # plane across the slip direction s, implicit like the others (explicit, a light link's
            # roll under a slow slip flipped and grew: k_s dt^2 / m far above 4)
            ks, s0, s1, s2 = _slip_turn(i, W)
            if ks > 0.0:
                c = dt2 * ks
                for a in range(d):
                    sa = s0 * Jpt[i, 0, a] + s1 * Jpt[i, 1, a] + s2 * Jpt[i, 2, a]
                    for b2 in range(a + 1):
                        sb = s0 * Jpt[i, 0, b2] + s1 * Jpt[i, 1, b2] + s2 * Jpt[i, 2, b2]
                        A[a, b2] += c * (Jpt[i, 0, a] * Jpt[i, 0, b2] + Jpt[i, 1, a] * Jpt[i, 1, b2]
                                         + Jpt[i, 2, a] * Jpt[i, 2, b2] - Jn[i, a] * Jn[i, b2] - sa * sb)
        for a in range(d):
            ja = cni * Jn[i, a]
            for b2 in range(a + 1):
                A[a, b2] += ja * Jn[i, b2]


@njit(inline="always", **_JIT)
def _slip_turn(i, W):
    """A slipping contact's (friction mode 2) turning stiffness k_s = |kinetic force| / |bristle|
    and its slip direction s (unit, along the kinetic force), from ``_implicit_step``'s scratch
    ``W``; (0, 0, 0, 0) if either is zero."""
    f0 = W[i, 9]; f1 = W[i, 10]; f2 = W[i, 11]
    fn = math.sqrt(f0 * f0 + f1 * f1 + f2 * f2)
    zn = math.sqrt(W[i, 6] * W[i, 6] + W[i, 7] * W[i, 7] + W[i, 8] * W[i, 8])
    if fn <= 0.0 or zn <= 0.0:
        return 0.0, 0.0, 0.0, 0.0
    return fn / zn, f0 / fn, f1 / fn, f2 / fn


@njit(inline="always", **_JIT)
def _watch_divergence(d, st, cnt, V):
    """K_OSC_RUN: steps in a row at whose start some coordinate of the proxy's velocity had
    reversed since the previous step's start without decaying (by DIVERGE_DECAY at most),
    faster than DIVERGE_SPEED;
    K_DIVERGED counts each time the run reaches DIVERGE_STEPS (``layout``: a numerical
    instability's signature, never a tool's motion). Starts, not ends: with direct coupling the
    device sets the velocity a step starts from."""
    qd0 = V[_V_QD0]
    osc = False
    for a in range(d):
        p = st[S_QDP + a]
        if qd0[a] * p < 0.0 and abs(qd0[a]) >= (1.0 - DIVERGE_DECAY) * abs(p) and abs(qd0[a]) > DIVERGE_SPEED:
            osc = True
        st[S_QDP + a] = qd0[a]
    if osc:
        cnt[K_OSC_RUN] += 1
        if cnt[K_OSC_RUN] == DIVERGE_STEPS:
            cnt[K_DIVERGED] += 1
    else:
        cnt[K_OSC_RUN] = 0


@njit(**_JIT)
def _zero_outputs(st):
    for r in range(6):
        st[S_FENV + r] = 0.0
        st[S_FIMP + r] = 0.0
        st[S_FPEN + r] = 0.0


@njit(**_JIT)
def commit_velocity(d, st, C, D, Zn, V, m):
    """After a finite ``_core``: store the new velocity, the friction stick points and the
    kinetic energy qd^T D qd / 2 (qd stays in ``V[_V_QD]`` for the tool's own integrator)."""
    qd = V[_V_QD]
    for a in range(d):
        st[S_QD + a] = qd[a]
    for i in range(m):
        for j in range(3):
            C[i, C_Z + j] = Zn[i, j]
    ke = 0.0
    for a in range(d):
        s = 0.0
        for b in range(d):
            s += D[a, b] * qd[b]
        ke += qd[a] * s
    st[S_KE] = 0.5 * ke


@njit(inline="always", **_JIT)
def hand_to_world(planar, src, so, dst, do):
    """The hand-space vector at ``src[so:]`` (planar: x, y and about z; spatial: all 6 of a twist
    or wrench) as the world 6-vector ``dst[do:do + 6]``; planar leaves z, about x and about y of
    ``dst`` as they are."""
    if planar:
        dst[do] = src[so]
        dst[do + 1] = src[so + 1]
        dst[do + 5] = src[so + 2]
    else:
        for j in range(6):
            dst[do + j] = src[so + j]


@njit(inline="always", **_JIT)
def take_hand(h, st, hand):
    """Store the ``h`` hand-wrench components of a step at S_FH; False (nothing stored) when
    one is not finite."""
    for r in range(h):
        if not math.isfinite(hand[r]):
            return False
    for r in range(h):
        st[S_FH + r] = hand[r]
    return True


@njit(inline="always", **_JIT)
def end_step(ok, d, par, st, C, cnt, D, Zn, V, m):
    """Close a step after ``_core``: a finite result is committed (``commit_velocity``), a
    non-finite one zeroes the rendered wrench and counts K_NONFINITE; time and K_STEPS advance
    either way. Returns ``ok``: the caller's integrator then moves q by qd = ``V[_V_QD]``."""
    if ok:
        commit_velocity(d, st, C, D, Zn, V, m)
        _watch_divergence(d, st, cnt, V)
    else:
        _zero_outputs(st)
        cnt[K_NONFINITE] += 1
    st[S_T] += par[P_DT]
    cnt[K_STEPS] += 1
    return ok


@njit(**_JIT)
def step_rigid(kind, par, st, C, CI, cnt, wk, hand):
    """One haptic step of a rigid tool. ``hand``: wrench on the proxy at the hand point, world
    frame (1dof: force along the axis; planar: fx, fy, tau_z; spatial: f (3), tau (3)).
    Returns an E_* code; on a non-finite result the state is kept, the rendered wrench is zero
    and K_NONFINITE counts it."""
    if kind == TOOL_1DOF:
        d = 1; h = 1
    elif kind == TOOL_PLANAR:
        d = 3; h = 3
    else:
        d = 6; h = 6
    if not take_hand(h, st, hand):
        return E_HAND_NONFINITE
    cap = C.shape[0]
    m = cnt[K_M]
    D, L, U, G, Y, Jh, Jpt, Jn, Bm, Cm, X, Zn, V = _views(wk, cap)
    R = Y  # 3x3 rotation in the corner of a scratch matrix not yet in use
    c = V[_V_T1]
    _kin_rigid(kind, par, st, C, m, R, c, D, V[_V_TAUG], Jpt, X, Jh)
    ok = _core(d, h, par, st, C, CI, cnt, D, L, U, G, Y, Jh, Jpt, Jn, Bm, Cm, X, Zn, V, m)
    if end_step(ok, d, par, st, C, cnt, D, Zn, V, m):
        _integrate_rigid(kind, st, V[_V_QD], par[P_DT])
    return E_OK


# --------------------------------------------------------------------------------------------
# model update (the notes' rule table)
# --------------------------------------------------------------------------------------------
@njit(**_JIT)
def _select_smallest(dsep, n_in, cap, sel):
    """Indices of the ``cap`` contacts with the smallest separation, in incoming order."""
    if n_in <= cap:
        for j in range(n_in):
            sel[j] = j
        return n_in
    # threshold by repeated selection: O(n_in * cap) worst case, no allocation
    for j in range(n_in):
        sel[j] = j
    # partial selection sort on the first cap slots of sel (cap is small: default 64)
    for a in range(cap):
        best = a
        for j in range(a + 1, n_in):
            ij = sel[j]
            ib = sel[best]
            if dsep[ij] < dsep[ib] or (dsep[ij] == dsep[ib] and ij < ib):
                best = j
        tmp = sel[a]
        sel[a] = sel[best]
        sel[best] = tmp
    # back to incoming order so the store is deterministic and order-stable
    for a in range(1, cap):
        v = sel[a]
        j = a - 1
        while j >= 0 and sel[j] > v:
            sel[j + 1] = sel[j]
            j -= 1
        sel[j + 1] = v
    return cap


@njit(**_JIT)
def validate_contacts(kind, n_links, keys, cp, nrm, dsep, vc, n_in):
    """E_* code for a contact set; touches nothing."""
    if n_in > keys.shape[0] or n_in > cp.shape[0] or n_in > nrm.shape[0] or n_in > dsep.shape[0] \
            or n_in > vc.shape[0]:
        return E_TOO_MANY
    for j in range(n_in):
        for a in range(3):
            if not (math.isfinite(cp[j, a]) and math.isfinite(nrm[j, a])):
                return E_CONTACT_NONFINITE
        if not (math.isfinite(dsep[j]) and math.isfinite(vc[j])):
            return E_CONTACT_NONFINITE
        nn = math.sqrt(nrm[j, 0] ** 2 + nrm[j, 1] ** 2 + nrm[j, 2] ** 2)
        if abs(nn - 1.0) > UNIT_TOL:
            return E_NORMAL_NOT_UNIT
        if kind == TOOL_PLANAR and abs(nrm[j, 2]) > UNIT_TOL:
            return E_NORMAL_OUT_OF_PLANE
        if keys[j, 0] < 0 or keys[j, 0] >= n_links:
            return E_LINK_OUT_OF_RANGE
    return E_OK


@njit(**_JIT)
def check_update(kind, n_links, keys, cp, nrm, dsep, vc, n_in, cap, sel):
    """Everything an update is checked for before anything changes: ``validate_contacts``, then
    the capacity rule and the duplicate-key check. Returns (E_* code, number kept); ``sel[:nk]``
    are the rows kept, in incoming order."""
    code = validate_contacts(kind, n_links, keys, cp, nrm, dsep, vc, n_in)
    if code != E_OK:
        return code, 0
    if n_in > sel.shape[0]:
        return E_TOO_MANY, 0
    nk = _select_smallest(dsep, n_in, cap, sel)
    for a in range(nk):
        ja = sel[a]
        for b2 in range(a):
            jb = sel[b2]
            if keys[ja, 0] == keys[jb, 0] and keys[ja, 1] == keys[jb, 1] and keys[ja, 2] == keys[jb, 2]:
                return E_DUPLICATE_KEY, 0
    return E_OK, nk


@njit(**_JIT)
def _pose_row(R, c, P, k):
    """Pack a link pose (R link->world, origin c, world) into row k of a pose-row array."""
    for a in range(3):
        for b2 in range(3):
            P[k, 3 * a + b2] = R[a, b2]
        P[k, 9 + a] = c[a]


# columns of the update's per-contact scratch W (cap x MAX_DOF; the step's impulse scratch Cm)
_W_SP = 0        # existing contact i: the proxy's separation s_p at the update
_W_TAKEN = 1     # existing contact i: 1 once an incoming contact continues it (same key, or re-keyed)
_W_FOUND = 2     # incoming contact a: the existing contact it continues (-1: none)
_W_FLIP = 3      # incoming contact a: 1 when its normal reversed the existing one's (kept as it was)
_W_XP = 4        # incoming contact a: 4..6 its tool feature as the proxy carries it, world
_W_DS = 7        # existing contact i: how far its constraint plane moved along n since its update
_W_TABLE = 8     # 8..11: pass 1's open-addressing key table, slot s at row s >> 2, column 8 + (s & 3);
                 # holds i + 1 for existing contact i, 0 when empty
_W_LEFT = 8      # 8..11, then pass 2's: row r holds a contact i not continued by its key, and n_i
#: Up to this many existing contacts, pass 1 scans them for each key: cheaper than filling the
#: key table (both find the same contact: the first with that key).
_SCAN_MAX_M = 8


#: Pass 2 sorts the contacts left into _NB x _NB buckets by (|n_x|, |n_y|), each 1 / _NB wide: two
#: normals whose |cos| reaches REKEY_COS differ by at most _NB_REACH in |n_x| and in |n_y|
#: (|a - b|^2 = |a|^2 + |b|^2 - 2 |a . b| for b turned the right way round, with the squared
#: lengths within _NB_NORM2_TOL of 1, which the kernel checks: a normal that is not is matched
#: against every bucket), so a new key looks only into the <= 2 x 2 buckets around its own.
#: Below _NB_MIN_PAIRS (contacts left x new keys) one bucket is cheaper.
_NB = 5
_NB_NORM2_TOL = 1e-5
_NB_REACH = math.sqrt(2.0 + 2.0 * _NB_NORM2_TOL - 2.0 * (REKEY_COS - 1e-12)) + 1e-9
_NB_MIN_PAIRS = 64
assert 2.0 * _NB_REACH <= 1.0 / _NB and _NB * _NB <= NCOLS_F


@njit(inline="always", **_JIT)
def _nb_coord(v, nb):
    """Bucket coordinate of a normal's |component| v >= 0 (the last one takes v >= 1 too)."""
    c = int(v * nb)
    return c if c < nb else nb - 1


@njit(inline="always", **_JIT)
def _key_slot(k0, k1, k2, mask):
    """Home slot of a contact key in a key table of mask + 1 (a power of two) slots. int64
    multiplications wrap, which is all a hash needs."""
    h = k0 * 0x5851F42D4C957F2D + k1 * 0x27D4EB2F165667C5 + k2 * 0x165667B19E3779F9
    h ^= h >> 29
    return h & mask


@njit(inline="always", **_JIT)
def _feature_point(j, k, cp, nrm, dsep, P, Pe, use_qe, W, a):
    """The reported tool feature as the proxy carries it (world, into ``W[a, _W_XP:_W_XP + 3]``);
    returns its separation s_w from the reported constraint along n (the engine frame: the
    feature taken in the engine tool's frame and put on the proxy; the paper's eq. 1: c_p + d n,
    s_w = d)."""
    if use_qe:
        fx = cp[j, 0] + dsep[j] * nrm[j, 0] - Pe[k, 9]
        fy = cp[j, 1] + dsep[j] * nrm[j, 1] - Pe[k, 10]
        fz = cp[j, 2] + dsep[j] * nrm[j, 2] - Pe[k, 11]
        bx = Pe[k, 0] * fx + Pe[k, 3] * fy + Pe[k, 6] * fz
        by = Pe[k, 1] * fx + Pe[k, 4] * fy + Pe[k, 7] * fz
        bz = Pe[k, 2] * fx + Pe[k, 5] * fy + Pe[k, 8] * fz
        x0 = P[k, 9] + P[k, 0] * bx + P[k, 1] * by + P[k, 2] * bz
        x1 = P[k, 10] + P[k, 3] * bx + P[k, 4] * by + P[k, 5] * bz
        x2 = P[k, 11] + P[k, 6] * bx + P[k, 7] * by + P[k, 8] * bz
        W[a, _W_XP] = x0
        W[a, _W_XP + 1] = x1
        W[a, _W_XP + 2] = x2
        return nrm[j, 0] * (x0 - cp[j, 0]) + nrm[j, 1] * (x1 - cp[j, 1]) + nrm[j, 2] * (x2 - cp[j, 2])
    for q_ in range(3):
        W[a, _W_XP + q_] = cp[j, q_] + dsep[j] * nrm[j, q_]
    return dsep[j]


@njit(inline="always", **_JIT)
def _same_contact(C, i, W, X, j, k, cp, nrm, dsep, P, Pe, use_qe, a):
    """A kept key names existing contact ``i`` only where ``i`` is (``layout.KEY_SLIDE_FACTOR``):
    the reported constraint plane within REKEY_DISTANCE_M of the old one (moved on along its
    normal since), and along the surface the reported constraint point (the environment's side)
    or feature (the tool's side, as the proxy carries it: written to ``W[a, _W_XP:]``) within
    REKEY_DISTANCE_M + KEY_SLIDE_FACTOR x how far the proxy's point of ``i`` now lies from the old
    constraint point along the surface."""
    ds = W[i, _W_DS]
    n0 = nrm[j, 0]
    n1 = nrm[j, 1]
    n2 = nrm[j, 2]
    e0 = cp[j, 0] - C[i, C_CP] - ds * C[i, C_N]
    e1 = cp[j, 1] - C[i, C_CP + 1] - ds * C[i, C_N + 1]
    e2 = cp[j, 2] - C[i, C_CP + 2] - ds * C[i, C_N + 2]
    en = e0 * n0 + e1 * n1 + e2 * n2
    if abs(en) > REKEY_DISTANCE_M:
        return False
    e0 -= en * n0
    e1 -= en * n1
    e2 -= en * n2
    m0 = X[i, 0] - C[i, C_CP] - ds * C[i, C_N]
    m1 = X[i, 1] - C[i, C_CP + 1] - ds * C[i, C_N + 1]
    m2 = X[i, 2] - C[i, C_CP + 2] - ds * C[i, C_N + 2]
    mn = m0 * n0 + m1 * n1 + m2 * n2
    m0 -= mn * n0
    m1 -= mn * n1
    m2 -= mn * n2
    tol = REKEY_DISTANCE_M + KEY_SLIDE_FACTOR * math.sqrt(m0 * m0 + m1 * m1 + m2 * m2)
    tol2 = tol * tol
    if e0 * e0 + e1 * e1 + e2 * e2 <= tol2:
        return True
    _feature_point(j, k, cp, nrm, dsep, P, Pe, use_qe, W, a)
    f0 = X[i, 0] - W[a, _W_XP]
    f1 = X[i, 1] - W[a, _W_XP + 1]
    f2 = X[i, 2] - W[a, _W_XP + 2]
    fn = f0 * n0 + f1 * n1 + f2 * n2
    f0 -= fn * n0
    f1 -= fn * n1
    f2 -= fn * n2
    return f0 * f0 + f1 * f1 + f2 * f2 <= tol2


@njit(inline="always", **_JIT)
def _refuse_reversal(C, CI, i, W, j, k, cp, nrm, P):
    """Existing contact ``i`` reported with a reversed normal (contact ``j``, tool link ``k``):
    refuse the report (``i`` kept as it was) or take it (``i`` leaves, ``j`` is new)? The link's
    frame origin lies in front of the true plane (``layout.FLIP_DOT``): a report that puts it in
    front where the held normal puts it behind is taken; one that puts it behind is refused up to
    FLIP_REFUSE_MAX updates in a row (``CI_FLIPS``), one that cannot be told once."""
    ph = -W[i, _W_DS]
    pr = 0.0
    for q_ in range(3):
        ph += C[i, C_N + q_] * (P[k, 9 + q_] - C[i, C_CP + q_])
        pr += nrm[j, q_] * (P[k, 9 + q_] - cp[j, q_])
    if pr > ph + 2.0 * REKEY_DISTANCE_M:
        return False
    limit = FLIP_REFUSE_MAX if ph > pr + 2.0 * REKEY_DISTANCE_M else 1
    return CI[i, CI_FLIPS] < limit


@njit(**_JIT)
def _held_depth(dr_m, now_m, cut):
    """Set-position modulation of a depth an update takes at once (the rigid policy; a new
    contact under the paper-literal one): of the deepening from ``now`` (the proxy's separation
    at the contact, 0 for a new one) to the reported ``dr``, only the share ``1 - cut`` is taken;
    the rest is deformation the recovery (or the next update) completes.

    Contract: ``dr`` itself when ``cut <= 0``, non-finite, or nothing deepens (``dr >= now``);
    otherwise ``dr + min(cut, 1) (now - dr)``: between ``dr`` and ``now``, ``now`` from
    ``cut >= 1``, monotone in ``cut``: never deeper than reported, never shallower than now."""
    if not cut > 0.0 or not dr_m < now_m:
        return dr_m
    if cut >= 1.0:
        return now_m
    return dr_m + cut * (now_m - dr_m)


@njit(**_JIT)
def apply_update(planar, par, st, C, CI, cnt, X, W, keys, cp, nrm, dsep, vc, n_in, nk, sel,
                 newF, newI, P, Pe, use_qe, Vk):
    """The rule table of the notes on a validated update (``sel[:nk]`` kept). ``P[k]``: pose row
    of tool link k (rotation link -> world row-major, then the link frame's origin, world) at the
    proxy's configuration, ``Pe[k]`` the same at the engine's (read only when ``use_qe``), ``Vk[k]``
    the link's angular velocity and its frame origin's velocity (world, 3 + 3). A contact's local
    point is stored in the frame of its link (key column 0). ``X`` (m x 3) and ``W`` (cap x 12):
    scratch.

    A contact the rules put touching (eq. 4) starts resting on the proxy, not as a collision: its
    first step applies no impulse unless the proxy moves into it faster than the resting speed
    ``P_REC_VN`` (the recovery's: 0 with the recovery off, the paper's model, where every
    approach is a collision). The impulse at a slow approach stopped whatever the proxy was doing
    in one step (m v / dt: 0.42 -> 4.07 -> 0.07 N for a 0.25 kg tool a recovery moved into the
    contact at 19 mm/s, ``tests/model/test_update_instant.py``): the force step proxy deformation
    exists to avoid. Every contact placed carries the proxy's normal speed there (``C_VN``), which
    the recovery's resting test reads at the next step.

    Events real engines produce are caught before the rules (``layout.FLIP_DOT``,
    ``FLIP_REFUSE_MAX``, ``KEY_SLIDE_FACTOR``, ``REKEY_COS``, ``REKEY_DISTANCE_M``): a kept key
    reported elsewhere is another contact (the old one leaves, or continues under its own new
    key); a reported normal that reverses an existing contact's is refused for this update (the
    contact keeps its previous geometry and state, so the force is not turned round into a pull
    towards the surface) when the tool lies in front of the held plane and behind the reported
    one, and taken when the tool says the held one was the reversed one; a new key at the feature
    of a contact that left in the same update continues that contact (its penetration is kept, as
    eq. 5 keeps any existing contact's, instead of restarting at zero through eq. 4).

    Cost: O(n + m) for the keys (a key table in W once m > _SCAN_MAX_M); then, for each new key
    only, the contacts left in the <= 2 x 2 buckets of normals near its own (``_NB``), the
    cheapest test (the normals' cosine) first, the feature point computed only for a candidate
    that passes the planes' test; nothing when every key was kept or every contact continued.
    The result is the plain rule's, bit for bit (each key against every contact in order, the
    first with that key; each new key, in order, against every contact not yet continued, the
    largest |cos| winning, the lowest index on a tie): ``tests/model/test_update_matching.py``
    runs that rule as first written on copies and compares."""
    m = cnt[K_M]
    t = st[S_T]
    policy = int(par[P_POLICY])
    cut = par[P_REC_CUT]
    # current world points and proxy separations s_p of the existing contacts
    for i in range(m):
        k = CI[i, CI_KEY]
        for a in range(3):
            s = P[k, 9 + a]
            for b2 in range(3):
                s += P[k, 3 * a + b2] * C[i, C_P + b2]
            X[i, a] = s
        s = -C[i, C_VC] * (t - C[i, C_TU]) - C[i, C_REC]
        for a in range(3):
            s += C[i, C_N + a] * (X[i, a] - C[i, C_CP + a])
        W[i, _W_SP] = s
        W[i, _W_TAKEN] = 0.0
        # the old constraint plane moved on with v_constr since its update (and by the recovery)
        W[i, _W_DS] = C[i, C_VC] * (t - C[i, C_TU]) + C[i, C_REC]
    # pass 1: the same keys (the first existing contact with the key, as a scan finds it)
    size = 4
    while size < 2 * m:                       # load factor <= 1/2
        size *= 2
    table = m > _SCAN_MAX_M and size <= 4 * W.shape[0]
    mask = size - 1
    if table:
        for s_ in range(size):
            W[s_ >> 2, _W_TABLE + (s_ & 3)] = 0.0
        for i in range(m):
            s_ = _key_slot(CI[i, CI_KEY], CI[i, CI_KEY + 1], CI[i, CI_KEY + 2], mask)
            while True:
                e = int(W[s_ >> 2, _W_TABLE + (s_ & 3)])
                if e == 0:
                    W[s_ >> 2, _W_TABLE + (s_ & 3)] = i + 1
                    break
                e -= 1
                if CI[e, CI_KEY] == CI[i, CI_KEY] and CI[e, CI_KEY + 1] == CI[i, CI_KEY + 1] \
                        and CI[e, CI_KEY + 2] == CI[i, CI_KEY + 2]:
                    break                     # a repeated key: the first one answers
                s_ = (s_ + 1) & mask
    n_found = 0
    for a in range(nk):
        j = sel[a]
        k0 = keys[j, 0]
        k1 = keys[j, 1]
        k2 = keys[j, 2]
        found = -1
        if table:
            s_ = _key_slot(k0, k1, k2, mask)
            while True:
                e = int(W[s_ >> 2, _W_TABLE + (s_ & 3)])
                if e == 0:
                    break
                e -= 1
                if CI[e, CI_KEY] == k0 and CI[e, CI_KEY + 1] == k1 and CI[e, CI_KEY + 2] == k2:
                    found = e
                    break
                s_ = (s_ + 1) & mask
        else:
            for i in range(m):
                if CI[i, CI_KEY] == k0 and CI[i, CI_KEY + 1] == k1 and CI[i, CI_KEY + 2] == k2:
                    found = i
                    break
        W[a, _W_FOUND] = found
        W[a, _W_FLIP] = 0.0
        if found >= 0:
            if not _same_contact(C, found, W, X, j, k0, cp, nrm, dsep, P, Pe, use_qe, a):
                W[a, _W_FOUND] = -1.0         # another contact under a kept key: a new one here
                continue
            n_found += 1
            W[found, _W_TAKEN] = 1.0
            dot = C[found, C_N] * nrm[j, 0] + C[found, C_N + 1] * nrm[j, 1] + C[found, C_N + 2] * nrm[j, 2]
            if dot < FLIP_DOT:
                if _refuse_reversal(C, CI, found, W, j, k0, cp, nrm, P):
                    W[a, _W_FLIP] = 1.0
                else:
                    W[a, _W_FOUND] = -2.0     # taken: ``found`` leaves, this one is new (not re-keyed)
    # pass 2: new keys at the feature of a contact that left (re-numbered, or reversed): the
    # existing contact i on the same link whose normal is within REKEY_COS of the new one (either
    # way round) and whose constraint plane and proxy point are within REKEY_DISTANCE_M of the
    # new feature (across the surface, and along it: the deformation only moved it along n);
    # the largest |n_old . n_new| wins, the lowest i of those on a tie
    n_rekey = 0
    n_left = m - n_found                      # distinct keys found distinct contacts
    if n_left > 0 and n_found < nk:
        # the contacts left, packed by bucket (pass 1's key table is done with): row r of
        # W[:, _W_LEFT:] holds i and n_i; bucket b's rows start at newF[0, b], newF[1, b] of them
        # (newF is written only by pass 3)
        nb = _NB if (newF.shape[0] >= 2 and n_left * (nk - n_found) >= _NB_MIN_PAIRS) else 1
        if nb > 1:
            for b in range(nb * nb):
                newF[1, b] = 0.0
            for i in range(m):
                if W[i, _W_TAKEN] == 0.0:
                    nn = C[i, C_N] * C[i, C_N] + C[i, C_N + 1] * C[i, C_N + 1] + C[i, C_N + 2] * C[i, C_N + 2]
                    if abs(nn - 1.0) > _NB_NORM2_TOL:
                        nb = 1                # the buckets' bound needs unit normals
                        break
                    newF[1, _nb_coord(abs(C[i, C_N]), nb) * nb + _nb_coord(abs(C[i, C_N + 1]), nb)] += 1.0
        if nb > 1:
            s = 0.0
            for b in range(nb * nb):
                newF[0, b] = s
                s += newF[1, b]
                newF[1, b] = 0.0
        nc = 0
        for i in range(m):
            if W[i, _W_TAKEN] == 0.0:
                r = nc
                if nb > 1:
                    b = _nb_coord(abs(C[i, C_N]), nb) * nb + _nb_coord(abs(C[i, C_N + 1]), nb)
                    r = int(newF[0, b] + newF[1, b])
                    newF[1, b] += 1.0
                W[r, _W_LEFT] = i
                W[r, _W_LEFT + 1] = C[i, C_N]
                W[r, _W_LEFT + 2] = C[i, C_N + 1]
                W[r, _W_LEFT + 3] = C[i, C_N + 2]
                nc += 1
        for a in range(nk):
            if W[a, _W_FOUND] != -1.0:       # continues a contact, or took a reversal: not re-keyed
                continue
            j = sel[a]
            k = keys[j, 0]
            xp0 = 0.0                         # the new feature, once a candidate needs it
            xp1 = 0.0
            xp2 = 0.0
            have_xp = False
            n0 = nrm[j, 0]
            n1 = nrm[j, 1]
            n2 = nrm[j, 2]
            # the buckets a normal within arccos(REKEY_COS) of n (either way round) can be in
            bx0 = 0
            bx1 = nb - 1
            by0 = 0
            by1 = nb - 1
            if nb > 1 and abs(n0 * n0 + n1 * n1 + n2 * n2 - 1.0) <= _NB_NORM2_TOL:
                bx0 = _nb_coord(max(abs(n0) - _NB_REACH, 0.0), nb)
                bx1 = _nb_coord(abs(n0) + _NB_REACH, nb)
                by0 = _nb_coord(max(abs(n1) - _NB_REACH, 0.0), nb)
                by1 = _nb_coord(abs(n1) + _NB_REACH, nb)
            best = -1
            best_r = -1
            best_b = 0
            best_dot = 0.0
            for bx in range(bx0, bx1 + 1):
                for by in range(by0, by1 + 1):
                    b = bx * nb + by
                    r0 = 0
                    r1 = nc
                    if nb > 1:
                        r0 = int(newF[0, b])
                        r1 = r0 + int(newF[1, b])
                    for r in range(r0, r1):
                        # the cheapest test first: the normals' cosine (the same products, in
                        # the same order, as C[i, C_N:C_N + 3] . n would give)
                        dot = W[r, _W_LEFT + 1] * n0 + W[r, _W_LEFT + 2] * n1 + W[r, _W_LEFT + 3] * n2
                        if abs(dot) < REKEY_COS:
                            continue
                        i = int(W[r, _W_LEFT])
                        # one that cannot beat the best so far needs no more tests (the result
                        # is the same; with many parallel normals, as a 1-DOF tool's, most stop here)
                        if best >= 0 and (abs(dot) < abs(best_dot) or (abs(dot) == abs(best_dot) and i > best)):
                            continue
                        if CI[i, CI_KEY] != k:
                            continue
                        ds = W[i, _W_DS]
                        across = 0.0
                        for q_ in range(3):
                            across += nrm[j, q_] * (cp[j, q_] - C[i, C_CP + q_] - ds * C[i, C_N + q_])
                        if abs(across) > REKEY_DISTANCE_M:
                            continue
                        if not have_xp:
                            _feature_point(j, k, cp, nrm, dsep, P, Pe, use_qe, W, a)
                            xp0 = W[a, _W_XP]
                            xp1 = W[a, _W_XP + 1]
                            xp2 = W[a, _W_XP + 2]
                            have_xp = True
                        e0 = X[i, 0] - xp0
                        e1 = X[i, 1] - xp1
                        e2 = X[i, 2] - xp2
                        en = e0 * n0 + e1 * n1 + e2 * n2
                        e0 -= en * n0
                        e1 -= en * n1
                        e2 -= en * n2
                        if e0 * e0 + e1 * e1 + e2 * e2 > REKEY_DISTANCE_M * REKEY_DISTANCE_M:
                            continue
                        # it beats the best so far (tested first; the scan's order is the
                        # buckets', not i's: the lowest i wins a tie)
                        best = i
                        best_r = r
                        best_b = b
                        best_dot = dot
            if best >= 0:
                W[a, _W_FOUND] = best
                W[best, _W_TAKEN] = 1.0
                if best_dot < 0.0:
                    if _refuse_reversal(C, CI, best, W, j, k, cp, nrm, P):
                        W[a, _W_FLIP] = 1.0
                    else:
                        W[a, _W_FOUND] = -2.0
                else:
                    n_rekey += 1
                # out of the candidates: the last row of its bucket takes its place
                last = nc - 1
                if nb > 1:
                    last = int(newF[0, best_b] + newF[1, best_b]) - 1
                    newF[1, best_b] -= 1.0
                for q_ in range(4):
                    W[best_r, _W_LEFT + q_] = W[last, _W_LEFT + q_]
                nc -= 1
                if nc == 0:                   # the later new keys can only be new contacts
                    break
    # pass 3: the rule table
    matched = 0
    n_new = 0
    n_def = 0
    n_flip = 0
    n_flip_taken = 0
    for a in range(nk):
        j = sel[a]
        k = keys[j, 0]
        found = int(W[a, _W_FOUND])
        if found >= 0:
            matched += 1
        elif found == -2:
            n_flip_taken += 1
        if found >= 0 and W[a, _W_FLIP] != 0.0:
            # refused for this update: the contact stays exactly as it was (key included)
            for q_ in range(NCOLS_F):
                newF[a, q_] = C[found, q_]
            for q_ in range(NCOLS_I):
                newI[a, q_] = CI[found, q_]
            newI[a, CI_AGE] = CI[found, CI_AGE] + 1
            newI[a, CI_FLIPS] = CI[found, CI_FLIPS] + 1
            n_flip += 1
            continue
        # the tool feature as the proxy carries it (xp) and its separation dj along n
        dj = _feature_point(j, k, cp, nrm, dsep, P, Pe, use_qe, W, a)
        xp0 = W[a, _W_XP]
        xp1 = W[a, _W_XP + 1]
        xp2 = W[a, _W_XP + 2]
        # the separation the rules render: the real tool's, or (the paper read literally, for the
        # reproductions only) the epsilon-inflated tool's, new contacts included (eq. 6, no eq. 4)
        literal = policy == POLICY_PAPER_LITERAL
        dr = dj - par[P_EPS] if literal else dj
        # offset along n of the target world point from c_p (eq. 1/6: d, eq. 5: s_p, eq. 4: 0)
        touch = False                         # put touching by eq. 4
        if found >= 0:
            s_p = W[found, _W_SP]
            if policy == POLICY_RIGID or dr > 0.0 or s_p < dr:
                # only the rigid policy deepens a contact here: by the share the layer allows
                off = _held_depth(dr, s_p if s_p < 0.0 else 0.0, cut)
                if off > dr:
                    n_def += 1
            elif s_p <= 0.0:
                off = s_p
                n_def += 1
            else:
                off = 0.0
                touch = True
                n_def += 1
            newF[a, C_S] = C[found, C_S]
            newF[a, C_SPREV] = C[found, C_SPREV]
            for q_ in range(3):
                newF[a, C_Z + q_] = C[found, C_Z + q_]
            newI[a, CI_SLIP] = CI[found, CI_SLIP]
            newI[a, CI_STATE] = CI[found, CI_STATE]
            newI[a, CI_AGE] = CI[found, CI_AGE] + 1
        else:
            n_new += 1
            if policy == POLICY_RIGID or literal or dr > 0.0:
                off = _held_depth(dr, 0.0, cut)
                if off > dr:
                    n_def += 1
            else:
                off = 0.0
                touch = True
                n_def += 1
            newF[a, C_S] = np.inf             # has just arisen: next step may be a collision
            newF[a, C_SPREV] = np.inf
            for q_ in range(3):
                newF[a, C_Z + q_] = 0.0
            newI[a, CI_SLIP] = 0
            newI[a, CI_STATE] = CST_IMPENDING
            newI[a, CI_AGE] = 0
        newI[a, CI_FLIPS] = 0
        for q_ in range(3):
            newI[a, CI_KEY + q_] = keys[j, q_]
            newF[a, C_CP + q_] = cp[j, q_]
            newF[a, C_N + q_] = nrm[j, q_]
        if planar:
            newF[a, C_CP + 2] = 0.0
            newF[a, C_N + 2] = 0.0
        newF[a, C_D] = dsep[j]
        newF[a, C_VC] = vc[j]
        newF[a, C_TU] = t
        newF[a, C_FN] = 0.0
        newF[a, C_IMP] = 0.0
        for q_ in range(3):
            newF[a, C_FT + q_] = 0.0
        # what the rules put the proxy off the true geometry by (eqs. 4/5): to be recovered. Only
        # known in the engine frame: with the paper's eq. 1 the reported separation is the engine
        # tool's, not the proxy's, and "recovering" towards it only creeps after the engine's tool
        newF[a, C_DEF] = off - dr if (off > dr and use_qe) else 0.0
        newF[a, C_REC] = 0.0
        # local contact point in the link frame: p = R^T (Xp + (off - s_w) n - c); with the
        # engine at the proxy's pose Xp = c_p + d n, s_w = d: p = R^T (c_p + off n - c)  (eqs. 1, 4, 5, 6)
        w0 = xp0 + (off - dj) * newF[a, C_N] - P[k, 9]
        w1 = xp1 + (off - dj) * newF[a, C_N + 1] - P[k, 10]
        w2 = xp2 + (off - dj) * newF[a, C_N + 2] - P[k, 11]
        for q_ in range(3):
            newF[a, C_P + q_] = P[k, q_] * w0 + P[k, 3 + q_] * w1 + P[k, 6 + q_] * w2
        if planar:
            newF[a, C_P + 2] = 0.0
        # the proxy's normal speed at the point, against the constraint's: v_o + w x r - v_constr
        vn = (newF[a, C_N] * (Vk[k, 3] + Vk[k, 1] * w2 - Vk[k, 2] * w1)
              + newF[a, C_N + 1] * (Vk[k, 4] + Vk[k, 2] * w0 - Vk[k, 0] * w2)
              + newF[a, C_N + 2] * (Vk[k, 5] + Vk[k, 0] * w1 - Vk[k, 1] * w0) - vc[j])
        newF[a, C_VN] = vn
        if touch:
            # eq. 4 put the proxy touching: it rests there unless it moves into the contact faster
            # than the resting speed (then the collision the paper's new contact is)
            newF[a, C_S] = np.inf if vn <= -par[P_REC_VN] else 0.0
    for a in range(nk):
        for q_ in range(NCOLS_F):
            C[a, q_] = newF[a, q_]
        for q_ in range(NCOLS_I):
            CI[a, q_] = newI[a, q_]
    cnt[K_M] = nk
    cnt[K_UPDATES] += 1
    cnt[K_DROPPED] += n_in - nk
    cnt[K_NEW] += n_new
    cnt[K_DEFORMED] += n_def
    cnt[K_LEFT] += m - matched
    cnt[K_FLIPS] += n_flip
    cnt[K_FLIPS_TAKEN] += n_flip_taken
    cnt[K_REKEYED] += n_rekey


@njit(**_JIT)
def update_rigid(kind, par, st, C, CI, cnt, wk, keys, cp, nrm, dsep, vc, n_in, sel, newF, newI,
                 qe, use_qe, st_e, Re, ce):
    """Replace the local contact set by the engine's (validated first; on error nothing changes).
    Contacts absent from the update leave the model. The proxy's q and qd are never touched.

    ``use_qe`` = 0: the paper's eq. 1, the reported feature point ``c_p + d n`` is taken relative
    to the proxy's COM (the engine's tool is assumed to be where the proxy is). ``use_qe`` = 1:
    ``qe`` is the engine's tool configuration at which the contacts were computed; the feature
    point is taken in the engine tool's body frame and carried onto the proxy, and the rule table
    compares the proxy's separation against that true geometry (``s_w``) instead of ``d``. When
    the engine's tool is where the proxy is, both are the same. ``st_e``, ``Re``, ``ce``: scratch."""
    cap = C.shape[0]
    code, nk = check_update(kind, 1, keys, cp, nrm, dsep, vc, n_in, cap, sel)
    if code != E_OK:
        return code
    # --- validated: from here on the update is applied ---
    D, L, U, G, Y, Jh, Jpt, Jn, Bm, Cm, X, Zn, V = _views(wk, cap)
    R = Y
    c = V[_V_T1]
    # one pose row each (rotation + origin: 12 = MAX_DOF floats) in vector scratch rows the
    # update does not otherwise use
    P = V[_V_T2:_V_T2 + 1]
    Pe = V[_V_TAU:_V_TAU + 1]
    _rigid_pose(kind, par, st, R, c)
    _pose_row(R, c, P, 0)
    # the tool's angular velocity and its COM's velocity, world (one more scratch row)
    Vk = V[_V_QD0:_V_QD0 + 1, 0:6]
    for a in range(6):
        Vk[0, a] = 0.0
    if kind == TOOL_1DOF:
        for a in range(3):
            Vk[0, 3 + a] = st[S_QD] * par[P_AXIS + a]
    elif kind == TOOL_PLANAR:
        Vk[0, 2] = st[S_QD + 2]
        Vk[0, 3] = st[S_QD]
        Vk[0, 4] = st[S_QD + 1]
    else:
        for a in range(3):
            Vk[0, a] = st[S_QD + 3 + a]
            Vk[0, 3 + a] = st[S_QD + a]
    if use_qe:
        nq = 1 if kind == TOOL_1DOF else (3 if kind == TOOL_PLANAR else 7)
        for a in range(nq):
            st_e[S_Q + a] = qe[a]
        _rigid_pose(kind, par, st_e, Re, ce)
        _pose_row(Re, ce, Pe, 0)
    apply_update(kind == TOOL_PLANAR, par, st, C, CI, cnt, X, Cm, keys, cp, nrm, dsep, vc, n_in, nk,
                 sel, newF, newI, P, Pe, use_qe, Vk)
    return E_OK
