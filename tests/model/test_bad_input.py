"""Bad input: a ValueError naming the field, and the model's state exactly as it was."""
import numpy as np
import pytest

from hapticproxy.server.model import ContactParams, LocalModel, ToolSpec


def _loaded(kind="planar"):
    tool = ToolSpec.planar(0.5, 1e-3) if kind == "planar" else ToolSpec.spatial(0.5, (1e-3,) * 3)
    m = LocalModel(tool, ContactParams(4000.0, 30.0, 0.0, 0.5, 0.3), capacity=8)
    m.reset(qd=np.full(m.dof, 0.01))
    m.update(np.array([[0, 1, 0], [0, 2, 0]]), [[0, -0.01, 0], [0.01, 0, 0]], [[0, 1, 0], [-1, 0, 0]], [0.0, 0.001])
    for _ in range(5):
        m.step(np.full(m.hand_dim, 0.1))
    return m


def _state(m):
    return [a.copy() for a in m.arrays()]


GOOD = dict(keys=[[0, 3, 0]], position_m=[[0.0, 0.0, 0.0]], normal=[[0.0, 1.0, 0.0]], separation_m=[0.001],
            v_constr_m_per_s=[0.0])


@pytest.mark.parametrize("field, value, match", [
    ("position_m", [[np.nan, 0.0, 0.0]], "contacts"),
    ("position_m", [[0.0, np.inf, 0.0]], "contacts"),
    ("separation_m", [np.nan], "contacts"),
    ("separation_m", [-np.inf], "contacts"),
    ("v_constr_m_per_s", [np.inf], "contacts"),
    ("normal", [[0.0, 0.0, 0.0]], "normal"),
    ("normal", [[0.0, 1.0 + 2e-6, 0.0]], "normal"),
    ("normal", [[np.nan, 1.0, 0.0]], "contacts"),
    ("normal", [[0.0, 0.6, 0.8]], "normal"),             # out of the plane of a planar tool
    ("keys", [[1, 3, 0]], "keys"),                       # tool link 1 on a rigid tool
    ("keys", [[0.5, 3, 0]], "keys"),                     # not integers
    ("position_m", [[0.0, 0.0]], "position_m"),          # wrong shape
    ("separation_m", [0.001, 0.002], "separation_m"),
])
def test_bad_contact_update_is_refused_and_changes_nothing(field, value, match):
    m = _loaded()
    before = _state(m)
    args = dict(GOOD)
    args[field] = value
    with pytest.raises(ValueError, match=match):
        m.update(**args)
    for a, b in zip(before, m.arrays()):
        np.testing.assert_array_equal(a, b)
    m.update(**GOOD)                                     # the model still works afterwards


def test_duplicate_keys_in_one_update_are_refused():
    m = _loaded()
    before = _state(m)
    with pytest.raises(ValueError, match="keys"):
        m.update([[0, 3, 0], [0, 3, 0]], [[0, 0, 0]] * 2, [[0, 1, 0]] * 2, [0.0, 0.0])
    for a, b in zip(before, m.arrays()):
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("value", [[np.nan, 0, 0], [0, np.inf, 0], [0, 0, -np.inf]])
def test_non_finite_hand_wrench_is_refused_and_changes_nothing(value):
    m = _loaded()
    before = _state(m)
    with pytest.raises(ValueError, match="hand_wrench"):
        m.step(np.array(value, dtype=float))
    for a, b in zip(before, m.arrays()):
        np.testing.assert_array_equal(a, b)


def test_wrong_hand_wrench_shape_is_refused():
    with pytest.raises(ValueError, match="hand_wrench"):
        _loaded().step([1.0, 2.0])


@pytest.mark.parametrize("make, match", [
    (lambda: ToolSpec.planar(-1.0, 1e-3), "mass_kg"),
    (lambda: ToolSpec.planar(0.0, 1e-3), "mass_kg"),
    (lambda: ToolSpec.planar(float("nan"), 1e-3), "mass_kg"),
    (lambda: ToolSpec.planar(1.0, -1e-3), "inertia"),
    (lambda: ToolSpec.spatial(1.0, (1e-3, -1e-3, 1e-3)), "inertia"),
    (lambda: ToolSpec.spatial(1.0, [[1, 2, 0], [0, 1, 0], [0, 0, 1]]), "inertia"),
    (lambda: ToolSpec.one_dof(1.0, axis=(1.0, 1.0, 0.0)), "axis"),
    (lambda: ToolSpec("hexapod", 1.0), "kind"),
])
def test_bad_tool_is_refused(make, match):
    with pytest.raises(ValueError, match=match):
        LocalModel(make(), warm=False)


@pytest.mark.parametrize("kwargs, match", [
    (dict(period_s=0.0), "period_s"),
    (dict(period_s=-1e-3), "period_s"),
    (dict(period_s=float("nan")), "period_s"),
    (dict(policy="magic"), "policy"),
    (dict(epsilon_m=-0.001), "epsilon_m"),
    (dict(policy="lm0", epsilon_m=0.005), "epsilon_m"),
    (dict(capacity=0), "capacity"),
    (dict(gravity_m_per_s2=(0, 0, float("inf"))), "gravity"),
])
def test_bad_model_settings_are_refused(kwargs, match):
    with pytest.raises(ValueError, match=match):
        LocalModel(ToolSpec.one_dof(1.0), warm=False, **kwargs)


@pytest.mark.parametrize("params, match", [
    (ContactParams(stiffness_n_per_m=-1.0), "stiffness"),
    (ContactParams(damping_n_s_per_m=float("nan")), "damping"),
    (ContactParams(restitution=1.5), "restitution"),
    (ContactParams(mu_static=0.2, mu_kinetic=0.5), "mu_kinetic"),
])
def test_bad_contact_params_are_refused(params, match):
    with pytest.raises(ValueError, match=match):
        LocalModel(ToolSpec.one_dof(1.0), params, warm=False)


def test_the_model_never_renders_a_nan_even_when_its_state_overflows():
    m = LocalModel(ToolSpec.one_dof(1.0), ContactParams(1e4, 0.0), period_s=1e-3)
    m.update([[0, 1, 0]], [[0.0, 0, 0]], [[1.0, 0, 0]], [0.0])
    m.arrays()[1][1] = -1e306          # k * s overflows to inf: no finite force represents it
    before = _state(m)
    for _ in range(3):
        f = m.step([0.0])
        assert np.isfinite(f).all() and f[0] == 0.0
    assert m.counters()["nonfinite"] == 3
    np.testing.assert_array_equal(before[1][1:20], m.arrays()[1][1:20])   # q, qd kept
