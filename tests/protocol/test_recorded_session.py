"""A real session recorded before the restructure (the hand-written codec of 6638e56, protocol
1.1: a pymunk testbed client and the server on UDP loopback, every datagram both ways,
``golden/record_session.py``), replayed through today's codec: every datagram decodes, and
encoded again at the minor it was written in it gives the same bytes, byte for byte. Today's
peers (minor 2) read it too: the fields minor 2 appended take their defaults."""
from __future__ import annotations

import json
from collections import Counter
from pathlib import Path

import numpy as np
from hapticproxy.protocol import codec as C
from hapticproxy.protocol.messages import PROTOCOL_MINOR

RECORDING = [json.loads(line) for line in
             (Path(__file__).with_name("golden") / "session_v1_1.jsonl").read_text(encoding="utf-8").splitlines()]


def test_the_recording_is_a_whole_session():
    """Hello, Welcome, the stream of updates and acknowledgements, Bye: what the replay covers."""
    kinds = Counter((r["dir"], type(C.Codec(minor=1).decode(bytes.fromhex(r["hex"]))).__name__) for r in RECORDING)
    assert kinds[("client->server", "Hello")] == 1 and kinds[("server->client", "Welcome")] == 1
    assert kinds[("client->server", "ContactUpdate")] >= 100
    assert kinds[("server->client", "ProxyState")] >= 100
    assert kinds[("client->server", "Bye")] >= 1
    assert {r["hex"][:6] for r in RECORDING} >= {"9b0101", "9e0101"}  # the header: major 1, minor 1


def test_every_datagram_encodes_again_to_the_same_bytes():
    codec = C.Codec(minor=1)
    differ = []
    for i, r in enumerate(RECORDING):
        data = bytes.fromhex(r["hex"])
        msg = codec.decode(data)
        if msg.minor != 1 or codec.encode(msg) != data:
            differ.append(f"{i} ({r['dir']} {type(msg).__name__})")
    assert not differ, f"{len(differ)} of {len(RECORDING)} datagrams differ: {', '.join(differ[:5])}"


def test_todays_peers_read_the_old_session():
    """A minor-2 codec decodes every datagram of the 1.1 session to the same values as a minor-1
    codec, the appended fields at their defaults (a ProxyState's advice 0: not advised)."""
    old, new = C.Codec(minor=1), C.Codec(minor=PROTOCOL_MINOR)
    for r in RECORDING:
        data = bytes.fromhex(r["hex"])
        a, b = old.decode(data), new.decode(data)
        assert type(a) is type(b)
        for name in a.__struct_fields__:
            x, y = getattr(a, name), getattr(b, name)
            if isinstance(x, np.ndarray):
                np.testing.assert_array_equal(x, y, err_msg=name)
            else:
                assert x == y, name
        if isinstance(b, C.ProxyState):
            assert b.epsilon_m == 0.0 and b.lead_s == 0.0
