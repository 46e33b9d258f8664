"""An engine's energy grant (ContactUpdate.work_on_tool_j, 1.4) reaches the passivity layer's
tank through the real protocol and the loop, in simulated time; a server configured without
grants ignores it."""
from __future__ import annotations

import pytest

from server_harness import WallEnv

from hapticproxy.server import control as ctl
from hapticproxy.server import passivity as pv

GRANT_J = 0.0005


class GrantingWallEnv(WallEnv):
    def _send(self, now):
        k, p, n, d, v = self.contacts()
        self.ep.send_contacts(now, now * 1e-9, self.pose, k, p, n, d, v, work_on_tool_j=GRANT_J)


@pytest.mark.parametrize("grants", [True, False])
def test_each_applied_updates_grant_feeds_the_tank(rig_factory, grants):
    r = rig_factory(passivity={"enabled": True, "engine_grants": grants, "max_tank_j": 1.0})
    r.env.close()
    r.env = GrantingWallEnv(r.settings["transport"]["url"], r.clock, start_pose=(0.0, 0.011, 0.0))
    r.run(1.0, record=False)
    ps = r.loop.proto
    ts = r.loop.ctrl.ts
    applied = ps.updates
    assert applied > 30
    if grants:
        # every update after the one that engaged (which has no previous update to be "since")
        assert ts[pv.TS_GRANTED] == pytest.approx(GRANT_J * (applied - 1), rel=1e-9)
        assert ps.granted_j == pytest.approx(ts[pv.TS_GRANTED])
    else:
        assert ts[pv.TS_GRANTED] == 0.0
    assert r.loop.ctrl.cs[ctl.CS_TANK + pv.TS_TANK] <= 1.0
