"""The numba step agrees with the plain-numpy reference (explicit pseudo-inverse) to 1e-9 (light tools:
1e-7), with either integrator."""
import numpy as np
import pytest
from linkage_helpers import random_normals

from hapticproxy.server.model import ContactParams, LocalModel, ToolSpec
from hapticproxy.server.model.layout import K_COLLISIONS, K_N_COLLIDING, K_RANK


def random_coupling(rng, m):
    """A coupling the implicit step takes in (any of its terms may be zero)."""
    on = rng.random(4) < 0.8
    m.set_coupling(*(on * np.array([rng.uniform(0, 3000), rng.uniform(0, 30), rng.uniform(0, 3), rng.uniform(0, 0.03)])))


def _scene(kind, rng, integrator):
    # the explicit step: tools it integrates stably; the implicit one: light ones too
    mass = rng.uniform(0.1, 3) if integrator == "explicit" else 10 ** rng.uniform(-3, 0.5)
    inertia = (rng.uniform(1e-3, 1e-1, 3) if integrator == "explicit" else 10 ** rng.uniform(-7, -1, 3))
    if kind == "1dof":
        tool = ToolSpec.one_dof(mass)
    elif kind == "planar":
        tool = ToolSpec.planar(mass, inertia[0], hand_point_m=rng.normal(size=2) * 0.05)
    else:
        tool = ToolSpec.spatial(mass, inertia, hand_point_m=rng.normal(size=3) * 0.05)
    mus = rng.uniform(0, 1)
    m = LocalModel(tool, ContactParams(rng.uniform(1e3, 1e4), rng.uniform(0, 50), rng.uniform(0, 1), mus,
                                       rng.uniform(0, mus)),
                   capacity=64, gravity_m_per_s2=rng.normal(size=3), policy=rng.choice(["rigid", "deformation"]),
                   integrator=integrator)
    random_coupling(rng, m)
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


@pytest.mark.parametrize("integrator", ["explicit", "implicit"])
@pytest.mark.parametrize("kind", ["1dof", "planar", "spatial"])
def test_numba_and_numpy_agree_on_random_scenes(kind, integrator, against_reference):
    rng = np.random.default_rng({"1dof": 11, "planar": 12, "spatial": 13}[kind] + 100 * (integrator == "implicit"))
    collisions = 0
    for _ in range(100):
        m = _scene(kind, rng, integrator)
        for _ in range(4):
            # +inf marks "just arisen" in both; the finite parts to 1e-9 (relative above 1); the
            # light tools' D has a condition number up to 3e7 (3 kg, 1e-7 kg m^2): to 1e-7
            cnt, rcnt = against_reference(m, rng.normal(size=m.hand_dim), rtol=1e-9 if integrator == "explicit" else 1e-7)
            assert cnt[K_RANK] == rcnt[K_RANK] or cnt[K_N_COLLIDING] == 0
        collisions += int(cnt[K_COLLISIONS])
    assert collisions >= 30        # the scenes exercise the impulse path, not only penalties
