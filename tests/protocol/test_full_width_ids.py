"""Tokens, nonces and session ids are compared on all of their bits, on every path of the session
layer (the server's and the client's, a packet that decodes and one that does not, a Hello
repeated or new): for each, a value that differs from the true one only in its high half (the
upper 32 bits of a 64-bit token or nonce, the upper 16 of a 32-bit session id) is refused as a
wrong one, and the true value is accepted (so the test cannot pass by refusing everything).
The server's kernel fast path (``server/ingest.py``) and the ProxyState packer are held to the
same in ``tests/server/test_ingest_parser.py`` and ``tests/server/test_egress.py``; the remote
device link's sessions in ``tests/server/test_devices_remote.py``."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from hapticproxy.protocol.codec import Codec, Heartbeat, Welcome
from hapticproxy.protocol.messages import Bye, ErrorCode, ProxyState
from hapticproxy.protocol.session import ClientState

sys.path.insert(0, str(Path(__file__).parent))  # test_session's Loop (--import-mode=importlib)
from test_session import IDENTITY, Loop, contacts, spatial_hello  # noqa: E402

#: tokens and nonces: one whose high half is zero, one using all 64 bits (top bit set)
WIDE = (0x0000_0000_89AB_CDEF, 0xF123_4567_89AB_CDEF)
#: flips of the high half only: its lowest bit, a middle one, its top bit
HIGH_BITS = (1 << 32, 1 << 45, 1 << 63)
_WIDE_IDS = ["high-zero", "all-64-bits"]
_BIT_IDS = ["bit32", "bit45", "bit63"]


def _loop(token: int) -> tuple[Loop, object]:
    """A client and a server in one session whose token is ``token`` (on both sides)."""
    loop = Loop()
    s = loop.connect()
    s.token = token
    loop.client.token = token
    return loop, s


def _update(s, token: int, seq: int, session_id: int | None = None, normal_scale: float = 1.0) -> bytes:
    keys, pos, nor, d, v = contacts(2)
    return Codec().encode_contact_update(s.session_id if session_id is None else session_id, token, seq, 0.0,
                                         IDENTITY, keys, pos, nor * normal_scale, d, v)


@pytest.mark.parametrize("token", WIDE, ids=_WIDE_IDS)
@pytest.mark.parametrize("bit", HIGH_BITS, ids=_BIT_IDS)
def test_the_server_refuses_a_token_differing_only_in_its_high_half(token, bit):
    loop, s = _loop(token)
    srv = loop.server
    forged = token ^ bit
    assert forged & 0xFFFF_FFFF == token & 0xFFFF_FFFF
    assert srv.receive(_update(s, forged, 5), "env", 0) is None
    assert srv.counters.bad_token == 1 and s.acked_seq == 0
    # a Heartbeat and a Bye with the forged token: the session neither refreshed nor closed
    srv.receive(Codec().encode(Heartbeat(seq=1, time_s=0.0, session_id=s.session_id, token=forged)), "env", 10)
    srv.receive(Codec().encode(Bye(code=ErrorCode.BYE_SHUTDOWN, reason="", session_id=s.session_id, token=forged)),
                "env", 10)
    assert srv.counters.bad_token == 3 and s.session_id in srv.sessions and srv.counters.byes_received == 0
    assert srv.receive(_update(s, token, 5), "env", 0).seq == 5  # the true token is taken


@pytest.mark.parametrize("bit", (1 << 16, 1 << 31), ids=["bit16", "bit31"])
def test_the_server_refuses_a_session_id_differing_only_in_its_high_half(bit):
    loop, s = _loop(WIDE[1])
    srv = loop.server
    sid = (s.session_id & 0xFFFF) or 1  # an id whose high half is zero, to flip bits into
    srv.sessions[sid] = srv.sessions.pop(s.session_id)
    s.session_id = sid
    loop.client.session_id = sid
    assert srv.receive(_update(s, s.token, 3, session_id=sid ^ bit), "env", 0) is None
    assert srv.counters.unknown_session == 1
    assert srv.receive(_update(s, s.token, 3), "env", 0).seq == 3


@pytest.mark.parametrize("token", WIDE, ids=_WIDE_IDS)
def test_a_bad_packet_is_answered_only_with_the_full_token(token):
    """The decode-error path answers a packet of a session with an Error only when its whole
    token (and peer) are the session's: never to one forged in the high half."""
    loop, s = _loop(token)
    loop.server.receive(_update(s, token ^ (1 << 40), 1, normal_scale=2.0), "env", 0)  # not unit: a decode error
    assert loop.to_client == [] and loop.server.counters.errors_sent == 0
    loop.server.receive(_update(s, token, 1, normal_scale=2.0), "env", 0)
    assert len(loop.to_client) == 1 and loop.server.counters.errors_sent == 1


@pytest.mark.parametrize("nonce", WIDE, ids=_WIDE_IDS)
def test_a_hello_is_repeated_only_for_the_full_nonce(nonce):
    """A Hello from the session's peer with the same nonce is a lost Welcome (repeated, the same
    session); with a nonce differing only in its high half it is a restarted client (a new one)."""
    loop = Loop(hello=spatial_hello())
    loop.client.start(0)
    loop.client.hello.client_nonce = nonce  # (start drew a random one)
    hello = loop.client.codec.encode(loop.client.hello)
    loop.to_server.clear()
    loop.server.receive(hello, "env", 0)
    first = next(iter(loop.server.sessions))
    loop.server.receive(hello, "env", 1)
    assert loop.server.counters.hello_repeats == 1 and list(loop.server.sessions) == [first]
    loop.client.hello.client_nonce = nonce ^ (1 << 50)
    loop.server.receive(loop.client.codec.encode(loop.client.hello), "env", 2)
    assert loop.server.counters.hello_repeats == 1 and loop.server.counters.sessions_opened == 2
    assert first not in loop.server.sessions


@pytest.mark.parametrize("nonce", WIDE, ids=_WIDE_IDS)
def test_the_client_takes_a_welcome_only_for_its_full_nonce(nonce):
    loop = Loop()
    loop.client.start(0)
    loop.client.hello.client_nonce = nonce
    loop.to_server.clear()
    loop.server.receive(loop.client.codec.encode(loop.client.hello), "env", 0)
    codec = Codec()
    w = codec.decode(loop.to_client.pop()[0])
    assert isinstance(w, Welcome) and w.client_nonce == nonce
    w.client_nonce = nonce ^ (1 << 33)
    loop.client.receive(codec.encode(w), "server", 0)
    assert loop.client.state == ClientState.HANDSHAKING and loop.client.counters.unexpected == 1
    w.client_nonce = nonce
    loop.client.receive(codec.encode(w), "server", 0)
    assert loop.client.state == ClientState.ESTABLISHED and loop.client.token == w.token


@pytest.mark.parametrize("token", WIDE, ids=_WIDE_IDS)
@pytest.mark.parametrize("bit", HIGH_BITS, ids=_BIT_IDS)
def test_the_client_refuses_a_server_token_differing_only_in_its_high_half(token, bit):
    loop, s = _loop(token)
    loop.send(2)
    loop.deliver()
    s.token = token ^ bit  # the server side sends with the forged token
    assert loop.server.send_proxy_state(s.session_id, 0, IDENTITY, np.zeros(6), np.zeros(6))
    _, states = loop.deliver()
    assert states == [] and loop.client.counters.bad_token == 1
    s.token = token
    assert loop.server.send_proxy_state(s.session_id, 0, IDENTITY, np.zeros(6), np.zeros(6))
    _, states = loop.deliver()
    assert len(states) == 1 and isinstance(states[0], ProxyState)


@pytest.mark.parametrize("token", WIDE, ids=_WIDE_IDS)
def test_the_client_answers_a_bad_packet_only_with_the_full_token(token):
    loop, s = _loop(token)
    codec = Codec()

    def bad(tok):
        """A ProxyState whose pose is not a unit quaternion (qw = 2: its bytes patched)."""
        good = codec.encode(ProxyState(seq=1, ack_seq=0, server_time_s=0.0, proxy_pose=IDENTITY,
                                       proxy_twist=np.zeros(6), wrench=np.zeros(6), session_id=s.session_id,
                                       token=tok))
        one, two = np.float64(1.0).tobytes(), np.float64(2.0).tobytes()
        assert good.count(one) == 1
        return good.replace(one, two)

    loop.client.receive(bad(token ^ (1 << 40)), "server", 0)
    assert loop.to_server == [] and loop.client.counters.errors_sent == 0
    loop.client.receive(bad(token), "server", 0)
    assert len(loop.to_server) == 1 and loop.client.counters.errors_sent == 1


@pytest.mark.parametrize("bit", (1 << 16, 1 << 31), ids=["bit16", "bit31"])
def test_the_client_refuses_a_session_id_differing_only_in_its_high_half(bit):
    loop, s = _loop(WIDE[1])
    codec = Codec()

    def state(sid):
        return codec.encode(ProxyState(seq=1, ack_seq=0, server_time_s=0.0, proxy_pose=IDENTITY,
                                       proxy_twist=np.zeros(6), wrench=np.zeros(6), session_id=sid, token=s.token))

    assert loop.client.receive(state(s.session_id ^ bit), "server", 0) is None
    assert loop.client.counters.unknown_session == 1
    assert isinstance(loop.client.receive(state(s.session_id), "server", 0), ProxyState)
