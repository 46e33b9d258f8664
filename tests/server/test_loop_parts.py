"""The loop receives its parts built and checks them at construction; the model the handshake's
check builds for a Hello is the one the engagement uses (never a second one)."""
from __future__ import annotations

import pytest
from server_harness import PointDevice, Rig, make_settings

from hapticproxy.protocol.transport import open_transport
from hapticproxy.server import control as ctl
from hapticproxy.server.loop import HapticLoop, ModelFactory


def test_parts_that_do_not_fit_are_refused_at_construction():
    s = make_settings()  # a planar tool on a planar device
    tr = open_transport(s["transport"]["url"], "server")
    try:
        with pytest.raises(ValueError, match="device"):
            HapticLoop(s, transport=tr, device=PointDevice(kind="1dof"))
        dev = PointDevice()
        with pytest.raises(ValueError, match="controller"):
            HapticLoop(s, transport=tr, device=dev, controller=ctl.Controller(s, "spatial"))
        with pytest.raises(ValueError, match="transport"):
            HapticLoop(s, transport=object(), device=dev)
    finally:
        tr.close()


def test_the_model_the_hello_check_built_is_the_one_engaged():
    s = make_settings()
    built = []

    class Counting(ModelFactory):
        def build(self, hello, epsilon_m, max_contacts):
            out = super().build(hello, epsilon_m, max_contacts)
            built.append(out[1])
            return out

    dev = PointDevice(hand=lambda t: (0.0, -0.5, 0.0))
    r = Rig(s, dev)
    try:
        r.loop.models = Counting(s, dev.kind, s.period_ns * 1e-9)
        r.run(0.5)
        assert r.loop.engagements == 1
        assert len(built) == 1 and r.loop.model is built[0]
    finally:
        r.close()
