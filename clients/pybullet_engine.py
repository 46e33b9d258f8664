"""pybullet engine for the environment client: a 3D peg-in-hole scene and a scene with loose bodies.

``PybulletEngine(gui=False)`` connects its own physics server (``DIRECT`` by default, ``GUI`` on
request) and passes ``physicsClientId`` to every call, so several engines coexist in one process.
The CLI finds it as ``hapticproxy.clients.pybullet_engine:PybulletEngine``.

Scenes (SI units; every collision shape is a box or a sphere; z up, gravity -9.81 m/s^2)
  * ``peg``: floor 1.0 x 1.0 x 0.05 m, top face at z = 0. A block 0.100 x 0.100 x 0.040 m on it
    with a square through-hole of side 0.021 m centred at x = y = 0 (the floor is the hole's
    bottom; depth 0.040 m), built from four boxes so every shape stays convex: two walls
    0.100 x 0.0395 x 0.040 m centred at y = +-0.03025 and two 0.0395 x 0.021 x 0.040 m at
    x = +-0.03025. Tool: a box peg 0.020 x 0.020 x 0.060 m, 0.2 kg (0.5 mm clearance per side
    in the hole), tool frame at its centre (its COM), starting axis-aligned at (0, 0, 0.080): its
    bottom 10 mm above the block.
  * ``loose``: the same floor; tool a 0.040 m cube of 0.3 kg at (0, 0, 0.023), 3 mm above the
    floor; three loose 0.050 m cubes of 0.2 kg at (0, 0.08, 0.025) (in the tool's way along +y),
    (0.07, 0.13, 0.025), (-0.08, 0.14, 0.025) and two loose spheres of radius 0.025 m and 0.1 kg
    at (0.08, -0.05, 0.025) and (-0.08, -0.06, 0.025), resting on the floor under gravity.
  ``SceneInfo.facts`` repeats these figures and maps names to pybullet body ids (``body_ids``), the
  ``env_body`` of the contact keys. The nominal step rate is ``rate_hz`` (default 500 Hz; the CLI's
  ``--rate``); ``step`` takes any step length.

Driving the tool (``drive_tool`` stores the target; ``step`` moves towards it)
  * A ``JOINT_FIXED`` user constraint from the tool's COM frame to a world set-point, bounded by
    ``max_drive_force_n`` (pybullet has one bound per constraint: N for the force rows, N m for
    the torque rows) and solved by Bullet in the same solver pass as the contacts, which are
    unbounded, so the tool stops at walls and pushes loose bodies with at most that force. Why
    not a kinematic update: a teleported or velocity-reset tool has infinite effective mass,
    jumps through walls when the proxy jumps, and pumps energy into the bodies it touches; the
    constraint is a velocity-level implicit coupling with no stored energy (dissipative).
    Its error reduction is ``drive_erp`` (pybullet's global ``erp``, used here by this constraint
    only: the scenes have no joints, contacts use their own ``contactERP``): at 0.8 the tool
    follows a proxy moving at 0.1 m/s with a 0.05 mm lag at 500 Hz.
  * No tunnelling, two guards. (1) The set-point leads the tool by at most one step at
    ``max_speed_m_per_s`` (0.5) and ``max_angular_speed_rad_per_s`` (5): the tool moves at most
    ``max_speed * dt`` per step (1 mm at 500 Hz), far less than the thinnest body (20 mm).
    Bullet's box-box collision reports penetrating contacts only (no speculative contacts: a peg
    driven at 2 m/s into a wall went 4 mm in before its first contact), so (2) the set-point's
    translation is cut at every *static* contact plane within reach of the current pose
    (``n . delta >= -max(d, 0)``; reach = max(epsilon, 2 max_speed dt); the contacts of the
    ``contacts()`` call after the last step, as the runner makes, else ``step`` finds them): the
    drive never pushes the tool into a wall or the floor, it slides along them; loose bodies are
    pushed by physics. Rotation is bounded by the angular speed only.
  * ``proxy_twist`` is not fed forward (the lag above is a fraction of epsilon); ``wrench`` is kept
    in ``last_wrench`` but not applied: with a stiff position coupling a feed-forward force would
    only change the constraint's share of the same motion.
  * The tool's own weight: it is held by the drive, and its gravity would only load the drive (and
    bias its push by m g when saturated). ``step`` applies ``m g`` upwards at the tool's COM, so
    the tool is weightless; the haptic force comes from the server's local model, never from here.
  * The tool is a multibody (pybullet refuses ``JOINT_FIXED`` to the world for a body in maximal
    coordinates); every other body is a maximal-coordinates rigid body (a Featherstone base cost
    ~1.6x the step time in the loose scene).

Contacts (``contacts``)
  * Candidates: ``getOverlappingObjects`` over the tool's bounding sphere grown by the reach, as an
    AABB (Bullet's broadphase boxes are grown by its contact threshold, so no body within reach is
    missed); poses and velocities of loose candidates are read each call, static ones once.
  * The contacts themselves: :mod:`.narrowphase` (exact closest features of the tool box against
    each candidate box or sphere, epsilon, keys, clustering; its docstring says how). Keys are
    ``(0, pybullet body id, feature)``. The tests check the smallest separation per body against
    pybullet's ``getClosestPoints`` for random poses. ``contacts_found`` is the count before
    clustering (the runner counts clustered steps by it).

Grasping (the device's buttons, protocol 1.3: ``device_inputs``)
  * While the device's button ``grasp_button`` (0) is held, the loose body nearest the tool within
    ``grasp_reach_m`` (5 mm) when it was pressed is carried: a ``JOINT_FIXED`` constraint from the
    tool to it at their relative pose then; released with the button. The carried body is part
    of the tool meanwhile: its contacts with the tool are not reported (the server's model would
    feel the tool holding it as a contact), nor are its own contacts with the world (the hand
    does not feel the carried body touch things). ``grasped`` names the body, ``grasp_events``
    lists ``(engine time, "grasp" or "release", body id)``; each is logged.

GUI (``gui=True``): pybullet's own window, framed on the scene, with the proxy as a ghost and the
contact normals (:mod:`.pybullet_gui`); ``window.update(runner)`` draws the session's state.
"""
from __future__ import annotations

import logging
import math

import numpy as np
from ._pybullet import p

from .contacts import EDGE_EDGE, NORMAL_WEIGHT_M
from .engine import ContactBuffer, SceneInfo, ToolDescription, checked_step
from .geometry import box_inertia, check_pose, quat_to_matrix, wxyz_from_xyzw, xyzw_from_wxyz
from .narrowphase import E_HALF, KIND_BOX, KIND_SPHERE, env_table
from .pybullet_common import (GRAVITY_M_PER_S2, PYBULLET_VERSION, PoseDrive, PybulletBase, fill_env_row, make_box,
                              make_sphere, reset_world, show_world)

__all__ = ["PybulletEngine", "EDGE_EDGE"]

_log = logging.getLogger("hapticproxy.client")


class PybulletEngine(PybulletBase):
    """pybullet with one box tool in one scene (see the module docstring for the method).

    Args:
        gui: open pybullet's own window (``GUI`` mode) instead of ``DIRECT``.
        rate_hz: nominal step rate (``SceneInfo.env_rate_hz``) [Hz].
        max_drive_force_n: bound of the drive constraint [N; N m for its torque rows].
        drive_erp: error reduction of the drive constraint per step, in (0, 1].
        max_speed_m_per_s, max_angular_speed_rad_per_s: speed bounds of the drive.
        solver_iterations: Bullet's solver iterations per step.
        cluster_normal_weight_m: normal weight of the clustering distance [m].

    ``ValueError`` naming the argument for a bad value. Extras beyond :class:`Engine` (for
    experiments and tests): ``client_id``, ``tool_id``, ``scene_info``, ``reset_tool_pose``,
    ``body_state``, ``tool_kinetic_energy_j`` and the counters ``contacts_found``,
    ``raw_contacts``, ``raw_overflows``, ``guard_freezes``.
    """

    name = f"pybullet {PYBULLET_VERSION}"

    _SCENES = ("peg", "loose")

    def __init__(self, *, gui: bool = False, rate_hz: float = 500.0,
                 max_drive_force_n: float = 50.0, drive_erp: float = 0.8,
                 max_speed_m_per_s: float = 0.5, max_angular_speed_rad_per_s: float = 5.0,
                 solver_iterations: int = 20, cluster_normal_weight_m: float = NORMAL_WEIGHT_M,
                 grasp_button: int = 0, grasp_reach_m: float = 0.005) -> None:
        self._init_drive(gui=gui, rate_hz=rate_hz, max_drive_force_n=max_drive_force_n, drive_erp=drive_erp,
                         max_speed_m_per_s=max_speed_m_per_s, max_angular_speed_rad_per_s=max_angular_speed_rad_per_s,
                         solver_iterations=solver_iterations, cluster_normal_weight_m=cluster_normal_weight_m)
        self.cluster_normal_weight_m = float(cluster_normal_weight_m)
        self._epsilon = 0.0
        #: the last ProxyState wrench (kept, not applied: see the module docstring)
        self.last_wrench = np.zeros(6)
        #: last ``contacts`` call (``contacts_found``: epsilon-active contacts before clustering):
        #: all contacts within the guard's reach; how often the raw array overflowed (extra
        #: contacts are dropped); how often the drive's guard could not satisfy every static
        #: contact (its translation was frozen for that step)
        self.raw_contacts = 0
        self.raw_overflows = 0
        self.guard_freezes = 0
        self._guard_buf = ContactBuffer(1)
        if not (isinstance(grasp_button, int) and 0 <= grasp_button < 32):
            raise ValueError(f"grasp_button: a button's bit, 0..31, got {grasp_button!r}")
        if not (math.isfinite(grasp_reach_m) and grasp_reach_m >= 0.0):
            raise ValueError(f"grasp_reach_m: must be finite and >= 0, got {grasp_reach_m!r}")
        self.grasp_button = grasp_button
        self.grasp_reach_m = float(grasp_reach_m)
        #: (engine time, "grasp" or "release", body id) of every grasp (the device's button)
        self.grasp_events: list[tuple[float, str, int]] = []
        self._reset_state()

    # ------------------------------------------------------------------ helpers
    def _reset_state(self) -> None:
        self._time = 0.0
        self._tool = -1
        self._drive: PoseDrive | None = None
        self._dt = self._default_dt
        self._pose = None  # cached (pos, quat w x y z) of the tool, None after a step
        self._guard_n = -1  # raw contacts usable by the guard (-1: none at the current pose)
        self._env, self._env_int = env_table(0)
        self._row_of: dict[int, int] = {}
        self._dynamic_rows: list[bool] = []
        self._rows = np.zeros(0, dtype=np.int64)
        self._bounding_radius = 0.0
        self._tool_half = (0.0, 0.0, 0.0)
        self._held = False        # the grasp button, as the last ProxyState had it
        self.grasped: int | None = None  # the body carried (pybullet id)
        self._grasp_c = -1

    @property
    def scene_info(self) -> SceneInfo | None:
        """What the last ``load_scene`` returned (None before)."""
        return self._scene

    def _require_scene(self) -> None:
        if self._scene is None:
            raise RuntimeError("load_scene first")

    # ------------------------------------------------------------------ Engine
    def load_scene(self, name: str) -> SceneInfo:
        if name not in self._SCENES:
            raise ValueError(f"scene: unknown scene {name!r}; choices: {', '.join(self._SCENES)}")
        if self._cid < 0:
            raise RuntimeError("engine closed")
        cid = self._cid
        if self.window is not None:
            self.window.close()
            self.window = None
        self._scene = None
        self._reset_state()
        reset_world(cid, self._dt, self.solver_iterations, self.drive_erp, self.gui)
        gui = self.gui
        env = []  # (body, kind, half extents or (radius, 0, 0), dynamic)
        floor_half = (0.5, 0.5, 0.025)
        floor = make_box(cid, floor_half, (0.0, 0.0, -floor_half[2]), 0.0, (0.6, 0.6, 0.6, 1.0), visual=gui)
        env.append((floor, KIND_BOX, floor_half, False))
        bodies = {"floor": floor}
        if name == "peg":
            hole, outer, height = 0.021, 0.100, 0.040
            wall_w = (outer - hole) / 2.0  # 0.0395
            off = hole / 2.0 + wall_w / 2.0  # 0.03025
            walls = {
                "wall_+y": ((outer / 2, wall_w / 2, height / 2), (0.0, off, height / 2)),
                "wall_-y": ((outer / 2, wall_w / 2, height / 2), (0.0, -off, height / 2)),
                "wall_+x": ((wall_w / 2, hole / 2, height / 2), (off, 0.0, height / 2)),
                "wall_-x": ((wall_w / 2, hole / 2, height / 2), (-off, 0.0, height / 2)),
            }
            for wname, (half, pos) in walls.items():
                body = make_box(cid, half, pos, 0.0, (0.8, 0.5, 0.2, 1.0), visual=gui)
                env.append((body, KIND_BOX, half, False))
                bodies[wname] = body
            tool_half = (0.010, 0.010, 0.030)
            tool_mass = 0.2
            tool_pos = (0.0, 0.0, height + tool_half[2] + 0.010)
            facts = {
                "floor_top_z_m": 0.0, "floor_size_m": [1.0, 1.0, 0.05],
                "block_size_m": [outer, outer, height], "block_top_z_m": height,
                "hole_side_m": hole, "hole_centre_m": [0.0, 0.0], "hole_depth_m": height,
                "peg_size_m": [2 * h for h in tool_half],
                "peg_clearance_per_side_m": (hole - 2 * tool_half[0]) / 2,
            }
        else:
            tool_half = (0.020, 0.020, 0.020)
            tool_mass = 0.3
            tool_pos = (0.0, 0.0, 0.023)  # 3 mm above the floor
            box_half = (0.025, 0.025, 0.025)
            for k, pos in enumerate(((0.0, 0.08, 0.025), (0.07, 0.13, 0.025), (-0.08, 0.14, 0.025))):
                body = make_box(cid, box_half, pos, 0.2, (0.2, 0.5, 0.8, 1.0), visual=gui)
                env.append((body, KIND_BOX, box_half, True))
                bodies[f"box{k}"] = body
            radius = 0.025
            for k, pos in enumerate(((0.08, -0.05, 0.025), (-0.08, -0.06, 0.025))):
                body = make_sphere(cid, radius, pos, 0.1, (0.2, 0.8, 0.3, 1.0), visual=gui)
                env.append((body, KIND_SPHERE, (radius, 0.0, 0.0), True))
                bodies[f"sphere{k}"] = body
            facts = {
                "floor_top_z_m": 0.0, "floor_size_m": [1.0, 1.0, 0.05],
                "tool_size_m": [2 * h for h in tool_half],
                "loose_box_size_m": [0.05, 0.05, 0.05], "loose_box_mass_kg": 0.2,
                "loose_sphere_radius_m": radius, "loose_sphere_mass_kg": 0.1,
            }
        inertia = box_inertia(tool_mass, tool_half)
        # the tool is a multibody: pybullet refuses a JOINT_FIXED to the world for a body in
        # maximal coordinates; the others are rigid bodies (a Featherstone base costs ~1.6x the
        # step time for the same free body)
        tool = make_box(cid, tool_half, tool_pos, tool_mass, (0.9, 0.2, 0.2, 1.0), maximal=False, visual=gui)
        p.changeDynamics(tool, -1, localInertiaDiagonal=list(inertia[:3]), physicsClientId=cid)
        self._tool = tool
        self._tool_mass = tool_mass
        self._tool_half = tool_half
        self._bounding_radius = math.sqrt(sum(h * h for h in tool_half))
        self._drive = PoseDrive(cid, tool, (tool_pos, (1.0, 0.0, 0.0, 0.0)), max_force_n=self.max_drive_force_n,
                                erp=self.drive_erp, max_speed_m_per_s=self.max_speed_m_per_s,
                                max_angular_speed_rad_per_s=self.max_angular_speed_rad_per_s)
        self._env, self._env_int = env_table(len(env))
        self._rows = np.zeros(len(env), dtype=np.int64)
        self._dynamic_rows = []
        for row, (body, kind, half, dynamic) in enumerate(env):
            pos, orn = p.getBasePositionAndOrientation(body, physicsClientId=cid)
            fill_env_row(self._env, row, pos, orn)
            self._env[row, E_HALF:E_HALF + 3] = half
            self._env_int[row] = (body, kind, int(dynamic))
            self._row_of[body] = row
            self._dynamic_rows.append(dynamic)
        facts["body_ids"] = dict(bodies, tool=tool)
        facts["tool_start_m"] = list(tool_pos)
        facts["time_step_s"] = self._dt
        facts["gravity_m_per_s2"] = [0.0, 0.0, -GRAVITY_M_PER_S2]
        tool_desc = ToolDescription(kind="spatial", mass_kg=tool_mass, com_m=(0.0, 0.0, 0.0),
                                    inertia_kg_m2=inertia)
        self._scene = SceneInfo(name=name, tool=tool_desc, env_rate_hz=1.0 / self._dt, facts=facts)
        if self.gui:
            from .pybullet_gui import PybulletView

            self.window = PybulletView(cid, [b for n, b in bodies.items() if n != "floor"] + [tool],
                                       ghost_boxes=[tool_half])
            show_world(cid)
        return self._scene

    def step(self, dt_s: float) -> None:
        self._require_scene()
        dt = checked_step(dt_s)
        cid = self._cid
        force = False
        if dt != self._dt:
            self._dt = dt
            p.setTimeStep(dt, physicsClientId=cid)
            force = True  # pybullet turns maxForce into an impulse bound with the step size
        if self._guard_n < 0:
            # the runner asks for contacts after every step; anyone else pays for them here
            self._find_contacts(self._guard_buf, 1, -math.inf)
        pos, orn = self._raw_pose()
        drive = self._drive
        drive.apply(drive.lead(pos, orn, dt, self._guard if self._guard_n > 0 else None), force=force)
        # the tool is weightless in the engine (module docstring)
        p.applyExternalForce(self._tool, -1, (0.0, 0.0, self._tool_mass * GRAVITY_M_PER_S2), pos,
                             p.WORLD_FRAME, physicsClientId=cid)
        p.stepSimulation(physicsClientId=cid)
        self._pose = None
        self._guard_n = -1
        self._time += dt

    def _guard(self, delta: np.ndarray) -> None:
        """Speculative contacts for the drive: the set-point never crosses a static contact's plane."""
        if not self._nph.guard(delta, self._guard_n, self._env_int):
            self.guard_freezes += 1

    def drive_tool(self, proxy_pose: np.ndarray, proxy_twist: np.ndarray, wrench: np.ndarray) -> None:
        self._require_scene()
        pose = check_pose(proxy_pose, "proxy_pose")
        twist = np.asarray(proxy_twist, dtype=float)
        if twist.shape != (6,) or not np.all(np.isfinite(twist)):
            raise ValueError(f"proxy_twist: must be 6 finite numbers, got shape {twist.shape}")
        w = np.asarray(wrench, dtype=float)
        if w.shape != (6,) or not np.all(np.isfinite(w)):
            raise ValueError(f"wrench: must be 6 finite numbers, got shape {w.shape}")
        self._drive.target = pose
        self.last_wrench[:] = w

    def tool_pose(self, out: np.ndarray) -> np.ndarray:
        self._require_scene()
        pos, orn = self._raw_pose()
        out[0:3] = pos
        out[3:7] = orn
        return out

    def contacts(self, buf: ContactBuffer, max_contacts: int) -> int:
        self._require_scene()
        if not 1 <= max_contacts <= buf.capacity:
            raise ValueError(f"max_contacts: must be in [1, {buf.capacity}] (buffer capacity), "
                             f"got {max_contacts!r}")
        n, self.contacts_found = self._find_contacts(buf, max_contacts, self._epsilon)
        return n

    def _find_contacts(self, buf: ContactBuffer, max_contacts: int, eps: float) -> tuple[int, int]:
        """Contacts within eps into buf (clustered to max_contacts), and every contact within the
        guard's reach into the raw arrays. Returns (written, found within eps)."""
        cid = self._cid
        pos, orn = self._raw_pose()
        self._nph.set_tool(pos, orn, self._tool_half)
        # Beyond epsilon, the drive's guard wants every static feature the tool can reach in one
        # step (twice the speed bound); those extra contacts are never reported.
        reach = max(self._epsilon, 2.0 * self.max_speed_m_per_s * self._dt)
        r = self._bounding_radius + reach
        overlapping = p.getOverlappingObjects((pos[0] - r, pos[1] - r, pos[2] - r),
                                              (pos[0] + r, pos[1] + r, pos[2] + r),
                                              physicsClientId=cid)
        m = 0
        if overlapping:
            row_of = self._row_of
            env = self._env
            rows = self._rows
            for body, _link in overlapping:
                row = row_of.get(body)
                if row is None or body == self.grasped:
                    continue  # the tool itself (or the GUI's ghost), or the body it carries
                if self._dynamic_rows[row]:
                    bpos, born = p.getBasePositionAndOrientation(body, physicsClientId=cid)
                    lin, ang = p.getBaseVelocity(body, physicsClientId=cid)
                    fill_env_row(env, row, bpos, born, lin, ang)
                rows[m] = row
                m += 1
        n, active, raw, overflow = self._nph.query_into(buf, self._env, self._env_int, self._rows, m, reach, eps,
                                                        max_contacts, self.cluster_normal_weight_m)
        self.raw_contacts = raw
        self.raw_overflows += overflow
        self._guard_n = raw
        buf.n = n
        return n, active

    @property
    def time_s(self) -> float:
        return self._time

    def device_inputs(self, buttons: int, gripper_angle_rad: float, gripper_velocity_rad_per_s: float,
                      reported: int) -> None:
        """Grasp while the device's ``grasp_button`` is held (module docstring)."""
        if self._scene is None:
            return
        held = bool(reported & 1) and bool((int(buttons) >> self.grasp_button) & 1)
        if held and not self._held:
            self._grasp()
        elif not held and self._held:
            self._release()
        self._held = held

    def _grasp(self) -> None:
        cid = self._cid
        best, body = self.grasp_reach_m, None
        for row, dynamic in enumerate(self._dynamic_rows):
            if not dynamic:
                continue
            b = int(self._env_int[row, 0])
            for pt in p.getClosestPoints(self._tool, b, self.grasp_reach_m, physicsClientId=cid) or ():
                if pt[8] <= best:
                    best, body = pt[8], b
        if body is None:
            _log.info("button %d held: nothing within %.1f mm of the tool to grasp", self.grasp_button,
                      self.grasp_reach_m * 1e3)
            return
        tpos, torn = p.getBasePositionAndOrientation(self._tool, physicsClientId=cid)
        bpos, born = p.getBasePositionAndOrientation(body, physicsClientId=cid)
        ipos, iorn = p.invertTransform(tpos, torn)
        rpos, rorn = p.multiplyTransforms(ipos, iorn, bpos, born)  # the body in the tool's frame
        self._grasp_c = p.createConstraint(self._tool, -1, body, -1, p.JOINT_FIXED, (0.0, 0.0, 0.0), rpos,
                                           (0.0, 0.0, 0.0), rorn, (0.0, 0.0, 0.0, 1.0), physicsClientId=cid)
        p.changeConstraint(self._grasp_c, maxForce=self.max_drive_force_n, physicsClientId=cid)
        self.grasped = body
        self.grasp_events.append((self._time, "grasp", body))
        _log.info("button %d held: grasped body %d (%.1f mm from the tool)", self.grasp_button, body, best * 1e3)

    def _release(self) -> None:
        if self.grasped is None:
            return
        p.removeConstraint(self._grasp_c, physicsClientId=self._cid)
        self.grasp_events.append((self._time, "release", self.grasped))
        _log.info("button %d released: body %d let go", self.grasp_button, self.grasped)
        self.grasped = None
        self._grasp_c = -1

    # ------------------------------------------------------------------ extras (not in Engine)
    def reset_tool_pose(self, pose: np.ndarray) -> None:
        """Teleport the tool (x y z qw qx qy qz) at rest and make that pose the drive's target.
        For setting up experiments and tests; never call it while the tool is in use."""
        self._require_scene()
        pos, orn = check_pose(pose, "pose")
        cid = self._cid
        p.resetBasePositionAndOrientation(self._tool, pos, xyzw_from_wxyz(orn), physicsClientId=cid)
        p.resetBaseVelocity(self._tool, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), physicsClientId=cid)
        self._pose = None
        self._guard_n = -1
        self._drive.target = (pos, orn)
        self._drive.apply(self._drive.target, force=True)

    def body_state(self, body: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(COM position, quaternion w x y z, linear velocity, angular velocity) of a body, world."""
        cid = self._cid
        pos, orn = p.getBasePositionAndOrientation(body, physicsClientId=cid)
        lin, ang = p.getBaseVelocity(body, physicsClientId=cid)
        return np.array(pos), np.array(wxyz_from_xyzw(orn)), np.array(lin), np.array(ang)

    def tool_kinetic_energy_j(self) -> float:
        """Kinetic energy of the engine's tool [J] (translation + rotation)."""
        self._require_scene()
        _pos, quat, lin, ang = self.body_state(self._tool)
        w_body = quat_to_matrix(quat).T @ ang
        inertia = np.asarray(self._scene.tool.inertia_kg_m2[:3])
        return 0.5 * self._tool_mass * float(lin @ lin) + 0.5 * float(inertia @ (w_body * w_body))

    # ------------------------------------------------------------------ internals
    def _raw_pose(self):
        """(position, quaternion w x y z) of the tool, cached until the next step."""
        if self._pose is None:
            pos, orn = p.getBasePositionAndOrientation(self._tool, physicsClientId=self._cid)
            self._pose = (pos, wxyz_from_xyzw(orn))
        return self._pose
