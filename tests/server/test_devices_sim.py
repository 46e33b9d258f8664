"""Simulated devices: dynamics against analytic solutions, end-stops, saturation, the safety
contract (non-finite, disable, watchdog with a fake clock), config validation, entry point,
no allocation per step."""
from __future__ import annotations

import math
import tracemalloc

import numpy as np
import pytest

from hapticproxy.server.devices import base
from hapticproxy.server.devices.base import (
    DEV_FAULT_DISABLED, DEV_FAULT_NONFINITE_COMMAND, DEV_FAULT_WATCHDOG, DEV_OK, load_device,
)
from hapticproxy.server.devices.sim import SimDevice, make_sim_device, parse_sim_config, warm_up

DT = 1e-3
BIG = {"workspace_min_m": [-10.0, -10.0, -10.0], "workspace_max_m": [10.0, 10.0, 10.0]}


class FakeClock:
    def __init__(self, ns: int = 1_000_000_000) -> None:
        self.ns = ns

    def __call__(self) -> int:
        return self.ns

    def advance(self, s: float) -> None:
        self.ns += int(round(s * 1e9))


def make(kind="1dof", *, clock=None, dt=DT, **cfg):
    if kind == "planar" and "workspace_min_m" in cfg:
        cfg["workspace_min_m"] = cfg["workspace_min_m"][:2]
        cfg["workspace_max_m"] = cfg["workspace_max_m"][:2]
    clock = clock or FakeClock()
    dev = make_sim_device({"kind": kind, **cfg}, period_s=dt, clock_ns=clock)
    dev.clock = clock
    return dev


def run(dev, wrench, n, *, dt=DT):
    """n steps with the fake clock advancing one period per step; returns the last status."""
    w = np.asarray(wrench, dtype=np.float64)
    status = None
    for _ in range(n):
        dev.clock.advance(dt)
        status = dev.write(w)
    return status


def row(dev):
    s = np.zeros(base.DEV_NSTATE)
    dev.read(s)
    return s


# ------------------------------------------------------------------------------ dynamics
@pytest.mark.parametrize("kind", ["1dof", "planar", "spatial"])
def test_constant_force_free_motion_matches_x_equals_f_t2_over_2m(kind):
    m, f, n = 0.5, 0.2, 1000
    extra = {} if kind == "1dof" else {"rotation_limit_rad": 0.0}
    dev = make(kind, mass_kg=m, damping_n_s_per_m=0.0, **BIG, **extra,
               **({} if kind == "1dof" else {"rot_damping_n_m_s_per_rad": 0.0}))
    dev.enable()
    w = np.zeros(6)
    w[0] = f
    assert run(dev, w, n) == DEV_OK
    s = row(dev)
    t = n * DT
    assert s[base.DS_TIME] == pytest.approx(t, rel=1e-12)
    # semi-implicit Euler is exact up to the O(dt) term: x_n = F dt^2 n (n + 1) / 2m
    assert s[0] == pytest.approx(f * DT * DT * n * (n + 1) / (2 * m), rel=1e-9)
    assert s[0] == pytest.approx(f * t * t / (2 * m), rel=2.0 / n)
    assert s[7] == pytest.approx(f * t / m, rel=1e-9)
    assert np.all(s[1:3] == 0.0) and np.all(s[8:10] == 0.0)


@pytest.mark.parametrize("kind", ["planar", "spatial"])
def test_constant_torque_spins_theta_equals_tau_t2_over_2i(kind):
    izz, tau, n = 2e-3, 1e-3, 1000
    inertia = izz if kind == "planar" else [1e-3, 1.5e-3, izz]
    dev = make(kind, inertia_kg_m2=inertia, rot_damping_n_m_s_per_rad=0.0, rotation_limit_rad=0.0)
    dev.enable()
    run(dev, [0, 0, 0, 0, 0, tau], n)
    s = row(dev)
    t = n * DT
    theta = 2 * math.atan2(s[6], s[3])
    assert theta == pytest.approx(tau * t * t / (2 * izz), rel=2.0 / n)
    assert s[12] == pytest.approx(tau * t / izz, rel=1e-9)
    assert abs(s[4]) < 1e-15 and abs(s[5]) < 1e-15


def test_1dof_moves_only_along_its_axis_with_the_projected_force():
    axis = np.array([0.6, 0.8, 0.0])
    dev = make("1dof", axis=axis.tolist(), origin_m=[0.01, 0.02, 0.03], damping_n_s_per_m=0.0,
               mass_kg=0.4, **BIG)
    dev.enable()
    run(dev, [1.0, 0.0, 5.0, 9.0, 9.0, 9.0], 500)     # fz and torques cannot act on it
    s = row(dev)
    t = 0.5
    travel = 0.6 * 1.0 * DT * DT * 500 * 501 / (2 * 0.4)
    assert s[0:3] == pytest.approx([0.01, 0.02, 0.03] + travel * axis, abs=1e-12)
    assert s[3:7].tolist() == [1.0, 0.0, 0.0, 0.0]
    assert s[7:10] == pytest.approx(0.6 * t / 0.4 * axis, rel=1e-9)
    assert np.all(s[10:13] == 0.0)
    assert dev.last_command == pytest.approx(np.r_[0.6 * axis, 0, 0, 0])


@pytest.mark.parametrize("kind", ["1dof", "planar", "spatial"])
def test_damping_decays_velocity_exponentially(kind):
    m, b, v0 = 0.4, 2.0, 0.1
    vel = {"1dof": [v0], "planar": [v0, 0, 0], "spatial": [v0, 0, 0, 0, 0, 0]}[kind]
    dev = make(kind, mass_kg=m, damping_n_s_per_m=b, initial_velocity=vel, **BIG)
    dev.enable()
    n = 500
    run(dev, np.zeros(6), n)
    s = row(dev)
    # implicit damping: v_n = v0 / (1 + b dt / m)^n, within O(dt) of v0 exp(-b t / m)
    assert s[7] == pytest.approx(v0 / (1 + b * DT / m) ** n, rel=1e-9)
    assert s[7] == pytest.approx(v0 * math.exp(-b * n * DT / m), rel=0.01)
    run(dev, np.zeros(6), 5000)
    assert row(dev)[0] == pytest.approx(v0 * m / b, rel=0.01)   # distance coasted


def test_rotational_damping_decays_spin():
    dev = make("planar", inertia_kg_m2=1e-3, rot_damping_n_m_s_per_rad=2e-3, initial_velocity=[0, 0, 0.5],
               rotation_limit_rad=0.0)
    dev.enable()
    run(dev, np.zeros(6), 300)
    assert row(dev)[12] == pytest.approx(0.5 * math.exp(-2.0 * 0.3), rel=0.01)


def test_spatial_free_tumbling_keeps_a_unit_quaternion_energy_and_momentum():
    inertia = np.diag([6e-4, 9e-4, 4e-4])
    w0 = np.array([2.0, 0.3, 1.0])
    dev = make("spatial", inertia_kg_m2=inertia.tolist(), rot_damping_n_m_s_per_rad=0.0, rotation_limit_rad=0.0,
               initial_velocity=[0, 0, 0, *w0], max_angular_speed_rad_per_s=100.0)
    dev.enable()

    def energy_momentum(s):
        qw, qx, qy, qz = s[3:7]
        R = np.array([[1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - qw * qz), 2 * (qx * qz + qw * qy)],
                      [2 * (qx * qy + qw * qz), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - qw * qx)],
                      [2 * (qx * qz - qw * qy), 2 * (qy * qz + qw * qx), 1 - 2 * (qx * qx + qy * qy)]])
        iw = R @ inertia @ R.T
        w = s[10:13]
        return 0.5 * w @ iw @ w, iw @ w

    e0, l0 = energy_momentum(row(dev))
    run(dev, np.zeros(6), 3000)
    s = row(dev)
    e1, l1 = energy_momentum(s)
    assert np.linalg.norm(s[3:7]) == pytest.approx(1.0, abs=1e-12)
    assert e1 == pytest.approx(e0, rel=0.02)
    assert np.linalg.norm(l1 - l0) < 0.02 * np.linalg.norm(l0)
    assert not np.allclose(s[10:13], w0)      # it does tumble: the axis moves


# ------------------------------------------------------------------------------ end-stops
def test_workspace_endstop_holds_and_releases():
    dev = make("1dof", workspace_min_m=[-0.05, -1, -1], workspace_max_m=[0.05, 1, 1])
    ks = dev.spec.values["endstop_stiffness_n_per_m"]
    dev.enable()
    run(dev, [5.0, 0, 0, 0, 0, 0], 3000)
    s = row(dev)
    assert 0.05 < s[0] <= 0.05 + 5.0 / ks * 1.001            # settles at the spring's deflection
    assert s[0] == pytest.approx(0.05 + 5.0 / ks, rel=1e-3)
    assert abs(s[7]) < 1e-6
    assert dev.endstop_wrench[0] == pytest.approx(-5.0, rel=1e-3)
    assert dev.counters()["endstop_steps"] > 0
    run(dev, [-1.0, 0, 0, 0, 0, 0], 200)                       # pulling away: the stop lets go
    assert row(dev)[0] < 0.05 and np.all(dev.endstop_wrench == 0.0)


def test_endstop_stops_a_fast_handle_and_never_pulls():
    dev = make("planar", initial_velocity=[1.0, -0.5, 0.0], workspace_min_m=[-0.06, -0.06],
               workspace_max_m=[0.06, 0.06])
    dev.enable()
    xs = []
    for _ in range(2000):
        run(dev, np.zeros(6), 1)
        s = row(dev)
        xs.append(s[0])
        assert dev.endstop_wrench[0] <= 0.0 and dev.endstop_wrench[1] >= 0.0   # push inwards only
    ks = dev.spec.values["endstop_stiffness_n_per_m"]
    assert max(xs) < 0.06 + 1.0 * math.sqrt(0.4 / ks) * 1.01   # at most v sqrt(m/k) past the wall
    assert -0.06 <= row(dev)[1] and row(dev)[0] <= 0.06 + 1e-9


def test_rotation_limits_hold_planar_and_spatial():
    for kind, lim in (("planar", 0.5), ("spatial", 0.4)):
        dev = make(kind, rotation_limit_rad=lim)
        ksr = dev.spec.values["endstop_rot_stiffness_n_m_per_rad"]
        dev.enable()
        run(dev, [0, 0, 0, 0, 0, 0.2], 3000)
        s = row(dev)
        theta = 2 * math.atan2(np.linalg.norm(s[4:7]), s[3])
        assert theta == pytest.approx(lim + 0.2 / ksr, rel=1e-3), kind
        assert dev.endstop_wrench[5] == pytest.approx(-0.2, rel=1e-3)


# ----------------------------------------------------------------------------- safety
def test_saturation_caps_per_axis_and_is_counted():
    dev = make("planar", max_force_n=10.0, max_torque_n_m=0.5, **BIG, rotation_limit_rad=0.0)
    dev.enable()
    run(dev, [100.0, -3.0, 50.0, 9.0, 9.0, -5.0], 1)
    assert dev.last_command.tolist() == [10.0, -3.0, 0.0, 0.0, 0.0, -0.5]   # fz, tx, ty: not rendered
    c = dev.counters()
    assert c["saturated_writes"] == 1 and c["saturated_components"] == 2
    run(dev, [1.0, 0, 0, 0, 0, 0], 5)
    assert dev.counters()["saturated_writes"] == 1
    one = make("1dof", max_force_n=2.0)
    one.enable()
    run(one, [-7.0, 0, 0, 0, 0, 0], 3)
    assert one.last_command[0] == -2.0 and one.counters()["saturated_writes"] == 3


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_non_finite_command_is_refused_zero_rendered_fault_latched(bad):
    dev = make("spatial", **BIG)
    dev.enable()
    run(dev, [1.0, 0, 0, 0, 0, 0], 10)
    v = row(dev)[7]
    w = np.array([1.0, 0, 0, 0, bad, 0])            # even in a component the caller might not care about
    assert run(dev, w, 1) == DEV_FAULT_NONFINITE_COMMAND
    assert dev.fault == DEV_FAULT_NONFINITE_COMMAND and np.all(dev.last_command == 0.0)
    assert run(dev, [1.0, 0, 0, 0, 0, 0], 50) == DEV_FAULT_NONFINITE_COMMAND    # latched
    assert np.all(dev.last_command == 0.0)
    assert row(dev)[7] <= v                            # no force since
    assert dev.counters()["nonfinite_refused"] == 1 and dev.counters()["zeroed_writes"] == 51
    dev.enable()
    assert run(dev, [1.0, 0, 0, 0, 0, 0], 1) == DEV_OK and dev.last_command[0] == 1.0


def test_starts_disabled_and_disable_zeroes_at_once_until_enable():
    dev = make("planar", **BIG)
    assert not dev.enabled
    assert run(dev, [1.0, 0, 0, 0, 0, 0], 3) == DEV_FAULT_DISABLED
    assert np.all(dev.last_command == 0.0) and row(dev)[0] == 0.0
    dev.enable()
    assert run(dev, [1.0, 0, 0, 0, 0, 0], 3) == DEV_OK and dev.last_command[0] == 1.0
    dev.disable()
    assert np.all(dev.last_command == 0.0)            # at once, before any write
    assert dev.read(np.zeros(base.DEV_NSTATE)) == DEV_FAULT_DISABLED
    assert run(dev, [1.0, 0, 0, 0, 0, 0], 20) == DEV_FAULT_DISABLED
    assert np.all(dev.last_command == 0.0) and dev.fault == DEV_OK
    dev.enable()
    assert run(dev, [1.0, 0, 0, 0, 0, 0], 1) == DEV_OK


def test_watchdog_zeroes_and_latches_until_enable():
    dev = make("1dof", watchdog_s=0.05)
    dev.enable()
    assert run(dev, [1.0, 0, 0, 0, 0, 0], 10) == DEV_OK
    dev.clock.advance(0.05)                             # exactly the watchdog: still fine
    assert dev.write(np.array([1.0, 0, 0, 0, 0, 0])) == DEV_OK
    dev.clock.advance(0.1)                              # the loop stalled for 100 ms
    assert dev.read(np.zeros(base.DEV_NSTATE)) == DEV_FAULT_WATCHDOG   # seen without a write
    assert dev.fault == DEV_FAULT_WATCHDOG
    v = row(dev)[7]
    assert run(dev, [1.0, 0, 0, 0, 0, 0], 200) == DEV_FAULT_WATCHDOG   # writes resume: still zero
    assert np.all(dev.last_command == 0.0) and row(dev)[7] <= v
    assert dev.counters()["watchdog_trips"] == 1
    dev.enable()
    assert run(dev, [1.0, 0, 0, 0, 0, 0], 1) == DEV_OK and dev.last_command[0] == 1.0


def test_watchdog_counts_from_enable_and_zero_disables_it():
    dev = make("1dof", watchdog_s=0.05)
    dev.clock.advance(10.0)                             # disabled: nothing to watch
    assert run(dev, np.zeros(6), 1) == DEV_FAULT_DISABLED
    dev.enable()
    dev.clock.advance(0.06)                             # enabled, then no write
    assert dev.write(np.zeros(6)) == DEV_FAULT_WATCHDOG
    off = make("1dof", watchdog_s=0.0)
    off.enable()
    off.clock.advance(100.0)
    assert off.write(np.array([1.0, 0, 0, 0, 0, 0])) == DEV_OK
    assert off.limits.watchdog_s == 0.0


def test_write_rejects_a_wrong_shape_without_stepping():
    dev = make("planar")
    dev.enable()
    with pytest.raises(ValueError, match="wrench"):
        dev.write(np.zeros(3))
    with pytest.raises(ValueError, match="wrench"):
        dev.write(np.zeros((1,)))
    assert dev.time_s == 0.0
    assert dev.write([0, 0, 0, 0, 0, 0]) == DEV_OK and dev.time_s == pytest.approx(DT)   # lists are fine
    with pytest.raises(ValueError, match="state_out"):
        dev.read(np.zeros(5))


def test_no_allocation_per_step():
    for kind, hand in (("planar", {"type": "sinusoid", "amplitude": [0, 0.5, 0], "frequency_hz": 2.5}),
                       ("spatial", {"type": "impedance", "target": {"type": "sinusoid"}}),
                       ("1dof", {"type": "steps", "steps": [[0, [1]], [0.3, [-1]]]})):
        dev = make(kind, hand=hand)
        dev.enable()
        w = np.array([0.1, 0.2, 0.0, 0.0, 0.0, 0.01])
        s = np.zeros(base.DEV_NSTATE)
        for _ in range(100):
            dev.write(w); dev.read(s)
        tracemalloc.start()
        try:
            before = tracemalloc.get_traced_memory()[0]
            for _ in range(1000):
                dev.clock.ns += 1_000_000
                dev.write(w)
                dev.read(s)
            grown = tracemalloc.get_traced_memory()[0] - before
        finally:
            tracemalloc.stop()
        assert grown < 512, (kind, grown)


_NRT_PROBE = """
import numpy as np
from numba import njit
from numba.core.runtime import rtsys
from hapticproxy.server.devices import dynamics as dyn, hands
from hapticproxy.server.devices.sim import make_sim_device


@njit
def loop(hp, tab, par, st, cnt, ctl, hout, w, out, n):
    for _ in range(n):
        hands.hand_eval(hp, tab, st, hout)
        dyn.sim_write(par, st, cnt, ctl, hout, w, 0)
        hands.inputs_eval(hp, tab, st)
        dyn.sim_read(st, ctl, cnt, out, 0)


res = []
for kind, hand in (("1dof", {"type": "steps", "steps": [[0, [1]], [0.3, [-1]]]}),
                   ("planar", {"type": "sinusoid"}),
                   ("spatial", {"type": "impedance", "target": {"type": "waypoints",
                                "points": [[0, [0, 0, 0, 0, 0, 0]], [1, [0.01, 0, 0, 0, 0, 0.1]]]}})):
    d = make_sim_device({"kind": kind, "hand": hand}, period_s=1e-3)
    d.enable()
    par, st, cnt, ctl, hp, tab = d.arrays()
    args = (hp, tab, par, st, cnt, ctl, d._hout, np.full(6, 0.1), np.zeros(dyn.DEV_NSTATE))
    loop(*args, 1)
    for n in (1, 3000):
        a = rtsys.get_allocation_stats().alloc
        loop(*args, n)
        res.append(rtsys.get_allocation_stats().alloc - a)
print(res)
"""


def test_kernels_allocate_nothing_per_step_nrt_count():
    """numba's own allocation counter (NRT stats, on in a child process): running 3000 steps
    inside compiled code allocates exactly what running one does (the call boundary only)."""
    import os
    import subprocess
    import sys

    env = dict(os.environ, NUMBA_NRT_STATS="1")
    out = subprocess.run([sys.executable, "-c", _NRT_PROBE], capture_output=True, text=True, env=env, timeout=300)
    assert out.returncode == 0, out.stderr
    res = [int(x) for x in out.stdout.strip().strip("[]").split(",")]
    assert len(res) == 6 and res[0::2] == res[1::2], res


# ------------------------------------------------------------------------------- config
def test_defaults_work_for_every_kind_and_the_planar_device_is_the_documented_one():
    for kind in ("1dof", "planar", "spatial"):
        dev = make_sim_device({"kind": kind}, period_s=DT)
        assert dev.kind == kind and dev.fault == DEV_OK and not dev.enabled
        assert dev.limits.max_force_n > 0 and dev.limits.watchdog_s == 0.05
    dev = make_sim_device({}, period_s=DT)
    assert dev.kind == "planar"
    assert dev.spec.values["mass_kg"] == 0.4 and dev.spec.values["inertia_kg_m2"] == 1.0e-3
    assert dev.limits.workspace_min_m == (-0.25, -0.25, 0.0) and dev.limits.max_torque_n_m == 0.5
    s = row(dev)
    assert s[3] == 1.0 and np.all(s[13:19] == 0.0)      # ideal sensor: zero, not NaN
    one = make_sim_device({"kind": "1dof"}, period_s=DT).limits
    assert one.max_torque_n_m == 0.0 and one.max_angular_speed_rad_per_s == math.inf   # renders no torque, cannot turn


@pytest.mark.parametrize("cfg, key", [
    ({"kind": "hexapod"}, "device.kind"),
    ({"mass_kg": -1.0}, "device.mass_kg"),
    ({"mass_kg": True}, "device.mass_kg"),
    ({"mass_kg": "heavy"}, "device.mass_kg"),
    ({"masss_kg": 1.0}, "device.masss_kg"),
    ({"max_force_n": math.nan}, "device.max_force_n"),
    ({"kind": "1dof", "inertia_kg_m2": 1e-3}, "device.inertia_kg_m2"),
    ({"kind": "planar", "axis": [1, 0, 0]}, "device.axis"),
    ({"kind": "1dof", "axis": [1, 1, 0]}, "device.axis"),
    ({"kind": "spatial", "inertia_kg_m2": [[1e-3, 0, 0], [0, -1e-3, 0], [0, 0, 1e-3]]}, "device.inertia_kg_m2"),
    ({"kind": "spatial", "inertia_kg_m2": [1e-3, 1e-3]}, "device.inertia_kg_m2"),
    ({"initial_pose": [0.5, 0.0, 0.0]}, "device.initial_pose"),
    ({"initial_pose": [0.0, 0.0, 1.5]}, "device.initial_pose"),
    ({"initial_pose": [0.0, 0.0]}, "device.initial_pose"),
    ({"kind": "spatial", "initial_pose": [0, 0, 0, 2, 0, 0, 0]}, "device.initial_pose"),
    ({"initial_velocity": [1.0]}, "device.initial_velocity"),
    ({"endstop_stiffness_n_per_m": 1e9}, "device.endstop_stiffness_n_per_m"),
    ({"endstop_rot_stiffness_n_m_per_rad": 1e6}, "device.endstop_rot_stiffness_n_m_per_rad"),
    ({"workspace_min_m": [0.1, 0.1], "workspace_max_m": [0.0, 0.0]}, "device.workspace_max_m"),
    ({"watchdog_s": -1.0}, "device.watchdog_s"),
    ({"watchdog_s": 1e-5}, "device.watchdog_s"),
    ({"rotation_limit_rad": 4.0}, "device.rotation_limit_rad"),
    ({"hand": "sinusoid"}, "device.hand"),
    ({"hand": {"type": "wave"}}, "device.hand.type"),
    ({"hand": {"type": "constant", "amplitude": [1, 0, 0]}}, "device.hand.amplitude"),
    ({"hand": {"type": "constant", "wrench": [1, 0]}}, "device.hand.wrench"),
    ({"hand": {"type": "sinusoid", "frequency_hz": -1}}, "device.hand.frequency_hz"),
    ({"hand": {"type": "steps", "steps": [[1.0, [0, 0, 0]], [0.5, [0, 0, 0]]]}}, "device.hand.steps[1]"),
    ({"hand": {"type": "steps", "steps": []}}, "device.hand.steps"),
    ({"hand": {"type": "steps", "steps": [[0, [1, 0, 0]], [2, [0, 0, 0]]], "repeat_period_s": 1.0}},
     "device.hand.repeat_period_s"),
    ({"hand": {"type": "impedance", "stiffness_n_per_m": -5}}, "device.hand.stiffness_n_per_m"),
    ({"hand": {"type": "impedance", "target": {"type": "waypoints"}}}, "device.hand.target.points"),
    ({"hand": {"type": "impedance", "target": {"type": "circle"}}}, "device.hand.target.type"),
    ({"hand": {"type": "impedance", "target": {"pose": [0, 0, 0], "speed": 1}}}, "device.hand.target.speed"),
    ({"hand": {"type": "replay"}}, "device.hand.file"),
    ({"hand": {"type": "replay", "file": "/nonexistent/rec.csv"}}, "device.hand.file"),
    ({"hand": {"type": "replay", "file": "x.csv", "mode": "force"}}, "device.hand.mode"),
])
def test_bad_config_names_the_key(cfg, key):
    with pytest.raises(ValueError) as exc:
        parse_sim_config(cfg, period_s=DT)
    msg = str(exc.value)
    assert msg.startswith(key + ":"), msg
    assert len(msg.splitlines()) == 1


def test_unknown_key_error_suggests_the_close_one():
    with pytest.raises(ValueError, match=r"device\.damping_n_s_per_m_: unknown key \(did you mean 'damping_n_s_per_m'"):
        parse_sim_config({"damping_n_s_per_m_": 1.0}, period_s=DT)
    with pytest.raises(ValueError, match=r"^period_s:"):
        parse_sim_config({}, period_s=0.0)


def test_default_endstop_stiffness_adapts_to_a_slow_period():
    spec = parse_sim_config({"kind": "1dof"}, period_s=1 / 100)
    k = spec.values["endstop_stiffness_n_per_m"]
    assert k == pytest.approx(0.2 / (0.01 ** 2))          # mass / period^2 < 20000
    assert parse_sim_config({"kind": "1dof"}, period_s=DT).values["endstop_stiffness_n_per_m"] == 20000.0


def test_entry_point_loading():
    dev = load_device("sim", {"driver": "sim", "kind": "spatial", "mass_kg": 0.5}, period_s=DT)
    assert isinstance(dev, SimDevice) and dev.kind == "spatial" and dev.name == "sim"
    assert dev.spec.values["mass_kg"] == 0.5
    with pytest.raises(ValueError, match="device.mass_kg"):
        load_device("sim", {"kind": "planar", "mass_kg": 0}, period_s=DT)
    with pytest.raises(ValueError, match="device.driver"):
        load_device("nosuch", {}, period_s=DT)


def test_reset_and_warm_up():
    warm_up()
    warm_up()
    dev = make("planar")
    dev.enable()
    run(dev, [1, 0, 0, 0, 0, 0.1], 100)
    dev.reset(pose=[0.01, -0.02, 0.3], velocity=[0.1, 0, 0])
    s = row(dev)
    assert s[0:2].tolist() == [0.01, -0.02] and 2 * math.atan2(s[6], s[3]) == pytest.approx(0.3)
    assert s[7] == 0.1 and dev.time_s == 0.0 and dev.counters()["steps"] == 0 and dev.enabled
