"""Workspace mapping between a device's frame and the scene's, with a clutch: two small kernels
the haptic tick calls around the controller, and the ``[device]`` keys that configure them.

The two calls (numba, no allocation, over the preallocated mapping array ``m``, float64[NM]):

- ``map_state(row, m)``, right after the device is read: the state row (float64[DEV_NSTATE]),
  device frame, becomes the scene's, in place;
- ``map_command(cmd, m, out)``, right before the device is written: the scene's wrench ``cmd``
  (float64[6], the safety filter's output, left untouched) becomes the device's in ``out``.

The haptic tick (``server/tick.py``) makes both calls itself when the loop's device has a mapping
(``TK_MAPPED``; ``m`` is ``TickArrays.map`` and ``out`` its block ``M_CMD``): the array and the
clutch's state in it are the loop's, shared with the :class:`~.mapped.MappedDevice` that holds it.

Contract
--------
Parameters: the scale ``s`` > 0 (scene metres per device metre: a 7.5 cm omega workspace onto a
1 m scene is ``s = 13.3``), the offset ``o`` (scene, m), the frame rotation ``R`` (unit
quaternion ``q_R``, device frame -> scene frame), the clutch button ``b`` (-1: none) and the
clutch's ramp ``T_r`` [s].

``map_state`` (device -> scene)::

    p_s = o + s R p_d                   position of the handle
    q_s = q_o * q_d                     its orientation (q_o = q_R until a clutch re-indexes it)
    v_s = s R v_d,   w_s = R w_d        its twist
    F_s = s R F_d,   t_s = R t_d        the hand's wrench, as a force sensor reads it (NaN stays NaN)
    time, buttons, gripper              unchanged

``map_command`` (scene -> device)::

    F_d = g R^T F_s / s,   t_d = g R^T t_s        g: the clutch's gain, 1 outside a clutch

**The force rule.** Positions scale by ``s``, forces by ``1 / s``. A spring ``K`` of the scene
(the coupling, a contact) is then felt as ``K`` at the device: ``F_d / x_d = (F_s / s) / (x_s /
s) = K``, and a damper ``B`` as ``B``; so what the device renders stably bounds the configured
gains as they are (``server/devices/safe.py`` checks them so), whatever the scale. Power is
scaled by a positive constant, ``F_d . v_d = (F_s . v_s) / s^2`` (with ``g = 1``): what is
passive in the scene stays passive at the hand. Angles are not scaled, so torques are not
either (the rotational gains are felt as configured). In the scene's units, the caps of
``[safety]`` are the scene's: the hand feels at most ``max_force_n / s``, and moves the scene's
tool ``s`` times faster than itself (``safety.max_speed_m_per_s`` is the scene's speed).

**The clutch.** While button ``b`` is held (bit ``b`` of the row's ``buttons``), ``map_state``
reports the scene state frozen where the clutch was pressed (the pose then, zero twist, the
hand's wrench zero where measured), so the proxy is held there, and ``map_command``'s gain ``g``
fades to 0 over ``T_r``: then nothing is rendered and the hand moves the device freely. On
release the mapping re-indexes, ``o' = p_frozen - s R p_d``, ``q_o' = q_frozen * q_d^-1``, so the
scene pose goes on from where it was frozen (no jump), and ``g`` ramps back to 1 over ``T_r``
(``T_r`` = 0: at once): the force comes and goes over ``T_r``, never in one step (no kick).

A device that the mapping must keep planar (``planar``: rotation about +z only, no z offset)
or on its axis (``1dof``: no rotation) is checked by :func:`parse_mapping`.
"""
from __future__ import annotations

import math
from typing import Annotated

import msgspec
import numpy as np
from msgspec import Meta
from numba import njit

from ...protocol.devlink import ROW_COLUMNS, ROW_FLOATS
from . import _check as ck

_JIT = dict(cache=True, nogil=True, error_model="numpy")

# the state row's columns (protocol/devlink.py; base.py takes the same numbers from there)
_C = {c.name: c.start for c in ROW_COLUMNS}
_POSE, _TWIST, _HAND, _BUTTONS = _C["pose"], _C["twist"], _C["hand"], _C["buttons"]

# -- the mapping array m (float64[NM]) -----------------------------------------------------------
M_SCALE = 0        # s, scene m per device m
M_OFF = 1          # 1..3 the offset o, scene [m] (re-indexed at each clutch release)
M_QR = 4           # 4..7 q_R, device frame -> scene frame (w x y z)
M_R = 8            # 8..16 R, row-major (from q_R)
M_QO = 17          # 17..20 q_o, the orientation offset (q_R until a clutch re-indexes it)
M_CLUTCH_BIT = 21  # the clutch button's bit (-1: no clutch)
M_RAMP = 22        # the gain's rise per map_command after a release (1: at once)
M_CLUTCHED = 23    # 1 while the clutch is held
M_FROZEN = 24      # 24..30 the scene pose frozen at the clutch (x y z qw qx qy qz)
M_GAIN = 31        # g, the command's gain
M_CLUTCHES = 32    # clutch presses so far
M_CMD = 34         # 34..39 the device's wrench (device frame): map_command's ``out`` in the tick,
                   # what the device was last written (a held servo tick writes it again)
NM = 40

#: the ``[device]`` keys the mapping takes (the rest of the table is the driver's)
MAPPING_KEYS = ("workspace_scale", "workspace_offset_m", "workspace_rotation", "clutch_button", "clutch_ramp_s")


# ------------------------------------------------------------------------------------- kernels
@njit(**_JIT)
def _qmul(aw, ax, ay, az, bw, bx, by, bz):
    return (aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw)


@njit(**_JIT)
def _rot3(m, x, y, z, out, o, k):
    """``out[o:o+3] = k R (x, y, z)``."""
    r = M_R
    out[o] = k * (m[r] * x + m[r + 1] * y + m[r + 2] * z)
    out[o + 1] = k * (m[r + 3] * x + m[r + 4] * y + m[r + 5] * z)
    out[o + 2] = k * (m[r + 6] * x + m[r + 7] * y + m[r + 8] * z)


@njit(**_JIT)
def _rot3t(m, x, y, z, out, o, k):
    """``out[o:o+3] = k R^T (x, y, z)``."""
    r = M_R
    out[o] = k * (m[r] * x + m[r + 3] * y + m[r + 6] * z)
    out[o + 1] = k * (m[r + 1] * x + m[r + 4] * y + m[r + 7] * z)
    out[o + 2] = k * (m[r + 2] * x + m[r + 5] * y + m[r + 8] * z)


@njit(**_JIT)
def _held(row, m):
    """The clutch button is held in this row (NaN buttons: not held)."""
    bit = int(m[M_CLUTCH_BIT])
    b = row[_BUTTONS]
    if bit < 0 or not (0.0 <= b <= 4294967295.0):
        return False
    return (int(b) >> bit) & 1 == 1


@njit(**_JIT)
def map_state(row, m):
    """The device's state row (device frame) -> the scene's, in place; the clutch (module
    docstring). Returns 1 while clutched, else 0."""
    s = m[M_SCALE]
    held = _held(row, m)
    if held and m[M_CLUTCHED] == 0.0:
        # pressed: freeze the scene pose where the mapping puts the device now
        m[M_CLUTCHED] = 1.0
        m[M_CLUTCHES] += 1.0
        _rot3(m, row[_POSE], row[_POSE + 1], row[_POSE + 2], m, M_FROZEN, s)
        for i in range(3):
            m[M_FROZEN + i] += m[M_OFF + i]
        qw, qx, qy, qz = _qmul(m[M_QO], m[M_QO + 1], m[M_QO + 2], m[M_QO + 3],
                               row[_POSE + 3], row[_POSE + 4], row[_POSE + 5], row[_POSE + 6])
        m[M_FROZEN + 3] = qw
        m[M_FROZEN + 4] = qx
        m[M_FROZEN + 5] = qy
        m[M_FROZEN + 6] = qz
    elif not held and m[M_CLUTCHED] != 0.0:
        # released: re-index so the device maps onto the frozen pose (o' = p_f - s R p_d,
        # q_o' = q_f q_d^-1); the gain ramps in from 0 (map_command)
        m[M_CLUTCHED] = 0.0
        _rot3(m, row[_POSE], row[_POSE + 1], row[_POSE + 2], m, M_OFF, -s)
        for i in range(3):
            m[M_OFF + i] += m[M_FROZEN + i]
        qw, qx, qy, qz = _qmul(m[M_FROZEN + 3], m[M_FROZEN + 4], m[M_FROZEN + 5], m[M_FROZEN + 6],
                               row[_POSE + 3], -row[_POSE + 4], -row[_POSE + 5], -row[_POSE + 6])
        n = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
        m[M_QO] = qw / n
        m[M_QO + 1] = qx / n
        m[M_QO + 2] = qy / n
        m[M_QO + 3] = qz / n
    if m[M_CLUTCHED] != 0.0:
        for i in range(7):
            row[_POSE + i] = m[M_FROZEN + i]
        for i in range(6):
            row[_TWIST + i] = 0.0
            if row[_HAND + i] == row[_HAND + i]:  # measured (not NaN): the hand acts on nothing
                row[_HAND + i] = 0.0
        return 1
    x, y, z = row[_POSE], row[_POSE + 1], row[_POSE + 2]
    _rot3(m, x, y, z, row, _POSE, s)
    for i in range(3):
        row[_POSE + i] += m[M_OFF + i]
    qw, qx, qy, qz = _qmul(m[M_QO], m[M_QO + 1], m[M_QO + 2], m[M_QO + 3],
                           row[_POSE + 3], row[_POSE + 4], row[_POSE + 5], row[_POSE + 6])
    row[_POSE + 3] = qw
    row[_POSE + 4] = qx
    row[_POSE + 5] = qy
    row[_POSE + 6] = qz
    _rot3(m, row[_TWIST], row[_TWIST + 1], row[_TWIST + 2], row, _TWIST, s)
    _rot3(m, row[_TWIST + 3], row[_TWIST + 4], row[_TWIST + 5], row, _TWIST + 3, 1.0)
    _rot3(m, row[_HAND], row[_HAND + 1], row[_HAND + 2], row, _HAND, s)
    _rot3(m, row[_HAND + 3], row[_HAND + 4], row[_HAND + 5], row, _HAND + 3, 1.0)
    return 0


@njit(**_JIT)
def map_command(cmd, m, out):
    """The scene's wrench ``cmd`` -> the device's, into ``out`` (``cmd`` untouched): ``F_d = g R^T
    F_s / s``, ``t_d = g R^T t_s``. The gain ``g`` moves by ``m[M_RAMP]`` per call towards 0
    while clutched and towards 1 otherwise (a clutch fades the force out, a release ramps it
    back in: it never jumps). Returns ``g``. A non-finite ``cmd`` stays non-finite (the driver
    refuses it and latches its fault, clutched or not)."""
    g = m[M_GAIN]
    if m[M_CLUTCHED] != 0.0:
        g -= m[M_RAMP]
        if g < 1e-12:  # (the sum of the ramp's steps is not exact: faded is exactly 0)
            g = 0.0
    else:
        g += m[M_RAMP]
        if g > 1.0 - 1e-12:
            g = 1.0
    m[M_GAIN] = g
    k = g / m[M_SCALE]
    _rot3t(m, cmd[0], cmd[1], cmd[2], out, 0, k)
    _rot3t(m, cmd[3], cmd[4], cmd[5], out, 3, g)
    for i in range(6):
        if not math.isfinite(cmd[i]):
            out[i] = cmd[i]  # (0 x inf would be NaN anyway; NaN x 0 stays NaN): refused downstream
    return g


@njit(**_JIT)
def unmap_state(row, m):
    """The inverse of ``map_state`` outside a clutch (scene -> device frame, in place), with the
    current offsets: what a scene pose is in the device's workspace."""
    s = m[M_SCALE]
    x, y, z = row[_POSE] - m[M_OFF], row[_POSE + 1] - m[M_OFF + 1], row[_POSE + 2] - m[M_OFF + 2]
    _rot3t(m, x, y, z, row, _POSE, 1.0 / s)
    qw, qx, qy, qz = _qmul(m[M_QO], -m[M_QO + 1], -m[M_QO + 2], -m[M_QO + 3],
                           row[_POSE + 3], row[_POSE + 4], row[_POSE + 5], row[_POSE + 6])
    row[_POSE + 3] = qw
    row[_POSE + 4] = qx
    row[_POSE + 5] = qy
    row[_POSE + 6] = qz
    _rot3t(m, row[_TWIST], row[_TWIST + 1], row[_TWIST + 2], row, _TWIST, 1.0 / s)
    _rot3t(m, row[_TWIST + 3], row[_TWIST + 4], row[_TWIST + 5], row, _TWIST + 3, 1.0)
    _rot3t(m, row[_HAND], row[_HAND + 1], row[_HAND + 2], row, _HAND, 1.0 / s)
    _rot3t(m, row[_HAND + 3], row[_HAND + 4], row[_HAND + 5], row, _HAND + 3, 1.0)


def warm_up() -> None:
    """Compile / load the kernels with the types the wrapper and the tick pass."""
    m = new_mapping()
    row = np.zeros(ROW_FLOATS)
    row[3] = 1.0
    map_state(row, m)
    map_command(np.zeros(6), m, np.zeros(6))
    unmap_state(row, m)


# ------------------------------------------------------------------------------------- config
Vec3 = tuple[float, float, float]


class MappingConfig(msgspec.Struct, forbid_unknown_fields=True, kw_only=True):
    """The mapping's ``[device]`` keys (the module docstring)."""

    #: scene metres per device metre
    workspace_scale: Annotated[float, Meta(gt=0.0, le=1e4)] = 1.0
    #: where the device's origin lands in the scene [m]
    workspace_offset_m: Vec3 = (0.0, 0.0, 0.0)
    #: device frame -> scene frame: a unit quaternion [qw, qx, qy, qz] or a rotation vector [rx, ry, rz] (rad)
    workspace_rotation: list[float] = msgspec.field(default_factory=lambda: [1.0, 0.0, 0.0, 0.0])
    #: the button (its bit) that holds the clutch; -1: no clutch
    clutch_button: Annotated[int, Meta(ge=-1, le=31)] = -1
    #: after a clutch the force ramps back in over this long [s]
    clutch_ramp_s: Annotated[float, Meta(ge=0.0, le=10.0)] = 0.2


def split(table: dict) -> tuple[dict, dict]:
    """``[device]`` -> (the driver's keys, the mapping's keys)."""
    driver = {k: v for k, v in table.items() if k not in MAPPING_KEYS}
    mapping = {k: v for k, v in table.items() if k in MAPPING_KEYS}
    return driver, mapping


def _quat(key: str, v) -> np.ndarray:
    a = ck.numbers(key, list(v), (3, 4))
    if len(a) == 4:
        n = float(np.linalg.norm(a))
        if abs(n - 1.0) > 1e-6:
            raise ck.fail(key, f"a quaternion [qw, qx, qy, qz] must be unit, |q| = {n:.9g}")
        q = a / n
    else:
        th = float(np.linalg.norm(a))
        if th < 1e-15:
            q = np.array([1.0, 0.0, 0.0, 0.0])
        else:
            q = np.concatenate([[math.cos(0.5 * th)], math.sin(0.5 * th) * a / th])
    return q if q[0] >= 0.0 else -q


def parse_mapping(table: dict | None, *, kind: str, period_s: float) -> tuple[MappingConfig, np.ndarray | None]:
    """The mapping keys of a ``[device]`` table -> (their effective values, the kernel's array
    ``m``), ``m`` None when they ask for no mapping (scale 1, no offset, no rotation, no clutch:
    the device is used as it is). ``ValueError("device.<key>: ...")`` naming what cannot be."""
    c = ck.convert(MappingConfig, dict(table or {}), "device")
    q = _quat("device.workspace_rotation", c.workspace_rotation)
    off = np.array(c.workspace_offset_m, dtype=float)
    ck.numbers("device.workspace_offset_m", list(off), (3,))
    if kind == "planar":
        if abs(q[1]) > 1e-12 or abs(q[2]) > 1e-12:
            raise ck.fail("device.workspace_rotation", "a planar device's mapping turns about +z only (it moves in "
                          "the x-y plane)")
        if off[2] != 0.0:
            raise ck.fail("device.workspace_offset_m", "a planar device's mapping keeps it in the x-y plane: z = 0")
    elif kind == "1dof" and np.any(np.abs(q[1:]) > 1e-12):
        raise ck.fail("device.workspace_rotation", "a 1dof device's mapping cannot turn it (its axis is device.axis)")
    identity = (c.workspace_scale == 1.0 and not np.any(off) and np.all(q == (1.0, 0.0, 0.0, 0.0))
                and c.clutch_button < 0)
    if identity:
        return c, None
    m = new_mapping(scale=c.workspace_scale, offset_m=off, rotation=q, clutch_button=c.clutch_button,
                    ramp_steps=c.clutch_ramp_s / period_s)
    return c, m


def new_mapping(*, scale: float = 1.0, offset_m=(0.0, 0.0, 0.0), rotation=(1.0, 0.0, 0.0, 0.0),
                clutch_button: int = -1, ramp_steps: float = 0.0) -> np.ndarray:
    """The kernel's array: scale, offset, rotation (unit quaternion w x y z), clutch button (-1:
    none) and the ramp after a clutch in haptic steps (0: at once)."""
    q = np.asarray(rotation, dtype=float)
    q = q / np.linalg.norm(q)
    w, x, y, z = q
    m = np.zeros(NM)
    m[M_SCALE] = float(scale)
    m[M_OFF:M_OFF + 3] = offset_m
    m[M_QR:M_QR + 4] = q
    m[M_R:M_R + 9] = (1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w),
                      2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w),
                      2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y))
    m[M_QO:M_QO + 4] = q
    m[M_CLUTCH_BIT] = float(clutch_button)
    m[M_RAMP] = 1.0 if ramp_steps <= 1.0 else 1.0 / ramp_steps
    m[M_GAIN] = 1.0
    m[M_FROZEN + 3] = 1.0
    return m


def effective(c: MappingConfig) -> dict:
    """The mapping keys as ``--print-config`` prints them."""
    return {"workspace_scale": c.workspace_scale, "workspace_offset_m": list(c.workspace_offset_m),
            "workspace_rotation": list(c.workspace_rotation), "clutch_button": c.clutch_button,
            "clutch_ramp_s": c.clutch_ramp_s}


__all__ = ["MAPPING_KEYS", "M_CLUTCHED", "M_CMD", "M_GAIN", "MappingConfig", "NM", "map_command", "map_state",
           "new_mapping", "parse_mapping", "split", "unmap_state"]
