"""The numba step agrees with the plain-numpy reference (explicit pseudo-inverse) to 1e-9."""
import numpy as np
import pytest
from linkage_helpers import random_normals

from hapticproxy.server.model import ContactParams, LocalModel, ToolSpec
from hapticproxy.server.model.layout import K_COLLISIONS, K_N_COLLIDING, K_RANK


def _scene(kind, rng):
    if kind == "1dof":
        tool = ToolSpec.one_dof(rng.uniform(0.1, 3))
    elif kind == "planar":
        tool = ToolSpec.planar(rng.uniform(0.1, 3), rng.uniform(1e-3, 1e-1), hand_point_m=rng.normal(size=2) * 0.05)
    else:
        tool = ToolSpec.spatial(rng.uniform(0.1, 3), rng.uniform(1e-3, 1e-1, 3), hand_point_m=rng.normal(size=3) * 0.05)
    mus = rng.uniform(0, 1)
    m = LocalModel(tool, ContactParams(rng.uniform(1e3, 1e4), rng.uniform(0, 50), rng.uniform(0, 1), mus,
                                       rng.uniform(0, mus)),
                   capacity=64, gravity_m_per_s2=rng.normal(size=3), policy=rng.choice(["rigid", "deformation"]))
    q = None
    if kind == "spatial":
        quat = rng.normal(size=4)
        q = np.r_[rng.normal(size=3) * 0.01, quat / np.linalg.norm(quat)]
    elif kind == "planar":
        q = np.r_[rng.normal(size=2) * 0.01, rng.uniform(-3, 3)]
    m.reset(q=q, qd=rng.normal(size=m.dof) * 0.1)
    n = int(rng.integers(0, 40))
    nrm = random_normals(rng, n, kind)
    keys = np.c_[np.zeros(n, int), np.arange(n), np.zeros(n, int)]
    m.update(keys, rng.normal(size=(n, 3)) * 0.02, nrm, rng.uniform(-0.002, 0.002, n), rng.normal(size=n) * 0.01)
    return m


@pytest.mark.parametrize("kind", ["1dof", "planar", "spatial"])
def test_numba_and_numpy_agree_on_random_scenes(kind, against_reference):
    rng = np.random.default_rng({"1dof": 11, "planar": 12, "spatial": 13}[kind])
    collisions = 0
    for _ in range(100):
        m = _scene(kind, rng)
        for _ in range(4):
            # +inf marks "just arisen" in both; the finite parts to 1e-9 (relative above 1)
            cnt, rcnt = against_reference(m, rng.normal(size=m.hand_dim), rtol=1e-9)
            assert cnt[K_RANK] == rcnt[K_RANK] or cnt[K_N_COLLIDING] == 0
        collisions += int(cnt[K_COLLISIONS])
    assert collisions >= 30        # the scenes exercise the impulse path, not only penalties
