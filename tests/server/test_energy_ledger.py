"""The energy ledger at the hand's port (``control.port_energy``): each command the device held
over a period times the handle's displacement during it, summed; translation and rotation."""
from __future__ import annotations

import math

import numpy as np
from hypothesis import given, settings, strategies as st

from hapticproxy.server import control as ctl

vec = st.lists(st.floats(-5.0, 5.0), min_size=3, max_size=3)


def _quat(rv):
    a = float(np.linalg.norm(rv))
    if a < 1e-15:
        return np.array([1.0, 0.0, 0.0, 0.0])
    ax = np.asarray(rv) / a
    return np.array([math.cos(a / 2), *(math.sin(a / 2) * ax)])


def _qmul(a, b):
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return np.array([aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw])


@settings(max_examples=200, deadline=None, derandomize=True, database=None)
@given(st.lists(st.tuples(vec, vec, vec, st.lists(st.floats(-0.2, 0.2), min_size=3, max_size=3)),
                min_size=2, max_size=20))
def test_the_ledger_pairs_each_held_command_with_the_motion_that_followed(seq):
    cs = np.zeros(ctl.NCS)
    dev = np.zeros(20)
    pos = np.zeros(3)
    q = np.array([1.0, 0.0, 0.0, 0.0])
    want = 0.0
    held_f = held_t = None
    for f, t, dx, drot in seq:
        dq = _quat(np.array(drot))
        pos_new, q_new = pos + 0.001 * np.asarray(dx), _qmul(dq, q)
        dev[0:3], dev[3:7] = pos_new, q_new
        ctl.port_energy(cs, dev)  # the device was read: the held command's period ends
        if held_f is not None:
            want += float(np.dot(held_f, pos_new - pos)) + float(np.dot(held_t, drot))
        cs[ctl.CS_PREV:ctl.CS_PREV + 3] = f  # the next command, written and held
        cs[ctl.CS_PREV + 3:ctl.CS_PREV + 6] = t
        held_f, held_t = np.asarray(f), np.asarray(t)
        pos, q = pos_new, q_new
    assert cs[ctl.CS_EHAND] == __import__("pytest").approx(want, rel=1e-9, abs=1e-12)


def test_a_non_finite_sample_loses_its_period_only():
    cs = np.zeros(ctl.NCS)
    dev = np.zeros(20)
    dev[3] = 1.0
    ctl.port_energy(cs, dev)
    cs[ctl.CS_PREV + 1] = 2.0
    dev[1] = math.nan
    ctl.port_energy(cs, dev)
    dev[1] = 0.01
    ctl.port_energy(cs, dev)   # no pose to pair with: nothing counted
    assert cs[ctl.CS_EHAND] == 0.0
    dev[1] = 0.03
    ctl.port_energy(cs, dev)
    assert cs[ctl.CS_EHAND] == __import__("pytest").approx(2.0 * 0.02)


def test_a_linkage_tools_ledger_counts_the_rotating_devices_torque():
    """A linkage tool on a spatial device: the port is the device's, so the ledger pairs the
    held command (force and torque) with the handle's displacement and rotation, as for a rigid
    tool. The device turns about a skew axis while it moves: the rotational coupling spring
    loads the handle with torque, and the kernel's ledger equals one kept here from the commands
    written and the device's own poses (the rotation's share is not small)."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).parents[1] / "model"))
    from light_rig import EPSILON_M, chain_tool

    from hapticproxy.server import config as cfg
    from hapticproxy.server.devices.base import empty_state
    from hapticproxy.server.model import ContactParams, LocalModel

    rate = 1000.0
    dt = 1.0 / rate
    settings = cfg.load({"loop": {"rate_hz": rate}, "model": {"tool": "linkage"},
                         "device": {"driver": "sim", "kind": "spatial"}})
    tool = chain_tool(0.08, 0.08 * (0.06 ** 2 + 0.015 ** 2) / 12, planar=False)
    m = LocalModel(tool, ContactParams(4000.0, 10.0, 0.0, 0.0, 0.0), period_s=dt, epsilon_m=EPSILON_M, capacity=8)
    m.reset([0.0, 0.05, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    c = ctl.Controller(settings, "spatial")
    row = empty_state()
    c.set_offset(*ctl.index_offset("spatial", row[:7], m.hand_state()[:7]))
    c.cs[ctl.CS_GAIN] = c.cs[ctl.CS_TARGET] = 1.0
    par, st_, C, CI, cnt = m.arrays()
    wk = m.kernel_args()[-1]
    lmeta, lk, lki, lw = m.linkage_args()
    axis = np.array([0.3, 0.5, 0.8]) / np.linalg.norm([0.3, 0.5, 0.8])
    omega = 3.0  # rad/s about the axis
    want = want_rot = 0.0
    prev_pose = held = None
    for k in range(400):
        t = k * dt
        row[0:3] = [0.01 * math.sin(5 * t), 0.0, 0.004 * t]
        row[3:7] = _quat(omega * t * axis)
        row[7:10] = [0.05 * math.cos(5 * t), 0.0, 0.004]
        row[10:13] = omega * axis
        row[13:19] = 0.0
        if held is not None:
            dq = _qmul(row[3:7], prev_pose[3:7] * np.array([1.0, -1.0, -1.0, -1.0]))
            rv = 2.0 * math.atan2(np.linalg.norm(dq[1:]), dq[0]) * dq[1:] / np.linalg.norm(dq[1:])
            want += float(np.dot(held[:3], row[0:3] - prev_pose[0:3]))
            want_rot += float(np.dot(held[3:], rv))
        rc = ctl.haptic_step_linkage(c.cp, c.cs, c.cc, row, c.cmd, par, lmeta, lk, lki, st_, C, CI, cnt, wk, lw,
                                     c.hand)
        assert rc == ctl.RC_OK
        held, prev_pose = c.cmd.copy(), row[0:7].copy()
    assert abs(want_rot) > 1e-4 and abs(want_rot) > 0.1 * abs(want)  # the rotation carries work
    assert c.cs[ctl.CS_EHAND] == __import__("pytest").approx(want + want_rot, rel=1e-9, abs=1e-12)
