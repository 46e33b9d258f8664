"""Numba kernels of the simulated devices: one call per ``read`` and one per ``write``.

Dynamics, per kind, at the handle (world frame, gravity compensated as real devices are):

    M a = F_hand + F_cmd - B v + F_stop

- ``1dof``: one coordinate ``s`` along the unit ``axis``; forces are projected on the axis.
- ``planar``: x, y and theta about +z; M = diag(m, m, I_zz).
- ``spatial``: position and a unit quaternion; the rotation obeys Euler's equations in the body
  frame, ``I_b dw_b/dt + w_b x I_b w_b = tau_b``, with the angular velocity reported in world.

Integration is semi-implicit (symplectic) Euler, with the linear terms taken implicitly so that
any damping and any grip stiffness is stable at any period: for each translational axis (and
theta) with the hand's grip spring K_h, damper B_h and mass m_h,

    v1 (m + m_h + dt (B + B_h) + dt^2 K_h) = (m + m_h) v0 + dt (F + K_h (x_t - x0) + B_h v_t)
    x1 = x0 + dt v1

and for the spatial rotation the same terms form a 3x3 system in the body frame (solved by
Cramer's rule), the gyroscopic term taken explicitly. The quaternion is advanced by the exact
exponential of the world angular velocity over the step and renormalised.

End-stops (workspace box, 1dof travel, rotation limit) are unilateral spring-dampers acting only
beyond the limit: the spring on the penetration at the start of the step (explicit; the config
checks ``k dt^2 / m <= 2``, inside the symplectic-Euler stability bound of 4), the damper
implicit. A stop only pushes: if its damper would pull the handle back into the stop as it
leaves, the step is solved with the spring alone.

The hand columns of the state row are what an ideal force sensor between hand and handle reads
over the step just taken: the scripted wrench, plus the grip's spring-damper force at the
implicit end-of-step state, minus the hand's own inertial force ``m_h a``. Only components the
kind can move in are reported (the rest is zero, as a real sensor on that mechanism would see).
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from .base import (
    DEV_FAULT_DISABLED, DEV_FAULT_NONFINITE_COMMAND, DEV_FAULT_WATCHDOG, DEV_NSTATE, DEV_OK,
)
from .hands import hand_eval, inputs_eval
from .layout import (
    DC_ENABLED, DC_FAULT, DC_LAST_NS, DC_WD_NS,
    HO_B, HO_BR, HO_I, HO_K, HO_KR, HO_M, HO_VT, HO_W, HO_XT,
    DK_ENDSTOP, DK_NONFINITE, DK_OVERSPEED, DK_SAT_COMPONENTS, DK_SAT_WRITES, DK_STEPS, DK_WATCHDOG,
    DK_ZEROED,
    KIND_1DOF, KIND_PLANAR,
    DP_AXIS, DP_B, DP_BR, DP_BS, DP_BSR, DP_DT, DP_FMAX, DP_HI, DP_IB, DP_IZZ, DP_KIND, DP_KS, DP_KSR, DP_LO,
    DP_MASS, DP_ORIGIN, DP_ROTLIM, DP_SHI, DP_SLO, DP_TMAX, DP_VMAX, DP_WMAX,
    DST_CMD, DST_HAND, DST_POSE, DST_S, DST_SD, DST_STOP, DST_TH, DST_TIME, DST_TWIST,
)

_JIT = dict(cache=True, nogil=True, error_model="numpy")


# --------------------------------------------------------------------------------- quaternions
@njit(**_JIT)
def qexp(rx, ry, rz):
    """Unit quaternion (w, x, y, z) of the rotation vector r [rad]."""
    a = math.sqrt(rx * rx + ry * ry + rz * rz)
    if a < 1e-12:
        return 1.0, 0.5 * rx, 0.5 * ry, 0.5 * rz
    s = math.sin(0.5 * a) / a
    return math.cos(0.5 * a), s * rx, s * ry, s * rz


@njit(**_JIT)
def qlog(w, x, y, z):
    """Rotation vector [rad] of the unit quaternion (w, x, y, z), angle in [0, pi]."""
    if w < 0.0:
        w = -w; x = -x; y = -y; z = -z
    n = math.sqrt(x * x + y * y + z * z)
    if n < 1e-12:
        return 2.0 * x, 2.0 * y, 2.0 * z
    a = 2.0 * math.atan2(n, w) / n
    return a * x, a * y, a * z


@njit(**_JIT)
def qmul(aw, ax, ay, az, bw, bx, by, bz):
    return (aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw)


# ------------------------------------------------------------------------------ scalar solves
@njit(**_JIT)
def _axis_step(m, x0, v0, dt, f, b, kh, bh, xt, vt, lo, hi, limited, ks, bs):
    """One implicit step of one coordinate; returns (v1, end-stop force)."""
    rhs = m * v0 + dt * (f + kh * (xt - x0) + bh * vt)
    den = m + dt * (b + bh) + dt * dt * kh
    if limited:
        sgn = 0.0
        pen = 0.0
        if x0 > hi:
            sgn = 1.0
            pen = x0 - hi
        elif x0 < lo:
            sgn = -1.0
            pen = lo - x0
        if sgn != 0.0:
            rhs_s = rhs - dt * sgn * ks * pen
            v1 = rhs_s / (den + dt * bs)
            push = ks * pen + bs * sgn * v1
            if push < 0.0:
                v1 = rhs_s / den
                push = ks * pen
            return v1, -sgn * push
    return rhs / den, 0.0


@njit(**_JIT)
def _solve3(a00, a01, a02, a10, a11, a12, a20, a21, a22, b0, b1, b2):
    c00 = a11 * a22 - a12 * a21
    c01 = a12 * a20 - a10 * a22
    c02 = a10 * a21 - a11 * a20
    det = a00 * c00 + a01 * c01 + a02 * c02
    inv = 1.0 / det
    x0 = (b0 * c00 + a01 * (a12 * b2 - b1 * a22) + a02 * (b1 * a21 - a11 * b2)) * inv
    x1 = (a00 * (b1 * a22 - a12 * b2) + b0 * (a12 * a20 - a10 * a22) + a02 * (a10 * b2 - b1 * a20)) * inv
    x2 = (a00 * (a11 * b2 - b1 * a21) + a01 * (b1 * a20 - a10 * b2) + b0 * (a10 * a21 - a11 * a20)) * inv
    return x0, x1, x2


# ------------------------------------------------------------------------------- the step
@njit(**_JIT)
def _step(par, st, cnt, hout):
    """Advance the device by one period under the rendered command ``st[DST_CMD]`` and the hand."""
    kind = int(par[DP_KIND])
    dt = par[DP_DT]
    kh = hout[HO_K]; bh = hout[HO_B]; mh = hout[HO_M]
    m = par[DP_MASS] + mh
    b = par[DP_B]
    ks = par[DP_KS]; bs = par[DP_BS]
    stop_engaged = False
    vmax = par[DP_VMAX]
    wmax = par[DP_WMAX]
    speed2 = 0.0
    wspeed2 = 0.0
    for i in range(6):
        st[DST_STOP + i] = 0.0
    if kind == KIND_1DOF:
        ax = par[DP_AXIS]; ay = par[DP_AXIS + 1]; az = par[DP_AXIS + 2]
        fw = ax * hout[HO_W] + ay * hout[HO_W + 1] + az * hout[HO_W + 2]
        fc = ax * st[DST_CMD] + ay * st[DST_CMD + 1] + az * st[DST_CMD + 2]
        ox = par[DP_ORIGIN]; oy = par[DP_ORIGIN + 1]; oz = par[DP_ORIGIN + 2]
        xt = ax * (hout[HO_XT] - ox) + ay * (hout[HO_XT + 1] - oy) + az * (hout[HO_XT + 2] - oz)
        vt = ax * hout[HO_VT] + ay * hout[HO_VT + 1] + az * hout[HO_VT + 2]
        s0 = st[DST_S]; v0 = st[DST_SD]
        v1, fs = _axis_step(m, s0, v0, dt, fw + fc, b, kh, bh, xt, vt, par[DP_SLO], par[DP_SHI], True, ks, bs)
        s1 = s0 + dt * v1
        fh = fw + kh * (xt - s0 - dt * v1) + bh * (vt - v1) - mh * (v1 - v0) / dt
        st[DST_S] = s1; st[DST_SD] = v1
        st[DST_POSE] = ox + s1 * ax; st[DST_POSE + 1] = oy + s1 * ay; st[DST_POSE + 2] = oz + s1 * az
        st[DST_POSE + 3] = 1.0; st[DST_POSE + 4] = 0.0; st[DST_POSE + 5] = 0.0; st[DST_POSE + 6] = 0.0
        st[DST_TWIST] = v1 * ax; st[DST_TWIST + 1] = v1 * ay; st[DST_TWIST + 2] = v1 * az
        st[DST_TWIST + 3] = 0.0; st[DST_TWIST + 4] = 0.0; st[DST_TWIST + 5] = 0.0
        st[DST_HAND] = fh * ax; st[DST_HAND + 1] = fh * ay; st[DST_HAND + 2] = fh * az
        st[DST_HAND + 3] = 0.0; st[DST_HAND + 4] = 0.0; st[DST_HAND + 5] = 0.0
        if fs != 0.0:
            stop_engaged = True
            st[DST_STOP] = fs * ax; st[DST_STOP + 1] = fs * ay; st[DST_STOP + 2] = fs * az
        speed2 = v1 * v1
    else:
        ntr = 2 if kind == KIND_PLANAR else 3
        for i in range(ntr):
            x0 = st[DST_POSE + i]; v0 = st[DST_TWIST + i]
            f = hout[HO_W + i] + st[DST_CMD + i]
            xt = hout[HO_XT + i]; vt = hout[HO_VT + i]
            v1, fs = _axis_step(m, x0, v0, dt, f, b, kh, bh, xt, vt, par[DP_LO + i], par[DP_HI + i], True, ks, bs)
            st[DST_HAND + i] = hout[HO_W + i] + kh * (xt - x0 - dt * v1) + bh * (vt - v1) - mh * (v1 - v0) / dt
            st[DST_POSE + i] = x0 + dt * v1
            st[DST_TWIST + i] = v1
            if fs != 0.0:
                stop_engaged = True
                st[DST_STOP + i] = fs
            speed2 += v1 * v1
        krh = hout[HO_KR]; brh = hout[HO_BR]; ih = hout[HO_I]
        lim = par[DP_ROTLIM]
        if kind == KIND_PLANAR:
            th0 = st[DST_TH]; w0 = st[DST_TWIST + 5]
            tau = hout[HO_W + 5] + st[DST_CMD + 5]
            tt = hout[HO_XT + 5]; wt = hout[HO_VT + 5]
            w1, ts = _axis_step(par[DP_IZZ] + ih, th0, w0, dt, tau, par[DP_BR], krh, brh, tt, wt,
                                -lim, lim, lim > 0.0, par[DP_KSR], par[DP_BSR])
            th1 = th0 + dt * w1
            st[DST_TH] = th1
            st[DST_POSE + 2] = 0.0
            st[DST_POSE + 3] = math.cos(0.5 * th1); st[DST_POSE + 4] = 0.0
            st[DST_POSE + 5] = 0.0; st[DST_POSE + 6] = math.sin(0.5 * th1)
            st[DST_TWIST + 2] = 0.0; st[DST_TWIST + 3] = 0.0; st[DST_TWIST + 4] = 0.0
            st[DST_TWIST + 5] = w1
            st[DST_HAND + 2] = 0.0; st[DST_HAND + 3] = 0.0; st[DST_HAND + 4] = 0.0
            st[DST_HAND + 5] = hout[HO_W + 5] + krh * (tt - th0 - dt * w1) + brh * (wt - w1) - ih * (w1 - w0) / dt
            if ts != 0.0:
                stop_engaged = True
                st[DST_STOP + 5] = ts
            wspeed2 = w1 * w1
        else:
            qw = st[DST_POSE + 3]; qx = st[DST_POSE + 4]; qy = st[DST_POSE + 5]; qz = st[DST_POSE + 6]
            # body -> world rotation R (columns are the body axes in world)
            r00 = 1.0 - 2.0 * (qy * qy + qz * qz); r01 = 2.0 * (qx * qy - qw * qz); r02 = 2.0 * (qx * qz + qw * qy)
            r10 = 2.0 * (qx * qy + qw * qz); r11 = 1.0 - 2.0 * (qx * qx + qz * qz); r12 = 2.0 * (qy * qz - qw * qx)
            r20 = 2.0 * (qx * qz - qw * qy); r21 = 2.0 * (qy * qz + qw * qx); r22 = 1.0 - 2.0 * (qx * qx + qy * qy)
            w0x = st[DST_TWIST + 3]; w0y = st[DST_TWIST + 4]; w0z = st[DST_TWIST + 5]
            # grip orientation error, world: log(q_t q^-1)
            tw, tx, ty, tz = qexp(hout[HO_XT + 3], hout[HO_XT + 4], hout[HO_XT + 5])
            ew, ex, ey, ez = qmul(tw, tx, ty, tz, qw, -qx, -qy, -qz)
            e0x, e0y, e0z = qlog(ew, ex, ey, ez)
            wtx = hout[HO_VT + 3]; wty = hout[HO_VT + 4]; wtz = hout[HO_VT + 5]
            taux = hout[HO_W + 3] + st[DST_CMD + 3] + krh * e0x + brh * wtx
            tauy = hout[HO_W + 4] + st[DST_CMD + 4] + krh * e0y + brh * wty
            tauz = hout[HO_W + 5] + st[DST_CMD + 5] + krh * e0z + brh * wtz
            # rotation limit: a cone about the identity orientation
            stop_on = False
            pen = 0.0
            nx = 0.0; ny = 0.0; nz = 0.0
            ksr = par[DP_KSR]; bsr = par[DP_BSR]
            if lim > 0.0:
                rx, ry, rz = qlog(qw, qx, qy, qz)
                ang = math.sqrt(rx * rx + ry * ry + rz * rz)
                if ang > lim:
                    stop_on = True
                    pen = ang - lim
                    nx = rx / ang; ny = ry / ang; nz = rz / ang
            # to the body frame (R^T); the rotation axis n is fixed by its own rotation: n_b = n
            tbx = r00 * taux + r10 * tauy + r20 * tauz
            tby = r01 * taux + r11 * tauy + r21 * tauz
            tbz = r02 * taux + r12 * tauy + r22 * tauz
            wbx = r00 * w0x + r10 * w0y + r20 * w0z
            wby = r01 * w0x + r11 * w0y + r21 * w0z
            wbz = r02 * w0x + r12 * w0y + r22 * w0z
            i00 = par[DP_IB] + ih; i01 = par[DP_IB + 1]; i02 = par[DP_IB + 2]
            i10 = par[DP_IB + 3]; i11 = par[DP_IB + 4] + ih; i12 = par[DP_IB + 5]
            i20 = par[DP_IB + 6]; i21 = par[DP_IB + 7]; i22 = par[DP_IB + 8] + ih
            hx = i00 * wbx + i01 * wby + i02 * wbz
            hy = i10 * wbx + i11 * wby + i12 * wbz
            hz = i20 * wbx + i21 * wby + i22 * wbz
            gx = wby * hz - wbz * hy; gy = wbz * hx - wbx * hz; gz = wbx * hy - wby * hx
            c = par[DP_BR] + brh + dt * krh
            idt = 1.0 / dt
            b0 = hx * idt - gx + tbx
            b1 = hy * idt - gy + tby
            b2 = hz * idt - gz + tbz
            a00 = i00 * idt + c; a01 = i01 * idt; a02 = i02 * idt
            a10 = i10 * idt; a11 = i11 * idt + c; a12 = i12 * idt
            a20 = i20 * idt; a21 = i21 * idt; a22 = i22 * idt + c
            push = 0.0
            if stop_on:
                # the spring (explicit) pushes back along -n, the damper is implicit
                ksp = ksr * pen
                b0s = b0 - ksp * nx; b1s = b1 - ksp * ny; b2s = b2 - ksp * nz
                w1bx, w1by, w1bz = _solve3(a00 + bsr * nx * nx, a01 + bsr * nx * ny, a02 + bsr * nx * nz,
                                           a10 + bsr * ny * nx, a11 + bsr * ny * ny, a12 + bsr * ny * nz,
                                           a20 + bsr * nz * nx, a21 + bsr * nz * ny, a22 + bsr * nz * nz,
                                           b0s, b1s, b2s)
                push = ksp + bsr * (nx * w1bx + ny * w1by + nz * w1bz)
                if push < 0.0:
                    w1bx, w1by, w1bz = _solve3(a00, a01, a02, a10, a11, a12, a20, a21, a22, b0s, b1s, b2s)
                    push = ksp
            else:
                w1bx, w1by, w1bz = _solve3(a00, a01, a02, a10, a11, a12, a20, a21, a22, b0, b1, b2)
            w1x = r00 * w1bx + r01 * w1by + r02 * w1bz
            w1y = r10 * w1bx + r11 * w1by + r12 * w1bz
            w1z = r20 * w1bx + r21 * w1by + r22 * w1bz
            dw, dx, dy, dz = qexp(w1x * dt, w1y * dt, w1z * dt)
            nw, nqx, nqy, nqz = qmul(dw, dx, dy, dz, qw, qx, qy, qz)
            inv = 1.0 / math.sqrt(nw * nw + nqx * nqx + nqy * nqy + nqz * nqz)
            st[DST_POSE + 3] = nw * inv; st[DST_POSE + 4] = nqx * inv
            st[DST_POSE + 5] = nqy * inv; st[DST_POSE + 6] = nqz * inv
            st[DST_TWIST + 3] = w1x; st[DST_TWIST + 4] = w1y; st[DST_TWIST + 5] = w1z
            st[DST_HAND + 3] = hout[HO_W + 3] + krh * (e0x - dt * w1x) + brh * (wtx - w1x) - ih * (w1x - w0x) * idt
            st[DST_HAND + 4] = hout[HO_W + 4] + krh * (e0y - dt * w1y) + brh * (wty - w1y) - ih * (w1y - w0y) * idt
            st[DST_HAND + 5] = hout[HO_W + 5] + krh * (e0z - dt * w1z) + brh * (wtz - w1z) - ih * (w1z - w0z) * idt
            if stop_on:
                stop_engaged = True
                st[DST_STOP + 3] = -push * nx; st[DST_STOP + 4] = -push * ny; st[DST_STOP + 5] = -push * nz
            wspeed2 = w1x * w1x + w1y * w1y + w1z * w1z
    cnt[DK_STEPS] += 1
    st[DST_TIME] = cnt[DK_STEPS] * dt
    if stop_engaged:
        cnt[DK_ENDSTOP] += 1
    if speed2 > vmax * vmax or wspeed2 > wmax * wmax:
        cnt[DK_OVERSPEED] += 1


@njit(**_JIT)
def _watchdog(ctl, cnt, now_ns):
    if ctl[DC_ENABLED] == 1 and ctl[DC_FAULT] == DEV_OK and ctl[DC_WD_NS] > 0 \
            and now_ns - ctl[DC_LAST_NS] > ctl[DC_WD_NS]:
        ctl[DC_FAULT] = DEV_FAULT_WATCHDOG
        cnt[DK_WATCHDOG] += 1


@njit(**_JIT)
def _status(ctl):
    if ctl[DC_FAULT] != DEV_OK:
        return ctl[DC_FAULT]
    if ctl[DC_ENABLED] == 0:
        return DEV_FAULT_DISABLED
    return DEV_OK


@njit(**_JIT)
def sim_write(par, st, cnt, ctl, hout, wrench, now_ns):
    """Check the watchdog and the command, render it (masked, capped), advance one period.

    Returns the status (``DEV_OK`` or the latched fault, ``DEV_FAULT_DISABLED`` when disabled).
    """
    _watchdog(ctl, cnt, now_ns)
    ctl[DC_LAST_NS] = now_ns
    finite = True
    for i in range(6):
        if not math.isfinite(wrench[i]):
            finite = False
    if not finite:
        cnt[DK_NONFINITE] += 1
        if ctl[DC_FAULT] == DEV_OK:
            ctl[DC_FAULT] = DEV_FAULT_NONFINITE_COMMAND
    for i in range(6):
        st[DST_CMD + i] = 0.0
    if ctl[DC_FAULT] != DEV_OK or ctl[DC_ENABLED] == 0:
        cnt[DK_ZEROED] += 1
    else:
        kind = int(par[DP_KIND])
        fmax = par[DP_FMAX]
        tmax = par[DP_TMAX]
        nsat = 0
        if kind == KIND_1DOF:
            ax = par[DP_AXIS]; ay = par[DP_AXIS + 1]; az = par[DP_AXIS + 2]
            f = ax * wrench[0] + ay * wrench[1] + az * wrench[2]
            if f > fmax:
                f = fmax; nsat += 1
            elif f < -fmax:
                f = -fmax; nsat += 1
            st[DST_CMD] = f * ax; st[DST_CMD + 1] = f * ay; st[DST_CMD + 2] = f * az
        else:
            for i in range(6):
                if kind == KIND_PLANAR and (i == 2 or i == 3 or i == 4):
                    continue
                cap = fmax if i < 3 else tmax
                v = wrench[i]
                if v > cap:
                    v = cap; nsat += 1
                elif v < -cap:
                    v = -cap; nsat += 1
                st[DST_CMD + i] = v
        if nsat > 0:
            cnt[DK_SAT_WRITES] += 1
            cnt[DK_SAT_COMPONENTS] += nsat
    _step(par, st, cnt, hout)
    return _status(ctl)


@njit(**_JIT)
def sim_write_hand(par, st, cnt, ctl, hp, tab, hout, wrench, cmd, now_ns):
    """One step of ``SimDevice.write`` in one call (a call per step costs us on a cold cache):
    keep the command (``cmd``, float64[6], as ``wrench``: float64[6], checked by the caller),
    evaluate the hand's script at the device time (``hands.hand_eval``), ``sim_write``, then
    the hand's input scripts (buttons, gripper) at the new device time (``hands.inputs_eval``)."""
    for i in range(6):
        cmd[i] = wrench[i]
    hand_eval(hp, tab, st, hout)
    rc = sim_write(par, st, cnt, ctl, hout, cmd, now_ns)
    inputs_eval(hp, tab, st)
    return rc


@njit(**_JIT)
def sim_read(st, ctl, cnt, out, now_ns):
    """Copy the state row into ``out`` (float64[>= DEV_NSTATE]); check the watchdog; status."""
    if out.shape[0] < DEV_NSTATE:  # numba does not bounds-check the writes below
        raise ValueError("state_out: expected float64[23] (DEV_NSTATE)")
    _watchdog(ctl, cnt, now_ns)
    for i in range(DEV_NSTATE):
        out[i] = st[i]
    return _status(ctl)


@njit(**_JIT)
def sim_hand_now(par, st, hout):
    """Fill the hand columns for the current state before any step (zero acceleration)."""
    kind = int(par[DP_KIND])
    kh = hout[HO_K]; bh = hout[HO_B]; krh = hout[HO_KR]; brh = hout[HO_BR]
    for i in range(6):
        st[DST_HAND + i] = 0.0
    if kind == KIND_1DOF:
        ax = par[DP_AXIS]; ay = par[DP_AXIS + 1]; az = par[DP_AXIS + 2]
        f = 0.0
        for i in range(3):
            a = par[DP_AXIS + i]
            f += a * (hout[HO_W + i] + kh * (hout[HO_XT + i] - st[DST_POSE + i])
                      + bh * (hout[HO_VT + i] - st[DST_TWIST + i]))
        st[DST_HAND] = f * ax; st[DST_HAND + 1] = f * ay; st[DST_HAND + 2] = f * az
        return
    ntr = 2 if kind == KIND_PLANAR else 3
    for i in range(ntr):
        st[DST_HAND + i] = hout[HO_W + i] + kh * (hout[HO_XT + i] - st[DST_POSE + i]) \
            + bh * (hout[HO_VT + i] - st[DST_TWIST + i])
    if kind == KIND_PLANAR:
        st[DST_HAND + 5] = hout[HO_W + 5] + krh * (hout[HO_XT + 5] - st[DST_TH]) \
            + brh * (hout[HO_VT + 5] - st[DST_TWIST + 5])
        return
    tw, tx, ty, tz = qexp(hout[HO_XT + 3], hout[HO_XT + 4], hout[HO_XT + 5])
    ew, ex, ey, ez = qmul(tw, tx, ty, tz, st[DST_POSE + 3], -st[DST_POSE + 4], -st[DST_POSE + 5], -st[DST_POSE + 6])
    e0x, e0y, e0z = qlog(ew, ex, ey, ez)
    st[DST_HAND + 3] = hout[HO_W + 3] + krh * e0x + brh * (hout[HO_VT + 3] - st[DST_TWIST + 3])
    st[DST_HAND + 4] = hout[HO_W + 4] + krh * e0y + brh * (hout[HO_VT + 4] - st[DST_TWIST + 4])
    st[DST_HAND + 5] = hout[HO_W + 5] + krh * e0z + brh * (hout[HO_VT + 5] - st[DST_TWIST + 5])


def warm_arrays():
    """Throw-away arrays of the right types (for compiling the kernels)."""
    from .layout import NCNT, NCTL, NHO, NPAR, NST
    return (np.zeros(NPAR), np.zeros(NST), np.zeros(NCNT, dtype=np.int64),
            np.zeros(NCTL, dtype=np.int64), np.zeros(NHO))
