"""Issue 13 section 4 (protocol half): the handshake's edge cases, sequence jumps, the scene bounds
granted in Welcome, and contacts the session's tool cannot have. Each refusal is an answer the
client can read (Reject, or Error naming the field), a counter, and nothing reaching the model."""
from __future__ import annotations

import msgpack
import numpy as np
import pytest

from hapticproxy.protocol import messages as M
from hapticproxy.protocol.codec import Codec, Error, Hello, Reject, Welcome
from hapticproxy.protocol.messages import ErrorCode, ToolKind
from hapticproxy.protocol.session import ClientState, ServerConfig

from .test_session import IDENTITY, Loop, contacts, spatial_hello

LINK0 = dict(mass_kg=1.0, com_m=(0.0, 0.0, 0.1), inertia_kg_m2=(0.01, 0.01, 0.02, 0.0, 0.0, 0.0), parent=-1,
             joint_type=0, joint_axis=(1.0, 0.0, 0.0), joint_origin=tuple(IDENTITY))
LINK1 = dict(LINK0, parent=0, joint_type=1, joint_axis=(0.0, 0.0, 1.0), joint_origin=(0.0, 0.0, 0.2, 1.0, 0.0, 0.0, 0.0))


def planar_hello(**kw):
    args = dict(client_nonce=0, engine="planar", tool_kind=ToolKind.PLANAR, mass_kg=0.3,
                inertia_kg_m2=(0.0, 0.0, 1e-3, 0.0, 0.0, 0.0), max_contacts=16)
    args.update(kw)
    return Hello(**args)


def linkage_hello():
    return Hello(client_nonce=0, engine="chain", tool_kind=ToolKind.LINKAGE, mass_kg=2.0, max_contacts=16,
                 links=(LINK0, LINK1), held_link=1)


def replies(loop, cls):
    codec = Codec()
    return [m for d, _ in loop.to_client if isinstance(m := codec.try_decode(d), cls)]


def hello_packet(loop, **fields) -> bytes:
    """The client's Hello with some elements changed (a packet its own encoder would refuse)."""
    loop.client.start(0)
    obj = msgpack.unpackb(loop.to_server.pop()[0])
    for name, value in fields.items():
        index = {"major": 0, "minor": 1, "session_id": 3, "token": 4}.get(name)
        obj[index if index is not None else 5 + M.HELLO.field_index(name)] = value
    return msgpack.packb(obj, use_bin_type=True)


# ----------------------------------------------------------------------------- handshake
def test_a_version_range_containing_our_major_is_accepted():
    loop = Loop(hello=spatial_hello(version_min=(1, 0), version_max=(3, 0)))
    loop.connect()
    assert loop.client.welcome.version == (1, M.PROTOCOL_MINOR)


def test_a_hello_in_another_major_s_layout_whose_range_holds_ours_gets_reject_40_then_its_resend_is_accepted():
    # SPEC 6: the server cannot read a layout it does not speak; its Reject names its range, and
    # the client resends in the highest major both speak.
    loop = Loop(hello=spatial_hello(version_min=(1, 0), version_max=(3, 0)))
    pkt = hello_packet(loop, major=3)
    loop.server.receive(pkt, "env", 0)
    (rej,) = replies(loop, Reject)
    assert rej.code == ErrorCode.UNSUPPORTED_VERSION and rej.version_max == (1, M.PROTOCOL_MINOR)
    assert rej.client_nonce == loop.client.hello.client_nonce
    loop.to_client.clear()
    loop.client.start(0)
    loop.deliver()
    assert loop.client.established


@pytest.mark.parametrize("change", [
    dict(engine="e" * 300),  # longer than max_str_bytes
    dict(session_id=7),  # a Hello carries no session
    dict(token=9),
    dict(mass_kg=-1.0),
])
def test_a_bad_hello_whose_nonce_can_be_read_gets_a_reject(change):
    loop = Loop()
    pkt = hello_packet(loop, **change)
    loop.server.receive(pkt, "env", 0)
    (rej,) = replies(loop, Reject)
    assert rej.code == ErrorCode.INVALID_HELLO and rej.client_nonce == loop.client.hello.client_nonce
    assert list(change)[0] in rej.reason
    assert loop.server.sessions == {} and loop.server.counters.rejects_sent == 1
    loop.deliver()
    assert loop.client.state == ClientState.REJECTED  # the client can read the answer


def test_a_truncated_hello_gets_a_reject():
    loop = Loop()
    loop.client.start(0)
    pkt = loop.to_server.pop()[0]
    cuts = (40, len(pkt) // 2, len(pkt) - 1)
    for cut in cuts:
        loop.server.receive(pkt[:cut], "env", 0)
    rejects = replies(loop, Reject)
    assert len(rejects) == 3 and all(r.code == ErrorCode.INVALID_HELLO for r in rejects)
    assert all(r.client_nonce == loop.client.hello.client_nonce for r in rejects)
    # never longer than what it answers: no amplification
    assert [len(d) <= cut for (d, _), cut in zip(loop.to_client, cuts)] == [True] * 3
    assert loop.server.sessions == {}
    loop.to_client.clear()
    loop.server.receive(pkt[:17], "env", 0)  # the nonce is just readable, a Reject would not fit
    assert loop.to_client == [] and loop.server.counters.errors_suppressed == 1


def test_a_hello_with_nonce_0_is_refused():
    loop = Loop()
    loop.server.receive(hello_packet(loop, client_nonce=0), "env", 0)
    (rej,) = replies(loop, Reject)
    assert rej.code == ErrorCode.INVALID_HELLO and rej.client_nonce == 0 and "client_nonce" in rej.reason
    assert loop.server.sessions == {}


def test_an_unsupported_tool_is_named_as_spec_names_it():
    loop = Loop(ServerConfig(supported_tools=frozenset({ToolKind.PLANAR})))
    loop.client.start(0)
    loop.deliver()
    assert loop.client.reject.code == ErrorCode.UNSUPPORTED_TOOL
    assert "spatial" in loop.client.reject.reason and "SPATIAL" not in loop.client.reject.reason
    assert "planar" in loop.client.reject.reason


def test_a_capped_epsilon_is_said_in_welcome():
    loop = Loop(ServerConfig(max_epsilon_m=0.002), hello=spatial_hello(epsilon_m=0.005))
    loop.connect()
    w = loop.client.welcome
    assert w.epsilon_m == 0.002 and "epsilon_m capped at 0.002 m (requested 0.005 m)" in w.note
    loop2 = Loop(ServerConfig(max_epsilon_m=0.01), hello=spatial_hello(epsilon_m=0.005))
    loop2.connect()
    assert loop2.client.welcome.epsilon_m == 0.005 and loop2.client.welcome.note == ""


def test_welcome_tells_the_scene_bounds_and_an_older_welcome_means_unbounded():
    cfg = ServerConfig(workspace_extent_m=2.0, max_constraint_speed_m_per_s=3.0, max_separation_m=0.1)
    loop = Loop(cfg)
    loop.connect()
    w = loop.client.welcome
    assert (w.workspace_extent_m, w.max_constraint_speed_m_per_s, w.max_separation_m) == (2.0, 3.0, 0.1)
    old = Codec(minor=1).encode(Welcome(client_nonce=1, version=(1, 1), haptic_rate_hz=1000.0, epsilon_m=0.0,
                                        max_contacts=4, heartbeat_interval_s=0.1, silence_timeout_s=1.0,
                                        session_id=1, token=1))
    w11 = Codec().decode(old)
    assert w11.workspace_extent_m == w11.max_separation_m == M.MAX_ABS_FLOAT and w11.note == ""


# ------------------------------------------------------------------------- sequence jumps
def test_a_huge_sequence_number_is_refused_and_later_updates_still_count():
    loop = Loop()
    s = loop.connect()
    c = loop.client
    keys, pos, nor, d, v = contacts(2)
    forged = Codec().encode_contact_update(s.session_id, s.token, 2 ** 64 - 1, 0.0, IDENTITY, keys, pos, nor, d, v)
    assert loop.server.receive(forged, "env", 0) is None
    (err,) = replies(loop, Error)
    assert err.code == ErrorCode.SEQ_JUMP and err.field == "seq" and err.ref_seq == 2 ** 64 - 1
    assert loop.server.counters.seq_jump == 1
    loop.to_client.clear()
    assert loop.send(2) == 1
    updates, _ = loop.deliver()
    assert [u.seq for u in updates] == [1]
    # a jump within the bound is a gap of lost packets, accepted
    c._contact_tx_seq = 1 + loop.server.config.max_seq_jump - 1
    loop.send(2)
    updates, _ = loop.deliver()
    assert len(updates) == 1 and loop.server.counters.seq_jump == 1


# ------------------------------------------------------------------------------ bounds
BOUNDS = ServerConfig(workspace_extent_m=2.0, max_constraint_speed_m_per_s=3.0, max_separation_m=0.1)


@pytest.mark.parametrize("what,value,counter,field", [
    ("position", 2.5, "oob_workspace", "contact_data.position_m"),
    ("position", -1e9, "oob_workspace", "contact_data.position_m"),
    ("pose", 1e9, "oob_workspace", "tool_pose"),
    ("v_constr", 1e9, "oob_speed", "contact_data.v_constr_m_per_s"),
    ("v_constr", -3.5, "oob_speed", "contact_data.v_constr_m_per_s"),
    ("separation", 0.2, "oob_separation", "contact_data.separation_m"),
])
def test_a_contact_update_outside_the_scene_bounds_is_refused_before_the_model(what, value, counter, field):
    loop = Loop(BOUNDS)
    s = loop.connect()
    keys, pos, nor, d, v = contacts(3)
    pos = np.clip(pos, -1.0, 1.0)
    pose = IDENTITY.copy()
    if what == "position":
        pos[1, 2] = value
    elif what == "pose":
        pose[1] = value
    elif what == "v_constr":
        v[2] = value
    else:
        d[0] = value
    loop.client.send_contacts(0, 0.0, pose, keys, pos, nor, d, v)
    updates, _ = loop.deliver()
    assert updates == []
    c = loop.server.counters
    assert getattr(c, counter) == 1 and c.out_of_bounds == 1 and c.unusable == 0 and c.accepted == 0
    assert s.acked_seq == 0
    assert loop.client.last_error.code == ErrorCode.OUT_OF_BOUNDS and loop.client.last_error.field == field
    # within the bounds, the same session goes on
    loop.client.send_contacts(0, 0.0, IDENTITY, keys, np.clip(pos, -1.0, 1.0), nor, np.clip(d, -0.1, 0.1), np.clip(v, -3, 3))
    updates, _ = loop.deliver()
    assert len(updates) == 1 and s.acked_seq == 2


# --------------------------------------------------------------------- unusable contacts
def _send(loop, keys, pos, nor, d, v, joints=None):
    loop.client.send_contacts(0, 0.0, IDENTITY, keys, pos, nor, d, v, tool_joint_position=joints)
    updates, _ = loop.deliver()
    return updates


def test_a_z_normal_on_a_planar_tool_is_refused():
    loop = Loop(hello=planar_hello())
    loop.connect()
    keys, pos, nor, d, v = contacts(3)
    flat = nor.copy()
    flat[:, 2] = 0.0
    flat /= np.linalg.norm(flat, axis=1)[:, None]
    assert len(_send(loop, keys, pos, flat, d, v)) == 1
    assert _send(loop, keys, pos, nor, d, v) == []
    c = loop.server.counters
    assert c.unusable == c.unusable_normal_z == 1
    assert (loop.client.last_error.code, loop.client.last_error.field) == (ErrorCode.UNUSABLE, "contact_data.normal")


def test_a_tool_link_other_than_0_on_a_rigid_tool_is_refused():
    loop = Loop()
    loop.connect()
    keys, pos, nor, d, v = contacts(3)
    keys[2, 0] = 1
    assert _send(loop, keys, pos, nor, d, v) == []
    assert loop.server.counters.unusable_tool_link == 1
    assert loop.client.last_error.field == "contact_keys.tool_link"


def test_joint_positions_for_a_rigid_tool_are_refused():
    loop = Loop()
    loop.connect()
    assert _send(loop, *contacts(2), joints=np.array([0.1])) == []
    assert loop.server.counters.unusable_joints == 1
    assert (loop.client.last_error.code, loop.client.last_error.field) == (ErrorCode.UNUSABLE, "tool_joint_position")


def test_a_linkage_takes_its_own_links_and_joint_count_only():
    loop = Loop(hello=linkage_hello())
    loop.connect()
    keys, pos, nor, d, v = contacts(3)
    keys[:, 0] = [0, 1, 1]
    assert len(_send(loop, keys, pos, nor, d, v, joints=np.array([0.2]))) == 1
    assert len(_send(loop, keys, pos, nor, d, v)) == 1  # joints may be absent (a 1.0 engine)
    keys[0, 0] = 2
    assert _send(loop, keys, pos, nor, d, v) == []
    keys[0, 0] = 0
    assert _send(loop, keys, pos, nor, d, v, joints=np.array([0.2, 0.3])) == []
    c = loop.server.counters
    assert (c.unusable_tool_link, c.unusable_joints, c.unusable) == (1, 1, 2)


def test_refusals_are_counted_as_dropped():
    loop = Loop(BOUNDS)
    loop.connect()
    keys, pos, nor, d, v = contacts(2)
    d[0] = 5.0
    _send(loop, keys, pos, nor, d, v)
    assert loop.server.counters.dropped == 1
