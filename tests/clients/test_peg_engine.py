"""The 1-DOF peg engine (Figs. 6 and 9): both walls at their analytic separations, epsilon
reporting, the tool following the proxy, bad input refused."""
from __future__ import annotations

import numpy as np
import pytest

from hapticproxy.clients.cli import load_engine_class
from hapticproxy.clients.engine import ContactBuffer
from hapticproxy.clients.peg_engine import PEG_HALF_WIDTH_M, PegEngine


def _at(e: PegEngine, x: float, buf: ContactBuffer) -> int:
    pose = np.zeros(7)
    pose[0], pose[3] = x, 1.0
    e.drive_tool(pose, np.zeros(6), np.zeros(6))
    e.step(1.0 / e.rate_hz)
    return e.contacts(buf, buf.capacity)


@pytest.mark.parametrize("x", [-0.003, -0.0004, 0.0, 0.0004, 0.003])
def test_walls_are_reported_where_they_are_within_epsilon(x):
    e = PegEngine()
    info = e.load_scene("peg1d")
    assert info.tool.kind == "1dof" and info.tool.mass_kg == 1.0 and info.env_rate_hz == 50.0
    buf = ContactBuffer(4)
    for eps in (0.0, 0.001, 0.005):
        e.set_epsilon(eps)
        n = _at(e, x, buf)
        rows = {int(buf.keys[i, 1]): (buf.position_m[i, 0], buf.normal[i, 0], buf.separation_m[i]) for i in range(n)}
        expect = {b: d for b, d in ((1, x), (2, -x)) if d <= eps}
        assert set(rows) == set(expect)
        for b, d in expect.items():
            cx, nx, sep = rows[b]
            assert sep == pytest.approx(d, abs=1e-12)
            assert (cx, nx) == ((-PEG_HALF_WIDTH_M, 1.0) if b == 1 else (PEG_HALF_WIDTH_M, -1.0))
        assert e.tool_pose(np.zeros(7))[0] == x


def test_registered_and_refuses_bad_input():
    assert load_engine_class("peg1d") is PegEngine
    e = PegEngine(rate_hz=40.0)
    with pytest.raises(ValueError, match="unknown scene"):
        e.load_scene("testbed")
    e.load_scene("peg1d")
    with pytest.raises(ValueError):
        e.set_epsilon(float("nan"))
    with pytest.raises(ValueError):
        e.step(0.0)
    with pytest.raises(ValueError):
        PegEngine(rate_hz=0.0)
    pose = np.zeros(7)
    pose[0], pose[3] = float("nan"), 1.0
    e.drive_tool(pose, np.zeros(6), np.zeros(6))   # ignored: the last good target is kept
    e.step(0.025)
    assert e.tool_pose(np.zeros(7))[0] == 0.0
