"""The server's whole-datagram ContactUpdate kernel (``server/ingest.py``: ``ContactParser``,
plugged into ``ServerEndpoint(update_parser=...)``) changes what receiving an update costs, never
what is accepted: for valid updates and for each way a datagram can break a rule of the codec
or of the session (at the edges of the rules, and in msgpack forms the kernel does not read),
the endpoint returns the same update (the same arrays and fields) or refuses it with the same
counters and the same Error reply as without the kernel. A slot that holds an update someone
keeps is never written over."""
from __future__ import annotations

import struct

import numba
import numpy as np
import pytest
from server_harness import break_contact_rule, random_contacts as _contacts

from hapticproxy.protocol.codec import Codec, Limits
from hapticproxy.protocol.messages import Hello, ToolKind
from hapticproxy.protocol.session import ClientEndpoint, ServerConfig, ServerEndpoint
from hapticproxy.server import ingest

PEER = ("127.0.0.1", 40000)
_BAR = dict(mass_kg=0.08, com_m=[0.03, 0.0, 0.0], inertia_kg_m2=[3e-6, 2.5e-5, 2.5e-5, 0.0, 0.0, 0.0])


def _hello(kind: str) -> Hello:
    common = dict(client_nonce=11, engine="test", max_contacts=16, epsilon_m=0.005, env_rate_hz=60.0)
    if kind == "linkage":
        links = [dict(_BAR, parent=-1, joint_type=0, joint_axis=[0.0, 0.0, 1.0],
                      joint_origin=[0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0])]
        links += [dict(_BAR, parent=k - 1, joint_type=1, joint_axis=[0.0, 0.0, 1.0],
                       joint_origin=[0.06, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]) for k in (1, 2)]
        return Hello(tool_kind=ToolKind.LINKAGE, mass_kg=0.24, links=links, held_link=2, **common)
    tk = ToolKind.PLANAR if kind == "planar" else ToolKind.SPATIAL
    return Hello(tool_kind=tk, mass_kg=0.2, inertia_kg_m2=(2e-4, 2e-4, 2e-4, 0.0, 0.0, 0.0), axis=(1.0, 0.0, 0.0),
                 **common)


class Pair:
    """A server endpoint (with or without the parser) holding one established session."""

    def __init__(self, kind: str, parser: bool):
        self.out: list = []
        lim = Limits(max_contacts=64)
        cfg = ServerConfig(limits=lim, workspace_extent_m=0.5, max_constraint_speed_m_per_s=2.0,
                           max_separation_m=0.05, max_seq_jump=1000)
        self.parser = ingest.ContactParser(lim) if parser else None
        self.server = ServerEndpoint(lambda d, p: self.out.append(d), cfg,
                                     codec=Codec(lim, contact_check=ingest.contacts_surely_valid),
                                     update_check=ingest.update_surely_in_bounds, update_parser=self.parser)
        to_server: list = []
        self.client = ClientEndpoint(to_server.append, _hello(kind))
        self.client.start(0)
        self.server.receive(to_server.pop(), PEER, 0)
        self.client.receive(self.out.pop(), PEER, 0)
        assert self.client.established
        s = next(iter(self.server.sessions.values()))
        self.sid, self.token = s.session_id, s.token


def _uint(v: int, width: int = 0) -> bytes:
    """msgpack unsigned int: the smallest form, or a given width (a form other encoders use)."""
    if width == 0:
        width = 0 if v < 0x80 else 1 if v <= 0xFF else 2 if v <= 0xFFFF else 4 if v <= 0xFFFF_FFFF else 8
    if width == 0:
        return bytes([v])
    return bytes([{1: 0xCC, 2: 0xCD, 4: 0xCE, 8: 0xCF}[width]]) + v.to_bytes(width, "big")


def _bin(b: bytes, form: int = 0) -> bytes:
    form = form or (0xC4 if len(b) <= 0xFF else 0xC5 if len(b) <= 0xFFFF else 0xC6)
    size = {0xC4: 1, 0xC5: 2, 0xC6: 4}[form]
    return bytes([form]) + len(b).to_bytes(size, "big") + b


def _packet(sid, token, seq, pose, keys, pos, normal, sep, vc, joints=None, *, env=0.5, wide=(), env_form="f64",
            count_form="fix", extra=b"", trailing=b"", major=1, tid=4, bin_form=0, count=None):
    fields = [_uint(major, 1 if "major" in wide else 0), _uint(2), _uint(tid), _uint(sid, 8 if "sid" in wide else 0),
              _uint(token, 8 if "token" in wide else 0), _uint(seq, 8 if "seq" in wide else 0)]
    fields.append(b"\xcb" + struct.pack(">d", env) if env_form == "f64" else
                  b"\xca" + struct.pack(">f", env) if env_form == "f32" else _uint(int(env)))
    n = keys.shape[0] if count is None else count
    data = np.concatenate([pos.reshape(-1), normal.reshape(-1), sep, vc]).astype("<f8").tobytes()
    fields += [_bin(np.asarray(pose, "<f8").tobytes(), bin_form), _uint(n, 2 if "n" in wide else 0),
               _bin(keys.astype("<i8").tobytes(), bin_form), _bin(data, bin_form)]
    if joints is not None:
        fields.append(_bin(np.asarray(joints, "<f8").tobytes(), bin_form))
    if extra:
        fields.append(extra)
    k = len(fields)
    head = bytes([0x90 + k]) if count_form == "fix" else b"\xdc" + k.to_bytes(2, "big")
    return head + b"".join(fields) + trailing


def _cases(rng, kind, sid, token, state):
    """(name, packet) of valid updates and of each way one breaks a rule; ``state["newest"]``:
    the newest seq the session accepted (the caller keeps it)."""
    planar = kind == "planar"
    for trial in range(12):
        for case in ("valid", "valid_zero", "valid_wide", "valid_array16", "valid_bin16", "nan", "inf", "big",
                     "not_unit", "unit_edge_in", "unit_edge_out", "duplicate", "pose_not_unit", "pose_far",
                     "pose_nan", "oob_position", "at_extent", "oob_speed", "oob_separation", "bad_link",
                     "planar_z", "too_many", "wrong_token", "wrong_session", "stale", "duplicate_seq", "jump",
                     "env_f32", "env_int", "env_nan", "trailing", "truncated", "unknown_field", "joints_wrong",
                     "joints_nan", "keys_short", "data_short", "major2", "wrong_type", "token_wide",
                     "wrong_token_bit32", "wrong_token_bit63", "wrong_token_low_half", "wrong_session_bit16",
                     "wrong_session_bit31", "wrong_session_bit32"):
            n = 0 if case == "valid_zero" else 17 if case == "too_many" else int(rng.integers(1, 12))
            keys, pos, normal, sep, vc = _contacts(rng, n, planar, 3 if kind == "linkage" else 1)
            seq = state["newest"]
            joints = rng.uniform(-1.0, 1.0, 2) if kind == "linkage" else None
            pose = np.array([0.0, 0.05, 0.0, 1.0, 0.0, 0.0, 0.0])
            i = int(rng.integers(0, max(n, 1)))
            kw: dict = {}
            seq_here = seq + int(rng.integers(1, 3))  # now and then one lost on the way
            if break_contact_rule(case, rng, i, keys, pos, normal, sep, vc):
                pass  # a codec rule of the contacts (shared with test_ingest.py)
            elif case == "pose_not_unit":
                pose[3] = 1.01
            elif case == "pose_far":
                pose[0] = 0.5 * (1 + rng.choice([0.0, 1e-12]))
            elif case == "pose_nan":
                pose[2] = np.nan
            elif case == "oob_position":
                pos[i, 2] = 0.5 * (1 + 1e-12)
            elif case == "at_extent":
                pos[i, 0] = -0.5
            elif case == "oob_speed":
                vc[i] = 2.0 * (1 + 1e-12)
            elif case == "oob_separation":
                sep[i] = -0.05 * (1 + 1e-12)
            elif case == "bad_link":
                keys[i, 0] = rng.choice([-1, 3])
            elif case == "planar_z":
                normal[i] = [np.sqrt(1 - 4e-12), 0.0, 2e-6]
            elif case == "wrong_token":
                kw["token_"] = token ^ 1
            elif case == "wrong_session":
                kw["sid_"] = sid + 1
            elif case.startswith("wrong_token_bit"):  # the high half only (the low half is right)
                kw["token_"] = token ^ (1 << int(case.removeprefix("wrong_token_bit")))
            elif case == "wrong_token_low_half":  # the low half alone (a u32 on the wire)
                kw["token_"] = token & 0xFFFF_FFFF
            elif case.startswith("wrong_session_bit"):  # the id's high half only (bit 32: beyond the u32
                # the SPEC gives it, which the wire's uint64 form can carry)
                kw["sid_"] = sid ^ (1 << int(case.removeprefix("wrong_session_bit")))
            elif case == "stale":
                seq_here = max(seq - 1, 0)
            elif case == "duplicate_seq":
                seq_here = seq
            elif case == "jump":
                seq_here = seq + 1001
            elif case == "env_f32":
                kw["env_form"] = "f32"
            elif case == "env_int":
                kw["env_form"] = "int"
            elif case == "env_nan":
                kw["env"] = float("nan")
            elif case == "trailing":
                kw["trailing"] = b"\x00"
            elif case == "unknown_field":
                kw["extra"] = _uint(7)
                joints_here = np.zeros(0) if joints is None else joints
            elif case == "valid_wide":
                kw["wide"] = ("major", "sid", "seq", "n")
            elif case == "token_wide":
                kw["wide"] = ("token",)
            elif case == "valid_array16":
                kw["count_form"] = "array16"
            elif case == "valid_bin16":
                kw["bin_form"] = 0xC5
            elif case == "major2":
                kw["major"] = 2
            elif case == "wrong_type":
                kw["tid"] = 3
            jts = joints
            if case == "joints_wrong":
                jts = np.zeros(3)
            elif case == "joints_nan":
                jts = np.array([0.1, np.nan]) if joints is not None else np.array([np.nan])
            elif case == "unknown_field":
                jts = joints_here
            pkt = _packet(kw.pop("sid_", sid), kw.pop("token_", token), seq_here, pose, keys, pos, normal, sep, vc,
                          jts, **kw)
            if case == "truncated":
                pkt = pkt[:-3]
            elif case == "keys_short":  # n says one contact more than the keys hold
                pkt = _packet(sid, token, seq_here, pose, keys[:-1], pos[:-1], normal[:-1], sep[:-1], vc[:-1], jts,
                              count=n)
            elif case == "data_short":
                pkt = _packet(sid, token, seq_here, pose, keys, pos, normal, sep[:-1], vc, jts)
            yield case, pkt


def _verdict(pair: Pair, pkt: bytes):
    srv = pair.server
    pair.out.clear()
    msg = srv.receive(bytearray(pkt), PEER, 1000)
    errors = [bytes(d) for d in pair.out]
    if msg is None:
        return ("refused", errors)
    return ("accepted", msg.seq, msg.session_id, msg.token, msg.env_time_s, msg.contact_count,
            msg.tool_pose.tobytes(), msg.keys.tobytes(), msg.position_m.tobytes(), msg.normal.tobytes(),
            msg.separation_m.tobytes(), msg.v_constr_m_per_s.tobytes(), msg.tool_joint_position.tobytes(),
            msg.contact_columns.tobytes())


def _counters(pair: Pair) -> tuple:
    return repr(pair.server.counters), repr(pair.server.codec.counters)  # every counter, by name


@pytest.mark.parametrize("kind", ["spatial", "planar", "linkage"])
def test_the_endpoint_accepts_and_refuses_the_same_datagrams_with_the_parser(kind):
    slow, fast = Pair(kind, parser=False), Pair(kind, parser=True)
    # the same session on both sides (ids and tokens are random per endpoint)
    for p in (slow, fast):
        s = p.server.sessions.pop(p.sid)
        s.session_id, s.token = 77, 0xDEAD_BEEF_0123_4567
        p.server.sessions[77] = s
    rng = np.random.default_rng({"spatial": 1, "planar": 2, "linkage": 3}[kind])
    taken = {}
    calls = []
    parse = fast.parser.__call__

    def spy(data):
        calls.append(parse(data))
        return calls[-1]

    fast.server._parser = spy
    spy.expect, spy.accepted = fast.parser.expect, fast.parser.accepted
    seen = set()
    state = {"newest": 0}
    for case, pkt in _cases(rng, kind, 77, 0xDEAD_BEEF_0123_4567, state):
        calls.clear()
        a, b = _verdict(slow, pkt), _verdict(fast, pkt)
        assert a == b, case
        assert _counters(slow) == _counters(fast), case
        if calls and calls[-1] is not None:
            taken[case] = taken.get(case, 0) + 1
        seen.add((case, a[0]))
        if a[0] == "accepted":
            state["newest"] = a[1]
    # every case was exercised as it says, and the kernel took the common updates itself
    accepted = {c for c, v in seen if v == "accepted"}
    assert {"valid", "valid_zero", "valid_wide", "valid_array16", "valid_bin16", "at_extent", "unit_edge_in",
            "token_wide", "env_int"} <= accepted
    assert not accepted & {"nan", "inf", "big", "not_unit", "unit_edge_out", "pose_not_unit", "pose_nan",
                           "oob_position", "oob_speed", "oob_separation", "bad_link", "too_many", "wrong_token",
                           "wrong_session", "wrong_token_bit32", "wrong_token_bit63", "wrong_token_low_half",
                           "wrong_session_bit16", "wrong_session_bit31", "wrong_session_bit32", "stale", "duplicate_seq", "jump", "env_nan", "trailing", "truncated",
                           "joints_wrong", "joints_nan", "keys_short", "data_short", "major2", "wrong_type"}
    assert ("planar_z" in accepted) == (kind != "planar")
    assert taken.get("valid", 0) >= 11 and taken.get("valid_wide", 0) >= 11 and taken.get("valid_array16", 0) >= 11
    assert not set(taken) & {"unit_edge_in", "env_int", "env_f32", "unknown_field"}  # left to the codec
    # the kernel vouches for no token or session id that differs from the session's in any bit
    assert not set(taken) & {"wrong_token", "wrong_token_bit32", "wrong_token_bit63", "wrong_token_low_half",
                             "wrong_session", "wrong_session_bit16", "wrong_session_bit31", "wrong_session_bit32"}


def test_a_slot_is_never_written_over_while_its_update_is_kept():
    p = Pair("spatial", parser=True)
    rng = np.random.default_rng(9)
    kept = []
    seq = 0
    # the first update is accepted by the codec; from then on the parser takes them
    for k in range(12):
        keys, pos, normal, sep, vc = _contacts(rng, 5, False)
        seq += 1
        msg = p.server.receive(bytearray(_packet(p.sid, p.token, seq, [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0], keys, pos,
                                                 normal, sep, vc)), PEER, 1000)
        assert msg is not None
        kept.append((msg, pos.copy(), vc.copy()))
    for msg, pos, vc in kept:
        assert np.array_equal(msg.position_m, pos) and np.array_equal(msg.v_constr_m_per_s, vc)
    # every slot was held: the rest went to the codec, counted
    assert p.parser.all_held == 12 - 1 - ingest.ContactParser.SLOTS
    kept.clear()  # the loop keeps at most two: slots are free again, and reused
    keys, pos, normal, sep, vc = _contacts(rng, 5, False)
    p.server.receive(bytearray(_packet(p.sid, p.token, seq + 1, [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0], keys, pos,
                                       normal, sep, vc)), PEER, 1000)
    assert p.parser.reused == 1


def test_the_parsers_arrays_have_the_codecs_types():
    """So every kernel downstream (the advice, the engine's tool configuration) runs the
    specialisation compiled for the codec's read-only views: none compiles in a haptic step."""
    p = Pair("linkage", parser=True)
    rng = np.random.default_rng(10)
    pose = [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]
    msgs = []
    for seq in (1, 2):
        keys, pos, normal, sep, vc = _contacts(rng, 4, False)
        msgs.append(p.server.receive(bytearray(_packet(p.sid, p.token, seq, pose, keys, pos, normal, sep, vc,
                                                       np.array([0.1, 0.2]))), PEER, 1000))
    by_codec, by_parser = msgs
    assert by_codec.contact_keys and not by_parser.contact_keys  # each took its path
    for name in ("tool_pose", "keys", "position_m", "normal", "separation_m", "v_constr_m_per_s",
                 "tool_joint_position", "contact_columns"):
        a, b = getattr(by_codec, name), getattr(by_parser, name)
        assert numba.typeof(a) == numba.typeof(b), name
        assert not b.flags.writeable, name
