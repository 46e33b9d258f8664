"""Shared contact helpers of the environment clients: feature keys, clustering (poses and
quaternions: :mod:`.geometry`).

Feature ids (the third int64 of a contact key) name the *pair of features* in contact, so that a
contact keeps its key across steps while the same two features touch::

    feature = kind << 32 | tool_feature << 16 | env_feature

``kind`` is one of :data:`VERTEX_FACE` (a tool vertex on an environment face),
:data:`FACE_VERTEX` (an environment vertex on a tool face), :data:`VERTEX_VERTEX` (two corners:
the planar counterpart of a 3-D edge-edge contact) and :data:`FACE_FACE` (a fallback for
engines that cannot tell which corner a face-face point came from). ``tool_feature`` and
``env_feature`` are the vertex or face (edge) indices within the tool's and the environment
body's polygon; a face-face contact is reported as its vertex-face / face-vertex ends, as the
protocol requires.

Clustering (the paper, after Kim, Otaduy, Lin and Manocha 2003): when an engine finds more
contacts than the server granted, :func:`reduce_contacts` merges the nearest ones (distance in
position plus a large penalty for differing normals) until the count fits; every cluster is
represented by its *deepest* member, a real basic contact with its own stable key, so the deepest
contact of all is always kept and no synthetic contact is ever invented.
"""
from __future__ import annotations

import numpy as np

from .engine import ContactBuffer

VERTEX_FACE = 1
FACE_VERTEX = 2
VERTEX_VERTEX = 3
FACE_FACE = 4
EDGE_EDGE = 5  # 3-D engines (pybullet): a tool edge against an environment edge


def feature_id(kind: int, tool_feature: int, env_feature: int) -> int:
    """Pack a feature pair into the contact key's third int64 (see the module docstring)."""
    return (kind << 32) | ((tool_feature & 0xFFFF) << 16) | (env_feature & 0xFFFF)


def split_feature(feature: int) -> tuple[int, int, int]:
    """Inverse of :func:`feature_id`: ``(kind, tool_feature, env_feature)``."""
    feature = int(feature)
    return feature >> 32, (feature >> 16) & 0xFFFF, feature & 0xFFFF


# ----------------------------------------------------------------------------- clustering
#: Normal penalty of the clustering distance [m]: two contacts whose normals differ by 90 deg are as
#: far apart as two contacts 10 cm apart with the same normal, so clusters form along one wall
#: before constraints of different directions are merged.
NORMAL_WEIGHT_M = 0.1


def copy_contacts(src: ContactBuffer, dst: ContactBuffer, rows) -> int:
    """Copy ``rows`` (indices into ``src``) into ``dst`` in the given order; set ``dst.n``."""
    n = len(rows)
    if n > dst.capacity:
        raise ValueError(f"rows: {n} contacts do not fit a buffer of capacity {dst.capacity}")
    if isinstance(rows, range) and rows.start == 0 and rows.step == 1:
        dst.keys[:n] = src.keys[:n]
        dst.position_m[:n] = src.position_m[:n]
        dst.normal[:n] = src.normal[:n]
        dst.separation_m[:n] = src.separation_m[:n]
        dst.v_constr_m_per_s[:n] = src.v_constr_m_per_s[:n]
    elif n:
        idx = np.asarray(rows, dtype=np.intp)
        dst.keys[:n] = src.keys[idx]
        dst.position_m[:n] = src.position_m[idx]
        dst.normal[:n] = src.normal[idx]
        dst.separation_m[:n] = src.separation_m[idx]
        dst.v_constr_m_per_s[:n] = src.v_constr_m_per_s[idx]
    dst.n = n
    return n


def cluster_rows(src: ContactBuffer, max_contacts: int, normal_weight_m: float = NORMAL_WEIGHT_M) -> list[int]:
    """Indices (into ``src``, ascending) of the contacts that represent at most ``max_contacts``
    clusters of ``src``'s ``n`` contacts.

    Agglomerative and deterministic: contacts are ranked deepest first (ties by key); the two
    closest representatives, by ``|p_i - p_j| + normal_weight_m * (1 - n_i . n_j)``, merge and the
    deeper one represents the union; repeat until the count fits. Representatives are real
    contacts, so keys stay unique and stable and the deepest contact is always kept.
    """
    if max_contacts < 1:
        raise ValueError(f"max_contacts: must be >= 1, got {max_contacts}")
    n = src.n
    if n <= max_contacts:
        return list(range(n))
    keys = src.keys[:n]
    # Deepest first; keys break ties so equal-depth contacts (a face flat on a face) rank the
    # same way every step.
    order = np.lexsort((keys[:, 2], keys[:, 1], keys[:, 0], src.separation_m[:n]))
    p = src.position_m[:n][order]
    nr = src.normal[:n][order]
    diff = p[:, None, :] - p[None, :, :]
    dist = np.sqrt(np.einsum("ijk,ijk->ij", diff, diff)) + normal_weight_m * (1.0 - nr @ nr.T)
    # Only pairs (i, j) with i < j: i ranks deeper, so it survives a merge with j.
    dist[np.tril_indices(n)] = np.inf
    removed = np.zeros(n, dtype=bool)
    for _ in range(n - max_contacts):
        j = int(np.argmin(dist)) % n
        removed[j] = True  # j joins the cluster of a deeper i and stops representing anything
        dist[j, :] = np.inf
        dist[:, j] = np.inf
    return sorted(int(order[i]) for i in np.flatnonzero(~removed))


def fill_planar(out: ContactBuffer, rows: list) -> int:
    """Write planar contact tuples ``(env_body, feature, cx, cy, nx, ny, d, v_constr[, tool_link])``
    (tool link 0 unless given, z = 0) into ``out`` (as many as fit, in order); set and return
    ``out.n``. One conversion and a few column copies, cheaper than writing element by element."""
    n = min(len(rows), out.capacity)
    if n:
        a = np.array(rows[:n] if n < len(rows) else rows, dtype=np.float64)
        # float64 holds the ids exactly: feature ids stay below 2**35 (< 2**53)
        out.keys[:n, 0] = a[:, 8] if a.shape[1] > 8 else 0
        out.keys[:n, 1] = a[:, 0]
        out.keys[:n, 2] = a[:, 1]
        out.position_m[:n, :2] = a[:, 2:4]
        out.position_m[:n, 2] = 0.0
        out.normal[:n, :2] = a[:, 4:6]
        out.normal[:n, 2] = 0.0
        out.separation_m[:n] = a[:, 6]
        out.v_constr_m_per_s[:n] = a[:, 7]
    out.n = n
    return n


def reduce_contacts(src: ContactBuffer, dst: ContactBuffer, max_contacts: int) -> int:
    """Copy ``src`` into ``dst``, clustered down to ``min(max_contacts, dst.capacity)``
    contacts when there are more; return and set ``dst.n``. Order: as in ``src``."""
    cap = min(max_contacts, dst.capacity)
    if src.n <= cap:
        return copy_contacts(src, dst, range(src.n))
    return copy_contacts(src, dst, cluster_rows(src, cap))
