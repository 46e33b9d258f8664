"""``LocalModel.read_eq6_literally`` (reproductions only): the rendered separation is s - epsilon
and a new contact keeps its penetration (eq. 6, no eq. 4)."""
import numpy as np
import pytest

from hapticproxy.server.model import ContactParams, LocalModel, ToolSpec

KEYS = np.array([[0, 1, 0]])
CP = np.array([[0.0, 0.0, 0.0]])
N = np.array([[0.0, 1.0, 0.0]])


def _model(eps=0.005):
    m = LocalModel(ToolSpec.planar(0.25, 1e-4), ContactParams(4000.0, 30.0), period_s=1e-3, epsilon_m=eps)
    m.reset([0.0, 0.002, 0.0])
    return m


@pytest.mark.parametrize("d", [0.004, 0.0, -0.003])
def test_the_inflated_tool_is_rendered_and_new_contacts_keep_their_penetration(d):
    notes, lit = _model(), _model()
    lit.read_eq6_literally()
    assert lit.policy == "paper-literal" and lit.recovery["speed_m_per_s"] == 0.0
    for m in (notes, lit):
        m.update(KEYS, CP, N, [d])
    assert notes.proxy_separations()[0] == pytest.approx(max(d, 0.0), abs=1e-12)   # eq. 6 / eq. 4
    assert lit.proxy_separations()[0] == pytest.approx(d - 0.005, abs=1e-12)       # (s - eps), eq. 6 always


def test_an_existing_contact_follows_the_same_table_on_s_minus_epsilon():
    lit = _model()
    lit.read_eq6_literally()
    lit.update(KEYS, CP, N, [0.004])                     # rendered at -1 mm
    lit.update(KEYS, CP, N, [0.003])                     # the world 1 mm deeper: eq. 5 keeps -1 mm
    assert lit.proxy_separations()[0] == pytest.approx(-0.001, abs=1e-12)
    lit.update(KEYS, CP, N, [0.0045])                    # the world shallower than the proxy: eq. 6
    assert lit.proxy_separations()[0] == pytest.approx(-0.0005, abs=1e-12)


def test_a_rigid_model_stays_rigid():
    m = LocalModel(ToolSpec.planar(0.25, 1e-4), ContactParams(4000.0, 30.0), period_s=1e-3, policy="rigid",
                   epsilon_m=0.005)
    m.read_eq6_literally()
    assert m.policy == "rigid"
    m.reset([0.0, 0.002, 0.0])
    m.update(KEYS, CP, N, [-0.002])
    assert m.proxy_separations()[0] == pytest.approx(-0.002, abs=1e-12)
