"""The pymunk (Chipmunk2D) engine: the paper's planar testbed and a scene with movable bodies.

Scenes (geometry in :mod:`.scenes`, SI units, pymunk works in metres directly):
``testbed`` (the paper's Fig. 12: enclosure, tight hole in the bottom wall, peg at the origin),
``hole`` (the peg rotated 90 deg and resting in the hole: Figs. 16/17), ``wall`` (the Fig. 14 wall
alone: touched at y_COM = 124 mm), ``push`` (a closed enclosure with three movable boxes) and
``linkage`` (the testbed with a 3-bar planar linkage as the tool, held by its last link).
Half-planes become static slabs 0.2 m thick. No gravity (a horizontal device); ``push``'s boxes
slide on a damped floor (``Space.damping`` 0.3: 70 % of their speed is lost per second).

**Driving the tool** (a coupling constraint in the engine): the tool is a dynamic body. A kinematic
control body is placed at the newest proxy pose with the proxy's velocity (clamped to
``max_speed_m_per_s``), and a ``PivotJoint`` plus a ``GearJoint`` tie the tool to it. Chipmunk
solves them at the velocity level together with the contacts: the tool is given the proxy's
velocity plus a position correction of at most ``max_speed_m_per_s`` (``max_bias``), with at most
``max_force_n`` / ``max_torque_n_m`` (``max_force``), contacts are perfectly plastic (elasticity
0) and the solver only removes relative velocity, so the coupling cannot inject energy beyond
the proxy's own motion. Tunnelling: the tool moves at most ``2 * max_speed_m_per_s / (rate_hz *
substeps)`` per substep (5 mm with the defaults), less than the thinnest obstacle (the 20 mm peg
itself against 40 mm walls). The server's ``wrench`` is applied to the tool as an external force
only with ``use_wrench=True``.

**Epsilon-active contacts**: a second polygon with the tool's vertices and ``radius = epsilon``
(Chipmunk's rounded polygon is exactly the tool swept by a disc of radius epsilon) is attached to
the tool body, never added to the space, and given to ``Space.shape_query`` after every step. Each
returned point has the inflated tool's separation ``s_eps`` (``distance``), so the real tool's is
``d = s_eps + epsilon``; ``point_b`` lies on the environment shape (``c_p``); the normal is
Chipmunk's negated (it points from the tool, shape a, to the environment). Chipmunk returns up to
two points per shape pair (the ends of a clipped face-face overlap); each is classified by
geometry into vertex-face / face-vertex / vertex-vertex with the feature indices, which makes the
keys stable. ``v_constr = n . v(c_p)`` for movable bodies.

**The linkage** (scene ``linkage``, issue 6): three dynamic bars joined by ``PivotJoint``s (the
engine's own chain), each link driven like the peg (pivot + gear to a kinematic control body at
the proxy's pose of that link, from the ProxyState's root pose and joint positions). Every link
is queried with its own inflated polygon; keys are ``(link, env body, feature)``. A link touching
another link of the chain (not its neighbours, which share a pivot) is a self-contact: its
query reports the other link as an environment body (id ``SELF_BODY_BASE + link``, its velocity
for ``v_constr``), and the other link's query reports the mirror contact, so each self-contact
arrives as two contacts, one on each link. Links do not collide with each other in the engine
(one group): the proxy keeps them apart and the drive makes the engine follow. The ContactUpdate
carries the engine's joint positions (``joint_positions``).

**GUI** (``gui=True``, needs pygame): :class:`.gui.PymunkWindow` opens with the scene; the runner
draws the session into it (``window.update(runner)``: the proxy's ghost, the force on the hand,
the epsilon band, the contacts, the server state).
"""
from __future__ import annotations

import math

import numpy as np
import pymunk

from .contacts import FACE_FACE, FACE_VERTEX, VERTEX_FACE, VERTEX_VERTEX, feature_id, fill_planar, reduce_contacts
from .engine import (ContactBuffer, Engine, LinkDescription, SceneInfo, ToolDescription, checked_epsilon,
                     checked_positive, checked_step)
from .geometry import planar_chain, planar_pose, planar_state, wrap_angle
from .scenes import (LINK_COUNT, LINK_IZZ_KG_M2, LINK_LENGTH_M, LINK_MASS_KG, LINK_WIDTH_M, TOOL_IZZ_KG_M2,
                     TOOL_LENGTH_M, TOOL_MASS_KG, TOOL_WIDTH_M, Box, HalfPlane, scene)

_RAW_CAPACITY = 256
_TOOL_GROUP = 1
_SLAB_THICKNESS_M = 0.2
_SLAB_HALF_LENGTH_M = 0.5
#: distance under which a contact point is taken to be at a vertex [m]
_VERTEX_TOL_M = 1e-6
#: env_body id of a tool link seen by another link's query (a self-contact): this + link index
SELF_BODY_BASE = 1000


class _EnvShape:
    """Bookkeeping of one environment shape: its key id and (for static shapes) cached geometry."""

    __slots__ = ("body_id", "shape", "static", "vx", "vy", "nx", "ny")

    def __init__(self, body_id: int, shape: pymunk.Poly, static: bool) -> None:
        self.body_id = body_id
        self.shape = shape
        self.static = static
        self.vx = self.vy = self.nx = self.ny = None
        if static:
            self.vx, self.vy, self.nx, self.ny = _world_geometry(shape)


def _world_geometry(shape: pymunk.Poly):
    """World vertices and outward unit edge normals of a polygon (edge j from vertex j to j+1)."""
    body = shape.body
    verts = [body.local_to_world(v) for v in shape.get_vertices()]
    m = len(verts)
    vx = [v.x for v in verts]
    vy = [v.y for v in verts]
    area2 = sum(vx[j] * vy[(j + 1) % m] - vx[(j + 1) % m] * vy[j] for j in range(m))
    sign = 1.0 if area2 > 0 else -1.0  # counter-clockwise: outward = edge rotated by -90 deg
    nx, ny = [], []
    for j in range(m):
        ex, ey = vx[(j + 1) % m] - vx[j], vy[(j + 1) % m] - vy[j]
        length = math.hypot(ex, ey)
        nx.append(sign * ey / length)
        ny.append(-sign * ex / length)
    return vx, vy, nx, ny


def _feature(px: float, py: float, ux: float, uy: float, vx, vy, nx, ny) -> tuple[bool, int]:
    """Which feature of a polygon the point p (on its surface) lies on: ``(True, vertex)`` if p is
    at a vertex, else ``(False, face)`` with the face whose outward normal best matches u."""
    tol2 = _VERTEX_TOL_M * _VERTEX_TOL_M
    for k in range(len(vx)):
        dx, dy = px - vx[k], py - vy[k]
        if dx * dx + dy * dy <= tol2:
            return True, k
    best, face = -2.0, 0
    for j in range(len(nx)):
        c = nx[j] * ux + ny[j] * uy
        if c > best:
            best, face = c, j
    return False, face


def _add_tool_part(space, mass_kg: float, izz_kg_m2: float, local: list, position: tuple[float, float],
                   angle_rad: float, center_of_gravity: tuple[float, float] | None = None):
    """A dynamic tool body (the rigid tool or one link) with its polygon ``local`` (body frame), in
    the tool's collision group (tool parts never collide with each other), added to ``space``."""
    body = pymunk.Body(mass_kg, izz_kg_m2)
    if center_of_gravity is not None:
        body.center_of_gravity = center_of_gravity
    body.position = position
    body.angle = angle_rad
    shape = pymunk.Poly(body, local)
    shape.friction = 0.5
    shape.elasticity = 0.0
    shape.filter = pymunk.ShapeFilter(group=_TOOL_GROUP)
    space.add(body, shape)
    return body, shape


class PymunkEngine(Engine):
    """pymunk 7 world with the peg as the tool (see the module docstring)."""

    name = f"pymunk {pymunk.version}"
    #: Chipmunk steps the same calls to the same results
    deterministic = True
    #: what ``--gui`` needs (the CLI checks before it starts)
    gui_packages = ("pygame",)

    def __init__(self, rate_hz: float = 60.0, *, substeps: int = 2, max_speed_m_per_s: float = 0.3,
                 max_force_n: float = 40.0, max_torque_n_m: float = 1.0, max_spin_rad_per_s: float = 6.0,
                 use_wrench: bool = False, gui: bool = False) -> None:
        checked_positive(rate_hz=rate_hz, max_speed_m_per_s=max_speed_m_per_s, max_force_n=max_force_n,
                         max_torque_n_m=max_torque_n_m, max_spin_rad_per_s=max_spin_rad_per_s)
        if not (isinstance(substeps, int) and 1 <= substeps <= 100):
            raise ValueError(f"substeps: must be an int in 1..100, got {substeps!r}")
        self.rate_hz = float(rate_hz)
        self.substeps = substeps
        self.max_speed_m_per_s = float(max_speed_m_per_s)
        self.max_force_n = float(max_force_n)
        self.max_torque_n_m = float(max_torque_n_m)
        self.max_spin_rad_per_s = float(max_spin_rad_per_s)
        self.use_wrench = bool(use_wrench)
        self._gui_wanted = bool(gui)
        self.window = None
        self.space: pymunk.Space | None = None
        self._eps = 0.0
        self._t = 0.0
        self._raw = ContactBuffer(_RAW_CAPACITY)
        self.steps = 0
        #: contacts found by the last ``contacts()`` before clustering (informative)
        self.contacts_found = 0

    # ------------------------------------------------------------------------ interface
    @classmethod
    def scenes(cls) -> tuple[str, ...]:
        return ("testbed", "hole", "wall", "push", "linkage")

    def load_scene(self, name: str) -> SceneInfo:
        sc = scene(name, self.scenes())
        self._linkage = name == "linkage"
        space = pymunk.Space()
        space.gravity = (0.0, 0.0)
        space.iterations = 20
        space.collision_slop = 1e-4  # 0.1 mm: the default (0.1) assumes pixels
        space.damping = 0.3 if any(isinstance(o, Box) and o.mass_kg for o in sc.obstacles) else 1.0
        self._env: dict[pymunk.Shape, _EnvShape] = {}
        self.movable: list[pymunk.Body] = []
        for body_id, ob in enumerate(sc.obstacles, start=1):
            if isinstance(ob, HalfPlane):
                shape = pymunk.Poly(space.static_body, _slab(ob))
                static = True
            elif ob.mass_kg is None:
                shape = pymunk.Poly(space.static_body, ob.vertices())
                static = True
            else:
                body = pymunk.Body(ob.mass_kg, pymunk.moment_for_box(ob.mass_kg, ob.size))
                body.position = ob.centre
                body.angle = ob.angle
                shape = pymunk.Poly.create_box(body, ob.size)
                space.add(body)
                self.movable.append(body)
                static = False
            shape.friction = 0.5
            shape.elasticity = 0.0
            space.add(shape)
            self._env[shape] = _EnvShape(body_id, shape, static)
        if self._linkage:
            return self._load_linkage(name, sc, space)
        # The tool and its driver.
        half_l, half_w = TOOL_LENGTH_M / 2, TOOL_WIDTH_M / 2
        self._tool_local = [(-half_l, -half_w), (half_l, -half_w), (half_l, half_w), (-half_l, half_w)]
        x, y, th = sc.tool_start
        tool, tool_shape = _add_tool_part(space, TOOL_MASS_KG, TOOL_IZZ_KG_M2, self._tool_local, (x, y), th)
        control = self._drive(space, tool, x, y, th)
        self.space, self.tool, self.tool_shape, self.control = space, tool, tool_shape, control
        self._target = (x, y, th, 0.0, 0.0, 0.0)
        info_tool = ToolDescription("planar", TOOL_MASS_KG, (0.0, 0.0, 0.0), (0.0, 0.0, TOOL_IZZ_KG_M2, 0.0, 0.0, 0.0))
        return self._loaded(name, sc, info_tool, "pivot+gear joints to a kinematic proxy body")

    def _loaded(self, name: str, sc, tool: ToolDescription, coupling: str) -> SceneInfo:
        """The end of every load: clocks reset, the query shapes, the window, the SceneInfo."""
        self._wrench = (0.0, 0.0, 0.0)
        self._t = 0.0
        self.steps = 0
        self._scene = sc
        self.set_epsilon(self._eps)
        if self._gui_wanted and self.window is None:
            from .gui import PymunkWindow  # pygame is an optional extra

            self.window = PymunkWindow(self)
        facts = dict(sc.facts)
        facts["obstacles"] = [ob.name for ob in sc.obstacles]
        facts["coupling"] = (f"{coupling}: max_bias {self.max_speed_m_per_s} m/s, max_force {self.max_force_n} N, "
                             f"{self.max_torque_n_m} N m")
        return SceneInfo(name, tool, env_rate_hz=self.rate_hz, facts=facts)

    def _drive(self, space, body: pymunk.Body, x: float, y: float, th: float) -> pymunk.Body:
        """A kinematic control body at (x, y, th) and the pivot + gear coupling of ``body`` to it."""
        control = pymunk.Body(body_type=pymunk.Body.KINEMATIC)
        control.position = (x, y)
        control.angle = th
        pivot = pymunk.PivotJoint(control, body, body.center_of_gravity, body.center_of_gravity)
        pivot.max_bias = self.max_speed_m_per_s
        pivot.max_force = self.max_force_n
        pivot.error_bias = (1.0 - 0.3) ** 60.0  # 30 % of the error per 1/60 s
        gear = pymunk.GearJoint(control, body, 0.0, 1.0)
        gear.max_bias = self.max_spin_rad_per_s
        gear.max_force = self.max_torque_n_m
        gear.error_bias = (1.0 - 0.3) ** 60.0
        space.add(control, pivot, gear)
        return control

    def _load_linkage(self, name, sc, space) -> SceneInfo:
        """The chain of ``scenes.LINK_*`` bars (module docstring)."""
        L, W = LINK_LENGTH_M, LINK_WIDTH_M
        self._link_local = [(0.0, -W / 2), (L, -W / 2), (L, W / 2), (0.0, W / 2)]
        x, y, th = sc.tool_start
        self.links, self.link_shapes, self.controls = [], [], []
        self._self_env: dict[pymunk.Shape, tuple[int, _EnvShape]] = {}
        for k in range(LINK_COUNT):
            body, shape = _add_tool_part(space, LINK_MASS_KG, LINK_IZZ_KG_M2, self._link_local,
                                         (x + k * L * math.cos(th), y + k * L * math.sin(th)), th,
                                         center_of_gravity=(L / 2, 0.0))  # position = the link's pivot
            if k:
                space.add(pymunk.PivotJoint(self.links[-1], body, (L, 0.0), (0.0, 0.0)))
            self.controls.append(self._drive(space, body, body.position.x, body.position.y, th))
            self.links.append(body)
            self.link_shapes.append(shape)
            self._self_env[shape] = (k, _EnvShape(SELF_BODY_BASE + k, shape, False))
        self.space, self.tool, self.tool_shape, self.control = space, self.links[0], self.link_shapes[0], self.controls[0]
        self._tool_local = self._link_local
        self._target = (x, y, th, 0.0, 0.0, 0.0)
        self._joint_target = np.zeros(LINK_COUNT - 1)
        self._joint_rate_target = np.zeros(LINK_COUNT - 1)
        inertia = (LINK_MASS_KG * W * W / 12.0, LINK_MASS_KG * L * L / 12.0, LINK_IZZ_KG_M2, 0.0, 0.0, 0.0)
        links = [LinkDescription(LINK_MASS_KG, (L / 2, 0.0, 0.0), inertia)]
        links += [LinkDescription(LINK_MASS_KG, (L / 2, 0.0, 0.0), inertia, k - 1, "revolute", (0.0, 0.0, 1.0),
                                  (L, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0)) for k in range(1, LINK_COUNT)]
        info_tool = ToolDescription("linkage", LINK_MASS_KG * LINK_COUNT, links=tuple(links), held_link=LINK_COUNT - 1)
        return self._loaded(name, sc, info_tool, "each link: pivot+gear joints to a kinematic proxy body")

    def link_targets(self) -> list[tuple[float, float, float, float, float, float]]:
        """(x, y, angle, vx, vy, w) of every link's frame at the proxy's state (the last ProxyState):
        the planar chain's forward kinematics from the root and the joints."""
        return planar_chain(self._target, self._joint_target, self._joint_rate_target, LINK_LENGTH_M)

    def drive_joints(self, position: np.ndarray, velocity: np.ndarray, effort: np.ndarray) -> None:
        if not self._linkage:
            raise NotImplementedError("this scene's tool is rigid: it has no joints")
        if len(position) == 0:
            return  # a server that does not model the joints: they keep their last targets
        if len(position) != LINK_COUNT - 1 or len(velocity) != LINK_COUNT - 1:
            raise ValueError(f"position, velocity: expected {LINK_COUNT - 1} joints, got {len(position)}, {len(velocity)}")
        self._joint_target[:] = position
        self._joint_rate_target[:] = velocity

    def joint_positions(self, out: np.ndarray) -> np.ndarray:
        if not self._linkage:
            raise NotImplementedError("this scene's tool is rigid: it has no joints")
        # in (-pi, pi]: the drive keeps each body's angle continuous with its own past, so two
        # neighbours' raw angles may be a turn apart (the chain's pose is the same)
        for k in range(1, LINK_COUNT):
            out[k - 1] = wrap_angle(self.links[k].angle - self.links[k - 1].angle)
        return out

    def set_epsilon(self, epsilon_m: float) -> None:
        self._eps = epsilon_m = checked_epsilon(epsilon_m)
        if self.space is not None and getattr(self, "_linkage", False):
            # one query shape per link; group 0 so the other links' shapes are found too
            self._queries = []
            for body in self.links:
                q = pymunk.Poly(body, self._link_local, radius=epsilon_m)
                q.filter = pymunk.ShapeFilter()
                self._queries.append(q)
            return
        if self.space is not None:
            q = pymunk.Poly(self.tool, self._tool_local, radius=epsilon_m)
            q.filter = pymunk.ShapeFilter(group=_TOOL_GROUP)
            self._query = q

    def drive_tool(self, proxy_pose: np.ndarray, proxy_twist: np.ndarray, wrench: np.ndarray) -> None:
        self._target = planar_state(proxy_pose, proxy_twist)
        self._wrench = (float(wrench[0]), float(wrench[1]), float(wrench[5]))

    def tool_pose(self, out: np.ndarray) -> np.ndarray:
        p = self.tool.position
        return planar_pose(p.x, p.y, self.tool.angle, out)

    @property
    def time_s(self) -> float:
        return self._t

    def step(self, dt_s: float) -> None:
        dt_s = checked_step(dt_s)
        targets = self.link_targets() if self._linkage else [self._target]
        bodies = self.links if self._linkage else [self.tool]
        controls = self.controls if self._linkage else [self.control]
        for (x, y, th, vx, vy, w), body, c in zip(targets, bodies, controls):
            speed = math.hypot(vx, vy)
            if speed > self.max_speed_m_per_s:
                vx, vy = vx * self.max_speed_m_per_s / speed, vy * self.max_speed_m_per_s / speed
            w = max(-self.max_spin_rad_per_s, min(self.max_spin_rad_per_s, w))
            # Keep the control angle continuous with the body's (the gear joint sees raw angles).
            th = body.angle + wrap_angle(th - body.angle)
            # (a link's control body sits at the link frame's origin, the drive's anchors at its COM)
            c.position = (x, y)
            c.angle = th
            c.velocity = (vx, vy)
            c.angular_velocity = w
        tool = self.tool
        h = dt_s / self.substeps
        for _ in range(self.substeps):
            if self.use_wrench and not self._linkage:
                tool.force = (self._wrench[0], self._wrench[1])
                tool.torque = self._wrench[2]
            self.space.step(h)
        self._t += dt_s
        self.steps += 1

    def contacts(self, buf: ContactBuffer, max_contacts: int) -> int:
        rows = []
        if self._linkage:
            for k, (body, query) in enumerate(zip(self.links, self._queries)):
                self._query_rows(rows, k, body, query)
        else:
            self._query_rows(rows, 0, self.tool, self._query)
        self.contacts_found = len(rows)
        if len(rows) <= min(max_contacts, buf.capacity):
            out = fill_planar(buf, rows)
        else:
            fill_planar(self._raw, rows)
            out = reduce_contacts(self._raw, buf, max_contacts)
        return out

    def _query_rows(self, rows: list, link: int, tool: pymunk.Body, query: pymunk.Poly) -> None:
        """The epsilon-active contacts of one tool body (a link) as rows for ``fill_planar``."""
        eps = self._eps
        tvx = tvy = tnx = tny = None
        for info in self.space.shape_query(query):
            env = self._env.get(info.shape)
            if env is None:
                other = self._self_env.get(info.shape) if self._linkage else None
                # a self-contact needs a link that is not this one nor a neighbour (they share a pivot)
                if other is None or abs(other[0] - link) <= 1:
                    continue
                env = other[1]
            cps = info.contact_point_set
            nab = cps.normal  # tool (a) -> environment (b)
            ux, uy = nab.x, nab.y
            norm = math.hypot(ux, uy)
            if norm == 0.0:
                continue
            ux, uy = ux / norm, uy / norm
            if tvx is None:
                tvx, tvy, tnx, tny = _world_geometry_of(tool, self._tool_local)
            if env.static:
                evx, evy, enx, eny = env.vx, env.vy, env.nx, env.ny
            else:
                evx, evy, enx, eny = _world_geometry(env.shape)
            seen = None
            for p in cps.points:
                pa, pb = p.point_a, p.point_b
                bx, by = pb.x, pb.y
                # the real tool's point: the rounded surface point minus the swept radius
                ax, ay = pa.x - eps * ux, pa.y - eps * uy
                t_vertex, t_idx = _feature(ax, ay, ux, uy, tvx, tvy, tnx, tny)
                e_vertex, e_idx = _feature(bx, by, -ux, -uy, evx, evy, enx, eny)
                if t_vertex:
                    feat = feature_id(VERTEX_VERTEX if e_vertex else VERTEX_FACE, t_idx, e_idx)
                else:
                    feat = feature_id(FACE_VERTEX if e_vertex else FACE_FACE, t_idx, e_idx)
                if feat == seen:
                    continue  # Chipmunk repeats a single point when the overlap is a corner
                seen = feat
                if env.static:
                    vc = 0.0
                else:
                    v = env.shape.body.velocity_at_world_point((bx, by))
                    vc = -(ux * v.x + uy * v.y)  # n . v(c_p), n = -u
                rows.append((env.body_id, feat, bx, by, -ux, -uy, p.distance + eps, vc, link))

    def close(self) -> None:
        if self.window is not None:
            self.window.close()
            self.window = None


def _world_geometry_of(body: pymunk.Body, local: list) -> tuple:
    """World vertices and outward normals of the tool (its local polygon is counter-clockwise)."""
    p = body.position
    c, s = math.cos(body.angle), math.sin(body.angle)
    x0, y0 = p.x, p.y
    vx = [x0 + c * lx - s * ly for lx, ly in local]
    vy = [y0 + s * lx + c * ly for lx, ly in local]
    m = len(local)
    nx, ny = [], []
    for j in range(m):
        ex, ey = vx[(j + 1) % m] - vx[j], vy[(j + 1) % m] - vy[j]
        length = math.hypot(ex, ey)
        nx.append(ey / length)
        ny.append(-ex / length)
    return vx, vy, nx, ny


def _slab(hp: HalfPlane) -> list[tuple[float, float]]:
    """A thick rectangle standing in for a half-plane: its free face on the plane."""
    (px, py), (nx, ny) = hp.point, hp.normal
    tx, ty = -ny, nx
    L, T = _SLAB_HALF_LENGTH_M, _SLAB_THICKNESS_M
    return [(px + tx * L, py + ty * L), (px - tx * L, py - ty * L),
            (px - tx * L - nx * T, py - ty * L - ny * T), (px + tx * L - nx * T, py + ty * L - ny * T)]
