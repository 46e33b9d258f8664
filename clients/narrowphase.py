"""Exact narrow phase of the 3-D engines: every basic contact of a box tool against boxes and
spheres within a reach, clustered down to a granted count. numba kernels over preallocated
arrays; engine-neutral (the pybullet adapters fill its tables, nothing here imports pybullet).

Why not the engine's own closest-point query: pybullet's ``getClosestPoints`` returns one point
per body pair (a box lying flat on a box gives a single point in the middle of the face) and
rounds box corners by the collision margin (0.4 mm error for a 20 mm box), while the local model
needs every basic contact (a face-face contact is four vertex-face contacts).

Tables (world frame, SI units, quaternions ``w x y z`` as in the protocol):
  * tool: ``[centre (3), quaternion (4), half extents (3)]`` of the tool box (its COM frame);
  * environment, one row per body (:data:`E_COLS` columns): centre :data:`E_POS` (3), quaternion
    :data:`E_QUAT` (4), half extents :data:`E_HALF` (3; a sphere: radius then zeros), linear
    :data:`E_LIN` (3) and angular :data:`E_ANG` (3) velocity; and an int64 row ``(body id,
    KIND_BOX | KIND_SPHERE, dynamic)``; the candidate rows to test are given per call.

What counts as a contact
  * Epsilon: a feature pair is active when the real features are within ``epsilon``: ``d <= eps``,
    which is exactly ``s_eps = d - eps <= 0`` for the tool inflated by a sphere of radius epsilon.
    The reported separation is the real tool's ``d`` (= ``s_eps + epsilon``).
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
    (walls standing on a floor, meeting at a hole's corners), a body vertex or edge point lying on
    another static box is inside the environment, not a corner of it: no contact (otherwise it
    flickers in and out while the tool rests exactly at its height).
  * Keys: ``(0, body id, feature)``, feature packed as ``contacts.feature_id(kind, tool_feature,
    env_feature)``: ``VERTEX_FACE`` (tool vertex 0-7, body face), ``FACE_VERTEX`` (tool face,
    body vertex 0-7; a sphere is vertex 0), ``EDGE_EDGE`` (tool edge 0-11, body edge 0-11).
    Faces are 0-5 = 2 axis + (sign > 0) in the box's frame: the face whose normal is nearest the
    contact normal (so a rounding error at an edge does not change it). Vertex i has sign bits
    x, y, z = bits 0, 1, 2 (set: +); edges are numbered as ``_EDGES``. Keys name geometric
    features, so they stay the same while the same features touch; no matching between steps.
  * Clustering (after Kim et al., as in the paper): above ``max_contacts`` the epsilon-active
    contacts are reduced exactly as ``contacts.cluster_rows`` does (agglomerative: deepest first,
    ties by key; the closest pair by ``|p_i - p_j| + weight (1 - n_i . n_j)`` merges and the deeper
    one represents both), compiled (the numpy helper took ~60 us for 28 contacts on the
    development machine; tests check both select the same contacts).
  * The drive's guard (:meth:`BoxNarrowPhase.guard`): the contacts within the reach stay in the
    raw arrays after a query, so an engine can cut a set-point's translation at every static
    contact plane (Bullet reports penetrating box contacts only: no speculative contacts).

Every kernel is called through :class:`BoxNarrowPhase`, which fixes the argument types, so each
has exactly one signature; :func:`warm_up_kernels` compiles them all (``hapticproxy warmup``).
The quaternion-to-matrix kernel is the protocol's :func:`~hapticproxy.protocol.quaternion.quat_to_matrix_into`
(re-exported by :mod:`.geometry`), jitted here as in the server's model kernels. Numba's cache
does not see edits to that file; ``server.warm.KERNEL_SOURCES`` lists it, so a changed source drops
the cached kernels at the next warm-up.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from . import geometry
from .contacts import EDGE_EDGE, FACE_VERTEX, VERTEX_FACE
from .engine import ContactBuffer

__all__ = ["BoxNarrowPhase", "E_POS", "E_QUAT", "E_HALF", "E_LIN", "E_ANG", "E_COLS", "KIND_BOX", "KIND_SPHERE",
           "RAW_CAPACITY", "env_table", "warm_up_kernels"]

_quat_to_mat = njit(inline="always", error_model="numpy")(geometry.quat_to_matrix_into)

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
# the typed entry point
# --------------------------------------------------------------------------------------------------

E_POS, E_QUAT, E_HALF, E_LIN, E_ANG, E_COLS = _E_POS, _E_QUAT, _E_HALF, _E_LIN, _E_ANG, _E_COLS
KIND_BOX, KIND_SPHERE = _KIND_BOX, _KIND_SPHERE
#: contacts within reach one query can hold (more are dropped and counted as an overflow)
RAW_CAPACITY = _RAW_CAPACITY


def env_table(rows: int) -> tuple[np.ndarray, np.ndarray]:
    """A zeroed environment table of ``rows`` bodies: (float rows, int rows); identity rotations."""
    env = np.zeros((rows, E_COLS))
    env[:, E_QUAT] = 1.0
    return env, np.zeros((rows, 3), dtype=np.int64)


class BoxNarrowPhase:
    """The work arrays of one engine's queries and the only caller of the kernels (one signature
    each). ``raw_i`` / ``raw_f`` keep the last query's contacts within reach (for :meth:`guard`)."""

    def __init__(self, raw_capacity: int = RAW_CAPACITY) -> None:
        self.raw_i = np.zeros((raw_capacity, 2), dtype=np.int64)
        self.raw_f = np.zeros((raw_capacity, 8))
        self._scratch_d = np.zeros(raw_capacity)
        self._scratch_i = np.zeros(4 * raw_capacity, dtype=np.int64)
        self._keep = np.zeros(raw_capacity, dtype=np.int64)
        self._work = np.zeros((_W_ROWS, 3))
        #: the tool box of the next query: centre, quaternion w x y z, half extents
        self.tool = np.zeros(10)
        self.tool[3] = 1.0

    def set_tool(self, position, quat_wxyz, half_m) -> None:
        t = self.tool
        t[0:3] = position
        t[3:7] = quat_wxyz
        t[7:10] = half_m

    def query(self, env: np.ndarray, env_int: np.ndarray, rows: np.ndarray, m: int, reach_m: float,
              epsilon_m: float, max_contacts: int, normal_weight_m: float, keys: np.ndarray, position_m: np.ndarray,
              normal: np.ndarray, separation_m: np.ndarray, v_constr_m_per_s: np.ndarray) -> tuple[int, int, int, int]:
        """Contacts of :attr:`tool` against the candidate ``rows[:m]`` of the table: every one within
        ``reach_m`` into the raw arrays, those within ``epsilon_m`` clustered to ``max_contacts`` and
        written into the output arrays (rows 0..). Returns (written, epsilon-active, within reach,
        raw overflow 0/1)."""
        return _contacts_kernel(self.tool, env, env_int, rows, int(m), float(reach_m), float(epsilon_m),
                                int(max_contacts), float(normal_weight_m), self.raw_i, self.raw_f, self._scratch_d,
                                self._scratch_i, self._keep, self._work, keys, position_m, normal, separation_m,
                                v_constr_m_per_s)

    def query_into(self, buf: ContactBuffer, env, env_int, rows, m, reach_m, epsilon_m, max_contacts,
                   normal_weight_m, start: int = 0) -> tuple[int, int, int, int]:
        """:meth:`query` writing into ``buf`` from row ``start`` (``buf.n`` is left to the caller)."""
        if start == 0:
            return self.query(env, env_int, rows, m, reach_m, epsilon_m, max_contacts, normal_weight_m, buf.keys,
                              buf.position_m, buf.normal, buf.separation_m, buf.v_constr_m_per_s)
        return self.query(env, env_int, rows, m, reach_m, epsilon_m, max_contacts, normal_weight_m,
                          buf.keys[start:], buf.position_m[start:], buf.normal[start:], buf.separation_m[start:],
                          buf.v_constr_m_per_s[start:])

    def guard(self, delta_m: np.ndarray, n_raw: int, env_int: np.ndarray) -> bool:
        """Shrink the translation ``delta_m`` (3,) in place so no static contact of the last query
        (its first ``n_raw`` raw contacts) moves past its plane; ``False`` if it had to be zeroed."""
        return _guard_translation(delta_m, self.raw_i, self.raw_f, int(n_raw), env_int)


def warm_up_kernels() -> None:
    """Compile (or load from numba's cache) every kernel of this module with the argument types
    the engines pass (``hapticproxy warmup``; :meth:`Engine.warm_up` of the 3-D engines)."""
    nph = BoxNarrowPhase()
    nph.set_tool((0.0, 0.0, 1.0), geometry.IDENTITY_WXYZ, (0.01, 0.01, 0.01))
    env, env_int = env_table(2)
    env[:, E_HALF:E_HALF + 3] = 0.5
    env_int[:] = ((0, KIND_BOX, 0), (1, KIND_SPHERE, 1))
    rows = np.arange(2, dtype=np.int64)
    buf = ContactBuffer(2)
    nph.query_into(buf, env, env_int, rows, 2, 0.0, 0.0, 1, 0.01)
    nph.query_into(buf, env, env_int, rows, 2, 0.0, 0.0, 1, 0.01, start=1)
    nph.guard(np.zeros(3), 0, env_int)
