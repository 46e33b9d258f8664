"""Codec: round trips, decoded layout, every bad-input class, versioning, counters."""
from __future__ import annotations

import math

import msgpack
import numpy as np
import pytest

from hapticproxy.protocol import messages as M
from hapticproxy.protocol.codec import Codec, Limits, ProtocolError, decode, encode
from hapticproxy.protocol.messages import (
    Bye,
    ContactUpdate,
    Error,
    ErrorCode,
    Heartbeat,
    Hello,
    ProxyState,
    Reject,
    Welcome,
)

IDENTITY = (0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0)


def contacts(n: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    keys = np.column_stack([np.zeros(n, np.int64), np.arange(n, dtype=np.int64) // 4, np.arange(n, dtype=np.int64)])
    pos = rng.normal(size=(n, 3))
    nor = rng.normal(size=(n, 3))
    nor /= np.linalg.norm(nor, axis=1)[:, None]
    return keys, pos, nor, rng.normal(size=n) * 1e-3, rng.normal(size=n) * 1e-2


def cu_packet(codec: Codec, n: int = 4, seq: int = 1, **over) -> bytes:
    keys, pos, nor, d, v = contacts(n)
    args = dict(session_id=7, token=99, seq=seq, env_time_s=0.25, tool_pose=IDENTITY, keys=keys,
                position_m=pos, normal=nor, separation_m=d, v_constr_m_per_s=v)
    args.update(over)
    return codec.encode_contact_update(**args)


def raw(packet: bytes) -> list:
    return msgpack.unpackb(packet)


def pack(obj) -> bytes:
    return msgpack.packb(obj, use_bin_type=True)


LINK0 = dict(mass_kg=1.0, com_m=(0.0, 0.0, 0.1), inertia_kg_m2=(0.01, 0.01, 0.02, 0.0, 0.0, 0.0), parent=-1,
             joint_type=0, joint_axis=(1.0, 0.0, 0.0), joint_origin=IDENTITY)
LINK1 = dict(LINK0, parent=0, joint_type=1, joint_axis=(0.0, 0.0, 1.0), joint_origin=(0.0, 0.0, 0.2, 1.0, 0.0, 0.0, 0.0))


def all_messages():
    return [
        Hello(client_nonce=5, engine="mujoco 3.1", tool_kind=M.ToolKind.SPATIAL, mass_kg=1.0,
              inertia_kg_m2=(0.1, 0.1, 0.1, 0.0, 0.0, 0.0), max_contacts=32, epsilon_m=0.005),
        Hello(client_nonce=6, engine="e", tool_kind=M.ToolKind.ONE_DOF, mass_kg=1.0, max_contacts=8,
              axis=(0.0, 1.0, 0.0)),
        Hello(client_nonce=7, engine="e", tool_kind=M.ToolKind.PLANAR, mass_kg=0.5,
              inertia_kg_m2=(0.0, 0.0, 0.01, 0.0, 0.0, 0.0), max_contacts=16),
        Hello(client_nonce=8, engine="e", tool_kind=M.ToolKind.LINKAGE, mass_kg=2.0, max_contacts=16,
              links=(LINK0, LINK1), held_link=1),
        Welcome(client_nonce=5, version=(1, 0), haptic_rate_hz=1000.0, epsilon_m=0.005, max_contacts=32,
                heartbeat_interval_s=0.1, silence_timeout_s=1.0, session_id=7, token=99),
        Reject(client_nonce=5, code=ErrorCode.UNSUPPORTED_VERSION, reason="no common major"),
        ProxyState(seq=3, ack_seq=2, server_time_s=0.5, proxy_pose=np.array(IDENTITY),
                   proxy_twist=np.arange(6.0), wrench=np.arange(6.0) - 3, session_id=7, token=99),
        ProxyState(seq=3, ack_seq=2, server_time_s=0.5, proxy_pose=np.array(IDENTITY), proxy_twist=np.zeros(6),
                   wrench=np.zeros(6), joint_position=np.array([0.1]), joint_velocity=np.array([0.2]),
                   joint_effort=np.array([0.3]), session_id=7, token=99),
        Heartbeat(seq=1, time_s=2.0, session_id=7, token=99),
        Bye(code=ErrorCode.BYE_NORMAL, reason="done", session_id=7, token=99),
        Error(code=ErrorCode.NON_FINITE, field="contact_data", detail="nan", ref_type=4, ref_seq=9,
              session_id=7, token=99),
        ContactUpdate.from_arrays(seq=1, env_time_s=0.0, tool_pose=np.array(IDENTITY), keys=np.zeros((0, 3), np.int64),
                      position_m=np.zeros((0, 3)), normal=np.zeros((0, 3)), separation_m=np.zeros(0),
                      v_constr_m_per_s=np.zeros(0), session_id=7, token=99),
    ]


@pytest.mark.parametrize("msg", all_messages(), ids=lambda m: type(m).__name__)
def test_round_trip_every_message(msg):
    codec = Codec()
    out = codec.decode(codec.encode(msg))
    assert type(out) is type(msg)
    assert out == msg
    assert out.unknown_fields == 0
    assert codec.counters.decoded == 1 and codec.counters.rejected == 0


def test_every_declared_message_is_covered_by_the_round_trip():
    assert {type(m).__name__ for m in all_messages()} == {s.name for s in M.MESSAGES}


def test_declarations_follow_the_versioning_rules():
    M.check_declarations()

    class Bad(Heartbeat, kw_only=True):
        x: M.f64("test-only field", since=1)

    with pytest.raises(ValueError, match="needs a default"):
        M.check_declarations((Bad,))

    class Unordered(Heartbeat, kw_only=True):
        x: M.f64("test-only field", since=2) = 0.0
        y: M.f64("test-only field", since=1) = 0.0

    with pytest.raises(ValueError, match="append only"):
        M.check_declarations((Unordered,))


@pytest.mark.parametrize("n", [0, 1, 8, 32, 64])
def test_contact_update_round_trip_and_layout(n):
    codec = Codec()
    keys, pos, nor, d, v = contacts(n, seed=n)
    pose = np.array([0.1, -0.2, 0.3, math.cos(0.2), 0.0, 0.0, math.sin(0.2)])
    pkt = codec.encode_contact_update(3, 4, 17, 1.5, pose, keys, pos, nor, d, v)
    m = codec.decode(pkt)
    assert (m.session_id, m.token, m.seq, m.env_time_s, m.n_contacts) == (3, 4, 17, 1.5, n)
    for name, arr, ref, shape, dtype in [
        ("keys", m.keys, keys, (n, 3), np.int64), ("position_m", m.position_m, pos, (n, 3), np.float64),
        ("normal", m.normal, nor, (n, 3), np.float64), ("separation_m", m.separation_m, d, (n,), np.float64),
        ("v_constr_m_per_s", m.v_constr_m_per_s, v, (n,), np.float64), ("tool_pose", m.tool_pose, pose, (7,), np.float64),
    ]:
        assert arr.shape == shape and arr.dtype == dtype, name
        assert arr.flags.c_contiguous, name
        assert not arr.flags.writeable, name  # views on the packet: the model must copy
        np.testing.assert_array_equal(arr, ref, err_msg=name)
    # Packed layout: header + 6 fields, two bins of exactly 24 n and 64 n bytes.
    obj = raw(pkt)
    assert obj[:5] == [1, M.PROTOCOL_MINOR, 4, 3, 4] and len(obj) == 11  # no joints: the 1.0 layout
    assert obj[8] == n and len(obj[9]) == 24 * n and len(obj[10]) == 64 * n
    np.testing.assert_array_equal(np.frombuffer(obj[10], "<f8")[: 3 * n], pos.ravel())


def test_encode_via_message_object_equals_fast_path():
    codec = Codec()
    keys, pos, nor, d, v = contacts(5)
    msg = ContactUpdate.from_arrays(seq=2, env_time_s=0.5, tool_pose=np.array(IDENTITY), keys=keys, position_m=pos, normal=nor,
                        separation_m=d, v_constr_m_per_s=v, session_id=1, token=2)
    assert codec.encode(msg) == codec.encode_contact_update(1, 2, 2, 0.5, IDENTITY, keys, pos, nor, d, v)


def test_module_level_helpers():
    hb = Heartbeat(seq=4, time_s=1.0, session_id=1, token=1)
    assert decode(encode(hb)) == hb


# ----------------------------------------------------------------------------- bad input
def expect(codec: Codec, data, code: ErrorCode, field: str | None = None) -> ProtocolError:
    before = codec.counters.as_dict()
    out = codec.try_decode(data)
    assert isinstance(out, ProtocolError), f"accepted: {out!r}"
    assert out.code == code, f"{out.code.name} != {code.name}: {out}"
    if field is not None:
        assert out.field.startswith(field), out.field
    after = codec.counters.as_dict()
    assert after[code.name.lower()] == before[code.name.lower()] + 1
    assert after["rejected"] == before["rejected"] + 1
    assert after["decoded"] == before["decoded"]
    with pytest.raises(ProtocolError):
        codec.decode(data)
    return out


def mutate(packet: bytes, index: int, value) -> bytes:
    obj = raw(packet)
    obj[index] = value
    return pack(obj)


def f64bin(values) -> bytes:
    return np.asarray(values, "<f8").tobytes()


def test_malformed_msgpack():
    codec = Codec()
    pkt = cu_packet(codec)
    expect(codec, pkt[:-5], ErrorCode.MALFORMED)  # truncated
    expect(codec, pkt + b"\x00", ErrorCode.MALFORMED)  # trailing bytes
    expect(codec, b"\xc1", ErrorCode.MALFORMED)  # never-used msgpack byte
    expect(codec, b"", ErrorCode.MALFORMED)
    expect(codec, pack({"a": 1}), ErrorCode.MALFORMED)  # maps are refused by the unpacker
    expect(codec, pack(msgpack.ExtType(1, b"x")), ErrorCode.MALFORMED)
    expect(codec, b"\xa2\xff\xfe", ErrorCode.MALFORMED)  # invalid UTF-8


def test_strings_over_max_str_bytes_name_their_field():
    # (not MALFORMED: the packet is readable, so a Hello's nonce is known and it can be answered)
    codec = Codec()
    expect(codec, pack([1, 0, 8, 1, 1, 9, "x" * 1000, "", 0, 0]), ErrorCode.BAD_SHAPE, "field")
    err = expect(codec, hello_raw(engine="e" * 257), ErrorCode.BAD_SHAPE, "engine")
    assert err.client_nonce == 5 and err.type_id == 1
    assert not isinstance(codec.try_decode(hello_raw(engine="e" * 256)), ProtocolError)
    assert isinstance(codec.try_decode(hello_raw(engine="\u00e9" * 129)), ProtocolError)  # 258 bytes UTF-8


def test_a_hello_is_refused_with_nonce_0_or_a_session_header():
    codec = Codec()
    expect(codec, hello_raw(client_nonce=0), ErrorCode.OUT_OF_RANGE, "client_nonce")
    obj = raw(hello_raw())
    obj[3] = 5
    err = expect(codec, pack(obj), ErrorCode.BAD_HEADER, "session_id")
    assert err.client_nonce == 5  # answerable with Reject
    obj[3], obj[4] = 0, 9
    expect(codec, pack(obj), ErrorCode.BAD_HEADER, "token")


def test_a_truncated_hello_is_malformed_but_its_nonce_is_read():
    codec = Codec()
    pkt = hello_raw()
    for cut in (20, 40, len(pkt) - 1):
        err = expect(codec, pkt[:cut], ErrorCode.MALFORMED)
        assert (err.type_id, err.client_nonce) == (1, 5)
    err = expect(codec, cu_packet(codec)[:-5], ErrorCode.MALFORMED)
    assert (err.type_id, err.session_id, err.seq) == (0, 0, 0)  # only a Hello is attributed


def test_oversize_checked_before_unpacking():
    codec = Codec(Limits(max_packet_bytes=512))
    # Not even msgpack: a decoder that unpacked first would say MALFORMED.
    expect(codec, b"\xc1" * 513, ErrorCode.OVERSIZE)
    expect(codec, cu_packet(codec, n=8), ErrorCode.OVERSIZE)
    assert not isinstance(codec.try_decode(cu_packet(codec, n=4)), ProtocolError)


def test_msgpack_limits_bound_elements():
    codec = Codec(Limits(max_contacts=4))
    pkt = cu_packet(Codec(), n=4)
    big = mutate(pkt, 10, b"\x00" * (codec.limits.max_bin_bytes + 8))
    expect(codec, big, ErrorCode.MALFORMED)  # bin over max_bin_len aborts inside the unpacker
    expect(codec, pack([1, 0, 6, 1, 1] + [0] * 100), ErrorCode.MALFORMED)  # array over max_array_len


def test_bad_header():
    codec = Codec()
    expect(codec, pack(5), ErrorCode.BAD_HEADER)
    expect(codec, pack([1, 0, 6]), ErrorCode.BAD_HEADER)
    expect(codec, pack([1, 0, 6, -1, 0, 1, 1.0]), ErrorCode.BAD_HEADER)
    expect(codec, pack([True, 0, 6, 1, 1, 1, 1.0]), ErrorCode.BAD_HEADER)  # bool is not an int
    expect(codec, pack([1, 0, 6, 1, -(2 ** 63), 1, 1.0]), ErrorCode.BAD_HEADER)  # token must be unsigned
    expect(codec, pack([1, 0, 99, 1, 1]), ErrorCode.UNKNOWN_TYPE)
    welcome = all_messages()[4]
    expect(codec, mutate(codec.encode(welcome), 4, 0), ErrorCode.BAD_HEADER, "session_id")


def test_unknown_major():
    codec = Codec()
    hb = codec.encode(Heartbeat(seq=1, time_s=0.0, session_id=1, token=1))
    expect(codec, mutate(hb, 0, 2), ErrorCode.UNKNOWN_MAJOR)
    # A Hello of another major still yields its frozen prefix, so the server can Reject it.
    hello = raw(codec.encode(all_messages()[0]))
    hello[0] = 2
    hello[7] = [2, 0]
    hello[8:] = ["a v2 body we cannot read"]
    err = expect(codec, pack(hello), ErrorCode.UNKNOWN_MAJOR)
    assert err.client_nonce == 5 and err.version_min == (1, 0) and err.version_max == (2, 0)
    # Reject's layout is frozen: readable whatever the major.
    rej = mutate(codec.encode(all_messages()[5]), 0, 7)
    assert isinstance(codec.decode(rej), Reject)


def test_missing_fields():
    codec = Codec()
    pkt = cu_packet(codec)
    for k in range(5, 11):
        expect(codec, pack(raw(pkt)[:k]), ErrorCode.MISSING_FIELD, M.CONTACT_UPDATE.fields[k - 5].name)
    hello = raw(codec.encode(all_messages()[0]))
    expect(codec, pack(hello[:-1]), ErrorCode.MISSING_FIELD, "held_link")


@pytest.mark.parametrize("index,value,code,field", [
    (5, "1", ErrorCode.WRONG_TYPE, "seq"),
    (5, 1.0, ErrorCode.WRONG_TYPE, "seq"),
    (5, 0, ErrorCode.OUT_OF_RANGE, "seq"),
    (6, "t", ErrorCode.WRONG_TYPE, "env_time_s"),
    (6, None, ErrorCode.WRONG_TYPE, "env_time_s"),
    (7, list(IDENTITY), ErrorCode.WRONG_TYPE, "tool_pose"),
    (7, f64bin(IDENTITY[:6]), ErrorCode.BAD_SHAPE, "tool_pose"),
    (8, 4.0, ErrorCode.WRONG_TYPE, "contact_count"),
    (8, -1, ErrorCode.OUT_OF_RANGE, "contact_count"),
    (8, 3, ErrorCode.BAD_SHAPE, "contact_keys"),
    (9, [1, 2, 3], ErrorCode.WRONG_TYPE, "contact_keys"),
    (9, b"\x00" * 23, ErrorCode.BAD_SHAPE, "contact_keys"),
    (10, "data", ErrorCode.WRONG_TYPE, "contact_data"),
    (10, b"\x00" * 255, ErrorCode.BAD_SHAPE, "contact_data"),
])
def test_contact_update_wrong_types_and_shapes(index, value, code, field):
    codec = Codec()
    expect(codec, mutate(cu_packet(codec, n=4), index, value), code, field)


def test_env_time_accepts_integers():
    codec = Codec()
    m = codec.decode(mutate(cu_packet(codec), 6, 3))  # JavaScript encoders pack 3.0 as 3
    assert m.env_time_s == 3.0 and type(m.env_time_s) is float


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
@pytest.mark.parametrize("column,offset", [("position", 0), ("normal", 12), ("separation", 24), ("v_constr", 28)])
def test_non_finite_in_every_contact_column(bad, column, offset):
    codec = Codec()
    pkt = cu_packet(codec, n=4)
    data = np.frombuffer(raw(pkt)[10], "<f8").copy()
    data[offset + 1] = bad
    expect(codec, mutate(pkt, 10, data.tobytes()), ErrorCode.NON_FINITE, "contact_data")


@pytest.mark.parametrize("bad", [math.nan, math.inf])
def test_non_finite_pose_and_time(bad):
    codec = Codec()
    pkt = cu_packet(codec)
    for i in range(7):
        pose = list(IDENTITY)
        pose[i] = bad
        expect(codec, mutate(pkt, 7, f64bin(pose)), ErrorCode.NON_FINITE, "tool_pose")
    expect(codec, mutate(pkt, 6, bad), ErrorCode.NON_FINITE, "env_time_s")


def test_out_of_range_floats():
    codec = Codec()
    pkt = cu_packet(codec, n=2)
    data = np.frombuffer(raw(pkt)[10], "<f8").copy()
    data[0] = 2 * M.MAX_ABS_FLOAT
    expect(codec, mutate(pkt, 10, data.tobytes()), ErrorCode.OUT_OF_RANGE, "contact_data")
    data[0] = 1e200  # its square overflows: must be a clean error, not a warning or inf
    expect(codec, mutate(pkt, 10, data.tobytes()), ErrorCode.OUT_OF_RANGE, "contact_data")
    expect(codec, mutate(pkt, 6, -1e300), ErrorCode.OUT_OF_RANGE, "env_time_s")


def test_unit_normal_tolerance_is_exact():
    codec = Codec()
    pkt = cu_packet(codec, n=8)
    base = np.frombuffer(raw(pkt)[10], "<f8").copy()
    for scale, ok in [(1 + 0.5e-6, True), (1 - 0.9e-6, True), (1 + 1.1e-6, False), (1 - 1.1e-6, False), (0.0, False), (2.0, False)]:
        data = base.copy()
        data[3 * 8 + 6: 3 * 8 + 9] *= scale  # contact 2's normal
        out = codec.try_decode(mutate(pkt, 10, data.tobytes()))
        if ok:
            assert not isinstance(out, ProtocolError), (scale, out)
        else:
            assert isinstance(out, ProtocolError) and out.code == ErrorCode.NOT_UNIT, (scale, out)
            assert "contact 2" in out.detail
    pose = list(IDENTITY)
    pose[3] = 1.01
    expect(codec, mutate(pkt, 7, f64bin(pose)), ErrorCode.NOT_UNIT, "tool_pose")


def test_many_slightly_off_normals_all_within_tolerance_are_accepted():
    # The fast sufficient test fails here (sum of squared deviations too big); the exact test must accept.
    codec = Codec()
    pkt = cu_packet(codec, n=64)
    data = np.frombuffer(raw(pkt)[10], "<f8").copy()
    data[64 * 3: 64 * 6] *= 1 + 0.9e-6
    assert not isinstance(codec.try_decode(mutate(pkt, 10, data.tobytes())), ProtocolError)


def test_too_many_contacts():
    codec = Codec(Limits(max_contacts=8))
    expect(codec, cu_packet(Codec(), n=9), ErrorCode.TOO_MANY_CONTACTS, "contact_count")
    assert not isinstance(codec.try_decode(cu_packet(Codec(), n=8)), ProtocolError)
    with pytest.raises(ValueError, match="max_contacts"):
        cu_packet(codec, n=9)


def test_duplicate_keys():
    codec = Codec()
    keys, pos, nor, d, v = contacts(6)
    keys[4] = keys[1]
    pkt = Codec().encode_contact_update(1, 1, 1, 0.0, IDENTITY, keys, pos, nor, d, v)
    expect(codec, pkt, ErrorCode.DUPLICATE_KEY, "contact_keys")
    with pytest.raises(ValueError, match="contact_keys"):
        codec.encode_contact_update(1, 1, 1, 0.0, IDENTITY, keys, pos, nor, d, v, check=True)


def hello_raw(**changes) -> bytes:
    codec = Codec()
    msg = all_messages()[3] if changes.pop("linkage", False) else all_messages()[0]
    obj = raw(codec.encode(msg))
    for name, value in changes.items():
        obj[5 + M.HELLO.field_index(name)] = value
    return pack(obj)


@pytest.mark.parametrize("changes,code,field", [
    (dict(mass_kg=-1.0), ErrorCode.OUT_OF_RANGE, "mass_kg"),
    (dict(mass_kg=0.0), ErrorCode.OUT_OF_RANGE, "mass_kg"),
    (dict(inertia_kg_m2=[-0.1, 0.1, 0.1, 0, 0, 0]), ErrorCode.OUT_OF_RANGE, "inertia_kg_m2"),
    (dict(inertia_kg_m2=[0.1, 0.1, 0.1, 0.5, 0, 0]), ErrorCode.OUT_OF_RANGE, "inertia_kg_m2"),  # not PSD
    (dict(inertia_kg_m2=[0.0, 0.1, 0.1, 0, 0, 0]), ErrorCode.OUT_OF_RANGE, "inertia_kg_m2"),  # spatial needs > 0
    (dict(inertia_kg_m2=[0.1, 0.1]), ErrorCode.BAD_SHAPE, "inertia_kg_m2"),
    (dict(inertia_kg_m2=[0.1, 0.1, math.nan, 0, 0, 0]), ErrorCode.NON_FINITE, "inertia_kg_m2"),
    (dict(tool_kind=9), ErrorCode.OUT_OF_RANGE, "tool_kind"),
    (dict(axis=[1.0, 1.0, 0.0]), ErrorCode.NOT_UNIT, "axis"),
    (dict(epsilon_m=-0.001), ErrorCode.OUT_OF_RANGE, "epsilon_m"),
    (dict(max_contacts=0), ErrorCode.OUT_OF_RANGE, "max_contacts"),
    (dict(engine=5), ErrorCode.WRONG_TYPE, "engine"),
    (dict(version_min=[1]), ErrorCode.BAD_SHAPE, "version_min"),
    (dict(links=[list(LINK0.values())]), ErrorCode.BAD_TREE, "links"),  # spatial tool with links
    (dict(held_link=1), ErrorCode.BAD_TREE, "held_link"),
])
def test_hello_validation(changes, code, field):
    expect(Codec(), hello_raw(**changes), code, field)


def link_rec(link: dict) -> list:
    return [list(v) if isinstance(v, tuple) else v for v in link.values()]


@pytest.mark.parametrize("links,held,field", [
    ([], 0, "links"),
    ([link_rec(dict(LINK0, parent=0))], 0, "links[0]"),
    ([link_rec(LINK0), link_rec(dict(LINK1, parent=1))], 0, "links[1].parent"),
    ([link_rec(LINK0), link_rec(dict(LINK1, joint_type=0))], 0, "links[1].joint_type"),
    ([link_rec(LINK0), link_rec(LINK1)], 2, "held_link"),
])
def test_linkage_tree_validation(links, held, field):
    expect(Codec(), hello_raw(linkage=True, links=links, held_link=held), ErrorCode.BAD_TREE, field)


def test_linkage_link_fields_validated():
    bad = link_rec(dict(LINK1, mass_kg=-2.0))
    expect(Codec(), hello_raw(linkage=True, links=[link_rec(LINK0), bad]), ErrorCode.OUT_OF_RANGE, "links[1].mass_kg")
    bad = link_rec(dict(LINK1, joint_axis=(0.0, 0.0, 2.0)))
    expect(Codec(), hello_raw(linkage=True, links=[link_rec(LINK0), bad]), ErrorCode.NOT_UNIT, "links[1].joint_axis")
    short = link_rec(LINK1)[:3]
    expect(Codec(), hello_raw(linkage=True, links=[link_rec(LINK0), short]), ErrorCode.MISSING_FIELD, "links[1]")


def test_proxy_state_validation():
    codec = Codec()
    pkt = codec.encode(all_messages()[6])
    idx = 5 + M.PROXY_STATE.field_index("wrench")
    expect(codec, mutate(pkt, idx, f64bin([0, 0, math.nan, 0, 0, 0])), ErrorCode.NON_FINITE, "wrench")
    expect(codec, mutate(pkt, idx, f64bin([0, 0, 0])), ErrorCode.BAD_SHAPE, "wrench")
    idx = 5 + M.PROXY_STATE.field_index("proxy_pose")
    expect(codec, mutate(pkt, idx, f64bin([0, 0, 0, 2, 0, 0, 0])), ErrorCode.NOT_UNIT, "proxy_pose")


def test_encoder_names_the_bad_field():
    codec = Codec()
    keys, pos, nor, d, v = contacts(3)
    with pytest.raises(ValueError, match="normal"):
        codec.encode_contact_update(1, 1, 1, 0.0, IDENTITY, keys, pos, nor[:2], d, v)
    with pytest.raises(ValueError, match="keys"):
        codec.encode_contact_update(1, 1, 1, 0.0, IDENTITY, keys.astype(np.int32), pos, nor, d, v)
    nor2 = nor.copy()
    nor2[0, 0] = math.nan
    with pytest.raises(ValueError, match="contact_data"):
        codec.encode_contact_update(1, 1, 1, 0.0, IDENTITY, keys, pos, nor2, d, v, check=True)
    assert codec.counters.rejected == 0  # a self-check is not traffic
    with pytest.raises(ValueError, match="mass_kg"):
        codec.encode(Hello(client_nonce=1, tool_kind=3, mass_kg=-1.0, max_contacts=1))
    with pytest.raises(ValueError, match="token"):
        codec.encode(Heartbeat(seq=1, time_s=0.0, session_id=1, token=-1))


# ----------------------------------------------------------------------------- versioning
def test_newer_minor_trailing_fields_are_ignored_and_counted():
    codec = Codec()
    hb = raw(codec.encode(Heartbeat(seq=2, time_s=1.0, session_id=1, token=1)))
    hb[1] = 3  # a sender speaking minor 3
    out = codec.decode(pack(hb + [42, "future", [1.0, 2.0]]))
    assert isinstance(out, Heartbeat) and out.seq == 2 and out.minor == 3 and out.unknown_fields == 3
    obj = raw(cu_packet(codec, n=4))
    obj[1] = 5  # after 1.4's work_on_tool_j (1.1's tool_joint_position empty), one field this codec does not know
    cu = codec.decode(pack(obj + [b"", 7.0, 7]))
    assert cu.unknown_fields == 1 and cu.n_contacts == 4 and cu.work_on_tool_j == 7.0
    assert codec.counters.unknown_trailing_fields == 4
    assert codec.counters.packets_with_unknown_fields == 2


def test_newer_minor_extra_contact_column_is_ignored_and_counted():
    codec = Codec()
    obj = raw(cu_packet(codec, n=4))
    ref = codec.decode(pack(obj))
    obj[10] = obj[10] + f64bin([9.0, 9.0, 9.0, 9.0])  # one more column block of n float64
    out = codec.decode(pack(obj))
    assert out.unknown_fields == 1
    assert codec.counters.unknown_trailing_fields == 1 and codec.counters.packets_with_unknown_fields == 1
    np.testing.assert_array_equal(out.v_constr_m_per_s, ref.v_constr_m_per_s)
    np.testing.assert_array_equal(out.position_m, ref.position_m)


def test_older_minor_missing_defaulted_fields_get_defaults():
    # A v1.1 declaration appends a defaulted field; the v1.1 codec reads v1.0 packets and vice versa.
    class Heartbeat13(Heartbeat, kw_only=True):
        battery: M.f64("test-only field", since=3) = 1.0

    M.check_declarations(tuple(Heartbeat13 if c is Heartbeat else c for c in M.MESSAGE_CLASSES.values()))
    new, old = Codec(messages=[Heartbeat13], minor=3), Codec(minor=2)
    from_old = new.decode(old.encode(Heartbeat(seq=1, time_s=0.0, session_id=1, token=1)))
    assert from_old.battery == 1.0 and from_old.minor == 2
    cls11 = type(from_old)
    pkt11 = new.encode(cls11(seq=2, time_s=0.5, battery=0.3, session_id=1, token=1))
    from_new = old.decode(pkt11)
    assert from_new.seq == 2 and from_new.minor == 3 and from_new.unknown_fields == 1
    assert old.counters.unknown_trailing_fields == 1


def test_contact_update_1_1_carries_a_linkage_engine_s_joint_positions():
    """1.1 appends tool_joint_position: a 1.1 decoder reads it (empty when absent, as from a 1.0
    sender); a 1.0 decoder would count it as one unknown trailing field."""
    codec = Codec()
    keys, pos, nor, d, v = contacts(3, seed=3)
    pose = np.array([0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0])
    joints = np.array([0.3, -1.2, 0.01])
    pkt = codec.encode_contact_update(1, 2, 5, 0.5, pose, keys, pos, nor, d, v, tool_joint_position=joints)
    m = codec.decode(pkt)
    np.testing.assert_array_equal(m.tool_joint_position, joints)
    assert m.unknown_fields == 0 and len(raw(pkt)) == 12
    assert codec.decode(codec.encode_contact_update(1, 2, 6, 0.5, pose, keys, pos, nor, d, v)).tool_joint_position.shape == (0,)
    assert codec.decode(codec.encode(m)).tool_joint_position.tolist() == joints.tolist()
    obj = raw(pkt)
    for bad, code in ((7, ErrorCode.WRONG_TYPE), (b"1234567", ErrorCode.BAD_SHAPE), (b"\x00" * 8 * 33, ErrorCode.BAD_SHAPE),
                      (np.array([np.nan]).tobytes(), ErrorCode.NON_FINITE)):
        expect(codec, pack(obj[:11] + [bad]), code)


def test_counters_cover_every_code_below_20():
    names = set(Codec().counters.as_dict())
    for code in ErrorCode:
        if code < 20:
            assert code.name.lower() in names


def test_proxy_state_encoder_refuses_bad_values():
    codec = Codec()
    good = dict(session_id=1, token=2, seq=1, ack_seq=0, server_time_s=0.0, proxy_pose=IDENTITY,
                proxy_twist=np.zeros(6), wrench=np.zeros(6))
    codec.encode_proxy_state(**good)
    for change, match in [(dict(wrench=np.array([0, 0, math.nan, 0, 0, 0])), "ProxyState arrays"),
                          (dict(proxy_pose=(0, 0, 0, 2.0, 0, 0, 0)), "quaternion"),
                          (dict(proxy_twist=np.zeros(5)), "proxy_twist"),
                          (dict(joint_position=[0.1], joint_velocity=[]), "same length"),
                          (dict(seq=0), "seq"),
                          (dict(server_time_s=math.inf), "server_time_s")]:
        with pytest.raises(ValueError, match=match):
            codec.encode_proxy_state(**{**good, **change})
    assert codec.counters.encoded == 1


# ------------------------------------------------------------------ decode fast paths (exactness)
def _exact_unit_verdict(normal: np.ndarray) -> bool:
    # The rule on the same |n_i|^2 the decoder computes (n*n @ [1,1,1]), per contact.
    sq = (normal * normal).dot(np.ones(3))
    lo, hi = (1.0 - M.UNIT_TOLERANCE) ** 2, (1.0 + M.UNIT_TOLERANCE) ** 2
    return bool(np.all((sq >= lo) & (sq <= hi)))


@pytest.mark.parametrize("n", [1, 2, 7, 32, 45, 64, 65, 100])
def test_unit_normal_fast_tests_agree_with_the_exact_rule(n):
    # Normals scaled to within a few 1e-7 of the tolerance either side, many of them at once
    # (the sufficient tests fail, the exact one decides) or one at a time (they decide alone).
    codec = Codec(Limits(max_contacts=128, max_packet_bytes=16384))
    rng = np.random.default_rng(n)
    pkt = cu_packet(codec, n=n)
    base = np.frombuffer(raw(pkt)[10], "<f8").copy()
    verdicts = set()
    for case in range(60):
        data = base.copy()
        nor = data[3 * n: 6 * n].reshape(n, 3)
        rows = rng.random(n) < (0.05 if case % 3 else 1.0)
        width = [0.2e-6, 0.9e-6, 1.05e-6, 1.3e-6][case % 4]
        nor[rows] *= 1.0 + rng.uniform(-width, width, size=(int(rows.sum()), 1))
        expect_ok = _exact_unit_verdict(nor)
        out = codec.try_decode(mutate(pkt, 10, data.tobytes()))
        if expect_ok:
            assert not isinstance(out, ProtocolError), (case, out)
            np.testing.assert_array_equal(out.normal, nor)
        else:
            assert isinstance(out, ProtocolError) and out.code == ErrorCode.NOT_UNIT, (case, out)
        verdicts.add(expect_ok)
    assert verdicts == {True, False}  # both sides of the boundary were exercised


def test_one_codec_shared_by_threads_gives_every_packet_its_own_verdict():
    # The unit-normal test writes scratch; it is per thread, so concurrent decodes on one codec
    # (e.g. the module-level one) never judge a packet by another packet's numbers.
    import threading

    codec = Codec()
    good = cu_packet(codec, n=32)
    data = np.frombuffer(raw(good)[10], "<f8").copy()
    data[3 * 32: 3 * 32 + 3] *= 1.5
    bad = mutate(good, 10, data.tobytes())
    wrong = []

    def work(pkt, ok):
        for _ in range(3000):
            out = codec.try_decode(pkt)
            if isinstance(out, ProtocolError) == ok:
                wrong.append(out)

    threads = [threading.Thread(target=work, args=(good, True)), threading.Thread(target=work, args=(bad, False))]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert wrong == []


def test_large_contact_limit_builds_per_count_tables_lazily():
    codec = Codec(Limits(max_contacts=65535, max_packet_bytes=65507))
    for n in (1, 3, 700):
        out = codec.decode(cu_packet(Codec(Limits(max_contacts=700, max_packet_bytes=65507)), n=n))
        assert out.n_contacts == n


def test_duplicate_key_anywhere_is_found():
    codec = Codec()
    keys, pos, nor, d, v = contacts(64)
    for i, j in [(0, 63), (31, 32), (5, 6), (62, 63)]:
        k = keys.copy()
        k[j] = k[i]
        pkt = Codec().encode_contact_update(1, 1, 1, 0.0, IDENTITY, k, pos, nor, d, v)
        expect(codec, pkt, ErrorCode.DUPLICATE_KEY, "contact_keys")
    # Keys differing in one int64 only (any column, any byte) are distinct.
    for col in range(3):
        k = np.zeros((2, 3), np.int64)
        k[1, col] = 1 << 56
        pkt = Codec().encode_contact_update(1, 1, 1, 0.0, IDENTITY, k, pos[:2], nor[:2], d[:2], v[:2])
        assert not isinstance(codec.try_decode(pkt), ProtocolError)


@pytest.mark.parametrize("n", [2, 16, 32, 64, 65])
def test_normal_one_ulp_outside_the_window_is_rejected_and_inside_accepted(n):
    # One contact's |n|^2 on either side of the window's edge, the rest unit: the sum of squared
    # deviations then sits at the sufficient test's threshold, where rounding must not let an
    # outside value through.
    codec = Codec(Limits(max_contacts=128, max_packet_bytes=16384))
    pkt = cu_packet(codec, n=n)
    base = np.frombuffer(raw(pkt)[10], "<f8").copy()
    lo, hi = (1.0 - M.UNIT_TOLERANCE) ** 2, (1.0 + M.UNIT_TOLERANCE) ** 2
    for edge, up in ((hi, True), (lo, False)):
        x = math.sqrt(edge)
        while (x * x <= edge) if up else (x * x >= edge):  # first x outside the window
            x = math.nextafter(x, math.inf if up else 0.0)
        inside = math.nextafter(x, 0.0 if up else math.inf)
        while not lo <= inside * inside <= hi:
            inside = math.nextafter(inside, 0.0 if up else math.inf)
        for value, ok in ((x, False), (inside, True)):
            for row in (0, n - 1):
                data = base.copy()
                data[3 * n + 3 * row: 3 * n + 3 * row + 3] = (value, 0.0, 0.0)
                out = codec.try_decode(mutate(pkt, 10, data.tobytes()))
                assert isinstance(out, ProtocolError) != ok, (edge, value, row, out)



def test_a_1_4_update_carries_the_engines_grant_and_older_ones_default_to_none():
    """ContactUpdate.work_on_tool_j (1.4): encoded only when not 0 (after an empty
    tool_joint_position for a rigid tool), decoded, 0 from a 1.3 packet, refused by name when
    negative (decoder and encoder alike); a 1.3 codec leaves it out."""
    codec = Codec()
    args = dict(session_id=3, token=4, seq=9, env_time_s=0.5, tool_pose=np.array([0, 0, 0, 1.0, 0, 0, 0]),
                keys=np.zeros((1, 3), np.int64), position_m=np.zeros((1, 3)), normal=np.array([[0.0, 0.0, 1.0]]),
                separation_m=np.zeros(1), v_constr_m_per_s=np.zeros(1))
    plain = raw(codec.encode_contact_update(**args))
    assert len(plain) == 11  # no grant: the 1.0 layout
    pk = codec.encode_contact_update(**args, work_on_tool_j=0.004)
    obj = raw(pk)
    assert len(obj) == 13 and obj[11] == b"" and obj[12] == 0.004
    out = codec.decode(pk)
    assert out.work_on_tool_j == 0.004 and out.unknown_fields == 0 and len(out.tool_joint_position) == 0
    assert codec.decode(codec.encode(out)).work_on_tool_j == 0.004  # through the message too
    assert codec.decode(pack(plain)).work_on_tool_j == 0.0
    bad = obj.copy()
    bad[12] = -0.001
    with pytest.raises(ProtocolError) as e:
        codec.decode(pack(bad))
    assert e.value.field == "work_on_tool_j"
    with pytest.raises(ValueError, match="work_on_tool_j"):
        codec.encode_contact_update(**args, work_on_tool_j=math.nan)
    assert len(raw(Codec(minor=3).encode_contact_update(**args, work_on_tool_j=0.004))) == 11
