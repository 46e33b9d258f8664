"""Session layer: handshake, sequence numbers, token/peer checks, timers, Bye, Error, HMAC.

Runs on an in-test loopback (lists of datagrams, explicit clock in ns) so every step is
deterministic; one test runs the same exchange over the project's mem transport.
"""
from __future__ import annotations

import os

import numpy as np
import pytest

from hapticproxy.protocol import messages as M
from hapticproxy.protocol.codec import Codec, ContactUpdate, Heartbeat, Hello, Limits, ProxyState
from hapticproxy.protocol.messages import ErrorCode, ToolKind
from hapticproxy.protocol.session import (
    HMAC_TAG_BYTES,
    ClientConfig,
    ClientEndpoint,
    ClientState,
    MacFramer,
    ServerConfig,
    ServerEndpoint,
    load_hmac_key,
)

MS = 1_000_000
IDENTITY = np.array([0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0])
KEY = bytes(range(32))


class Loop:
    """A server and a client joined by two lists (the 'network')."""

    def __init__(self, server_cfg=None, client_cfg=None, hello=None, server_key=None, client_key=None,
                 client_peer="env"):
        self.to_server: list[tuple[bytes, object]] = []
        self.to_client: list[tuple[bytes, object]] = []
        self.client_peer = client_peer
        self.server = ServerEndpoint(lambda d, p: self.to_client.append((d, p)), server_cfg, hmac_key=server_key)
        self.client = ClientEndpoint(lambda d: self.to_server.append((d, client_peer)),
                                     hello or spatial_hello(), client_cfg, hmac_key=client_key)
        self.now = 0

    def deliver(self, now=None):
        """Deliver everything in flight; returns (updates at the server, states at the client)."""
        if now is not None:
            self.now = now
        updates, states = [], []
        while self.to_server or self.to_client:
            batch, self.to_server = self.to_server, []
            for d, p in batch:
                u = self.server.receive(d, p, self.now)
                if u is not None:
                    updates.append(u)
            batch, self.to_client = self.to_client, []
            for d, _ in batch:
                s = self.client.receive(d, "server", self.now)
                if s is not None:
                    states.append(s)
        return updates, states

    def connect(self):
        self.client.start(self.now)
        self.deliver()
        assert self.client.state == ClientState.ESTABLISHED
        return self.server.sessions[self.client.session_id]

    def send(self, n=2, seed=0):
        return self.client.send_contacts(self.now, 0.01 * self.now / MS, IDENTITY, *contacts(n, seed))


def spatial_hello(**kw):
    args = dict(client_nonce=0, engine="test-engine", tool_kind=ToolKind.SPATIAL, mass_kg=1.0,
                inertia_kg_m2=(0.1, 0.1, 0.1, 0.0, 0.0, 0.0), max_contacts=32, epsilon_m=0.005)
    args.update(kw)
    return Hello(**args)


def contacts(n, seed=0):
    rng = np.random.default_rng(seed)
    nor = rng.normal(size=(n, 3))
    nor /= np.linalg.norm(nor, axis=1)[:, None]
    keys = np.column_stack([np.zeros(n), np.ones(n), np.arange(n)]).astype(np.int64)
    return keys, rng.normal(size=(n, 3)), nor, rng.normal(size=n) * 1e-3, np.zeros(n)


def test_handshake_grants_and_ack_round_trip():
    loop = Loop(ServerConfig(max_epsilon_m=0.002, max_contacts=16, haptic_rate_hz=512.0))
    s = loop.connect()
    w = loop.client.welcome
    assert (w.version, w.haptic_rate_hz, w.epsilon_m, w.max_contacts) == ((1, M.PROTOCOL_MINOR), 512.0, 0.002, 16)
    assert s.peer == "env" and s.token == loop.client.token != 0 and s.hello.engine == "test-engine"
    assert loop.server.counters.sessions_opened == 1 and loop.server.counters.welcomes_sent == 1
    seq = loop.send(3)
    updates, _ = loop.deliver()
    assert seq == 1 and len(updates) == 1 and isinstance(updates[0], ContactUpdate)
    assert updates[0].session_id == s.session_id and updates[0].n_contacts == 3
    assert loop.server.send_proxy_state(s.session_id, loop.now, IDENTITY, np.zeros(6), np.arange(6.0))
    _, states = loop.deliver()
    assert len(states) == 1 and isinstance(states[0], ProxyState)
    assert states[0].ack_seq == 1 and states[0].seq == 1
    np.testing.assert_array_equal(states[0].wrench, np.arange(6.0))
    assert loop.server.counters.dropped == 0 and loop.client.counters.dropped == 0


def test_lost_welcome_is_repeated_for_the_same_hello():
    loop = Loop()
    loop.client.start(0)
    loop.server.receive(*loop.to_server.pop(), 0)
    loop.to_client.clear()  # the Welcome is lost
    loop.client.poll(100 * MS)  # before hello_retry_s: nothing
    assert loop.to_server == []
    loop.client.poll(300 * MS)  # retry
    loop.deliver(300 * MS)
    assert loop.client.established
    assert len(loop.server.sessions) == 1 and loop.server.counters.hello_repeats == 1
    assert loop.client.counters.hellos_sent == 2


def test_client_gives_up_after_hello_attempts():
    loop = Loop(client_cfg=ClientConfig(hello_attempts=2, hello_retry_s=0.1))
    loop.client.start(0)
    loop.to_server.clear()
    loop.client.poll(100 * MS)
    loop.to_server.clear()
    loop.client.poll(200 * MS)
    assert loop.client.state == ClientState.CLOSED and loop.client.counters.hellos_sent == 2


@pytest.mark.parametrize("hello_kw,server_cfg,code", [
    (dict(version_min=(2, 0), version_max=(3, 1)), None, ErrorCode.UNSUPPORTED_VERSION),
    (dict(units="imperial"), None, ErrorCode.UNSUPPORTED_UNITS),
    (dict(), ServerConfig(supported_tools=frozenset({ToolKind.PLANAR})), ErrorCode.UNSUPPORTED_TOOL),
    (dict(mass_kg=-1.0), None, ErrorCode.INVALID_HELLO),
])
def test_rejects(hello_kw, server_cfg, code):
    loop = Loop(server_cfg)
    hello = spatial_hello(**{k: v for k, v in hello_kw.items() if k != "mass_kg"})
    loop.client.hello = hello
    loop.client.start(0)
    if "mass_kg" in hello_kw:  # an invalid Hello the client's own encoder would refuse: forge it
        import msgpack
        obj = msgpack.unpackb(loop.to_server[0][0])
        obj[5 + M.HELLO.field_index("mass_kg")] = hello_kw["mass_kg"]
        loop.to_server[0] = (msgpack.packb(obj), "env")
    loop.deliver()
    assert loop.client.state == ClientState.REJECTED
    assert loop.client.reject.code == code and loop.client.reject.reason
    assert loop.server.sessions == {} and loop.server.counters.rejects_sent == 1


def test_unknown_major_hello_is_rejected_with_the_server_range():
    import msgpack
    loop = Loop()
    loop.client.start(0)
    obj = msgpack.unpackb(loop.to_server[0][0])
    obj[0] = 2
    obj[6:8] = [[2, 0], [2, 5]]
    obj[8:] = ["v2 body"]
    loop.to_server[0] = (msgpack.packb(obj), "env")
    loop.deliver()
    assert loop.client.state == ClientState.REJECTED
    assert loop.client.reject.code == ErrorCode.UNSUPPORTED_VERSION
    assert loop.client.reject.version_max == (M.PROTOCOL_MAJOR, M.PROTOCOL_MINOR)
    assert loop.server.codec.counters.unknown_major == 1


def test_server_full_and_restarted_client():
    loop = Loop()
    loop.connect()
    other = ClientEndpoint(lambda d: loop.to_server.append((d, "intruder")), spatial_hello())
    other.start(0)
    for d, p in loop.to_server:
        loop.server.receive(d, p, 0)
    loop.to_server.clear()
    other.receive(loop.to_client.pop()[0], "server", 0)
    assert other.state == ClientState.REJECTED and other.reject.code == ErrorCode.SERVER_FULL
    # Same peer, new nonce: the client restarted, the old session goes.
    old = loop.client.session_id
    loop.client.start(0)
    loop.deliver()
    assert loop.client.established and old not in loop.server.sessions and len(loop.server.sessions) == 1


def test_newest_wins_stale_and_duplicate_contact_updates():
    loop = Loop()
    loop.connect()
    packets = []
    for i in range(5):
        loop.send(2, seed=i)
        packets.append(loop.to_server.pop())
    srv = loop.server
    order = [0, 2, 1, 2, 4, 3, 4]  # reordered and repeated
    accepted = [u.seq for d, p in (packets[i] for i in order) if (u := srv.receive(d, p, 0)) is not None]
    assert accepted == [1, 3, 5]
    c = srv.counters
    assert (c.stale, c.duplicate, c.lost) == (2, 2, 2)
    assert srv.sessions[loop.client.session_id].acked_seq == 5


def test_newest_wins_on_the_client_and_ack_of_unsent_seq():
    loop = Loop()
    s = loop.connect()
    loop.send(1)
    loop.deliver()
    for _ in range(3):
        loop.server.send_proxy_state(s.session_id, 0, IDENTITY, np.zeros(6), np.zeros(6))
    p1, p2, p3 = loop.to_client
    loop.to_client.clear()
    got = [loop.client.receive(d, "server", 0) for d in (p2[0], p1[0], p2[0], p3[0])]
    assert [g.seq if g else None for g in got] == [2, None, None, 3]
    assert loop.client.counters.stale == 1 and loop.client.counters.duplicate == 1
    # A ProxyState acknowledging a ContactUpdate the client never sent is dropped.
    s.contact_seq.newest = 99
    loop.server.send_proxy_state(s.session_id, 0, IDENTITY, np.zeros(6), np.zeros(6))
    _, states = loop.deliver()
    assert states == [] and loop.client.counters.unexpected == 1


def test_wrong_token_unknown_session_and_wrong_peer_are_dropped_and_counted():
    loop = Loop()
    s = loop.connect()
    codec = Codec()
    good = dict(seq=7, env_time_s=0.0, tool_pose=IDENTITY)
    keys, pos, nor, d, v = contacts(2)
    bad_token = codec.encode_contact_update(s.session_id, s.token ^ 1, 7, 0.0, IDENTITY, keys, pos, nor, d, v)
    unknown = codec.encode_contact_update(s.session_id ^ 1, s.token, 7, 0.0, IDENTITY, keys, pos, nor, d, v)
    genuine = codec.encode_contact_update(s.session_id, s.token, 7, 0.0, IDENTITY, keys, pos, nor, d, v)
    srv = loop.server
    assert srv.receive(bad_token, "env", 0) is None
    assert srv.receive(unknown, "env", 0) is None
    assert srv.receive(genuine, "elsewhere", 0) is None  # right token, other source address
    c = srv.counters
    assert (c.bad_token, c.unknown_session, c.wrong_peer) == (1, 1, 1)
    assert loop.to_client == []  # no replies to unauthenticated packets
    assert srv.sessions[s.session_id].acked_seq == 0  # nothing reached the model
    assert srv.receive(genuine, "env", 0).seq == 7
    del good


def test_client_drops_server_packets_with_wrong_token_or_peer():
    loop = Loop()
    s = loop.connect()
    forged = Codec().encode(Heartbeat(seq=1, time_s=0.0, session_id=s.session_id, token=s.token ^ 5))
    loop.client.receive(forged, "server", 0)
    real = Codec().encode(Heartbeat(seq=1, time_s=0.0, session_id=s.session_id, token=s.token))
    loop.client.receive(real, "someone-else", 0)
    assert loop.client.counters.bad_token == 1 and loop.client.counters.wrong_peer == 1
    assert loop.client.counters.accepted == 1  # only the Welcome


def test_invalid_packets_in_a_session_get_rate_limited_errors():
    loop = Loop(ServerConfig(error_rate_per_s=2.0))
    s = loop.connect()
    keys, pos, nor, d, v = contacts(2)
    nor = nor.copy()
    nor[0] *= 2.0  # not unit
    bad = Codec().encode_contact_update(s.session_id, s.token, 1, 0.0, IDENTITY, keys, pos, nor, d, v)
    for _ in range(5):
        assert loop.server.receive(bad, "env", 0) is None
    errors = list(loop.to_client)
    assert len(errors) == 2 and loop.server.counters.errors_suppressed == 3
    loop.deliver()
    assert loop.client.last_error.code == ErrorCode.NOT_UNIT and loop.client.last_error.ref_seq == 1
    assert loop.client.last_error.field.startswith("contact_data")
    assert loop.server.codec.counters.not_unit == 5 and loop.server.counters.decode_errors == 5
    # The bucket refills with time.
    loop.server.receive(bad, "env", 1000 * MS)
    assert len(loop.to_client) == 1
    # From another peer: no reply at all.
    loop.to_client.clear()
    loop.server.receive(bad, "elsewhere", 5000 * MS)
    assert loop.to_client == []


def test_capacity_granted_is_enforced():
    loop = Loop(ServerConfig(max_contacts=4))
    s = loop.connect()
    with pytest.raises(ValueError, match="granted"):
        loop.send(5)
    over = Codec().encode_contact_update(s.session_id, s.token, 1, 0.0, IDENTITY, *contacts(5))
    assert loop.server.receive(over, "env", 0) is None
    assert loop.server.counters.capacity_exceeded == 1
    loop.deliver()
    assert loop.client.last_error.code == ErrorCode.TOO_MANY_CONTACTS


def test_heartbeats_and_silence_timeout():
    cfg = ServerConfig(heartbeat_interval_s=0.1, silence_timeout_s=0.5)
    loop = Loop(cfg)
    s = loop.connect()
    loop.server.poll(50 * MS)
    loop.client.poll(50 * MS)
    assert loop.to_client == [] and loop.to_server == []
    loop.server.poll(100 * MS)
    loop.client.poll(100 * MS)
    loop.deliver(100 * MS)
    assert loop.server.counters.heartbeats_sent == 1 and loop.client.counters.heartbeats_sent == 1
    assert s.silence_ns(150 * MS) == 50 * MS and loop.client.silence_ns(150 * MS) == 50 * MS
    # The client goes silent: the server's silence timer grows, then it times out with Bye.
    assert s.silence_ns(599 * MS) == 499 * MS
    loop.server.poll(599 * MS)
    assert s.session_id in loop.server.sessions
    loop.to_client.clear()
    loop.server.poll(600 * MS)
    assert s.session_id not in loop.server.sessions and loop.server.counters.timeouts == 1
    loop.deliver(600 * MS)
    assert loop.client.state == ClientState.CLOSED and loop.client.bye.code == ErrorCode.BYE_TIMEOUT
    # Bye was sent 3 times: the repeats are unknown-session drops at the client.
    assert loop.client.counters.byes_received == 1 and loop.client.counters.unknown_session == 2


def test_client_bye_ends_the_server_session():
    loop = Loop()
    s = loop.connect()
    loop.client.close(now_ns=0)
    loop.deliver()
    assert s.session_id not in loop.server.sessions
    assert loop.server.counters.byes_received == 1 and loop.server.counters.unknown_session == 2
    assert loop.client.send_contacts(0, 0.0, IDENTITY, *contacts(1)) == 0  # closed: nothing sent


def test_receive_path_never_raises_on_garbage():
    loop = Loop()
    loop.connect()
    for junk in (b"", b"\x00", b"\xff" * 50, bytes(100_000), bytearray(b"\x95\x01\x00\x04\x01\x01")):
        assert loop.server.receive(junk, "env", 0) is None
        assert loop.client.receive(junk, "server", 0) is None
    assert loop.server.counters.oversize == 1 and loop.client.counters.oversize == 1


def test_hmac_mode():
    loop = Loop(server_key=KEY, client_key=KEY)
    s = loop.connect()
    loop.send(2)
    assert all(len(d) > HMAC_TAG_BYTES for d, _ in loop.to_server)
    updates, _ = loop.deliver()
    assert len(updates) == 1
    # Tampering with any byte, or a wrong key, or no tag: dropped as bad_mac before decoding.
    loop.send(2)
    d, p = loop.to_server.pop()
    assert loop.server.receive(d[:10] + bytes([d[10] ^ 1]) + d[11:], p, 0) is None
    assert loop.server.receive(MacFramer(bytes(32)).seal(d[:-HMAC_TAG_BYTES]), p, 0) is None
    assert loop.server.receive(d[:-HMAC_TAG_BYTES], p, 0) is None
    assert loop.server.counters.bad_mac == 3 and loop.server.codec.counters.rejected == 0
    assert loop.server.receive(d, p, 0).seq == 2
    # A client without the key cannot even open a session.
    plain = Loop(server_key=KEY)
    plain.client.start(0)
    plain.deliver()
    assert plain.client.state == ClientState.HANDSHAKING and plain.server.counters.bad_mac == 1
    del s


def test_load_hmac_key(tmp_path):
    assert load_hmac_key(environ={}) is None
    assert load_hmac_key(environ={"HAPTICPROXY_HMAC_KEY": KEY.hex()}) == KEY
    with pytest.raises(ValueError, match="at least 16 bytes"):
        load_hmac_key(environ={"HAPTICPROXY_HMAC_KEY": "abcd"})
    with pytest.raises(ValueError, match="hex"):
        load_hmac_key(environ={"HAPTICPROXY_HMAC_KEY": "zz" * 20})
    f = tmp_path / "key"
    f.write_text(KEY.hex() + "\n")
    os.chmod(f, 0o600)
    assert load_hmac_key(f, environ={}) == KEY
    assert load_hmac_key(environ={"HAPTICPROXY_HMAC_KEY_FILE": str(f)}) == KEY
    os.chmod(f, 0o644)
    with pytest.raises(ValueError, match="chmod 600"):
        load_hmac_key(f, environ={})


def test_linkage_hello_reaches_the_server_session():
    link0 = dict(mass_kg=1.0, com_m=(0.0, 0.0, 0.0), inertia_kg_m2=(0.01, 0.01, 0.01, 0.0, 0.0, 0.0), parent=-1,
                 joint_type=0, joint_axis=(1.0, 0.0, 0.0), joint_origin=tuple(IDENTITY))
    link1 = dict(link0, parent=0, joint_type=2, joint_axis=(0.0, 1.0, 0.0))
    loop = Loop(hello=spatial_hello(tool_kind=ToolKind.LINKAGE, links=(link0, link1), held_link=1))
    s = loop.connect()
    assert len(s.hello.links) == 2 and s.hello.links[1]["joint_type"] == M.JointType.PRISMATIC
    assert s.hello.held_link == 1
    assert loop.server.send_proxy_state(s.session_id, 0, IDENTITY, np.zeros(6), np.zeros(6),
                                        joint_position=[0.1], joint_velocity=[0.0], joint_effort=[0.0])
    _, states = loop.deliver()
    assert states[0].joint_position.tolist() == [0.1]


def test_over_the_mem_transport():
    from hapticproxy.protocol.transport import open_transport

    server_t = open_transport("mem://session-test", role="server")
    client_t = open_transport("mem://session-test", role="client")
    try:
        server = ServerEndpoint(server_t.send)
        client = ClientEndpoint(client_t.send, spatial_hello())
        client.start(0)
        for step in range(1, 6):
            now = step * MS
            for data, peer in server_t.drain():
                u = server.receive(data, peer, now)
                if u is not None:
                    server.send_proxy_state(u.session_id, now, IDENTITY, np.zeros(6), np.zeros(6))
            while (got := client_t.recv()) is not None:
                client.receive(got[0], got[1], now)
            if client.established:
                client.send_contacts(now, step * 0.016, IDENTITY, *contacts(3, step))
        assert client.established and server.counters.accepted >= 3
        assert client.counters.accepted >= 3 and server.counters.dropped == 0 and client.counters.dropped == 0
    finally:
        client_t.close()
        server_t.close()


def test_limits_shared_by_codec_and_session():
    loop = Loop(ServerConfig(limits=Limits(max_contacts=8), max_contacts=8))
    assert loop.server.codec.limits.max_contacts == 8
    with pytest.raises(ValueError, match="max_contacts"):
        ServerConfig(limits=Limits(max_contacts=8), max_contacts=9)


def test_client_start_resets_the_sequence_windows_for_a_new_session():
    """A client endpoint reused after a session accepts the new server's ProxyState seq 1."""
    from hapticproxy.protocol.session import _SeqWindow  # noqa: F401 - the window type under test
    from hapticproxy.protocol.codec import Hello
    from hapticproxy.protocol.messages import ToolKind
    from hapticproxy.protocol.session import ClientEndpoint

    ep = ClientEndpoint(lambda b: None, Hello(client_nonce=1, engine="t", tool_kind=ToolKind.PLANAR, mass_kg=1.0,
                                              inertia_kg_m2=(1e-3,) * 3 + (0.0,) * 3, max_contacts=4,
                                              epsilon_m=0.0, env_rate_hz=60.0))
    ep.start(0)
    ep._proxy_seq.newest = 500
    ep._heartbeat_seq.newest = 7
    ep.start(1)
    assert ep._proxy_seq.newest == 0 and ep._heartbeat_seq.newest == 0
