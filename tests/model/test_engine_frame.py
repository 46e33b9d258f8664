"""Update with the engine's tool pose (ContactUpdate.tool_pose): the generalisation of eq. 1."""
import numpy as np
import pytest

from hapticproxy.server.model.model import ContactParams, LocalModel, ToolSpec

KEYS = np.array([[0, 1, 0], [0, 1, 1]])
NRM = np.array([[0.0, 1.0, 0.0], [0.0, 1.0, 0.0]])


def _model(policy="deformation"):
    m = LocalModel(ToolSpec.planar(0.2, 2e-4), ContactParams(stiffness_n_per_m=4000.0), period_s=1e-3, policy=policy,
                   epsilon_m=0.005)
    return m


def _floor(y_tool, hy=0.01, hx=0.02, x=0.0):
    """Corners of a box whose centre is at (x, y_tool), against the floor y = 0."""
    cp = np.array([[x - hx, 0.0, 0.0], [x + hx, 0.0, 0.0]])
    d = np.full(2, y_tool - hy)
    return cp, d


@pytest.mark.parametrize("policy", ["rigid", "lm", "deformation"])
def test_engine_at_the_proxy_pose_is_the_papers_eq1(policy):
    for q in ([0.0, 0.012, 0.0], [0.003, 0.008, 0.1]):
        a, b = _model(policy), _model(policy)
        a.reset(q)
        b.reset(q)
        cp, d = _floor(q[1])
        a.update(KEYS, cp, NRM, d)
        b.update(KEYS, cp, NRM, d, tool_q=q)
        np.testing.assert_allclose(a.proxy_separations(), b.proxy_separations(), atol=1e-15)
        np.testing.assert_allclose(a.contacts().local_point_body_m, b.contacts().local_point_body_m, atol=1e-15)


def test_engine_tool_held_at_the_wall_gives_the_true_wall_to_a_deeper_proxy():
    # proxy 3 mm into the floor; the engine's tool rests on it (d = 0 at y = hy)
    m = _model("rigid")
    m.reset([0.0, 0.007, 0.0])
    cp, d = _floor(0.01)
    m.update(KEYS, cp, NRM, d, tool_q=[0.0, 0.01, 0.0])
    np.testing.assert_allclose(m.proxy_separations(), [-0.003, -0.003], atol=1e-12)
    # the paper's eq. 1 would put the wall at the proxy: no penetration, no force
    p = _model("rigid")
    p.reset([0.0, 0.007, 0.0])
    p.update(KEYS, cp, NRM, d)
    np.testing.assert_allclose(p.proxy_separations(), [0.0, 0.0], atol=1e-12)


def test_engine_frame_update_never_deepens_a_penetration():
    m = _model("deformation")
    m.reset([0.0, 0.009, 0.0])
    cp, d = _floor(0.0095)
    m.update(KEYS, cp, NRM, d, tool_q=[0.0, 0.0095, 0.0])  # arrives late: new contacts just touch
    assert np.all(m.proxy_separations() >= -1e-12)
    before = m.proxy_separations().copy()
    cp, d = _floor(0.0092)
    m.update(KEYS, cp, NRM, d, tool_q=[0.0, 0.0092, 0.0])
    assert np.all(m.proxy_separations() >= before - 1e-12)


def test_tool_q_is_validated():
    m = _model()
    cp, d = _floor(0.01)
    with pytest.raises(ValueError, match="tool_q"):
        m.update(KEYS, cp, NRM, d, tool_q=[0.0, np.nan, 0.0])
    with pytest.raises(ValueError, match="tool_q"):
        m.update(KEYS, cp, NRM, d, tool_q=[0.0, 0.0])
