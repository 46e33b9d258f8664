"""Through the server (simulated time, the real protocol over the in-memory transport): a hand
pushes a box onto a floor and the engine's first two updates that carry the floor's contacts
have their normals reversed (issue 28: the model then refused every true normal after them as
"flipped", the proxy fell 250 mm through the floor and the device pulled the hand after it at up
to 10 N). Now the true normals are taken at the next update: the tool stays on the floor, the
device never pulls the hand into it, and the force settles on the push."""
from __future__ import annotations

import numpy as np
from server_harness import PointDevice, WallEnv

from hapticproxy.server.shm import LS, TEL

PUSH = lambda t: (0.0, -0.5, 0.0)  # noqa: E731 - the hand presses down with 0.5 N


class FlippingWallEnv(WallEnv):
    """``WallEnv`` whose updates number ``flip`` (counting those that carry contacts) report the
    floor's normal reversed: the same points and separations."""

    def __init__(self, *a, flip=(0, 1), **kw):
        super().__init__(*a, **kw)
        self.flip = set(flip)
        self.with_contacts = 0
        self.flipped = 0

    def contacts(self):
        keys, pos, nor, sep, vc = super().contacts()
        if len(keys):
            if self.with_contacts in self.flip:
                nor = -nor
                self.flipped += 1
            self.with_contacts += 1
        return keys, pos, nor, sep, vc


def _run(rig_factory, flip):
    r = rig_factory(device=PointDevice(hand=PUSH), env_kwargs={"start_pose": (0.0, 0.013, 0.0)})
    r.env.close()
    r.env = FlippingWallEnv(r.settings["transport"]["url"], r.clock, start_pose=(0.0, 0.013, 0.0), flip=flip)
    rows = r.run(3.0)
    return r, rows


def test_a_pushing_hand_keeps_the_tool_on_the_floor_through_reversed_normals(rig_factory):
    r, rows = _run(rig_factory, flip=(0, 1))
    assert r.env.flipped == 2
    floor_com = r.env.hy                            # the COM of a box resting on y = 0
    engaged = rows[:, TEL["loop_state"]] == LS["engaged"]
    assert engaged[-2000:].all()
    y = rows[engaged, TEL["proxy_y"]]
    fy = rows[:, TEL["cmd_fy"]]
    # no fall: the proxy stays on the floor (pressed in by the push, less than a millimetre)
    assert y.min() > floor_com - 0.001, y.min()
    # no pull: the device never pulls the hand down towards (or through) the floor
    assert fy.min() > -0.05, fy.min()
    # the floor carries the push once settled, and the session refused nothing after the two
    assert abs(np.mean(fy[-500:]) - 0.5) < 0.02
    mc = r.loop.model.counters()
    assert mc["flips_taken"] == 2 and mc["flips_refused"] == 0


def test_without_reversals_the_same_press_settles_the_same(rig_factory):
    """The reference run: the press with true normals throughout ends where the one above does."""
    r, rows = _run(rig_factory, flip=())
    _, flipped_rows = _run(rig_factory, flip=(0, 1))
    assert abs(rows[-1, TEL["proxy_y"]] - flipped_rows[-1, TEL["proxy_y"]]) < 1e-4
    assert r.loop.model.counters()["flips_taken"] == 0
