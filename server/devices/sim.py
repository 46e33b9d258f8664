"""Simulated haptic devices with their own dynamics (entry point ``sim``).

``make_sim_device(config, period_s=..., clock_ns=...)`` builds a :class:`SimDevice` from the
``[device]`` table of the server config. The device advances its dynamics by one period inside
each ``write`` (see :mod:`.dynamics` for the equations, the integrator and the end-stops) and
takes a simulated hand (see :mod:`.hands`). Per step: two numba kernel calls over preallocated
arrays, no allocation.

The paper's planar device (a planar 3-DOF twin-pantograph impedance display; its mass and
inertia are not given in the paper) is simulated with values chosen as plausible for a
direct-drive twin pantograph, as seen at the handle: **mass 0.4 kg, I_zz 1.0e-3 kg m^2** (a
0.4 kg body with a 5 cm radius of gyration), viscous damping 2 N s/m and 2e-3 N m s/rad,
workspace +-25 cm in x and y (the shipped planar scenes fit in it), rotation +-1 rad, 10 N and 0.5 N m
peak.

Config keys (``[device]``; every key optional; defaults per kind written ``1dof / planar /
spatial``, ``-`` where the key does not apply to the kind and is an error if given):

``driver`` = ``"sim"``
    The entry point name (the loader's; not checked here).
``kind`` = ``"planar"``
    ``1dof``, ``planar`` or ``spatial``.
``mass_kg`` = 0.2 / 0.4 / 0.3
    Moving mass at the handle [kg].
``inertia_kg_m2`` = - / 1.0e-3 / [6e-4, 6e-4, 4e-4]
    Planar: I_zz about the handle. Spatial: 3 principal moments or a symmetric positive definite
    3x3 matrix, body frame, about the handle [kg m^2].
``damping_n_s_per_m`` = 1.0 / 2.0 / 1.0
    Viscous damping of the translation [N s/m].
``rot_damping_n_m_s_per_rad`` = - / 2e-3 / 1e-3
    Viscous damping of the rotation [N m s/rad].
``axis`` = [1, 0, 0] / - / -
    1dof: the unit direction of travel, world.
``origin_m`` = [0, 0, 0] / - / -
    1dof: the handle position at s = 0, world [m].
``workspace_min_m``, ``workspace_max_m`` = +-0.1 on x y z / +-0.25 on x y / +-0.1 on x y z
    The workspace box, world [m] (planar: ``[x, y]``, a z entry is ignored). A 1dof device
    travels where the line through ``origin_m`` along ``axis`` is inside the box.
``rotation_limit_rad`` = - / 1.0 / 1.0
    Planar: abs(theta) at most this; spatial: the angle of the rotation from identity (a cone
    about the initial frame); 0 = no limit.
``endstop_stiffness_n_per_m`` = min(20000, mass_kg / period^2)
    End-stop spring; at most ``2 mass_kg / period^2`` (stability of the explicit spring).
``endstop_damping_n_s_per_m`` = 50
    End-stop damper (implicit: any value is stable).
``endstop_rot_stiffness_n_m_per_rad`` = - / min(20, I_min / period^2)
    Rotational end-stop spring; at most ``2 I_min / period^2`` (I_min: the smallest moment).
``endstop_rot_damping_n_m_s_per_rad`` = - / 0.05
    Rotational end-stop damper.
``max_force_n`` = 10 / 10 / 8
    Force cap per axis [N]; larger commands are saturated and counted.
``max_torque_n_m`` = - / 0.5 / 0.5
    Torque cap per axis [N m] (a 1dof device reports 0: it renders no torque).
``max_speed_m_per_s`` = 2.0
    Rated speed, reported in ``limits``; faster steps are counted.
``max_angular_speed_rad_per_s`` = - / 20 / 20
    Rated angular speed (a 1dof device reports ``inf``: it cannot turn).
``watchdog_s`` = 0.05
    No ``write`` for longer than this -> zero output and ``DEV_FAULT_WATCHDOG`` latched until
    ``enable()``; 0 = no watchdog.
``initial_pose`` = the workspace centre, identity
    Reduced pose: 1dof ``[s]``; planar ``[x, y, theta]``; spatial ``[x, y, z, rx, ry, rz]``
    (rotation vector) or ``[x, y, z, qw, qx, qy, qz]``. Must be inside the limits.
``initial_velocity`` = zeros
    Reduced twist: 1dof ``[v]``; planar ``[vx, vy, wz]``; spatial ``[vx, vy, vz, wx, wy, wz]``.
``hand`` = ``{type = "none"}``
    The simulated hand (a table; types and keys in :mod:`.hands`).

A key that does not apply to the kind (e.g. ``inertia_kg_m2`` on a 1dof device) is an error, as
is any unknown key; errors are ``ValueError("device.<key>: <reason>")``.

The device starts **disabled** (output zero) and at rest at ``initial_pose``; ``enable()`` arms
it. ``read``/``write`` return the latched fault if any, else ``DEV_FAULT_DISABLED`` while
disabled, else ``DEV_OK``; the state row is always filled. Devices are gravity compensated.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from typing import Annotated, Literal, Optional, Union

import msgspec
import numpy as np
from msgspec import Meta, Struct

from ..readonly import ArrayBool, ArrayFloat, ArrayInt
from . import _check as ck
from . import dynamics as _dyn
from . import hands as _hands
from .base import (
    DEV_FAULT_NAMES, DEV_NSTATE, DEV_OK, DEVICE_KINDS, DeviceDriver, DeviceInfo, DeviceLimits, info_from_limits,
)
from .layout import (
    DC_ENABLED, DC_FAULT, DC_LAST_NS, DC_WD_NS, COUNTER_NAMES, KIND_IDS, NCNT, NCTL, NHO, NPAR, NST,
    DP_AXIS, DP_B, DP_BR, DP_BS, DP_BSR, DP_DT, DP_FMAX, DP_HI, DP_IB, DP_IZZ, DP_KIND, DP_KS, DP_KSR, DP_LO,
    DP_MASS, DP_ORIGIN, DP_ROTLIM, DP_SHI, DP_SLO, DP_TMAX, DP_VMAX, DP_WMAX,
    DST_CMD, DST_POSE, DST_S, DST_SD, DST_STOP, DST_TH, DST_TIME, DST_TWIST,
)

ENDSTOP_STIFFNESS_N_PER_M = 20000.0
ENDSTOP_ROT_STIFFNESS_N_M_PER_RAD = 20.0
#: k dt^2 / m at most this (symplectic Euler is stable below 4 for an undamped spring)
ENDSTOP_STABILITY = 2.0

# --------------------------------------------------------------------------- the [device] table
# One Struct per kind: its keys, defaults and bounds (the module docstring says what each means).
# A key of another kind "does not apply" to this one. ``Limits*`` are the keys every driver of
# the kind shares (the remote driver's tables extend them).
Mass = Annotated[float, Meta(gt=0.0, le=1e3)]
NonNeg = Annotated[float, Meta(ge=0.0)]
Vec = Union[float, list[float]]
Vec3 = tuple[float, float, float]


class _Limits(Struct, forbid_unknown_fields=True, kw_only=True):
    driver: str = "sim"
    kind: str = "planar"
    max_speed_m_per_s: Annotated[float, Meta(gt=0.0, le=1e3)] = 2.0
    watchdog_s: Annotated[float, Meta(ge=0.0, le=10.0)] = 0.05


class Limits1dof(_Limits):
    kind: Literal["1dof"] = "1dof"
    max_force_n: Annotated[float, Meta(gt=0.0, le=1e4)] = 10.0
    workspace_min_m: list[float] = msgspec.field(default_factory=lambda: [-0.1, -0.1, -0.1])
    workspace_max_m: list[float] = msgspec.field(default_factory=lambda: [0.1, 0.1, 0.1])


class LimitsPlanar(_Limits):
    kind: Literal["planar"] = "planar"
    max_force_n: Annotated[float, Meta(gt=0.0, le=1e4)] = 10.0
    max_torque_n_m: Annotated[float, Meta(gt=0.0, le=1e3)] = 0.5
    max_angular_speed_rad_per_s: Annotated[float, Meta(gt=0.0, le=1e4)] = 20.0
    # +-25 cm: the shipped planar scenes fit (the pymunk testbed's peg travels 124 mm to its wall)
    workspace_min_m: list[float] = msgspec.field(default_factory=lambda: [-0.25, -0.25])
    workspace_max_m: list[float] = msgspec.field(default_factory=lambda: [0.25, 0.25])


class LimitsSpatial(_Limits):
    kind: Literal["spatial"] = "spatial"
    max_force_n: Annotated[float, Meta(gt=0.0, le=1e4)] = 8.0
    max_torque_n_m: Annotated[float, Meta(gt=0.0, le=1e3)] = 0.5
    max_angular_speed_rad_per_s: Annotated[float, Meta(gt=0.0, le=1e4)] = 20.0
    workspace_min_m: list[float] = msgspec.field(default_factory=lambda: [-0.1, -0.1, -0.1])
    workspace_max_m: list[float] = msgspec.field(default_factory=lambda: [0.1, 0.1, 0.1])


class Sim1dof(Limits1dof):
    mass_kg: Mass = 0.2
    damping_n_s_per_m: Annotated[float, Meta(ge=0.0, le=1e5)] = 1.0
    axis: Vec3 = (1.0, 0.0, 0.0)
    origin_m: Vec3 = (0.0, 0.0, 0.0)
    endstop_stiffness_n_per_m: Optional[NonNeg] = None          # None: min(20000, m / dt^2)
    endstop_damping_n_s_per_m: Annotated[float, Meta(ge=0.0, le=1e6)] = 50.0
    initial_pose: Optional[Vec] = None                          # None: s = 0
    initial_velocity: Optional[Vec] = None                      # None: at rest
    hand: dict = msgspec.field(default_factory=lambda: {"type": "none"})


class SimPlanar(LimitsPlanar):
    mass_kg: Mass = 0.4
    inertia_kg_m2: Mass = 1.0e-3
    damping_n_s_per_m: Annotated[float, Meta(ge=0.0, le=1e5)] = 2.0
    rot_damping_n_m_s_per_rad: Annotated[float, Meta(ge=0.0, le=1e3)] = 2e-3
    rotation_limit_rad: Annotated[float, Meta(ge=0.0, le=math.pi)] = 1.0
    endstop_stiffness_n_per_m: Optional[NonNeg] = None          # None: min(20000, m / dt^2)
    endstop_damping_n_s_per_m: Annotated[float, Meta(ge=0.0, le=1e6)] = 50.0
    endstop_rot_stiffness_n_m_per_rad: Optional[NonNeg] = None  # None: min(20, I_min / dt^2)
    endstop_rot_damping_n_m_s_per_rad: Annotated[float, Meta(ge=0.0, le=1e4)] = 0.05
    initial_pose: Optional[Vec] = None                          # None: the workspace centre
    initial_velocity: Optional[Vec] = None
    hand: dict = msgspec.field(default_factory=lambda: {"type": "none"})


class SimSpatial(LimitsSpatial):
    mass_kg: Mass = 0.3
    #: 3 principal moments, or a symmetric positive definite 3x3 matrix
    inertia_kg_m2: list[Union[float, list[float]]] = msgspec.field(default_factory=lambda: [6e-4, 6e-4, 4e-4])
    damping_n_s_per_m: Annotated[float, Meta(ge=0.0, le=1e5)] = 1.0
    rot_damping_n_m_s_per_rad: Annotated[float, Meta(ge=0.0, le=1e3)] = 1e-3
    rotation_limit_rad: Annotated[float, Meta(ge=0.0, le=math.pi)] = 1.0
    endstop_stiffness_n_per_m: Optional[NonNeg] = None
    endstop_damping_n_s_per_m: Annotated[float, Meta(ge=0.0, le=1e6)] = 50.0
    endstop_rot_stiffness_n_m_per_rad: Optional[NonNeg] = None
    endstop_rot_damping_n_m_s_per_rad: Annotated[float, Meta(ge=0.0, le=1e4)] = 0.05
    initial_pose: Optional[Vec] = None
    initial_velocity: Optional[Vec] = None
    hand: dict = msgspec.field(default_factory=lambda: {"type": "none"})


#: kind -> its ``[device]`` table for the ``sim`` driver
SIM_CONFIGS: dict[str, type] = {"1dof": Sim1dof, "planar": SimPlanar, "spatial": SimSpatial}


def _defaults(cls) -> dict:
    return {k: v for k, v in msgspec.structs.asdict(cls()).items() if k not in ("driver", "kind", "hand")}


#: Per-kind defaults (keys of the kind only), from the tables above.
KIND_DEFAULTS: dict[str, dict] = {k: _defaults(c) for k, c in SIM_CONFIGS.items()}


def convert_kind(configs: dict[str, type], config, *, default_driver: str):
    """The kind's table (``configs[kind]``) from a ``[device]`` dict, or ``ValueError("device.<key>: ...")``."""
    if config is None:
        config = {}
    if not isinstance(config, dict):
        raise ck.fail("device", f"expected a table, got {config!r}")
    kind = ck.string("device.kind", config.get("kind", "planar"), DEVICE_KINDS)
    c = ck.convert(configs[kind], config, "device", siblings=configs, kind=kind)
    if "driver" in config:
        ck.string("device.driver", config["driver"])
    else:
        c.driver = default_driver
    return c


@dataclass
class SimSpec:
    """A validated simulated device (what ``parse_sim_config`` returns)."""

    kind: str
    period_s: float
    par: np.ndarray
    limits: DeviceLimits
    initial_pose6: np.ndarray     # world 6-vector (x y z rx ry rz)
    initial_twist6: np.ndarray    # world 6-vector
    hand: _hands.Hand
    values: dict = field(default_factory=dict)  # effective config values (defaults filled in)


def _period(period_s) -> float:
    p = ck.num("period_s", period_s, lo=0.0, lo_open=True, hi=0.1)
    return p


def _travel(origin, axis, lo, hi) -> tuple[float, float]:
    """The interval of s with origin + s axis inside the box [lo, hi]."""
    s_lo, s_hi = -math.inf, math.inf
    for i in range(3):
        if abs(axis[i]) < 1e-12:
            continue
        a, b = (lo[i] - origin[i]) / axis[i], (hi[i] - origin[i]) / axis[i]
        s_lo, s_hi = max(s_lo, min(a, b)), min(s_hi, max(a, b))
    return s_lo, s_hi


def workspace(c) -> tuple[np.ndarray, np.ndarray, int]:
    """The workspace box of a ``Limits*`` table as 3-vectors (planar: z = 0) and its dimension."""
    lens = (2, 3) if c.kind == "planar" else (3,)
    lo = ck.numbers("device.workspace_min_m", c.workspace_min_m, lens)
    hi = ck.numbers("device.workspace_max_m", c.workspace_max_m, lens)
    dims = 2 if c.kind == "planar" else 3
    lo, hi = np.append(lo[:dims], [0.0] * (3 - dims)), np.append(hi[:dims], [0.0] * (3 - dims))
    for i in range(dims):
        if not hi[i] > lo[i]:
            raise ck.fail("device.workspace_max_m",
                          f"must exceed workspace_min_m on every axis ({lo[:dims].tolist()} .. {hi[:dims].tolist()})")
    return lo, hi, dims


def limits_of(c, lo, hi) -> DeviceLimits:
    """The ``DeviceLimits`` of a ``Limits*`` table (a 1dof device renders no torque and cannot turn)."""
    one = c.kind == "1dof"
    return DeviceLimits(max_force_n=c.max_force_n, max_torque_n_m=0.0 if one else c.max_torque_n_m,
                        max_speed_m_per_s=c.max_speed_m_per_s,
                        max_angular_speed_rad_per_s=math.inf if one else c.max_angular_speed_rad_per_s,
                        workspace_min_m=tuple(lo.tolist()), workspace_max_m=tuple(hi.tolist()),
                        watchdog_s=c.watchdog_s)


def parse_sim_config(config: dict, *, period_s: float) -> SimSpec:
    """Validate a ``[device]`` table for the ``sim`` driver (:data:`SIM_CONFIGS`). Raises
    ``ValueError("device.<key>: ...")``. ``values``: every key of the kind, defaults filled in."""
    dt = _period(period_s)
    c = convert_kind(SIM_CONFIGS, config, default_driver="sim")
    kind = c.kind
    par = np.zeros(NPAR)
    par[DP_KIND] = KIND_IDS[kind]
    par[DP_DT] = dt
    par[DP_MASS] = mass = c.mass_kg
    par[DP_B] = c.damping_n_s_per_m
    i_min = None
    if kind == "planar":
        par[DP_IZZ] = i_min = c.inertia_kg_m2
    elif kind == "spatial":
        raw = c.inertia_kg_m2
        if all(isinstance(r, list) for r in raw) and len(raw) == 3 and all(len(r) == 3 for r in raw):
            inertia = np.array(raw, dtype=np.float64)
        else:
            inertia = np.diag(ck.numbers("device.inertia_kg_m2", raw, (3,)))
        if not np.allclose(inertia, inertia.T, rtol=1e-9, atol=1e-15):
            raise ck.fail("device.inertia_kg_m2", "must be symmetric")
        eig = np.linalg.eigvalsh(inertia)
        if not eig[0] > 0:
            raise ck.fail("device.inertia_kg_m2", f"must be positive definite (eigenvalues {eig.tolist()})")
        par[DP_IB:DP_IB + 9] = inertia.ravel()
        i_min = float(eig[0])
        c.inertia_kg_m2 = inertia.tolist() if np.any(inertia != np.diag(np.diag(inertia))) else np.diag(inertia).tolist()
    if kind != "1dof":
        par[DP_BR] = c.rot_damping_n_m_s_per_rad

    # geometry
    axis = np.array([1.0, 0.0, 0.0])
    origin = np.zeros(3)
    if kind == "1dof":
        axis = np.array(c.axis)
        n = float(np.linalg.norm(axis))
        if abs(n - 1.0) > 1e-6:
            raise ck.fail("device.axis", f"must be a unit vector, |axis| = {n:.9g}")
        axis = axis / n
        origin = np.array(c.origin_m)
        par[DP_AXIS:DP_AXIS + 3] = axis
        par[DP_ORIGIN:DP_ORIGIN + 3] = origin
        c.axis, c.origin_m = tuple(axis.tolist()), tuple(origin.tolist())
    lo, hi, dims = workspace(c)
    par[DP_LO:DP_LO + 3] = lo
    par[DP_HI:DP_HI + 3] = hi
    c.workspace_min_m, c.workspace_max_m = lo[:dims].tolist(), hi[:dims].tolist()
    if kind == "1dof":
        if np.any(origin < lo) or np.any(origin > hi):
            raise ck.fail("device.origin_m", f"must be inside the workspace box ({lo.tolist()} .. {hi.tolist()})")
        par[DP_SLO], par[DP_SHI] = _travel(origin, axis, lo, hi)
    else:
        par[DP_ROTLIM] = c.rotation_limit_rad

    # end-stops: the explicit spring must be stable at this period
    k_max = ENDSTOP_STABILITY * mass / dt ** 2
    if c.endstop_stiffness_n_per_m is None:
        c.endstop_stiffness_n_per_m = min(ENDSTOP_STIFFNESS_N_PER_M, mass / dt ** 2)
    if c.endstop_stiffness_n_per_m > k_max:
        raise ck.fail("device.endstop_stiffness_n_per_m", f"{c.endstop_stiffness_n_per_m:g} N/m is unstable at "
                      f"period {dt:g} s with mass {mass:g} kg (at most {k_max:.4g})")
    par[DP_KS] = c.endstop_stiffness_n_per_m
    par[DP_BS] = c.endstop_damping_n_s_per_m
    if kind != "1dof":
        kr_max = ENDSTOP_STABILITY * i_min / dt ** 2
        if c.endstop_rot_stiffness_n_m_per_rad is None:
            c.endstop_rot_stiffness_n_m_per_rad = min(ENDSTOP_ROT_STIFFNESS_N_M_PER_RAD, i_min / dt ** 2)
        if c.endstop_rot_stiffness_n_m_per_rad > kr_max:
            raise ck.fail("device.endstop_rot_stiffness_n_m_per_rad",
                          f"{c.endstop_rot_stiffness_n_m_per_rad:g} N m/rad is unstable at period {dt:g} s with "
                          f"inertia {i_min:g} kg m^2 (at most {kr_max:.4g})")
        par[DP_KSR] = c.endstop_rot_stiffness_n_m_per_rad
        par[DP_BSR] = c.endstop_rot_damping_n_m_s_per_rad

    # limits
    if 0.0 < c.watchdog_s < dt:
        raise ck.fail("device.watchdog_s", f"{c.watchdog_s:g} s is shorter than one period ({dt:g} s); 0 disables it")
    limits = limits_of(c, lo, hi)
    par[DP_FMAX], par[DP_TMAX] = limits.max_force_n, limits.max_torque_n_m
    par[DP_VMAX], par[DP_WMAX] = limits.max_speed_m_per_s, limits.max_angular_speed_rad_per_s

    # initial state
    r = ck.REDUCED_DIMS[kind]
    centre = 0.5 * (lo + hi)
    if c.initial_pose is None:
        c.initial_pose = [0.0] if kind == "1dof" else (
            [centre[0], centre[1], 0.0] if kind == "planar" else [*centre.tolist(), 0.0, 0.0, 0.0])
    pose_arr = ck.numbers("device.initial_pose", c.initial_pose, (r, 7) if kind == "spatial" else (r,))
    pose6 = ck.pose6("device.initial_pose", pose_arr, kind, axis, origin)
    if kind == "1dof":
        s0 = float(pose_arr[0])
        if not par[DP_SLO] <= s0 <= par[DP_SHI]:
            raise ck.fail("device.initial_pose", f"s = {s0:g} is outside the travel [{par[DP_SLO]:g}, {par[DP_SHI]:g}] m")
    else:
        p = pose6[:dims]
        if np.any(p < lo[:dims]) or np.any(p > hi[:dims]):
            raise ck.fail("device.initial_pose", f"position {p.tolist()} is outside the workspace")
        ang = abs(pose6[5]) if kind == "planar" else float(np.linalg.norm(pose6[3:]))
        if par[DP_ROTLIM] > 0 and ang > par[DP_ROTLIM]:
            raise ck.fail("device.initial_pose", f"rotation {ang:g} rad is beyond rotation_limit_rad")
    c.initial_pose = pose_arr.tolist()
    if c.initial_velocity is None:
        c.initial_velocity = [0.0] * r
    vel_arr = ck.numbers("device.initial_velocity", c.initial_velocity, (r,))
    twist6 = ck.vector6("device.initial_velocity", vel_arr, kind, axis)
    c.initial_velocity = vel_arr.tolist()

    hand = _hands.parse_hand(c.hand, kind=kind, axis=axis, origin=origin, rest_pose6=pose6,
                             rest_reduced=c.initial_pose)
    c.hand = hand.config
    values = ck.table(c)
    return SimSpec(kind, dt, par, limits, pose6, twist6, hand, values)


def effective_config(config: dict, *, period_s: float) -> dict:
    """The ``[device]`` table with every key of its kind, defaults filled in (``--print-config``);
    loading it again gives the same device. Raises ``ValueError("device.<key>: ...")``."""
    return parse_sim_config(config, period_s=period_s).values


class SimDevice(DeviceDriver):
    """A simulated device. Owns its arrays; ``read`` and ``write`` are one kernel call each
    (``write`` evaluates the hand, then steps the device, in the one call) and allocate nothing.

    ``clock_ns``: callable returning ns (the loop's clock), used only by the watchdog.
    """

    name = "sim"

    def __init__(self, spec: SimSpec, *, clock_ns=None) -> None:
        self.spec = spec
        self.kind = spec.kind
        self._clock = clock_ns if clock_ns is not None else time.monotonic_ns
        self._par = spec.par.copy()
        self._hp = spec.hand.hp.copy()
        self._tab = spec.hand.tab.copy()
        self._st = np.zeros(NST)
        self._cnt = np.zeros(NCNT, dtype=np.int64)
        self._ctl = np.zeros(NCTL, dtype=np.int64)
        self._ctl[DC_WD_NS] = int(round(spec.limits.watchdog_s * 1e9))
        self._hout = np.zeros(NHO)
        self._cmd = np.zeros(6)
        warm_up()
        self.reset()

    # -- DeviceDriver ------------------------------------------------------------------------
    @property
    def limits(self) -> DeviceLimits:
        return self.spec.limits

    @property
    def info(self) -> DeviceInfo:
        """A simulated device: its figures are its config's (its moving mass, the buttons and
        gripper its hand's scripts use); it advances inside ``write``, so the loop owns the clock."""
        info = info_from_limits(self.kind, self.spec.limits, model=f"simulated {self.kind}", vendor="hapticproxy",
                                driver=self.name, source="config")
        hand = self.spec.hand
        return replace(info, buttons=hand.buttons, gripper=hand.gripper,
                       sensed=info.sensed + (("gripper",) if hand.gripper else ()),
                       moving_mass_kg=float(self.spec.par[DP_MASS]),
                       moving_inertia_kg_m2=self._inertia_min(), moving_inertia_max_kg_m2=self._inertia_min(-1),
                       damping_n_s_per_m=float(self.spec.par[DP_B]),
                       rot_damping_n_m_s_per_rad=float(self.spec.par[DP_BR]) if self.kind != "1dof" else None)

    def _inertia_min(self, which: int = 0):
        """The handle's smallest principal moment (``which`` -1: the largest); None for one axis."""
        if self.kind == "planar":
            return float(self.spec.par[DP_IZZ])
        if self.kind == "spatial":
            return float(np.linalg.eigvalsh(self.spec.par[DP_IB:DP_IB + 9].reshape(3, 3))[which])
        return None

    def enable(self) -> None:
        """Arm the output; clears a latched fault (a simulated device's causes are all gone)."""
        self._ctl[DC_FAULT] = DEV_OK
        self._ctl[DC_LAST_NS] = self._clock()
        self._ctl[DC_ENABLED] = 1

    def disable(self) -> None:
        self._ctl[DC_ENABLED] = 0
        self._st[DST_CMD:DST_CMD + 6] = 0.0

    enabled = ArrayBool("_ctl", DC_ENABLED, doc="The output is armed (``enable``).")
    fault = ArrayInt("_ctl", DC_FAULT, doc="The latched ``DEV_FAULT_*`` code (0: none).")

    def read(self, state_out: np.ndarray) -> int:
        return _dyn.sim_read(self._st, self._ctl, self._cnt, state_out, self._clock())

    def write(self, wrench: np.ndarray) -> int:
        cmd = self._cmd
        if not (type(wrench) is np.ndarray and wrench.dtype == cmd.dtype and wrench.shape == cmd.shape):
            self._copy_command(wrench)  # checked (raises on a bad shape), into cmd
            wrench = cmd
        return _dyn.sim_write_hand(self._par, self._st, self._cnt, self._ctl, self._hp, self._tab, self._hout, wrench,
                                   cmd, self._clock())

    # -- extras --------------------------------------------------------------------------------
    def warm_up(self) -> None:
        """Compile / load the kernels (done at construction already; cheap to repeat)."""
        warm_up()

    def on_engage(self) -> None:
        """A new session engaged: a hand whose script starts at engagement starts it now."""
        if self.spec.hand.config.get("start") == "engagement":
            self._hp[_hands.HP_T0] = self._st[DST_TIME]
            self._hp[_hands.HP_WAIT] = 0.0
            _hands.hand_eval(self._hp, self._tab, self._st, self._hout)
            _hands.inputs_eval(self._hp, self._tab, self._st)
            _dyn.sim_hand_now(self._par, self._st, self._hout)  # the sensor reads the hand at once

    def _copy_command(self, wrench) -> None:
        a = np.asarray(wrench, dtype=np.float64)
        if a.shape != (6,):
            raise ValueError(f"wrench: expected 6 numbers (fx fy fz tx ty tz), got shape {a.shape}")
        self._cmd[:] = a

    def reset(self, pose=None, velocity=None) -> None:
        """Put the device at rest (or at ``velocity``) at ``pose`` (reduced coordinates, as in
        the config; default: the configured initial state). Time and counters restart at 0;
        enable state and latched faults are kept."""
        spec = self.spec
        axis = self._par[DP_AXIS:DP_AXIS + 3].copy()
        origin = self._par[DP_ORIGIN:DP_ORIGIN + 3].copy()
        r = ck.REDUCED_DIMS[self.kind]
        if pose is None:
            pose6 = spec.initial_pose6
            s0 = float(spec.values["initial_pose"][0])
        else:
            lens = (r, 7) if self.kind == "spatial" else (r,)
            pa = ck.numbers("pose", pose, lens)
            pose6 = ck.pose6("pose", pa, self.kind, axis, origin)
            s0 = float(pa[0])
        twist6 = spec.initial_twist6 if velocity is None else ck.vector6(
            "velocity", ck.numbers("velocity", velocity, (r,)), self.kind, axis)
        st = self._st
        st[:] = 0.0
        self._cnt[:] = 0
        self._hp[_hands.HP_T0] = 0.0
        self._hp[_hands.HP_WAIT] = spec.hand.hp[_hands.HP_WAIT]  # a waiting script waits again
        if self.kind == "1dof":
            st[DST_S] = s0
            st[DST_SD] = float(np.dot(twist6[:3], axis))
            st[DST_POSE:DST_POSE + 3] = origin + s0 * axis
            st[DST_POSE + 3] = 1.0
            st[DST_TWIST:DST_TWIST + 3] = st[DST_SD] * axis
        elif self.kind == "planar":
            th = pose6[5]
            st[DST_TH] = th
            st[DST_POSE:DST_POSE + 2] = pose6[:2]
            st[DST_POSE + 3] = math.cos(0.5 * th)
            st[DST_POSE + 6] = math.sin(0.5 * th)
            st[DST_TWIST:DST_TWIST + 2] = twist6[:2]
            st[DST_TWIST + 5] = twist6[5]
        else:
            st[DST_POSE:DST_POSE + 3] = pose6[:3]
            st[DST_POSE + 3:DST_POSE + 7] = _dyn.qexp(*pose6[3:])
            st[DST_TWIST:DST_TWIST + 6] = twist6
        _hands.hand_eval(self._hp, self._tab, st, self._hout)
        _hands.inputs_eval(self._hp, self._tab, st)
        _dyn.sim_hand_now(self._par, st, self._hout)

    @property
    def period_s(self) -> float:
        return self.spec.period_s

    time_s = ArrayFloat("_st", DST_TIME, doc="Device clock, s (0 at ``reset``).")

    @property
    def state(self) -> np.ndarray:
        """A copy of the current state row (float64[DEV_NSTATE])."""
        return self._st[:DEV_NSTATE].copy()

    @property
    def last_command(self) -> np.ndarray:
        """The wrench rendered in the last step (masked and capped), world, at the handle."""
        return self._st[DST_CMD:DST_CMD + 6].copy()

    @property
    def endstop_wrench(self) -> np.ndarray:
        """The end-stop wrench of the last step, world (zero when inside the workspace)."""
        return self._st[DST_STOP:DST_STOP + 6].copy()

    @property
    def hand(self) -> _hands.Hand:
        return self.spec.hand

    def counters(self) -> dict[str, int]:
        return {name: int(v) for name, v in zip(COUNTER_NAMES, self._cnt)}

    def status_text(self) -> str:
        return DEV_FAULT_NAMES.get(self.fault, f"fault {self.fault}")

    def arrays(self):
        """The raw arrays (par, state, counters, control, hand params, hand table), for tests."""
        return self._par, self._st, self._cnt, self._ctl, self._hp, self._tab

    def tick_arrays(self):
        """What the compiled haptic tick (``server/tick.py``) reads and writes to run this device
        inside its own call: ``(par, state, counters, control, hand params, hand table, hand output,
        command)``, as ``dynamics.sim_read`` / ``sim_write_hand`` take them."""
        return self._par, self._st, self._cnt, self._ctl, self._hp, self._tab, self._hout, self._cmd


def make_sim_device(config: dict, *, period_s: float, clock_ns=None) -> SimDevice:
    """Entry point ``sim``: build a simulated device from the ``[device]`` table."""
    return SimDevice(parse_sim_config(config, period_s=period_s), clock_ns=clock_ns)


#: the config loader asks the driver for its effective table (``server/config.py``)
make_sim_device.effective_config = effective_config


_WARM = False


def warm_up() -> None:
    """Load (or compile, first time on a machine) the device and hand kernels for every kind,
    once per process, on throw-away arrays, so the first haptic step does not pay for it."""
    global _WARM
    if _WARM:
        return
    par, st, cnt, ctl, hout = _dyn.warm_arrays()
    hp = np.zeros(_hands.NHP)
    tab = np.zeros((2, _hands.NTAB))
    tab[1, 0] = 1.0
    out = np.zeros(DEV_NSTATE)
    w = np.zeros(6)
    for kind in KIND_IDS.values():
        par[:] = 0.0
        par[DP_KIND] = kind
        par[DP_DT] = 1e-3
        par[DP_MASS] = 1.0
        par[DP_IZZ] = 1.0
        par[DP_IB:DP_IB + 9] = np.eye(3).ravel()
        par[DP_AXIS] = 1.0
        par[DP_SLO], par[DP_SHI] = -1.0, 1.0
        par[DP_LO:DP_LO + 3], par[DP_HI:DP_HI + 3] = -1.0, 1.0
        par[DP_FMAX] = par[DP_TMAX] = par[DP_VMAX] = par[DP_WMAX] = 1.0
        st[:] = 0.0
        st[DST_POSE + 3] = 1.0
        ctl[DC_ENABLED] = 1
        for mode, prof in ((0, 0), (1, 1), (1, 2), (2, 3)):
            hp[_hands.HP_MODE] = mode
            hp[_hands.HP_PROF] = prof
            hp[_hands.HP_NROWS] = 2
            _hands.hand_eval(hp, tab, st, hout)
            _hands.inputs_eval(hp, tab, st)
            _dyn.sim_write(par, st, cnt, ctl, hout, w, 0)
            _dyn.sim_write_hand(par, st, cnt, ctl, hp, tab, hout, w, np.zeros(6), 0)
        _dyn.sim_hand_now(par, st, hout)
        _dyn.sim_read(st, ctl, cnt, out, 0)
        _dyn.qexp(0.0, 0.0, 0.0)
    _WARM = True

#: for `hapticproxy plugins` and `hapticproxy devices`
make_sim_device.about = {"clock": "loop", "models": ["simulated 1dof / planar / spatial"]}
