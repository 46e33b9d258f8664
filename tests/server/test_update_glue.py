"""The loop hands the model exactly what each ContactUpdate carried. An injected bug that zeroed
``v_constr`` on every update after the first once passed every loop, fault and experiment test:
this compares, after every applied update, each live contact in the model's store with the
update that set it (key, normal, reported separation, constraint velocity), for every rigid
tool kind, with values that change from update to update."""
from __future__ import annotations

import numpy as np
import pytest
from server_harness import PointDevice, Rig, WallEnv, make_settings

from hapticproxy.server.clock import SimClock
from hapticproxy.server.devices.base import load_device
from hapticproxy.server.model.layout import C_D, C_N, C_VC, CI_KEY, K_M


class MovingFloorEnv(WallEnv):
    """The harness's floor, with a constraint velocity and a depth that change every update."""

    def __init__(self, *a, **kw):
        super().__init__(*a, **kw)
        self.sent = []

    def contacts(self):
        k, p, n, d, v = super().contacts()
        i = self.updates_sent
        v = np.full(len(k), 0.002 * np.sin(0.7 * i) + 0.0005 * np.arange(len(k)))
        d = d + 1e-4 * np.cos(0.3 * i)
        self.sent.append((k.copy(), n.copy(), d.copy(), v.copy()))
        return k, p, n, d, v


def _rig_with(env_class, kind: str) -> Rig:
    """The harness's rig (simulated time, a sim device of ``kind``) with ``env_class`` as its
    environment, its tool 11 mm above the floor."""
    clock = SimClock(start_ns=1_000_000_000)
    s = make_settings(device={"driver": "sim", "kind": kind})
    dev = load_device("sim", dict(s["device"]), period_s=1e-3, clock_ns=clock.now_ns)
    r = Rig(s, dev, clock=clock)
    r.env.close()
    r.env = env_class(s["transport"]["url"], clock, kind=kind, start_pose=(0.0, 0.011, 0.0), epsilon=0.005)
    return r


@pytest.mark.parametrize("kind", ["1dof", "planar", "spatial"])
def test_every_column_of_every_update_reaches_the_model(kind):
    r = _rig_with(MovingFloorEnv, kind)
    try:
        checked = 0
        for _ in range(3000):
            r.env.service()
            u0 = r.loop.updates
            r.loop.step()
            if r.loop.updates == u0 or r.loop.model is None:
                continue
            keys, normal, sep, vc = r.env.sent[r.loop.updates - 1 + (len(r.env.sent) - r.env.updates_sent)]
            par, st, C, CI, cnt = r.loop.model.arrays()
            m = int(cnt[K_M])
            got = {tuple(CI[i, CI_KEY:CI_KEY + 3]): i for i in range(m)}
            for j in range(len(keys)):
                i = got.get(tuple(keys[j]))
                if i is None:
                    continue  # outside the model's capacity / epsilon band: not stored
                assert C[i, C_VC] == vc[j], (kind, "v_constr", C[i, C_VC], vc[j])
                assert C[i, C_D] == sep[j], (kind, "separation", C[i, C_D], sep[j])
                np.testing.assert_array_equal(C[i, C_N:C_N + 3], normal[j])
                checked += 1
        assert checked > 100
    finally:
        r.close()


class BurstyFloorEnv(WallEnv):
    """The harness's floor at 60 Hz, but every fourth update is followed one haptic step later by
    another: that one arrives while the loop applies the first. Records the ack_seq of every
    ProxyState it gets."""

    def __init__(self, *a, **kw):
        super().__init__(*a, **kw)
        self.acked = []

    def _follow(self, ps):
        self.acked.append(ps.ack_seq)
        super()._follow(ps)

    def _next_ns(self, now):
        return now + (1_000_000 if self.updates_sent % 4 == 1 else int(1e9 / self.rate_hz))


@pytest.mark.parametrize("kind", ["planar", "spatial"])
def test_an_update_is_applied_and_acknowledged_in_steps_without_housekeeping(kind):
    """An update received in one step is staged in the next, and the tick of the step after that
    applies it; that step's Python part acknowledges it (ack_seq its seq, even when a newer update
    arrived meanwhile). No step that stages, applies or acknowledges an update runs the loop's
    housekeeping as well (each costs some us of Python: a step paying for two would overrun a
    4 kHz period); housekeeping waits for the next step that handles no update."""
    r = _rig_with(BurstyFloorEnv, kind)
    loop = r.loop
    try:
        applied_seqs, steps = [], []
        for _ in range(3000):
            r.env.service()
            pending, staged = loop._pending, loop._staged
            u0, a0, h0 = loop.updates, loop.acks, loop._hk_n
            loop.step()
            applied, acked, hk = loop.updates != u0, loop.acks != a0, loop._hk_n != h0
            staged_here = pending is not None and loop._staged is pending
            if applied:
                applied_seqs.append(staged.seq)  # (the update staged before this step)
            steps.append((applied, acked, hk, staged_here))
        assert loop.faults_total == 0
        # housekeeping every 10 ms, a few steps later when it waited for a step without an update
        assert len(applied_seqs) > 150 and sum(s[2] for s in steps) >= 0.9 * len(steps) / loop._hk_every
        for i, (applied, acked, hk, staged_here) in enumerate(steps):
            assert acked == applied, (i, steps[i])
            if i > 0 and steps[i - 1][3]:
                assert applied, f"step {i} did not apply the update staged in step {i - 1}"
            assert not ((applied or staged_here) and hk), f"step {i} handled an update and ran housekeeping"
        r.env.service()
        # back-to-back updates happened (one arrived in the step that applied the previous one)
        assert any(b - a == 1 for a, b in zip(applied_seqs, applied_seqs[1:]))
        assert r.env.acked == applied_seqs[:len(r.env.acked)] and len(r.env.acked) >= len(applied_seqs) - 1
        # the kernels did that work (``server/ingest.py``, ``server/egress.py``): every update but
        # the session's first was read whole by the parser, even the one that arrived while its
        # predecessor waited to be applied, and every ProxyState packed by the packer; none of
        # their specialisations compiled after warm_up
        ep = loop.endpoint
        sent = r.env.updates_sent  # (the last may still be in flight)
        assert sent - 2 <= ep._parser.parsed <= sent - 1 and ep._parser.all_held == 0
        assert ep.codec._ps_packer.packed == loop.acks
        from hapticproxy.server.loop import kernels_compiled
        assert kernels_compiled() == loop._kernels_compiled
    finally:
        r.close()


def test_datagrams_that_waited_through_the_warm_up_are_dropped_at_start():
    """A client started before the server sends Hellos while the loop compiles its kernels (a
    minute on a cold cache), from a new socket at each attempt; a session opened for one of
    those would hold the only slot for a peer that is gone. ``start()`` drops them (counted)."""
    from hapticproxy.benchmarks.update_steps import _hello
    from hapticproxy.protocol.session import ClientEndpoint
    from hapticproxy.protocol.transport import open_transport
    from hapticproxy.server.loop import HapticLoop

    clock = SimClock(start_ns=1_000_000_000)
    s = make_settings()
    loop = HapticLoop.build(s, clock=clock)
    stale = [open_transport(s["transport"]["url"], "client") for _ in range(3)]
    try:
        for tr in stale:  # three attempts' Hellos, queued before the loop runs
            ClientEndpoint(tr.send, _hello("planar", 4)).start(clock.now_ns())
        loop.warm_up()
        loop.start()
        assert loop.dropped_at_start == 3
        for _ in range(50):
            loop.step()
        assert not loop.endpoint.sessions  # no session for a peer that is gone
        ep = ClientEndpoint(stale[-1].send, _hello("planar", 4))  # the attempt that is still there
        ep.start(clock.now_ns())
        for _ in range(5):
            loop.step()
        assert len(loop.endpoint.sessions) == 1 and loop.dropped_at_start == 3
    finally:
        for tr in stale:
            tr.close()
        loop.close()
