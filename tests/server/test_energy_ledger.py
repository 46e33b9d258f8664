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
