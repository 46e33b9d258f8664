"""Contact events real engines produce (issue 13, section 4): a reported normal that reverses an
existing contact's (edge-edge normals without a fixed sign) and a key that changes at an
unchanged feature (re-numbered feature ids). Neither may step the force nor pull the proxy
towards the surface."""
import numpy as np
import pytest

from hapticproxy.server.model import ContactParams, LocalModel, ToolSpec

K = 4000.0
FLOOR_N = np.array([0.0, 1.0, 0.0])   # floor y = 0, the tool above it


def _resting(policy="deformation", push=0.5):
    """A planar box (20 mm high) pressed onto the floor y = 0 by ``push`` N at its two bottom
    corners, settled; returns (model, keys, cp, normals, d) of the corners as the engine reports them."""
    m = LocalModel(ToolSpec.planar(0.25, 1.4e-4), ContactParams(K, 30.0), period_s=1e-3, policy=policy)
    m.reset([0.0, 0.010, 0.0])
    keys = np.array([[0, 1, 10], [0, 1, 11]])
    cp = np.array([[-0.04, 0.0, 0.0], [0.04, 0.0, 0.0]])
    nrm = np.array([FLOOR_N, FLOOR_N])
    for _ in range(3000):
        y = m.q[1]
        d = np.full(2, y - 0.010)
        if m.time_s % 0.02 < 1e-3:               # a 50 Hz engine at the proxy's pose
            m.update(keys, cp, nrm, d, tool_q=m.q.copy())
        m.step([0.0, -push, 0.0])
    return m, keys, cp, nrm


def _force_y(m):
    return float(m.env_wrench[1])


def _steps(m, n, push=0.5):
    f = []
    for _ in range(n):
        f.append(m.step([0.0, -push, 0.0])[1])
    return np.array(f)


def test_settled_box_carries_the_push():
    m, *_ = _resting()
    assert _force_y(m) == pytest.approx(0.5, abs=1e-3)


@pytest.mark.parametrize("flip", [[0], [0, 1]])
def test_a_reversed_normal_is_refused_not_turned_into_a_pull(flip):
    m, keys, cp, nrm = _resting()
    before = m.contacts()
    f0 = _force_y(m)
    n2 = nrm.copy()
    n2[flip] *= -1.0                              # the same point and depth, the normal reversed
    d = np.full(2, m.q[1] - 0.010)
    m.update(keys, cp, n2, d, tool_q=m.q.copy())
    after = m.contacts()
    assert m.counters()["flips_refused"] == len(flip)
    np.testing.assert_array_equal(after.normal, before.normal)          # kept as it was
    np.testing.assert_allclose(after.local_point_body_m, before.local_point_body_m, atol=1e-15)
    f = _steps(m, 200)
    assert np.all(f > 0.0)                                                # never pulls into the floor
    assert np.max(np.abs(np.diff(np.r_[f0, f]))) < 1e-3                   # no step at the update
    assert f[-1] == pytest.approx(0.5, abs=1e-3)


def test_a_normal_reversed_for_many_updates_keeps_the_floor():
    m, keys, cp, nrm = _resting()
    n2 = nrm.copy()
    n2[0] *= -1.0
    f = []
    for _ in range(25):                             # half a second of a persistently reversed normal
        m.update(keys, cp, n2, np.full(2, m.q[1] - 0.010), tool_q=m.q.copy())
        f.extend(_steps(m, 20))
    assert m.counters()["flips_refused"] == 25
    assert min(f) > 0.45 and max(f) < 0.55
    assert m.q[1] == pytest.approx(0.010 - 0.5 / (2 * K), abs=2e-6)      # still on the floor (two corners)


def test_a_renumbered_key_continues_the_contact():
    m, keys, cp, nrm = _resting()
    s_before = m.proxy_separations().copy()
    f0 = _force_y(m)
    new_keys = keys.copy()
    new_keys[:, 2] += 1000                          # the engine re-numbered both features
    m.update(new_keys, cp, nrm, np.full(2, m.q[1] - 0.010), tool_q=m.q.copy())
    snap = m.contacts()
    np.testing.assert_array_equal(snap.keys, new_keys)
    assert m.counters()["rekeyed"] == 2
    np.testing.assert_allclose(m.proxy_separations(), s_before, atol=1e-12)   # the penetration kept
    assert np.all(snap.age_updates > 0)
    f = _steps(m, 300)
    assert np.max(np.abs(np.diff(np.r_[f0, f]))) < 1e-3                        # no drop, no overshoot
    assert np.max(f) < 0.501


def test_a_renumbered_key_at_a_deformed_contact_keeps_the_deformation():
    # the proxy 4 mm into the floor, the engine's tool on it: the late contact deformed the proxy
    m = LocalModel(ToolSpec.planar(0.25, 1.4e-4), ContactParams(K, 30.0), period_s=1e-3)
    m.reset([0.0, 0.006, 0.0])
    keys = np.array([[0, 1, 10], [0, 1, 11]])
    cp = np.array([[-0.04, 0.0, 0.0], [0.04, 0.0, 0.0]])
    nrm = np.array([FLOOR_N, FLOOR_N])
    m.update(keys, cp, nrm, np.zeros(2), tool_q=[0.0, 0.010, 0.0])
    m.update(keys, cp, nrm, np.zeros(2), tool_q=[0.0, 0.010, 0.0])
    s0 = m.proxy_separations().copy()
    assert np.all(np.abs(s0) < 1e-12)                                          # eq. 4: just touching
    m.update(keys + [0, 0, 7], cp, nrm, np.zeros(2), tool_q=[0.0, 0.010, 0.0])
    np.testing.assert_allclose(m.proxy_separations(), s0, atol=1e-12)
    assert m.counters()["rekeyed"] == 2


def test_a_new_key_elsewhere_is_a_new_contact():
    m, keys, cp, nrm = _resting()
    # the right corner left, a contact 10 mm further along the floor appeared (another feature)
    keys2 = np.array([[0, 1, 10], [0, 1, 99]])
    cp2 = cp.copy()
    cp2[1, 0] += 0.010
    q = m.q.copy()
    q[0] += 0.0                                   # the tool where it is; the feature point moved
    m.update(keys2, cp2, nrm, np.full(2, m.q[1] - 0.010), tool_q=q)
    assert m.counters()["rekeyed"] == 0
    assert m.contacts().age_updates[1] == 0


def test_a_new_key_with_a_reversed_normal_at_a_leaving_contact_keeps_the_old_one():
    m, keys, cp, nrm = _resting()
    keys2 = keys.copy()
    keys2[0, 2] = 500
    n2 = nrm.copy()
    n2[0] *= -1.0
    m.update(keys2, cp, n2, np.full(2, m.q[1] - 0.010), tool_q=m.q.copy())
    snap = m.contacts()
    assert m.counters()["flips_refused"] == 1
    assert [tuple(k) for k in snap.keys] == [tuple(keys[0]), tuple(keys[1])]
    np.testing.assert_array_equal(snap.normal, nrm)
    f = _steps(m, 100)
    assert np.all(f > 0.45)


def test_the_rigid_policy_also_refuses_a_flip():
    m, keys, cp, nrm = _resting("rigid")
    n2 = nrm.copy()
    n2[:] *= -1.0
    m.update(keys, cp, n2, np.full(2, m.q[1] - 0.010), tool_q=m.q.copy())
    f = _steps(m, 100)
    assert m.counters()["flips_refused"] == 2
    assert np.all(f > 0.45)
