"""Light tools through the whole server (issue 31, item 1), in simulated time: a client's Hello
declares a 0.1 kg spatial tool, the loop engages it on the simulated spatial device whose hand
pushes down, and the wall environment (the real protocol over the in-memory transport) keeps it
on the floor. Before the proxy's integration treated the coupling and the contacts implicitly, a
40 mm cube flipped between +-0.53 rad/s every step and a 20 x 80 x 20 mm peg standing on its
end spun up 1.25x per step until the device's speed trip, while the ProxyStates said
``engaged``."""
from __future__ import annotations

import numpy as np
import pytest

from hapticproxy.protocol.messages import ServerState

from server_harness import WallEnv, make_settings, Rig

PUSH_N = 1.0


class _Recording(WallEnv):
    """The wall environment, keeping every ProxyState's angular speed and server state."""

    def __init__(self, *a, inertia3=None, **kw):
        super().__init__(*a, **kw)
        if inertia3 is not None:
            self.hello.inertia_kg_m2 = (*inertia3, 0.0, 0.0, 0.0)
        self.seen: list[tuple[float, float, int]] = []

    def _follow(self, ps):
        tw = np.asarray(ps.proxy_twist, dtype=float)
        self.seen.append((float(np.linalg.norm(tw[:3])), float(np.linalg.norm(tw[3:])), int(ps.server_state)))
        super()._follow(ps)


def _run(hx, hy, mass, inertia3, rate_hz=1000.0, seconds=2.0):
    settings = make_settings(loop={"rate_hz": rate_hz},
                             device={"driver": "sim", "kind": "spatial",
                                     "hand": {"type": "constant", "wrench": [0.0, -PUSH_N, 0.0, 0.0, 0.0, 0.0]}})
    rig = Rig.__new__(Rig)
    from hapticproxy.server.clock import SimClock
    from hapticproxy.server.loop import HapticLoop

    rig.clock = SimClock(start_ns=1_000_000_000)
    rig.settings = settings
    rig.loop = HapticLoop.build(settings, clock=rig.clock)
    rig.device = rig.loop.device
    rig.loop.warm_up()
    rig.loop.start()
    rig.env = _Recording(settings["transport"]["url"], rig.clock, kind="spatial", hx=hx, hy=hy, mass_kg=mass,
                         inertia=inertia3[0], inertia3=inertia3, start_pose=(0.0, hy + 0.001, 0.0), epsilon=0.005)
    rig.rows = []
    return rig


@pytest.mark.parametrize("shape", ["cube", "peg"])
def test_a_light_tool_resting_on_the_floor_is_at_rest_in_every_proxy_state(shape):
    if shape == "cube":
        hx, hy = 0.02, 0.02
        inertia3 = (0.1 * 0.0032 / 12,) * 3                       # 40 mm cube, 2.7e-5 kg m^2
    else:
        hx, hy = 0.01, 0.04
        inertia3 = (0.1 * 0.0068 / 12, 0.1 * 0.0008 / 12, 0.1 * 0.0068 / 12)  # I about the vertical 6.7e-6
    rig = _run(hx, hy, 0.1, inertia3)
    try:
        rig.run(2.0, record=False)
        seen = rig.env.seen
        assert rig.loop.engagements == 1 and len(seen) > 60
        late = seen[len(seen) // 2:]                               # the second second
        states = {s for _, _, s in late}
        assert states == {int(ServerState.ENGAGED)}
        assert max(w for _, w, _ in late) < 1e-3, max(w for _, w, _ in late)
        assert max(v for v, _, _ in late) < 1e-3
        # the hand's push is balanced by the force on the handle
        cmd = rig.loop.ctrl.cmd
        assert cmd[1] == pytest.approx(PUSH_N, rel=0.02)
    finally:
        rig.close()


def test_a_diverging_proxy_is_not_engaged_in_its_proxy_states(monkeypatch):
    """With the explicit step (the paper's; the server's before issue 31) the peg spins up; once
    the model has flagged its integration as diverged, no ProxyState may say ``engaged``."""
    import functools

    from hapticproxy.server.model import model as model_mod

    monkeypatch.setattr(model_mod.LocalModel, "__init__",
                        functools.partialmethod(model_mod.LocalModel.__init__, integrator="explicit"))
    monkeypatch.setattr(model_mod, "check_step_stability", lambda *a, **k: None)
    rig = _run(0.01, 0.04, 0.1, (0.1 * 0.0068 / 12, 0.1 * 0.0008 / 12, 0.1 * 0.0068 / 12))
    flagged_at = []
    try:
        def watch(i):
            m = rig.loop.model
            if not flagged_at and m is not None and m.diverged:
                flagged_at.append(len(rig.env.seen))
        rig.run(2.0, record=False, on_step=watch)
        assert flagged_at, "the explicit peg did not diverge"
        after = rig.env.seen[flagged_at[0] + 2:]
        assert after and all(s != int(ServerState.ENGAGED) for _, _, s in after)
        # lifecycle.FAULT_POLICY "diverged": faded (the device stays on), latched until a re-arm
        from hapticproxy.server.lifecycle import Fault
        loop = rig.loop
        assert loop.state_name == "fault" and loop.fault == Fault.DIVERGED
        assert float(np.abs(loop.ctrl.cmd).max()) == 0.0 and not loop.device.fault
    finally:
        rig.close()
