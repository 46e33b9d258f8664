"""pybullet's own window for the pybullet engines (``--gui``): the scene framed by the camera, the
proxy as a translucent ghost of the tool, the contact normals and the server state
(:mod:`.views` says what each shows and in which colour).

- **Camera**: :func:`frame_camera` aims at the centre of the scene's bodies other than the floor
  (the tool, the hole's block, the loose bodies, the obstacle) and backs off until their bounding
  sphere fits the view with a margin, for the window's field of view and aspect; pybullet's
  default camera sits ~5 m away from a scene a few centimetres across. The side panels are hidden
  so the scene gets the whole window.
- **Ghost**: a visual-only body (no collision shape, so it never touches anything and no contact
  query sees it) per box of the tool, or a second copy of a linkage's URDF with its collisions
  filtered out, moved to the newest ProxyState's pose and joints.
- **Contacts**: one debug line per reported contact along its normal (:data:`NORMAL_LENGTH_M`),
  drawn beside the contact, :data:`NORMAL_OFFSET_M` away from it, outwards from the tool's centre
  (perpendicular to the normal): from ``c_p`` itself the normal runs inside the tool (a cube on
  the floor: its corners' normals run up its edges, hidden by its faces). Line ids are reused
  (pybullet redraws a replaced item in place).
- **Force on the hand**: an arrow (:data:`FORCE_M_PER_N`, at most :data:`MAX_ARROW_M`) along the
  force the hand feels, from the hand point pushed out of the proxy's ghost along the arrow (by
  the ghost's bounding radius), so no body hides it.
- **State**: a line of text above the scene in the state's colour.

Drawing costs pybullet round trips to its GUI thread, so :meth:`PybulletView.update` draws at
most ``fps`` frames per second. The computations (:func:`frame_camera`, :func:`normal_segments`,
:func:`project`) are plain functions so they are tested without a display.
"""
from __future__ import annotations

import math
import time

import numpy as np
from ._pybullet import p

from .geometry import IDENTITY_WXYZ, xyzw_from_wxyz
from .views import FORCE_RGB, PROXY_RGB, contact_colour, state_style, view_state

__all__ = ["PybulletView", "frame_camera", "normal_segments", "force_segments", "project", "GUI_FOV_DEG",
           "GUI_ASPECT", "NORMAL_LENGTH_M", "NORMAL_OFFSET_M", "FORCE_M_PER_N", "MAX_ARROW_M"]

#: the vertical field of view [deg] and aspect we frame for: pybullet's GUI camera (60 deg in its
#: example browser) is at least this wide, so what fits here fits the window
GUI_FOV_DEG = 50.0
GUI_ASPECT = 4.0 / 3.0
#: drawn length of a contact normal [m]
NORMAL_LENGTH_M = 0.01
#: how far beside its contact a normal is drawn, outwards from the tool [m]
NORMAL_OFFSET_M = 0.004
#: the force arrow's length per newton [m/N], and its longest [m]
FORCE_M_PER_N = 0.04
MAX_ARROW_M = 0.1
#: the arrow's head: its length as a fraction of the arrow's, and half its opening [deg]
_HEAD_FRACTION = 0.25
_HEAD_HALF_ANGLE_DEG = 25.0
_GHOST_ALPHA = 0.35


def frame_camera(lo, hi, *, fov_deg: float = GUI_FOV_DEG, aspect: float = GUI_ASPECT, yaw_deg: float = 45.0,
                 pitch_deg: float = -35.0, margin: float = 1.3, min_distance_m: float = 0.05) -> dict:
    """Camera (``resetDebugVisualizerCamera`` arguments) that shows the box ``lo``..``hi`` (world,
    m) whole: aimed at its centre, at the distance where its bounding sphere (times ``margin``)
    fits the narrower of the vertical and horizontal fields of view."""
    lo = np.asarray(lo, dtype=float)
    hi = np.asarray(hi, dtype=float)
    if lo.shape != (3,) or hi.shape != (3,) or not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
        raise ValueError("lo, hi: must be 3 finite numbers each")
    centre = 0.5 * (lo + hi)
    radius = 0.5 * float(np.linalg.norm(hi - lo)) * margin
    half_v = math.radians(fov_deg) / 2.0
    half_h = math.atan(math.tan(half_v) * aspect)
    distance = max(min_distance_m, radius / math.sin(min(half_v, half_h)))
    return {"cameraDistance": distance, "cameraYaw": yaw_deg, "cameraPitch": pitch_deg,
            "cameraTargetPosition": [float(v) for v in centre]}


def camera_matrices(camera: dict, *, fov_deg: float = GUI_FOV_DEG, aspect: float = GUI_ASPECT):
    """pybullet's view and projection matrices (column-major 16-tuples) of a :func:`frame_camera`."""
    view = p.computeViewMatrixFromYawPitchRoll(camera["cameraTargetPosition"], camera["cameraDistance"],
                                               camera["cameraYaw"], camera["cameraPitch"], 0.0, 2)
    proj = p.computeProjectionMatrixFOV(fov_deg, aspect, 0.01, 100.0)
    return view, proj


def project(points, view, proj) -> np.ndarray:
    """Normalised device coordinates (n, 3) of world points (n, 3): inside the window when x and
    y are in [-1, 1] (and z in [-1, 1]: between the clipping planes)."""
    V = np.asarray(view, dtype=float).reshape(4, 4).T  # pybullet's matrices are column-major
    P = np.asarray(proj, dtype=float).reshape(4, 4).T
    pts = np.asarray(points, dtype=float)
    h = np.hstack([pts, np.ones((len(pts), 1))]) @ (P @ V).T
    return h[:, :3] / h[:, 3:4]


def normal_segments(position_m, normal, separation_m, length_m: float = NORMAL_LENGTH_M, *, centre_m=None,
                    offset_m: float = NORMAL_OFFSET_M) -> list[tuple]:
    """``(from, to, rgb 0..1)`` of each contact's normal line, along the normal. With the tool's
    ``centre_m`` it starts ``offset_m`` beside ``c_p``, outwards from the centre (the component of
    ``c_p - centre_m`` across the normal; at ``c_p`` when that is nil); without, at ``c_p``."""
    out = []
    centre = None if centre_m is None else np.asarray(centre_m, dtype=float)[:3]
    for c, nrm, d in zip(position_m, normal, separation_m):
        c = np.asarray(c, dtype=float)
        n = np.asarray(nrm, dtype=float)
        start = c
        if centre is not None and offset_m > 0.0:
            r = c - centre
            across = r - float(r @ n) * n
            norm = float(np.linalg.norm(across))
            if norm > 1e-9:
                start = c + (offset_m / norm) * across
        rgb = tuple(v / 255.0 for v in contact_colour(float(d)))
        out.append((tuple(float(v) for v in start), tuple(float(v) for v in start + length_m * n), rgb))
    return out


def force_segments(hand_point_m, force_n, clear_m: float = 0.0, *, m_per_n: float = FORCE_M_PER_N,
                   max_m: float = MAX_ARROW_M) -> list[tuple]:
    """``(from, to)`` of the force arrow's lines (the shaft, then four lines of its head, so it
    reads as an arrow from any side): along ``force_n``, ``m_per_n`` long per newton (at most
    ``max_m``), starting ``clear_m`` from ``hand_point_m`` along it. None for a force below 1 mN."""
    f = np.asarray(force_n, dtype=float)[:3]
    mag = float(np.linalg.norm(f))
    if not (math.isfinite(mag) and mag > 1e-3):
        return []
    u = f / mag
    start = np.asarray(hand_point_m, dtype=float)[:3] + clear_m * u
    length = min(max_m, m_per_n * mag)
    tip = start + length * u
    side = np.cross(u, [0.0, 0.0, 1.0] if abs(u[2]) < 0.9 else [1.0, 0.0, 0.0])
    side /= np.linalg.norm(side)
    other = np.cross(u, side)
    head = _HEAD_FRACTION * length
    back = head * math.cos(math.radians(_HEAD_HALF_ANGLE_DEG))
    spread = head * math.sin(math.radians(_HEAD_HALF_ANGLE_DEG))
    out = [(start, tip)]
    for w in (side, -side, other, -other):
        out.append((tip, tip - back * u + spread * w))
    return [(tuple(float(v) for v in a), tuple(float(v) for v in b)) for a, b in out]


def scene_bounds(cid: int, bodies) -> tuple[np.ndarray, np.ndarray]:
    """The world box holding every body's AABB (all its links)."""
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    for body in bodies:
        for link in range(-1, p.getNumJoints(body, physicsClientId=cid)):
            a, b = p.getAABB(body, link, physicsClientId=cid)
            lo = np.minimum(lo, a)
            hi = np.maximum(hi, b)
    return lo, hi


class PybulletView:
    """The GUI's drawing for one loaded scene (see the module docstring).

    Args:
        cid: the engine's physics client (a ``GUI`` connection).
        focus_bodies: bodies the camera frames (not the floor).
        ghost_boxes: half extents of the tool's boxes (a rigid tool: one), each drawn at the proxy
            pose (a box's centre at the tool frame).
        ghost_urdf: a linkage: its URDF, loaded again as the ghost (joints set from the proxy).
        link_com: a linkage: the base COM frame in the root link frame ``(position, quaternion)``,
            (the ghost's base is placed by its COM, like the tool's).
        fps: most frames drawn per second.
    """

    def __init__(self, cid: int, focus_bodies, *, ghost_boxes=(), ghost_urdf=None, link_com=None,
                 fps: float = 30.0) -> None:
        self.cid = cid
        self.period_s = 1.0 / fps
        self._next_frame = 0.0
        #: called when the window was closed (the CLI stops the client)
        self.on_close = None
        self.camera = frame_camera(*scene_bounds(cid, focus_bodies))
        p.configureDebugVisualizer(p.COV_ENABLE_GUI, 0, physicsClientId=cid)
        p.resetDebugVisualizerCamera(**self.camera, physicsClientId=cid)
        self._ghosts: list[int] = []
        self._ghost_rgb = None
        #: how far the force arrow starts from the hand point: the ghost's bounding radius [m]
        self.clear_m = max((float(np.linalg.norm(half)) for half in ghost_boxes), default=0.0)
        rgba = [v / 255.0 for v in PROXY_RGB] + [_GHOST_ALPHA]
        for half in ghost_boxes:
            vis = p.createVisualShape(p.GEOM_BOX, halfExtents=list(half), rgbaColor=rgba, physicsClientId=cid)
            self._ghosts.append(p.createMultiBody(0.0, -1, vis, [0.0, 0.0, -10.0], physicsClientId=cid))
        self._ghost_urdf = None
        self._link_com = link_com
        if ghost_urdf is not None:
            g = p.loadURDF(str(ghost_urdf), [0.0, 0.0, -10.0], useFixedBase=True, physicsClientId=cid)
            for link in range(-1, p.getNumJoints(g, physicsClientId=cid)):
                p.setCollisionFilterGroupMask(g, link, 0, 0, physicsClientId=cid)
                p.changeVisualShape(g, link, rgbaColor=rgba, physicsClientId=cid)
            self._ghost_urdf = g
            last = p.getNumJoints(g, physicsClientId=cid) - 1
            lo, hi = p.getAABB(g, last, physicsClientId=cid)  # the hand's link (the last)
            self.clear_m = 0.5 * float(np.linalg.norm(np.subtract(hi, lo)))
        self._lines: list[int] = []
        self._arrow: list[int] = []
        self._text = -1
        self.frames = 0
        #: what the last frame drew (the normals' segments, the force arrow's, the state line and
        #: its colour)
        self.last_segments: list = []
        self.last_arrow: list = []
        self.last_text = ""
        self.last_rgb = (0, 0, 0)

    def ghost_bodies(self) -> list[int]:
        """Body ids of the ghost (contact queries skip them: they are not in any engine's table)."""
        return self._ghosts + ([self._ghost_urdf] if self._ghost_urdf is not None else [])

    def update(self, runner, force: bool = False) -> bool:
        """Draw the runner's session (at most ``fps`` frames per second unless ``force``); returns
        whether it drew. Notices a window the user closed and calls :attr:`on_close`."""
        now = time.monotonic()
        if not force and now < self._next_frame:
            return False
        self._next_frame = now + self.period_s
        if not p.isConnected(physicsClientId=self.cid):
            if self.on_close is not None:
                self.on_close()
            return False
        self.draw(view_state(runner))
        return True

    def draw(self, vs) -> None:
        """Draw one frame of a :class:`~.views.ViewState`: the ghost at the proxy, the contact
        normals (:attr:`last_segments`), the state line (:attr:`last_text`, :attr:`last_rgb`)."""
        cid = self.cid
        label, rgb = state_style(vs.server_state)
        if vs.proxy_pose is not None:
            pos = [float(v) for v in vs.proxy_pose[:3]]
            orn = list(xyzw_from_wxyz(vs.proxy_pose[3:7]))
            ghost_rgb = PROXY_RGB if vs.following else rgb
            recolour = ghost_rgb != self._ghost_rgb
            rgba = [v / 255.0 for v in ghost_rgb] + [_GHOST_ALPHA]
            for g in self._ghosts:
                p.resetBasePositionAndOrientation(g, pos, orn, physicsClientId=cid)
                if recolour:
                    p.changeVisualShape(g, -1, rgbaColor=rgba, physicsClientId=cid)
            if self._ghost_urdf is not None:
                self._place_linkage_ghost(vs, rgba if recolour else None)
            self._ghost_rgb = ghost_rgb
        centre = vs.tool_pose[:3] if vs.tool_pose is not None else None
        segments = normal_segments(vs.contact_position_m, vs.contact_normal, vs.contact_separation_m,
                                   centre_m=centre)
        self._draw_lines(self._lines, segments, 2.0)
        arrow = []
        if vs.proxy_pose is not None:
            arrow = force_segments(self._hand_point(vs), vs.hand_wrench[:3], self.clear_m)
        force_rgb = tuple(v / 255.0 for v in FORCE_RGB)
        self._draw_lines(self._arrow, [(a, b, force_rgb) for a, b in arrow], 3.0)
        target = self.camera["cameraTargetPosition"]
        where = [target[0], target[1], target[2] + 0.45 * self.camera["cameraDistance"]]
        text = f"{label}   contacts {len(segments)}   |F| {float(np.linalg.norm(vs.hand_wrench[:3])):.2f} N"
        kw = {"replaceItemUniqueId": self._text} if self._text >= 0 else {}
        self._text = p.addUserDebugText(text, where, [v / 255.0 for v in rgb], 1.3, physicsClientId=cid, **kw)
        self.last_segments, self.last_arrow, self.last_text, self.last_rgb = segments, arrow, text, rgb
        self.frames += 1

    def _draw_lines(self, ids: list, segments, width: float) -> None:
        """Draw ``(from, to, rgb)`` segments on the debug lines ``ids`` (grown as needed, the
        unused ones collapsed to nothing below the floor)."""
        cid = self.cid
        for k, (a, b, colour) in enumerate(segments):
            if k < len(ids):
                p.addUserDebugLine(a, b, colour, width, replaceItemUniqueId=ids[k], physicsClientId=cid)
            else:
                ids.append(p.addUserDebugLine(a, b, colour, width, physicsClientId=cid))
        for k in range(len(segments), len(ids)):
            p.addUserDebugLine([0, 0, -10], [0, 0, -10], [0, 0, 0], 1.0, replaceItemUniqueId=ids[k],
                               physicsClientId=cid)

    def _hand_point(self, vs):
        """Where the hand holds the proxy (world): the tool frame's origin; a linkage's, its last
        link's frame (the ghost placed at the proxy first)."""
        if self._ghost_urdf is not None:
            last = p.getNumJoints(self._ghost_urdf, physicsClientId=self.cid) - 1
            if last >= 0:
                return p.getLinkState(self._ghost_urdf, last, physicsClientId=self.cid)[4]
        return vs.proxy_pose[:3]

    def _place_linkage_ghost(self, vs, rgba) -> None:
        from .geometry import compose

        cid = self.cid
        g = self._ghost_urdf
        pose = vs.proxy_pose
        com_p, com_q = self._link_com or ((0.0, 0.0, 0.0), IDENTITY_WXYZ)
        pos, q = compose(pose[:3], pose[3:7], com_p, com_q)
        p.resetBasePositionAndOrientation(g, pos, xyzw_from_wxyz(q), physicsClientId=cid)
        for j, qj in enumerate(vs.proxy_joint_position):
            p.resetJointState(g, j, float(qj), physicsClientId=cid)
        if rgba is not None:
            for link in range(-1, p.getNumJoints(g, physicsClientId=cid)):
                p.changeVisualShape(g, link, rgbaColor=rgba, physicsClientId=cid)

    def close(self) -> None:
        if p.isConnected(physicsClientId=self.cid):
            p.removeAllUserDebugItems(physicsClientId=self.cid)
