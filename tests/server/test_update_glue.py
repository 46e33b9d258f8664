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


@pytest.mark.parametrize("kind", ["1dof", "planar", "spatial"])
def test_every_column_of_every_update_reaches_the_model(kind):
    clock = SimClock(start_ns=1_000_000_000)
    s = make_settings(device={"driver": "sim", "kind": kind})
    dev = load_device("sim", dict(s["device"]), period_s=1e-3, clock_ns=clock.now_ns)
    r = Rig(s, dev, clock=clock)
    r.env.close()
    r.env = MovingFloorEnv(s["transport"]["url"], clock, kind=kind, start_pose=(0.0, 0.011, 0.0), epsilon=0.005)
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
