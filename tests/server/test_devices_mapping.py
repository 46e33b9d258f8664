"""The workspace mapping and the clutch (issue 30, section 3; ``server/devices/mapping.py``): the
two kernels' contract as properties (round trips, the force rule keeping power's sign and ratio,
a scene spring felt at its own stiffness, the clutch holding the scene and releasing without a
jump), the ``[device]`` keys, the ``MappedDevice`` wrapper keeping the driver contract, and the
whole server with a mapped device against a wall."""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from hapticproxy.server import config as cfgmod
from hapticproxy.server.devices import mapping as mp
from hapticproxy.server.devices.base import DEV_NSTATE, DS_BUTTONS, load_device
from hapticproxy.server.devices.mapped import MappedDevice

_f = st.floats(-1.0, 1.0, allow_nan=False, allow_infinity=False)
_vec = st.tuples(_f, _f, _f).map(np.array)
_scale = st.floats(0.05, 50.0)


@st.composite
def _rotation(draw):
    q = np.array([draw(st.floats(-1, 1)) for _ in range(4)])
    assume(np.linalg.norm(q) > 0.1)
    return q / np.linalg.norm(q)


@st.composite
def _row(draw):
    r = np.zeros(DEV_NSTATE)
    r[0:3] = draw(_vec) * 0.1
    q = draw(_rotation())
    r[3:7] = q if q[0] >= 0 else -q
    r[7:13] = np.r_[draw(_vec), draw(_vec)]
    r[13:19] = np.r_[draw(_vec) * 5, draw(_vec) * 0.5]
    r[19] = 1.25
    r[DS_BUTTONS:] = np.nan
    return r


def _m(s, q, off, **kw):
    return mp.new_mapping(scale=s, offset_m=off, rotation=q, **kw)


def _qmul(a, b):
    w1, x1, y1, z1 = a
    w2, x2, y2, z2 = b
    return np.array([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                     w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2])


def _R(m):
    return m[mp.M_R:mp.M_R + 9].reshape(3, 3)


# ------------------------------------------------------------------------------------ the contract
@settings(max_examples=200, deadline=None)
@given(row=_row(), s=_scale, q=_rotation(), off=_vec)
def test_map_state_is_the_contracts_formula_and_unmap_state_undoes_it(row, s, q, off):
    m = _m(s, q, off)
    R = _R(m)
    out = row.copy()
    assert mp.map_state(out, m) == 0
    np.testing.assert_allclose(out[0:3], off + s * R @ row[0:3], atol=1e-12)
    want_q = _qmul(q, row[3:7])
    assert abs(abs(float(out[3:7] @ want_q)) - 1.0) < 1e-12
    np.testing.assert_allclose(out[7:10], s * R @ row[7:10], atol=1e-12)
    np.testing.assert_allclose(out[10:13], R @ row[10:13], atol=1e-12)
    np.testing.assert_allclose(out[13:16], s * R @ row[13:16], atol=1e-11)
    np.testing.assert_allclose(out[16:19], R @ row[16:19], atol=1e-12)
    assert out[19] == row[19] and np.all(np.isnan(out[DS_BUTTONS:]))
    mp.unmap_state(out, m)                                      # the round trip
    np.testing.assert_allclose(out[:19], row[:19], atol=1e-10)


@settings(max_examples=200, deadline=None)
@given(s=_scale, q=_rotation(), f=_vec, t=_vec)
def test_map_command_inverts_the_hand_wrench_mapping(s, q, f, t):
    """The scene's wrench to the device and back through the hand-wrench path of ``map_state``:
    the same wrench (the two directions are inverse)."""
    m = _m(s, q, np.zeros(3))
    cmd = np.r_[f * 10, t]
    out = np.zeros(6)
    assert mp.map_command(cmd, m, out) == 1.0
    row = np.zeros(DEV_NSTATE)
    row[3] = 1.0
    row[13:19] = out
    row[DS_BUTTONS:] = np.nan
    mp.map_state(row, m)
    # F_s -> F_d = R^T F_s / s -> (map_state: s R F_d) = F_s, t likewise
    np.testing.assert_allclose(row[13:19], cmd, atol=1e-10)


@settings(max_examples=300, deadline=None)
@given(s=_scale, q=_rotation(), v=_vec, w=_vec, f=_vec, t=_vec)
def test_the_force_rule_keeps_power_consistent(s, q, v, w, f, t):
    """F_d . v_d = (F_s . v_s) / s^2 and t_d . w_d = t_s . w_s: power changes by a positive constant,
    so the scene's passivity is the hand's (and energy flows keep their direction)."""
    m = _m(s, q, np.zeros(3))
    row = np.zeros(DEV_NSTATE)
    row[3] = 1.0
    row[7:13] = np.r_[v, w]
    row[DS_BUTTONS:] = np.nan
    mp.map_state(row, m)
    vs, ws = row[7:10], row[10:13]
    fs, ts = f * 10, t
    out = np.zeros(6)
    mp.map_command(np.r_[fs, ts], m, out)
    assert float(out[:3] @ v) == pytest.approx(float(fs @ vs) / (s * s), abs=1e-9)
    assert float(out[3:] @ w) == pytest.approx(float(ts @ ws), abs=1e-9)


@settings(max_examples=200, deadline=None)
@given(s=_scale, q=_rotation(), off=_vec, k=st.floats(10.0, 5000.0), d=_vec)
def test_a_scene_spring_is_felt_at_its_own_stiffness(s, q, off, k, d):
    """F_s = -K (p_s - p_s0) at the mapped device positions gives F_d = -K (p_d - p_d0): the stiffness
    the device renders is the scene's whatever the scale (the stable limits apply unchanged)."""
    m = _m(s, q, off)
    rows = []
    for p in (np.zeros(3), d * 0.01):
        r = np.zeros(DEV_NSTATE)
        r[0:3] = p
        r[3] = 1.0
        r[DS_BUTTONS:] = np.nan
        mp.map_state(r, m)
        rows.append(r)
    fs = -k * (rows[1][0:3] - rows[0][0:3])
    out = np.zeros(6)
    mp.map_command(np.r_[fs, 0, 0, 0], m, out)
    np.testing.assert_allclose(out[:3], -k * d * 0.01, atol=1e-9)


def test_a_non_finite_command_stays_non_finite_clutched_or_not():
    m = _m(2.0, (1, 0, 0, 0), np.zeros(3), clutch_button=0, ramp_steps=10)
    out = np.zeros(6)
    mp.map_command(np.array([math.nan, 0, 0, 0, 0, 0]), m, out)
    assert math.isnan(out[0])
    m[mp.M_CLUTCHED] = 1.0
    m[mp.M_GAIN] = 0.0
    mp.map_command(np.array([0, math.inf, 0, 0, 0, 0]), m, out)
    assert not math.isfinite(out[1])
    mp.map_command(np.array([0, 0, 0, 0, 0, math.nan]), m, out)
    assert math.isnan(out[5])


# ------------------------------------------------------------------------------------- the clutch
def _stepper(m, ramp):
    def step(p, q, held, cmd):
        r = np.zeros(DEV_NSTATE)
        r[0:3] = p
        r[3:7] = q
        r[7:10] = 0.3
        r[13:19] = 1.0
        r[DS_BUTTONS] = 1.0 if held else 0.0
        r[DS_BUTTONS + 1:] = np.nan
        clutched = mp.map_state(r, m)
        out = np.zeros(6)
        g = mp.map_command(cmd, m, out)
        return r, out, g, clutched
    return step


@settings(max_examples=100, deadline=None)
@given(s=_scale, q=_rotation(), off=_vec, path=st.lists(_vec, min_size=12, max_size=40),
       turns=st.lists(_rotation(), min_size=12, max_size=40), press=st.integers(1, 4), length=st.integers(1, 6),
       ramp=st.integers(1, 5))
def test_the_clutch_holds_the_scene_frees_the_device_and_releases_without_a_jump(s, q, off, path, turns, press,
                                                                                 length, ramp):
    m = _m(s, q, off, clutch_button=0, ramp_steps=ramp)
    step = _stepper(m, ramp)
    n = min(len(path), len(turns))
    release = press + length
    assume(release + ramp + 1 < n)
    cmd = np.array([3.0, -2.0, 1.0, 0.1, 0.0, -0.1])
    gains, last = [], None
    for i in range(n):
        p = path[i] * 0.05
        qd = turns[i] if turns[i][0] >= 0 else -turns[i]
        held = press <= i < release
        r, out, g, clutched = step(p, qd, held, cmd)
        gains.append(g)
        if i == press:
            frozen = r[0:7].copy()
            np.testing.assert_allclose(r[0:3], last[0:3] + s * _R(m) @ (p - prev_p), atol=1e-9)  # no jump on press
        if held:
            assert clutched == 1
            np.testing.assert_allclose(r[0:7], frozen, atol=0)      # the scene holds its pose
            assert np.all(r[7:13] == 0.0) and np.all(r[13:19] == 0.0)
        if i == release:
            assert clutched == 0
            np.testing.assert_allclose(r[0:3], frozen[0:3], atol=1e-9)          # released where it was held
            assert abs(abs(float(r[3:7] @ frozen[3:7])) - 1.0) < 1e-9
        if i > release:
            np.testing.assert_allclose(r[0:3] - last[0:3], s * _R(m) @ (p - prev_p), atol=1e-9)  # follows again
        last, prev_p = r, p
    dg = np.diff(np.r_[1.0, gains])
    assert np.all(np.abs(dg) <= 1.0 / ramp + 1e-12)                 # the gain never jumps
    assert gains[press] == max(0.0, 1.0 - 1.0 / ramp)               # fades from the press on
    if length >= ramp:
        assert min(gains[press:release]) == 0.0                     # nothing rendered: the device is free
    assert gains[-1] == 1.0 and all(gains[i] > gains[i - 1] for i in range(release + 1, release + ramp)
                                    if gains[i - 1] < 1.0)


def test_the_clutch_counts_presses_and_ignores_other_buttons_and_nan():
    m = _m(1.0, (1, 0, 0, 0), np.zeros(3), clutch_button=2)
    step = _stepper(m, 1)
    for held_bits in (1.0, 2.0, math.nan):
        r = np.zeros(DEV_NSTATE)
        r[3] = 1.0
        r[DS_BUTTONS] = held_bits
        r[DS_BUTTONS + 1:] = np.nan
        assert mp.map_state(r, m) == 0
    r = np.zeros(DEV_NSTATE)
    r[3] = 1.0
    r[DS_BUTTONS] = 4.0 + 1.0
    assert mp.map_state(r, m) == 1 and m[mp.M_CLUTCHES] == 1
    del step


# -------------------------------------------------------------------------------------- config
def test_no_mapping_asked_means_the_driver_as_it_is():
    d = load_device("sim", {"kind": "planar"}, period_s=1e-3)
    assert not isinstance(d, MappedDevice) and hasattr(d, "tick_arrays")
    d = load_device("sim", {"kind": "planar", "workspace_scale": 1.0, "clutch_button": -1}, period_s=1e-3)
    assert not isinstance(d, MappedDevice)


def test_a_mapping_wraps_the_driver_and_limits_come_in_the_scenes_units():
    inner_lim = load_device("sim", {"kind": "spatial"}, period_s=1e-3).limits
    d = load_device("sim", {"kind": "spatial", "workspace_scale": 10.0, "workspace_offset_m": [0.0, 0.0, 0.5]},
                    period_s=1e-3)
    assert isinstance(d, MappedDevice) and not hasattr(d, "tick_arrays")   # the loop drives d.inner's; the tick maps
    lim = d.limits
    assert lim.max_force_n == pytest.approx(10.0 * inner_lim.max_force_n)
    assert lim.max_speed_m_per_s == pytest.approx(10.0 * inner_lim.max_speed_m_per_s)
    assert lim.max_torque_n_m == inner_lim.max_torque_n_m
    assert lim.workspace_min_m == pytest.approx((-1.0, -1.0, -0.5)) and lim.workspace_max_m == pytest.approx((1, 1, 1.5))
    assert d.info == d.inner.info and d.counters() == d.inner.counters()


@pytest.mark.parametrize("table, key, why", [
    ({"kind": "planar", "workspace_rotation": [0.0, 0.5, 0.0]}, "device.workspace_rotation", "about +z only"),
    ({"kind": "planar", "workspace_offset_m": [0.0, 0.0, 0.1]}, "device.workspace_offset_m", "z = 0"),
    ({"kind": "1dof", "workspace_rotation": [0.0, 0.0, 0.3]}, "device.workspace_rotation", "cannot turn"),
    ({"kind": "spatial", "workspace_rotation": [0.9, 0.0, 0.0, 0.0]}, "device.workspace_rotation", "must be unit"),
    ({"kind": "spatial", "workspace_scale": 0.0}, "device.workspace_scale", "> 0"),
    ({"kind": "spatial", "workspace_scael": 2.0}, "device.workspace_scael", "unknown key"),
    ({"kind": "spatial", "clutch_button": 0}, "device.clutch_button", "has no buttons"),
    ({"kind": "spatial", "clutch_button": 3, "hand": {"type": "none", "buttons": [[0, 1]]}}, "device.clutch_button",
     "has 1 button (0..0)"),
])
def test_a_mapping_the_device_cannot_take_is_refused_naming_the_key(table, key, why):
    with pytest.raises(ValueError) as e:
        cfgmod.load({"device": {"driver": "sim", **table}}) if "clutch" not in key else \
            load_device("sim", table, period_s=1e-3)
    assert key in str(e.value) and why in str(e.value), str(e.value)


def test_print_config_shows_the_mapping_when_asked_and_it_loads_back():
    s = cfgmod.load({"device": {"kind": "spatial", "workspace_scale": 13.3, "workspace_rotation": [0.0, 0.0, 0.5]}})
    dev = s["device"]
    assert dev["workspace_scale"] == 13.3 and dev["clutch_button"] == -1 and dev["clutch_ramp_s"] == 0.2
    again = cfgmod.load({**{k: v for k, v in s.data.items() if k != "preset"}, "preset": s["preset"]})
    assert again.data == s.data
    assert "workspace_scale" not in cfgmod.load({})["device"]


# --------------------------------------------------------------------- the wrapper and the contract
@pytest.mark.parametrize("kind", ["1dof", "planar", "spatial"])
def test_a_mapped_device_keeps_the_driver_contract(kind):
    from hapticproxy.testing.device_contract import RULES, SimHarness, check

    table = {"workspace_scale": 3.0, "workspace_offset_m": [0.1, -0.2, 0.0]}
    if kind == "spatial":
        table["workspace_rotation"] = [0.2, -0.1, 0.4]
    elif kind == "planar":
        table["workspace_rotation"] = [0.0, 0.0, 0.4]

    class Mapped(SimHarness):
        def __init__(self, kind=kind, period_s=1e-3, config=None):
            super().__init__(kind, period_s, config)
            self.driver = MappedDevice(self.driver, mp.parse_mapping(table, kind=kind, period_s=period_s)[1])

        def rendered(self):
            return self.driver.inner.last_command

    for rule in RULES:
        check(rule, lambda: Mapped())


# ------------------------------------------------------------------------------ the whole server
def test_the_server_with_a_scaled_workspace_feels_the_wall_where_it_is(rig_factory):
    """A planar device mapped at scale 2 pushes the testbed's peg onto its wall with 0.5 N: the
    wall is where the scene has it, the scene's force is 1 N and the device renders 0.5 N
    (forces / 2), balancing the push."""
    from server_harness import make_settings

    from hapticproxy.server.shm import TEL

    s = make_settings(device={"kind": "planar", "watchdog_s": 0.0, "workspace_scale": 2.0,
                              "hand": {"type": "constant", "wrench": [0.0, -0.5, 0.0], "start": "server"}})
    dev = load_device("sim", s["device"], period_s=1e-3)
    r = rig_factory(settings=s, device=dev)
    rows = r.run(3.0)
    last = rows[-300:]
    assert abs(np.mean(last[:, TEL["cmd_fy"]]) - 1.0) < 0.02                 # the scene's force
    assert abs(dev.inner.last_command[1] - 0.5) < 0.01                       # what the hand feels
    np.testing.assert_allclose(last[:, TEL["dev_y"]], last[:, TEL["proxy_y"]], atol=0.002)  # at the wall


def test_a_clutch_in_the_server_lets_the_device_go_and_catches_it_without_a_kick(rig_factory):
    """The hand holds the handle pressed on the wall; it presses the clutch at 2 s, lifts the
    handle 10 mm (doubled in the scene) while it is held, and lets the clutch go at 2.5 s with the
    handle at rest: the force fades out over the ramp (0.1 s), nothing is rendered while the clutch
    is held, and on release it comes back over the ramp, in steps far below what the safety
    filter's rate limit lets through (1 N per step of the scene, 0.5 N at this hand), with the
    scene's pose going on from where it was held: the wall is felt there again."""
    from server_harness import make_settings

    from hapticproxy.server.shm import LS, TEL

    hand = {"type": "impedance", "start": "server",
            "target": {"type": "waypoints", "points": [[0.0, [0, 0, 0]], [1.0, [0, -0.02, 0]], [2.0, [0, -0.02, 0]],
                                                       [2.2, [0, -0.01, 0]], [4.0, [0, -0.01, 0]]]},
            "buttons": [[0.0, 0], [2.0, 1], [2.5, 0]]}
    s = make_settings(device={"kind": "planar", "watchdog_s": 0.0, "workspace_scale": 2.0, "clutch_button": 0,
                              "clutch_ramp_s": 0.1, "hand": hand})
    dev = load_device("sim", s["device"], period_s=1e-3)
    r = rig_factory(settings=s, device=dev)
    felt = []
    r.run(4.0, on_step=lambda i: felt.append(dev.inner.last_command[1]))
    felt = np.array(felt)
    rows = np.array(r.rows)
    t = rows[:, TEL["t_s"]] - rows[0, TEL["t_s"]]
    before = felt[(t > 1.8) & (t < 2.0)]
    assert np.all(before > 0.2)                                               # pressed on the wall
    assert np.all(felt[(t > 2.11) & (t < 2.5)] == 0.0)                      # clutched: nothing rendered
    step = np.abs(np.diff(felt))[(t[1:] >= 2.5) & (t[1:] < 2.7)]
    assert step.size and step.max() < 0.01                                   # released: no kick
    assert abs(felt[-1]) > 0.02 and np.all(rows[t > 1.0, TEL["loop_state"]] == LS["engaged"])  # never faded
    np.testing.assert_allclose(rows[t > 3.5, TEL["dev_y"]], rows[t > 3.5, TEL["proxy_y"]], atol=1e-4)
    assert dev.clutch_gain == 1.0 and dev.mapping[mp.M_CLUTCHES] == 1
