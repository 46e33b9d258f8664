"""``hapticproxy bench codec [--json]``: protocol codec speed against a naive codec, same run.

For each row the message is encoded and decoded (decode includes full validation and yields the
numpy arrays the server's local model reads) by :class:`hapticproxy.protocol.codec.Codec`, and
the same content by a *naive* codec: plain ``msgpack.packb`` of a dict with one dict per contact
(lists of floats), decoded with ``msgpack.unpackb`` and turned into the same numpy arrays with the
same checks (finite values, unit normals, unique keys). ``server_decode_median_us``: the decode of
the server's codec, whose value rules a numba kernel vouches for (``server/ingest.py``; the same
verdicts). Times are medians over batches of
``time.perf_counter_ns`` (per call = batch time / batch size), so timer overhead is amortised.
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time

import msgpack
import numpy as np

from ..protocol.logs import doc_summary
from ..protocol.codec import Codec, ProtocolError, ProxyState
from ..protocol.jsonout import print_json

CONTACT_COUNTS = (0, 8, 32, 64)
POSE = np.array([0.1, -0.2, 0.3, 1.0, 0.0, 0.0, 0.0])


def make_contacts(n: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    keys = np.column_stack([np.zeros(n), np.arange(n) // 4, np.arange(n)]).astype(np.int64)
    normal = rng.normal(size=(n, 3))
    normal /= np.linalg.norm(normal, axis=1)[:, None]
    return keys, rng.normal(size=(n, 3)), normal, rng.normal(size=n) * 1e-3, rng.normal(size=n) * 1e-2


# ------------------------------------------------------------------------------ naive codec
def naive_encode_contacts(seq, env_time_s, pose, keys, position_m, normal, separation_m, v_constr_m_per_s) -> bytes:
    contacts = [
        {"key": k, "position": p, "normal": nn, "separation": d, "v_constr": v}
        for k, p, nn, d, v in zip(keys.tolist(), position_m.tolist(), normal.tolist(), separation_m.tolist(),
                                  v_constr_m_per_s.tolist())
    ]
    return msgpack.packb({"type": "ContactUpdate", "session_id": 1, "token": 2, "seq": seq, "env_time_s": env_time_s,
                          "tool_pose": list(pose), "contacts": contacts})


def naive_decode_contacts(data: bytes):
    m = msgpack.unpackb(data)
    cs = m["contacts"]
    n = len(cs)
    keys = np.array([c["key"] for c in cs], dtype=np.int64).reshape(n, 3)
    pos = np.array([c["position"] for c in cs], dtype=np.float64).reshape(n, 3)
    nor = np.array([c["normal"] for c in cs], dtype=np.float64).reshape(n, 3)
    sep = np.array([c["separation"] for c in cs], dtype=np.float64)
    vc = np.array([c["v_constr"] for c in cs], dtype=np.float64)
    pose = np.array(m["tool_pose"], dtype=np.float64)
    if not (np.isfinite(pos).all() and np.isfinite(nor).all() and np.isfinite(sep).all() and np.isfinite(vc).all()
            and np.isfinite(pose).all()):
        raise ValueError("non-finite")
    if n and not (np.abs(np.linalg.norm(nor, axis=1) - 1.0) <= 1e-6).all():
        raise ValueError("normal")
    if len({tuple(k) for k in keys.tolist()}) != n:
        raise ValueError("duplicate key")
    return keys, pos, nor, sep, vc, pose


def naive_encode_proxy(msg) -> bytes:
    return msgpack.packb({"type": "ProxyState", "session_id": 1, "token": 2, "seq": msg.seq, "ack_seq": msg.ack_seq,
                          "server_time_s": msg.server_time_s, "proxy_pose": msg.proxy_pose.tolist(),
                          "proxy_twist": msg.proxy_twist.tolist(), "wrench": msg.wrench.tolist(),
                          "joint_position": [], "joint_velocity": [], "joint_effort": []})


def naive_decode_proxy(data: bytes):
    m = msgpack.unpackb(data)
    out = [np.array(m[k], dtype=np.float64) for k in ("proxy_pose", "proxy_twist", "wrench")]
    for a in out:
        if not np.isfinite(a).all():
            raise ValueError("non-finite")
    return out


# ------------------------------------------------------------------------------ timing
def median_us(fn, batch: int, repeats: int) -> float:
    for _ in range(batch):  # warm-up
        fn()
    per_call = []
    for _ in range(repeats):
        t0 = time.perf_counter_ns()
        for _ in range(batch):
            fn()
        per_call.append((time.perf_counter_ns() - t0) / batch)
    return round(statistics.median(per_call) / 1000.0, 3)


def run(batch: int = 500, repeats: int = 41) -> list[dict]:
    from ..server import ingest

    codec = Codec()
    ingest.warm_up()
    server_codec = Codec(contact_check=ingest.contacts_surely_valid)
    rows = []
    for n in CONTACT_COUNTS:
        keys, pos, nor, sep, vc = make_contacts(n, seed=n)
        packet = codec.encode_contact_update(1, 2, 7, 0.5, POSE, keys, pos, nor, sep, vc)
        decoded = codec.try_decode(packet)
        assert not isinstance(decoded, ProtocolError), decoded
        naive = naive_encode_contacts(7, 0.5, POSE, keys, pos, nor, sep, vc)
        naive_decode_contacts(naive)
        enc = codec.encode_contact_update
        dec = codec.try_decode
        sdec = server_codec.try_decode
        assert not isinstance(sdec(packet), ProtocolError)
        rows.append({
            "message": "ContactUpdate",
            "contacts": n,
            "encode_median_us": median_us(lambda: enc(1, 2, 7, 0.5, POSE, keys, pos, nor, sep, vc), batch, repeats),
            "decode_median_us": median_us(lambda: dec(packet), batch, repeats),
            "server_decode_median_us": median_us(lambda: sdec(packet), batch, repeats),
            "bytes": len(packet),
            "naive_encode_median_us": median_us(
                lambda: naive_encode_contacts(7, 0.5, POSE, keys, pos, nor, sep, vc), batch, repeats),
            "naive_decode_median_us": median_us(lambda: naive_decode_contacts(naive), batch, repeats),
            "naive_bytes": len(naive),
        })
    msg = ProxyState(seq=3, ack_seq=2, server_time_s=0.5, proxy_pose=POSE, proxy_twist=np.arange(6.0),
                     wrench=np.arange(6.0), session_id=1, token=2)
    packet = codec.encode(msg)
    naive = naive_encode_proxy(msg)
    rows.append({
        "message": "ProxyState",
        "contacts": 0,
        "encode_median_us": median_us(lambda: codec.encode(msg), batch, repeats),
        "decode_median_us": median_us(lambda: codec.try_decode(packet), batch, repeats),
        "bytes": len(packet),
        "naive_encode_median_us": median_us(lambda: naive_encode_proxy(msg), batch, repeats),
        "naive_decode_median_us": median_us(lambda: naive_decode_proxy(naive), batch, repeats),
        "naive_bytes": len(naive),
    })
    for row in rows:
        row["encode_speedup"] = round(row["naive_encode_median_us"] / row["encode_median_us"], 2)
        row["decode_speedup"] = round(row["naive_decode_median_us"] / row["decode_median_us"], 2)
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="hapticproxy bench codec", description=doc_summary(__doc__))
    parser.add_argument("--json", action="store_true", help="print the rows as a JSON list")
    parser.add_argument("--batch", type=int, default=500, help="calls per timed batch (default 500)")
    parser.add_argument("--repeats", type=int, default=41, help="timed batches per figure (default 41)")
    args = parser.parse_args(argv)
    if args.batch < 1 or args.repeats < 1:
        parser.error("--batch and --repeats must be >= 1")
    rows = run(args.batch, args.repeats)
    if args.json:
        print_json(rows, indent=1)
        return 0
    head = ["message", "contacts", "bytes", "encode_median_us", "decode_median_us", "server_decode_median_us",
            "naive_encode_median_us",
            "naive_decode_median_us", "encode_speedup", "decode_speedup"]
    print("  ".join(f"{h:>14}" for h in head))
    for row in rows:
        print("  ".join(f"{row.get(h, '-')!s:>14}" for h in head))
    return 0


if __name__ == "__main__":
    sys.exit(main())
