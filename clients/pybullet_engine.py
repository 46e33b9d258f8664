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

Contacts (``contacts``): how epsilon, separation, keys and clustering work
  * Candidates: ``getOverlappingObjects`` over the tool's bounding sphere grown by the reach, as an
    AABB (Bullet's broadphase boxes are grown by its contact threshold, so no body within reach is
    missed); poses and velocities of loose candidates are read each call, static ones once.
  * Why not ``getClosestPoints`` for the contacts themselves: it returns one point per body pair
    (checked with pybullet 3.2.7: a box lying flat on a box gives a single point in the middle of
    the face) and rounds box corners by the collision margin (0.4 mm error for a 20 mm box),
    while the local model needs every basic contact (a face-face contact is four vertex-face
    contacts). So a numba kernel computes the exact closest features of the tool box against each
    candidate box or sphere: tool vertex -> body, body vertex -> tool, and edge-edge pairs. The
    tests check the smallest separation per body against ``getClosestPoints`` for random poses.
  * Epsilon: a feature pair is active when the real features are within ``epsilon``: ``d <= eps``,
    which is exactly ``s_eps = d - eps <= 0`` for the tool inflated by a sphere of radius epsilon.
    The reported separation is the real tool's ``d`` (= ``s_eps + epsilon``); epsilon enters only
    as that threshold (and to size the broadphase box).
  * Per contact: ``position_m`` = the closest point on the environment feature; ``normal`` from the
    environment towards the tool; ``separation_m = d`` with tool point = ``c_p + d n`` (negative:
    penetrating; inside a body the shallowest face is used); ``v_constr = n . (v + w x (c_p - com))``
    of the environment body (0 for static bodies).
  * Which pairs: every tool vertex with its closest point on the body; every body vertex whose
    closest tool feature is not a vertex (a vertex-vertex pair is reported once, by the tool
    vertex); an edge pair only when both closest points lie inside the edges, the edges are not
    parallel, the normal lies in both edges' normal cones (within ``_CONE_TOL``), and it is a
    contact of the pair as a whole: apart (separating-axis value > 0), only ``d >= 0``; overlapping,
    only ``d`` at the penetration depth (``_PEN_TOL``). Other edge pairs are faces of the
    Minkowski difference far from the contact. A sphere has one contact. Where static boxes touch
    (the walls stand on the floor and meet at the hole's corners), a body vertex or edge point
    lying on another static box is inside the environment, not a corner of it: no contact
    (otherwise it flickers in and out while the peg rests exactly at its height).
  * Keys: ``(0, body id, feature)``, feature packed as ``contacts.feature_id(kind, tool_feature,
    env_feature)``: ``VERTEX_FACE`` (tool vertex 0-7, body face), ``FACE_VERTEX`` (tool face,
    body vertex 0-7; a sphere is vertex 0), ``EDGE_EDGE`` = 5 (tool edge 0-11, body edge 0-11).
    Faces are 0-5 = 2 axis + (sign > 0) in the box's frame: the face whose normal is nearest the
    contact normal (so a rounding error at an edge does not change it). Vertex i has sign bits
    x, y, z = bits 0, 1, 2 (set: +); edges are numbered as ``_EDGES``. Keys name geometric
    features, so they stay the same while the same features touch (a vertex sliding across a
    face keeps its key; one sliding over an edge onto the next face changes key half-way round
    the edge). No matching between steps is needed.
  * Clustering (after Kim et al., as in the paper): above ``max_contacts`` the epsilon-active
    contacts are reduced exactly as ``contacts.cluster_rows`` does (agglomerative: deepest first,
    ties by key; the closest pair by ``|p_i - p_j| + cluster_normal_weight_m (1 - n_i . n_j)``
    merges and the deeper one represents both) but compiled (the numpy helper took ~60 us for 28
    contacts on the development machine; tests check both select the same contacts).
    ``contacts_found`` is the count before clustering (the runner counts clustered steps by it).

The kernels are compiled on first use (numba, ``cache=True``: ~7 s once per machine), which
``warm_up()`` forces.
"""
from __future__ import annotations

import importlib.metadata
import math

import numpy as np
import pybullet as p
from numba import njit

from .contacts import EDGE_EDGE, FACE_VERTEX, NORMAL_WEIGHT_M, VERTEX_FACE
from .engine import ContactBuffer, Engine, SceneInfo, ToolDescription

__all__ = ["PybulletEngine"]

_GRAVITY_M_PER_S2 = 9.81
#: normal-cone tolerance for edge-edge pairs (dot product, ~1.1 deg)
_CONE_TOL = 0.02
#: relative margin keeping edge-edge closest points away from edge ends (ends are vertex contacts)
_EDGE_INTERIOR = 1e-6
#: sin^2 of the smallest angle between edges for an edge-edge pair (parallel edges: vertex contacts)
_PARALLEL_SIN2 = 1e-8
#: an overlapping edge pair counts when it is this close [m] to the boxes' penetration depth
_PEN_TOL = 1e-4
#: a point this close [m] to another static box counts as on it (internal vertices and edges)
_INTERNAL_TOL = 1e-7
_RAW_CAPACITY = 512

_KIND_BOX = 0
_KIND_SPHERE = 1

# Box vertex i has signs (bit 0 -> x, bit 1 -> y, bit 2 -> z), -1 when the bit is clear.
_VSIGN = np.array([[(1.0 if i & (1 << k) else -1.0) for k in range(3)] for i in range(8)])
# Box edge: (vertex at the -1 end, vertex at the +1 end, axis).
_EDGES = np.array([(i, i | (1 << k), k) for k in range(3) for i in range(8) if not i & (1 << k)],
                  dtype=np.int64)

# Columns of the environment table (one row per environment body).
_E_POS, _E_QUAT, _E_HALF, _E_LIN, _E_ANG = 0, 3, 7, 10, 13
_E_COLS = 16


# --------------------------------------------------------------------------------------------------
# numba kernels
# --------------------------------------------------------------------------------------------------

@njit(cache=True, error_model='numpy')
def _quat_to_mat(q, R):
    """pybullet quaternion (x, y, z, w) -> rotation matrix R (body to world)."""
    x, y, z, w = q[0], q[1], q[2], q[3]
    R[0, 0] = 1.0 - 2.0 * (y * y + z * z)
    R[0, 1] = 2.0 * (x * y - z * w)
    R[0, 2] = 2.0 * (x * z + y * w)
    R[1, 0] = 2.0 * (x * y + z * w)
    R[1, 1] = 1.0 - 2.0 * (x * x + z * z)
    R[1, 2] = 2.0 * (y * z - x * w)
    R[2, 0] = 2.0 * (x * z - y * w)
    R[2, 1] = 2.0 * (y * z + x * w)
    R[2, 2] = 1.0 - 2.0 * (x * x + y * y)


@njit(cache=True, error_model='numpy')
def _closest_on_box(c, R, h, x, q_out, n_out):
    """Closest point of the box (centre c, rotation R, half extents h) to world point x.

    Writes the point on the box surface into q_out and the box's outward normal there (towards x)
    into n_out; returns (signed distance, face, number of clamped axes). ``face`` (0-5:
    2 axis + (sign > 0)) is the box face whose normal is closest to n_out, so it does not change
    when the point crosses into an edge region by a rounding error. Inside the box the
    shallowest face is used: the distance is minus the depth."""
    dx0, dx1, dx2 = x[0] - c[0], x[1] - c[1], x[2] - c[2]
    l0 = dx0 * R[0, 0] + dx1 * R[1, 0] + dx2 * R[2, 0]
    l1 = dx0 * R[0, 1] + dx1 * R[1, 1] + dx2 * R[2, 1]
    l2 = dx0 * R[0, 2] + dx1 * R[1, 2] + dx2 * R[2, 2]
    q0 = min(max(l0, -h[0]), h[0])
    q1 = min(max(l1, -h[1]), h[1])
    q2 = min(max(l2, -h[2]), h[2])
    clamped = (q0 != l0) + (q1 != l1) + (q2 != l2)
    if clamped > 0:
        d0, d1, d2 = l0 - q0, l1 - q1, l2 - q2
        dist = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
        for r in range(3):
            q_out[r] = c[r] + R[r, 0] * q0 + R[r, 1] * q1 + R[r, 2] * q2
            n_out[r] = (R[r, 0] * d0 + R[r, 1] * d1 + R[r, 2] * d2) / dist
        face = int(d0 > 0.0)
        big = abs(d0)
        if abs(d1) > big:
            face, big = 2 + int(d1 > 0.0), abs(d1)
        if abs(d2) > big:
            face = 4 + int(d2 > 0.0)
        return dist, face, clamped
    best = 0
    depth = h[0] - abs(l0)
    lb = l0
    if h[1] - abs(l1) < depth:
        best, depth, lb = 1, h[1] - abs(l1), l1
    if h[2] - abs(l2) < depth:
        best, depth, lb = 2, h[2] - abs(l2), l2
    s = 1.0 if lb >= 0.0 else -1.0
    for r in range(3):
        n_out[r] = s * R[r, best]
        q_out[r] = x[r] + n_out[r] * depth
    return -depth, 2 * best + int(lb >= 0.0), 0


@njit(cache=True, error_model='numpy')
def _inside_box(c, R, h, x, tol):
    """x lies inside the box or within tol of its surface."""
    dx0, dx1, dx2 = x[0] - c[0], x[1] - c[1], x[2] - c[2]
    for k in range(3):
        if abs(dx0 * R[0, k] + dx1 * R[1, k] + dx2 * R[2, k]) > h[k] + tol:
            return False
    return True


@njit(cache=True, error_model='numpy')
def _edge_near_box(p0, p1, c, R, h, reach):
    """The segment p0-p1 may come within reach of the box (its midpoint's distance to the box,
    less half its length, is at most reach)."""
    s = 0.0
    half2 = 0.0
    for k in range(3):
        proj = 0.0
        for r in range(3):
            proj += (0.5 * (p0[r] + p1[r]) - c[r]) * R[r, k]
        excess = abs(proj) - h[k]
        if excess > 0.0:
            s += excess * excess
    for r in range(3):
        half2 += (p1[r] - p0[r]) * (p1[r] - p0[r])
    return math.sqrt(s) - 0.5 * math.sqrt(half2) <= reach


@njit(cache=True, error_model='numpy')
def _box_vertices(c, R, h, out):
    for i in range(8):
        for r in range(3):
            out[i, r] = c[r] + (R[r, 0] * _VSIGN[i, 0] * h[0] + R[r, 1] * _VSIGN[i, 1] * h[1]
                                + R[r, 2] * _VSIGN[i, 2] * h[2])


@njit(cache=True, error_model='numpy')
def _feature(kind, tool_feature, env_feature):
    """Same packing as ``contacts.feature_id``."""
    return (np.int64(kind) << 32) | (np.int64(tool_feature) << 16) | np.int64(env_feature)


@njit(cache=True, error_model='numpy')
def _push(raw_i, raw_f, n, row, feature, pos, nrm, d):
    if n >= raw_i.shape[0]:
        return n
    raw_i[n, 0] = row
    raw_i[n, 1] = feature
    for r in range(3):
        raw_f[n, r] = pos[r]
        raw_f[n, 3 + r] = nrm[r]
    raw_f[n, 6] = d
    return n + 1


# Rows of the kernel's work array.
_W_Q, _W_N, _W_NEG, _W_PE, _W_TR, _W_ER, _W_TV, _W_EV = 0, 1, 2, 3, 4, 7, 10, 18
_W_ROWS = 26


@njit(cache=True, error_model='numpy')
def _sat_axis(n0, n1, n2, tR, th, eR, eh, dx, dy, dz):
    """Separation of the two boxes along the unit axis n: the gap between their projections."""
    rt = (th[0] * abs(n0 * tR[0, 0] + n1 * tR[1, 0] + n2 * tR[2, 0])
          + th[1] * abs(n0 * tR[0, 1] + n1 * tR[1, 1] + n2 * tR[2, 1])
          + th[2] * abs(n0 * tR[0, 2] + n1 * tR[1, 2] + n2 * tR[2, 2]))
    re = (eh[0] * abs(n0 * eR[0, 0] + n1 * eR[1, 0] + n2 * eR[2, 0])
          + eh[1] * abs(n0 * eR[0, 1] + n1 * eR[1, 1] + n2 * eR[2, 1])
          + eh[2] * abs(n0 * eR[0, 2] + n1 * eR[1, 2] + n2 * eR[2, 2]))
    return abs(n0 * dx + n1 * dy + n2 * dz) - rt - re


@njit(cache=True, error_model='numpy')
def _sat_separation(tc, tR, th, ec, eR, eh):
    """Separating-axis value of two boxes: the largest gap between their projections over the
    15 candidate axes (> 0: apart, at most their distance; <= 0: minus the penetration depth).
    Every face of their Minkowski difference has a signed distance <= this."""
    dx, dy, dz = tc[0] - ec[0], tc[1] - ec[1], tc[2] - ec[2]
    best = -np.inf
    for k in range(3):
        s = _sat_axis(tR[0, k], tR[1, k], tR[2, k], tR, th, eR, eh, dx, dy, dz)
        if s > best:
            best = s
        s = _sat_axis(eR[0, k], eR[1, k], eR[2, k], tR, th, eR, eh, dx, dy, dz)
        if s > best:
            best = s
    for a in range(3):
        for b in range(3):
            n0 = tR[1, a] * eR[2, b] - tR[2, a] * eR[1, b]
            n1 = tR[2, a] * eR[0, b] - tR[0, a] * eR[2, b]
            n2 = tR[0, a] * eR[1, b] - tR[1, a] * eR[0, b]
            nl = math.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
            if nl < 1e-6:
                continue  # parallel edges: the face axes cover this direction
            s = _sat_axis(n0 / nl, n1 / nl, n2 / nl, tR, th, eR, eh, dx, dy, dz)
            if s > best:
                best = s
    return best


@njit(cache=True, error_model='numpy')
def _tool_vs_box(tc, tR, th, tv, ec, eR, eh, row, reach, raw_i, raw_f, n, work):
    """Basic contacts within ``reach`` between the tool box and one environment box."""
    q = work[_W_Q]
    nn = work[_W_N]
    neg = work[_W_NEG]
    pe = work[_W_PE]
    ev = work[_W_EV:_W_EV + 8]
    sat = _sat_separation(tc, tR, th, ec, eR, eh)
    if sat > reach:
        return n  # the boxes are farther apart than reach
    _box_vertices(ec, eR, eh, ev)
    # tool vertex -> environment box
    for i in range(8):
        d, face, _ = _closest_on_box(ec, eR, eh, tv[i], q, nn)
        if d <= reach:
            n = _push(raw_i, raw_f, n, row, _feature(VERTEX_FACE, i, face), q, nn, d)
    # environment vertex -> tool box (a tool vertex as closest feature is reported above)
    for j in range(8):
        d, face, clamped = _closest_on_box(tc, tR, th, ev[j], q, nn)
        if d <= reach and clamped < 3:
            for r in range(3):
                neg[r] = -nn[r]
            n = _push(raw_i, raw_f, n, row, _feature(FACE_VERTEX, face, j), ev[j], neg, d)
    # edge-edge: every pair that is a face of the Minkowski difference has d <= sat; when the
    # boxes are apart, a pair with d < 0 is a far-away face, not a contact; when they overlap,
    # only the pairs at the penetration depth are contacts
    lowest = 0.0 if sat > 0.0 else sat - _PEN_TOL
    near_e = 0  # bit b: environment edge b may come within reach of the tool
    for b in range(12):
        if _edge_near_box(ev[_EDGES[b, 0]], ev[_EDGES[b, 1]], tc, tR, th, reach):
            near_e |= 1 << b
    if near_e == 0:
        return n
    for a in range(12):
        ta0, ta1, tk = _EDGES[a, 0], _EDGES[a, 1], _EDGES[a, 2]
        if not _edge_near_box(tv[ta0], tv[ta1], ec, eR, eh, reach):
            continue
        u0 = tv[ta1, 0] - tv[ta0, 0]
        u1 = tv[ta1, 1] - tv[ta0, 1]
        u2 = tv[ta1, 2] - tv[ta0, 2]
        aa = u0 * u0 + u1 * u1 + u2 * u2
        for b in range(12):
            if not near_e & (1 << b):
                continue
            eb0, eb1, ek = _EDGES[b, 0], _EDGES[b, 1], _EDGES[b, 2]
            v0 = ev[eb1, 0] - ev[eb0, 0]
            v1 = ev[eb1, 1] - ev[eb0, 1]
            v2 = ev[eb1, 2] - ev[eb0, 2]
            w0 = tv[ta0, 0] - ev[eb0, 0]
            w1 = tv[ta0, 1] - ev[eb0, 1]
            w2 = tv[ta0, 2] - ev[eb0, 2]
            ee = v0 * v0 + v1 * v1 + v2 * v2
            bb = u0 * v0 + u1 * v1 + u2 * v2
            cc = u0 * w0 + u1 * w1 + u2 * w2
            ff = v0 * w0 + v1 * w1 + v2 * w2
            denom = aa * ee - bb * bb
            if denom <= _PARALLEL_SIN2 * aa * ee:
                continue
            s = (bb * ff - cc * ee) / denom
            t = (aa * ff - bb * cc) / denom
            if s <= _EDGE_INTERIOR or s >= 1.0 - _EDGE_INTERIOR:
                continue
            if t <= _EDGE_INTERIOR or t >= 1.0 - _EDGE_INTERIOR:
                continue
            n0 = u1 * v2 - u2 * v1
            n1 = u2 * v0 - u0 * v2
            n2 = u0 * v1 - u1 * v0
            nl = math.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
            n0 /= nl
            n1 /= nl
            n2 /= nl
            # n must lie in the environment edge's normal cone (spanned by its two faces' outward
            # normals) and -n in the tool edge's
            ea = (ek + 1) % 3
            eb = (ek + 2) % 3
            fa = _VSIGN[eb0, ea] * (n0 * eR[0, ea] + n1 * eR[1, ea] + n2 * eR[2, ea])
            fb = _VSIGN[eb0, eb] * (n0 * eR[0, eb] + n1 * eR[1, eb] + n2 * eR[2, eb])
            if fa + fb < 0.0:
                n0, n1, n2 = -n0, -n1, -n2
                fa, fb = -fa, -fb
            if fa < -_CONE_TOL or fb < -_CONE_TOL:
                continue
            ta = (tk + 1) % 3
            tb = (tk + 2) % 3
            ga = -_VSIGN[ta0, ta] * (n0 * tR[0, ta] + n1 * tR[1, ta] + n2 * tR[2, ta])
            gb = -_VSIGN[ta0, tb] * (n0 * tR[0, tb] + n1 * tR[1, tb] + n2 * tR[2, tb])
            if ga < -_CONE_TOL or gb < -_CONE_TOL:
                continue
            pe[0] = ev[eb0, 0] + t * v0
            pe[1] = ev[eb0, 1] + t * v1
            pe[2] = ev[eb0, 2] + t * v2
            d = (n0 * (tv[ta0, 0] + s * u0 - pe[0]) + n1 * (tv[ta0, 1] + s * u1 - pe[1])
                 + n2 * (tv[ta0, 2] + s * u2 - pe[2]))
            if d > reach or d < lowest:
                continue
            nn[0], nn[1], nn[2] = n0, n1, n2
            n = _push(raw_i, raw_f, n, row, _feature(EDGE_EDGE, a, b), pe, nn, d)
    return n


@njit(cache=True, error_model='numpy')
def _tool_vs_sphere(tc, tR, th, sc, radius, row, reach, raw_i, raw_f, n, work):
    """The one contact of a sphere: its point nearest the tool (an environment 'vertex')."""
    q = work[_W_Q]
    nn = work[_W_N]
    dist, face, _ = _closest_on_box(tc, tR, th, sc, q, nn)
    d = dist - radius
    if d <= reach:
        for r in range(3):
            nn[r] = -nn[r]
            q[r] = sc[r] + radius * nn[r]
        n = _push(raw_i, raw_f, n, row, _feature(FACE_VERTEX, face, 0), q, nn, d)
    return n


@njit(cache=True, error_model='numpy')
def _ranks_before(raw_f, raw_i, env_int, a, b):
    """Contact a ranks before contact b: deeper, then by key (as ``contacts.cluster_rows``)."""
    if raw_f[a, 6] != raw_f[b, 6]:
        return raw_f[a, 6] < raw_f[b, 6]
    ka, kb = env_int[raw_i[a, 0], 0], env_int[raw_i[b, 0], 0]
    if ka != kb:
        return ka < kb
    return raw_i[a, 1] < raw_i[b, 1]


@njit(cache=True, error_model='numpy')
def _pair_distance(raw_f, a, b, weight):
    dx = raw_f[a, 0] - raw_f[b, 0]
    dy = raw_f[a, 1] - raw_f[b, 1]
    dz = raw_f[a, 2] - raw_f[b, 2]
    dot = raw_f[a, 3] * raw_f[b, 3] + raw_f[a, 4] * raw_f[b, 4] + raw_f[a, 5] * raw_f[b, 5]
    return math.sqrt(dx * dx + dy * dy + dz * dz) + weight * (1.0 - dot)


@njit(cache=True, error_model='numpy')
def _row_minimum(raw_f, rank, alive, a, n, weight, row_min, row_arg):
    best = np.inf
    arg = -1
    for b in range(a + 1, n):
        if alive[b]:
            dist = _pair_distance(raw_f, rank[a], rank[b], weight)
            if dist < best:
                best = dist
                arg = b
    row_min[a] = best
    row_arg[a] = arg


@njit(cache=True, error_model='numpy')
def _cluster(raw_f, raw_i, env_int, idx, n, k, weight, scratch_d, scratch_i, keep):
    """``contacts.cluster_rows`` for the n contacts ``idx[:n]``: rank them deepest first (ties by
    key); while more than k remain, the closest pair of representatives (position distance +
    weight (1 - n_i . n_j)) merges and the deeper one represents both. Sets keep[] = 1 for the
    representatives. A cached row minimum keeps it O(n^2). scratch_i holds 3 n ints."""
    rank = scratch_i[0:n]
    row_arg = scratch_i[n:2 * n]
    alive = scratch_i[2 * n:3 * n]
    row_min = scratch_d[0:n]
    for a in range(n):  # insertion sort: n is tens
        x = idx[a]
        b = a
        while b > 0 and _ranks_before(raw_f, raw_i, env_int, x, rank[b - 1]):
            rank[b] = rank[b - 1]
            b -= 1
        rank[b] = x
    for a in range(n):
        alive[a] = 1
    for a in range(n):
        _row_minimum(raw_f, rank, alive, a, n, weight, row_min, row_arg)
    for _ in range(n - k):
        best = np.inf
        best_a = -1
        for a in range(n):
            if alive[a] and row_arg[a] >= 0 and row_min[a] < best:
                best = row_min[a]
                best_a = a
        j = row_arg[best_a]
        alive[j] = 0
        for a in range(j):
            if alive[a] and row_arg[a] == j:
                _row_minimum(raw_f, rank, alive, a, n, weight, row_min, row_arg)
    for a in range(n):
        if alive[a]:
            keep[rank[a]] = 1


@njit(cache=True, error_model='numpy')
def _contacts_kernel(tool, env, env_int, rows, m, reach, eps, max_contacts, weight,
                     raw_i, raw_f, scratch_d, scratch_i, keep, work,
                     out_keys, out_pos, out_nrm, out_sep, out_v):
    """All basic contacts of the tool within ``reach`` of the candidate rows (kept in raw_i/raw_f
    for the drive's guard), then those within ``eps`` clustered to max_contacts and written into
    the output arrays. Returns (count written, epsilon-active count, raw count, raw overflow)."""
    tc = tool[0:3]
    th = tool[7:10]
    tR = work[_W_TR:_W_TR + 3]
    eR = work[_W_ER:_W_ER + 3]
    tv = work[_W_TV:_W_TV + 8]
    _quat_to_mat(tool[3:7], tR)
    _box_vertices(tc, tR, th, tv)
    n = 0
    overflow = 0
    for j in range(m):
        row = rows[j]
        before = n
        if env_int[row, 1] == _KIND_BOX:
            _quat_to_mat(env[row, 3:7], eR)
            n = _tool_vs_box(tc, tR, th, tv, env[row, 0:3], eR, env[row, 7:10], row, reach, raw_i,
                             raw_f, n, work)
        else:
            n = _tool_vs_sphere(tc, tR, th, env[row, 0:3], env[row, 7], row, reach, raw_i, raw_f,
                                n, work)
        if n == raw_i.shape[0] and n > before:
            overflow = 1
    # Where static boxes touch (a wall standing on the floor, two walls of the hole meeting), their
    # shared vertices and edges are inside the union, not corners of the environment: an
    # environment vertex or edge point on another static box is no contact (it would flicker
    # as the tool rests exactly at its height).
    kept = 0
    for i in range(n):
        row = raw_i[i, 0]
        kind = raw_i[i, 1] >> 32
        internal = False
        if env_int[row, 2] == 0 and (kind == FACE_VERTEX or kind == EDGE_EDGE):
            for j in range(m):
                other = rows[j]
                if other == row or env_int[other, 2] != 0 or env_int[other, 1] != _KIND_BOX:
                    continue
                _quat_to_mat(env[other, 3:7], eR)
                if _inside_box(env[other, 0:3], eR, env[other, 7:10], raw_f[i], _INTERNAL_TOL):
                    internal = True
                    break
        if not internal:
            if kept != i:
                raw_i[kept, 0] = raw_i[i, 0]
                raw_i[kept, 1] = raw_i[i, 1]
                for r in range(7):
                    raw_f[kept, r] = raw_f[i, r]
            kept += 1
    n = kept
    # constraint velocity of the environment point: n . (v + w x (c_p - com))
    for i in range(n):
        row = raw_i[i, 0]
        rx = raw_f[i, 0] - env[row, 0]
        ry = raw_f[i, 1] - env[row, 1]
        rz = raw_f[i, 2] - env[row, 2]
        wx, wy, wz = env[row, 13], env[row, 14], env[row, 15]
        vx = env[row, 10] + wy * rz - wz * ry
        vy = env[row, 11] + wz * rx - wx * rz
        vz = env[row, 12] + wx * ry - wy * rx
        raw_f[i, 7] = raw_f[i, 3] * vx + raw_f[i, 4] * vy + raw_f[i, 5] * vz
    # the epsilon-active ones, clustered when there are too many
    idx = scratch_i[0:n]
    active = 0
    for i in range(n):
        keep[i] = 0
        if raw_f[i, 6] <= eps:
            idx[active] = i
            active += 1
    if active > max_contacts:
        _cluster(raw_f, raw_i, env_int, idx, active, max_contacts, weight, scratch_d,
                 scratch_i[n:], keep)
    else:
        for j in range(active):
            keep[idx[j]] = 1
    out = 0
    for i in range(n):
        if keep[i] == 0:
            continue
        row = raw_i[i, 0]
        out_keys[out, 0] = 0
        out_keys[out, 1] = env_int[row, 0]
        out_keys[out, 2] = raw_i[i, 1]
        for r in range(3):
            out_pos[out, r] = raw_f[i, r]
            out_nrm[out, r] = raw_f[i, 3 + r]
        out_sep[out] = raw_f[i, 6]
        out_v[out] = raw_f[i, 7]
        out += 1
    return out, active, n, overflow


@njit(cache=True, error_model='numpy')
def _guard_translation(delta, raw_i, raw_f, n, env_int):
    """Speculative contacts for the drive: shrink the set-point's translation ``delta`` (world, in
    place) so that no static contact point moves past its constraint plane,
    ``n . delta >= -max(d, 0)``, by projecting onto the violated half-spaces. Returns False (and
    zeroes delta) if a few passes cannot satisfy them all."""
    for _ in range(4):
        moved = False
        for i in range(n):
            if env_int[raw_i[i, 0], 2] != 0:
                continue  # a dynamic body: the tool pushes it
            lim = -raw_f[i, 6] if raw_f[i, 6] > 0.0 else 0.0
            viol = lim - (raw_f[i, 3] * delta[0] + raw_f[i, 4] * delta[1] + raw_f[i, 5] * delta[2])
            if viol > 1e-12:
                for r in range(3):
                    delta[r] += viol * raw_f[i, 3 + r]
                moved = True
        if not moved:
            return True
    for i in range(n):
        if env_int[raw_i[i, 0], 2] != 0:
            continue
        lim = -raw_f[i, 6] if raw_f[i, 6] > 0.0 else 0.0
        if lim - (raw_f[i, 3] * delta[0] + raw_f[i, 4] * delta[1] + raw_f[i, 5] * delta[2]) > 1e-9:
            delta[0] = 0.0
            delta[1] = 0.0
            delta[2] = 0.0
            return False
    return True


# --------------------------------------------------------------------------------------------------
# quaternion helpers (protocol order w, x, y, z; pybullet order x, y, z, w)
# --------------------------------------------------------------------------------------------------

def _slerp_xyzw(q0, q1, frac):
    """Spherical interpolation from q0 towards q1 (both x, y, z, w), shortest way."""
    dot = q0[0] * q1[0] + q0[1] * q1[1] + q0[2] * q1[2] + q0[3] * q1[3]
    if dot < 0.0:
        q1 = (-q1[0], -q1[1], -q1[2], -q1[3])
        dot = -dot
    dot = min(dot, 1.0)
    theta = math.acos(dot)
    if theta < 1e-9:
        return tuple(q1)
    s = math.sin(theta)
    a = math.sin((1.0 - frac) * theta) / s
    b = math.sin(frac * theta) / s
    q = [a * q0[i] + b * q1[i] for i in range(4)]
    norm = math.sqrt(sum(x * x for x in q))
    return tuple(x / norm for x in q)


def _box_inertia(mass_kg, half_m):
    hx, hy, hz = (2.0 * h for h in half_m)
    return (mass_kg * (hy * hy + hz * hz) / 12.0, mass_kg * (hx * hx + hz * hz) / 12.0,
            mass_kg * (hx * hx + hy * hy) / 12.0, 0.0, 0.0, 0.0)


_PYBULLET_VERSION = importlib.metadata.version("pybullet")


class PybulletEngine(Engine):
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

    name = f"pybullet {_PYBULLET_VERSION}"

    _SCENES = ("peg", "loose")

    def __init__(self, *, gui: bool = False, rate_hz: float = 500.0,
                 max_drive_force_n: float = 50.0, drive_erp: float = 0.8,
                 max_speed_m_per_s: float = 0.5, max_angular_speed_rad_per_s: float = 5.0,
                 solver_iterations: int = 20, cluster_normal_weight_m: float = NORMAL_WEIGHT_M) -> None:
        for field, value in (("rate_hz", rate_hz), ("max_drive_force_n", max_drive_force_n),
                             ("max_speed_m_per_s", max_speed_m_per_s),
                             ("max_angular_speed_rad_per_s", max_angular_speed_rad_per_s),
                             ("cluster_normal_weight_m", cluster_normal_weight_m)):
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0.0):
                raise ValueError(f"{field}: must be finite and > 0, got {value!r}")
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
        self.cluster_normal_weight_m = float(cluster_normal_weight_m)
        self._default_dt = 1.0 / float(rate_hz)
        self._cid = p.connect(p.GUI if self.gui else p.DIRECT)
        if self._cid < 0:
            raise RuntimeError("pybullet: could not connect a physics server")
        self._epsilon = 0.0
        self._scene: SceneInfo | None = None
        #: the last ProxyState wrench (kept, not applied: see the module docstring)
        self.last_wrench = np.zeros(6)
        #: last ``contacts`` call: epsilon-active contacts before clustering, and all contacts
        #: within the guard's reach; how often the raw array overflowed (extra contacts are
        #: dropped); how often the drive's guard could not satisfy every static contact (its
        #: translation was frozen for that step)
        self.contacts_found = 0
        self.raw_contacts = 0
        self.raw_overflows = 0
        self.guard_freezes = 0
        self._raw_i = np.zeros((_RAW_CAPACITY, 2), dtype=np.int64)
        self._raw_f = np.zeros((_RAW_CAPACITY, 8))
        self._scratch_d = np.zeros(_RAW_CAPACITY)
        self._scratch_i = np.zeros(4 * _RAW_CAPACITY, dtype=np.int64)
        self._keep = np.zeros(_RAW_CAPACITY, dtype=np.int64)
        self._work = np.zeros((_W_ROWS, 3))
        self._tool_arr = np.zeros(10)
        self._delta = np.zeros(3)
        self._guard_buf = ContactBuffer(1)
        self._reset_state()

    # ------------------------------------------------------------------ helpers
    def _reset_state(self) -> None:
        self._time = 0.0
        self._tool = -1
        self._constraint = -1
        self._dt = self._default_dt
        self._pose = None  # cached (pos, quat xyzw) of the tool, None after a step
        self._target = None  # (pos, quat xyzw) the drive heads for
        self._setpoint = None  # last set-point given to the constraint
        self._guard_n = -1  # raw contacts usable by the guard (-1: none at the current pose)
        self._env = np.zeros((0, _E_COLS))
        self._env_int = np.zeros((0, 3), dtype=np.int64)
        self._row_of: dict[int, int] = {}
        self._dynamic_rows: list[bool] = []
        self._rows = np.zeros(0, dtype=np.int64)
        self._bounding_radius = 0.0

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

    @property
    def scene_info(self) -> SceneInfo | None:
        """What the last ``load_scene`` returned (None before)."""
        return self._scene

    def _require_scene(self) -> None:
        if self._scene is None:
            raise RuntimeError("load_scene first")

    def _box(self, half, pos, mass, rgba, maximal: bool = True) -> int:
        cid = self._cid
        shape = p.createCollisionShape(p.GEOM_BOX, halfExtents=list(half), physicsClientId=cid)
        visual = -1
        if self.gui:
            visual = p.createVisualShape(p.GEOM_BOX, halfExtents=list(half), rgbaColor=rgba,
                                         physicsClientId=cid)
        return p.createMultiBody(mass, shape, visual, list(pos), useMaximalCoordinates=maximal,
                                 physicsClientId=cid)

    def _sphere(self, radius, pos, mass, rgba) -> int:
        cid = self._cid
        shape = p.createCollisionShape(p.GEOM_SPHERE, radius=radius, physicsClientId=cid)
        visual = -1
        if self.gui:
            visual = p.createVisualShape(p.GEOM_SPHERE, radius=radius, rgbaColor=rgba,
                                         physicsClientId=cid)
        return p.createMultiBody(mass, shape, visual, list(pos), useMaximalCoordinates=True,
                                 physicsClientId=cid)

    # ------------------------------------------------------------------ Engine
    @classmethod
    def scenes(cls) -> tuple[str, ...]:
        return cls._SCENES

    def load_scene(self, name: str) -> SceneInfo:
        if name not in self._SCENES:
            raise ValueError(f"scene: unknown scene {name!r}; choices: {', '.join(self._SCENES)}")
        if self._cid < 0:
            raise RuntimeError("engine closed")
        cid = self._cid
        p.resetSimulation(physicsClientId=cid)
        self._scene = None
        self._reset_state()
        p.setGravity(0.0, 0.0, -_GRAVITY_M_PER_S2, physicsClientId=cid)
        p.setTimeStep(self._dt, physicsClientId=cid)
        p.setPhysicsEngineParameter(numSolverIterations=self.solver_iterations, erp=self.drive_erp,
                                    physicsClientId=cid)
        if self.gui:
            p.configureDebugVisualizer(p.COV_ENABLE_RENDERING, 0, physicsClientId=cid)
        env = []  # (body, kind, half extents or (radius, 0, 0), dynamic)
        floor_half = (0.5, 0.5, 0.025)
        floor = self._box(floor_half, (0.0, 0.0, -floor_half[2]), 0.0, (0.6, 0.6, 0.6, 1.0))
        env.append((floor, _KIND_BOX, floor_half, False))
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
                body = self._box(half, pos, 0.0, (0.8, 0.5, 0.2, 1.0))
                env.append((body, _KIND_BOX, half, False))
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
                body = self._box(box_half, pos, 0.2, (0.2, 0.5, 0.8, 1.0))
                env.append((body, _KIND_BOX, box_half, True))
                bodies[f"box{k}"] = body
            radius = 0.025
            for k, pos in enumerate(((0.08, -0.05, 0.025), (-0.08, -0.06, 0.025))):
                body = self._sphere(radius, pos, 0.1, (0.2, 0.8, 0.3, 1.0))
                env.append((body, _KIND_SPHERE, (radius, 0.0, 0.0), True))
                bodies[f"sphere{k}"] = body
            facts = {
                "floor_top_z_m": 0.0, "floor_size_m": [1.0, 1.0, 0.05],
                "tool_size_m": [2 * h for h in tool_half],
                "loose_box_size_m": [0.05, 0.05, 0.05], "loose_box_mass_kg": 0.2,
                "loose_sphere_radius_m": radius, "loose_sphere_mass_kg": 0.1,
            }
        inertia = _box_inertia(tool_mass, tool_half)
        # the tool is a multibody: pybullet refuses a JOINT_FIXED to the world for a body in
        # maximal coordinates; the others are rigid bodies (a Featherstone base costs ~1.6x the
        # step time for the same free body)
        tool = self._box(tool_half, tool_pos, tool_mass, (0.9, 0.2, 0.2, 1.0), maximal=False)
        p.changeDynamics(tool, -1, localInertiaDiagonal=list(inertia[:3]), physicsClientId=cid)
        self._tool = tool
        self._tool_mass = tool_mass
        self._tool_arr[7:10] = tool_half
        self._bounding_radius = math.sqrt(sum(h * h for h in tool_half))
        self._constraint = p.createConstraint(tool, -1, -1, -1, p.JOINT_FIXED, [0, 0, 0], [0, 0, 0],
                                              list(tool_pos), physicsClientId=cid)
        self._target = (tuple(tool_pos), (0.0, 0.0, 0.0, 1.0))
        self._apply_setpoint(self._target, force=True)
        k = len(env)
        self._env = np.zeros((k, _E_COLS))
        self._env_int = np.zeros((k, 3), dtype=np.int64)  # body id, kind, dynamic
        self._rows = np.zeros(k, dtype=np.int64)
        self._dynamic_rows = []
        for row, (body, kind, half, dynamic) in enumerate(env):
            pos, orn = p.getBasePositionAndOrientation(body, physicsClientId=cid)
            self._env[row, _E_POS:_E_POS + 3] = pos
            self._env[row, _E_QUAT:_E_QUAT + 4] = orn
            self._env[row, _E_HALF:_E_HALF + 3] = half
            self._env_int[row] = (body, kind, int(dynamic))
            self._row_of[body] = row
            self._dynamic_rows.append(dynamic)
        if self.gui:
            p.configureDebugVisualizer(p.COV_ENABLE_RENDERING, 1, physicsClientId=cid)
        facts["body_ids"] = dict(bodies, tool=tool)
        facts["tool_start_m"] = list(tool_pos)
        facts["time_step_s"] = self._dt
        facts["gravity_m_per_s2"] = [0.0, 0.0, -_GRAVITY_M_PER_S2]
        tool_desc = ToolDescription(kind="spatial", mass_kg=tool_mass, com_m=(0.0, 0.0, 0.0),
                                    inertia_kg_m2=inertia)
        self._scene = SceneInfo(name=name, tool=tool_desc, env_rate_hz=1.0 / self._dt, facts=facts)
        return self._scene

    def set_epsilon(self, epsilon_m: float) -> None:
        eps = float(epsilon_m)
        if not (math.isfinite(eps) and eps >= 0.0):
            raise ValueError(f"epsilon_m: must be finite and >= 0, got {epsilon_m!r}")
        self._epsilon = eps

    def step(self, dt_s: float) -> None:
        self._require_scene()
        dt = float(dt_s)
        if not (math.isfinite(dt) and dt > 0.0):
            raise ValueError(f"dt_s: must be finite and > 0, got {dt_s!r}")
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
        self._apply_setpoint(self._lead_setpoint(pos, orn, dt), force=force)
        # the tool is weightless in the engine (module docstring)
        p.applyExternalForce(self._tool, -1, (0.0, 0.0, self._tool_mass * _GRAVITY_M_PER_S2), pos,
                             p.WORLD_FRAME, physicsClientId=cid)
        p.stepSimulation(physicsClientId=cid)
        self._pose = None
        self._guard_n = -1
        self._time += dt

    def drive_tool(self, proxy_pose: np.ndarray, proxy_twist: np.ndarray, wrench: np.ndarray) -> None:
        self._require_scene()
        pose = self._check_pose(proxy_pose, "proxy_pose")
        twist = np.asarray(proxy_twist, dtype=float)
        if twist.shape != (6,) or not np.all(np.isfinite(twist)):
            raise ValueError(f"proxy_twist: must be 6 finite numbers, got shape {twist.shape}")
        w = np.asarray(wrench, dtype=float)
        if w.shape != (6,) or not np.all(np.isfinite(w)):
            raise ValueError(f"wrench: must be 6 finite numbers, got shape {w.shape}")
        self._target = pose
        self.last_wrench[:] = w

    def tool_pose(self, out: np.ndarray) -> np.ndarray:
        self._require_scene()
        pos, orn = self._raw_pose()
        out[0:3] = pos
        out[3] = orn[3]
        out[4:7] = orn[0:3]
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
        tool = self._tool_arr
        tool[0:3] = pos
        tool[3:7] = orn
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
                if row is None:
                    continue  # the tool itself
                if self._dynamic_rows[row]:
                    bpos, born = p.getBasePositionAndOrientation(body, physicsClientId=cid)
                    lin, ang = p.getBaseVelocity(body, physicsClientId=cid)
                    env[row, _E_POS:_E_POS + 3] = bpos
                    env[row, _E_QUAT:_E_QUAT + 4] = born
                    env[row, _E_LIN:_E_LIN + 3] = lin
                    env[row, _E_ANG:_E_ANG + 3] = ang
                rows[m] = row
                m += 1
        n, active, raw, overflow = _contacts_kernel(
            tool, self._env, self._env_int, self._rows, m, reach, eps, max_contacts,
            self.cluster_normal_weight_m, self._raw_i, self._raw_f, self._scratch_d,
            self._scratch_i, self._keep, self._work, buf.keys, buf.position_m, buf.normal,
            buf.separation_m, buf.v_constr_m_per_s)
        self.raw_contacts = raw
        self.raw_overflows += overflow
        self._guard_n = raw
        buf.n = n
        return n, active

    @property
    def time_s(self) -> float:
        return self._time

    def close(self) -> None:
        if self._cid >= 0:
            try:
                p.disconnect(physicsClientId=self._cid)
            finally:
                self._cid = -1
                self._scene = None

    # ------------------------------------------------------------------ extras (not in Engine)
    def warm_up(self) -> None:
        """Compile the numba kernels now (cached on disk after the first process)."""
        buf = ContactBuffer(1)
        tool = np.array([0, 0, 1, 0, 0, 0, 1, 0.01, 0.01, 0.01], dtype=float)
        env = np.zeros((2, _E_COLS))
        env[:, _E_QUAT:_E_QUAT + 4] = (0, 0, 0, 1)
        env[:, _E_HALF:_E_HALF + 3] = (0.5, 0.5, 0.5)
        env_int = np.array([[0, _KIND_BOX, 0], [1, _KIND_SPHERE, 1]], dtype=np.int64)
        _contacts_kernel(tool, env, env_int, np.arange(2, dtype=np.int64), 2, 0.0, 0.0, 1, 0.01,
                         self._raw_i, self._raw_f, self._scratch_d, self._scratch_i, self._keep,
                         self._work, buf.keys, buf.position_m, buf.normal, buf.separation_m,
                         buf.v_constr_m_per_s)
        _guard_translation(np.zeros(3), self._raw_i, self._raw_f, 0, env_int)

    def reset_tool_pose(self, pose: np.ndarray) -> None:
        """Teleport the tool (x y z qw qx qy qz) at rest and make that pose the drive's target.
        For setting up experiments and tests; never call it while the tool is in use."""
        self._require_scene()
        pos, orn = self._check_pose(pose, "pose")
        cid = self._cid
        p.resetBasePositionAndOrientation(self._tool, pos, orn, physicsClientId=cid)
        p.resetBaseVelocity(self._tool, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), physicsClientId=cid)
        self._pose = None
        self._guard_n = -1
        self._target = (pos, orn)
        self._apply_setpoint(self._target, force=True)

    def body_state(self, body: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(COM position, quaternion w x y z, linear velocity, angular velocity) of a body, world."""
        cid = self._cid
        pos, orn = p.getBasePositionAndOrientation(body, physicsClientId=cid)
        lin, ang = p.getBaseVelocity(body, physicsClientId=cid)
        return (np.array(pos), np.array((orn[3], orn[0], orn[1], orn[2])), np.array(lin),
                np.array(ang))

    def tool_kinetic_energy_j(self) -> float:
        """Kinetic energy of the engine's tool [J] (translation + rotation)."""
        self._require_scene()
        _pos, quat, lin, ang = self.body_state(self._tool)
        R = np.array(p.getMatrixFromQuaternion((quat[1], quat[2], quat[3], quat[0]))).reshape(3, 3)
        w_body = R.T @ ang
        inertia = np.asarray(self._scene.tool.inertia_kg_m2[:3])
        return 0.5 * self._tool_mass * float(lin @ lin) + 0.5 * float(inertia @ (w_body * w_body))

    # ------------------------------------------------------------------ internals
    @staticmethod
    def _check_pose(pose, field):
        arr = np.asarray(pose, dtype=float)
        if arr.shape != (7,) or not np.all(np.isfinite(arr)):
            raise ValueError(f"{field}: must be 7 finite numbers (x y z qw qx qy qz), got shape "
                             f"{arr.shape}")
        qn = float(np.linalg.norm(arr[3:7]))
        if not 0.5 < qn < 1.5:
            raise ValueError(f"{field}: quaternion norm {qn:.3g} is not close to 1")
        q = arr[3:7] / qn
        return ((float(arr[0]), float(arr[1]), float(arr[2])),
                (float(q[1]), float(q[2]), float(q[3]), float(q[0])))

    def _raw_pose(self):
        if self._pose is None:
            self._pose = p.getBasePositionAndOrientation(self._tool, physicsClientId=self._cid)
        return self._pose

    def _lead_setpoint(self, pos, orn, dt):
        """The set-point for the next step: the target, at most one step at the speed bounds away
        from the tool's current pose (the constraint closes drive_erp of the gap per step), its
        translation cut at the static contacts' planes when contacts at this pose are known."""
        tpos, torn = self._target
        lead = self.max_speed_m_per_s * dt / self.drive_erp
        delta = self._delta
        delta[0] = tpos[0] - pos[0]
        delta[1] = tpos[1] - pos[1]
        delta[2] = tpos[2] - pos[2]
        dist = math.sqrt(delta[0] * delta[0] + delta[1] * delta[1] + delta[2] * delta[2])
        clipped = dist > lead
        if clipped:
            delta *= lead / dist
        if self._guard_n > 0:  # always known here (step computes it when contacts() did not)
            if not _guard_translation(delta, self._raw_i, self._raw_f, self._guard_n, self._env_int):
                self.guard_freezes += 1
            clipped = True
        spos = (pos[0] + float(delta[0]), pos[1] + float(delta[1]), pos[2] + float(delta[2])) \
            if clipped else tpos
        dot = abs(orn[0] * torn[0] + orn[1] * torn[1] + orn[2] * torn[2] + orn[3] * torn[3])
        angle = 2.0 * math.acos(min(1.0, dot))
        lead_rad = self.max_angular_speed_rad_per_s * dt / self.drive_erp
        sorn = _slerp_xyzw(orn, torn, lead_rad / angle) if angle > lead_rad else torn
        return spos, sorn

    def _apply_setpoint(self, setpoint, force: bool = False) -> None:
        if not force and setpoint == self._setpoint:
            return
        p.changeConstraint(self._constraint, list(setpoint[0]),
                           jointChildFrameOrientation=list(setpoint[1]),
                           maxForce=self.max_drive_force_n, physicsClientId=self._cid)
        self._setpoint = setpoint
