"""The simulated user's hand on a simulated device: the ``[device.hand]`` table.

Each step the hand kernel (:func:`hand_eval`, numba, no allocation) says what the hand wants at
the device time of the step's start: an explicit wrench (scripted hands), or a target pose and
twist with the grip's spring, damper and mass (impedance hands). The device kernel integrates
it with the device (implicitly, so any grip stiffness is stable) and reports what an ideal force
sensor between hand and handle reads over the step.

Wrenches, displacements and poses are written in the device's reduced coordinates (1dof: ``[f]``
along the axis; planar: ``[fx, fy, tz]`` / ``[x, y, theta]``; spatial: six) or as full world
6-vectors ``[fx, fy, fz, tx, ty, tz]`` / ``[x, y, z, rx, ry, rz]`` (rotation vector, rad) at the
handle; a spatial pose may also be ``[x, y, z, qw, qx, qy, qz]``.

Hand types and their keys (defaults in brackets):

``type = "none"``
    No hand: the handle is free. [the default hand]
``type = "constant"``
    ``wrench`` [zeros]: a constant wrench [N, N m].
``type = "sinusoid"``
    ``wrench = offset + amplitude * sin(2 pi frequency_hz t + phase_rad)``, per component:
    ``amplitude`` [1 N on the first coordinate], ``frequency_hz`` [1.0] (a number, or one per
    coordinate), ``phase_rad`` [0] (a number, or one per coordinate), ``offset`` [zeros].
``type = "steps"``
    ``steps`` [``[[0.0, zeros]]``]: a list of ``[t_s, wrench]`` (or flat ``[t_s, w...]``), strictly
    increasing times; each wrench holds from its time to the next; zero before the first.
    ``repeat_period_s`` [0: hold the last]: the profile restarts every this many seconds.
``type = "impedance"``
    A hand that grips the handle and follows a target trajectory: the hand's mass moves with the
    handle and the arm pulls it towards the target through a spring-damper,
    ``F = K (x_t - x) + B (v_t - v) - m_h a`` (rotation alike, the error being the rotation vector
    of ``q_t q^-1``). Keys: ``stiffness_n_per_m`` [300], ``damping_n_s_per_m`` [5],
    ``mass_kg`` [0.1], ``rot_stiffness_n_m_per_rad`` [0.5], ``rot_damping_n_m_s_per_rad`` [0.01],
    ``inertia_kg_m2`` [1e-4, isotropic], and ``target`` (a table):

    - ``{type = "constant", pose = [...]}`` [pose: the device's initial pose];
    - ``{type = "sinusoid", amplitude = [...], frequency_hz = 1.0, phase_rad = 0, offset = [pose]}``
      (amplitude [0.02 m on the first coordinate], offset [the initial pose]);
    - ``{type = "waypoints", points = [[t_s, pose...], ...], repeat_period_s = 0}``: piecewise
      linear in the 6-vector (rotation vectors interpolated linearly: fine for rotations about a
      fixed axis and for small ones); the first pose before the first time, the last after.
``type = "replay"``
    A recorded trajectory from ``file`` (required). ``mode = "pose"`` [default]: the recorded
    poses become the target of a stiff grip (the impedance keys above, defaults
    ``stiffness_n_per_m`` 2000, ``damping_n_s_per_m`` 20, ``rot_stiffness_n_m_per_rad`` 5,
    ``rot_damping_n_m_s_per_rad`` 0.05), i.e. the hand drags the handle along the recording and
    the device's commanded wrench pushes back against the grip. ``mode = "wrench"``: the recorded
    wrench is applied as is (linearly interpolated). ``repeat_period_s`` [0: hold the last].

    File formats: CSV (comma separated; ``#`` comments and one header line allowed) or ``.npz``.
    CSV columns: ``t_s`` then, for ``pose``, ``x y z qw qx qy qz`` (the pose columns of a device
    state row, so a recorded device can be replayed) or the reduced pose or a 6-vector; for
    ``wrench``, the reduced wrench or a 6-vector. ``.npz``: arrays ``t_s`` and ``pose`` (n x 7,
    n x reduced or n x 6) or ``wrench``. Times strictly increasing; relative paths are relative
    to the working directory.

Every hand type also takes the device's inputs as scripts on the same clock (``start``):

``buttons`` [``[]``: the device has no buttons]
    ``[[t_s, mask], ...]``: the buttons held (a bit mask, bit i = button i), each from its time
    to the next, none before the first; strictly increasing times. The state row's ``buttons``
    column (NaN without a script).
``gripper`` [``[]``: the device has no gripper]
    ``[[t_s, angle_rad], ...]``: the gripper's opening angle, piecewise linear (the first angle
    before the first time, the last after), its rate the slope. The state row's gripper columns
    (NaN without a script).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, Literal, Optional, Union

import msgspec
import numpy as np
from msgspec import Meta, Struct
from numba import njit

from ..readonly import ArrayFloat
from . import _check as ck
from .layout import HO_B, HO_BR, HO_I, HO_K, HO_KR, HO_M, HO_VT, HO_W, HO_XT, NHO, DST_BUTTONS, DST_GRIP, DST_TIME

_JIT = dict(cache=True, nogil=True, error_model="numpy")


# -- hand parameters (float64[NHP]) -------------------------------------------------------------
HP_MODE = 0       # MODE_*
HP_PROF = 1       # PROF_*
HP_NROWS = 2      # rows of the table in use
HP_PERIOD = 3     # repeat period [s] (0: hold the last value)
HP_K = 4
HP_B = 5
HP_KR = 6
HP_BR = 7
HP_M = 8
HP_I = 9
HP_AMP = 10       # 10..15
HP_FREQ = 16      # 16..21 [Hz]
HP_PHASE = 22     # 22..27 [rad]
HP_OFF = 28       # 28..33 constant value / sinusoid offset / value before the first step
HP_T0 = 34        # device time [s] at which the script started (its t = 0)
HP_WAIT = 35      # 1: the script waits for the first engagement (the handle is free until then)
HP_BROW = 36      # first row of the button script in the table
HP_BN = 37        # its rows (0: the device has no buttons)
HP_GROW = 38      # first row of the gripper script in the table
HP_GN = 39        # its rows (0: the device has no gripper)
NHP = 40

MODE_NONE = 0
MODE_WRENCH = 1
MODE_IMPEDANCE = 2

PROF_CONSTANT = 0
PROF_SINUSOID = 1
PROF_HOLD = 2      # zero-order hold over the table (steps)
PROF_LINEAR = 3    # piecewise linear over the table (waypoints, replay)

#: table columns: t_s, then the 6-vector (the input scripts' rows: t_s, then their one value)
NTAB = 7
#: largest button mask a script may hold (the ProxyState field is a u32)
MAX_BUTTON_MASK = 0xFFFF_FFFF


@njit(**_JIT)
def _row_at(tab, n, t):
    """Largest row index i < n with tab[i, 0] <= t, or -1."""
    if n == 0 or t < tab[0, 0]:
        return -1
    lo = 0
    hi = n - 1
    while lo < hi:
        mid = (lo + hi + 1) // 2
        if tab[mid, 0] <= t:
            lo = mid
        else:
            hi = mid - 1
    return lo


@njit(**_JIT)
def _row_from(tab, r0, n, t):
    """Largest row index i in [r0, r0 + n) with tab[i, 0] <= t, or -1."""
    if n == 0 or t < tab[r0, 0]:
        return -1
    lo = r0
    hi = r0 + n - 1
    while lo < hi:
        mid = (lo + hi + 1) // 2
        if tab[mid, 0] <= t:
            lo = mid
        else:
            hi = mid - 1
    return lo


@njit(**_JIT)
def inputs_eval(hp, tab, st):
    """The button and gripper scripts at the device time ``st[DST_TIME]``, into the state row's
    input columns: NaN where the hand has no script (the device has none). On the hand's clock:
    while it waits for the engagement nothing is held and the gripper rests at its first angle."""
    t = st[DST_TIME] - hp[HP_T0]
    wait = hp[HP_WAIT] != 0.0
    nb = int(hp[HP_BN])
    if nb == 0:
        st[DST_BUTTONS] = np.nan
    else:
        j = -1 if wait else _row_from(tab, int(hp[HP_BROW]), nb, t)
        st[DST_BUTTONS] = 0.0 if j < 0 else tab[j, 1]
    ng = int(hp[HP_GN])
    if ng == 0:
        st[DST_GRIP] = np.nan
        st[DST_GRIP + 1] = np.nan
        return
    g0 = int(hp[HP_GROW])
    last = g0 + ng - 1
    j = -1 if wait else _row_from(tab, g0, ng, t)
    if j < 0:
        st[DST_GRIP] = tab[g0, 1]
        st[DST_GRIP + 1] = 0.0
    elif j >= last:
        st[DST_GRIP] = tab[last, 1]
        st[DST_GRIP + 1] = 0.0
    else:
        span = tab[j + 1, 0] - tab[j, 0]
        rate = (tab[j + 1, 1] - tab[j, 1]) / span
        st[DST_GRIP] = tab[j, 1] + (t - tab[j, 0]) * rate
        st[DST_GRIP + 1] = rate


@njit(**_JIT)
def hand_eval(hp, tab, st, hout):
    """What the hand wants at the device time ``st[DST_TIME]``: fills ``hout`` (layout ``HO_*``).
    The script's time is counted from ``hp[HP_T0]``; while ``hp[HP_WAIT]`` the handle is free."""
    t = st[DST_TIME] - hp[HP_T0]
    mode = int(hp[HP_MODE])
    prof = int(hp[HP_PROF])
    period = hp[HP_PERIOD]
    if period > 0.0 and t >= 0.0:
        t = t - period * math.floor(t / period)
    for i in range(NHO):
        hout[i] = 0.0
    if mode == MODE_NONE or hp[HP_WAIT] != 0.0:
        return
    # value -> hout[base], rate -> hout[rbase] (rate only meaningful for impedance targets)
    base = HO_W if mode == MODE_WRENCH else HO_XT
    rbase = HO_VT
    if prof == PROF_CONSTANT:
        for i in range(6):
            hout[base + i] = hp[HP_OFF + i]
    elif prof == PROF_SINUSOID:
        for i in range(6):
            w = 2.0 * math.pi * hp[HP_FREQ + i]
            arg = w * t + hp[HP_PHASE + i]
            a = hp[HP_AMP + i]
            hout[base + i] = hp[HP_OFF + i] + a * math.sin(arg)
            if mode == MODE_IMPEDANCE:
                hout[rbase + i] = a * w * math.cos(arg)
    else:
        n = int(hp[HP_NROWS])
        j = _row_at(tab, n, t)
        if prof == PROF_HOLD:
            for i in range(6):
                hout[base + i] = hp[HP_OFF + i] if j < 0 else tab[j, 1 + i]
        else:
            if j < 0:
                j0 = 0; j1 = 0
            elif j >= n - 1:
                j0 = n - 1; j1 = n - 1
            else:
                j0 = j; j1 = j + 1
            if j0 == j1:
                for i in range(6):
                    hout[base + i] = tab[j0, 1 + i]
            else:
                span = tab[j1, 0] - tab[j0, 0]
                u = (t - tab[j0, 0]) / span
                for i in range(6):
                    v0 = tab[j0, 1 + i]
                    v1 = tab[j1, 1 + i]
                    hout[base + i] = v0 + u * (v1 - v0)
                    if mode == MODE_IMPEDANCE:
                        hout[rbase + i] = (v1 - v0) / span
    if mode == MODE_IMPEDANCE:
        hout[HO_K] = hp[HP_K]
        hout[HO_B] = hp[HP_B]
        hout[HO_KR] = hp[HP_KR]
        hout[HO_BR] = hp[HP_BR]
        hout[HO_M] = hp[HP_M]
        hout[HO_I] = hp[HP_I]


# ------------------------------------------------------------------------------------ config
#: A wrench, displacement or pose in reduced coordinates (or a 6-vector): a list, or a bare number.
Vec = Union[float, list[float]]
#: Per-component (frequency, phase): a number for all, or one per coordinate.
PerAxis = Union[float, list[float]]
Grip = Annotated[float, Meta(ge=0.0, le=1e7)]
Period = Annotated[float, Meta(ge=0.0)]
#: ``[[t_s, values...], ...]`` rows (checked row by row: strictly increasing times, lengths).
Rows = list[list[Any]]


class _HandTable(Struct, forbid_unknown_fields=True, kw_only=True):
    type: str = "none"
    #: when the script's clock starts: at each new session's engagement (the hand waits, the
    #: handle free, until a client engages, so a client attached later finds the script at its
    #: start), or when the server starts
    start: Literal["engagement", "server"] = "engagement"
    #: the button script ``[[t_s, mask], ...]`` (empty: the device has no buttons)
    buttons: Rows = msgspec.field(default_factory=list)
    #: the gripper script ``[[t_s, angle_rad], ...]`` (empty: the device has no gripper)
    gripper: Rows = msgspec.field(default_factory=list)


class HandNone(_HandTable):
    """``type = "none"``: the handle is free."""
    type: Literal["none"] = "none"


class HandConstant(_HandTable):
    type: Literal["constant"] = "constant"
    wrench: Optional[Vec] = None          # None: zeros


class HandSinusoid(_HandTable):
    type: Literal["sinusoid"] = "sinusoid"
    amplitude: Optional[Vec] = None       # None: 1 N on the first coordinate
    frequency_hz: PerAxis = 1.0
    phase_rad: PerAxis = 0.0
    offset: Optional[Vec] = None          # None: zeros


class HandSteps(_HandTable):
    type: Literal["steps"] = "steps"
    steps: Optional[Rows] = None          # None: [[0, zeros]]
    repeat_period_s: Period = 0.0


class HandImpedance(_HandTable):
    type: Literal["impedance"] = "impedance"
    stiffness_n_per_m: Grip = 300.0
    damping_n_s_per_m: Grip = 5.0
    mass_kg: Grip = 0.1
    rot_stiffness_n_m_per_rad: Grip = 0.5
    rot_damping_n_m_s_per_rad: Grip = 0.01
    inertia_kg_m2: Grip = 1e-4
    target: dict = msgspec.field(default_factory=dict)


class HandReplay(_HandTable):
    type: Literal["replay"] = "replay"
    file: str = ""                        # required
    mode: Literal["pose", "wrench"] = "pose"
    repeat_period_s: Period = 0.0
    #: the grip (mode = "pose" only); None: the replay grip's defaults (``_GRIP_DEFAULTS``)
    stiffness_n_per_m: Optional[Grip] = None
    damping_n_s_per_m: Optional[Grip] = None
    mass_kg: Optional[Grip] = None
    rot_stiffness_n_m_per_rad: Optional[Grip] = None
    rot_damping_n_m_s_per_rad: Optional[Grip] = None
    inertia_kg_m2: Optional[Grip] = None


class _TargetTable(Struct, forbid_unknown_fields=True, kw_only=True):
    type: str = "constant"


class TargetConstant(_TargetTable):
    type: Literal["constant"] = "constant"
    pose: Optional[Vec] = None            # None: the device's initial pose


class TargetSinusoid(_TargetTable):
    type: Literal["sinusoid"] = "sinusoid"
    amplitude: Optional[Vec] = None       # None: 0.02 m on the first coordinate
    frequency_hz: PerAxis = 1.0
    phase_rad: PerAxis = 0.0
    offset: Optional[Vec] = None          # None: the device's initial pose


class TargetWaypoints(_TargetTable):
    type: Literal["waypoints"] = "waypoints"
    points: Optional[Rows] = None         # required
    repeat_period_s: Period = 0.0


#: hand type -> its table (one declaration per type: keys, defaults, bounds)
HANDS: dict[str, type] = {"none": HandNone, "constant": HandConstant, "sinusoid": HandSinusoid,
                          "steps": HandSteps, "impedance": HandImpedance, "replay": HandReplay}
TARGETS: dict[str, type] = {"constant": TargetConstant, "sinusoid": TargetSinusoid, "waypoints": TargetWaypoints}
HAND_TYPES = tuple(HANDS)

_GRIP_KEYS = ("stiffness_n_per_m", "damping_n_s_per_m", "mass_kg", "rot_stiffness_n_m_per_rad",
              "rot_damping_n_m_s_per_rad", "inertia_kg_m2")
_GRIP_SLOTS = (HP_K, HP_B, HP_M, HP_KR, HP_BR, HP_I)
#: the replay grip: stiff, so the hand drags the handle along the recording
_REPLAY_GRIP = (2000.0, 20.0, 0.1, 5.0, 0.05, 1e-4)


@dataclass
class Hand:
    """A parsed hand: the parameter vector and table the kernel reads, and its effective config
    (every key of its type, defaults filled in, in the device's reduced coordinates)."""

    type: str
    hp: np.ndarray
    tab: np.ndarray
    config: dict = field(default_factory=dict)

    mass_kg = ArrayFloat("hp", HP_M, doc="Mass of a gripping hand (it moves with the handle), kg.")
    inertia_kg_m2 = ArrayFloat("hp", HP_I, doc="Rotational inertia of a gripping hand, kg m^2.")

    @property
    def buttons(self) -> int:
        """Buttons the button script presses (its highest bit, plus one); 0: no script."""
        r0, n = int(self.hp[HP_BROW]), int(self.hp[HP_BN])
        return max((int(v).bit_length() for v in self.tab[r0:r0 + n, 1]), default=0) if n else 0

    @property
    def gripper(self) -> bool:
        """The hand has a gripper script (the simulated device has a gripper)."""
        return int(self.hp[HP_GN]) > 0


def _first_unit(kind: str, axis: np.ndarray, value: float) -> np.ndarray:
    """``value`` on the kind's first coordinate, as a world 6-vector."""
    out = np.zeros(6)
    if kind == "1dof":
        out[:3] = value * axis
    else:
        out[0] = value
    return out


def _reduced_first(kind: str, value: float) -> list[float]:
    out = [0.0] * ck.REDUCED_DIMS[kind]
    out[0] = value
    return out


def _as_list(v):
    return [float(x) for x in v] if isinstance(v, (list, tuple)) else float(v)


def _table(key: str, rows, *, kind, axis, origin, pose: bool) -> np.ndarray:
    """``[[t, v...], ...]`` or ``[[t, [v...]], ...]`` -> (n, 7) with strictly increasing t."""
    if not isinstance(rows, (list, tuple)) or not rows:
        raise ck.fail(key, f"expected a non-empty list of [t_s, values], got {rows!r}")
    out = np.zeros((len(rows), NTAB))
    for i, row in enumerate(rows):
        rk = f"{key}[{i}]"
        if not isinstance(row, (list, tuple)) or len(row) < 2:
            raise ck.fail(rk, f"expected [t_s, values], got {row!r}")
        t = ck.num(f"{rk}[0]", row[0], lo=0.0)
        vals = row[1] if len(row) == 2 and isinstance(row[1], (list, tuple)) else list(row[1:])
        out[i, 0] = t
        out[i, 1:] = (ck.pose6(rk, vals, kind, axis, origin) if pose else ck.vector6(rk, vals, kind, axis))
        if i and not t > out[i - 1, 0]:
            raise ck.fail(rk, f"times must increase strictly ({out[i - 1, 0]:g} then {t:g})")
    return out


def _repeat(key: str, period: float, tab: np.ndarray) -> float:
    if period > 0.0 and period < tab[-1, 0]:
        raise ck.fail(key, f"must be 0 or at least the last time ({tab[-1, 0]:g} s), got {period:g}")
    return period


def _sinusoid(prefix: str, c, hp: np.ndarray, *, kind, axis, origin, pose: bool,
              default_amp: float, default_offset: np.ndarray, rest_reduced) -> dict:
    """Fill the sinusoid slots of ``hp``; return the effective keys."""
    if c.amplitude is not None:
        hp[HP_AMP:HP_AMP + 6] = ck.vector6(f"{prefix}.amplitude", c.amplitude, kind, axis)
        amp = _as_list(c.amplitude)
    else:
        hp[HP_AMP:HP_AMP + 6] = _first_unit(kind, axis, default_amp)
        amp = _reduced_first(kind, default_amp)
    freq = ck.placed6(f"{prefix}.frequency_hz", c.frequency_hz, kind)
    if np.any(freq < 0) or np.any(freq > 1e4):
        raise ck.fail(f"{prefix}.frequency_hz", f"must be in [0, 10000] Hz, got {freq.tolist()}")
    hp[HP_FREQ:HP_FREQ + 6] = freq
    hp[HP_PHASE:HP_PHASE + 6] = ck.placed6(f"{prefix}.phase_rad", c.phase_rad, kind)
    if c.offset is not None:
        hp[HP_OFF:HP_OFF + 6] = (ck.pose6(f"{prefix}.offset", c.offset, kind, axis, origin) if pose
                                 else ck.vector6(f"{prefix}.offset", c.offset, kind, axis))
        off = _as_list(c.offset)
    else:
        hp[HP_OFF:HP_OFF + 6] = default_offset
        off = list(rest_reduced) if pose else [0.0] * ck.REDUCED_DIMS[kind]
    return {"amplitude": amp, "frequency_hz": _as_list(c.frequency_hz), "phase_rad": _as_list(c.phase_rad),
            "offset": off}


def _grip(c, defaults, hp: np.ndarray) -> dict:
    out = {}
    for k, d, slot in zip(_GRIP_KEYS, defaults, _GRIP_SLOTS):
        v = getattr(c, k)
        hp[slot] = d if v is None else v
        out[k] = float(hp[slot])
    return out


def _rows_out(tab: np.ndarray, rows) -> list:
    """The rows as given, normalised to ``[t_s, [values...]]``."""
    out = []
    for row in rows:
        vals = row[1] if len(row) == 2 and isinstance(row[1], (list, tuple)) else list(row[1:])
        out.append([float(row[0]), [float(x) for x in vals]])
    return out


def _load_recording(key: str, path: str, mode: str, *, kind, axis, origin) -> np.ndarray:
    """A recording file -> (n, 7) table (t_s, world 6-vector)."""
    p = Path(path)
    if not p.is_file():
        raise ck.fail(key, f"no such file: {path}")
    try:
        if p.suffix == ".npz":
            with np.load(p) as z:
                if "t_s" not in z or mode not in z:
                    raise ck.fail(key, f"{path}: expected arrays 't_s' and '{mode}', found {sorted(z.files)}")
                t = np.asarray(z["t_s"], dtype=np.float64).reshape(-1)
                vals = np.asarray(z[mode], dtype=np.float64)
                if vals.ndim == 1:
                    vals = vals.reshape(-1, 1)
        else:
            lines = [ln for ln in p.read_text().splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
            if lines and any(c.isalpha() and c not in "eE" for c in lines[0].replace("nan", "").replace("inf", "")):
                lines = lines[1:]
            if not lines:
                raise ck.fail(key, f"{path}: no data rows")
            data = np.array([[float(x) for x in ln.split(",")] for ln in lines], dtype=np.float64)
            t, vals = data[:, 0], data[:, 1:]
    except ValueError as exc:
        if str(exc).startswith(key):
            raise
        raise ck.fail(key, f"{path}: not a readable recording ({exc})") from None
    except OSError as exc:
        raise ck.fail(key, f"{path}: {exc}") from None
    if len(t) == 0 or len(t) != len(vals):
        raise ck.fail(key, f"{path}: {len(t)} times for {len(vals)} rows")
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(vals))):
        raise ck.fail(key, f"{path}: non-finite values")
    if np.any(np.diff(t) <= 0):
        raise ck.fail(key, f"{path}: times must increase strictly")
    r = ck.REDUCED_DIMS[kind]
    ncol = vals.shape[1]
    out = np.zeros((len(t), NTAB))
    out[:, 0] = t
    if mode == "pose" and ncol == 7:
        out[:, 1:4] = vals[:, :3]
        q = vals[:, 3:7]
        nq = np.linalg.norm(q, axis=1)
        if np.any(np.abs(nq - 1.0) > 1e-3):
            raise ck.fail(key, f"{path}: quaternions (qw qx qy qz) must be unit")
        q = q / nq[:, None]
        if kind == "planar":
            out[:, 6] = np.unwrap(2.0 * np.arctan2(q[:, 3], q[:, 0]))
        elif kind == "spatial":
            # keep the sign continuous, then the rotation vector of each row
            for i in range(1, len(q)):
                if np.dot(q[i], q[i - 1]) < 0:
                    q[i] = -q[i]
            for i in range(len(q)):
                qi = q[i] if q[i, 0] >= 0 else -q[i]
                out[i, 4:7] = ck.rotvec_from_quat(key, qi)
        return out
    allowed = sorted({r, 6})
    if ncol not in allowed:
        want = " or ".join(str(1 + n) for n in sorted(set(allowed) | ({7} if mode == "pose" else set())))
        raise ck.fail(key, f"{path}: expected {want} columns (t_s first), got {1 + ncol}")
    for i in range(len(t)):
        out[i, 1:] = (ck.pose6(key, vals[i], kind, axis, origin) if mode == "pose"
                      else ck.vector6(key, vals[i], kind, axis))
    return out


def _input_rows(key: str, rows, *, mask: bool) -> np.ndarray:
    """``[[t_s, value], ...]`` -> (n, NTAB) rows (t_s, value, zeros): strictly increasing times,
    a button mask an integer in [0, MAX_BUTTON_MASK], a gripper angle in [-pi, pi]."""
    if not isinstance(rows, (list, tuple)):
        raise ck.fail(key, f"expected a list of [t_s, {'mask' if mask else 'angle_rad'}] (empty: none), got {rows!r}")
    out = np.zeros((len(rows), NTAB))
    for i, row in enumerate(rows):
        rk = f"{key}[{i}]"
        if not isinstance(row, (list, tuple)) or len(row) != 2:
            raise ck.fail(rk, f"expected [t_s, {'mask' if mask else 'angle_rad'}], got {row!r}")
        t = ck.num(f"{rk}[0]", row[0], lo=0.0)
        if mask:
            v = row[1]
            if isinstance(v, bool) or not isinstance(v, int) or not 0 <= v <= MAX_BUTTON_MASK:
                raise ck.fail(f"{rk}[1]", f"a button mask is an integer in [0, {MAX_BUTTON_MASK}] (bit i: button i), "
                              f"got {v!r}")
            v = float(v)
        else:
            v = ck.num(f"{rk}[1]", row[1], lo=-math.pi, hi=math.pi)
        out[i, 0] = t
        out[i, 1] = v
        if i and not t > out[i - 1, 0]:
            raise ck.fail(rk, f"times must increase strictly ({out[i - 1, 0]:g} then {t:g})")
    return out


def parse_hand(cfg, *, kind: str, axis, origin, rest_pose6, prefix: str = "device.hand",
               rest_reduced=None) -> Hand:
    """Validate a ``[device.hand]`` table (:data:`HANDS`) and build the kernel's arrays.

    ``rest_pose6``: the device's initial pose as a world 6-vector (default impedance target);
    ``rest_reduced``: the same pose as written in the config (for the effective values).
    """
    axis = np.asarray(axis, dtype=np.float64)
    origin = np.asarray(origin, dtype=np.float64)
    rest = np.asarray(rest_pose6, dtype=np.float64)
    if rest_reduced is None:
        rest_reduced = rest.tolist()
    if cfg is None:
        cfg = {}
    if not isinstance(cfg, dict):
        raise ck.fail(prefix, f"expected a table, got {cfg!r}")
    htype = ck.string(f"{prefix}.type", cfg.get("type", "none"), HAND_TYPES)
    c = ck.convert(HANDS[htype], cfg, prefix)
    hp = np.zeros(NHP)
    tab = np.zeros((1, NTAB))
    geo = dict(kind=kind, axis=axis, origin=origin)
    eff: dict = {"type": htype, "start": c.start}
    btab = _input_rows(f"{prefix}.buttons", c.buttons, mask=True)
    gtab = _input_rows(f"{prefix}.gripper", c.gripper, mask=False)
    if htype != "none" or len(btab) or len(gtab):
        hp[HP_WAIT] = 1.0 if c.start == "engagement" else 0.0
    if htype == "none":
        hp[HP_MODE] = MODE_NONE
    elif htype == "constant":
        hp[HP_MODE] = MODE_WRENCH
        hp[HP_PROF] = PROF_CONSTANT
        w = c.wrench if c.wrench is not None else [0.0] * ck.REDUCED_DIMS[kind]
        hp[HP_OFF:HP_OFF + 6] = ck.vector6(f"{prefix}.wrench", w, kind, axis)
        eff["wrench"] = _as_list(w)
    elif htype == "sinusoid":
        hp[HP_MODE] = MODE_WRENCH
        hp[HP_PROF] = PROF_SINUSOID
        eff.update(_sinusoid(prefix, c, hp, pose=False, default_amp=1.0, default_offset=np.zeros(6),
                             rest_reduced=rest_reduced, **geo))
    elif htype == "steps":
        hp[HP_MODE] = MODE_WRENCH
        hp[HP_PROF] = PROF_HOLD
        rows = c.steps if c.steps is not None else [[0.0, [0.0] * ck.REDUCED_DIMS[kind]]]
        tab = _table(f"{prefix}.steps", rows, pose=False, **geo)
        hp[HP_PERIOD] = _repeat(f"{prefix}.repeat_period_s", c.repeat_period_s, tab)
        eff.update(steps=_rows_out(tab, rows), repeat_period_s=c.repeat_period_s)
    elif htype == "impedance":
        hp[HP_MODE] = MODE_IMPEDANCE
        eff.update(_grip(c, (None,) * 6, hp))
        tp = f"{prefix}.target"
        ttype = ck.string(f"{tp}.type", c.target.get("type", "constant"), tuple(TARGETS))
        t = ck.convert(TARGETS[ttype], c.target, tp)
        teff: dict = {"type": ttype}
        if ttype == "constant":
            hp[HP_PROF] = PROF_CONSTANT
            hp[HP_OFF:HP_OFF + 6] = ck.pose6(f"{tp}.pose", t.pose, **geo) if t.pose is not None else rest
            teff["pose"] = _as_list(t.pose) if t.pose is not None else list(rest_reduced)
        elif ttype == "sinusoid":
            hp[HP_PROF] = PROF_SINUSOID
            teff.update(_sinusoid(tp, t, hp, pose=True, default_amp=0.02, default_offset=rest,
                                  rest_reduced=rest_reduced, **geo))
        else:
            hp[HP_PROF] = PROF_LINEAR
            if t.points is None:
                raise ck.fail(f"{tp}.points", "required for waypoints: [[t_s, pose...], ...]")
            tab = _table(f"{tp}.points", t.points, pose=True, **geo)
            hp[HP_PERIOD] = _repeat(f"{tp}.repeat_period_s", t.repeat_period_s, tab)
            teff.update(points=_rows_out(tab, t.points), repeat_period_s=t.repeat_period_s)
        eff["target"] = teff
    else:  # replay
        if not c.file:
            raise ck.fail(f"{prefix}.file", "required: a CSV or .npz recording")
        if c.mode == "pose":
            hp[HP_MODE] = MODE_IMPEDANCE
            grip = _grip(c, _REPLAY_GRIP, hp)
        else:
            hp[HP_MODE] = MODE_WRENCH
            for k in _GRIP_KEYS:
                if getattr(c, k) is not None:
                    raise ck.fail(f"{prefix}.{k}", "only used with mode = \"pose\"")
            grip = {}
        tab = _load_recording(f"{prefix}.file", c.file, c.mode, **geo)
        hp[HP_PROF] = PROF_LINEAR
        hp[HP_PERIOD] = _repeat(f"{prefix}.repeat_period_s", c.repeat_period_s, tab)
        eff.update(file=c.file, mode=c.mode, repeat_period_s=c.repeat_period_s, **grip)
    hp[HP_NROWS] = len(tab)
    # the input scripts' rows follow the hand's own in the one table
    hp[HP_BROW], hp[HP_BN] = len(tab), len(btab)
    hp[HP_GROW], hp[HP_GN] = len(tab) + len(btab), len(gtab)
    eff["buttons"] = [[float(t), int(v)] for t, v in btab[:, :2]]
    eff["gripper"] = [[float(t), float(v)] for t, v in gtab[:, :2]]
    return Hand(htype, hp, np.ascontiguousarray(np.vstack([tab, btab, gtab])), eff)
