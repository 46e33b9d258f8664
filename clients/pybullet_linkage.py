"""pybullet engine with a linkage tool (issue 6): a URDF chain whose links report their contacts.

``PybulletLinkageEngine`` loads a kinematic tree from a URDF (default ``urdf/chain.urdf``: four
60 x 20 x 20 mm box links of 0.1 kg joined by revolute joints about z, y, z, a floating base) and
builds the protocol's link records from what pybullet loaded (:func:`links_from_body`: masses,
inertias, joint axes and joint origins as pybullet reports them, so the server's proxy and the
engine agree on the same chain). The hand holds the last link. CLI name ``pybullet-linkage``.

Scene ``chain``: the ``peg`` scene's floor (1.0 x 1.0 x 0.05 m, top face at z = 0) and a static
block 0.10 x 0.30 x 0.06 m centred at (0.30, 0, 0.03) in the chain's way along +x; the chain
starts straight along +x (to x = 0.19 m) with its root frame at (-0.05, 0, 0.05), 40 mm above
the floor.

Frames: link k's frame is the URDF link frame (at its proximal joint); ``tool_pose`` and the
ProxyState's ``proxy_pose`` are the root (base) link's frame; joint positions are pybullet's
joint angles in link order. pybullet reports a base's pose at its centre of mass and a joint
origin relative to the parent's centre-of-mass frame; both are converted here.

Driving (like :mod:`.pybullet_engine`'s peg): the base follows the proxy's root pose through
:class:`.pybullet_common.PoseDrive` (a force-bounded ``JOINT_FIXED`` constraint whose set-point leads by at most one step at
``max_speed_m_per_s`` / ``max_angular_speed_rad_per_s``); each joint follows the proxy's joint
position and rate with a force-bounded position motor (``max_joint_effort``). The chain is
weightless in the engine (``m g`` upwards at every link's COM): the haptic force comes from the
server's model. No self-collision in the engine: the proxy keeps its links apart.

Contacts: every link is a box, so :mod:`.narrowphase`'s exact kernel (vertex-face,
face-vertex and edge-edge features within epsilon, the static-corner filter) runs once per link
against the boxes and spheres near it; the other links of the chain, except its neighbours
(which share a joint), are candidates too: a self-contact is found from both links, so it arrives
as two contacts, one on each link, the other link as the environment body (id
``SELF_BODY_BASE + link``, its velocity for ``v_constr``). Keys are ``(link, body, feature)``.
Above the granted count all links' contacts are clustered together (``contacts.reduce_contacts``).

GUI (``gui=True``): :mod:`.pybullet_gui` frames the chain and the block, draws the proxy as a
ghost copy of the URDF at the ProxyState's root pose and joints, and the contact normals.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
from ._pybullet import p

from .contacts import reduce_contacts
from .engine import ContactBuffer, LinkDescription, SceneInfo, ToolDescription, checked_step
from .geometry import IDENTITY_WXYZ, compose, inverse, quat_to_matrix, wxyz_from_xyzw
from .narrowphase import E_HALF, KIND_BOX, RAW_CAPACITY, env_table
from .pybullet_common import (GRAVITY_M_PER_S2, PYBULLET_VERSION, PoseDrive, PybulletBase, fill_env_row, make_box,
                              reset_world, show_world)

__all__ = ["PybulletLinkageEngine", "links_from_body", "DEFAULT_URDF", "SELF_BODY_BASE"]

#: the chain this engine loads unless given another URDF
DEFAULT_URDF = Path(__file__).with_name("urdf") / "chain.urdf"
#: env_body id of a tool link seen by another link's contact query: this + link index
SELF_BODY_BASE = 1000
_JOINT_NAMES = {p.JOINT_REVOLUTE: "revolute", p.JOINT_PRISMATIC: "prismatic"}


def links_from_body(body: int, client_id: int) -> list[LinkDescription]:
    """The protocol's link records of a pybullet multibody, from what pybullet loaded: link 0 the
    base (the floating root), link k + 1 pybullet's link k. COM and inertia in each URDF link
    frame (pybullet gives the principal moments in the inertial frame: rotated into the link
    frame here); a joint's origin is the child link frame in the parent link frame at q = 0
    (pybullet gives it relative to the parent's COM frame: composed here). ``ValueError`` for a
    joint other than revolute or prismatic (a fixed joint: merge the links in the URDF)."""
    def inertial(link):
        info = p.getDynamicsInfo(body, link, physicsClientId=client_id)
        mass, diag, pos, orn = info[0], info[2], info[3], wxyz_from_xyzw(info[4])
        R = quat_to_matrix(orn)
        I = R @ np.diag(diag) @ R.T
        return mass, tuple(pos), orn, (I[0, 0], I[1, 1], I[2, 2], I[0, 1], I[0, 2], I[1, 2])

    mass, com, com_orn, inertia = inertial(-1)
    frames = {-1: (com, com_orn)}  # each link's COM frame in its own link frame
    out = [LinkDescription(mass, com, inertia)]
    for j in range(p.getNumJoints(body, physicsClientId=client_id)):
        info = p.getJointInfo(body, j, physicsClientId=client_id)
        jtype, axis, ppos, porn, parent = info[2], info[13], info[14], wxyz_from_xyzw(info[15]), info[16]
        if jtype not in _JOINT_NAMES:
            raise ValueError(f"joint {info[1].decode()!r}: type {jtype} is not revolute or prismatic")
        mass, com, com_orn, inertia = inertial(j)
        frames[j] = (com, com_orn)
        origin_p, origin_q = compose(*frames[parent], ppos, porn)
        out.append(LinkDescription(mass, com, inertia, parent + 1, _JOINT_NAMES[jtype], tuple(axis),
                                   tuple(origin_p) + tuple(origin_q)))
    return out


class PybulletLinkageEngine(PybulletBase):
    """pybullet with a URDF chain as the tool (see the module docstring).

    Args:
        gui: pybullet's own window instead of ``DIRECT``.
        rate_hz: nominal step rate [Hz].
        urdf: the chain's URDF (box links only: the contact kernel's shapes).
        held_link: the link the hand holds (default the last).
        max_drive_force_n: bound of the base's drive constraint [N; N m for its torque rows].
        max_joint_effort: bound of each joint motor [N m or N].
        max_speed_m_per_s, max_angular_speed_rad_per_s: speed bounds of the base's drive.
    """

    name = f"pybullet {PYBULLET_VERSION} (linkage)"
    _SCENES = ("chain",)

    def __init__(self, *, gui: bool = False, rate_hz: float = 500.0, urdf: str | Path = DEFAULT_URDF,
                 held_link: int | None = None, max_drive_force_n: float = 50.0, max_joint_effort: float = 2.0,
                 max_speed_m_per_s: float = 0.5, max_angular_speed_rad_per_s: float = 5.0,
                 drive_erp: float = 0.8, solver_iterations: int = 20) -> None:
        if not Path(urdf).is_file():
            raise ValueError(f"urdf: no such file: {urdf}")
        self._init_drive(gui=gui, rate_hz=rate_hz, max_drive_force_n=max_drive_force_n, drive_erp=drive_erp,
                         max_speed_m_per_s=max_speed_m_per_s, max_angular_speed_rad_per_s=max_angular_speed_rad_per_s,
                         solver_iterations=solver_iterations, max_joint_effort=max_joint_effort)
        self.urdf = Path(urdf)
        self._held = held_link
        self.max_joint_effort = float(max_joint_effort)
        self._time = 0.0
        self._raw = ContactBuffer(RAW_CAPACITY)

    # ------------------------------------------------------------------ Engine
    def load_scene(self, name: str) -> SceneInfo:
        if name not in self._SCENES:
            raise ValueError(f"scene: unknown scene {name!r}; choices: {', '.join(self._SCENES)}")
        cid = self._cid
        if self.window is not None:
            self.window.close()
            self.window = None
        reset_world(cid, self._dt, self.solver_iterations, self.drive_erp, self.gui)
        env = []  # (body, half extents), all static
        floor_half = (0.5, 0.5, 0.025)
        env.append((make_box(cid, floor_half, (0.0, 0.0, -0.025), visual=self.gui), floor_half))
        block_half = (0.05, 0.15, 0.03)
        env.append((make_box(cid, block_half, (0.30, 0.0, 0.03), rgba=(0.8, 0.5, 0.2, 1.0), visual=self.gui),
                    block_half))
        start = (-0.05, 0.0, 0.05)
        tool = p.loadURDF(str(self.urdf), list(start), flags=p.URDF_USE_INERTIA_FROM_FILE, physicsClientId=cid)
        self._tool = tool
        self._nj = p.getNumJoints(tool, physicsClientId=cid)
        self._nl = self._nj + 1
        links = links_from_body(tool, cid)
        held = self._nl - 1 if self._held is None else int(self._held)
        if not 0 <= held < self._nl:
            raise ValueError(f"held_link: expected 0..{self._nl - 1}, got {held}")
        # box half extents and the box centre's offset from each link's COM frame
        self._half = np.zeros((self._nl, 3))
        self._masses = np.array([ln.mass_kg for ln in links])
        for k in range(self._nl):
            shapes = p.getCollisionShapeData(tool, k - 1, physicsClientId=cid)
            if len(shapes) != 1 or shapes[0][2] != p.GEOM_BOX:
                raise ValueError(f"urdf: link {k} must have exactly one box collision shape")
            self._half[k] = np.asarray(shapes[0][3]) / 2.0
            if np.linalg.norm(np.asarray(shapes[0][5])) > 1e-9 or abs(abs(shapes[0][6][3]) - 1.0) > 1e-9:
                raise ValueError(f"urdf: link {k}'s collision box must be centred on its inertial frame")
            p.changeDynamics(tool, k - 1, linearDamping=0.0, angularDamping=0.0, physicsClientId=cid)
        # base COM frame in the base link frame (pybullet reports the base at its COM)
        self._base_com = (links[0].com_m, wxyz_from_xyzw(p.getDynamicsInfo(tool, -1, physicsClientId=cid)[4]))
        pos, orn = p.getBasePositionAndOrientation(tool, physicsClientId=cid)
        self._drive = PoseDrive(cid, tool, (start, IDENTITY_WXYZ), max_force_n=self.max_drive_force_n,
                                erp=self.drive_erp, max_speed_m_per_s=self.max_speed_m_per_s,
                                max_angular_speed_rad_per_s=self.max_angular_speed_rad_per_s)
        self._drive.target = (tuple(pos), wxyz_from_xyzw(orn))
        self._drive.apply(self._drive.target)
        self._jq_target = np.zeros(self._nj)
        self._jqd_target = np.zeros(self._nj)
        # the narrow phase's environment table: the static bodies, then one row per tool link
        k = len(env) + self._nl
        self._env, self._env_int = env_table(k)
        self._row_of = {}
        for row, (body, half) in enumerate(env):
            bpos, born = p.getBasePositionAndOrientation(body, physicsClientId=cid)
            fill_env_row(self._env, row, bpos, born)
            self._env[row, E_HALF:E_HALF + 3] = half
            self._env_int[row] = (body, KIND_BOX, 0)
            self._row_of[body] = row
        self._link_row0 = len(env)
        for j in range(self._nl):
            row = self._link_row0 + j
            self._env[row, E_HALF:E_HALF + 3] = self._half[j]
            self._env_int[row] = (SELF_BODY_BASE + j, KIND_BOX, 1)
        self._rows = np.zeros(k, dtype=np.int64)
        self._time = 0.0
        tool_desc = ToolDescription("linkage", float(self._masses.sum()), links=tuple(links), held_link=held)
        facts = {"urdf": str(self.urdf), "links": self._nl, "held_link": held, "floor_top_z_m": 0.0,
                 "block_centre_m": [0.30, 0.0, 0.03], "block_size_m": [0.1, 0.3, 0.06], "tool_start_m": list(start),
                 "body_ids": {"floor": env[0][0], "block": env[1][0], "tool": tool}, "time_step_s": self._dt}
        self._scene = SceneInfo(name=name, tool=tool_desc, env_rate_hz=1.0 / self._dt, facts=facts)
        if self.gui:
            from .pybullet_gui import PybulletView

            self.window = PybulletView(cid, [env[1][0], tool], ghost_urdf=self.urdf, link_com=self._base_com)
            show_world(cid)
        return self._scene

    def drive_joints(self, position: np.ndarray, velocity: np.ndarray, effort: np.ndarray) -> None:
        if len(position) == 0:
            return  # a server that does not model the joints: they keep their last targets
        if len(position) != self._nj or len(velocity) != self._nj:
            raise ValueError(f"position, velocity: expected {self._nj} joints, got {len(position)}, {len(velocity)}")
        self._jq_target[:] = position
        self._jqd_target[:] = velocity

    def drive_tool(self, proxy_pose: np.ndarray, proxy_twist: np.ndarray, wrench: np.ndarray) -> None:
        pose = np.asarray(proxy_pose, dtype=float)
        if pose.shape != (7,) or not np.all(np.isfinite(pose)):
            raise ValueError(f"proxy_pose: must be 7 finite numbers, got shape {pose.shape}")
        q = pose[3:7] / np.linalg.norm(pose[3:7])
        # the root link frame -> the base's COM frame (what the constraint holds)
        self._drive.target = compose(pose[:3], q, *self._base_com)

    def joint_positions(self, out: np.ndarray) -> np.ndarray:
        states = p.getJointStates(self._tool, range(self._nj), physicsClientId=self._cid)
        for j, s in enumerate(states):
            out[j] = s[0]
        return out

    def tool_pose(self, out: np.ndarray) -> np.ndarray:
        pos, orn = p.getBasePositionAndOrientation(self._tool, physicsClientId=self._cid)
        lp, lq = compose(pos, wxyz_from_xyzw(orn), *inverse(*self._base_com))
        out[0:3] = lp
        out[3:7] = lq
        return out

    @property
    def time_s(self) -> float:
        return self._time

    def step(self, dt_s: float) -> None:
        dt = checked_step(dt_s)
        cid = self._cid
        if dt != self._dt:
            self._dt = dt
            p.setTimeStep(dt, physicsClientId=cid)
        pos, orn = p.getBasePositionAndOrientation(self._tool, physicsClientId=cid)
        self._drive.apply(self._drive.lead(pos, wxyz_from_xyzw(orn), dt), force=True)
        p.setJointMotorControlArray(self._tool, range(self._nj), p.POSITION_CONTROL,
                                    targetPositions=list(self._jq_target), targetVelocities=list(self._jqd_target),
                                    forces=[self.max_joint_effort] * self._nj, physicsClientId=cid)
        # weightless in the engine: the haptic force is the server's
        for k in range(self._nl):
            com = pos if k == 0 else p.getLinkState(self._tool, k - 1, physicsClientId=cid)[0]
            p.applyExternalForce(self._tool, k - 1, (0.0, 0.0, self._masses[k] * GRAVITY_M_PER_S2), com,
                                 p.WORLD_FRAME, physicsClientId=cid)
        p.stepSimulation(physicsClientId=cid)
        self._time += dt

    def contacts(self, buf: ContactBuffer, max_contacts: int) -> int:
        if not 1 <= max_contacts <= buf.capacity:
            raise ValueError(f"max_contacts: must be in [1, {buf.capacity}] (buffer capacity), got {max_contacts!r}")
        cid = self._cid
        tool = self._tool
        env, env_int = self._env, self._env_int
        # the links' boxes (COM frames) and velocities, as environment rows for each other
        states = [p.getBasePositionAndOrientation(tool, physicsClientId=cid) + p.getBaseVelocity(tool, physicsClientId=cid)]
        for j in range(self._nj):
            s = p.getLinkState(tool, j, computeLinkVelocity=1, physicsClientId=cid)
            states.append((s[0], s[1], s[6], s[7]))
        for k, (pos, orn, lin, ang) in enumerate(states):
            fill_env_row(env, self._link_row0 + k, pos, orn, lin, ang)
        raw = self._raw
        n = 0
        eps = self._epsilon
        nph = self._nph
        for k, (pos, orn, _lin, _ang) in enumerate(states):
            nph.set_tool(pos, wxyz_from_xyzw(orn), self._half[k])
            r = float(np.linalg.norm(self._half[k])) + eps
            m = 0
            for body, _link in p.getOverlappingObjects([pos[i] - r for i in range(3)], [pos[i] + r for i in range(3)],
                                                       physicsClientId=cid) or ():
                row = self._row_of.get(body)
                if row is not None and row not in self._rows[:m]:
                    self._rows[m] = row
                    m += 1
            for j in range(self._nl):
                if j != k and not self._adjacent(j, k):
                    self._rows[m] = self._link_row0 + j
                    m += 1
            cap = raw.capacity - n
            if cap <= 0:
                break
            got, _active, _raw_n, _ovf = nph.query_into(raw, env, env_int, self._rows, m, eps, eps, cap, 0.1, start=n)
            raw.keys[n:n + got, 0] = k
            n += got
        raw.n = n
        self.contacts_found = n
        return reduce_contacts(raw, buf, max_contacts)

    def _adjacent(self, a: int, b: int) -> bool:
        """Links a and b share a joint (parent and child)."""
        links = self._scene.tool.links
        return links[a].parent == b or links[b].parent == a

    def link_states(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """(frame origin, quaternion w x y z) of every link's URDF frame, world (tests, experiments)."""
        cid = self._cid
        out = []
        pose = self.tool_pose(np.zeros(7))
        out.append((pose[:3].copy(), pose[3:7].copy()))
        for j in range(self._nj):
            s = p.getLinkState(self._tool, j, computeForwardKinematics=1, physicsClientId=cid)
            lp, lq = compose(s[0], wxyz_from_xyzw(s[1]), *inverse(s[2], wxyz_from_xyzw(s[3])))
            out.append((np.asarray(lp), np.asarray(lq)))
        return out

