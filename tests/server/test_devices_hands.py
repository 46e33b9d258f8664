"""The simulated hands: scripted wrenches, the impedance grip, recorded trajectories."""
from __future__ import annotations

import math

import numpy as np
import pytest

from hapticproxy.server.devices import base
from hapticproxy.server.devices.sim import make_sim_device

DT = 1e-3


class FakeClock:
    def __init__(self) -> None:
        self.ns = 0

    def __call__(self) -> int:
        return self.ns


def make(kind, hand, **cfg):
    clock = FakeClock()
    dev = make_sim_device({"kind": kind, "hand": hand, **cfg}, period_s=DT, clock_ns=clock)
    dev.clock = clock
    dev.enable()
    dev.on_engage()  # a session engages at t = 0: the script starts
    return dev


def steps(dev, n, wrench=(0, 0, 0, 0, 0, 0)):
    """n steps; returns the state rows after each (n x DEV_NSTATE)."""
    w = np.asarray(wrench, dtype=np.float64)
    out = np.zeros((n, base.DEV_NSTATE))
    for i in range(n):
        dev.clock.ns += 1_000_000
        dev.write(w)
        dev.read(out[i])
    return out


def test_constant_hand_pushes_the_handle_and_the_sensor_reads_it():
    dev = make("1dof", {"type": "constant", "wrench": [0.5]}, mass_kg=0.25, damping_n_s_per_m=0.0,
               workspace_min_m=[-5, -5, -5], workspace_max_m=[5, 5, 5])
    assert dev.state[13] == 0.5                         # before any step too
    rows = steps(dev, 400)
    assert rows[-1, 0] == pytest.approx(0.5 * DT * DT * 400 * 401 / (2 * 0.25), rel=1e-9)
    assert np.all(rows[:, 13] == 0.5) and np.all(rows[:, 14:19] == 0.0)


def test_sinusoid_hand_per_axis_with_phase_and_offset():
    hand = {"type": "sinusoid", "amplitude": [0, 0.5, 0.01], "frequency_hz": 2.5, "phase_rad": [0, 0.3, 0.0],
            "offset": [0.1, 0, 0]}
    dev = make("planar", hand, workspace_min_m=[-5, -5], workspace_max_m=[5, 5])
    rows = steps(dev, 500)
    # the hand columns hold the wrench applied over the step that ended at `time`: profile(time - dt)
    t0 = rows[:, 19] - DT
    assert rows[:, 13] == pytest.approx(np.full(500, 0.1))
    assert rows[:, 14] == pytest.approx(0.5 * np.sin(2 * np.pi * 2.5 * t0 + 0.3), abs=1e-12)
    assert rows[:, 18] == pytest.approx(0.01 * np.sin(2 * np.pi * 2.5 * t0), abs=1e-12)
    assert np.all(rows[:, 15:18] == 0.0)               # fz, tx, ty: not a planar device's
    assert rows[-1, 1] != 0.0                          # and it moves the handle


def test_steps_hand_holds_each_wrench_and_repeats():
    dev = make("1dof", {"type": "steps", "steps": [[0.1, [1.0]], [0.3, [-2.0]]], "repeat_period_s": 0.5})
    rows = steps(dev, 1200)
    t0 = np.round(rows[:, 19] - DT, 9) % 0.5
    expect = np.where(t0 < 0.1, 0.0, np.where(t0 < 0.3, 1.0, -2.0))
    assert rows[:, 13] == pytest.approx(expect)
    flat = make("1dof", {"type": "steps", "steps": [[0.0, 1.0, 0, 0, 0, 0, 0], [0.2, 0, 0, 0, 0, 0, 0]]})
    r = steps(flat, 400)
    assert r[100, 13] == 1.0 and r[300, 13] == 0.0 and r[-1, 13] == 0.0   # holds the last


def test_impedance_hand_settles_on_its_target_and_balances_the_command():
    hand = {"type": "impedance", "stiffness_n_per_m": 400.0, "damping_n_s_per_m": 10.0, "mass_kg": 0.1,
            "target": {"type": "constant", "pose": [0.03]}}
    dev = make("1dof", hand)
    rows = steps(dev, 3000)
    assert rows[-1, 0] == pytest.approx(0.03, abs=1e-6)
    assert abs(rows[-1, 13]) < 1e-3
    rows = steps(dev, 3000, wrench=[2.0, 0, 0, 0, 0, 0])   # the device pushes; the grip gives
    assert rows[-1, 0] == pytest.approx(0.03 + 2.0 / 400.0, abs=1e-6)
    assert rows[-1, 13] == pytest.approx(-2.0, abs=1e-4)   # the sensor reads the hand holding back


def test_impedance_hand_mass_moves_with_the_handle():
    hand = {"type": "impedance", "stiffness_n_per_m": 0.0, "damping_n_s_per_m": 0.0, "mass_kg": 0.3,
            "target": {"type": "constant", "pose": [0.0]}}
    dev = make("1dof", hand, mass_kg=0.2, damping_n_s_per_m=0.0)
    rows = steps(dev, 100, wrench=[1.0, 0, 0, 0, 0, 0])
    a = 1.0 / 0.5
    assert rows[-1, 7] == pytest.approx(a * 0.1, rel=1e-9)
    assert rows[-1, 13] == pytest.approx(-0.3 * a, rel=1e-9)   # the sensor reads -m_h a


def test_impedance_sinusoid_target_gives_the_second_order_response():
    k, b_h, m_h, m, b = 300.0, 5.0, 0.1, 0.2, 1.0
    f, amp = 3.0, 0.01
    hand = {"type": "impedance", "stiffness_n_per_m": k, "damping_n_s_per_m": b_h, "mass_kg": m_h,
            "target": {"type": "sinusoid", "amplitude": [amp], "frequency_hz": f, "offset": [0.0]}}
    dev = make("1dof", hand, mass_kg=m, damping_n_s_per_m=b)
    rows = steps(dev, 6000)
    w = 2 * math.pi * f
    gain = abs(complex(k, w * b_h) / complex(k - (m + m_h) * w * w, w * (b_h + b)))
    measured = np.max(np.abs(rows[-2000:, 0])) / amp     # after the transient, 6 periods
    assert measured == pytest.approx(gain, rel=0.02)


def test_waypoints_target_is_followed():
    hand = {"type": "impedance", "stiffness_n_per_m": 2000.0, "damping_n_s_per_m": 40.0,
            "target": {"type": "waypoints", "points": [[0.0, [0.0, 0.0, 0.0]], [1.0, [0.04, -0.02, 0.3]],
                                                       [1.5, 0.04, -0.02, 0.3]]}}
    dev = make("planar", hand)
    rows = steps(dev, 2500)
    mid = rows[499]                                      # t = 0.5: target (0.02, -0.01, 0.15)
    assert mid[0] == pytest.approx(0.02, abs=1e-3) and mid[1] == pytest.approx(-0.01, abs=1e-3)
    assert 2 * math.atan2(mid[6], mid[3]) == pytest.approx(0.15, abs=0.02)
    end = rows[-1]
    assert end[0] == pytest.approx(0.04, abs=1e-5) and end[1] == pytest.approx(-0.02, abs=1e-5)
    assert 2 * math.atan2(end[6], end[3]) == pytest.approx(0.3, abs=1e-3)


def test_spatial_impedance_target_rotation():
    hand = {"type": "impedance", "rot_stiffness_n_m_per_rad": 0.5, "rot_damping_n_m_s_per_rad": 0.02,
            "target": {"type": "constant", "pose": [0.01, 0.02, -0.01, 0.3, 0.0, -0.2]}}
    dev = make("spatial", hand)
    rows = steps(dev, 4000)
    s = rows[-1]
    assert s[0:3] == pytest.approx([0.01, 0.02, -0.01], abs=1e-5)
    r = np.array([0.3, 0.0, -0.2])
    a = np.linalg.norm(r)
    q = np.r_[math.cos(a / 2), math.sin(a / 2) * r / a]
    assert s[3:7] == pytest.approx(q, abs=1e-4)
    assert np.all(np.abs(s[13:19]) < 1e-3)


def _circle(n=201, T=2.0):
    t = np.linspace(0.0, T, n)
    x = 0.02 * np.cos(2 * np.pi * t / T) - 0.02
    y = 0.02 * np.sin(2 * np.pi * t / T)
    th = 0.4 * np.sin(2 * np.pi * t / T)
    return t, x, y, th


def test_replay_pose_from_csv_and_npz_equals_the_same_waypoints(tmp_path):
    t, x, y, th = _circle()
    pose = np.c_[x, y, np.zeros_like(x), np.cos(th / 2), 0 * x, 0 * x, np.sin(th / 2)]
    csv = tmp_path / "rec.csv"
    with open(csv, "w") as fh:
        fh.write("# recorded\nt_s,x,y,z,qw,qx,qy,qz\n")
        for i in range(len(t)):
            fh.write(",".join(repr(float(v)) for v in (t[i], *pose[i])) + "\n")
    npz = tmp_path / "rec.npz"
    np.savez(npz, t_s=t, pose=pose)
    grip = {"stiffness_n_per_m": 2000.0, "damping_n_s_per_m": 20.0}
    runs = []
    for hand in ({"type": "replay", "file": str(csv), **grip},
                 {"type": "replay", "file": str(npz), "mode": "pose", **grip},
                 {"type": "impedance", **grip, "rot_stiffness_n_m_per_rad": 5.0, "rot_damping_n_m_s_per_rad": 0.05,
                  "target": {"type": "waypoints", "points": [[t[i], [x[i], y[i], th[i]]] for i in range(len(t))]}}):
        runs.append(steps(make("planar", hand), 2500))
    assert runs[0] == pytest.approx(runs[1], abs=1e-12, nan_ok=True)  # (no inputs: NaN columns)
    assert runs[0] == pytest.approx(runs[2], abs=1e-9, nan_ok=True)
    follow = runs[0]
    i = 1000                                             # t = 1 s: the far side of the circle
    assert follow[i, 0] == pytest.approx(-0.04, abs=2e-3) and abs(follow[i, 1]) < 3e-3


def test_replay_wrench_interpolates_and_repeats(tmp_path):
    csv = tmp_path / "w.csv"
    csv.write_text("0.0,0.0,0.0,0.0\n0.1,1.0,-1.0,0.02\n0.2,1.0,-1.0,0.02\n")
    dev = make("planar", {"type": "replay", "file": str(csv), "mode": "wrench", "repeat_period_s": 0.25})
    rows = steps(dev, 600)
    t0 = np.round(rows[:, 19] - DT, 9) % 0.25
    fx = np.clip(t0 / 0.1, 0.0, 1.0)
    assert rows[:, 13] == pytest.approx(fx, abs=1e-9)
    assert rows[:, 14] == pytest.approx(-fx, abs=1e-9)
    assert rows[:, 18] == pytest.approx(0.02 * fx, abs=1e-9)


def test_replay_file_errors_name_the_key(tmp_path):
    bad = tmp_path / "bad.csv"
    bad.write_text("0.0,1.0\n0.0,2.0\n")                 # times not increasing
    with pytest.raises(ValueError, match=r"^device\.hand\.file: .*increase"):
        make_sim_device({"kind": "1dof", "hand": {"type": "replay", "file": str(bad), "mode": "wrench"}}, period_s=DT)
    cols = tmp_path / "cols.csv"
    cols.write_text("0.0,1.0,2.0\n0.1,1.0,2.0\n")         # 2 values: not a 1dof wrench
    with pytest.raises(ValueError, match=r"^device\.hand\.file: .*columns"):
        make_sim_device({"kind": "1dof", "hand": {"type": "replay", "file": str(cols), "mode": "wrench"}}, period_s=DT)
    junk = tmp_path / "junk.csv"
    junk.write_text("0.0,abc\n")
    with pytest.raises(ValueError, match=r"^device\.hand\.file: "):
        make_sim_device({"kind": "1dof", "hand": {"type": "replay", "file": str(junk)}}, period_s=DT)
    with pytest.raises(ValueError, match=r"^device\.hand\.damping_n_s_per_m: only used"):
        make_sim_device({"kind": "1dof", "hand": {"type": "replay", "file": str(cols), "mode": "wrench",
                                                  "damping_n_s_per_m": 1.0}}, period_s=DT)


@pytest.mark.parametrize("hand", [{"type": "constant", "wrench": [0.5]},
                                  {"type": "steps", "steps": [[0.0, [0.5]], [0.1005, [0.2]]]},
                                  {"type": "impedance", "target": {"type": "constant", "pose": [0.05]}}])
def test_a_script_waits_for_the_engagement_and_restarts_with_each_session(hand):
    clock = FakeClock()
    dev = make_sim_device({"kind": "1dof", "hand": hand}, period_s=DT, clock_ns=clock)
    dev.clock = clock
    dev.enable()
    before = steps(dev, 300)                            # no client yet: the handle stays free
    assert np.all(before[:, 13] == 0.0) and np.all(before[:, 0] == 0.0)
    dev.on_engage()
    a = steps(dev, 200)
    assert np.any(a[:, 13] != 0.0)
    dev.on_engage()                                     # the next session: from the start again
    b = steps(dev, 200)
    if hand["type"] == "steps":
        np.testing.assert_allclose(a[:, 13], b[:, 13])  # the same profile, from its t = 0


def test_a_script_may_start_with_the_server():
    clock = FakeClock()
    dev = make_sim_device({"kind": "1dof", "hand": {"type": "constant", "wrench": [0.5], "start": "server"}},
                          period_s=DT, clock_ns=clock)
    dev.clock = clock
    dev.enable()
    assert np.all(steps(dev, 10)[:, 13] == 0.5)
