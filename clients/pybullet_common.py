"""What the pybullet engines share: connecting a physics server, building bodies, reading body
states into the narrow phase's table, and the force-bounded pose drive.

The only place where pybullet's quaternion order ``(x, y, z, w)`` meets the protocol's
``(w, x, y, z)``: every function here takes and returns protocol-order quaternions and converts
with :func:`.geometry.xyzw_from_wxyz` / :func:`.geometry.wxyz_from_xyzw` when it talks to pybullet.

The drive (:class:`PoseDrive`; why this and not a kinematic update, see :mod:`.pybullet_engine`):
a ``JOINT_FIXED`` user constraint from a body's base (its COM frame) to a world set-point, bounded
by ``max_force_n`` (N for the force rows, N m for the torque rows) and solved by Bullet with the
contacts. The set-point leads the body's current pose by at most one step at the speed bounds
(the constraint closes ``erp`` of the gap per step), so the body moves at most ``max_speed * dt``
per step; an engine may cut the set-point's translation further (:meth:`PoseDrive.lead`'s
``guard``).
"""
from __future__ import annotations

import importlib.metadata
import math
import os
import sys

import numpy as np
from ._pybullet import p

from .engine import Engine, SceneInfo, checked_epsilon, checked_positive
from .geometry import quat_angle, slerp, wxyz_from_xyzw, xyzw_from_wxyz
from .narrowphase import E_ANG, E_HALF, E_LIN, E_POS, E_QUAT, BoxNarrowPhase, warm_up_kernels

__all__ = ["PYBULLET_VERSION", "GRAVITY_M_PER_S2", "connect", "reset_world", "show_world", "close_world", "base_pose",
           "fill_env_row", "make_box", "make_sphere", "PoseDrive", "PybulletBase"]

PYBULLET_VERSION = importlib.metadata.version("pybullet")
GRAVITY_M_PER_S2 = 9.81


#: the GUI connections open; while there is one, the C stdout is muted (:func:`_mute_c_stdout`)
_GUI_CIDS: set[int] = set()
_MUTED: dict = {}


def _mute_c_stdout(on: bool) -> None:
    """pybullet's GUI (its example browser, in C threads) prints about 25 lines to the C stdout
    (threads, X11, the GL context, its shutdown), some from its own thread after ``connect`` has
    returned: while a GUI is open, fd 1 points at /dev/null and Python's ``sys.stdout`` writes to
    a copy of the real one, so the command's own output is unchanged."""
    if on and not _MUTED:
        try:
            sys.stdout.flush()
            python_on_fd1 = sys.stdout.fileno() == 1
        except (AttributeError, OSError, ValueError):  # not a real stream (captured): it never uses fd 1
            python_on_fd1 = False
        saved = os.dup(1)
        null = os.open(os.devnull, os.O_WRONLY)
        os.dup2(null, 1)
        os.close(null)
        _MUTED["fd"] = saved
        if python_on_fd1:
            out = sys.stdout
            _MUTED["stdout"] = out
            sys.stdout = open(os.dup(saved), "w", buffering=1 if out.line_buffering else -1,  # noqa: SIM115
                              encoding=out.encoding, errors=out.errors)
    elif not on and _MUTED:
        out = _MUTED.pop("stdout", None)
        if out is not None:
            sys.stdout.flush()
            sys.stdout.close()
            sys.stdout = out
        saved = _MUTED.pop("fd")
        os.dup2(saved, 1)
        os.close(saved)


def connect(gui: bool) -> int:
    """A new physics server (``GUI`` or ``DIRECT``); ``RuntimeError`` if pybullet refuses. A GUI
    mutes the C stdout until :func:`close_world` closes it (:func:`_mute_c_stdout`)."""
    if gui:
        _mute_c_stdout(True)
    cid = p.connect(p.GUI if gui else p.DIRECT)
    if cid < 0:
        if gui and not _GUI_CIDS:
            _mute_c_stdout(False)
        raise RuntimeError("pybullet: could not connect a physics server" + (" (GUI: is there a display?)" if gui else ""))
    if gui:
        _GUI_CIDS.add(cid)
    return cid


def reset_world(cid: int, dt_s: float, solver_iterations: int, erp: float, gui: bool) -> None:
    """An empty world: gravity -z, the step, the solver's iterations and its global ``erp`` (used
    by the drive's constraint only: the scenes have no joints, contacts use their own
    ``contactERP``); a GUI stops rendering while the scene is built (:func:`show_world`)."""
    p.resetSimulation(physicsClientId=cid)
    p.setGravity(0.0, 0.0, -GRAVITY_M_PER_S2, physicsClientId=cid)
    p.setTimeStep(dt_s, physicsClientId=cid)
    p.setPhysicsEngineParameter(numSolverIterations=solver_iterations, erp=erp, physicsClientId=cid)
    if gui:
        p.configureDebugVisualizer(p.COV_ENABLE_RENDERING, 0, physicsClientId=cid)


def show_world(cid: int) -> None:
    p.configureDebugVisualizer(p.COV_ENABLE_RENDERING, 1, physicsClientId=cid)


def close_world(cid: int, window=None) -> int:
    """Close the window (if any) and the physics server (if still connected); returns -1."""
    if window is not None:
        window.close()
    if cid >= 0:
        p.disconnect(physicsClientId=cid)
    if cid in _GUI_CIDS:
        _GUI_CIDS.discard(cid)
        if not _GUI_CIDS:
            _mute_c_stdout(False)
    return -1


def base_pose(cid: int, body: int) -> tuple[tuple, tuple]:
    """``(COM position, quaternion w x y z)`` of a body's base, world."""
    pos, orn = p.getBasePositionAndOrientation(body, physicsClientId=cid)
    return tuple(pos), wxyz_from_xyzw(orn)


def fill_env_row(env: np.ndarray, row: int, pos, orn_xyzw, lin=None, ang=None) -> None:
    """Write a body's pose (pybullet's quaternion order, as pybullet returns it) and velocity
    into row ``row`` of the narrow phase's environment table (protocol order)."""
    env[row, E_POS:E_POS + 3] = pos
    env[row, E_QUAT:E_QUAT + 4] = (orn_xyzw[3], orn_xyzw[0], orn_xyzw[1], orn_xyzw[2])  # to w x y z
    if lin is not None:
        env[row, E_LIN:E_LIN + 3] = lin
        env[row, E_ANG:E_ANG + 3] = ang


def set_env_shape(env: np.ndarray, row: int, half_or_radius) -> None:
    env[row, E_HALF:E_HALF + 3] = half_or_radius


def make_box(cid: int, half, pos, mass: float = 0.0, rgba=None, *, maximal: bool = True, visual: bool = False) -> int:
    """A box body (half extents ``half``, centre ``pos``, identity rotation); a visual shape only
    when ``visual`` (a GUI)."""
    shape = p.createCollisionShape(p.GEOM_BOX, halfExtents=list(half), physicsClientId=cid)
    vis = -1
    if visual:
        vis = p.createVisualShape(p.GEOM_BOX, halfExtents=list(half), rgbaColor=list(rgba or (0.6, 0.6, 0.6, 1.0)),
                                  physicsClientId=cid)
    return p.createMultiBody(mass, shape, vis, list(pos), useMaximalCoordinates=maximal, physicsClientId=cid)


def make_sphere(cid: int, radius: float, pos, mass: float = 0.0, rgba=None, *, visual: bool = False) -> int:
    shape = p.createCollisionShape(p.GEOM_SPHERE, radius=radius, physicsClientId=cid)
    vis = -1
    if visual:
        vis = p.createVisualShape(p.GEOM_SPHERE, radius=radius, rgbaColor=list(rgba or (0.6, 0.6, 0.6, 1.0)),
                                  physicsClientId=cid)
    return p.createMultiBody(mass, shape, vis, list(pos), useMaximalCoordinates=True, physicsClientId=cid)


class PybulletBase(Engine):
    """What the pybullet engines share: their own physics client (``_cid``), scene names
    (``_SCENES``), the epsilon, the narrow phase's warm-up, closing (the window too)."""

    #: Bullet in DIRECT mode steps the same calls to the same results (the contract suite checks it)
    deterministic = True
    _SCENES: tuple[str, ...] = ()
    _cid = -1
    _tool = -1
    _epsilon = 0.0
    _scene: SceneInfo | None = None
    #: the GUI's view (``gui=True``, after ``load_scene``): ``window.update(runner)`` draws
    window = None

    @classmethod
    def scenes(cls) -> tuple[str, ...]:
        return cls._SCENES

    def _init_drive(self, *, gui: bool, rate_hz: float, max_drive_force_n: float, drive_erp: float,
                    max_speed_m_per_s: float, max_angular_speed_rad_per_s: float, solver_iterations: int,
                    **positive: float) -> None:
        """Check and keep the settings both engines take (the tool's drive, Bullet's step; each
        engine's own ``positive`` ones are checked with them), then open the physics client."""
        checked_positive(rate_hz=rate_hz, max_drive_force_n=max_drive_force_n, max_speed_m_per_s=max_speed_m_per_s,
                         max_angular_speed_rad_per_s=max_angular_speed_rad_per_s, **positive)
        if not (isinstance(drive_erp, (int, float)) and math.isfinite(drive_erp)
                and 0.0 < drive_erp <= 1.0):
            raise ValueError(f"drive_erp: must be in (0, 1], got {drive_erp!r}")
        if int(solver_iterations) < 1:
            raise ValueError(f"solver_iterations: must be >= 1, got {solver_iterations!r}")
        self.gui = bool(gui)
        self.max_drive_force_n = float(max_drive_force_n)
        self.drive_erp = float(drive_erp)
        self.max_speed_m_per_s = float(max_speed_m_per_s)
        self.max_angular_speed_rad_per_s = float(max_angular_speed_rad_per_s)
        self.solver_iterations = int(solver_iterations)
        #: the nominal step (``rate_hz``) and the one in use (a ``step`` with another dt changes it)
        self._default_dt = 1.0 / float(rate_hz)
        self._dt = self._default_dt
        self._cid = connect(self.gui)
        self._scene = None
        self.contacts_found = 0
        self._nph = BoxNarrowPhase()

    @property
    def client_id(self) -> int:
        """pybullet physics client id (pass it as ``physicsClientId``)."""
        return self._cid

    @property
    def tool_id(self) -> int:
        """pybullet body id of the tool (-1 before ``load_scene``)."""
        return self._tool

    @property
    def epsilon_m(self) -> float:
        """The epsilon the tool is inflated by [m]."""
        return self._epsilon

    def set_epsilon(self, epsilon_m: float) -> None:
        self._epsilon = checked_epsilon(epsilon_m)

    def warm_up(self) -> None:
        """Compile the narrow phase's kernels now (cached on disk after the first process)."""
        warm_up_kernels()

    def close(self) -> None:
        self._cid = close_world(self._cid, self.window)
        self.window = None
        self._scene = None


class PoseDrive:
    """A force-bounded ``JOINT_FIXED`` constraint holding ``body``'s base (COM frame) at a world
    set-point that leads the body towards :attr:`target` (see the module docstring).

    Poses are ``(position, quaternion w x y z)`` tuples of the base's COM frame, world."""

    def __init__(self, cid: int, body: int, start, *, max_force_n: float, erp: float, max_speed_m_per_s: float,
                 max_angular_speed_rad_per_s: float) -> None:
        self.cid = cid
        self.max_force_n = float(max_force_n)
        self.erp = float(erp)
        self.max_speed_m_per_s = float(max_speed_m_per_s)
        self.max_angular_speed_rad_per_s = float(max_angular_speed_rad_per_s)
        self.constraint = p.createConstraint(body, -1, -1, -1, p.JOINT_FIXED, [0, 0, 0], [0, 0, 0], list(start[0]),
                                             physicsClientId=cid)
        #: where the drive heads for
        self.target = (tuple(start[0]), tuple(start[1]))
        self._setpoint = None
        self._delta = np.zeros(3)
        self.apply(self.target, force=True)

    def lead(self, pos, quat_wxyz, dt_s: float, guard=None) -> tuple[tuple, tuple]:
        """The set-point for the next step from the body's current pose: the target, at most one
        step at the speed bounds away. ``guard(delta)`` may shrink the translation (3,) in place;
        it is then used even when the target is nearer than the bound."""
        tpos, torn = self.target
        lead = self.max_speed_m_per_s * dt_s / self.erp
        delta = self._delta
        delta[0] = tpos[0] - pos[0]
        delta[1] = tpos[1] - pos[1]
        delta[2] = tpos[2] - pos[2]
        dist = math.sqrt(delta[0] * delta[0] + delta[1] * delta[1] + delta[2] * delta[2])
        clipped = dist > lead
        if clipped:
            delta *= lead / dist
        if guard is not None:
            guard(delta)
            clipped = True
        spos = (pos[0] + float(delta[0]), pos[1] + float(delta[1]), pos[2] + float(delta[2])) if clipped else tuple(tpos)
        angle = quat_angle(quat_wxyz, torn)
        lead_rad = self.max_angular_speed_rad_per_s * dt_s / self.erp
        sorn = slerp(quat_wxyz, torn, lead_rad / angle) if angle > lead_rad else tuple(torn)
        return spos, sorn

    def apply(self, setpoint, force: bool = False) -> None:
        """Give the constraint this set-point (``force``: even when unchanged, e.g. after the step
        length changed: pybullet turns ``maxForce`` into an impulse bound with the step)."""
        if not force and setpoint == self._setpoint:
            return
        p.changeConstraint(self.constraint, list(setpoint[0]), jointChildFrameOrientation=list(xyzw_from_wxyz(setpoint[1])),
                           maxForce=self.max_force_n, physicsClientId=self.cid)
        self._setpoint = setpoint
