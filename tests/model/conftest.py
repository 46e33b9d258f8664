import sys
from pathlib import Path

import numpy as np
import pytest

# the linkage helpers (``from linkage_helpers import ...``): with --import-mode=importlib test
# folders are not on sys.path by themselves
sys.path.insert(0, str(Path(__file__).parent))

from hapticproxy.server.model import ContactParams, LocalModel, ToolSpec
from hapticproxy.server.model.layout import K_RANK
from hapticproxy.server.model.reference import reference_step


@pytest.fixture
def make_model():
    def _make(kind="1dof", *, k=4000.0, b=0.0, e=0.0, mus=0.0, muk=0.0, policy="deformation",
              dt=1e-3, capacity=64, mass=1.0, inertia=1e-2, hand=None, gravity=(0.0, 0.0, 0.0),
              integrator="implicit", **kw):
        if kind == "1dof":
            tool = ToolSpec.one_dof(mass, **kw)
        elif kind == "planar":
            tool = ToolSpec.planar(mass, inertia, hand_point_m=hand or (0.0, 0.0))
        else:
            tool = ToolSpec.spatial(mass, inertia if np.ndim(inertia) else (inertia,) * 3,
                                    hand_point_m=hand or (0.0, 0.0, 0.0))
        return LocalModel(tool, ContactParams(k, b, e, mus, muk), period_s=dt, policy=policy,
                          capacity=capacity, gravity_m_per_s2=gravity, integrator=integrator)
    return _make


def wall(key, cp, n, d, vc=0.0):
    """One contact as arrays for LocalModel.update."""
    return (np.array([[0, key, 0]]), np.array([cp], float), np.array([n], float), np.array([d], float),
            np.array([vc], float))


def contacts(rows):
    """rows: list of (key, cp, n, d[, vc]) -> update arrays."""
    keys = np.array([[0, r[0], 0] for r in rows], dtype=np.int64).reshape(-1, 3)
    cp = np.array([r[1] for r in rows], float).reshape(-1, 3)
    n = np.array([r[2] for r in rows], float).reshape(-1, 3)
    d = np.array([r[3] for r in rows], float)
    vc = np.array([r[4] if len(r) > 4 else 0.0 for r in rows], float)
    return keys, cp, n, d, vc


@pytest.fixture
def cs():
    return contacts


def step_against_reference(m, hand, *, rtol, linkage=None):
    """One numba step of ``m`` with ``hand`` against ``reference_step`` from the same arrays: +inf
    ("just arisen") in the same places of the state and contact tables and the finite parts
    within ``rtol`` (atol 1e-9), the integer table and every counter but the rank identical.
    Returns the counters of both, (numba, reference)."""
    par, st, C, CI, cnt = m.arrays()
    rst, rC, rCI, rcnt = reference_step(m.kind, par, st, C, CI, cnt, hand, linkage=linkage)
    m.step(hand)
    for got, want in ((st, rst), (C, rC)):
        assert np.array_equal(np.isinf(got), np.isinf(want))
        g = np.where(np.isinf(got), 0.0, got)
        w = np.where(np.isinf(want), 0.0, want)
        np.testing.assert_allclose(g, w, rtol=rtol, atol=1e-9)
    np.testing.assert_array_equal(CI, rCI)
    np.testing.assert_array_equal(np.delete(cnt, K_RANK), np.delete(rcnt, K_RANK))
    return cnt, rcnt


@pytest.fixture
def against_reference():
    return step_against_reference
