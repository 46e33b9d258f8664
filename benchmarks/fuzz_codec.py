"""``python -m hapticproxy.benchmarks.fuzz_codec``: the long decoder fuzzing run (opt-in).

The default test run fuzzes the decoder with hypothesis (``tests/protocol/test_codec_fuzz.py``,
12,600 cases). This is the long run: ``--inputs`` (default 1,000,000) inputs to
``Codec.try_decode``, then prints one JSON object with the figures the README reports.

Engines:

- ``random`` (default; numpy and the standard library only): a seeded, structure-aware generator
  mixing random bytes; msgpack-shaped garbage behind a real header; bit flips, byte writes,
  insertions, deletions, truncations and splices of real packets of every message type (contact
  counts 0 to 64); field swaps (a field of a real packet replaced by a random msgpack value of any
  type); poisoned floats (NaN, inf, huge, subnormal) in the packed contact arrays and poses; and
  size extremes (claimed lengths beyond the limits, deep nesting, huge integers).
- ``atheris`` (coverage-guided libFuzzer, if ``atheris`` is importable; not a project
  dependency: ``pip install --target DIR atheris`` and put DIR on ``PYTHONPATH``): the codec
  module is instrumented and libFuzzer mutates a seed corpus of the same real packets.

For every input: ``try_decode`` must return, never raise (an exception escaping it is an
*unhandled exception*); a ``ProtocolError`` from the decoder's last-resort catch-all (detail
"unexpected ...") means a validator itself failed on the input (*caught by the catch-all*);
every accepted message is re-checked independently of the decoder (every float finite and within
``MAX_ABS_FLOAT``, unit quaternions and normals, positive masses, unique keys, shapes and counts
within the limits): a failure is an *invalid value that reached the model*; and every accepted
ContactUpdate is applied to a spatial ``LocalModel`` (update + one haptic step from a fresh
state): a non-finite model state counts there too (``model_nonfinite``). Each decode is timed
(``perf_counter_ns``, garbage collector frozen and disabled as in the haptic-loop process): the
worst observed time includes whatever the OS did meanwhile, so every decode slower than 20 us is
timed again at once (best of 3) and the 20 slowest by that measure again at the end (best of 5):
the slowest input's own cost. With ``--jobs N``
the inputs are split across N child processes; a child that dies (e.g. a segfault in a C
extension) is a *crash* (its chunk's seed is reported) and the run goes on.
"""
from __future__ import annotations

import argparse
import heapq
import math
import multiprocessing as mp
import os
import platform
import queue
import random
import struct
import sys
import time

import msgpack
import msgspec
import numpy as np

from ..protocol import messages as M
from ..protocol.codec import (
    Bye, Codec, ContactUpdate, Error, Heartbeat, Hello, Limits, Message, ProtocolError, ProxyState, Reject, Welcome,
)
from ..protocol.jsonout import print_json

LIMITS = Limits()
IDENTITY = (0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0)
POISON = (math.nan, math.inf, -math.inf, 1e300, -1e300, 1e9 * 1.0000001, 5e-324, -0.0, 1e-320, 2.0 ** 63)
CHUNK = 50_000
RETIME_NS = 20_000  # a decode slower than this is timed again for the input's own cost


# ------------------------------------------------------------------------------ seeds
def _contact_update(codec: Codec, n: int, rng: np.random.Generator, joints: int = 0) -> bytes:
    keys = np.column_stack([np.zeros(n, np.int64), rng.integers(0, 5, n), np.arange(n)]).astype(np.int64)
    nor = rng.normal(size=(n, 3))
    nor /= np.linalg.norm(nor, axis=1)[:, None]
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    pose = np.concatenate([rng.normal(scale=0.1, size=3), q])
    kw = {"tool_joint_position": rng.normal(size=joints)} if joints else {}
    return codec.encode_contact_update(7, 99, 1 + n, 0.25, pose, keys, rng.normal(scale=0.05, size=(n, 3)), nor,
                                       rng.normal(scale=0.003, size=n), rng.normal(scale=0.01, size=n), **kw)


def seed_packets() -> list[bytes]:
    """Real packets of every message type (contact counts 0..64); a seed the current protocol
    cannot build is skipped, so the script follows the protocol as it evolves."""
    codec = Codec(LIMITS)
    rng = np.random.default_rng(0)
    link0 = dict(mass_kg=1.0, com_m=(0.0, 0.0, 0.1), inertia_kg_m2=(0.01, 0.01, 0.02, 0.0, 0.0, 0.0), parent=-1,
                 joint_type=0, joint_axis=(1.0, 0.0, 0.0), joint_origin=IDENTITY)
    link1 = dict(link0, parent=0, joint_type=1, joint_axis=(0.0, 0.0, 1.0), joint_origin=(0.0, 0.0, 0.2, 1.0, 0.0, 0.0, 0.0))
    makers = [
        lambda: Hello(client_nonce=5, engine="fuzz", tool_kind=M.ToolKind.SPATIAL, mass_kg=1.0,
                      inertia_kg_m2=(0.1, 0.1, 0.1, 0.0, 0.0, 0.0), max_contacts=32, epsilon_m=0.005),
        lambda: Hello(client_nonce=6, engine="e", tool_kind=M.ToolKind.ONE_DOF, mass_kg=1.0, max_contacts=8,
                      axis=(0.0, 1.0, 0.0)),
        lambda: Hello(client_nonce=7, engine="e", tool_kind=M.ToolKind.PLANAR, mass_kg=0.5,
                      inertia_kg_m2=(0.0, 0.0, 0.01, 0.0, 0.0, 0.0), max_contacts=16),
        lambda: Hello(client_nonce=8, engine="e", tool_kind=M.ToolKind.LINKAGE, mass_kg=2.0, max_contacts=16,
                      links=(link0, link1), held_link=1),
        lambda: Welcome(client_nonce=5, version=(1, 0), haptic_rate_hz=1000.0, epsilon_m=0.005, max_contacts=32,
                        heartbeat_interval_s=0.1, silence_timeout_s=1.0, session_id=7, token=99),
        lambda: Reject(client_nonce=5, code=M.ErrorCode.UNSUPPORTED_VERSION, reason="no common major"),
        lambda: ProxyState(seq=3, ack_seq=2, server_time_s=0.5, proxy_pose=np.array(IDENTITY),
                           proxy_twist=np.arange(6.0), wrench=np.arange(6.0) - 3, session_id=7, token=99),
        lambda: ProxyState(seq=3, ack_seq=2, server_time_s=0.5, proxy_pose=np.array(IDENTITY), proxy_twist=np.zeros(6),
                           wrench=np.zeros(6), joint_position=np.array([0.1]), joint_velocity=np.array([0.2]),
                           joint_effort=np.array([0.3]), session_id=7, token=99),
        lambda: Heartbeat(seq=1, time_s=2.0, session_id=7, token=99),
        lambda: Bye(code=M.ErrorCode.BYE_NORMAL, reason="done", session_id=7, token=99),
        lambda: Error(code=M.ErrorCode.NON_FINITE, field="contact_data", detail="nan", ref_type=4, ref_seq=9,
                      session_id=7, token=99),
    ]
    out = []
    for make in makers:
        try:
            out.append(codec.encode(make()))
        except (TypeError, ValueError):
            pass
    for n in (0, 1, 2, 3, 8, 16, 32, 64):
        out.append(_contact_update(codec, n, rng))
    try:
        out.append(_contact_update(codec, 4, rng, joints=3))
    except (TypeError, ValueError):
        pass
    return out


# ------------------------------------------------------------------------------ generator
def _rand_value(r: random.Random, depth: int = 0):
    k = r.randrange(12 if depth < 3 else 9)
    if k == 0:
        return None
    if k == 1:
        return r.random() < 0.5
    if k == 2:
        return r.choice((0, 1, -1, 255, 256, 65535, 65536, 2**32 - 1, 2**32, 2**63 - 1, 2**64 - 1, -(2**63)))
    if k == 3:
        return r.randrange(-(2**63), 2**64)
    if k == 4:
        return r.choice(POISON) if r.random() < 0.5 else r.uniform(-10, 10)
    if k == 5:
        return "".join(chr(r.randrange(32, 0x2FF)) for _ in range(r.randrange(0, 12)))
    if k == 6:
        return r.randbytes(r.randrange(0, 80))
    if k == 7:  # a packed float64 array, some values poisoned
        n = r.randrange(0, 40)
        return struct.pack(f"<{n}d", *[r.choice(POISON) if r.random() < 0.2 else r.uniform(-1, 1) for _ in range(n)])
    if k == 8:
        return r.uniform(-1e12, 1e12)
    return [_rand_value(r, depth + 1) for _ in range(r.randrange(0, 8))]


class Generator:
    """The ``random`` engine: ``next()`` returns one input (bytes)."""

    def __init__(self, seed: int, seeds: list[bytes]) -> None:
        self.r = random.Random(seed)
        self.seeds = seeds
        self.objs = [msgpack.unpackb(s, strict_map_key=False) for s in seeds]
        self.strategies = (self.random_bytes, self.header_garbage, self.mutate, self.mutate, self.mutate,
                           self.field_swap, self.field_swap, self.poison_floats, self.poison_floats, self.extremes)

    def next(self) -> bytes:
        return self.r.choice(self.strategies)()

    def random_bytes(self) -> bytes:
        return self.r.randbytes(self.r.randrange(0, 512))

    def header_garbage(self) -> bytes:
        r = self.r
        head = [r.choice((1, 1, 1, 0, 2, 65535)), r.randrange(0, 4), r.choice([int(m.type_id) for m in M.MESSAGES] + [0, 99]),
                r.choice((0, 7, r.randrange(2**32))), r.choice((0, 99, r.randrange(2**64)))]
        return msgpack.packb(head + [_rand_value(r) for _ in range(r.randrange(0, 20))], use_bin_type=True)

    def mutate(self) -> bytes:
        r = self.r
        b = bytearray(r.choice(self.seeds))
        for _ in range(r.choice((1, 1, 1, 2, 3, 8))):
            if not b:
                break
            op = r.randrange(7)
            i = r.randrange(len(b))
            if op == 0:
                b[i] ^= 1 << r.randrange(8)
            elif op == 1:
                b[i] = r.choice((0x00, 0xFF, 0x7F, 0x80, 0xC0, 0xC1, 0xC4, 0xC5, 0xC6, 0xCB, 0xDC, 0xDD, r.randrange(256)))
            elif op == 2:
                b[i:i] = r.randbytes(r.randrange(1, 9))
            elif op == 3:
                del b[i:i + r.randrange(1, 9)]
            elif op == 4:
                del b[i:]
            elif op == 5:
                other = r.choice(self.seeds)
                j = r.randrange(len(other))
                b = b[:i] + bytearray(other[j:])
            else:
                j = r.randrange(len(b))
                b[i:i] = b[j:j + r.randrange(1, 16)]
        return bytes(b)

    def field_swap(self) -> bytes:
        r = self.r
        obj = list(r.choice(self.objs))
        for _ in range(r.choice((1, 1, 2, 3))):
            i = r.randrange(len(obj))
            if r.random() < 0.3 and len(obj) > 1:
                j = r.randrange(len(obj))
                obj[i], obj[j] = obj[j], obj[i]
            else:
                obj[i] = _rand_value(r)
        if r.random() < 0.1:
            obj = obj[: r.randrange(len(obj) + 1)]
        elif r.random() < 0.1:
            obj = obj + [_rand_value(r) for _ in range(r.randrange(1, 4))]
        return msgpack.packb(obj, use_bin_type=True)

    def poison_floats(self) -> bytes:
        r = self.r
        obj = list(r.choice(self.objs))
        bins = [i for i, v in enumerate(obj) if isinstance(v, bytes) and len(v) >= 8 and len(v) % 8 == 0]
        if not bins:
            return self.field_swap()
        i = r.choice(bins)
        a = bytearray(obj[i])
        for _ in range(r.choice((1, 1, 2, 5))):
            k = r.randrange(len(a) // 8)
            v = r.choice(POISON) if r.random() < 0.7 else r.uniform(-2.0, 2.0)
            a[8 * k:8 * k + 8] = struct.pack("<d", v)
        obj[i] = bytes(a)
        return msgpack.packb(obj, use_bin_type=True)

    def extremes(self) -> bytes:
        r = self.r
        k = r.randrange(5)
        if k == 0:  # a bin/str/array claiming a huge length
            marker = r.choice((b"\xc6", b"\xdb", b"\xdd", b"\xc5", b"\xda", b"\xdc"))
            width = {b"\xc6": 4, b"\xdb": 4, b"\xdd": 4}.get(marker, 2)
            return b"\x9f\x01\x00\x04\x07\xcf" + b"\x00" * 7 + b"\x63" + marker + (2**(8 * width) - 1).to_bytes(width, "big")
        if k == 1:  # deep nesting
            d = r.randrange(10, 3000)
            return b"\x91" * d + b"\x01"
        if k == 2:  # an array header claiming 2**32 - 1 elements
            return b"\xdd\xff\xff\xff\xff" + r.randbytes(r.randrange(0, 64))
        if k == 3:  # maps and extension types, which the protocol never uses
            return msgpack.packb([1, 0, 4, 7, 99, {"a": 1}, msgpack.ExtType(5, b"xx")], use_bin_type=True)
        return r.randbytes(r.randrange(LIMITS.max_packet_bytes - 8, LIMITS.max_packet_bytes + 64))


# ------------------------------------------------------------------------------ checks
def _floats_ok(v) -> bool:
    if isinstance(v, bool) or v is None or isinstance(v, (int, str, bytes)):
        return True
    if isinstance(v, float):
        return math.isfinite(v) and abs(v) <= M.MAX_ABS_FLOAT
    if isinstance(v, np.ndarray):
        if v.dtype.kind == "f":
            return bool(np.all(np.isfinite(v)) and np.all(np.abs(v) <= M.MAX_ABS_FLOAT))
        return True
    if isinstance(v, (list, tuple)):
        return all(_floats_ok(x) for x in v)
    if isinstance(v, dict):
        return all(_floats_ok(x) for x in v.values())
    if isinstance(v, msgspec.Struct):  # e.g. a Hello's Link records
        return all(_floats_ok(getattr(v, f)) for f in v.__struct_fields__)
    return all(_floats_ok(x) for x in vars(v).values()) if hasattr(v, "__dict__") else True


def invalid_reason(msg: Message, limits: Limits = LIMITS) -> str:
    """Why an accepted message is not valid, re-checked without the decoder ("" if valid)."""
    fields = {}
    for name in dir(msg):
        if name.startswith("_"):
            continue
        try:
            v = getattr(msg, name)
        except Exception:  # noqa: BLE001
            continue
        if not callable(v):
            fields[name] = v
    for name, v in fields.items():
        if not _floats_ok(v):
            return f"{name}: non-finite or out of bounds"
        if isinstance(v, str) and len(v.encode("utf-8", "surrogatepass")) > limits.max_str_bytes:
            return f"{name}: string longer than max_str_bytes"
    spec = M.MESSAGES_BY_ID[int(msg.TYPE_ID)]
    for f in spec.fields:
        v = fields.get(f.name)
        if v is None:
            continue
        if f.check == "pos" and not v > 0:
            return f"{f.name}: not > 0"
        if f.check == "nonneg" and not v >= 0:
            return f"{f.name}: negative"
        if f.check == "unit" and abs(float(np.linalg.norm(np.asarray(v, float))) - 1.0) > M.UNIT_TOLERANCE * 1.0000001:
            return f"{f.name}: not a unit vector"
        if f.type == "pose" and abs(float(np.linalg.norm(np.asarray(v, float)[3:7])) - 1.0) > M.UNIT_TOLERANCE * 1.0000001:
            return f"{f.name}: quaternion not unit"
    if isinstance(msg, ContactUpdate):
        n = msg.keys.shape[0]
        if not 0 <= n <= limits.max_contacts:
            return "contact count out of limits"
        if msg.keys.dtype != np.int64 or msg.keys.shape != (n, 3):
            return "keys shape/dtype"
        for a, shape in ((msg.position_m, (n, 3)), (msg.normal, (n, 3)), (msg.separation_m, (n,)),
                         (msg.v_constr_m_per_s, (n,)), (msg.tool_pose, (7,))):
            if a.dtype != np.float64 or a.shape != shape:
                return "array shape/dtype"
        if n and np.any(np.abs(np.linalg.norm(msg.normal, axis=1) - 1) > M.UNIT_TOLERANCE * 1.0000001):
            return "normal not unit"
        if abs(np.linalg.norm(msg.tool_pose[3:]) - 1) > M.UNIT_TOLERANCE * 1.0000001:
            return "tool_pose quaternion not unit"
        if len({tuple(k) for k in msg.keys.tolist()}) != n:
            return "duplicate contact keys"
        if not (isinstance(msg.seq, int) and msg.seq >= 1):
            return "seq"
    return ""


class ModelProbe:
    """A spatial local model every accepted ContactUpdate is applied to (fresh state each time)."""

    def __init__(self) -> None:
        from ..server.model import ContactParams, LocalModel, ToolSpec

        self.model = LocalModel(ToolSpec.spatial(0.25, (1e-4, 1e-4, 1e-4)), ContactParams(stiffness_n_per_m=4000.0),
                                period_s=1e-3, capacity=LIMITS.max_contacts, epsilon_m=0.005,
                                max_update_contacts=LIMITS.max_contacts)
        self.hand = np.zeros(6)

    def nonfinite(self, cu: ContactUpdate) -> bool:
        from ..server.loop import q_from_tool_pose

        m = self.model
        m.reset(IDENTITY[:3] + (1.0, 0.0, 0.0, 0.0))
        n = cu.keys.shape[0]
        q = q_from_tool_pose("spatial", cu.tool_pose, (0.0, 0.0, 0.0))
        code = m.update_arrays(cu.keys, cu.position_m, cu.normal, cu.separation_m, cu.v_constr_m_per_s, n, q)
        if code != 0:
            return False  # refused by the model's own checks: did not reach the dynamics
        f = m.step(self.hand)
        return not (np.all(np.isfinite(f)) and np.all(np.isfinite(m.q)))


class Stats:
    def __init__(self) -> None:
        self.inputs = 0
        self.accepted: dict[str, int] = {}
        self.rejected: dict[str, int] = {}
        self.unhandled: list[str] = []
        self.catch_all: list[str] = []
        self.invalid: list[str] = []
        self.model_nonfinite = 0
        self.worst_ns = 0
        self.worst_len = 0
        self.hist = np.zeros(10001, dtype=np.int64)  # 1 us bins, last = >= 10 ms
        self.slowest: list = []  # heap of (ns, input): the 20 slowest, re-timed at the end

    def merge(self, d: dict) -> None:
        self.inputs += d["inputs"]
        for k, v in d["accepted"].items():
            self.accepted[k] = self.accepted.get(k, 0) + v
        for k, v in d["rejected"].items():
            self.rejected[k] = self.rejected.get(k, 0) + v
        self.unhandled += d["unhandled"]
        self.catch_all += d["catch_all"]
        self.invalid += d["invalid"]
        self.model_nonfinite += d["model_nonfinite"]
        if d["worst_ns"] > self.worst_ns:
            self.worst_ns, self.worst_len = d["worst_ns"], d["worst_len"]
        self.hist += np.asarray(d["hist"], dtype=np.int64)
        for item in d["slowest"]:
            self._keep_slow(item[0], bytes.fromhex(item[1]))

    def _keep_slow(self, dt: int, data: bytes) -> None:
        if len(self.slowest) < 20:
            heapq.heappush(self.slowest, (dt, data))
        elif dt > self.slowest[0][0]:
            heapq.heapreplace(self.slowest, (dt, data))

    def as_dict(self) -> dict:
        return {"inputs": self.inputs, "accepted": self.accepted, "rejected": self.rejected,
                "unhandled": self.unhandled[:20], "catch_all": self.catch_all[:20], "invalid": self.invalid[:20],
                "model_nonfinite": self.model_nonfinite, "worst_ns": self.worst_ns, "worst_len": self.worst_len,
                "hist": self.hist.tolist(), "slowest": [(dt, d.hex()) for dt, d in self.slowest]}

    def retime_slowest(self, repeats: int = 5) -> tuple[float, int]:
        """The inputs slowest by their own cost (each slow decode was timed again at once), decoded
        again here (best of ``repeats``). Returns (us, input bytes) of the slowest."""
        codec = Codec(LIMITS)
        best = (0.0, 0, b"")
        for _, data in self.slowest:
            t = min(_timed(codec, data) for _ in range(repeats)) / 1000.0
            if t > best[0]:
                best = (t, len(data), data)
        self.slowest_input = best[2]
        return best[:2]


def _timed(codec: Codec, data: bytes) -> int:
    t0 = time.perf_counter_ns()
    codec.try_decode(data)
    return time.perf_counter_ns() - t0


def check_one(codec: Codec, data: bytes, st: Stats, probe: ModelProbe | None) -> None:
    st.inputs += 1
    t0 = time.perf_counter_ns()
    try:
        out = codec.try_decode(data)
    except BaseException as exc:  # noqa: BLE001 - that is what is being counted
        st.unhandled.append(f"{type(exc).__name__}: {exc} <- {data[:64].hex()}")
        return
    dt = time.perf_counter_ns() - t0
    st.hist[min(dt // 1000, 10000)] += 1
    if dt > st.worst_ns:
        st.worst_ns, st.worst_len = dt, len(data)
    if dt > RETIME_NS:
        # slow this time: its own cost is the best of three more (a preemption lands in one)
        own = min(_timed(codec, data) for _ in range(3))
        if len(st.slowest) < 20 or own > st.slowest[0][0]:
            st._keep_slow(own, bytes(data))
    if isinstance(out, ProtocolError):
        name = out.code.name.lower() if isinstance(out.code, M.ErrorCode) else str(out.code)
        st.rejected[name] = st.rejected.get(name, 0) + 1
        if str(out.detail).startswith("unexpected"):
            st.catch_all.append(f"{out} <- {data[:64].hex()}")
        return
    name = type(out).__name__
    st.accepted[name] = st.accepted.get(name, 0) + 1
    why = invalid_reason(out)
    if why:
        st.invalid.append(f"{name}: {why} <- {data[:64].hex()}")
        return
    if probe is not None and isinstance(out, ContactUpdate) and probe.nonfinite(out):
        st.model_nonfinite += 1


def run_chunk(seed: int, n: int, model: bool = True, quiet_gc: bool = True) -> dict:
    """``n`` inputs of the random engine from ``seed`` (what one child process runs). With
    ``quiet_gc`` the garbage collector is frozen and disabled first, as in the haptic-loop process
    (decoding allocates no cycles; a collection would otherwise land in some decode's time)."""
    import gc

    if quiet_gc:
        gc.collect()
        gc.freeze()
        gc.disable()
    seeds = seed_packets()
    gen = Generator(seed, seeds)
    codec = Codec(LIMITS)
    probe = ModelProbe() if model else None
    st = Stats()
    for s in seeds:
        check_one(codec, s, st, probe)
    for _ in range(n - len(seeds)):
        check_one(codec, gen.next(), st, probe)
    return st.as_dict()


def _child(seed, n, model, q) -> None:
    q.put(run_chunk(seed, n, model))


def run_random(inputs: int, seed: int, jobs: int, model: bool = True, log=None) -> tuple[Stats, list[int]]:
    st = Stats()
    crashes: list[int] = []
    ctx = mp.get_context("spawn")
    chunks = [(seed * 1_000_003 + i, min(CHUNK, inputs - i * CHUNK)) for i in range((inputs + CHUNK - 1) // CHUNK)]
    pending = list(chunks)
    running: list = []
    while pending or running:
        while pending and len(running) < jobs:
            s, n = pending.pop(0)
            q = ctx.Queue()
            p = ctx.Process(target=_child, args=(s, n, model, q), daemon=True)
            p.start()
            running.append((p, q, s))
        p, q, s = running.pop(0)
        d = None
        while d is None:
            try:
                d = q.get(timeout=1.0)
            except queue.Empty:
                if not p.is_alive():  # died without reporting: a crash
                    break
        p.join(60)
        if d is None or p.exitcode != 0:
            crashes.append(s)
        else:
            st.merge(d)
        if log:
            log(f"{st.inputs} inputs, {len(crashes)} crashes, {len(st.unhandled)} unhandled")
    return st, crashes


# ------------------------------------------------------------------------------ atheris
def run_atheris(inputs: int, seed: int, corpus_dir: str) -> None:
    """libFuzzer over ``try_decode`` with the codec instrumented; prints the JSON at exit."""
    import atexit

    import atheris  # noqa: F401 - optional

    from ..protocol import codec as codec_mod

    # the codec is imported already (this module uses it): instrument its functions in place
    for obj in list(vars(codec_mod).values()) + list(vars(codec_mod.Codec).values()):
        if callable(obj) and getattr(obj, "__module__", "") == codec_mod.__name__ and hasattr(obj, "__code__"):
            atheris.instrument_func(obj)
    codec = codec_mod.Codec(LIMITS)
    probe = ModelProbe()
    st = Stats()
    t0 = time.monotonic()
    os.makedirs(corpus_dir, exist_ok=True)
    for i, s in enumerate(seed_packets()):
        with open(os.path.join(corpus_dir, f"seed-{i}"), "wb") as f:
            f.write(s)

    def report() -> None:
        print_json(figures(st, [], "atheris", seed, time.monotonic() - t0), indent=1)

    def one(data: bytes) -> None:
        check_one(codec, data, st, probe)
        if st.inputs == inputs:  # libFuzzer's last run: it exits without Python's atexit
            report()

    atexit.register(lambda: st.inputs < inputs and report())
    atheris.Setup([sys.argv[0], f"-runs={inputs}", f"-seed={seed}", "-max_len=9000", "-rss_limit_mb=4096",
                   "-print_final_stats=1", corpus_dir], one)
    atheris.Fuzz()


# ------------------------------------------------------------------------------ CLI
def figures(st: Stats, crashes: list[int], engine: str, seed: int, seconds: float) -> dict:
    retimed = st.retime_slowest()
    retimed = (round(retimed[0], 1), retimed[1])
    n = int(st.hist.sum())
    cum = np.cumsum(st.hist)
    p999 = float(np.searchsorted(cum, 0.999 * n) + 1) if n else None
    p50 = float(np.searchsorted(cum, 0.5 * n) + 1) if n else None
    return {
        "engine": engine, "seed": seed, "inputs": st.inputs, "seconds": round(seconds, 1),
        "crashes": len(crashes), "crashed_chunk_seeds": crashes,
        "unhandled_exceptions": len(st.unhandled), "caught_by_catch_all": len(st.catch_all),
        "invalid_reached_model": len(st.invalid), "model_nonfinite": st.model_nonfinite,
        "accepted": dict(sorted(st.accepted.items())), "accepted_total": sum(st.accepted.values()),
        "rejected": dict(sorted(st.rejected.items(), key=lambda kv: -kv[1])), "rejected_total": sum(st.rejected.values()),
        "decode_us": {"p50": p50, "p999": p999, "worst_observed": round(st.worst_ns / 1000, 1),
                      "worst_observed_input_bytes": st.worst_len, "slowest_input_retimed": retimed[0],
                      "slowest_input_bytes": retimed[1], "slowest_input_head": st.slowest_input[:48].hex()},
        "examples": {"unhandled": st.unhandled[:5], "catch_all": st.catch_all[:5], "invalid": st.invalid[:5]},
        "machine": f"{platform.machine()} {os.cpu_count()} cpus, {platform.system()} {platform.release()}, "
                   f"python {platform.python_version()}, load average {os.getloadavg()[0]:.2f} at the end",
        "date_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m hapticproxy.benchmarks.fuzz_codec", description=__doc__.splitlines()[0])
    ap.add_argument("--inputs", type=int, default=1_000_000, help="inputs to try (default 1,000,000)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--engine", choices=("random", "atheris"), default="random")
    ap.add_argument("--jobs", type=int, default=1, help="child processes (random engine)")
    ap.add_argument("--no-model", action="store_true", help="do not apply accepted updates to a local model")
    ap.add_argument("--corpus", default="out/fuzz-corpus", help="atheris: corpus directory (seeds written there)")
    ap.add_argument("-q", "--quiet", action="store_true")
    args = ap.parse_args(argv)
    if args.inputs < 1 or args.jobs < 1:
        print("fuzz_codec: --inputs and --jobs must be >= 1", file=sys.stderr)
        return 2
    if args.engine == "atheris":
        run_atheris(args.inputs, args.seed, args.corpus)
        return 0
    t0 = time.monotonic()
    log = None if args.quiet else (lambda m: print(f"fuzz_codec: {m}", file=sys.stderr, flush=True))
    st, crashes = run_random(args.inputs, args.seed, args.jobs, model=not args.no_model, log=log)
    out = figures(st, crashes, "random", args.seed, time.monotonic() - t0)
    print_json(out, indent=1)
    bad = out["crashes"] + out["unhandled_exceptions"] + out["caught_by_catch_all"] + out["invalid_reached_model"] + out["model_nonfinite"]
    return 0 if bad == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
