"""Controllers between the device and the proxy, and the safety layer, as one numba kernel.

``haptic_step`` is the whole per-step computation after the device has been read: map the
device into the world, run the controller, step the local model, map the command back to the
device, then the safety filter (finite check, fade, per-axis caps, rate limit). One compiled
call per haptic step; the arrays are owned by :class:`Controller`.

Controllers (the paper's section II and V; Sirouspour's four-channel architecture):

- ``four_channel``: force channels (measured hand wrench -> proxy, environment wrench -> device)
  plus position channels (translational and rotational spring-dampers between the device
  handle and the proxy hand point). Proxy: ``F_h + F_c``; device: ``F_env - F_c``, where
  ``F_c = K (x_dev - x_proxy) + B (v_dev - v_proxy)`` (world, at the hand point).
- ``coupler`` (virtual coupler): the spring-damper only. Proxy ``F_c``; device ``-F_c``.
- ``direct`` (direct coupling, the intermediate-representation baseline of Berkelman et al.): the
  device *is* the tool: the proxy state is set to the device state every step and the device
  gets the environment wrench; no position coordination.

Frames: the device reports its handle pose in device coordinates; the world pose of the handle
is ``R_off p_dev + p_off`` (orientation ``q_off * q_dev``). With ``mapping = "index"`` the
offset is set when a session engages so that the handle maps exactly onto the proxy's hand
point (no jump; the classic indexing of haptic workspaces); ``absolute`` keeps the identity.
The hand point is the tool frame's origin (``-com_m`` in the body frame).

Safety: a non-finite device state -> zero output and a latched ``NONFINITE`` code (the loop
disables the device); device speed over its limit -> the gain target drops to 0 (a fade-out) and
a trip is counted; then the command goes through the safety filter (``safety.safety_filter``,
whose docstring is its contract: finite, caps on the norm and per axis, the gain's fade and ramp
envelopes, the rate limit). The filter's arrays are blocks of the controller's (``CP_SAFETY``,
``CS_SAFETY``, ``CC_SAFETY``).
"""
from __future__ import annotations

import logging
import math

import numpy as np
from numba import njit

from ..protocol.vocab import CONTROLLERS

from . import passivity as pv
from . import safety as sf
from .devices import safe
from .devices import frozen as fz
from .readonly import ArrayBool, ArrayFloat, ArrayInt
from .model.kernels import _rigid_pose, hand_to_world, step_rigid
from .model.layout import (
    DIVERGE_STEPS, INTEG_EXPLICIT, K_OSC_RUN, LM_PLANAR, P_AXIS, P_CPL_BR, P_CPL_BT, P_CPL_KR, P_CPL_KT, P_HAND, P_INTEG, P_ORIGIN,
    P_REC_CUT, S_FCPL,
    S_FENV, S_Q, S_QD, TOOL_1DOF, TOOL_PLANAR, TOOL_SPATIAL,
)
from .model.linkage import hand_state_linkage, step_linkage
from .model.model import quat_to_matrix
from .prediction import advice_update
from .stability import coupling_damping_for_tool, device_damper_limit_n_s_per_m, rot_coupling_damping_for_tool

log = logging.getLogger("hapticproxy.control")

_JIT = dict(cache=True, nogil=True, error_model="numpy")

CTRL_FOUR_CHANNEL = 0
CTRL_COUPLER = 1
CTRL_DIRECT = 2
#: kernel code of each controller name (the names: ``protocol.vocab.CONTROLLERS``, in this order)
CONTROLLER_IDS = {name: code for code, name in enumerate(CONTROLLERS)}
assert CONTROLLER_IDS == {"four_channel": CTRL_FOUR_CHANNEL, "coupler": CTRL_COUPLER, "direct": CTRL_DIRECT}

# ---- parameters (float64[NCP])
CP_TYPE = 0
CP_KT = 1          # translational spring, N/m
CP_BT = 2          # translational damper, N s/m
CP_KR = 3          # rotational spring, N m/rad
CP_BR = 4          # rotational damper, N m s/rad
CP_HG = 5          # hand force-channel gain
CP_EG = 6          # environment force-channel gain
CP_ROFF = 7        # 7..15 device -> world rotation, row-major
CP_POFF = 16       # 16..18 device -> world translation, m
CP_QOFF = 19       # 19..22 the same rotation as a quaternion (w x y z)
CP_VMAX = 23       # device speed limit, m/s
CP_WMAX = 24       # device angular speed limit, rad/s
CP_SAFETY = 25     # 25..38 the safety filter's parameters (``safety.SP_*``)
CP_TANK = CP_SAFETY + sf.NSP  # 39.. the passivity layer's parameters (``passivity.TP_*``)
CP_FROZEN = CP_TANK + pv.NTP  # the frozen-position watch's parameters (``devices.frozen.FP_*``)
NCP = CP_FROZEN + fz.NFP

# ---- state (float64[NCS]); rows for telemetry and the ProxyState
CS_SAFETY = 0      # 0..8 the safety filter's state (``safety.SS_*``): gain, target, previous output
CS_GAIN = CS_SAFETY + sf.SS_GAIN        # gain of the rendered force, 0..1
CS_TARGET = CS_SAFETY + sf.SS_TARGET    # where the gain goes
CS_PREV = CS_SAFETY + sf.SS_PREV        # 2..7 previous output, device frame
CS_SKIPPED = CS_SAFETY + sf.SS_SKIPPED  # periods the loop skipped before this step (it woke late)
CS_FC = 9          # 9..14 coupling wrench on the proxy, world
CS_HAND = 15       # 15..20 wrench applied to the proxy at the hand point, world
CS_ENV = 21        # 21..26 environment wrench at the hand point, world
CS_DPOSE = 27      # 27..33 device handle pose, world (x y z qw qx qy qz)
CS_DTWIST = 34     # 34..39 device handle twist, world
CS_PPOSE = 40      # 40..46 proxy hand-point (tool-frame) pose, world, after the step
CS_PTWIST = 47     # 47..52 proxy hand-point twist, world, after the step
CS_CMDW = 53       # 53..58 controller command before safety, world
CS_DRIVE = 59      # 1: the device drives the proxy (hand and coupling channels, model step); 0: held
CS_SLIDE = 60      # 1: the device->world offset follows the proxy while the force ramps in
CS_EHAND = 61      # the energy the device gave the hand since start, J (``port_energy``)
CS_EPOSE = 62      # 62..68 the device's pose (device frame) when the last command was written
CS_EVALID = 69     # 1: CS_EPOSE holds a pose (the ledger pairs the next displacement with it)
CS_EDX2 = 70       # the last paired period's squared displacement of the handle, m^2
CS_EDR2 = 71       # and squared rotation, rad^2 (the declared device damping's share, ``passivity``)
CS_TANK = 72       # 72.. the passivity layer's state (``passivity.TS_*``): the tank and its books
CS_FROZEN = CS_TANK + pv.NTS  # the frozen-position watch's state (``devices.frozen.FS_*``)
NCS = CS_FROZEN + fz.NFS

# ---- counters (int64[NCC])
CC_SAFETY = 0          # 0..2 the safety filter's counters (``safety.SC_*``)
CC_SATURATED = CC_SAFETY + sf.SC_SATURATED        # steps in which a cap clipped the command
CC_RATE_LIMITED = CC_SAFETY + sf.SC_RATE_LIMITED  # steps in which the rate limit clipped it
CC_CMD_NONFINITE = CC_SAFETY + sf.SC_NONFINITE    # steps whose command was not finite
CC_STEPS = 3
CC_SPEED_TRIPS = 4     # steps over the speed limit
CC_NONFINITE = 5       # steps with a non-finite device state or model result
CC_HAND_MISSING = 6    # steps with no (finite) measured hand wrench in four-channel
CC_TANK = 7            # 7.. the passivity layer's counters (``passivity.TC_*``)
NCC = CC_TANK + pv.NTC

RC_OK = sf.RC_OK
RC_NONFINITE = sf.RC_NONFINITE
RC_SPEED = 2
RC_DIVERGED = 3     # the model's integration diverged (model.layout DIVERGE_STEPS): forces fade, device on


@njit(**_JIT)
def _rot(R, off, x, y, z, out, o):
    out[o] = R[off] * x + R[off + 1] * y + R[off + 2] * z
    out[o + 1] = R[off + 3] * x + R[off + 4] * y + R[off + 5] * z
    out[o + 2] = R[off + 6] * x + R[off + 7] * y + R[off + 8] * z


@njit(**_JIT)
def _rot_t(R, off, x, y, z, out, o):
    out[o] = R[off] * x + R[off + 3] * y + R[off + 6] * z
    out[o + 1] = R[off + 1] * x + R[off + 4] * y + R[off + 7] * z
    out[o + 2] = R[off + 2] * x + R[off + 5] * y + R[off + 8] * z


@njit(**_JIT)
def _qmul(aw, ax, ay, az, bw, bx, by, bz, out, o):
    out[o] = aw * bw - ax * bx - ay * by - az * bz
    out[o + 1] = aw * bx + ax * bw + ay * bz - az * by
    out[o + 2] = aw * by - ax * bz + ay * bw + az * bx
    out[o + 3] = aw * bz + ax * by - ay * bx + az * bw


@njit(**_JIT)
def _wrap(a):
    return (a + math.pi) % (2.0 * math.pi) - math.pi


@njit(**_JIT)
def proxy_hand_state(kind, par, st, R, c, out, o):
    """Proxy hand-point pose (7) at out[o:o+7] and twist (6) at out[o+7:o+13], world."""
    _rigid_pose(kind, par, st, R, c)
    hx = R[0, 0] * par[P_HAND] + R[0, 1] * par[P_HAND + 1] + R[0, 2] * par[P_HAND + 2]
    hy = R[1, 0] * par[P_HAND] + R[1, 1] * par[P_HAND + 1] + R[1, 2] * par[P_HAND + 2]
    hz = R[2, 0] * par[P_HAND] + R[2, 1] * par[P_HAND + 1] + R[2, 2] * par[P_HAND + 2]
    out[o] = c[0] + hx
    out[o + 1] = c[1] + hy
    out[o + 2] = c[2] + hz
    for j in range(13):
        if j >= 3:
            out[o + j] = 0.0
    out[o + 3] = 1.0
    if kind == TOOL_1DOF:
        for j in range(3):
            out[o + 7 + j] = st[S_QD] * par[P_AXIS + j]
    elif kind == TOOL_PLANAR:
        th = st[S_Q + 2]
        out[o + 3] = math.cos(0.5 * th)
        out[o + 6] = math.sin(0.5 * th)
        w = st[S_QD + 2]
        out[o + 7] = st[S_QD] - w * hy
        out[o + 8] = st[S_QD + 1] + w * hx
        out[o + 12] = w
    else:
        for j in range(4):
            out[o + 3 + j] = st[S_Q + 3 + j]
        wx = st[S_QD + 3]; wy = st[S_QD + 4]; wz = st[S_QD + 5]
        out[o + 7] = st[S_QD] + wy * hz - wz * hy
        out[o + 8] = st[S_QD + 1] + wz * hx - wx * hz
        out[o + 9] = st[S_QD + 2] + wx * hy - wy * hx
        out[o + 10] = wx
        out[o + 11] = wy
        out[o + 12] = wz


@njit(**_JIT)
def ack_state(kind, par, st, R, c, out, adv_a, adv_p, now_s, engine_tool_pose, separation_m):
    """What acknowledges an update of a rigid tool, in one call: the proxy's hand-point pose
    and twist (``proxy_hand_state`` into ``out[0:13]``) and the engine's advice from them
    (``prediction.advice_update``; ``adv_a`` / ``adv_p``: ``EngineAdvice.kernel_arrays``)."""
    proxy_hand_state(kind, par, st, R, c, out, 0)
    advice_update(adv_a, adv_p, now_s, out[0:7], out[7:13], engine_tool_pose, separation_m, False)


@njit(**_JIT)
def _fault_zero(cs, cc, cmd):
    """A non-finite device state or model result: zero output, no gain, counted."""
    for k in range(6):
        cmd[k] = 0.0
    sf.reset(cs[CS_SAFETY:CS_SAFETY + sf.NSS])
    cc[CC_NONFINITE] += 1
    return RC_NONFINITE


@njit(**_JIT)
def _safety(cp, cs, cc, cmd):
    """The safety filter (``safety.safety_filter``: its docstring is the contract) on the
    controller's blocks."""
    return sf.safety_filter(cp[CP_SAFETY:CP_SAFETY + sf.NSP], cs[CS_SAFETY:CS_SAFETY + sf.NSS],
                            cc[CC_SAFETY:CC_SAFETY + sf.NSC], cmd)


@njit(**_JIT)
def port_energy(cs, dev):
    """The energy ledger at the hand's port: the work the command written last period did on the
    hand, paired exactly (the force and torque held over the period, device frame, times the
    displacement and rotation of the handle during it), added to CS_EHAND; then this sample's
    pose is kept for the next. Call after reading the device, before the new command: the
    command in ``CS_PREV`` is the one that was held. A rotation counts by its rotation vector
    (q_new conj(q_old)); a device whose sample is not finite is skipped (its period is lost).
    Returns the period's energy (0 when nothing was paired) and keeps its squared displacement and
    rotation in CS_EDX2 / CS_EDR2 (what a viscous damper dissipated at least: ``passivity``)."""
    cs[CS_EDX2] = 0.0
    cs[CS_EDR2] = 0.0
    w = 0.0
    for j in range(7):
        if not math.isfinite(dev[j]):
            cs[CS_EVALID] = 0.0
            return w
    if cs[CS_EVALID] != 0.0:
        dx2 = 0.0
        for j in range(3):
            d = dev[j] - cs[CS_EPOSE + j]
            w += cs[CS_PREV + j] * d
            dx2 += d * d
        cs[CS_EDX2] = dx2
        # rotation vector of dq = q_new conj(q_old)
        aw = dev[3]; ax = dev[4]; ay = dev[5]; az = dev[6]
        bw = cs[CS_EPOSE + 3]; bx = -cs[CS_EPOSE + 4]; by = -cs[CS_EPOSE + 5]; bz = -cs[CS_EPOSE + 6]
        qw = aw * bw - ax * bx - ay * by - az * bz
        qx = aw * bx + ax * bw + ay * bz - az * by
        qy = aw * by - ax * bz + ay * bw + az * bx
        qz = aw * bz + ax * by - ay * bx + az * bw
        if qw < 0.0:
            qw = -qw; qx = -qx; qy = -qy; qz = -qz
        vn = math.sqrt(qx * qx + qy * qy + qz * qz)
        if vn > 1e-15:
            ang = 2.0 * math.atan2(vn, qw) / vn
            w += ang * (cs[CS_PREV + 3] * qx + cs[CS_PREV + 4] * qy + cs[CS_PREV + 5] * qz)
            cs[CS_EDR2] = (ang * vn) ** 2
        cs[CS_EHAND] += w
    for j in range(7):
        cs[CS_EPOSE + j] = dev[j]
    cs[CS_EVALID] = 1.0
    return w


@njit(**_JIT)
def _port_in(cp, cs, dev):
    """The ledger (``port_energy``), then its period into the passivity layer's tank."""
    w = port_energy(cs, dev)
    pv.account(cp[CP_TANK:CP_TANK + pv.NTP], cs[CS_TANK:CS_TANK + pv.NTS], w, cs[CS_EDX2], cs[CS_EDR2])


@njit(**_JIT)
def _map_device(cp, cs, dev):
    """The device handle's pose and twist in the world (CS_DPOSE, CS_DTWIST) through the offset."""
    _rot(cp, CP_ROFF, dev[0], dev[1], dev[2], cs, CS_DPOSE)
    for j in range(3):
        cs[CS_DPOSE + j] += cp[CP_POFF + j]
    _qmul(cp[CP_QOFF], cp[CP_QOFF + 1], cp[CP_QOFF + 2], cp[CP_QOFF + 3],
          dev[3], dev[4], dev[5], dev[6], cs, CS_DPOSE + 3)
    _rot(cp, CP_ROFF, dev[7], dev[8], dev[9], cs, CS_DTWIST)
    _rot(cp, CP_ROFF, dev[10], dev[11], dev[12], cs, CS_DTWIST + 3)


@njit(**_JIT)
def _slide(cp, cs, dev, mode):
    """Re-index: set the device -> world offset so that the handle maps exactly onto the proxy's
    hand point (CS_PPOSE), then map the handle again. Run every step while the force ramps in:
    a hand that keeps pushing moves the device while the output is still small, and a fixed
    offset would store that motion in the coupling spring (and drag the proxy into what it
    touches) to release it when the ramp ends. With the offset following, the spring stays
    relaxed and only the damper couples the two until the ramp is complete. ``mode`` as in
    ``_coupling``: 0 keeps the axis alignment set at engagement, 1 re-aligns about +z, 2 fully."""
    if mode == 1:
        th = (2.0 * math.atan2(cs[CS_PPOSE + 6], cs[CS_PPOSE + 3])
              - 2.0 * math.atan2(dev[6], dev[3]))
        ch = math.cos(0.5 * th)
        sh = math.sin(0.5 * th)
        cp[CP_QOFF] = ch; cp[CP_QOFF + 1] = 0.0; cp[CP_QOFF + 2] = 0.0; cp[CP_QOFF + 3] = sh
    elif mode == 2:
        # q_off = q_proxy conj(q_dev)
        _qmul(cs[CS_PPOSE + 3], cs[CS_PPOSE + 4], cs[CS_PPOSE + 5], cs[CS_PPOSE + 6],
              dev[3], -dev[4], -dev[5], -dev[6], cp, CP_QOFF)
        qn = math.sqrt(cp[CP_QOFF] ** 2 + cp[CP_QOFF + 1] ** 2 + cp[CP_QOFF + 2] ** 2 + cp[CP_QOFF + 3] ** 2)
        for j in range(4):
            cp[CP_QOFF + j] /= qn
    if mode != 0:
        w = cp[CP_QOFF]; x = cp[CP_QOFF + 1]; y = cp[CP_QOFF + 2]; z = cp[CP_QOFF + 3]
        cp[CP_ROFF] = 1.0 - 2.0 * (y * y + z * z)
        cp[CP_ROFF + 1] = 2.0 * (x * y - w * z)
        cp[CP_ROFF + 2] = 2.0 * (x * z + w * y)
        cp[CP_ROFF + 3] = 2.0 * (x * y + w * z)
        cp[CP_ROFF + 4] = 1.0 - 2.0 * (x * x + z * z)
        cp[CP_ROFF + 5] = 2.0 * (y * z - w * x)
        cp[CP_ROFF + 6] = 2.0 * (x * z - w * y)
        cp[CP_ROFF + 7] = 2.0 * (y * z + w * x)
        cp[CP_ROFF + 8] = 1.0 - 2.0 * (x * x + y * y)
    for j in range(3):
        cp[CP_POFF + j] = 0.0
    _rot(cp, CP_ROFF, dev[0], dev[1], dev[2], cs, CS_DPOSE)
    for j in range(3):
        cp[CP_POFF + j] = cs[CS_PPOSE + j] - cs[CS_DPOSE + j]
    _map_device(cp, cs, dev)


@njit(**_JIT)
def _device_in(cp, cs, cc, dev, cmd):
    """Check the device row, map the handle into the world, the speed trip; clear the step's
    wrench rows. Returns RC_NONFINITE (output already zeroed), RC_SPEED or RC_OK."""
    for j in range(13):
        if not math.isfinite(dev[j]):
            return _fault_zero(cs, cc, cmd)
    rc = RC_OK
    _map_device(cp, cs, dev)
    speed = math.sqrt(dev[7] ** 2 + dev[8] ** 2 + dev[9] ** 2)
    wspeed = math.sqrt(dev[10] ** 2 + dev[11] ** 2 + dev[12] ** 2)
    if speed > cp[CP_VMAX] or wspeed > cp[CP_WMAX]:
        cs[CS_TARGET] = 0.0
        cc[CC_SPEED_TRIPS] += 1
        rc = RC_SPEED
    for j in range(6):
        cs[CS_ENV + j] = 0.0
        cs[CS_HAND + j] = 0.0
        cs[CS_FC + j] = 0.0
        cs[CS_CMDW + j] = 0.0
    return rc


@njit(**_JIT)
def _coupling(cp, cs, mode, ax, ay, az, scratch):
    """Position channels: the spring-damper wrench on the proxy (CS_FC) from the device handle
    minus the proxy hand point, world. ``mode`` 0: along the unit axis (ax, ay, az) only;
    1: planar (x, y, rotation about z); 2: spatial (rotation vector of q_dev conj(q_proxy))."""
    ex = cs[CS_DPOSE] - cs[CS_PPOSE]
    ey = cs[CS_DPOSE + 1] - cs[CS_PPOSE + 1]
    ez = cs[CS_DPOSE + 2] - cs[CS_PPOSE + 2]
    evx = cs[CS_DTWIST] - cs[CS_PTWIST]
    evy = cs[CS_DTWIST + 1] - cs[CS_PTWIST + 1]
    evz = cs[CS_DTWIST + 2] - cs[CS_PTWIST + 2]
    erx = 0.0; ery = 0.0; erz = 0.0
    ewx = cs[CS_DTWIST + 3] - cs[CS_PTWIST + 3]
    ewy = cs[CS_DTWIST + 4] - cs[CS_PTWIST + 4]
    ewz = cs[CS_DTWIST + 5] - cs[CS_PTWIST + 5]
    if mode == 0:
        e = ex * ax + ey * ay + ez * az
        ev = evx * ax + evy * ay + evz * az
        ex = e * ax; ey = e * ay; ez = e * az
        evx = ev * ax; evy = ev * ay; evz = ev * az
        ewx = 0.0; ewy = 0.0; ewz = 0.0
    elif mode == 1:
        thd = 2.0 * math.atan2(cs[CS_DPOSE + 6], cs[CS_DPOSE + 3])
        thp = 2.0 * math.atan2(cs[CS_PPOSE + 6], cs[CS_PPOSE + 3])
        erz = _wrap(thd - thp)
        ez = 0.0; evz = 0.0; ewx = 0.0; ewy = 0.0
    else:
        pw = cs[CS_PPOSE + 3]; px = cs[CS_PPOSE + 4]; py = cs[CS_PPOSE + 5]; pz = cs[CS_PPOSE + 6]
        _qmul(cs[CS_DPOSE + 3], cs[CS_DPOSE + 4], cs[CS_DPOSE + 5], cs[CS_DPOSE + 6],
              pw, -px, -py, -pz, scratch, 0)
        qw = scratch[0]; qx = scratch[1]; qy = scratch[2]; qz = scratch[3]
        if qw < 0.0:
            qw = -qw; qx = -qx; qy = -qy; qz = -qz
        vn = math.sqrt(qx * qx + qy * qy + qz * qz)
        if vn > 1e-12:
            ang = 2.0 * math.atan2(vn, qw)
            erx = ang * qx / vn; ery = ang * qy / vn; erz = ang * qz / vn
    kt = cp[CP_KT]; bt = cp[CP_BT]; kr = cp[CP_KR]; br = cp[CP_BR]
    cs[CS_FC] = kt * ex + bt * evx
    cs[CS_FC + 1] = kt * ey + bt * evy
    cs[CS_FC + 2] = kt * ez + bt * evz
    cs[CS_FC + 3] = kr * erx + br * ewx
    cs[CS_FC + 4] = kr * ery + br * ewy
    cs[CS_FC + 5] = kr * erz + br * ewz


@njit(**_JIT)
def _hand_channel(cp, cs, cc, dev, ctype):
    """The wrench on the proxy at the hand point (CS_HAND): the measured hand wrench (four-channel
    force channel; skipped and counted when the device has no finite reading) plus CS_FC."""
    hg = 0.0
    if ctype == CTRL_FOUR_CHANNEL:
        hg = cp[CP_HG]
        have = True
        for j in range(6):
            if not math.isfinite(dev[13 + j]):
                have = False
        if not have:
            hg = 0.0
            cc[CC_HAND_MISSING] += 1
    if hg != 0.0:
        _rot(cp, CP_ROFF, dev[13], dev[14], dev[15], cs, CS_HAND)
        _rot(cp, CP_ROFF, dev[16], dev[17], dev[18], cs, CS_HAND + 3)
        for j in range(6):
            cs[CS_HAND + j] *= hg
    for j in range(6):
        cs[CS_HAND + j] += cs[CS_FC + j]


@njit(**_JIT)
def _command_out(cp, cs, cc, cmd, ctype, rc, dev):
    """Controller output (CS_CMDW, world) -> device frame -> the passivity layer (``passivity.limit``,
    with the handle's twist and the hand's measured wrench from ``dev``) -> safety filter.
    Returns RC_*."""
    if ctype == CTRL_FOUR_CHANNEL:
        for j in range(6):
            cs[CS_CMDW + j] = cp[CP_EG] * cs[CS_ENV + j] - cs[CS_FC + j]
    elif ctype == CTRL_COUPLER:
        for j in range(6):
            cs[CS_CMDW + j] = -cs[CS_FC + j]
    else:
        for j in range(6):
            cs[CS_CMDW + j] = cs[CS_ENV + j]
    _rot_t(cp, CP_ROFF, cs[CS_CMDW], cs[CS_CMDW + 1], cs[CS_CMDW + 2], cmd, 0)
    _rot_t(cp, CP_ROFF, cs[CS_CMDW + 3], cs[CS_CMDW + 4], cs[CS_CMDW + 5], cmd, 3)
    # the passivity layer under the controller, before the safety filter (which then bounds every
    # step of what the layer asked by its rate limit)
    pv.limit(cp[CP_TANK:CP_TANK + pv.NTP], cs[CS_TANK:CS_TANK + pv.NTS], cc[CC_TANK:CC_TANK + pv.NTC], cmd,
             dev[7:13], dev[13:19], cs[CS_SAFETY + sf.SS_PREV:CS_SAFETY + sf.SS_PREV + 6],
             cp[CP_SAFETY + sf.SP_FRATE], cp[CP_SAFETY + sf.SP_TRATE])
    src = _safety(cp, cs, cc, cmd)
    if src != RC_OK:
        return src
    return rc


@njit(**_JIT)
def _env_from_state(kind, par, st, cs):
    """The model's environment wrench (S_FENV, in the tool's coordinates) as a world wrench."""
    if kind == TOOL_1DOF:
        for j in range(3):
            cs[CS_ENV + j] = st[S_FENV] * par[P_AXIS + j]
    else:
        hand_to_world(kind == TOOL_PLANAR, st, S_FENV, cs, CS_ENV)


@njit(**_JIT)
def _hand_in(kind, par, cs, hand):
    """The hand wrench (CS_HAND, world) reduced to the tool's hand space: 1dof along the axis,
    planar fx, fy, tau_z, spatial all six; the inverse of ``_env_from_state``."""
    if kind == TOOL_1DOF:
        hand[0] = (cs[CS_HAND] * par[P_AXIS] + cs[CS_HAND + 1] * par[P_AXIS + 1]
                   + cs[CS_HAND + 2] * par[P_AXIS + 2])
    elif kind == TOOL_PLANAR:
        hand[0] = cs[CS_HAND]
        hand[1] = cs[CS_HAND + 1]
        hand[2] = cs[CS_HAND + 5]
    else:
        for j in range(6):
            hand[j] = cs[CS_HAND + j]


@njit(**_JIT)
def _ramp_slide(cp, cs, dev, mode, ctype):
    """While the force ramps in after an engagement (CS_SLIDE), re-index every step; the slide
    ends once the gain is whole. Direct coupling has no spring to keep relaxed."""
    if cs[CS_SLIDE] != 0.0:
        if cs[CS_GAIN] >= 1.0 or ctype == CTRL_DIRECT or cs[CS_DRIVE] == 0.0:
            cs[CS_SLIDE] = 0.0
        else:
            _slide(cp, cs, dev, mode)


@njit(**_JIT)
def _coupling_to_model(cp, cs, par, ctype):
    """Hand the model the coupling's spring-damper on the proxy's hand point (``_coupling``), so
    its implicit step takes it in; no spring while the slide re-indexes it every step (it never
    stretches). Direct coupling has none, and its model steps explicitly: the device sets the
    proxy every step, so the model integrates nothing and renders the penalty of the device's
    own state (the intermediate representation as Berkelman's)."""
    on = 0.0 if ctype == CTRL_DIRECT else 1.0
    if ctype == CTRL_DIRECT:
        par[P_INTEG] = INTEG_EXPLICIT
    spring = 0.0 if cs[CS_SLIDE] != 0.0 else on
    # the deformation recovery is an active element: it slows with the passivity layer's last
    # limiting factor and stops when the tank is empty (``passivity``; 0 with the layer off)
    par[P_REC_CUT] = cs[CS_TANK + pv.TS_BETA]
    par[P_CPL_KT] = spring * cp[CP_KT]
    par[P_CPL_BT] = on * cp[CP_BT]
    par[P_CPL_KR] = spring * cp[CP_KR]
    par[P_CPL_BR] = on * cp[CP_BR]


@njit(**_JIT)
def _diverged(cs, cnt, rc):
    """The model flagged its integration as diverged (a velocity flipping every step without
    decaying for DIVERGE_STEPS steps): the force it renders is the instability's, not the
    contact's. The step it is flagged the gain's target drops to zero and RC_DIVERGED is
    returned (lifecycle.FAULT_POLICY: fade, re-arm: the proxy restarts at rest, and is flagged
    again if it still diverges), unless the step already had a fault of its own (the target
    drops all the same)."""
    if cnt[K_OSC_RUN] != DIVERGE_STEPS:
        return rc
    cs[CS_TARGET] = 0.0
    return RC_DIVERGED if rc == RC_OK else rc


@njit(**_JIT)
def _coupling_from_model(kind, par, st, cs):
    """The coupling wrench at the end of the model's implicit step (``S_FCPL``: what its motion
    changed), so the device gets the reaction of what the proxy felt."""
    if kind == TOOL_1DOF:
        for j in range(3):
            cs[CS_FC + j] += st[S_FCPL] * par[P_AXIS + j]
    elif kind == TOOL_PLANAR:
        cs[CS_FC] += st[S_FCPL]
        cs[CS_FC + 1] += st[S_FCPL + 1]
        cs[CS_FC + 5] += st[S_FCPL + 2]
    else:
        for j in range(6):
            cs[CS_FC + j] += st[S_FCPL + j]


@njit(**_JIT)
def haptic_step(cp, cs, cc, dev, cmd, active, kind, par, st, C, CI, cnt, wk, hand, R, c):
    """One haptic step after the device read. ``dev``: device state row (see devices.base);
    ``cmd`` (6): output, device frame. ``active``: a session has engaged the model.
    ``hand`` (6), ``R`` (3x3), ``c`` (3): scratch. Returns RC_*."""
    cc[CC_STEPS] += 1
    _port_in(cp, cs, dev)
    rc = _device_in(cp, cs, cc, dev, cmd)
    if rc == RC_NONFINITE:
        return rc
    ctype = int(cp[CP_TYPE])
    if active:
        proxy_hand_state(kind, par, st, R, c, cs, CS_PPOSE)
        mode = 0 if kind == TOOL_1DOF else (1 if kind == TOOL_PLANAR else 2)
        _ramp_slide(cp, cs, dev, mode, ctype)
        _coupling(cp, cs, mode, par[P_AXIS], par[P_AXIS + 1], par[P_AXIS + 2], hand)
        if cs[CS_DRIVE] == 0.0:
            # held: a device that renders nothing (idle, fading, fault) must not push the proxy
            # into what it touches (a penetration stored there would be released at the next
            # engagement); the environment wrench stays the last one computed
            _env_from_state(kind, par, st, cs)
            return _command_out(cp, cs, cc, cmd, ctype, rc, dev)
        if ctype == CTRL_DIRECT:
            # the device is the tool: proxy COM state from the handle (hand point = tool origin)
            _rigid_pose(kind, par, st, R, c)
            if kind == TOOL_1DOF:
                s = 0.0
                v = 0.0
                for j in range(3):
                    s += (cs[CS_DPOSE + j] - par[P_HAND + j] - par[P_ORIGIN + j]) * par[P_AXIS + j]
                    v += cs[CS_DTWIST + j] * par[P_AXIS + j]
                st[S_Q] = s
                st[S_QD] = v
            elif kind == TOOL_PLANAR:
                th = st[S_Q + 2] + _wrap(2.0 * math.atan2(cs[CS_DPOSE + 6], cs[CS_DPOSE + 3]) - st[S_Q + 2])
                ct = math.cos(th); sn = math.sin(th)
                hx = ct * par[P_HAND] - sn * par[P_HAND + 1]
                hy = sn * par[P_HAND] + ct * par[P_HAND + 1]
                w = cs[CS_DTWIST + 5]
                st[S_Q] = cs[CS_DPOSE] - hx
                st[S_Q + 1] = cs[CS_DPOSE + 1] - hy
                st[S_Q + 2] = th
                st[S_QD] = cs[CS_DTWIST] + w * hy
                st[S_QD + 1] = cs[CS_DTWIST + 1] - w * hx
                st[S_QD + 2] = w
            else:
                for j in range(4):
                    st[S_Q + 3 + j] = cs[CS_DPOSE + 3 + j]
                _rigid_pose(kind, par, st, R, c)
                hx = R[0, 0] * par[P_HAND] + R[0, 1] * par[P_HAND + 1] + R[0, 2] * par[P_HAND + 2]
                hy = R[1, 0] * par[P_HAND] + R[1, 1] * par[P_HAND + 1] + R[1, 2] * par[P_HAND + 2]
                hz = R[2, 0] * par[P_HAND] + R[2, 1] * par[P_HAND + 1] + R[2, 2] * par[P_HAND + 2]
                wx = cs[CS_DTWIST + 3]; wy = cs[CS_DTWIST + 4]; wz = cs[CS_DTWIST + 5]
                st[S_Q] = cs[CS_DPOSE] - hx
                st[S_Q + 1] = cs[CS_DPOSE + 1] - hy
                st[S_Q + 2] = cs[CS_DPOSE + 2] - hz
                # v_com = v_hand - w x r_h
                st[S_QD] = cs[CS_DTWIST] - (wy * hz - wz * hy)
                st[S_QD + 1] = cs[CS_DTWIST + 1] - (wz * hx - wx * hz)
                st[S_QD + 2] = cs[CS_DTWIST + 2] - (wx * hy - wy * hx)
                st[S_QD + 3] = wx
                st[S_QD + 4] = wy
                st[S_QD + 5] = wz
        else:
            _hand_channel(cp, cs, cc, dev, ctype)
        _hand_in(kind, par, cs, hand)
        _coupling_to_model(cp, cs, par, ctype)
        if step_rigid(kind, par, st, C, CI, cnt, wk, hand) != 0:
            return _fault_zero(cs, cc, cmd)
        rc = _diverged(cs, cnt, rc)
        _coupling_from_model(kind, par, st, cs)
        _env_from_state(kind, par, st, cs)
        proxy_hand_state(kind, par, st, R, c, cs, CS_PPOSE)
        return _command_out(cp, cs, cc, cmd, ctype, rc, dev)
    return _command_out(cp, cs, cc, cmd, -1, rc, dev)  # no model: only the (fading) safety filter on zero


@njit(**_JIT)
def haptic_step_linkage(cp, cs, cc, dev, cmd, par, lmeta, lk, lki, st, C, CI, cnt, wk, lw, hand):
    """``haptic_step`` for an engaged linkage tool (a kernel of its own, so rigid tools' steps
    never branch on linkages): the device maps onto the held link's frame (its origin is the
    hand point), the controller is the same four-channel or coupler (``direct`` is refused for
    linkages by the config: the device cannot be a whole chain), the model step is
    ``linkage.step_linkage``. Returns RC_*."""
    cc[CC_STEPS] += 1
    _port_in(cp, cs, dev)
    rc = _device_in(cp, cs, cc, dev, cmd)
    if rc == RC_NONFINITE:
        return rc
    planar = lmeta[LM_PLANAR] == 1
    kind = TOOL_PLANAR if planar else TOOL_SPATIAL
    ctype = int(cp[CP_TYPE])
    hand_state_linkage(lmeta, lk, lki, st, lw, cs, CS_PPOSE)
    _ramp_slide(cp, cs, dev, 1 if planar else 2, ctype)
    _coupling(cp, cs, 1 if planar else 2, 1.0, 0.0, 0.0, hand)
    if cs[CS_DRIVE] == 0.0:
        _env_from_state(kind, par, st, cs)
        return _command_out(cp, cs, cc, cmd, ctype, rc, dev)
    _hand_channel(cp, cs, cc, dev, ctype)
    # the hand wrench in the tool's hand space, at the held link's frame origin
    _hand_in(kind, par, cs, hand)
    _coupling_to_model(cp, cs, par, ctype)
    if step_linkage(par, lmeta, lk, lki, st, C, CI, cnt, wk, lw, hand) != 0:
        return _fault_zero(cs, cc, cmd)
    rc = _diverged(cs, cnt, rc)
    _coupling_from_model(kind, par, st, cs)
    _env_from_state(kind, par, st, cs)
    hand_state_linkage(lmeta, lk, lki, st, lw, cs, CS_PPOSE)
    return _command_out(cp, cs, cc, cmd, ctype, rc, dev)


@njit(**_JIT)
def fade_only(cp, cs, cc, cmd):
    """Safety filter alone on a zero command (the loop's step when no device data is usable)."""
    for j in range(6):
        cmd[j] = 0.0
    return _safety(cp, cs, cc, cmd)


#: ``tool_q_from_pose`` kinds: the rigid tool kinds, then a linkage's root on each device kind
QK_1DOF = 0
QK_PLANAR = 1
QK_SPATIAL = 2
QK_LINKAGE_PLANAR = 3
QK_LINKAGE_SPATIAL = 4
Q_KINDS = {"1dof": QK_1DOF, "planar": QK_PLANAR, "spatial": QK_SPATIAL, "linkage-planar": QK_LINKAGE_PLANAR,
           "linkage-spatial": QK_LINKAGE_SPATIAL}


@njit(**_JIT)
def tool_q_from_pose(qk, pose, com, axis, joints, out):
    """The engine tool's configuration q (like the model's ``q``) from its tool-frame pose (x y z
    qw qx qy qz) at each model update: a rigid tool's COM pose (``com``: the COM in the tool
    frame; 1dof: the coordinate along ``axis``), a linkage's root-frame pose then ``joints``.
    The quaternion is normalised (a zero one reads as the identity). Writes ``out``."""
    px = pose[0]; py = pose[1]; pz = pose[2]
    w = pose[3]; x = pose[4]; y = pose[5]; z = pose[6]
    n = math.sqrt(w * w + x * x + y * y + z * z)
    if n > 0.0:
        w /= n; x /= n; y /= n; z /= n
    else:
        w = 1.0; x = 0.0; y = 0.0; z = 0.0
    if qk == QK_LINKAGE_PLANAR or qk == QK_LINKAGE_SPATIAL:
        if qk == QK_LINKAGE_PLANAR:
            out[0] = px; out[1] = py; out[2] = 2.0 * math.atan2(z, w)
            o = 3
        else:
            out[0] = px; out[1] = py; out[2] = pz; out[3] = w; out[4] = x; out[5] = y; out[6] = z
            o = 7
        for j in range(joints.shape[0]):
            out[o + j] = joints[j]
        return
    cx = com[0]; cy = com[1]; cz = com[2]
    if qk == QK_1DOF:
        out[0] = (px + cx) * axis[0] + (py + cy) * axis[1] + (pz + cz) * axis[2]
        return
    # c = p + R com
    rx = (1 - 2 * (y * y + z * z)) * cx + 2 * (x * y - w * z) * cy + 2 * (x * z + w * y) * cz
    ry = 2 * (x * y + w * z) * cx + (1 - 2 * (x * x + z * z)) * cy + 2 * (y * z - w * x) * cz
    rz = 2 * (x * z - w * y) * cx + 2 * (y * z + w * x) * cy + (1 - 2 * (x * x + y * y)) * cz
    if qk == QK_PLANAR:
        out[0] = px + rx; out[1] = py + ry; out[2] = 2.0 * math.atan2(z, w)
        return
    out[0] = px + rx; out[1] = py + ry; out[2] = pz + rz
    out[3] = w; out[4] = x; out[5] = y; out[6] = z


class Controller:
    """Owns the controller/safety arrays; ``configure`` from validated settings."""

    def __init__(self, settings, device_kind: str, device_limits=None) -> None:
        from .devices.base import KIND_WRENCH_MASK

        ctl = settings["controller"]
        saf = settings["safety"]
        dt = settings.period_ns * 1e-9
        self.device_kind = device_kind
        self.cp = np.zeros(NCP)
        self.cs = np.zeros(NCS)
        self.cc = np.zeros(NCC, dtype=np.int64)
        self.cmd = np.zeros(6)
        self.hand = np.zeros(6)
        self.R = np.zeros((3, 3))
        self.c = np.zeros(3)
        cp = self.cp
        cp[CP_TYPE] = CONTROLLER_IDS[ctl["type"]]
        cp[CP_KT] = ctl["stiffness_n_per_m"]
        cp[CP_BT] = ctl["damping_n_s_per_m"]
        cp[CP_KR] = ctl["rot_stiffness_n_m_per_rad"]
        cp[CP_BR] = ctl["rot_damping_n_m_s_per_rad"]
        cp[CP_HG] = ctl["hand_gain"]
        cp[CP_EG] = ctl["env_gain"]
        fmax, tmax = saf["max_force_n"], saf["max_torque_n_m"]
        faxis = taxis = None
        vmax, wmax = saf["max_speed_m_per_s"], saf["max_angular_speed_rad_per_s"]
        if device_limits is not None:  # never command more than the hardware can take
            # the configured cap is on the norm; a device declares its own norm cap (its motors
            # saturate together) and a cap per axis (a motor's own limit), each kept
            fmax = min(fmax, getattr(device_limits, "max_force_norm_n", math.inf))
            tmax = min(tmax, getattr(device_limits, "max_torque_norm_n_m", math.inf))
            faxis = device_limits.max_force_n
            taxis = device_limits.max_torque_n_m
            vmax = min(vmax, device_limits.max_speed_m_per_s)
            wmax = min(wmax, device_limits.max_angular_speed_rad_per_s)
        cp[CP_VMAX] = vmax
        cp[CP_WMAX] = wmax
        #: the safety filter's parameters (a view: the kernels read them in ``cp``)
        self.sp = cp[CP_SAFETY:CP_SAFETY + sf.NSP]
        sf.set_parameters(self.sp, max_force_n=fmax, max_torque_n_m=tmax, max_force_axis_n=faxis,
                          max_torque_axis_n_m=taxis, force_rate_n_per_step=saf["force_rate_n_per_s"] * dt,
                          torque_rate_n_m_per_step=saf["torque_rate_n_m_per_s"] * dt, fade_per_step=dt / saf["fade_s"],
                          ramp_per_step=dt / saf["ramp_in_s"], mask=KIND_WRENCH_MASK[device_kind])
        #: the passivity layer's parameters and state (views: the kernels read them in ``cp``/``cs``)
        self.tp = cp[CP_TANK:CP_TANK + pv.NTP]
        self.ts = self.cs[CS_TANK:CS_TANK + pv.NTS]
        pas = settings["passivity"]
        pv.set_parameters(self.tp, enabled=pas["enabled"], initial_budget_j=pas["initial_budget_j"],
                          max_tank_j=pas["max_tank_j"], low_level_j=pas["low_level_j"],
                          **dict(zip(("moving_mass_kg", "moving_inertia_kg_m2"),
                                     pv.moving_figures(pas["moving_mass_kg"], pas["moving_inertia_kg_m2"]))),
                          **dict(zip(("device_damping_n_s_per_m", "device_rot_damping_n_m_s_per_rad"),
                                     pv.damping_figures(pas["device_damping_n_s_per_m"],
                                                        pas["device_rot_damping_n_m_s_per_rad"],
                                                        share=pas["damping_credit"]))),
                          period_s=dt, engine_grants=pas["engine_grants"], input_credit=pas["input_credit"])
        pv.reset(self.tp, self.ts)
        self._moving_config = (pas["moving_mass_kg"], pas["moving_inertia_kg_m2"])
        #: the heavy-tool rule's inputs (``fit_tool``): the configured coupling, the contacts, the
        #: handle's figures (its mass from ``set_moving_figures``)
        mdl = settings["model"]
        self._heavy = dict(coupling_n_per_m=float(ctl["stiffness_n_per_m"]), coupling_n_s_per_m=float(ctl["damping_n_s_per_m"]),
                           env_gain=float(ctl["env_gain"]) if ctl["type"] == "four_channel" else 0.0,
                           contact_n_per_m=float(mdl["stiffness_n_per_m"]), contact_n_s_per_m=float(mdl["damping_n_s_per_m"]),
                           max_contacts=int(mdl["capacity"]), device_damping_n_s_per_m=float(pas["device_damping_n_s_per_m"]),
                           device_mass_kg=float(pas["moving_mass_kg"]) if pas["moving_mass_kg"] > 0.0 else None)
        self._heavy_rot = dict(coupling_n_m_per_rad=float(ctl["rot_stiffness_n_m_per_rad"]),
                               coupling_n_m_s_per_rad=float(ctl["rot_damping_n_m_s_per_rad"]),
                               env_gain=self._heavy["env_gain"],
                               contact_damping_per_stiffness_s=float(mdl["damping_n_s_per_m"]) / float(mdl["stiffness_n_per_m"]),
                               device_rot_damping_n_m_s_per_rad=float(pas["device_rot_damping_n_m_s_per_rad"]),
                               device_inertia_kg_m2=(float(pas["moving_inertia_kg_m2"]) if pas["moving_inertia_kg_m2"] > 0.0
                                                     else None))
        self._rate_hz = 1.0 / dt
        self._damping_cap = math.inf
        self._rot_damping_cap = math.inf
        #: the last ``fit_tool``'s rotational damping and why it falls short ("" if not)
        self.fit_rot = (float(ctl["rot_damping_n_m_s_per_rad"]), "")
        self._fitted: dict[float, tuple[float, str]] = {}
        #: the last ``fit_tool``: the tool's mass, the damping set, and why it falls short ("" if not)
        self.fit = (0.0, float(ctl["damping_n_s_per_m"]), "")
        self._damping_config = (pas["device_damping_n_s_per_m"], pas["device_rot_damping_n_m_s_per_rad"])
        self._damping_share = float(pas["damping_credit"])
        #: the device's position frozen under force (``devices.frozen``; the tick runs the watch)
        self.frozen_s = saf["frozen_s"]
        self.frozen_force_n = fz.min_force_n(saf["frozen_force_n"], fmax)
        self.watch_frozen(True)
        self.set_offset(np.eye(3), np.zeros(3), np.array([1.0, 0.0, 0.0, 0.0]))
        self.cs[CS_DRIVE] = 1.0  # a bare kernel user drives its model; the loop holds until engaged
        self.cs[CS_DPOSE + 3] = 1.0
        self.cs[CS_PPOSE + 3] = 1.0

    controller_type = ArrayInt("cp", CP_TYPE, doc="The controller's id (``CONTROLLER_IDS``).")
    force_cap_n = ArrayFloat("cp", CP_SAFETY + sf.SP_FMAX,
                             doc="Cap on the force's norm, N (the device's limit when lower).")
    torque_cap_n_m = ArrayFloat("cp", CP_SAFETY + sf.SP_TMAX, doc="Cap on the torque's norm, N m.")
    force_rate_n_per_step = ArrayFloat("cp", CP_SAFETY + sf.SP_FRATE,
                                       doc="Largest change of the force vector per step, N.")

    def set_moving_figures(self, info) -> None:
        """The passivity layer's moving mass and inertia, and the damping that feeds its tank, from
        the device's ``DeviceInfo`` where the config sets none (``passivity.moving_figures``,
        ``passivity.damping_figures``); the heavy-tool rule's handle mass likewise
        (the config's ``passivity.moving_mass_kg``, else the device's stated figure, else none: the
        rule then keeps the configured damping) and the most damping the device renders
        (``devices.safe.gain_limits``)."""
        self.tp[pv.TP_MASS], self.tp[pv.TP_INERTIA] = pv.moving_figures(*self._moving_config, info)
        self.tp[pv.TP_BDEV], self.tp[pv.TP_BRDEV] = pv.damping_figures(*self._damping_config, info,
                                                                       share=self._damping_share)
        if self._heavy["device_mass_kg"] is None:
            m = getattr(info, "moving_mass_kg", None)
            self._heavy["device_mass_kg"] = float(m) if m else None
        i_small = self._heavy_rot["device_inertia_kg_m2"] or getattr(info, "moving_inertia_kg_m2", None)
        if self._heavy_rot["device_inertia_kg_m2"] is None:
            # the rotational rule's damping grows with the handle's moment: its largest where stated
            i = getattr(info, "moving_inertia_max_kg_m2", None) or i_small
            self._heavy_rot["device_inertia_kg_m2"] = float(i) if i else None
        if info is not None and int(self.cp[CP_TYPE]) != CTRL_DIRECT:
            for lim in safe.gain_limits(info, self._rate_hz, CONTROLLERS[int(self.cp[CP_TYPE])]):
                if lim.key == "controller.damping_n_s_per_m":
                    self._damping_cap = lim.limit
                if lim.key == "controller.rot_damping_n_m_s_per_rad":
                    self._rot_damping_cap = lim.limit
        if i_small:  # the handle's own (smallest) moment bounds a rotational damper as its mass does a damper
            self._rot_damping_cap = min(self._rot_damping_cap, device_damper_limit_n_s_per_m(float(i_small), self._rate_hz))
        self._fitted.clear()

    def fit_tool(self, tool) -> tuple[float, float, str]:
        """Set the coupling's translational damping for a session's rigid ``tool`` (a ``ToolSpec``)
        by ``stability.coupling_damping_for_tool``: the configured damping, raised for a heavy tool
        until the four-channel loop at rest on 1 to ``model.capacity`` contacts is stable with the
        rule's margin. Capped at what the device renders (``_damping_cap``): a tool that needs more,
        or that no damping steadies, gets the cap and a reason (logged; ``fit``). A linkage, or no
        tool, keeps the configured damping. At engagement (``loop_lifecycle``), not per step: the
        rule's search costs about 20 Hurwitz checks (under a millisecond), and is kept per mass. Returns ``fit``: (mass,
        damping, reason)."""
        h = self._heavy
        b = h["coupling_n_s_per_m"]
        br = self._heavy_rot["coupling_n_m_s_per_rad"]
        self.cp[CP_BR] = br
        self.fit_rot = (br, "")
        if tool is None or getattr(tool, "kind", "linkage") == "linkage" or int(self.cp[CP_TYPE]) == CTRL_DIRECT:
            self.cp[CP_BT] = b
            self.fit = (0.0, b, "")
            return self.fit
        self._fit_rot(tool)
        mass = float(tool.mass_kg)
        got = self._fitted.get(mass)
        if got is None:
            want = self._damping_for(mass)
            why = ""
            if want is None or want > self._damping_cap:
                why = (f"tool.mass_kg: {mass:g} kg needs more coupling damping than the device renders "
                       f"({self._damping_cap:g} N s/m) to rest stably")
                want = min(self._damping_cap, max(b, self._damping_cap if want is None else want))
            got = (want, why)
            self._fitted[mass] = got
            if why:
                log.warning("%s", why)
        self.cp[CP_BT] = got[0]
        self.fit = (mass, got[0], got[1])
        return self.fit

    def _fit_rot(self, tool) -> None:
        """The rotational half of ``fit_tool``: ``stability.rot_coupling_damping_for_tool`` about the
        tool's principal moments (a planar tool's I_zz; none for a 1dof tool or device), capped at
        what the device renders (its figure; its moment x rate)."""
        if tool.kind == "1dof" or self.device_kind == "1dof":
            return
        inertia = np.asarray(tool.inertia_kg_m2, dtype=np.float64)
        moments = (float(inertia[2, 2]),) if tool.kind == "planar" else tuple(float(v) for v in np.linalg.eigvalsh(inertia))
        got = self._fitted.get(moments)
        if got is None:
            want = rot_coupling_damping_for_tool(moments, **self._heavy_rot)
            why = ""
            cap = self._rot_damping_cap
            if want is None or want > cap:
                why = (f"tool.inertia_kg_m2: {max(moments):g} kg m^2 needs more rotational coupling damping than "
                       f"the device renders ({cap:g} N m s/rad) to rest stably")
                want = min(cap, max(self._heavy_rot["coupling_n_m_s_per_rad"], cap if want is None else want))
                log.warning("%s", why)
            got = (want, why)
            self._fitted[moments] = got
        self.cp[CP_BR] = got[0]
        self.fit_rot = got

    def _damping_for(self, mass_kg: float) -> float | None:
        return coupling_damping_for_tool(float(mass_kg), **self._heavy)

    def hello_refusal(self, tool) -> str:
        """Why a Hello's rigid ``tool`` is to be refused, or "": the coupling damping its rest loop
        needs (``fit_tool``'s rule) is more than the device renders (``_damping_cap``). The reason
        names the field, the damping needed and the largest mass below it that works (the
        smallest failing mass, bisected in log mass from the lightest tool, which keeps the
        configured damping, to ``tool``'s), within a Reject's 120 characters. For the handshake's
        check (``ProtocolSide.check_hello``); Python, and only a refused tool costs a search."""
        if tool is None or getattr(tool, "kind", "linkage") == "linkage" or int(self.cp[CP_TYPE]) == CTRL_DIRECT:
            return ""
        mass = float(tool.mass_kg)
        cap = self._damping_cap

        def fails(m: float) -> bool:
            b = self._damping_for(m)
            return b is None or b > cap

        if not fails(mass):
            return ""
        lo = 1e-3
        if fails(lo):
            return ""  # the configured damping itself is beyond the device (the config's research override)
        hi = mass
        for _ in range(30):
            mid = math.sqrt(lo * hi)
            if fails(mid):
                hi = mid
            else:
                lo = mid
        need = self._damping_for(mass)
        needs = "more coupling damping than any" if need is None else f"{need:.3g} N s/m of coupling damping"
        step = 10.0 ** (math.floor(math.log10(lo)) - 2)  # three digits, rounded down: the value works
        most = math.floor(lo / step) * step
        return (f"tool.mass_kg: {mass:g} kg needs {needs} to rest, the device renders {cap:.3g}; "
                f"at most {float(f'{most:.3g}'):g} kg")

    def set_offset(self, R_off: np.ndarray, p_off: np.ndarray, q_off: np.ndarray) -> None:
        self.cp[CP_ROFF:CP_ROFF + 9] = np.asarray(R_off, dtype=float).reshape(9)
        self.cp[CP_POFF:CP_POFF + 3] = p_off
        self.cp[CP_QOFF:CP_QOFF + 4] = q_off

    def set_target(self, engaged: bool) -> None:
        self.cs[CS_TARGET] = 1.0 if engaged else 0.0

    def engage(self, *, slide: bool) -> None:
        """Render the model: the gain ramps in (from wherever it is) and the device drives the
        proxy. ``slide``: re-index every step until the gain is whole (see ``_slide``)."""
        cs = self.cs
        cs[CS_TARGET] = 1.0
        cs[CS_DRIVE] = 1.0
        cs[CS_SLIDE] = 1.0 if slide and cs[CS_GAIN] < 1.0 else 0.0

    def hold(self) -> None:
        """Stop rendering: the gain fades to zero and the proxy is held (not driven)."""
        cs = self.cs
        cs[CS_TARGET] = 0.0
        cs[CS_DRIVE] = 0.0
        cs[CS_SLIDE] = 0.0

    driving = ArrayBool("cs", CS_DRIVE, doc="The device drives the proxy (``engage``), or it is held.")

    def skip(self, steps: int) -> None:
        """The loop woke ``steps`` whole periods late and skipped them: the gain moves on as if
        they had run, so a fade reaches zero and a ramp-in completes in their wall-clock times
        (``fade_s``, ``ramp_in_s``), not in a number of steps. The output itself still changes
        only through the kernel's rate limit and fade/ramp bounds, which compare with the last
        command written (so a ramp that the gain finished during a stall still adds force at the
        ramp's slope per command, and a fade still never pushes harder)."""
        self.cs[CS_SKIPPED] += steps

    gain = ArrayFloat("cs", CS_GAIN, doc="Gain of the rendered force, 0..1 (fades and ramps in).")

    def watch_frozen(self, on: bool) -> None:
        """The tick's frozen-position watch on (``safety.frozen_s``) or off (a driver that watches
        its own raw readings). The tick runs it on the raw row, before the mapping, against the
        force written to the device: a held clutch cannot trip it."""
        fz.set_parameters(self.cp, CP_FROZEN, frozen_s=self.frozen_s if on else 0.0, min_force_n=self.frozen_force_n)
        fz.reset(self.cs, CS_FROZEN)

    def cut(self) -> None:
        """The device was disabled (it renders nothing now): the safety filter starts again from
        zero output and zero gain, so whatever comes next ramps in from what the hand feels."""
        sf.reset(self.cs[CS_SAFETY:CS_SAFETY + sf.NSS])

    _COUNTERS = (("steps", CC_STEPS), ("saturated", CC_SATURATED), ("rate_limited", CC_RATE_LIMITED),
                 ("speed_trips", CC_SPEED_TRIPS), ("nonfinite", CC_NONFINITE), ("hand_missing", CC_HAND_MISSING),
                 ("command_nonfinite", CC_CMD_NONFINITE), ("passivity_limited", CC_TANK + pv.TC_LIMITED),
                 ("tank_empty", CC_TANK + pv.TC_EMPTY))

    tank_j = ArrayFloat("cs", CS_TANK + pv.TS_TANK, doc="The passivity layer's tank level, J.")

    def grant(self, energy_j: float) -> float:
        """An engine's declared work on the tool into the tank (``passivity.grant``); the energy added."""
        # compiled by the loop's warm-up (HapticLoop.warm_up), so an update never compiles it
        return float(pv.grant(self.tp, self.ts, float(energy_j)))

    def counters(self) -> dict[str, int]:
        out = {n: int(self.cc[i]) for n, i in self._COUNTERS}
        out["nonfinite"] += out["command_nonfinite"]  # any non-finite value before the device
        return out


# ------------------------------------------------------------------------------ mapping
def quat_mul(a, b) -> np.ndarray:
    """Hamilton product (w x y z). Plain Python: it runs at engagement, where calling a kernel
    with a new signature would compile inside the loop."""
    aw, ax, ay, az = (float(v) for v in a)
    bw, bx, by, bz = (float(v) for v in b)
    return np.array([aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw])


def index_offset(kind: str, device_pose: np.ndarray, proxy_pose: np.ndarray, tool_axis=None,
                 device_axis=None):
    """Offset (R_off, p_off, q_off) that maps the device handle pose onto the proxy hand pose.

    planar: a rotation about +z only; 1dof: the rotation taking the device axis onto the tool
    axis (no rotation if they agree); spatial: the full rotation.
    """
    pd = np.asarray(device_pose[:3], dtype=float)
    qd = np.asarray(device_pose[3:7], dtype=float)
    pp = np.asarray(proxy_pose[:3], dtype=float)
    qp = np.asarray(proxy_pose[3:7], dtype=float)
    if kind == "planar":
        th = 2 * math.atan2(qp[3], qp[0]) - 2 * math.atan2(qd[3], qd[0])
        q_off = np.array([math.cos(th / 2), 0.0, 0.0, math.sin(th / 2)])
    elif kind == "spatial":
        q_off = quat_mul(qp, qd * np.array([1.0, -1.0, -1.0, -1.0]))
        q_off /= np.linalg.norm(q_off)
    else:
        a = np.asarray(device_axis if device_axis is not None else (1.0, 0.0, 0.0), dtype=float)
        b = np.asarray(tool_axis if tool_axis is not None else a, dtype=float)
        a /= np.linalg.norm(a)
        b /= np.linalg.norm(b)
        v = np.cross(a, b)
        cw = 1.0 + float(a @ b)
        if cw < 1e-9:  # opposite axes: half turn about any perpendicular
            perp = np.cross(a, [1.0, 0.0, 0.0])
            if np.linalg.norm(perp) < 1e-6:
                perp = np.cross(a, [0.0, 1.0, 0.0])
            perp /= np.linalg.norm(perp)
            q_off = np.array([0.0, *perp])
        else:
            q_off = np.array([cw, *v])
            q_off /= np.linalg.norm(q_off)
    R_off = quat_to_matrix(q_off)
    p_off = pp - R_off @ pd
    return R_off, p_off, q_off
