"""The device's buttons and gripper reach the engine (issue 30, section 3): the state row's input
columns, filled by every driver (the sim's button and gripper scripts, the vendor drivers on
their emulators, the remote link in both STATE layouts), and the ProxyState fields of protocol 1.3
that carry them (the codec and the egress kernel the same bytes, the loop's acknowledgement)."""
from __future__ import annotations

import importlib.util
import math

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hapticproxy.protocol import devlink as dl
from hapticproxy.protocol.codec import Codec, ProxyState
from hapticproxy.protocol.messages import INPUT_BUTTONS, INPUT_GRIPPER, INPUT_GRIPPER_RATE, device_inputs_fields
from hapticproxy.server.devices.base import DEV_NSTATE, DS_BUTTONS, DS_GRIPPER, DS_GRIPPER_RATE, empty_state
from hapticproxy.server.devices.sim import make_sim_device
from hapticproxy.server.egress import ProxyStatePacker

BUTTONS = [[0.0, 0], [0.1, 1], [0.2, 3], [0.3, 0]]
GRIPPER = [[0.0, 0.1], [0.2, 0.5], [0.4, 0.3]]


def _sim(kind="planar", **hand):
    d = make_sim_device({"kind": kind, "watchdog_s": 0.0, "hand": {"type": "none", "start": "server", **hand}},
                        period_s=1e-3)
    d.enable()
    return d


def _run(d, seconds):
    row = np.zeros(DEV_NSTATE)
    out = []
    for _ in range(int(round(seconds / 1e-3))):
        d.write(np.zeros(6))
        d.read(row)
        out.append(row.copy())
    return np.array(out)


# ------------------------------------------------------------------------------ the sim's scripts
def test_the_sims_button_and_gripper_scripts_fill_the_rows_inputs():
    rows = _run(_sim(buttons=BUTTONS, gripper=GRIPPER), 0.5)
    t = rows[:, 19]
    b = rows[:, DS_BUTTONS]
    for t0, mask in BUTTONS:
        held = b[(t >= t0 + 1e-9) & (t < t0 + 0.1 - 1e-9)]
        assert held.size and np.all(held == mask), (t0, mask)
    g, gr = rows[:, DS_GRIPPER], rows[:, DS_GRIPPER_RATE]
    at = np.interp(t, [r[0] for r in GRIPPER], [r[1] for r in GRIPPER])
    np.testing.assert_allclose(g, at, atol=1e-12)                       # piecewise linear
    assert gr[t < 0.2 - 1e-9] == pytest.approx(2.0) and gr[(t > 0.2) & (t < 0.4 - 1e-9)] == pytest.approx(-1.0)
    assert np.all(gr[t >= 0.4] == 0.0) and np.all(g[t >= 0.4] == 0.3)  # the last angle, at rest


def test_without_scripts_the_sim_has_no_buttons_and_no_gripper():
    d = _sim()
    rows = _run(d, 0.01)
    assert np.all(np.isnan(rows[:, DS_BUTTONS:])), "NaN: not reported"
    info = d.info
    assert (info.buttons, info.gripper, "gripper" in info.sensed) == (0, False, False)
    d2 = _sim(buttons=[[0.0, 0], [0.1, 1 << 5]], gripper=[[0, 0.2]])
    assert (d2.info.buttons, d2.info.gripper, "gripper" in d2.info.sensed) == (6, True, True)
    assert d2.info.moving_mass_kg == pytest.approx(0.4)


def test_the_scripts_wait_for_the_engagement_like_the_hand():
    d = make_sim_device({"kind": "planar", "watchdog_s": 0.0,
                         "hand": {"type": "none", "buttons": [[0.0, 1]], "gripper": [[0.0, 0.2], [0.1, 0.4]]}},
                        period_s=1e-3)
    d.enable()
    rows = _run(d, 0.05)
    assert np.all(rows[:, DS_BUTTONS] == 0.0) and np.all(rows[:, DS_GRIPPER] == 0.2)  # nothing pressed yet
    d.on_engage()
    rows = _run(d, 0.05)
    assert np.all(rows[:, DS_BUTTONS] == 1.0) and rows[-1, DS_GRIPPER] > 0.2


@pytest.mark.parametrize("key, rows, why", [
    ("buttons", [[0.0, -1]], "integer in [0"),
    ("buttons", [[0.0, 1.5]], "integer in [0"),
    ("buttons", [[0.0, 1 << 32]], "integer in [0"),
    ("buttons", [[0.1, 1], [0.1, 0]], "increase strictly"),
    ("gripper", [[0.0, 4.0]], "<= 3.14159"),
    ("gripper", [[0.0]], "expected [t_s, angle_rad]"),
    ("buttons", 3, "expected a list"),
])
def test_bad_scripts_are_refused_naming_the_key(key, rows, why):
    with pytest.raises(ValueError, match=r"device\.hand\." + key) as e:
        make_sim_device({"kind": "planar", "hand": {"type": "none", key: rows}}, period_s=1e-3)
    assert why in str(e.value)


# ------------------------------------------------------------------------------- vendor drivers
_needs = {m: importlib.util.find_spec(m) is None for m in ("forcedimension_core", "pyOpenHaptics", "websockets")}


@pytest.mark.skipif(_needs["forcedimension_core"], reason="forcedimension-core is not installed")
def test_forcedimension_buttons_and_gripper_angle_and_rate_reach_the_row():
    from hapticproxy.testing.emulators.harness import ForceDimensionHarness

    h = ForceDimensionHarness(system_type=35, hand={"type": "none", "start": "server", "buttons": [[0.0, 2]],
                                                    "gripper": [[0.0, 0.1], [1.0, 0.6]]})   # an omega.7
    try:
        for _ in range(50):
            h.step(np.zeros(6))
        r = h.row
        assert r[DS_BUTTONS] == 2.0 and h.driver.buttons == 2
        assert 0.1 < r[DS_GRIPPER] < 0.6 and r[DS_GRIPPER_RATE] == pytest.approx(0.5)
    finally:
        h.close()
    h = ForceDimensionHarness(system_type=33)   # an omega.3: buttons, no gripper
    try:
        h.block["buttons"] = 1.0
        h.step(np.zeros(6))
        assert h.row[DS_BUTTONS] == 1.0 and np.isnan(h.row[DS_GRIPPER]) and np.isnan(h.row[DS_GRIPPER_RATE])
    finally:
        h.close()


@pytest.mark.skipif(_needs["pyOpenHaptics"], reason="pyopenhaptics is not installed")
def test_touch_buttons_reach_the_row_and_it_has_no_gripper():
    from hapticproxy.testing.emulators.harness import TouchHarness

    h = TouchHarness()
    try:
        h.block["buttons"] = 3.0
        h.step(np.zeros(6))
        h.step(np.zeros(6))
        assert h.row[DS_BUTTONS] == 3.0 and np.all(np.isnan(h.row[DS_GRIPPER:]))
    finally:
        h.close()


@pytest.mark.skipif(_needs["websockets"], reason="websockets is not installed")
@pytest.mark.parametrize("versegrip", [True, False])
def test_haply_buttons_are_the_versegrips_or_none(versegrip):
    from hapticproxy.testing.emulators.harness import HaplyServiceHarness

    h = HaplyServiceHarness(versegrip=versegrip)
    try:
        h.driver.enable()
        h.block["buttons"] = 5.0
        for _ in range(3):
            h.step(np.zeros(6))
        if versegrip:
            assert h.row[DS_BUTTONS] == 5.0
        else:
            assert np.isnan(h.row[DS_BUTTONS])
        assert np.all(np.isnan(h.row[DS_GRIPPER:]))
    finally:
        h.close()


# --------------------------------------------------------------------------------- remote link
def _link(sim_hand):
    from hapticproxy.protocol.transport import open_transport
    from hapticproxy.server.devices.remote import DeviceProgram, RemoteDevice
    from hapticproxy.server.devices.sim import limits_of, LimitsPlanar

    name = f"mem://devlink-inputs-{id(sim_hand)}"
    srv_tr = open_transport(name, "server")
    cli_tr = open_transport(name, "client")
    clock = [1_000_000_000]
    now = lambda: clock[0]  # noqa: E731
    srv = RemoteDevice(kind="planar", limits=limits_of(LimitsPlanar(), np.array([-.2, -.2, 0.]), np.array([.2, .2, 0.])),
                       transport=srv_tr, clock_ns=now)
    sim = make_sim_device({"kind": "planar", "watchdog_s": 0.0, "hand": sim_hand}, period_s=1e-3, clock_ns=now)
    prog = DeviceProgram(sim, transport=cli_tr, clock_ns=now)
    return srv, prog, clock


@pytest.mark.parametrize("with_inputs", [True, False])
def test_the_remote_link_carries_the_inputs_in_state_v2_and_a_device_without_sends_v1(with_inputs):
    hand = {"type": "none", "start": "server", **({"buttons": [[0.0, 6]], "gripper": [[0.0, 0.25]]} if with_inputs
                                                   else {})}
    srv, prog, clock = _link(hand)
    try:
        assert prog._layout is (dl.STATE if with_inputs else dl.STATE_V1)
        row = empty_state()
        for _ in range(5):
            clock[0] += 1_000_000
            prog.tick()
            srv.read(row)
        assert srv.counters()["states"] >= 3 and srv.counters()["malformed"] == 0
        if with_inputs:
            assert row[DS_BUTTONS] == 6.0 and row[DS_GRIPPER] == 0.25 and row[DS_GRIPPER_RATE] == 0.0
        else:
            assert np.all(np.isnan(row[DS_BUTTONS:]))   # version 1: the inputs are not known
        assert np.isfinite(row[:13]).all()
    finally:
        prog.close()
        srv.close()


def test_a_server_driver_takes_an_old_device_programs_state_v1():
    """An older device program sends STATE version 1 (216 bytes): the pose is taken, the inputs
    are unknown (NaN); a version-1 byte on version 2's size, or the other way round, is not."""
    srv, prog, clock = _link({"type": "none"})
    try:
        row = empty_state()
        base = dict(flags=0, device_session=77, server_session=0, epoch=0, period_us=1000, cmd_seq=0, kind=1,
                    fault=0)
        state = empty_state()[:dl.ROW_FLOATS_V1]
        state[0] = 0.012
        peer_send = prog._tr.send
        peer_send(dl.STATE_V1.pack(seq=1, state=state, **base), None)
        srv.read(row)
        assert srv.device_session == 77 and row[0] == 0.012 and np.isnan(row[DS_BUTTONS])
        bad = bytearray(dl.STATE_V1.pack(seq=2, state=state, **base))
        bad[4] = 2
        peer_send(bytes(bad), None)
        bad2 = bytearray(dl.STATE.pack(seq=3, state=np.r_[state, 1.0, 0.1, 0.0], **base))
        bad2[4] = 1
        peer_send(bytes(bad2), None)
        srv.read(row)
        assert srv.counters()["malformed"] == 2 and srv.counters()["states"] == 1
    finally:
        prog.close()
        srv.close()


# --------------------------------------------------------------------------- ProxyState 1.3
POSE = np.array([0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0])
Z6 = np.zeros(6)
J0 = np.zeros(0)


def _encode(codec, inputs, **kw):
    return codec.encode_proxy_state(5, 9, 3, 2, 0.5, POSE, Z6, Z6, J0, J0, J0, 2, epsilon_m=0.01, lead_s=0.02,
                                    inputs=inputs, **kw)


def test_the_inputs_reach_proxy_state_and_decode():
    c = Codec()
    ps = c.decode(_encode(c, np.array([5.0, 0.3, -0.1])))
    assert (ps.buttons, ps.gripper_angle_rad, ps.gripper_velocity_rad_per_s, ps.device_inputs) == (5, 0.3, -0.1, 7)
    ps = c.decode(_encode(c, np.array([np.nan, np.nan, np.nan])))
    assert (ps.buttons, ps.gripper_angle_rad, ps.gripper_velocity_rad_per_s, ps.device_inputs) == (0, 0.0, 0.0, 0)
    ps = c.decode(_encode(c, None))
    assert ps.device_inputs == 0
    # the message round trip keeps them (encode(msg) goes through the same rule)
    again = c.decode(c.encode(ProxyState(seq=4, ack_seq=1, server_time_s=0.0, proxy_pose=POSE, proxy_twist=Z6,
                                         wrench=Z6, buttons=9, gripper_angle_rad=0.2, device_inputs=INPUT_BUTTONS
                                         | INPUT_GRIPPER, session_id=5, token=9)))
    assert (again.buttons, again.gripper_angle_rad, again.device_inputs) == (9, 0.2, 3)


def test_a_12_peer_and_a_12_packet_still_understand_each_other():
    new, old = Codec(), Codec(minor=2)
    pkt = _encode(new, np.array([1.0, 0.1, 0.0]))
    ps = old.decode(pkt)                     # a 1.3 packet read by the same declarations: every field
    assert ps.buttons == 1
    obj = msgpack.unpackb(pkt)
    legacy = msgpack.packb(obj[:17])         # what a 1.2 server sends: no inputs
    ps = new.decode(legacy)
    assert (ps.buttons, ps.device_inputs, ps.unknown_fields) == (0, 0, 0)
    pkt_12 = _encode(old, np.array([1.0, 0.1, 0.0]))
    assert len(msgpack.unpackb(pkt_12)) == 17 and msgpack.unpackb(pkt_12)[1] == 2  # a 1.2 codec writes none


def test_invalid_inputs_on_the_wire_are_refused_by_the_decoder():
    c = Codec()
    obj = msgpack.unpackb(_encode(c, np.array([1.0, 0.1, 0.0])))
    for i, v, field in ((17, 1 << 40, "buttons"), (17, -1, "buttons"), (18, math.nan, "gripper_angle_rad"),
                        (20, 300, "device_inputs")):
        bad = list(obj)
        bad[i] = v
        out = c.try_decode(msgpack.packb(bad))
        assert not isinstance(out, ProxyState) and out.field == field, (field, out)


def test_device_inputs_fields_rule():
    assert device_inputs_fields([3.0, 0.5, 1.0]) == (3, 0.5, 1.0, 7)
    assert device_inputs_fields([np.nan, 0.5, np.nan]) == (0, 0.5, 0.0, INPUT_GRIPPER)
    assert device_inputs_fields([-1.0, np.inf, 2e9]) == (0, 0.0, 0.0, 0)          # out of range: not reported
    assert device_inputs_fields([4294967295.0, -1e9, 1e9]) == (4294967295, -1e9, 1e9, 7)  # the bounds are in
    assert device_inputs_fields([4294967296.0, 0.0, 0.0])[3] == INPUT_GRIPPER | INPUT_GRIPPER_RATE


_value = st.one_of(st.floats(allow_nan=True, allow_infinity=True, width=64),
                   st.integers(0, (1 << 33)).map(float), st.sampled_from([0.0, -0.0, 4294967295.0, 4294967296.0]))


@settings(max_examples=300, deadline=None)
@given(b=_value, g=_value, gr=_value, minor=st.sampled_from([2, 3]))
def test_the_egress_kernel_packs_the_inputs_as_the_codec_does(b, g, gr, minor):
    inputs = np.zeros(DEV_NSTATE)[DS_BUTTONS:DS_BUTTONS + 3]   # as the loop passes them: a view of its row
    inputs[:] = (b, g, gr)
    fast = Codec(minor=minor, proxy_state_packer=ProxyStatePacker(4))
    plain = Codec(minor=minor)
    a = _encode(fast, inputs, trusted=True)
    c = _encode(plain, inputs)
    assert a == c
    assert fast._ps_packer.packed == 1


# ------------------------------------------------------------------------------ the loop's ack
def test_the_loops_acknowledgement_carries_the_sims_buttons_and_gripper(rig_factory):
    from server_harness import make_settings

    from hapticproxy.server.devices.base import load_device

    s = make_settings(device={"kind": "planar", "watchdog_s": 0.0,
                              "hand": {"type": "constant", "wrench": [0.0, -0.5, 0.0], "start": "server",
                                       "buttons": [[0.0, 0], [0.4, 1], [0.8, 3]], "gripper": [[0.0, 0.1], [2.0, 0.5]]}})
    dev = load_device("sim", s["device"], period_s=1e-3)
    r = rig_factory(settings=s, device=dev)
    seen = []
    r.run(1.2, on_step=lambda i: seen.append((r.loop.dev[DS_BUTTONS], r.env.last_proxy)))
    states = [ps for _, ps in seen if ps is not None]
    assert states and all(ps.device_inputs == 7 for ps in states)
    masks = [ps.buttons for ps in states]
    assert masks[0] == 0 and 1 in masks and masks[-1] == 3 and masks == sorted(masks)
    last = states[-1]
    assert 0.1 < last.gripper_angle_rad < 0.5 and last.gripper_velocity_rad_per_s == pytest.approx(0.2)
