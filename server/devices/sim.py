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
workspace +-6 cm in x and y, rotation +-1 rad, 10 N and 0.5 N m peak.

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
``workspace_min_m``, ``workspace_max_m`` = +-0.1 on x y z / +-0.06 on x y / +-0.1 on x y z
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
from dataclasses import dataclass, field

import numpy as np

from . import _check as ck
from . import dynamics as _dyn
from . import hands as _hands
from .base import (
    DEV_FAULT_NAMES, DEV_NSTATE, DEV_OK, DEVICE_KINDS, DeviceDriver, DeviceLimits,
)
from .layout import (
    C_ENABLED, C_FAULT, C_LAST_NS, C_WD_NS, COUNTER_NAMES, KIND_IDS, NCNT, NCTL, NHO, NPAR, NST,
    P_AXIS, P_B, P_BR, P_BS, P_BSR, P_DT, P_FMAX, P_HI, P_IB, P_IZZ, P_KIND, P_KS, P_KSR, P_LO,
    P_MASS, P_ORIGIN, P_ROTLIM, P_SHI, P_SLO, P_TMAX, P_VMAX, P_WMAX,
    ST_CMD, ST_POSE, ST_S, ST_SD, ST_STOP, ST_TH, ST_TWIST,
)

#: Per-kind defaults (``None``: the key does not apply to the kind).
KIND_DEFAULTS: dict[str, dict] = {
    "1dof": {
        "mass_kg": 0.2, "inertia_kg_m2": None, "damping_n_s_per_m": 1.0, "rot_damping_n_m_s_per_rad": None,
        "axis": [1.0, 0.0, 0.0], "origin_m": [0.0, 0.0, 0.0],
        "workspace_min_m": [-0.1, -0.1, -0.1], "workspace_max_m": [0.1, 0.1, 0.1],
        "rotation_limit_rad": None, "max_force_n": 10.0, "max_torque_n_m": None,
        "max_angular_speed_rad_per_s": None,
        "endstop_rot_stiffness_n_m_per_rad": None, "endstop_rot_damping_n_m_s_per_rad": None,
    },
    "planar": {
        "mass_kg": 0.4, "inertia_kg_m2": 1.0e-3, "damping_n_s_per_m": 2.0, "rot_damping_n_m_s_per_rad": 2e-3,
        "axis": None, "origin_m": None,
        "workspace_min_m": [-0.06, -0.06], "workspace_max_m": [0.06, 0.06],
        "rotation_limit_rad": 1.0, "max_force_n": 10.0, "max_torque_n_m": 0.5,
        "max_angular_speed_rad_per_s": 20.0,
    },
    "spatial": {
        "mass_kg": 0.3, "inertia_kg_m2": [6e-4, 6e-4, 4e-4], "damping_n_s_per_m": 1.0,
        "rot_damping_n_m_s_per_rad": 1e-3, "axis": None, "origin_m": None,
        "workspace_min_m": [-0.1, -0.1, -0.1], "workspace_max_m": [0.1, 0.1, 0.1],
        "rotation_limit_rad": 1.0, "max_force_n": 8.0, "max_torque_n_m": 0.5,
        "max_angular_speed_rad_per_s": 20.0,
    },
}
COMMON_DEFAULTS = {
    "endstop_damping_n_s_per_m": 50.0,
    "endstop_rot_damping_n_m_s_per_rad": 0.05,
    "max_speed_m_per_s": 2.0,
    "watchdog_s": 0.05,
}
ENDSTOP_STIFFNESS_N_PER_M = 20000.0
ENDSTOP_ROT_STIFFNESS_N_M_PER_RAD = 20.0
#: k dt^2 / m at most this (symplectic Euler is stable below 4 for an undamped spring)
ENDSTOP_STABILITY = 2.0

CONFIG_KEYS = (
    "driver", "kind", "mass_kg", "inertia_kg_m2", "damping_n_s_per_m", "rot_damping_n_m_s_per_rad",
    "axis", "origin_m", "workspace_min_m", "workspace_max_m", "rotation_limit_rad",
    "endstop_stiffness_n_per_m", "endstop_damping_n_s_per_m", "endstop_rot_stiffness_n_m_per_rad",
    "endstop_rot_damping_n_m_s_per_rad", "max_force_n", "max_torque_n_m", "max_speed_m_per_s",
    "max_angular_speed_rad_per_s", "watchdog_s", "initial_pose", "initial_velocity", "hand",
)


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


def parse_sim_config(config: dict, *, period_s: float) -> SimSpec:
    """Validate a ``[device]`` table for the ``sim`` driver. Raises ``ValueError("device.<key>: ...")``."""
    dt = _period(period_s)
    if config is None:
        config = {}
    ck.check_keys("device", config, CONFIG_KEYS)
    if "driver" in config:
        ck.string("device.driver", config["driver"])
    kind = ck.string("device.kind", config.get("kind", "planar"), DEVICE_KINDS)
    kd = {**COMMON_DEFAULTS, **KIND_DEFAULTS[kind]}
    for k, v in kd.items():
        if v is None and k in config:
            raise ck.fail(f"device.{k}", f"does not apply to a {kind} device")

    def get(k):
        return config.get(k, kd.get(k))

    values: dict = {"driver": config.get("driver", "sim"), "kind": kind}
    par = np.zeros(NPAR)
    par[P_KIND] = KIND_IDS[kind]
    par[P_DT] = dt
    mass = ck.num("device.mass_kg", get("mass_kg"), lo=0.0, lo_open=True, hi=1e3)
    par[P_MASS] = mass
    par[P_B] = ck.num("device.damping_n_s_per_m", get("damping_n_s_per_m"), lo=0.0, hi=1e5)
    values.update(mass_kg=mass, damping_n_s_per_m=par[P_B])
    i_min = None
    if kind == "planar":
        izz = ck.num("device.inertia_kg_m2", get("inertia_kg_m2"), lo=0.0, lo_open=True, hi=1e3)
        par[P_IZZ] = izz
        i_min = izz
        values["inertia_kg_m2"] = izz
    elif kind == "spatial":
        raw = get("inertia_kg_m2")
        arr = np.asarray(raw, dtype=object)
        if arr.shape == (3, 3):
            inertia = np.array([[ck.num(f"device.inertia_kg_m2[{i}][{j}]", raw[i][j]) for j in range(3)]
                                for i in range(3)])
        else:
            inertia = np.diag(ck.numbers("device.inertia_kg_m2", raw, (3,)))
        if not np.allclose(inertia, inertia.T, rtol=1e-9, atol=1e-15):
            raise ck.fail("device.inertia_kg_m2", "must be symmetric")
        eig = np.linalg.eigvalsh(inertia)
        if not eig[0] > 0:
            raise ck.fail("device.inertia_kg_m2", f"must be positive definite (eigenvalues {eig.tolist()})")
        par[P_IB:P_IB + 9] = inertia.ravel()
        i_min = float(eig[0])
        values["inertia_kg_m2"] = inertia.tolist()
    if kind != "1dof":
        par[P_BR] = ck.num("device.rot_damping_n_m_s_per_rad", get("rot_damping_n_m_s_per_rad"), lo=0.0, hi=1e3)
        values["rot_damping_n_m_s_per_rad"] = par[P_BR]

    # geometry
    axis = np.array([1.0, 0.0, 0.0])
    origin = np.zeros(3)
    if kind == "1dof":
        axis = ck.numbers("device.axis", get("axis"), (3,))
        n = float(np.linalg.norm(axis))
        if abs(n - 1.0) > 1e-6:
            raise ck.fail("device.axis", f"must be a unit vector, |axis| = {n:.9g}")
        axis = axis / n
        origin = ck.numbers("device.origin_m", get("origin_m"), (3,))
        par[P_AXIS:P_AXIS + 3] = axis
        par[P_ORIGIN:P_ORIGIN + 3] = origin
        values.update(axis=axis.tolist(), origin_m=origin.tolist())
    lens = (2, 3) if kind == "planar" else (3,)
    lo = ck.numbers("device.workspace_min_m", get("workspace_min_m"), lens)
    hi = ck.numbers("device.workspace_max_m", get("workspace_max_m"), lens)
    if kind == "planar":
        lo, hi = np.append(lo[:2], 0.0), np.append(hi[:2], 0.0)
        dims = 2
    else:
        dims = 3
    for i in range(dims):
        if not hi[i] > lo[i]:
            raise ck.fail("device.workspace_max_m", f"must exceed workspace_min_m on every axis ({lo.tolist()} .. {hi.tolist()})")
    par[P_LO:P_LO + 3] = lo
    par[P_HI:P_HI + 3] = hi
    values.update(workspace_min_m=lo[:dims].tolist(), workspace_max_m=hi[:dims].tolist())
    if kind == "1dof":
        if np.any(origin < lo) or np.any(origin > hi):
            raise ck.fail("device.origin_m", f"must be inside the workspace box ({lo.tolist()} .. {hi.tolist()})")
        s_lo, s_hi = _travel(origin, axis, lo, hi)
        par[P_SLO], par[P_SHI] = s_lo, s_hi
    if kind != "1dof":
        lim = ck.num("device.rotation_limit_rad", get("rotation_limit_rad"), lo=0.0, hi=math.pi)
        par[P_ROTLIM] = lim
        values["rotation_limit_rad"] = lim

    # end-stops: the explicit spring must be stable at this period
    k_max = ENDSTOP_STABILITY * mass / dt ** 2
    ks = ck.num("device.endstop_stiffness_n_per_m",
                config.get("endstop_stiffness_n_per_m", min(ENDSTOP_STIFFNESS_N_PER_M, mass / dt ** 2)), lo=0.0)
    if ks > k_max:
        raise ck.fail("device.endstop_stiffness_n_per_m",
                      f"{ks:g} N/m is unstable at period {dt:g} s with mass {mass:g} kg (at most {k_max:.4g})")
    par[P_KS] = ks
    par[P_BS] = ck.num("device.endstop_damping_n_s_per_m", get("endstop_damping_n_s_per_m"), lo=0.0, hi=1e6)
    values.update(endstop_stiffness_n_per_m=ks, endstop_damping_n_s_per_m=par[P_BS])
    if kind != "1dof":
        kr_max = ENDSTOP_STABILITY * i_min / dt ** 2
        ksr = ck.num("device.endstop_rot_stiffness_n_m_per_rad",
                     config.get("endstop_rot_stiffness_n_m_per_rad",
                                min(ENDSTOP_ROT_STIFFNESS_N_M_PER_RAD, i_min / dt ** 2)), lo=0.0)
        if ksr > kr_max:
            raise ck.fail("device.endstop_rot_stiffness_n_m_per_rad",
                          f"{ksr:g} N m/rad is unstable at period {dt:g} s with inertia {i_min:g} kg m^2 "
                          f"(at most {kr_max:.4g})")
        par[P_KSR] = ksr
        par[P_BSR] = ck.num("device.endstop_rot_damping_n_m_s_per_rad", get("endstop_rot_damping_n_m_s_per_rad"),
                            lo=0.0, hi=1e4)
        values.update(endstop_rot_stiffness_n_m_per_rad=ksr, endstop_rot_damping_n_m_s_per_rad=par[P_BSR])

    # limits
    fmax = ck.num("device.max_force_n", get("max_force_n"), lo=0.0, lo_open=True, hi=1e4)
    tmax = 0.0
    if kind != "1dof":
        tmax = ck.num("device.max_torque_n_m", get("max_torque_n_m"), lo=0.0, lo_open=True, hi=1e3)
    vmax = ck.num("device.max_speed_m_per_s", get("max_speed_m_per_s"), lo=0.0, lo_open=True, hi=1e3)
    wmax = math.inf  # a 1dof device cannot turn: no angular-speed limit applies
    if kind != "1dof":
        wmax = ck.num("device.max_angular_speed_rad_per_s", get("max_angular_speed_rad_per_s"),
                      lo=0.0, lo_open=True, hi=1e4)
    wd = ck.num("device.watchdog_s", get("watchdog_s"), lo=0.0, hi=10.0)
    if 0.0 < wd < dt:
        raise ck.fail("device.watchdog_s", f"{wd:g} s is shorter than one period ({dt:g} s); 0 disables it")
    par[P_FMAX], par[P_TMAX], par[P_VMAX] = fmax, tmax, vmax
    par[P_WMAX] = wmax
    values.update(max_force_n=fmax, max_speed_m_per_s=vmax, watchdog_s=wd)
    if kind != "1dof":
        values.update(max_torque_n_m=tmax, max_angular_speed_rad_per_s=wmax)
    limits = DeviceLimits(max_force_n=fmax, max_torque_n_m=tmax, max_speed_m_per_s=vmax,
                          max_angular_speed_rad_per_s=wmax, workspace_min_m=tuple(lo.tolist()),
                          workspace_max_m=tuple(hi.tolist()), watchdog_s=wd)

    # initial state
    r = ck.REDUCED_DIMS[kind]
    centre = 0.5 * (lo + hi)
    if kind == "1dof":
        default_pose = [0.0]
    elif kind == "planar":
        default_pose = [centre[0], centre[1], 0.0]
    else:
        default_pose = [*centre.tolist(), 0.0, 0.0, 0.0]
    pose_in = config.get("initial_pose", default_pose)
    lens_p = (r, 7) if kind == "spatial" else (r,)
    pose_arr = ck.numbers("device.initial_pose", pose_in, lens_p)
    pose6 = ck.pose6("device.initial_pose", pose_arr, kind, axis, origin)
    if kind == "1dof":
        s0 = float(pose_arr[0])
        if not par[P_SLO] <= s0 <= par[P_SHI]:
            raise ck.fail("device.initial_pose", f"s = {s0:g} is outside the travel [{par[P_SLO]:g}, {par[P_SHI]:g}] m")
    else:
        p = pose6[:dims]
        if np.any(p < lo[:dims]) or np.any(p > hi[:dims]):
            raise ck.fail("device.initial_pose", f"position {p.tolist()} is outside the workspace")
        ang = abs(pose6[5]) if kind == "planar" else float(np.linalg.norm(pose6[3:]))
        if par[P_ROTLIM] > 0 and ang > par[P_ROTLIM]:
            raise ck.fail("device.initial_pose", f"rotation {ang:g} rad is beyond rotation_limit_rad")
    values["initial_pose"] = pose_arr.tolist()
    vel_arr = ck.numbers("device.initial_velocity", config.get("initial_velocity", [0.0] * r), (r,))
    twist6 = ck.vector6("device.initial_velocity", vel_arr, kind, axis)
    values["initial_velocity"] = vel_arr.tolist()

    hand = _hands.parse_hand(config.get("hand", {"type": "none"}), kind=kind, axis=axis, origin=origin,
                             rest_pose6=pose6)
    values["hand"] = hand.config or {"type": "none"}
    return SimSpec(kind, dt, par, limits, pose6, twist6, hand, values)


class SimDevice(DeviceDriver):
    """A simulated device. Owns its arrays; ``read`` and ``write`` are one kernel call each
    (``write`` two: the hand, then the device) and allocate nothing.

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
        self._ctl[C_WD_NS] = int(round(spec.limits.watchdog_s * 1e9))
        self._hout = np.zeros(NHO)
        self._cmd = np.zeros(6)
        warm_up()
        self.reset()

    # -- DeviceDriver ------------------------------------------------------------------------
    @property
    def limits(self) -> DeviceLimits:
        return self.spec.limits

    def enable(self) -> None:
        """Arm the output; clears a latched fault (a simulated device's causes are all gone)."""
        self._ctl[C_FAULT] = DEV_OK
        self._ctl[C_LAST_NS] = self._clock()
        self._ctl[C_ENABLED] = 1

    def disable(self) -> None:
        self._ctl[C_ENABLED] = 0
        self._st[ST_CMD:ST_CMD + 6] = 0.0

    @property
    def enabled(self) -> bool:
        return bool(self._ctl[C_ENABLED])

    @property
    def fault(self) -> int:
        return int(self._ctl[C_FAULT])

    def read(self, state_out: np.ndarray) -> int:
        return _dyn.sim_read(self._st, self._ctl, self._cnt, state_out, self._clock())

    def write(self, wrench: np.ndarray) -> int:
        cmd = self._cmd
        if type(wrench) is np.ndarray and wrench.dtype == cmd.dtype and wrench.shape == cmd.shape:
            cmd[:] = wrench
        else:
            self._copy_command(wrench)
        _hands.hand_eval(self._hp, self._tab, self._st, self._hout)
        return _dyn.sim_write(self._par, self._st, self._cnt, self._ctl, self._hout, cmd, self._clock())

    # -- extras --------------------------------------------------------------------------------
    def warm_up(self) -> None:
        """Compile / load the kernels (done at construction already; cheap to repeat)."""
        warm_up()

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
        axis = self._par[P_AXIS:P_AXIS + 3].copy()
        origin = self._par[P_ORIGIN:P_ORIGIN + 3].copy()
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
        if self.kind == "1dof":
            st[ST_S] = s0
            st[ST_SD] = float(np.dot(twist6[:3], axis))
            st[ST_POSE:ST_POSE + 3] = origin + s0 * axis
            st[ST_POSE + 3] = 1.0
            st[ST_TWIST:ST_TWIST + 3] = st[ST_SD] * axis
        elif self.kind == "planar":
            th = pose6[5]
            st[ST_TH] = th
            st[ST_POSE:ST_POSE + 2] = pose6[:2]
            st[ST_POSE + 3] = math.cos(0.5 * th)
            st[ST_POSE + 6] = math.sin(0.5 * th)
            st[ST_TWIST:ST_TWIST + 2] = twist6[:2]
            st[ST_TWIST + 5] = twist6[5]
        else:
            st[ST_POSE:ST_POSE + 3] = pose6[:3]
            st[ST_POSE + 3:ST_POSE + 7] = _dyn.qexp(*pose6[3:])
            st[ST_TWIST:ST_TWIST + 6] = twist6
        _hands.hand_eval(self._hp, self._tab, st, self._hout)
        _dyn.sim_hand_now(self._par, st, self._hout)

    @property
    def period_s(self) -> float:
        return self.spec.period_s

    @property
    def time_s(self) -> float:
        return float(self._st[19])

    @property
    def state(self) -> np.ndarray:
        """A copy of the current state row (float64[DEV_NSTATE])."""
        return self._st[:DEV_NSTATE].copy()

    @property
    def last_command(self) -> np.ndarray:
        """The wrench rendered in the last step (masked and capped), world, at the handle."""
        return self._st[ST_CMD:ST_CMD + 6].copy()

    @property
    def endstop_wrench(self) -> np.ndarray:
        """The end-stop wrench of the last step, world (zero when inside the workspace)."""
        return self._st[ST_STOP:ST_STOP + 6].copy()

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


def make_sim_device(config: dict, *, period_s: float, clock_ns=None) -> SimDevice:
    """Entry point ``sim``: build a simulated device from the ``[device]`` table."""
    return SimDevice(parse_sim_config(config, period_s=period_s), clock_ns=clock_ns)


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
        par[P_KIND] = kind
        par[P_DT] = 1e-3
        par[P_MASS] = 1.0
        par[P_IZZ] = 1.0
        par[P_IB:P_IB + 9] = np.eye(3).ravel()
        par[P_AXIS] = 1.0
        par[P_SLO], par[P_SHI] = -1.0, 1.0
        par[P_LO:P_LO + 3], par[P_HI:P_HI + 3] = -1.0, 1.0
        par[P_FMAX] = par[P_TMAX] = par[P_VMAX] = par[P_WMAX] = 1.0
        st[:] = 0.0
        st[ST_POSE + 3] = 1.0
        ctl[C_ENABLED] = 1
        for mode, prof in ((0, 0), (1, 1), (1, 2), (2, 3)):
            hp[_hands.HP_MODE] = mode
            hp[_hands.HP_PROF] = prof
            hp[_hands.HP_NROWS] = 2
            _hands.hand_eval(hp, tab, st, hout)
            _dyn.sim_write(par, st, cnt, ctl, hout, w, 0)
        _dyn.sim_hand_now(par, st, hout)
        _dyn.sim_read(st, ctl, cnt, out, 0)
        _dyn.qexp(0.0, 0.0, 0.0)
    _WARM = True
