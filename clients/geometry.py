"""Rigid-body geometry of the environment clients, in one place: quaternions, poses, planar and
1-DOF coordinates, and the planar chain's forward kinematics.

**Convention: the protocol's** (``protocol/SPEC.md``): a pose is ``x y z qw qx qy qz`` (a unit
quaternion, scalar first) of a frame in the world; a quaternion here is always ``(w, x, y, z)``.
pybullet orders its quaternions ``(x, y, z, w)``: convert at the boundary with
:func:`xyzw_from_wxyz` / :func:`wxyz_from_xyzw` (the pybullet adapters do, nowhere else).

Reduced coordinates (what a 1-DOF or planar engine works in) are expanded to and from the
protocol's 7-number pose and 6-number twist here only: :func:`planar_pose` / :func:`planar_state`,
:func:`axis_pose` / :func:`axis_coordinate`, :func:`planar_chain` (a planar linkage's links from
its root and joints).

:func:`quat_to_matrix_into` is the protocol's own (:mod:`hapticproxy.protocol.quaternion`), written
so that numba compiles it too: the narrow phase (:mod:`.narrowphase`) and the server's model
kernels jit that very function rather than keeping copies. No numba here, so the planar engines
do not pay for importing it.
"""
from __future__ import annotations

import math

import numpy as np

from ..protocol.quaternion import quat_to_matrix_into

__all__ = [
    "IDENTITY_WXYZ", "xyzw_from_wxyz", "wxyz_from_xyzw", "quat_to_matrix_into", "quat_to_matrix",
    "quat_mul", "quat_conjugate", "quat_rotate", "quat_from_axis_angle", "quat_normalised", "quat_angle",
    "slerp", "compose", "inverse", "check_pose", "planar_pose", "planar_angle", "planar_state", "wrap_angle",
    "axis_pose", "axis_coordinate", "planar_chain", "box_inertia",
]

IDENTITY_WXYZ = (1.0, 0.0, 0.0, 0.0)


# ------------------------------------------------------------------------ conventions
def xyzw_from_wxyz(q) -> tuple[float, float, float, float]:
    """The protocol's ``(w, x, y, z)`` as pybullet's ``(x, y, z, w)``."""
    return float(q[1]), float(q[2]), float(q[3]), float(q[0])


def wxyz_from_xyzw(q) -> tuple[float, float, float, float]:
    """pybullet's ``(x, y, z, w)`` as the protocol's ``(w, x, y, z)``."""
    return float(q[3]), float(q[0]), float(q[1]), float(q[2])


# ------------------------------------------------------------------------ quaternions (w, x, y, z)
def quat_to_matrix(q) -> np.ndarray:
    """A new 3x3 rotation matrix of ``q = (w, x, y, z)``."""
    return quat_to_matrix_into(q, np.empty((3, 3)))


def quat_mul(a, b) -> tuple[float, float, float, float]:
    """Hamilton product ``a b`` (both ``(w, x, y, z)``): rotate by ``b``, then by ``a``."""
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return (aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw)


def quat_conjugate(q) -> tuple[float, float, float, float]:
    """The inverse rotation of a unit quaternion."""
    return float(q[0]), -float(q[1]), -float(q[2]), -float(q[3])


def quat_rotate(q, v) -> np.ndarray:
    """``v`` (3,) rotated by ``q = (w, x, y, z)``."""
    return quat_to_matrix(q) @ np.asarray(v, dtype=float)


def quat_from_axis_angle(axis, angle_rad: float) -> tuple[float, float, float, float]:
    """The rotation by ``angle_rad`` about ``axis`` (any non-zero length)."""
    a = np.asarray(axis, dtype=float)
    norm = float(np.linalg.norm(a))
    if not norm > 0.0:
        raise ValueError(f"axis: must be a non-zero vector, got {axis!r}")
    s = math.sin(0.5 * angle_rad) / norm
    return math.cos(0.5 * angle_rad), float(a[0] * s), float(a[1] * s), float(a[2] * s)


def quat_normalised(q) -> tuple[float, float, float, float]:
    n = math.sqrt(sum(float(v) * float(v) for v in q))
    return tuple(float(v) / n for v in q)  # type: ignore[return-value]


def quat_angle(q0, q1) -> float:
    """Angle [rad, 0..pi] of the rotation from ``q0`` to ``q1`` (either sign of either)."""
    dot = abs(q0[0] * q1[0] + q0[1] * q1[1] + q0[2] * q1[2] + q0[3] * q1[3])
    return 2.0 * math.acos(min(1.0, float(dot)))


def slerp(q0, q1, frac: float) -> tuple[float, float, float, float]:
    """Spherical interpolation from ``q0`` (frac 0) towards ``q1`` (frac 1), the short way round.
    Works for either order of the four numbers (it never looks at which one is the scalar)."""
    dot = sum(float(a) * float(b) for a, b in zip(q0, q1))
    if dot < 0.0:
        q1 = tuple(-float(v) for v in q1)
        dot = -dot
    dot = min(dot, 1.0)
    theta = math.acos(dot)
    if theta < 1e-9:
        return tuple(float(v) for v in q1)  # type: ignore[return-value]
    s = math.sin(theta)
    a = math.sin((1.0 - frac) * theta) / s
    b = math.sin(frac * theta) / s
    return quat_normalised([a * float(x) + b * float(y) for x, y in zip(q0, q1)])


# ------------------------------------------------------------------------ poses
def compose(pa, qa, pb, qb) -> tuple[tuple[float, float, float], tuple[float, float, float, float]]:
    """``(pa, qa) * (pb, qb)``: the frame ``b`` given in frame ``a``, returned in ``a``'s parent."""
    p = np.asarray(pa, dtype=float) + quat_rotate(qa, pb)
    return (float(p[0]), float(p[1]), float(p[2])), quat_mul(qa, qb)


def inverse(pa, qa) -> tuple[tuple[float, float, float], tuple[float, float, float, float]]:
    """The inverse of the frame ``(pa, qa)``."""
    qi = quat_conjugate(qa)
    p = -quat_rotate(qi, pa)
    return (float(p[0]), float(p[1]), float(p[2])), qi


def check_pose(pose, field: str) -> tuple[tuple[float, float, float], tuple[float, float, float, float]]:
    """``(position, unit quaternion w x y z)`` of a pose ``x y z qw qx qy qz``; ``ValueError``
    naming ``field`` unless it is 7 finite numbers with a quaternion of norm near 1."""
    arr = np.asarray(pose, dtype=float)
    if arr.shape != (7,) or not np.all(np.isfinite(arr)):
        raise ValueError(f"{field}: must be 7 finite numbers (x y z qw qx qy qz), got shape {arr.shape}")
    qn = float(np.linalg.norm(arr[3:7]))
    if not 0.5 < qn < 1.5:
        raise ValueError(f"{field}: quaternion norm {qn:.3g} is not close to 1")
    q = arr[3:7] / qn
    return (float(arr[0]), float(arr[1]), float(arr[2])), (float(q[0]), float(q[1]), float(q[2]), float(q[3]))


# ------------------------------------------------------------------------ planar tools (x, y, angle about +z)
def planar_pose(x: float, y: float, angle_rad: float, out: np.ndarray) -> np.ndarray:
    """Fill ``out`` (7,) with the pose of a planar tool: x y 0, rotation ``angle_rad`` about +z."""
    half = 0.5 * angle_rad
    out[0] = x
    out[1] = y
    out[2] = 0.0
    out[3] = math.cos(half)
    out[4] = 0.0
    out[5] = 0.0
    out[6] = math.sin(half)
    return out


def planar_angle(pose) -> float:
    """Rotation about +z [rad] of a pose (x y z qw qx qy qz) of a planar tool, in (-pi, pi]."""
    return wrap_angle(2.0 * math.atan2(float(pose[6]), float(pose[3])))


def planar_state(pose, twist) -> tuple[float, float, float, float, float, float]:
    """``(x, y, angle, vx, vy, angular rate)`` of a planar tool from its pose and twist."""
    return (float(pose[0]), float(pose[1]), planar_angle(pose), float(twist[0]), float(twist[1]), float(twist[5]))


def wrap_angle(a: float) -> float:
    """``a`` wrapped into (-pi, pi]."""
    a = math.fmod(a + math.pi, 2.0 * math.pi)
    if a <= 0.0:
        a += 2.0 * math.pi
    return a - math.pi


def planar_chain(root, joint_position, joint_velocity, link_length_m: float) -> list[tuple]:
    """Frames ``(x, y, angle, vx, vy, angular rate)`` of a planar chain of revolute links, each
    link's frame at its proximal joint with the next joint at ``(link_length_m, 0)`` of it, from
    the root's ``root = (x, y, angle, vx, vy, rate)`` and the joints' positions and rates."""
    x, y, th, vx, vy, w = (float(v) for v in root)
    out = [(x, y, th, vx, vy, w)]
    for q, qd in zip(joint_position, joint_velocity):
        # the next joint is at (L, 0) of this link: its velocity adds w x r
        rx, ry = link_length_m * math.cos(th), link_length_m * math.sin(th)
        x, y, vx, vy = x + rx, y + ry, vx - w * ry, vy + w * rx
        th += float(q)
        w += float(qd)
        out.append((x, y, th, vx, vy, w))
    return out


# ------------------------------------------------------------------------ 1-DOF tools (a coordinate along an axis)
def axis_pose(s: float, axis, out: np.ndarray) -> np.ndarray:
    """Fill ``out`` (7,) with the pose of a 1-DOF tool at coordinate ``s`` [m] along the unit
    ``axis`` (no rotation)."""
    out[0] = s * float(axis[0])
    out[1] = s * float(axis[1])
    out[2] = s * float(axis[2])
    out[3] = 1.0
    out[4] = out[5] = out[6] = 0.0
    return out


def axis_coordinate(pose, axis) -> float:
    """Coordinate [m] of a 1-DOF tool's pose along its unit ``axis``."""
    return float(pose[0]) * float(axis[0]) + float(pose[1]) * float(axis[1]) + float(pose[2]) * float(axis[2])


# ------------------------------------------------------------------------ mass properties
def box_inertia(mass_kg: float, half_m) -> tuple[float, float, float, float, float, float]:
    """``[Ixx, Iyy, Izz, Ixy, Ixz, Iyz]`` about the COM of a uniform box of half extents ``half_m``."""
    hx, hy, hz = (2.0 * float(h) for h in half_m)
    return (mass_kg * (hy * hy + hz * hz) / 12.0, mass_kg * (hx * hx + hz * hz) / 12.0,
            mass_kg * (hx * hx + hy * hy) / 12.0, 0.0, 0.0, 0.0)


def advance_pose(pose, twist, dt: float, out: np.ndarray) -> np.ndarray:
    """``pose`` (x y z qw qx qy qz) moved along ``twist`` (v, w: world) for ``dt`` seconds (a
    constant twist: the translation, and the rotation about the world axis w): what an engine
    tracks, the proxy advanced by ``ProxyState.lead_s`` (SPEC 8)."""
    out[:3] = np.asarray(pose[:3], dtype=float) + dt * np.asarray(twist[:3], dtype=float)
    w = np.asarray(twist[3:6], dtype=float)
    wn = float(np.linalg.norm(w))
    q = np.asarray(pose[3:7], dtype=float)
    if wn * dt == 0.0:
        out[3:7] = q
        return out
    h = 0.5 * wn * dt
    s = math.sin(h) / wn
    dw, dx, dy, dz = math.cos(h), s * w[0], s * w[1], s * w[2]
    qw, qx, qy, qz = q
    out[3] = dw * qw - dx * qx - dy * qy - dz * qz
    out[4] = dw * qx + dx * qw + dy * qz - dz * qy
    out[5] = dw * qy - dx * qz + dy * qw + dz * qx
    out[6] = dw * qz + dx * qy - dy * qx + dz * qw
    out[3:7] /= np.linalg.norm(out[3:7])
    return out
