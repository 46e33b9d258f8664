"""A Vortex-style stub engine: the engine-neutral reference environment, written from the spec's
point of view.

What it models, deliberately like a commercial penalty-based engine of the paper's time:

- **Geometry**: analytic and planar. The tool is a convex polygon (the paper's rectangular peg);
  the environment is half-planes and static convex polygons (the scenes of :mod:`.scenes`:
  ``testbed``, ``hole``, ``wall``, ``piston``). No connectivity information is kept or used.
- **Contacts**: basic contacts only, found per feature pair: *vertex-face* (a tool corner on an
  environment face), *face-vertex* (an environment corner on a tool face) and *vertex-vertex*
  (two corners; the planar counterpart of a 3-D edge-edge contact). Collision detection runs on
  the tool inflated by a disc of radius epsilon (the swept sphere): a contact is reported when
  the inflated tool touches or overlaps, i.e. when the real tool's separation
  ``d = s_eps + epsilon <= epsilon``. Keys are ``(0, body, feature)`` with the feature pair of
  :func:`.contacts.feature_id`, so a contact keeps its key while the same features touch. The
  moving wall of ``piston`` reports its normal velocity as ``v_constr``.
- **Tool and driving**: the tool is a dynamic rigid body (the scene's mass and inertia) pulled
  towards the newest proxy pose and twist by a critically damped spring-damper (8 Hz; the
  coupling, its spring saturating at 20 N and 0.5 N m), pushed out of the environment by
  one-sided penalty springs (20 kN/m, damped) at its penetrating contacts, so a proxy deep inside
  a wall presses the tool in by at most 20 N / 20 kN/m = 1 mm (0.5 mm on two corners). Both are integrated with *linearly implicit* Euler
  ``(M + h B + h^2 K) dv = h (f - h K v)``, which is stable for any stiffness and step and
  dissipative (it cannot inject energy into a spring-damper system). It does not tunnel: a step
  whose motion would exceed 4 mm is split into substeps (at most 8, then the velocity is
  capped), far less than the thinnest wall (40 mm; half-planes have no far side). The server's
  ``wrench`` is applied to the tool only with ``use_wrench=True`` (the coupling already carries the
  proxy's motion).
- **Rate**: variable, 30-60 Hz: the nominal rate wanders (a bounded random walk) and every step
  jitters by +-10 %; :meth:`StubEngine.next_step_s` draws it. Everything, rate included, is
  deterministic for a given ``seed`` and sequence of ``drive_tool`` calls.

Pure Python floats: a testbed step plus contact query costs tens of microseconds
(``hapticproxy bench clients``).
"""
from __future__ import annotations

import math
import random

import numpy as np

from .contacts import FACE_VERTEX, VERTEX_FACE, VERTEX_VERTEX, feature_id, fill_planar, reduce_contacts
from .engine import ContactBuffer, Engine, SceneInfo, ToolDescription, checked_epsilon, checked_step
from .geometry import planar_pose, planar_state, wrap_angle
from .scenes import TOOL_IZZ_KG_M2, TOOL_LENGTH_M, TOOL_MASS_KG, TOOL_WIDTH_M, Box, HalfPlane, scene

_RAW_CAPACITY = 256
_TWO_PI = 2.0 * math.pi


class _Half:
    __slots__ = ("body", "px", "py", "nx", "ny", "amp", "omega")

    def __init__(self, body: int, hp: HalfPlane) -> None:
        self.body = body
        self.px, self.py = hp.point
        self.nx, self.ny = hp.normal
        self.amp, f = hp.oscillation or (0.0, 0.0)
        self.omega = _TWO_PI * f


class _Poly:
    __slots__ = ("body", "vx", "vy", "nx", "ny", "ex", "ey", "len2", "cx", "cy", "xmin", "xmax", "ymin", "ymax")

    def __init__(self, body: int, verts: list[tuple[float, float]]) -> None:
        self.body = body
        self.vx = [v[0] for v in verts]
        self.vy = [v[1] for v in verts]
        m = len(verts)
        self.ex, self.ey, self.nx, self.ny, self.len2 = [], [], [], [], []
        for j in range(m):
            ex = self.vx[(j + 1) % m] - self.vx[j]
            ey = self.vy[(j + 1) % m] - self.vy[j]
            length = math.hypot(ex, ey)
            self.ex.append(ex)
            self.ey.append(ey)
            self.len2.append(ex * ex + ey * ey)
            self.nx.append(ey / length)  # counter-clockwise winding: outward = edge rotated by -90 deg
            self.ny.append(-ex / length)
        self.cx, self.cy = sum(self.vx) / m, sum(self.vy) / m  # inside: the polygon is convex
        self.xmin, self.xmax = min(self.vx), max(self.vx)
        self.ymin, self.ymax = min(self.vy), max(self.vy)


#: points within this distance of a polygon's boundary count as on it [m] (rounding, not geometry)
_ON_BOUNDARY_M = 1e-9


def _point_vs_poly(qx: float, qy: float, vx, vy, ex, ey, len2, nx, ny, reach: float, rx: float, ry: float):
    """Nearest feature of a convex polygon to the point q, if within ``reach`` of its boundary
    (or inside). Returns ``(is_face, index, cpx, cpy, normal_x, normal_y, signed_distance)`` with
    the normal pointing from the polygon towards q, or ``None``.

    ``(rx, ry)`` is a point inside the *other* body (its centroid): when q sits on a corner of the
    polygon (two faces equally near, e.g. the peg's corner at the bottom corner of a tight hole),
    the face that looks towards the other body is the contact's face; a corner-corner normal
    from a rounding-sized displacement would point anywhere.
    """
    m = len(vx)
    smax = -math.inf
    jmax = 0
    for j in range(m):
        sj = nx[j] * (qx - vx[j]) + ny[j] * (qy - vy[j])
        if sj > smax:
            smax, jmax = sj, j
    if smax <= _ON_BOUNDARY_M:  # inside or on the boundary: the face of least penetration
        best = -math.inf
        for j in range(m):
            sj = nx[j] * (qx - vx[j]) + ny[j] * (qy - vy[j])
            if sj >= smax - _ON_BOUNDARY_M:
                facing = nx[j] * (rx - qx) + ny[j] * (ry - qy)
                if facing > best:
                    best, jmax = facing, j
        sj = nx[jmax] * (qx - vx[jmax]) + ny[jmax] * (qy - vy[jmax])
        return True, jmax, qx - sj * nx[jmax], qy - sj * ny[jmax], nx[jmax], ny[jmax], sj
    if smax > reach:  # outside a convex polygon the distance is at least the largest face distance
        return None
    best = math.inf
    hit = None
    for j in range(m):
        u = ((qx - vx[j]) * ex[j] + (qy - vy[j]) * ey[j]) / len2[j]
        if u <= 0.0:
            cx, cy, is_face, k = vx[j], vy[j], False, j
        elif u >= 1.0:
            k = (j + 1) % m
            cx, cy, is_face = vx[k], vy[k], False
        else:
            cx, cy, is_face, k = vx[j] + u * ex[j], vy[j] + u * ey[j], True, j
        dx, dy = qx - cx, qy - cy
        dist2 = dx * dx + dy * dy
        if dist2 < best:
            best, hit = dist2, (is_face, k, cx, cy, dx, dy)
    dist = math.sqrt(best)  # >= smax > _ON_BOUNDARY_M: q is outside
    if dist > reach:
        return None
    is_face, k, cx, cy, dx, dy = hit
    if is_face:
        return True, k, cx, cy, nx[k], ny[k], dist
    return False, k, cx, cy, dx / dist, dy / dist, dist


class StubEngine(Engine):
    """The Vortex-style reference engine (see the module docstring)."""

    name = "hapticproxy-stub 1"
    #: the same seed and drive calls give the same steps, rate included
    deterministic = True

    #: coupling natural frequency [Hz] (critically damped spring-damper to the proxy)
    COUPLING_HZ = 8.0
    #: the coupling spring's force [N] and torque [N m] saturate here (a constant pull beyond)
    MAX_COUPLING_FORCE_N = 20.0
    MAX_COUPLING_TORQUE_N_M = 0.5
    #: penalty stiffness [N/m] and damping ratio of the environment's contacts
    PENALTY_N_PER_M = 20000.0
    PENALTY_DAMPING_RATIO = 0.7
    #: largest tool displacement in one (sub)step [m], the anti-tunnelling bound
    MAX_STEP_MOTION_M = 0.004
    MAX_SUBSTEPS = 8

    def __init__(self, seed: int = 0, *, rate_range_hz: tuple[float, float] = (30.0, 60.0), jitter: float = 0.1,
                 use_wrench: bool = False) -> None:
        lo, hi = rate_range_hz
        if not (0 < lo <= hi):
            raise ValueError(f"rate_range_hz: need 0 < low <= high, got {rate_range_hz!r}")
        if not 0 <= jitter < 1:
            raise ValueError(f"jitter: must be in [0, 1), got {jitter!r}")
        self.seed = int(seed)
        self.rate_range_hz = (float(lo), float(hi))
        self.jitter = float(jitter)
        self.use_wrench = bool(use_wrench)
        self._rng = random.Random(self.seed)
        self._rate_hz = 0.5 * (lo + hi)
        self._scene = None
        self._env: list = []
        self._eps = 0.0
        self._t = 0.0
        self._raw = ContactBuffer(_RAW_CAPACITY)
        self._cache = None
        self.steps = 0
        self.substeps = 0
        #: contacts found by the last ``contacts()`` before clustering (informative)
        self.contacts_found = 0
        self._set_tool(TOOL_LENGTH_M, TOOL_WIDTH_M, TOOL_MASS_KG, TOOL_IZZ_KG_M2)

    def _set_tool(self, length: float, width: float, mass: float, izz: float) -> None:
        a, b = length / 2, width / 2
        self._tool_local = ((-a, -b), (a, -b), (a, b), (-a, b))  # counter-clockwise
        self._tool_normals = ((0.0, -1.0), (1.0, 0.0), (0.0, 1.0), (-1.0, 0.0))
        self._tool_radius = math.hypot(a, b)
        self.mass_kg, self.izz_kg_m2 = mass, izz
        w = _TWO_PI * self.COUPLING_HZ
        self._kc, self._bc = mass * w * w, 2.0 * mass * w
        self._kr, self._br = izz * w * w, 2.0 * izz * w
        self._ke = self.PENALTY_N_PER_M
        self._be = 2.0 * self.PENALTY_DAMPING_RATIO * math.sqrt(self._ke * mass)

    # ------------------------------------------------------------------------ interface
    @classmethod
    def scenes(cls) -> tuple[str, ...]:
        return ("testbed", "hole", "wall", "piston")

    def load_scene(self, name: str) -> SceneInfo:
        sc = scene(name, self.scenes())
        env = []
        for body, ob in enumerate(sc.obstacles, start=1):
            if isinstance(ob, HalfPlane):
                env.append(_Half(body, ob))
            elif isinstance(ob, Box) and ob.mass_kg is None:
                env.append(_Poly(body, ob.vertices()))
            else:  # pragma: no cover - the stub's scene list has no movable bodies
                raise ValueError(f"scene {name!r}: the stub has no movable bodies ({ob.name})")
        self._scene = sc
        self._env = env
        self._t = 0.0
        self.steps = self.substeps = 0
        self._rng = random.Random(self.seed)
        self._rate_hz = 0.5 * sum(self.rate_range_hz)
        x, y, th = sc.tool_start
        self._q = [x, y, th]
        self._v = [0.0, 0.0, 0.0]
        self._target = [x, y, th, 0.0, 0.0, 0.0]  # hold the start pose until a proxy state arrives
        self._wrench = (0.0, 0.0, 0.0)
        self._cache = None
        tool = ToolDescription("planar", self.mass_kg, (0.0, 0.0, 0.0), (0.0, 0.0, self.izz_kg_m2, 0.0, 0.0, 0.0))
        facts = dict(sc.facts)
        facts["obstacles"] = [ob.name for ob in sc.obstacles]
        return SceneInfo(name, tool, env_rate_hz=self._rate_hz, facts=facts)

    def set_epsilon(self, epsilon_m: float) -> None:
        self._eps = checked_epsilon(epsilon_m)

    def next_step_s(self) -> float:
        lo, hi = self.rate_range_hz
        rng = self._rng
        self._rate_hz = min(hi, max(lo, self._rate_hz + rng.gauss(0.0, 0.05 * (hi - lo))))
        dt = (1.0 + self.jitter * (2.0 * rng.random() - 1.0)) / self._rate_hz
        return min(1.0 / lo, max(1.0 / hi, dt))

    def drive_tool(self, proxy_pose: np.ndarray, proxy_twist: np.ndarray, wrench: np.ndarray) -> None:
        self._target = list(planar_state(proxy_pose, proxy_twist))
        self._wrench = (float(wrench[0]), float(wrench[1]), float(wrench[5]))

    def tool_pose(self, out: np.ndarray) -> np.ndarray:
        x, y, th = self._q
        return planar_pose(x, y, th, out)

    @property
    def time_s(self) -> float:
        return self._t

    def step(self, dt_s: float) -> None:
        dt_s = checked_step(dt_s)
        q0, v0, t0 = list(self._q), list(self._v), self._t
        motion = self._substep(dt_s)
        n = 1
        if motion > self.MAX_STEP_MOTION_M:
            # Too far for one step: redo it in substeps so contacts are found on the way.
            n = min(self.MAX_SUBSTEPS, math.ceil(motion / self.MAX_STEP_MOTION_M))
            self._q, self._v, self._t = q0, v0, t0
            h = dt_s / n
            for _ in range(n):
                self._substep(h, cap=True)
        self.steps += 1
        self.substeps += n

    def contacts(self, buf: ContactBuffer, max_contacts: int) -> int:
        found = self._contacts_here(self._eps)
        self.contacts_found = len(found)
        if len(found) <= min(max_contacts, buf.capacity):
            return fill_planar(buf, found)
        fill_planar(self._raw, found)
        return reduce_contacts(self._raw, buf, max_contacts)

    # ------------------------------------------------------------------------ internals
    def _substep(self, h: float, cap: bool = False) -> float:
        """One linearly implicit Euler step of length ``h``; returns the largest point motion [m]."""
        x, y, th = self._q
        vx, vy, w = self._v
        px, py, pth, pvx, pvy, pw = self._target
        kc, bc, kr, br, ke, be = self._kc, self._bc, self._kr, self._br, self._ke, self._be
        # The coupling spring saturates (like a joint's max force): beyond the cap it pulls with a
        # constant force and contributes no stiffness, so a proxy far inside a wall presses the
        # tool into the penalty springs by at most cap / stiffness.
        sx, sy, st = kc * (px - x), kc * (py - y), kr * wrap_angle(pth - th)
        f = math.hypot(sx, sy)
        if f > self.MAX_COUPLING_FORCE_N:
            sx, sy, kc = sx * self.MAX_COUPLING_FORCE_N / f, sy * self.MAX_COUPLING_FORCE_N / f, 0.0
        if abs(st) > self.MAX_COUPLING_TORQUE_N_M:
            st, kr = math.copysign(self.MAX_COUPLING_TORQUE_N_M, st), 0.0
        fx = sx + bc * (pvx - vx)
        fy = sy + bc * (pvy - vy)
        ft = st + br * (pw - w)
        if self.use_wrench:
            fx += self._wrench[0]
            fy += self._wrench[1]
            ft += self._wrench[2]
        # The penetrating contacts' geometry G = sum of J J^T, J = (nx, ny, jt) (symmetric 3x3: xx xy
        # xt yy yt tt); their penalty springs and dampers add ke G and be G to the coupling's.
        gxx = gxy = gxt = gyy = gyt = gtt = 0.0
        for _body, _feature, cx, cy, nx, ny, d, _vc in self._contacts_here(0.0):
            if d >= 0.0:
                continue
            # lever arm to the real tool's point of the contact: c_p + d n (eq. 1's point)
            rx = cx + d * nx - x
            ry = cy + d * ny - y
            jt = rx * ny - ry * nx
            lam = ke * (-d) - be * (nx * vx + ny * vy + jt * w)
            if lam > 0.0:
                fx += lam * nx
                fy += lam * ny
                ft += lam * jt
            gxx += nx * nx
            gxy += nx * ny
            gxt += nx * jt
            gyy += ny * ny
            gyt += ny * jt
            gtt += jt * jt
        kxx, kxy, kxt, kyy, kyt, ktt = kc + ke * gxx, ke * gxy, ke * gxt, kc + ke * gyy, ke * gyt, kr + ke * gtt
        bxx, bxy, bxt, byy, byt, btt = bc + be * gxx, be * gxy, be * gxt, bc + be * gyy, be * gyt, br + be * gtt
        m, iz, h2 = self.mass_kg, self.izz_kg_m2, h * h
        a11 = m + h * bxx + h2 * kxx
        a12 = h * bxy + h2 * kxy
        a13 = h * bxt + h2 * kxt
        a22 = m + h * byy + h2 * kyy
        a23 = h * byt + h2 * kyt
        a33 = iz + h * btt + h2 * ktt
        r1 = h * (fx - h * (kxx * vx + kxy * vy + kxt * w))
        r2 = h * (fy - h * (kxy * vx + kyy * vy + kyt * w))
        r3 = h * (ft - h * (kxt * vx + kyt * vy + ktt * w))
        # Symmetric 3x3 solve by cofactors (the matrix is positive definite).
        c11 = a22 * a33 - a23 * a23
        c12 = a13 * a23 - a12 * a33
        c13 = a12 * a23 - a13 * a22
        det = a11 * c11 + a12 * c12 + a13 * c13
        c22 = a11 * a33 - a13 * a13
        c23 = a12 * a13 - a11 * a23
        c33 = a11 * a22 - a12 * a12
        vx += (c11 * r1 + c12 * r2 + c13 * r3) / det
        vy += (c12 * r1 + c22 * r2 + c23 * r3) / det
        w += (c13 * r1 + c23 * r2 + c33 * r3) / det
        motion = h * (math.hypot(vx, vy) + abs(w) * self._tool_radius)
        if cap and motion > self.MAX_STEP_MOTION_M:
            scale = self.MAX_STEP_MOTION_M / motion  # removes energy, never adds it
            vx, vy, w = vx * scale, vy * scale, w * scale
            motion = self.MAX_STEP_MOTION_M
        self._q = [x + h * vx, y + h * vy, th + h * w]
        self._v = [vx, vy, w]
        self._t += h
        return motion

    def _contacts_here(self, reach: float) -> list:
        """The contacts with ``d <= reach`` at the current state. The runner asks for the epsilon
        contacts after a step and the next step needs the penetrating ones at the same state, so
        the last query is cached and filtered when it reached at least as far."""
        x, y, th = self._q
        key = (x, y, th, self._t)
        cached = self._cache
        if cached is not None and cached[0] == key and cached[1] >= reach:
            found = cached[2]
            return found if cached[1] == reach else [c for c in found if c[6] <= reach]
        found = []
        self._detect(x, y, th, self._t, reach, found)
        self._cache = (key, reach, found)
        return found

    def _detect(self, x: float, y: float, th: float, t: float, reach: float, out: list) -> None:
        """Append every basic contact with real separation ``d <= reach`` to ``out`` as tuples
        ``(body, feature, cx, cy, nx, ny, d, v_constr)``."""
        c, s = math.cos(th), math.sin(th)
        tvx, tvy, tnx, tny = [], [], [], []
        for (lx, ly), (lnx, lny) in zip(self._tool_local, self._tool_normals):
            tvx.append(x + c * lx - s * ly)
            tvy.append(y + s * lx + c * ly)
            tnx.append(c * lnx - s * lny)
            tny.append(s * lnx + c * lny)
        nt = len(tvx)
        txmin, txmax = min(tvx) - reach, max(tvx) + reach
        tymin, tymax = min(tvy) - reach, max(tvy) + reach
        tex = [tvx[(i + 1) % nt] - tvx[i] for i in range(nt)]
        tey = [tvy[(i + 1) % nt] - tvy[i] for i in range(nt)]
        tl2 = [tex[i] * tex[i] + tey[i] * tey[i] for i in range(nt)]
        for ob in self._env:
            if type(ob) is _Half:
                nx, ny = ob.nx, ob.ny
                px, py, vc = ob.px, ob.py, 0.0
                if ob.amp:
                    off = ob.amp * math.sin(ob.omega * t)
                    px, py = px + nx * off, py + ny * off
                    vc = ob.amp * ob.omega * math.cos(ob.omega * t)
                for i in range(nt):
                    d = nx * (tvx[i] - px) + ny * (tvy[i] - py)
                    if d <= reach:
                        out.append((ob.body, feature_id(VERTEX_FACE, i, 0), tvx[i] - d * nx, tvy[i] - d * ny, nx, ny, d, vc))
                continue
            if ob.xmin > txmax or ob.xmax < txmin or ob.ymin > tymax or ob.ymax < tymin:
                continue
            # (a) tool corners against the polygon: vertex-face or vertex-vertex
            bxmin, bxmax, bymin, bymax = ob.xmin - reach, ob.xmax + reach, ob.ymin - reach, ob.ymax + reach
            for i in range(nt):
                qx, qy = tvx[i], tvy[i]
                if qx < bxmin or qx > bxmax or qy < bymin or qy > bymax:
                    continue
                hit = _point_vs_poly(qx, qy, ob.vx, ob.vy, ob.ex, ob.ey, ob.len2, ob.nx, ob.ny, reach, x, y)
                if hit is not None:
                    is_face, k, cx, cy, nx, ny, d = hit
                    kind = VERTEX_FACE if is_face else VERTEX_VERTEX
                    out.append((ob.body, feature_id(kind, i, k), cx, cy, nx, ny, d, 0.0))
            # (b) environment corners against the tool: face-vertex (corner-corner is (a)'s)
            for k in range(len(ob.vx)):
                qx, qy = ob.vx[k], ob.vy[k]
                if qx < txmin or qx > txmax or qy < tymin or qy > tymax:
                    continue
                hit = _point_vs_poly(qx, qy, tvx, tvy, tex, tey, tl2, tnx, tny, reach, ob.cx, ob.cy)
                if hit is not None and hit[0]:
                    i, d = hit[1], hit[6]
                    # the normal points from the environment (the corner) towards the tool
                    out.append((ob.body, feature_id(FACE_VERTEX, i, k), qx, qy, -tnx[i], -tny[i], d, 0.0))
