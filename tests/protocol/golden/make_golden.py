"""Write ``codec_golden.json``: wire bytes and decode verdicts of the codec as it was before the
msgspec rewrite (issue 14 item 2). Run once from the old codec; the file is the reference the
new codec must reproduce (``tests/protocol/test_golden.py``).

    python tests/protocol/golden/make_golden.py   # rewrites codec_golden.json next to this file

Every entry is plain JSON: packets as hex, arrays as ``{"dtype", "shape", "data"}``. Messages are
described by the keyword arguments of their constructors (``Hello(**kwargs)``) or of
``Codec.encode_contact_update`` / ``encode_proxy_state``, so both codecs build them the same way.
"""
from __future__ import annotations

import json
import math
from enum import IntEnum
from pathlib import Path

import msgpack
import numpy as np

from hapticproxy.protocol import codec as C
from hapticproxy.protocol.session import MacFramer

OUT = Path(__file__).with_name("codec_golden.json")
IDENTITY = [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]
POSE = [0.1, -0.2, 0.3, math.cos(0.2), 0.0, 0.0, math.sin(0.2)]
LINK0 = dict(mass_kg=1.0, com_m=[0.0, 0.0, 0.1], inertia_kg_m2=[0.01, 0.01, 0.02, 0.0, 0.0, 0.0], parent=-1,
             joint_type=0, joint_axis=[1.0, 0.0, 0.0], joint_origin=IDENTITY)
LINK1 = dict(LINK0, parent=0, joint_type=1, joint_axis=[0.0, 0.0, 1.0], joint_origin=[0.0, 0.0, 0.2, 1.0, 0.0, 0.0, 0.0])
LINK2 = dict(LINK0, mass_kg=0.3, parent=1, joint_type=2, joint_axis=[1.0, 0.0, 0.0],
             joint_origin=[0.1, 0.0, 0.0, math.cos(0.3), 0.0, 0.0, math.sin(0.3)])
HMAC_KEY = bytes(range(32))


def arr(a) -> dict:
    a = np.asarray(a)
    return {"dtype": str(a.dtype), "shape": list(a.shape), "data": a.ravel().tolist()}


def plain(v):
    """A decoded attribute as JSON."""
    if isinstance(v, np.ndarray):
        return arr(v)
    if isinstance(v, IntEnum):
        return int(v)
    if isinstance(v, (tuple, list)):
        return [plain(x) for x in v]
    if isinstance(v, dict):
        return {k: plain(x) for k, x in v.items()}
    return v


def contacts(n: int, seed: int):
    rng = np.random.default_rng(seed)
    keys = np.column_stack([np.zeros(n, np.int64), np.arange(n, dtype=np.int64) // 4,
                            np.arange(n, dtype=np.int64) * 1_000_003 - 7]).astype(np.int64)
    pos = rng.normal(size=(n, 3))
    nor = rng.normal(size=(n, 3))
    nor /= np.linalg.norm(nor, axis=1)[:, None]
    return dict(keys=keys.tolist(), position_m=pos.tolist(), normal=nor.tolist(),
                separation_m=(rng.normal(size=n) * 1e-3).tolist(), v_constr_m_per_s=(rng.normal(size=n) * 1e-2).tolist())


def cu_args(n: int, seed: int = 0, **over) -> dict:
    a = dict(session_id=0x12345678, token=0xFEDCBA9876543210, seq=17, env_time_s=1.5, tool_pose=POSE)
    a.update(contacts(n, seed))
    a.update(over)
    return a


def call_cu(codec, a: dict) -> bytes:
    a = dict(a)
    for k in ("position_m", "normal"):
        a[k] = np.array(a[k], dtype=np.float64).reshape(-1, 3)
    a["keys"] = np.array(a["keys"], dtype=np.int64).reshape(-1, 3)
    for k in ("separation_m", "v_constr_m_per_s"):
        a[k] = np.array(a[k], dtype=np.float64)
    if a.get("tool_joint_position") is not None:
        a["tool_joint_position"] = np.array(a["tool_joint_position"], dtype=np.float64)
    return codec.encode_contact_update(**a)


def ps_args(**over) -> dict:
    a = dict(session_id=7, token=99, seq=3, ack_seq=2, server_time_s=0.5, proxy_pose=POSE,
             proxy_twist=[0.1, -0.2, 0.3, 0.0, 0.0, 1.5], wrench=[1.0, -2.0, 0.5, 0.0, 0.01, -0.02])
    a.update(over)
    return a


def call_ps(codec, a: dict) -> bytes:
    a = {k: (np.array(v, dtype=np.float64) if isinstance(v, list) else v) for k, v in a.items()}
    return codec.encode_proxy_state(**a)


def build(cls_name: str, kwargs: dict):
    kw = dict(kwargs)
    if "links" in kw:
        kw["links"] = tuple({k: (tuple(v) if isinstance(v, list) else v) for k, v in ln.items()} for ln in kw["links"])
    for k in ("proxy_pose", "proxy_twist", "wrench", "joint_position", "joint_velocity", "joint_effort"):
        if k in kw:
            kw[k] = np.array(kw[k], dtype=np.float64)
    for k in ("com_m", "inertia_kg_m2", "axis", "version", "version_min", "version_max"):
        if k in kw:
            kw[k] = tuple(kw[k])
    return getattr(C, cls_name)(**kw)


HELLO_SPATIAL = dict(client_nonce=5, engine="mujoco 3.1", tool_kind=3, mass_kg=1.0,
                     inertia_kg_m2=[0.1, 0.1, 0.1, 0.0, 0.0, 0.0], max_contacts=32, epsilon_m=0.005)
MESSAGES = {
    "hello_spatial": ("Hello", HELLO_SPATIAL),
    "hello_1dof": ("Hello", dict(client_nonce=6, engine="e", tool_kind=1, mass_kg=1.0, max_contacts=8, axis=[0.0, 1.0, 0.0])),
    "hello_planar": ("Hello", dict(client_nonce=2 ** 64 - 1, engine="pymunk 6.6 \u00e9\u00e8", tool_kind=2, mass_kg=0.25,
                                   inertia_kg_m2=[0.0, 0.0, 1e-3, 0.0, 0.0, 0.0], max_contacts=64, epsilon_m=0.0,
                                   env_rate_hz=30.0, com_m=[0.0, 0.01, 0.0])),
    "hello_linkage": ("Hello", dict(client_nonce=8, engine="e", tool_kind=4, mass_kg=2.3, max_contacts=16,
                                    links=[LINK0, LINK1, LINK2], held_link=1, version_min=[1, 0], version_max=[1, 1])),
    "welcome": ("Welcome", dict(client_nonce=5, version=[1, 0], haptic_rate_hz=1000.0, epsilon_m=0.005, max_contacts=32,
                                heartbeat_interval_s=0.1, silence_timeout_s=1.0, session_id=7, token=99)),
    "welcome_big_ids": ("Welcome", dict(client_nonce=2 ** 63 + 5, version=[1, 2], haptic_rate_hz=4000.0, epsilon_m=0.01,
                                        max_contacts=64, heartbeat_interval_s=0.05, silence_timeout_s=0.5,
                                        server_name="lab rig", session_id=0xFFFFFFFF, token=2 ** 64 - 1)),
    "reject": ("Reject", dict(client_nonce=5, code=40, reason="no common major")),
    "reject_nonce0": ("Reject", dict(client_nonce=0, code=44, reason="", version_min=[1, 0], version_max=[1, 2])),
    "proxy_state_obj": ("ProxyState", dict(seq=3, ack_seq=2, server_time_s=0.5, proxy_pose=IDENTITY,
                                           proxy_twist=[0.0, 1.0, 2.0, 3.0, 4.0, 5.0],
                                           wrench=[-3.0, -2.0, -1.0, 0.0, 1.0, 2.0], session_id=7, token=99)),
    "proxy_state_obj_linkage": ("ProxyState", dict(seq=3, ack_seq=2, server_time_s=0.5, proxy_pose=IDENTITY,
                                                   proxy_twist=[0.0] * 6, wrench=[0.0] * 6, joint_position=[0.1],
                                                   joint_velocity=[0.2], joint_effort=[0.3], server_state=2,
                                                   session_id=7, token=99)),
    "heartbeat": ("Heartbeat", dict(seq=1, time_s=2.0, session_id=7, token=99)),
    "heartbeat_big_seq": ("Heartbeat", dict(seq=2 ** 64 - 1, time_s=-1e9, session_id=1, token=1)),
    "bye": ("Bye", dict(code=60, reason="done", session_id=7, token=99)),
    "bye_default_reason": ("Bye", dict(code=62, session_id=7, token=99)),
    "error": ("Error", dict(code=8, field="contact_data", detail="nan", ref_type=4, ref_seq=9, session_id=7, token=99)),
    "error_defaults": ("Error", dict(code=25, session_id=7, token=99)),
}

CONTACT_UPDATES = {
    "cu_0": cu_args(0),
    "cu_1": cu_args(1, 1),
    "cu_32": cu_args(32, 32),
    "cu_64": cu_args(64, 64),
    "cu_joints": cu_args(3, 3, tool_joint_position=[0.3, -1.2, 0.01]),
    "cu_empty_joints": cu_args(2, 2, tool_joint_position=[]),
    "cu_small_ids": cu_args(2, 5, session_id=1, token=2, seq=1, env_time_s=0.0, tool_pose=IDENTITY),
}

PROXY_STATES = {
    "ps_rigid": ps_args(),
    "ps_rigid_state": ps_args(server_state=2),
    "ps_linkage": ps_args(joint_position=[0.1, -0.2], joint_velocity=[1.0, 2.0], joint_effort=[0.5, -0.5], server_state=3),
    "ps_fault": ps_args(server_state=4, seq=2 ** 64 - 1, ack_seq=2 ** 64 - 1),
}


def pk(obj) -> bytes:
    return msgpack.packb(obj, use_bin_type=True)


def mut(packet: bytes, index: int, value) -> bytes:
    obj = msgpack.unpackb(packet)
    obj[index] = value
    return pk(obj)


def f64(values) -> bytes:
    return np.asarray(values, "<f8").tobytes()


def invalid_packets(codec) -> list[tuple[str, bytes, dict | None]]:
    """(name, packet, limits overrides or None)."""
    cu4 = call_cu(codec, cu_args(4, 4))
    cu2 = call_cu(codec, cu_args(2, 2))
    cu8 = call_cu(codec, cu_args(8, 8))
    hello = codec.encode(build(*MESSAGES["hello_spatial"]))
    hello_l = codec.encode(build(*MESSAGES["hello_linkage"]))
    ps = codec.encode(build(*MESSAGES["proxy_state_obj"]))
    hb = codec.encode(build(*MESSAGES["heartbeat"]))
    welcome = codec.encode(build(*MESSAGES["welcome"]))
    out: list[tuple[str, bytes, dict | None]] = []
    add = lambda name, data, limits=None: out.append((name, data, limits))  # noqa: E731
    add("truncated", cu4[:-5])
    add("trailing_byte", cu4 + b"\x00")
    add("never_used_byte", b"\xc1")
    add("empty", b"")
    add("map", pk({"a": 1}))
    add("ext", pk(msgpack.ExtType(1, b"x")))
    add("invalid_utf8", b"\xa2\xff\xfe")
    add("oversize", b"\xc1" * 513, {"max_packet_bytes": 512})
    add("oversize_cu8", cu8, {"max_packet_bytes": 512})
    add("array_over_max_array_len", pk([1, 0, 6, 1, 1] + [0] * 100))
    add("not_array", pk(5))
    add("short_header", pk([1, 0, 6]))
    add("negative_session", pk([1, 0, 6, -1, 0, 1, 1.0]))
    add("bool_major", pk([True, 0, 6, 1, 1, 1, 1.0]))
    add("negative_token", pk([1, 0, 6, 1, -(2 ** 63), 1, 1.0]))
    add("float_type_id", pk([1, 0, 6.0, 1, 1, 1, 1.0]))
    add("unknown_type", pk([1, 0, 99, 1, 1]))
    add("welcome_session0", mut(welcome, 4, 0))
    add("welcome_token0", mut(welcome, 3, 0))
    add("major2_heartbeat", mut(hb, 0, 2))
    h2 = msgpack.unpackb(hello)
    h2[0] = 2
    h2[7] = [2, 0]
    h2[8:] = ["a v2 body we cannot read"]
    add("major2_hello", pk(h2))
    for k in range(5, 11):
        add(f"cu_missing_{k}", pk(msgpack.unpackb(cu4)[:k]))
    add("hello_missing_held_link", pk(msgpack.unpackb(hello)[:-1]))
    add("hello_only_nonce", pk(msgpack.unpackb(hello)[:6]))
    for i, (index, value) in enumerate([
            (5, "1"), (5, 1.0), (5, 0), (6, "t"), (6, None), (7, IDENTITY), (7, f64(IDENTITY[:6])), (8, 4.0), (8, -1),
            (8, 3), (9, [1, 2, 3]), (9, b"\x00" * 23), (10, "data"), (10, b"\x00" * 255)]):
        add(f"cu_field_{index}_{i}", mut(cu4, index, value))
    add("cu_env_time_int_ok", mut(cu4, 6, 3))
    data = np.frombuffer(msgpack.unpackb(cu4)[10], "<f8")
    for bad in (math.nan, math.inf, -math.inf):
        for col, off in (("position", 0), ("normal", 12), ("separation", 24), ("v_constr", 28)):
            d = data.copy()
            d[off + 1] = bad
            add(f"cu_nonfinite_{col}_{bad}", mut(cu4, 10, d.tobytes()))
        for i in range(7):
            pose = list(IDENTITY)
            pose[i] = bad
            add(f"cu_pose_nonfinite_{i}_{bad}", mut(cu4, 7, f64(pose)))
        add(f"cu_time_nonfinite_{bad}", mut(cu4, 6, bad))
    d2 = np.frombuffer(msgpack.unpackb(cu2)[10], "<f8").copy()
    for name, v in (("2e9", 2e9), ("1e200", 1e200)):
        d = d2.copy()
        d[0] = v
        add(f"cu_data_out_of_range_{name}", mut(cu2, 10, d.tobytes()))
    add("cu_time_out_of_range", mut(cu4, 6, -1e300))
    add("cu_time_huge_int", mut(cu4, 6, 2 ** 40))
    add("cu_pose_position_out_of_range", mut(cu4, 7, f64([2e9, 0, 0, 1, 0, 0, 0])))
    for scale in (1 + 0.5e-6, 1 - 0.9e-6, 1 + 1.1e-6, 1 - 1.1e-6, 0.0, 2.0):
        d = data.copy()
        d[12 + 6:12 + 9] *= scale
        add(f"cu_normal_scale_{scale!r}", mut(cu4, 10, d.tobytes()))
    pose = list(IDENTITY)
    pose[3] = 1.01
    add("cu_pose_not_unit", mut(cu4, 7, f64(pose)))
    add("cu_too_many_contacts", call_cu(codec, cu_args(9, 9)), {"max_contacts": 8})
    a = cu_args(6, 6)
    a["keys"][4] = a["keys"][1]
    add("cu_duplicate_key", call_cu(codec, a))
    obj = msgpack.unpackb(call_cu(codec, cu_args(3, 3, tool_joint_position=[0.3, -1.2, 0.01])))
    for i, bad in enumerate((7, b"1234567", b"\x00" * 8 * 33, f64([math.nan]))):
        add(f"cu_joints_bad_{i}", pk(obj[:11] + [bad]))
    big = mut(call_cu(codec, cu_args(4, 4)), 10, b"\x00" * (C.Limits(max_contacts=4).max_bin_bytes + 8))
    add("cu_bin_over_max_bin_len", big, {"max_contacts": 4})
    # newer-minor packets: unknown trailing fields / column blocks (valid; counted)
    hbo = msgpack.unpackb(hb)
    hbo[1] = 3
    add("hb_trailing_fields_ok", pk(hbo + [42, "future", [1.0, 2.0]]))
    o = msgpack.unpackb(cu4)
    o[1] = 2
    add("cu_trailing_after_joints_ok", pk(o + [b"", 7]))
    o = msgpack.unpackb(cu4)
    o[10] = o[10] + f64([9.0] * 4)
    add("cu_extra_column_ok", pk(o))
    o = msgpack.unpackb(ps)
    add("ps_1_1_layout_ok", pk(o[:-1]))
    add("ps_trailing_ok", pk(o + [5]))
    # Hello content
    def hello_mut(base: bytes, **changes) -> bytes:
        ob = msgpack.unpackb(base)
        names = [f.name for f in C.HELLO.fields]
        for name, value in changes.items():
            ob[5 + names.index(name)] = value
        return pk(ob)
    for i, ch in enumerate([
            dict(mass_kg=-1.0), dict(mass_kg=0.0), dict(inertia_kg_m2=[-0.1, 0.1, 0.1, 0, 0, 0]),
            dict(inertia_kg_m2=[0.1, 0.1, 0.1, 0.5, 0, 0]), dict(inertia_kg_m2=[0.0, 0.1, 0.1, 0, 0, 0]),
            dict(inertia_kg_m2=[0.1, 0.1]), dict(inertia_kg_m2=[0.1, 0.1, math.nan, 0, 0, 0]), dict(tool_kind=9),
            dict(tool_kind=0), dict(axis=[1.0, 1.0, 0.0]), dict(epsilon_m=-0.001), dict(max_contacts=0),
            dict(max_contacts=70000), dict(engine=5), dict(version_min=[1]), dict(version_min=[1, 70000]),
            dict(version_min="1.0"), dict(links=[list(LINK0.values())]), dict(held_link=1), dict(units="mm"),
            dict(client_nonce=0), dict(client_nonce=-1), dict(env_rate_hz=0.0), dict(com_m=[0.0, 0.0]),
            dict(com_m=[0.0, "x", 0.0]), dict(axis=[0.0, 0.0, math.inf]), dict(mass_kg=True), dict(links="x"),
            dict(engine="x" * 300), dict(version_min=[1, 0], version_max=[3, 0])]):
        add(f"hello_{i}_{'_'.join(ch)}", hello_mut(hello, **ch))
    add("hello_planar_izz0", hello_mut(hello, tool_kind=2, inertia_kg_m2=[0.1, 0.1, 0.0, 0, 0, 0]))
    rec = lambda ln: list(ln.values())  # noqa: E731
    for i, (links, held) in enumerate([
            ([], 0), ([rec(dict(LINK0, parent=0))], 0), ([rec(LINK0), rec(dict(LINK1, parent=1))], 0),
            ([rec(LINK0), rec(dict(LINK1, joint_type=0))], 0), ([rec(LINK0), rec(LINK1)], 2),
            ([rec(LINK0), rec(dict(LINK1, mass_kg=-2.0))], 0), ([rec(LINK0), rec(dict(LINK1, joint_axis=[0.0, 0.0, 2.0]))], 0),
            ([rec(LINK0), rec(LINK1)[:3]], 0), ([rec(LINK0), rec(dict(LINK1, joint_type=7))], 0),
            ([rec(LINK0), rec(dict(LINK1, joint_origin=[0, 0, 0, 2.0, 0, 0, 0]))], 0),
            ([rec(LINK0), "x"], 0), ([rec(LINK0)] * 33, 0), ([rec(LINK0), rec(LINK1) + [1, 2]], 1),
            ([rec(LINK0), rec(dict(LINK1, inertia_kg_m2=[0.1, 0.1, 0.1, 0.5, 0, 0]))], 1)]):
        add(f"linkage_{i}", hello_mut(hello_l, links=links, held_link=held))
    # ProxyState content
    names = [f.name for f in C.PROXY_STATE.fields]
    idx = lambda n: 5 + names.index(n)  # noqa: E731
    add("ps_wrench_nan", mut(ps, idx("wrench"), f64([0, 0, math.nan, 0, 0, 0])))
    add("ps_wrench_short", mut(ps, idx("wrench"), f64([0, 0, 0])))
    add("ps_pose_not_unit", mut(ps, idx("proxy_pose"), f64([0, 0, 0, 2, 0, 0, 0])))
    add("ps_seq0", mut(ps, idx("seq"), 0))
    add("ps_ack_str", mut(ps, idx("ack_seq"), "x"))
    add("ps_time_nan", mut(ps, idx("server_time_s"), math.nan))
    add("ps_joint_mismatch", mut(ps, idx("joint_position"), f64([1.0])))
    add("ps_joint_odd_bytes", pk(msgpack.unpackb(ps)[:11] + [b"123", b"123", b"123", 2]))
    add("ps_state_9", mut(ps, idx("server_state"), 9))
    add("ps_state_str", mut(ps, idx("server_state"), "x"))
    add("ps_twist_list", mut(ps, idx("proxy_twist"), [0.0] * 6))
    add("ps_missing", pk(msgpack.unpackb(ps)[:10]))
    # Other messages
    add("hb_seq0", mut(hb, 5, 0))
    add("hb_time_str", mut(hb, 6, "x"))
    add("hb_missing", pk(msgpack.unpackb(hb)[:6]))
    err = codec.encode(build(*MESSAGES["error"]))
    add("error_code_str", mut(err, 5, "x"))
    add("error_ref_type_300", mut(err, 8, 300))
    add("error_long_str", pk([1, 0, 8, 1, 1, 9, "x" * 1000, ""]))
    bye = codec.encode(build(*MESSAGES["bye"]))
    add("bye_code_neg", mut(bye, 5, -1))
    add("bye_missing_reason", pk(msgpack.unpackb(bye)[:6]))
    rej = codec.encode(build(*MESSAGES["reject"]))
    add("reject_major7_ok", mut(rej, 0, 7))
    add("reject_version_bad", mut(rej, 8, [1]))
    add("welcome_rate0", mut(welcome, 7, 0.0))
    add("welcome_version_str", mut(welcome, 6, "1.0"))
    add("truncated_hello", hello[:40])
    return out


def decoded(msg) -> dict:
    attrs = {n: plain(getattr(msg, n)) for n in msg._ATTRS}
    for n in ("session_id", "token", "minor", "unknown_fields"):
        attrs[n] = plain(getattr(msg, n))
    return {"type": type(msg).__name__, "attrs": attrs}


def error_verdict(err: C.ProtocolError) -> dict:
    """A refused packet's verdict: the error code and field, and what the codec read of the packet."""
    return {"error": err.code.name, "field": err.field, "type_id": err.type_id, "session_id": err.session_id,
            "token": err.token, "seq": err.seq, "client_nonce": err.client_nonce,
            "version_min": list(err.version_min) if err.version_min else None,
            "version_max": list(err.version_max) if err.version_max else None}


def verdict(codec, data: bytes) -> dict:
    out = codec.try_decode(data)
    if isinstance(out, C.ProtocolError):
        return error_verdict(out)
    return {"ok": decoded(out)}


def main() -> None:
    codec = C.Codec()
    entries = []
    for name, (cls, kwargs) in MESSAGES.items():
        pkt = codec.encode(build(cls, kwargs))
        entries.append({"name": name, "build": {"message": cls, "kwargs": kwargs}, "hex": pkt.hex(),
                        "decoded": verdict(codec, pkt)})
    for name, a in CONTACT_UPDATES.items():
        pkt = call_cu(codec, a)
        entries.append({"name": name, "build": {"encode_contact_update": a}, "hex": pkt.hex(), "decoded": verdict(codec, pkt)})
    for name, a in PROXY_STATES.items():
        pkt = call_ps(codec, a)
        entries.append({"name": name, "build": {"encode_proxy_state": a}, "hex": pkt.hex(), "decoded": verdict(codec, pkt)})
    mac = MacFramer(HMAC_KEY)
    hb = codec.encode(build(*MESSAGES["heartbeat"]))
    hmac_entries = [{"name": "hmac_heartbeat", "key": HMAC_KEY.hex(), "packet": hb.hex(), "sealed": mac.seal(hb).hex()}]
    invalid = []
    for name, data, limits in invalid_packets(codec):
        c = C.Codec(C.Limits(**limits)) if limits else C.Codec()
        invalid.append({"name": name, "hex": data.hex(), "limits": limits, "verdict": verdict(c, data)})
    OUT.write_text(json.dumps({"about": __doc__.splitlines()[0], "messages": entries, "hmac": hmac_entries,
                               "packets": invalid}, indent=1) + "\n", encoding="utf-8")
    print(f"wrote {OUT}: {len(entries)} messages, {len(invalid)} packets")


if __name__ == "__main__":
    main()
