"""The 3-D scene of one instant, once, for every view: the live Foxglove server (``live.py``), the
recordings (``recording.py``: the same messages in the MCAP file) and the rerun viewer
(``cli/view.py``).

A :class:`Frame` is what one instant shows: the device handle's and the proxy's poses (world),
the command at the device and the environment's force at the proxy, the contacts of the last
applied model update (position, normal, separation), the state. :class:`ToolShape` is what the
proxy is drawn as: the tool's own boxes (its frame, about its centre of mass) from the client's
Hello where the view has it (:meth:`ToolShape.from_hello`: the box with the Hello's mass and
inertia; exact for a uniform box whose inertia is given whole, as a spatial engine sends it), else
what the tool kind implies (:meth:`ToolShape.for_kind`).

Standard schemas (Foxglove's, protobuf through the Foxglove SDK), frames ``world`` (z up),
``device`` and ``proxy``:

- ``/tf`` (``foxglove.FrameTransforms``): world -> device, world -> proxy;
- ``/device/pose``, ``/proxy/pose`` (``foxglove.PoseInFrame``, in ``world``);
- ``/scene`` (``foxglove.SceneUpdate``): ``device`` (blue sphere and its axes, the command as a
  green arrow), ``proxy`` (the tool's shape, orange, half transparent; the environment force as
  a purple arrow; the state as a label), ``contacts`` (a red sphere per contact, its normal as an
  arrow, a grey patch of the surface it lies on, 20 mm across).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

FORCE_M_PER_N = 0.02   # arrow length per newton
NORMAL_M = 0.015       # contact normal arrow length
PATCH_M = 0.02         # side of the surface patch drawn under a contact
#: the instants a recording carries the 3-D scene at (the per-step topics keep every step)
SCENE_HZ = 30.0
FRAMES = ("world", "device", "proxy")


@dataclass
class ToolShape:
    """Boxes in the tool frame: ``(centre xyz [m], quaternion x y z w, size xyz [m])``;
    ``source`` says where they came from ("hello" or "kind")."""

    boxes: list = field(default_factory=list)
    source: str = "kind"

    @classmethod
    def for_kind(cls, kind: str) -> "ToolShape":
        """What the kind implies when the Hello is not known: a 1-DOF peg (a bar along its axis,
        drawn along x), the paper's planar peg (80 x 20 mm in x-y, 10 mm thick), a 40 mm cube."""
        size = {"1dof": (0.08, 0.02, 0.02), "planar": (0.08, 0.02, 0.01), "spatial": (0.04, 0.04, 0.04),
                "linkage": (0.06, 0.02, 0.02)}.get(kind, (0.02, 0.02, 0.02))
        return cls([((0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0), size)], "kind")

    @classmethod
    def from_hello(cls, kind: str, mass_kg: float, com_m, inertia_kg_m2) -> "ToolShape":
        """The uniform box with the Hello's mass and inertia (``[Ixx, Iyy, Izz, Ixy, Ixz, Iyz]``
        about the centre of mass), centred on ``com_m`` in the tool frame: side a along x has
        a^2 = 6 (Iyy + Izz - Ixx) / m. A planar tool gives only Izz: a square of that Izz, 10 mm
        thick. Falls back to :meth:`for_kind` when the numbers make no box (zeros, a 1-DOF tool)."""
        m = float(mass_kg)
        ixx, iyy, izz = (float(v) for v in tuple(inertia_kg_m2)[:3])
        com = tuple(float(v) for v in com_m)
        if not (m > 0 and math.isfinite(m)) or kind not in ("planar", "spatial"):
            return cls.for_kind(kind)
        if kind == "planar" or not (ixx > 0 and iyy > 0):
            if not izz > 0:
                return cls.for_kind(kind)
            a = math.sqrt(6.0 * izz / m)
            return cls([(com, (0.0, 0.0, 0.0, 1.0), (a, a, 0.01))], "hello")
        sq = [6.0 * (iyy + izz - ixx) / m, 6.0 * (ixx + izz - iyy) / m, 6.0 * (ixx + iyy - izz) / m]
        if not all(v > 0 and math.isfinite(v) for v in sq):
            return cls.for_kind(kind)
        return cls([(com, (0.0, 0.0, 0.0, 1.0), tuple(math.sqrt(v) for v in sq))], "hello")


@dataclass
class Frame:
    """One instant of the scene. Poses ``x y z qw qx qy qz`` (world); wrenches ``fx fy fz tx ty
    tz``; contacts as arrays ``position`` [n, 3], ``normal`` [n, 3], ``separation`` [n]."""

    t_s: float
    device_pose: list
    proxy_pose: list
    command: list
    environment_wrench: list
    position: np.ndarray
    normal: np.ndarray
    separation: np.ndarray
    state: str = ""
    gain: float = 0.0
    #: the ledger at the hand's port: energy the device gave the hand since start [J] (nan: unknown)
    energy_hand_j: float = math.nan

    @property
    def label(self) -> str:
        n = len(self.separation)
        pen = max(0.0, -float(np.min(self.separation))) if n else 0.0
        e = f"  hand {self.energy_hand_j * 1e3:+.1f} mJ" if math.isfinite(self.energy_hand_j) else ""
        return f"{self.state} gain {self.gain:.2f}  {n} contacts" + (f", deepest {pen * 1e3:.2f} mm" if n else "") + e


def frame_of(t_s: float, device_pose, proxy_pose, command, environment_wrench, contacts=None, state: str = "",
             gain: float = 0.0, energy_hand_j=None) -> Frame:
    """A :class:`Frame` from telemetry values (non-finite values drawn as zero) and ``contacts``
    ``(position, normal, separation)`` (None: none)."""
    pos, nrm, sep = contacts if contacts is not None else (np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0))
    pos, nrm, sep = (np.nan_to_num(np.asarray(a, dtype=float)) for a in (pos, nrm, sep))
    g = float(gain) if gain is not None and math.isfinite(float(gain)) else 0.0
    e = float(energy_hand_j) if energy_hand_j is not None else math.nan
    return Frame(float(t_s), _fin(device_pose, 7), _fin(proxy_pose, 7), _fin(command, 6), _fin(environment_wrench, 6),
                 pos.reshape(-1, 3), nrm.reshape(-1, 3), sep.reshape(-1), state, g, e)


def _fin(a, n: int) -> list:
    out = [0.0 if v is None or not math.isfinite(float(v)) else float(v) for v in list(a)[:n]]
    if n == 7 and not any(out[3:7]):
        out[3] = 1.0  # no orientation known: identity
    return out


def quat_x_to(d) -> tuple[float, float, float, float]:
    """Quaternion (x, y, z, w) turning +x onto the unit vector ``d``."""
    x, y, z = d
    w = 1.0 + x
    if w < 1e-9:
        return (0.0, 0.0, 1.0, 0.0)  # d = -x: half a turn about z
    qx, qy, qz, qw = 0.0, -z, y, w
    n = math.sqrt(qx * qx + qy * qy + qz * qz + qw * qw)
    return (qx / n, qy / n, qz / n, qw / n)


def quat_z_to(d) -> tuple[float, float, float, float]:
    """Quaternion (x, y, z, w) turning +z onto the unit vector ``d`` (a patch's normal)."""
    x, y, z = d
    w = 1.0 + z
    if w < 1e-9:
        return (1.0, 0.0, 0.0, 0.0)
    qx, qy, qz, qw = -y, x, 0.0, w
    n = math.sqrt(qx * qx + qy * qy + qz * qz + qw * qw)
    return (qx / n, qy / n, qz / n, qw / n)


def xyzw(pose7) -> tuple[float, float, float, float]:
    """Our ``w x y z`` orientation as Foxglove's and rerun's ``x y z w``."""
    return (pose7[4], pose7[5], pose7[6], pose7[3])


def rotate(q_xyzw, v) -> np.ndarray:
    x, y, z, w = q_xyzw
    u = np.array([x, y, z])
    v = np.asarray(v, dtype=float)
    return v + 2.0 * np.cross(u, np.cross(u, v) + w * v)


def mul(a, b) -> tuple[float, float, float, float]:
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return (aw * bx + ax * bw + ay * bz - az * by, aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw, aw * bw - ax * bx - ay * by - az * bz)


def tool_boxes_world(frame: Frame, shape: ToolShape) -> list:
    """The tool's boxes placed at the proxy: ``(centre, quaternion xyzw, size)`` in world."""
    q = xyzw(frame.proxy_pose)
    p = np.asarray(frame.proxy_pose[:3])
    return [(p + rotate(q, c), mul(q, bq), size) for c, bq, size in shape.boxes]


# ---------------------------------------------------------------------------- Foxglove
def _fx():
    from foxglove import messages as fm

    return fm


def _pose(fm, p, q=(0.0, 0.0, 0.0, 1.0)):
    return fm.Pose(position=fm.Vector3(x=float(p[0]), y=float(p[1]), z=float(p[2])),
                   orientation=fm.Quaternion(x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])))


def _stamp(fm, log_ns: int):
    return fm.Timestamp(sec=int(log_ns // 1_000_000_000), nsec=int(log_ns % 1_000_000_000))


def _arrow(fm, origin, vec, per_unit, color, diameter=0.003) -> list:
    n = math.sqrt(sum(float(v) * float(v) for v in vec))
    if not n > 1e-9:
        return []
    d = [float(v) / n for v in vec]
    length = n * per_unit
    return [fm.ArrowPrimitive(pose=_pose(fm, origin, quat_x_to(d)), shaft_length=0.7 * length,
                              shaft_diameter=diameter, head_length=0.3 * length, head_diameter=2 * diameter,
                              color=color)]


def foxglove_transforms(frame: Frame, log_ns: int):
    """``foxglove.FrameTransforms``: world -> device, world -> proxy."""
    fm = _fx()
    ts = _stamp(fm, log_ns)
    return fm.FrameTransforms(transforms=[
        fm.FrameTransform(timestamp=ts, parent_frame_id="world", child_frame_id=name,
                          translation=fm.Vector3(x=p[0], y=p[1], z=p[2]),
                          rotation=fm.Quaternion(x=p[4], y=p[5], z=p[6], w=p[3]))
        for name, p in (("device", frame.device_pose), ("proxy", frame.proxy_pose))])


def foxglove_pose(pose7, log_ns: int):
    """``foxglove.PoseInFrame`` of a pose in ``world``."""
    fm = _fx()
    return fm.PoseInFrame(timestamp=_stamp(fm, log_ns), frame_id="world", pose=_pose(fm, pose7[:3], xyzw(pose7)))


def foxglove_scene(frame: Frame, shape: ToolShape, log_ns: int = 0):
    """``foxglove.SceneUpdate`` of one instant (see the module docstring)."""
    fm = _fx()
    ts = _stamp(fm, log_ns)
    blue, orange = fm.Color(r=0.2, g=0.45, b=1.0, a=1.0), fm.Color(r=1.0, g=0.55, b=0.1, a=0.55)
    red, green, purple = (fm.Color(r=0.9, g=0.1, b=0.1, a=1.0), fm.Color(r=0.1, g=0.8, b=0.2, a=1.0),
                          fm.Color(r=0.6, g=0.2, b=0.8, a=1.0))
    grey = fm.Color(r=0.6, g=0.6, b=0.6, a=0.5)
    dev, prx = frame.device_pose, frame.proxy_pose
    axes = []
    for k, col in enumerate(((1.0, 0.2, 0.2), (0.2, 1.0, 0.2), (0.2, 0.4, 1.0))):
        e = [0.0, 0.0, 0.0]
        e[k] = 1.0
        axes += _arrow(fm, dev[:3], rotate(xyzw(dev), e), 0.02, fm.Color(r=col[0], g=col[1], b=col[2], a=1.0), 0.0015)
    cubes = [fm.CubePrimitive(pose=_pose(fm, c, q), size=fm.Vector3(x=s[0], y=s[1], z=s[2]), color=orange)
             for c, q, s in tool_boxes_world(frame, shape)]
    ents = [
        fm.SceneEntity(timestamp=ts, frame_id="world", id="device", spheres=[fm.SpherePrimitive(
            pose=_pose(fm, dev[:3], xyzw(dev)), size=fm.Vector3(x=0.012, y=0.012, z=0.012), color=blue)],
            arrows=_arrow(fm, dev[:3], frame.command[:3], FORCE_M_PER_N, green) + axes),
        fm.SceneEntity(timestamp=ts, frame_id="world", id="proxy", cubes=cubes,
                       arrows=_arrow(fm, prx[:3], frame.environment_wrench[:3], FORCE_M_PER_N, purple),
                       texts=[fm.TextPrimitive(pose=_pose(fm, [prx[0], prx[1], prx[2] + 0.04]), billboard=True,
                                               font_size=14.0, scale_invariant=True,
                                               color=fm.Color(r=1, g=1, b=1, a=1), text=frame.label)]),
    ]
    spheres, arrows, patches = [], [], []
    for p, n in zip(frame.position, frame.normal):
        spheres.append(fm.SpherePrimitive(pose=_pose(fm, p), size=fm.Vector3(x=0.004, y=0.004, z=0.004), color=red))
        arrows += _arrow(fm, p, n, NORMAL_M, red, 0.0015)
        if np.linalg.norm(n) > 0.5:
            patches.append(fm.CubePrimitive(pose=_pose(fm, p, quat_z_to(n / np.linalg.norm(n))),
                                            size=fm.Vector3(x=PATCH_M, y=PATCH_M, z=0.0005), color=grey))
    ents.append(fm.SceneEntity(timestamp=ts, frame_id="world", id="contacts", spheres=spheres, arrows=arrows,
                               cubes=patches))
    return fm.SceneUpdate(entities=ents)
