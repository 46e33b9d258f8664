"""The update-rule invariant (property-based): an update never deepens any local penetration
(a new contact starts touching or apart, or continues a contact that left at its feature) and
never moves the proxy."""
import numpy as np
from hypothesis import given, settings, strategies as st
from linkage_helpers import random_normals

from hapticproxy.server.model import ContactParams, LocalModel, ToolSpec
from hapticproxy.server.model.layout import S_Q, S_QD

def _model(kind):
    """A new model per example: one reused across examples carried an earlier example's state
    into the next (CI's fresh clone once found a falsifying example that no fresh model
    reproduces), so an example was not a function of its inputs."""
    tool = {"1dof": ToolSpec.one_dof(1.0), "planar": ToolSpec.planar(0.5, 1e-3),
            "spatial": ToolSpec.spatial(0.5, (1e-3, 2e-3, 3e-3))}[kind]
    return LocalModel(tool, ContactParams(3000.0, 20.0), period_s=1e-3, capacity=16)


def _contact_set(rng, kind, keys, epsilon):
    """Contacts as an engine with epsilon-active geometry reports them: d = s_eps + epsilon."""
    n = len(keys)
    nrm = random_normals(rng, n, kind)
    cp = rng.normal(size=(n, 3)) * 0.02
    if kind == "planar":
        cp[:, 2] = 0.0
    d = rng.uniform(-0.005, 0.0, n) + rng.uniform(0.0, 0.005, n) + rng.uniform(0.0, epsilon if epsilon > 0 else 1e-9, n)
    k = np.zeros((n, 3), dtype=np.int64)
    k[:, 1] = keys
    return k, cp, nrm, d, rng.normal(size=n) * 0.05


@settings(max_examples=300, deadline=None, derandomize=True)
@given(kind=st.sampled_from(["1dof", "planar", "spatial"]),
       epsilon=st.floats(0.0, 0.01),
       seed=st.integers(0, 2**32 - 1),
       first=st.sets(st.integers(0, 20), max_size=12),
       second=st.sets(st.integers(0, 20), max_size=12),
       steps=st.integers(0, 30))
def test_update_never_deepens_penetration_nor_moves_the_proxy(kind, epsilon, seed, first, second, steps):
    rng = np.random.default_rng(seed)
    m = _model(kind)
    m.reset(qd=rng.normal(size=m.dof) * 0.05)
    m.update(*_contact_set(rng, kind, sorted(first), epsilon))
    hand = rng.normal(size=m.hand_dim)
    for _ in range(steps):                 # let the proxy move into / away from the contacts
        m.step(hand)
    before = dict(zip(map(int, m.contacts().keys[:, 1]), m.proxy_separations()))
    st_before = m.arrays()[1].copy()
    c_before = m.counters()
    k, cp, nrm, d, vc = _contact_set(rng, kind, sorted(second), epsilon)
    m.update(k, cp, nrm, d, vc)
    c_after = m.counters()
    np.testing.assert_array_equal(m.arrays()[1][S_Q:S_QD + m.dof], st_before[S_Q:S_QD + m.dof])
    after = dict(zip(map(int, m.contacts().keys[:, 1]), m.proxy_separations()))
    reported = dict(zip(map(int, k[:, 1]), d))
    # a reversed normal keeps the contact as it was (under its old key, if the new report came
    # under another); a new key at the feature of a contact that left continues that contact
    flipped = c_after["flips_refused"] > c_before["flips_refused"]
    rekeyed = c_after["rekeyed"] > c_before["rekeyed"]
    assert len(after) == len(second)
    assert set(after) <= set(second) | (set(before) if flipped else set())
    deepest_before = max([0.0] + [-v for v in before.values()])
    for key, s_new in after.items():
        if key in before:
            assert max(0.0, -s_new) <= max(0.0, -before[key]) + 1e-12
        elif rekeyed and abs(s_new - max(reported[key], 0.0)) >= 1e-12:
            assert max(0.0, -s_new) <= deepest_before + 1e-12
        else:
            assert s_new >= -1e-12
            assert abs(s_new - max(reported[key], 0.0)) < 1e-12
