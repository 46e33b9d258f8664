"""Shared contact helpers: feature ids, planar poses (geometry), clustering (cap, deepest kept, one
representative per direction, determinism)."""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hapticproxy.clients.contacts import FACE_VERTEX, VERTEX_FACE, cluster_rows, feature_id, fill_planar, reduce_contacts, split_feature
from hapticproxy.clients.engine import ContactBuffer
from hapticproxy.clients.geometry import planar_angle, planar_pose, wrap_angle


def buffer(rows):
    """rows: (body, feature, x, y, nx, ny, d)."""
    b = ContactBuffer(max(1, len(rows)))
    fill_planar(b, [(r[0], r[1], r[2], r[3], r[4], r[5], r[6], 0.0) for r in rows])
    return b


def test_feature_ids_round_trip_and_differ_by_kind():
    f = feature_id(VERTEX_FACE, 3, 2)
    assert split_feature(f) == (VERTEX_FACE, 3, 2)
    assert feature_id(FACE_VERTEX, 3, 2) != f and feature_id(VERTEX_FACE, 2, 3) != f


@pytest.mark.parametrize("angle", [0.0, 0.3, -1.2, math.pi / 2, 3.0, -3.0])
def test_planar_pose_round_trip(angle):
    pose = planar_pose(0.1, -0.2, angle, np.zeros(7))
    assert np.linalg.norm(pose[3:]) == pytest.approx(1.0)
    assert planar_angle(pose) == pytest.approx(angle)
    assert wrap_angle(angle + 4 * math.pi) == pytest.approx(angle)


def test_fill_planar_writes_rows_and_zero_z():
    b = ContactBuffer(2)
    n = fill_planar(b, [(4, feature_id(1, 2, 0), 0.1, 0.2, 0.0, -1.0, -0.001, 0.05)] * 3)
    assert n == 2 == b.n  # as many as fit
    assert list(b.keys[0]) == [0, 4, feature_id(1, 2, 0)]
    assert list(b.position_m[0]) == [0.1, 0.2, 0.0] and list(b.normal[0]) == [0.0, -1.0, 0.0]
    assert b.separation_m[0] == -0.001 and b.v_constr_m_per_s[0] == 0.05


def test_no_clustering_when_the_count_fits():
    src = buffer([(1, i, 0.01 * i, 0.0, 0.0, 1.0, 0.001 * i) for i in range(4)])
    dst = ContactBuffer(8)
    assert reduce_contacts(src, dst, 4) == 4
    assert np.array_equal(dst.keys[:4], src.keys[:4])


def test_clusters_one_representative_per_direction_the_deepest():
    # a floor (normal +y) with 5 contacts, a left wall (+x) with 3, a right wall (-x) with 2
    rows = [(1, i, 0.01 * i, 0.0, 0.0, 1.0, -0.001 * (i % 3)) for i in range(5)]
    rows += [(2, i, -0.1, 0.01 * i, 1.0, 0.0, 0.002 - 0.0005 * i) for i in range(3)]
    rows += [(3, i, 0.1, 0.01 * i, -1.0, 0.0, 0.003 + 0.001 * i) for i in range(2)]
    src = buffer(rows)
    dst = ContactBuffer(3)
    assert reduce_contacts(src, dst, 3) == 3
    kept = {tuple(k) for k in dst.keys[:3]}
    # floor: the deepest is feature 2 (d = -0.002; 2 ranks before 5 by key); left: feature 2; right: feature 0
    assert kept == {(0, 1, 2), (0, 2, 2), (0, 3, 0)}


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.integers(1, 4), st.floats(-0.1, 0.1), st.floats(-0.1, 0.1), st.floats(-math.pi, math.pi),
                          st.floats(-0.01, 0.005)), min_size=1, max_size=40),
       st.integers(1, 12))
def test_clustering_caps_keeps_real_unique_contacts_and_the_deepest(raw, cap):
    rows = [(body, i, x, y, math.cos(a), math.sin(a), d) for i, (body, x, y, a, d) in enumerate(raw)]
    src = buffer(rows)
    dst = ContactBuffer(cap)
    n = reduce_contacts(src, dst, cap)
    assert n == min(cap, len(rows))
    kept = [tuple(k) for k in dst.keys[:n]]
    all_keys = [tuple(k) for k in src.keys[:src.n]]
    assert len(set(kept)) == n and set(kept) <= set(all_keys)
    # deepest, ties by the whole key (tool link, body, feature), as cluster_rows ranks them
    k = src.keys[:src.n]
    deepest = all_keys[int(np.lexsort((k[:, 2], k[:, 1], k[:, 0], src.separation_m[:src.n]))[0])]
    assert deepest in kept
    for i, k in enumerate(kept):  # rows travel whole
        j = all_keys.index(k)
        assert dst.separation_m[i] == src.separation_m[j] and np.array_equal(dst.normal[i], src.normal[j])
    assert cluster_rows(src, cap) == cluster_rows(src, cap)  # deterministic
