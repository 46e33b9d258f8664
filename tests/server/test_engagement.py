"""Engagement never kicks the hand, on every device kind, with the worst hand there is.

The worst case for any ramp-in is a hand that keeps pushing as a pure force source: the device
moves freely while the force is still small. Each case engages (first engagement with the hand
already pushing, a re-arm after a device fault, a new client while the previous one's fade is
still running, a client restarted on the same socket) and asserts that within 2 s the force on
the hand never exceeds the steady force (the 0.5 N push) plus 1 N, for a pure force hand and for a
gripping (impedance) hand, on the simulated 1-DOF, planar and spatial devices. Simulated time.
"""
from __future__ import annotations

import numpy as np
import pytest
from server_harness import Rig, WallEnv, make_settings

from hapticproxy.protocol.session import ClientEndpoint
from hapticproxy.server.clock import SimClock
from hapticproxy.server.devices.base import load_device

PUSH_N = 0.5
MARGIN_N = 1.0

HANDS = {
    # reduced coordinates of each kind; the floor's normal is +y (1dof: the device moves along y)
    # start = "server": the hand pushes from the server's start, before any client (the worst case)
    "force": lambda kind: {"type": "constant", "start": "server", "wrench": {"1dof": [-PUSH_N], "planar": [0.0, -PUSH_N, 0.0],
                                                          "spatial": [0.0, -PUSH_N, 0.0, 0.0, 0.0, 0.0]}[kind]},
    # a soft arm gripping the handle and pulling it 5 cm further down: about the same push
    "grip": lambda kind: {"type": "impedance", "start": "server", "stiffness_n_per_m": 10.0, "damping_n_s_per_m": 5.0,
                          "target": {"type": "constant", "pose": {"1dof": [-0.05], "planar": [0.0, -0.05, 0.0],
                                                                  "spatial": [0.0, -0.05, 0.0, 0.0, 0.0, 0.0]}[kind]}},
}


def _device_cfg(kind, hand):
    cfg = {"driver": "sim", "kind": kind, "hand": HANDS[hand](kind)}
    if kind == "1dof":
        cfg.update(axis=[0.0, 1.0, 0.0], workspace_min_m=[-0.3, -0.3, -0.3], workspace_max_m=[0.3, 0.3, 0.3])
    elif kind == "planar":
        cfg.update(workspace_min_m=[-0.3, -0.3], workspace_max_m=[0.3, 0.3])
    else:
        cfg.update(workspace_min_m=[-0.3, -0.3, -0.3], workspace_max_m=[0.3, 0.3, 0.3])
    return cfg


def _rig(kind, hand, **sections):
    clock = SimClock(start_ns=1_000_000_000)
    settings = make_settings(device=_device_cfg(kind, hand), **sections)
    dev = load_device("sim", dict(settings["device"]), period_s=settings.period_ns * 1e-9, clock_ns=clock.now_ns)
    # the engine's tool rests on the floor (y = 0) from the start
    env = {"kind": kind, "start_pose": (0.0, 0.01, 0.0)}
    r = Rig(settings, dev, env, clock=clock)
    return r


class Recorder:
    """The force rendered to the hand: the command the device accepted, every step."""

    def __init__(self, rig):
        self.rig = rig
        self.f = []
        self.hand = []

    def run(self, seconds):
        def on_step(_):
            self.f.append(self.rig.loop.ctrl.cmd[:3].copy())
            self.hand.append(self.rig.loop.dev[13:16].copy())  # the hand's push, as a sensor reads it
        self.rig.run(seconds, record=False, on_step=on_step)

    def peak_since(self, i0):
        return float(np.max(np.linalg.norm(np.asarray(self.f[i0:]), axis=1)))

    def last(self):
        return float(np.linalg.norm(self.f[-1]))


def _assert_no_kick(rec, i0, what, rate_hz=1000.0):
    """Within 2 s of engagement the force stays below the steady force (the mean of the last
    0.5 s of a 3 s run: what the hand is balanced by at rest) plus 1 N; the contact is then at
    rest and rendered (a force that balances a push)."""
    f = np.linalg.norm(np.asarray(rec.f[i0:]), axis=1)
    two_s, half_s = int(2.0 * rate_hz), int(0.5 * rate_hz)
    assert len(f) >= int(3.0 * rate_hz) - 1
    steady = float(np.mean(f[-half_s:]))
    peak = float(np.max(f[:two_s]))
    print(f"{what}: peak {peak:.3f} N, steady {steady:.3f} N")
    hand = np.linalg.norm(np.mean(np.asarray(rec.hand[i0:])[-half_s:], axis=0))
    assert np.ptp(f[-half_s:]) < 0.05, f"{what}: not at rest"
    assert steady > 0.1 and abs(steady - hand) < 0.05, f"{what}: {steady:.3f} N rendered against a {hand:.3f} N push"
    assert peak <= steady + MARGIN_N, f"{what}: peak {peak:.3f} N within 2 s of engagement, steady {steady:.3f} N"
    return peak, steady


KINDS = ("1dof", "planar", "spatial")


def _first_engagement(r, rec):
    r.env.alive = False
    rec.run(0.3)                  # the hand pushes the free device for 0.3 s before any client
    r.env.alive = True


def _rearm_after_a_device_fault(r, rec):
    rec.run(2.0)                  # resting on the floor, pushing
    r.device.disable()            # the device reports a fault (disabled under the loop)
    rec.run(0.5)                  # the hand pushes the dead handle on
    assert r.loop.state_name == "fault"
    assert r.loop.rearm()


def _new_client_while_the_fade_runs(r, rec):
    rec.run(2.0)
    r.env.bye()
    rec.run(0.05)                 # the fade is still running
    old = r.env
    r.env = WallEnv(r.settings["transport"]["url"], r.clock, kind=old.kind, start_pose=(0.0, 0.01, 0.0), seed=2)
    old.close()


def _client_restarted_on_the_same_socket(r, rec):
    rec.run(2.0)
    env = r.env
    # the engine process restarts: same address, a new Hello, its tool back at its start
    env.ep = ClientEndpoint(env.tr.send, env.hello)
    env.started = False
    env.pose[:] = (0.0, 0.01, 0.0, 1.0, 0.0, 0.0, 0.0)


#: what happens before the engagement judged, and the engagements counted by then
CASES = {
    "first engagement": (_first_engagement, 1),
    "re-arm after a device fault": (_rearm_after_a_device_fault, 1),
    "new client while the previous fade runs": (_new_client_while_the_fade_runs, 2),
    "client restarted on the same socket": (_client_restarted_on_the_same_socket, 2),
}


@pytest.mark.parametrize("case", list(CASES))
@pytest.mark.parametrize("hand", list(HANDS))
@pytest.mark.parametrize("kind", KINDS)
def test_an_engagement_never_kicks_the_hand(kind, hand, case):
    prepare, engagements = CASES[case]
    r = _rig(kind, hand)
    try:
        rec = Recorder(r)
        prepare(r, rec)
        i0 = len(rec.f)
        rec.run(3.0)
        assert r.loop.engagements == engagements
        _assert_no_kick(rec, i0, f"{kind}/{hand} {case}")
    finally:
        r.close()
