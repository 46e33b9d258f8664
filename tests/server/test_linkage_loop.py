"""The haptic loop with a linkage tool, in simulated time: a 3-bar chain held by its last link
engages, falls onto the floor under the hand's push and settles with the rendered force
balancing the push; its ProxyState carries the joint positions, velocities and efforts; with the
engine's joint positions in each ContactUpdate (1.1) the proxy does not creep into the floor
when the engine's chain is held back by it (without them, the paper's eq. 1, it does); a Hello
the model cannot hold is refused by name; the config's linkage rules."""
from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))

from linkage_env import BAR_L, BAR_W, LinkageWallEnv, bar_links  # noqa: E402
from server_harness import PointDevice, make_settings  # noqa: E402

from hapticproxy.protocol.codec import Hello  # noqa: E402
from hapticproxy.protocol.messages import ErrorCode, ToolKind  # noqa: E402
from hapticproxy.protocol.session import ClientEndpoint  # noqa: E402
from hapticproxy.protocol.transport import open_transport  # noqa: E402
from hapticproxy.server import config as cfg  # noqa: E402
from hapticproxy.server.clock import SimClock  # noqa: E402
from hapticproxy.server.loop import HapticLoop  # noqa: E402
from hapticproxy.server.shm import LS, TEL  # noqa: E402
from hapticproxy.testing.cleanup import made_then_ended  # noqa: E402

PUSH = lambda t: (0.0, -0.5, 0.0)  # noqa: E731
#: The bars are light (80 g; a contact at a corner sees 24-45 g of the chain): the explicit
#: contact damping needs dt < 2 m_eff / b_sum, so 10 N s/m, not the peg's 30. With friction the
#: pressed chain cannot splay (frictionless, the pivot under the push buckles, as it should).
MODEL = {"damping_n_s_per_m": 10.0, "mu_static": 0.5, "mu_kinetic": 0.4}


class LinkageRig:
    def __init__(self, env_kwargs=None, **sections):
        sections.setdefault("model", {})
        sections["model"] = {"tool": "linkage", **MODEL, **sections["model"]}
        self.settings = make_settings(**sections)
        self.clock = SimClock(start_ns=1_000_000_000)
        self.device = PointDevice(hand=PUSH, period_s=self.settings.period_ns * 1e-9)
        self.loop = HapticLoop.build(self.settings, clock=self.clock, device=self.device)
        self.loop.warm_up()
        self.loop.start()
        self.env = LinkageWallEnv(self.settings["transport"]["url"], self.clock, **(env_kwargs or {}))

    def run(self, seconds):
        rows = []
        ring = self.loop.shared
        for _ in range(int(round(seconds * self.settings.rate_hz))):
            self.env.service()
            self.loop.step()
            rows.append(ring.ring[(int(ring.head[0]) - 1) % ring.ring_rows].copy())
        return np.array(rows)

    def close(self):
        self.env.close()
        self.loop.close()


@pytest.fixture
def linkage_rig():
    yield from made_then_ended(LinkageRig)


def test_a_held_chain_falls_onto_the_floor_and_settles_balancing_the_push(linkage_rig):
    r = linkage_rig(env_kwargs={"start": (-0.09, 0.0105, 0.0), "joints": (0.0, 0.0)})
    rows = r.run(4.0)
    L = r.loop
    assert L.model is not None and L.model.is_linkage and L.state_name == "engaged"
    last = rows[-500:]
    # the device feels the floor: the command balances the 0.5 N push and the device is at rest
    assert np.all(last[:, TEL["loop_state"]] == LS["engaged"])
    assert abs(np.mean(last[:, TEL["cmd_fy"]]) - 0.5) < 0.02
    assert np.max(np.abs(last[:, TEL["dev_vy"]])) < 1e-3
    # the held link (the proxy pose in telemetry: its frame origin) rests on the floor
    assert last[-1, TEL["proxy_y"]] == pytest.approx(BAR_W / 2, abs=1.5e-3)
    ps = r.env.last_proxy
    assert len(ps.joint_position) == len(ps.joint_velocity) == len(ps.joint_effort) == 2
    np.testing.assert_allclose(ps.joint_position, L.model.q[3:], atol=1e-4)  # acked <= 17 ms ago, at rest
    np.testing.assert_allclose(ps.proxy_pose, L.model.joint_state(np.zeros(6))[0], atol=1e-4)  # the root frame
    assert L.update_errors == 0 and L.faults_total == 0


@pytest.mark.parametrize("send_joints", [True, False])
def test_engine_joint_positions_keep_the_proxy_out_of_the_floor(linkage_rig, send_joints):
    """The engine's chain is held out of the floor (a rigid engine). With its joint positions
    the server places the features on the engine's links and the proxy stays on the floor;
    without them (a 1.0 client: the paper's eq. 1) every update forgives the proxy's penetration
    and the pushed proxy creeps in."""
    r = linkage_rig(env_kwargs={"start": (-0.09, 0.0105, 0.0), "joints": (0.0, 0.0), "rigid": True,
                                "send_joints": send_joints})
    rows = r.run(3.0)
    y_end = rows[-1, TEL["proxy_y"]]
    if send_joints:
        assert y_end > BAR_W / 2 - 1.5e-3
        assert abs(np.mean(rows[-300:, TEL["cmd_fy"]]) - 0.5) < 0.05
    else:
        assert y_end < BAR_W / 2 - 5e-3


def test_a_hello_the_model_cannot_hold_is_refused_by_name():
    s = make_settings(model={"tool": "linkage"})
    clock = SimClock(start_ns=1_000_000_000)
    loop = HapticLoop.build(s, clock=clock, device=PointDevice(period_s=1e-3))
    tr = open_transport(s["transport"]["url"], "client")
    try:
        links = bar_links(3)
        links[2]["joint_axis"] = [1.0, 0.0, 0.0]  # turns out of the plane: not a planar linkage
        ep = ClientEndpoint(tr.send, Hello(client_nonce=1, tool_kind=ToolKind.LINKAGE, mass_kg=0.24, max_contacts=8,
                                           links=links, held_link=2))
        loop.start()  # (what waited before start() is dropped: stale by then)
        ep.start(clock.now_ns())
        for _ in range(50):
            loop.step()
            while (item := tr.recv()) is not None:
                ep.receive(item[0], item[1], clock.now_ns())
            if ep.reject is not None:
                break
        assert ep.reject is not None and ep.reject.code == ErrorCode.INVALID_HELLO
        assert "links[2].axis" in ep.reject.reason
    finally:
        tr.close()
        loop.close()


def test_config_linkage_rules():
    assert make_settings(model={"tool": "linkage"}).tool_kind == "linkage"
    assert make_settings(model={"tool": "linkage"}, device={"kind": "spatial"})["device"]["kind"] == "spatial"
    with pytest.raises(cfg.ConfigError, match="model.tool"):
        make_settings(model={"tool": "linkage"}, device={"kind": "1dof"})
    with pytest.raises(cfg.ConfigError, match="controller.type"):
        make_settings(model={"tool": "linkage"}, controller={"type": "direct"})
    with pytest.raises(cfg.ConfigError, match="model.linkage_dynamics"):
        make_settings(model={"tool": "linkage", "linkage_dynamics": "approximate"})
    assert make_settings(model={"tool": "linkage", "linkage_dynamics": "paper"})["model"]["linkage_dynamics"] == "paper"
    assert math.isfinite(BAR_L)


def test_the_daemon_accepts_a_linkage_on_the_configured_device():
    from hapticproxy.server.daemon import _check_device

    _check_device(make_settings(model={"tool": "linkage"}))  # the sim driver builds the planar device
    _check_device(make_settings(model={"tool": "linkage"}, device={"kind": "spatial"}))


def test_a_diverging_chain_fades_as_the_fault_policy_says(linkage_rig):
    """lifecycle.FAULT_POLICY "diverged" for a linkage (its own kernel): the divergence watch's
    signature injected on a resting chain, the force fades from that step, latched."""
    from hapticproxy.server.lifecycle import Fault
    from hapticproxy.server.model.layout import DIVERGE_STEPS, K_OSC_RUN, S_QD, S_QDP

    r = linkage_rig(env_kwargs={"start": (-0.09, 0.0105, 0.0), "joints": (0.0, 0.0)})
    r.run(3.0)
    assert r.loop.state_name == "engaged"
    _, st, _, _, cnt = r.loop.model.arrays()
    st[S_QD + 1] = 0.01
    st[S_QDP + 1] = -0.01
    cnt[K_OSC_RUN] = DIVERGE_STEPS - 1
    rows = r.run(0.5)
    assert r.loop.state_name == "fault" and r.loop.fault == Fault.DIVERGED
    fy = rows[:, TEL["cmd_fy"]]
    assert fy[0] > 0.4 and np.all(np.abs(np.diff(fy)) <= r.loop.ctrl.force_rate_n_per_step + 1e-9)
    assert fy[-1] == 0.0 and not r.device.fault
