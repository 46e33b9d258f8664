"""Recordings in MCAP: the loop's shared rings drained to a crash-safe file by the supervisor.

An MCAP file (the robotics log format Foxglove and PlotJuggler open) with JSON messages, one
JSON schema per message type, generated from the ``msgspec`` structs below (declared once: the
writer encodes them, the reader decodes them, the schema in the file is made from them):

==========================  ========================  =====================================================
topic                       schema                    what, when
==========================  ========================  =====================================================
``/device``                 ``hapticproxy.Device``    device handle pose, twist (world), measured hand
                                                      wrench (device frame; null: no sensor); every step
``/proxy``                  ``hapticproxy.Proxy``     proxy hand-point pose, twist, the position channel's
                                                      wrench on the proxy (world); every step
``/command``                ``hapticproxy.Command``   the wrench written to the device (device frame), the
                                                      gain; every step
``/environment_wrench``     ``hapticproxy.Wrench``    the local model's wrench at the hand point (world);
                                                      every step
``/loop``                   ``hapticproxy.LoopTiming`` wake-up lateness, compute time, state, gain, contacts,
                                                      updates; every step
``/contacts``               ``hapticproxy.Contacts``  the contacts of each applied model update (key,
                                                      position, normal, separation), 30-60 Hz
``/transitions``            ``hapticproxy.Transition`` every state change with its reason
==========================  ========================  =====================================================

Every message carries ``t_s``, the loop's time since it started (the telemetry rows' clock); its
MCAP log time is the same instant as Unix-epoch nanoseconds. A metadata record ``hapticproxy``
holds the rate, the start time, the device and tool kinds, the caps and the whole config (JSON).

Beside them, the 3-D scene the live view shows, in Foxglove's standard schemas (protobuf, through
the Foxglove SDK: ``server/scene.py`` builds them), at ``scene.SCENE_HZ`` (30 Hz) from the rows
and the contacts above, so a run replays in Foxglove's 3D panel (and rerun reads the transforms
and poses) as it looked live:

==========================  ==============================  ===========================================
``/tf``                     ``foxglove.FrameTransforms``    world -> device, world -> proxy
``/device/pose``            ``foxglove.PoseInFrame``        the device handle in ``world``
``/proxy/pose``             ``foxglove.PoseInFrame``        the proxy's hand point in ``world``
``/scene``                  ``foxglove.SceneUpdate``        device, the proxy drawn as the tool's shape,
                                                            contacts, normals, force arrows, state
==========================  ==============================  ===========================================

The MCAP header's profile is ``hapticproxy`` (the JSON topics' own; the Foxglove topics are
recognised by their schema names).

Crash safety: messages go into a chunk that is closed, written, flushed and fsync'ed every
``flush_rows`` telemetry rows, so after a crash of the loop (or of the supervisor) every closed
chunk is readable; ``read`` stops at a torn tail and reports its size. A file that lost its
summary (a crash of the supervisor) is read by ``read`` and by Foxglove as it is; PlotJuggler
wants the summary: ``hapticproxy convert IN.mcap OUT.mcap`` rewrites it whole.

The writer is the Foxglove SDK's (Rust) MCAP writer: about 1.6 us a message here, against 9 us
for the pure-Python ``mcap`` writer (measured on the 2-core development machine); the ``mcap``
package reads. ``hapticproxy bench recorder`` measures that the supervisor keeps up at 4 kHz.
"""
from __future__ import annotations

import json
import math
import os
import struct
import time
import typing
from dataclasses import dataclass, field
from pathlib import Path

import msgspec
import numpy as np

from . import scene as scn
from .lifecycle import LOOP_STATES, Reason, describe
from .shm import NTEL, ST, TEL, TEL_DTYPE, SharedState, flat_rows

Num = typing.Optional[float]  # a number; null when it is not one (NaN, not measured)


# ---------------------------------------------------------------------------- message types
class Vector3(msgspec.Struct):
    x: Num
    y: Num
    z: Num


class Quaternion(msgspec.Struct):
    x: Num
    y: Num
    z: Num
    w: Num


class Pose(msgspec.Struct):
    position: Vector3       # m
    orientation: Quaternion


class Twist(msgspec.Struct):
    linear: Vector3         # m/s
    angular: Vector3        # rad/s


class WrenchValue(msgspec.Struct):
    force: Vector3          # N
    torque: Vector3         # N m


class Device(msgspec.Struct):
    """The device handle, world frame; the hand wrench as its sensor measures it (device frame)."""
    t_s: float
    pose: Pose
    twist: Twist
    hand_wrench: WrenchValue


class Proxy(msgspec.Struct):
    """The proxy's hand point after the step, world frame; the position channel's wrench on it."""
    t_s: float
    pose: Pose
    twist: Twist
    coupling_wrench: WrenchValue


class Command(msgspec.Struct):
    """The wrench written to the device (device frame, after the safety filter)."""
    t_s: float
    wrench: WrenchValue
    gain: Num


class Wrench(msgspec.Struct):
    """The environment wrench from the local model at the hand point, world frame."""
    t_s: float
    wrench: WrenchValue


class LoopTiming(msgspec.Struct):
    t_s: float
    lateness_us: Num
    compute_us: Num
    state: int
    state_name: str
    gain: Num
    contacts: int
    updates: int
    #: the energy the device gave the hand since the server started, J (the ledger at the hand's
    #: port: each command held over its period times the handle's displacement; absent before it)
    energy_hand_j: Num = None
    #: the passivity layer's tank level, J (server/passivity.py; absent before it)
    tank_j: Num = None


class Contact(msgspec.Struct):
    key: typing.List[int]   # tool link, environment body, feature
    position: Vector3       # m, world
    normal: Vector3         # unit, world
    separation_m: Num


class Contacts(msgspec.Struct):
    t_s: float
    env_time_s: Num
    update: int
    count: int
    min_separation_m: Num   # the deepest penetration is -min_separation_m (null: no contact)
    contacts: typing.List[Contact]


class Transition(msgspec.Struct):
    t_s: float
    from_state: str
    to_state: str
    reason: str
    detail: Num
    text: str


#: topic -> (schema name, message type)
TOPICS = {
    "/device": ("hapticproxy.Device", Device),
    "/proxy": ("hapticproxy.Proxy", Proxy),
    "/command": ("hapticproxy.Command", Command),
    "/environment_wrench": ("hapticproxy.Wrench", Wrench),
    "/loop": ("hapticproxy.LoopTiming", LoopTiming),
    "/contacts": ("hapticproxy.Contacts", Contacts),
    "/transitions": ("hapticproxy.Transition", Transition),
}
STEP_TOPICS = ("/device", "/proxy", "/command", "/environment_wrench", "/loop")
META_NAME = "hapticproxy"
#: the metadata record of each engaged client's tool shape (``McapRecorder.set_shape``), the last
#: one in a file is its ``Recording.meta["tool_shape"]``: a replay draws the proxy with it
SHAPE_META_NAME = "hapticproxy.tool_shape"
FORMAT = "hapticproxy-mcap-1"
PROFILE = "hapticproxy"
#: the standard-schema topics beside ``TOPICS`` (written from them; ``read`` skips them)
SCENE_TOPICS = ("/tf", "/device/pose", "/proxy/pose", "/scene")


def json_schema(tp) -> dict:
    """A plain JSON schema of a message type (objects inlined, no ``$ref``, numbers as
    ``number``: the subset Foxglove parses; PlotJuggler reads the messages themselves)."""
    if tp is float or tp == Num:
        return {"type": "number"}
    if tp is int:
        return {"type": "integer"}
    if tp is str:
        return {"type": "string"}
    origin = typing.get_origin(tp)
    if origin in (list, typing.List):
        return {"type": "array", "items": json_schema(typing.get_args(tp)[0])}
    if isinstance(tp, type) and issubclass(tp, msgspec.Struct):
        hints = typing.get_type_hints(tp)
        out = {"type": "object", "title": tp.__name__,
               "properties": {f: json_schema(hints[f]) for f in tp.__struct_fields__}}
        if tp.__doc__:
            out["description"] = " ".join(tp.__doc__.split())
        return out
    raise TypeError(f"no JSON schema for {tp!r}")


def _num(v: float):
    return v if v == v and v not in (math.inf, -math.inf) else None


# column indices of the flat telemetry row, once
_D, _P = TEL["dev_x"], TEL["proxy_x"]
_CMD, _ENV, _HAND, _CPL = TEL["cmd_fx"], TEL["env_fx"], TEL["hand_fx"], TEL["couple_fx"]
_T, _LATE, _COMP, _STATE, _GAIN, _NC, _UPD, _SEQ, _EHAND, _TANK = (
    TEL[n] for n in ("t_s", "lateness_us", "compute_us", "loop_state", "gain", "contacts", "updates", "seq",
                     "energy_hand_j", "tank_j"))


def _pose(r, o) -> Pose:  # pose columns: x y z qw qx qy qz
    return Pose(Vector3(r[o], r[o + 1], r[o + 2]), Quaternion(r[o + 4], r[o + 5], r[o + 6], r[o + 3]))


def _twist(r, o) -> Twist:
    return Twist(Vector3(r[o], r[o + 1], r[o + 2]), Vector3(r[o + 3], r[o + 4], r[o + 5]))


def _wrench(r, o) -> WrenchValue:
    return WrenchValue(Vector3(r[o], r[o + 1], r[o + 2]), Vector3(r[o + 3], r[o + 4], r[o + 5]))


def state_name(code) -> str:
    c = int(code) if code == code else -1
    return LOOP_STATES[c] if 0 <= c < len(LOOP_STATES) else "?"


def _int(v) -> int:
    return int(v) if v == v and v not in (math.inf, -math.inf) else -1


def step_messages(r: list, name: str | None = None) -> tuple:
    """The five per-step messages of one flat telemetry row (a list of floats, columns ``TEL``)."""
    t = r[_T]
    return (Device(t, _pose(r, _D), _twist(r, _D + 7), _wrench(r, _HAND)),
            Proxy(t, _pose(r, _P), _twist(r, _P + 7), _wrench(r, _CPL)),
            Command(t, _wrench(r, _CMD), r[_GAIN]),
            Wrench(t, _wrench(r, _ENV)),
            LoopTiming(t, r[_LATE], r[_COMP], _int(r[_STATE]), state_name(r[_STATE]) if name is None else name,
                       r[_GAIN], _int(r[_NC]), _int(r[_UPD]), r[_EHAND], r[_TANK]))


_INT_COLS = (_STATE, _NC, _UPD)
_F_SENT, _I_SENT = 100_000_000, 200_000_000


class StepEncoder:
    """Encodes telemetry rows as the five per-step JSON messages, fast: every row of a batch is
    formatted by one ``msgspec`` call and poured into byte templates made once by encoding
    ``step_messages`` of a row of sentinel values, so the bytes are exactly what encoding the
    structs gives (a test checks it) at a third of the cost of building them per row."""

    def __init__(self) -> None:
        import re
        from operator import itemgetter

        enc = msgspec.json.Encoder()
        row = [float(_F_SENT + c) for c in range(NTEL)]
        for c in _INT_COLS:
            row[c] = float(_I_SENT + c)
        msgs = step_messages(row, "\x01")
        self.templates = []
        self.getters = []
        pat = re.compile(rb'(?<=[:\[,])(1\d{8}\.0|2\d{8}|"\\u0001")(?=[,}\]])')
        for m in msgs:
            raw = enc.encode(m)
            idx = []

            def sub(mo, idx=idx):
                tok = mo.group(1)
                if tok.startswith(b'"'):
                    idx.append(NTEL + len(_INT_COLS))
                elif tok.endswith(b".0"):
                    idx.append(int(float(tok)) - _F_SENT)
                else:
                    idx.append(NTEL + _INT_COLS.index(int(tok) - _I_SENT))
                return b"%s"

            tmpl = pat.sub(sub, raw.replace(b"%", b"%%"))
            self.templates.append(tmpl)
            self.getters.append(itemgetter(*idx))
        self._enc = enc
        self._names = tuple(enc.encode(n) for n in LOOP_STATES) + (b'"?"',)

    def encode(self, flat: np.ndarray) -> list[tuple[float, list[bytes]]]:
        """``[(t_s, [five messages]), ...]`` for float64 rows ``flat[n, NTEL]``."""
        n = len(flat)
        if n == 0:
            return []
        nums = self._enc.encode(flat.ravel().tolist())[1:-1].split(b",")
        iv = flat[:, _INT_COLS]
        ints = np.where(np.isfinite(iv), iv, -1).astype(np.int64)
        istr = self._enc.encode(ints.ravel().tolist())[1:-1].split(b",")
        names = self._names
        nn = len(names) - 1
        codes = ints[:, 0].tolist()
        pairs = tuple(zip(self.templates, self.getters))
        ni = len(_INT_COLS)
        out = []
        ts = flat[:, _T].tolist()
        for k in range(n):
            c = codes[k]
            row = nums[k * NTEL:(k + 1) * NTEL] + istr[k * ni:(k + 1) * ni]
            row.append(names[c] if 0 <= c < nn else names[nn])
            out.append((ts[k], [t % g(row) for t, g in pairs]))
        return out


def scene_frame(row, contacts=None) -> scn.Frame:
    """The 3-D scene's :class:`~.scene.Frame` of one flat telemetry row (columns by name) and the
    contacts ``(position, normal, separation)`` applied by then."""
    def cols(prefix, names):
        return [row[TEL[f"{prefix}_{n}"]] for n in names]

    pose = ("x", "y", "z", "qw", "qx", "qy", "qz")
    wrench = ("fx", "fy", "fz", "tx", "ty", "tz")
    return scn.frame_of(row[_T], cols("dev", pose), cols("proxy", pose), cols("cmd", wrench), cols("env", wrench),
                        contacts, state_name(row[_STATE]), row[_GAIN], row[_EHAND])


def contacts_message(hdr, key, pos, nrm, sep) -> Contacts:
    n = len(sep)
    cs = [Contact([int(k) for k in key[j]], Vector3(*(float(v) for v in pos[j])),
                  Vector3(*(float(v) for v in nrm[j])), float(sep[j])) for j in range(n)]
    return Contacts(float(hdr["t_s"]), _num(float(hdr["env_time_s"])), int(hdr["update"]), int(hdr["count"]),
                    float(np.min(sep)) if n else None, cs)


def transition_message(t_s: float, frm: int, to: int, reason: int, detail: float) -> Transition:
    name = (lambda i: LOOP_STATES[i] if 0 <= i < len(LOOP_STATES) else str(i))
    try:
        why = Reason(int(reason)).name.lower()
    except ValueError:
        why = str(reason)
    return Transition(t_s, name(frm), name(to), why, _num(float(detail)), describe(reason, detail))


# ---------------------------------------------------------------------------- writing
class McapRecorder:
    """Writes a recording; ``drain(shared)`` copies what the loop wrote since the last call.

    ``t0_epoch_ns``: the Unix time of the loop's ``t_s = 0`` (its start), so every message's log
    time is the wall-clock instant of its step. ``rows_written``: telemetry rows in chunks that
    are on disk (closed, flushed, fsync'ed); ``rows_lost``: rows the loop overwrote in the ring
    before they could be copied; ``contacts_lost`` likewise for the contact ring."""

    def __init__(self, path: str | Path, *, rate_hz: float, config: dict | None = None, t0_epoch_ns: int = 0,
                 flush_rows: int = 512, meta: dict | None = None, shape: scn.ToolShape | None = None,
                 defer_meta: bool = False) -> None:
        import foxglove
        from foxglove.channels import FrameTransformsChannel, PoseInFrameChannel, SceneUpdateChannel
        from foxglove.mcap import MCAPWriteOptions

        self.path = Path(path)
        self.flush_rows = max(1, int(flush_rows))
        self.t0_epoch_ns = int(t0_epoch_ns)
        self._f = open(self.path, "wb")  # the caller made sure of the directory: nothing is created here
        self._ctx = foxglove.Context()
        # chunks close only when this writer says (every flush_rows rows), each then fsync'ed; with
        # seeking off the SDK keeps the chunk in progress in memory and writes it whole: a crash
        # leaves no half chunk in the file
        self._w = foxglove.open_mcap(self._f, context=self._ctx,
                                     writer_options=MCAPWriteOptions(chunk_size=None, profile=PROFILE,
                                                                     disable_seeking=True))
        info = {"format": FORMAT, "rate_hz": repr(float(rate_hz)), "t0_epoch_ns": str(self.t0_epoch_ns),
                "started_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(self.t0_epoch_ns * 1e-9 or None)),
                "config": json.dumps(config or {}, sort_keys=True)}
        for k, v in (meta or {}).items():
            info[k] = v if isinstance(v, str) else json.dumps(v)
        self._info = info
        self.meta_written = False
        if not defer_meta:  # deferred: ``write_meta`` when what it says is known (at the latest, ``close``)
            self.write_meta()
        self._ch = {topic: foxglove.Channel(topic, schema=json_schema(tp) | {"title": name}, context=self._ctx).base
                    for topic, (name, tp) in TOPICS.items()}
        self._step_ch = tuple(self._ch[t] for t in STEP_TOPICS)
        self._tf = FrameTransformsChannel("/tf", context=self._ctx)
        self._dev_pose = PoseInFrameChannel("/device/pose", context=self._ctx)
        self._prx_pose = PoseInFrameChannel("/proxy/pose", context=self._ctx)
        self._scene = SceneUpdateChannel("/scene", context=self._ctx)
        kind = (meta or {}).get("tool_kind") or (config or {}).get("model", {}).get("tool") or \
            (config or {}).get("device", {}).get("kind", "")
        #: what the proxy is drawn as (the tool kind's shape until ``set_shape`` gives the Hello's)
        self.shape = scn.ToolShape.for_kind(kind)
        if shape is not None:  # a client engaged before the recording started: kept for a replay too
            self.set_shape(shape)
        self._scene_period_s = 1.0 / scn.SCENE_HZ
        self._next_scene_t = -math.inf
        self._recent: list = []   # contact updates not yet behind the scene's instant: (t_s, pos, nrm, sep)
        self._contacts_now = None
        self.scenes_written = 0
        self._enc = msgspec.json.Encoder()
        self._steps = _step_encoder()
        self.rows_written = 0
        self.rows_lost = 0
        self.contacts_written = 0
        self.contacts_lost = 0
        self.transitions_written = 0
        self.chunks = 0
        self._pending = 0
        self._read = self.start_row = 0          # telemetry ring rows consumed (absolute count)
        self.start_contact = 0
        self._contact_seq = 0   # contact ring rows consumed
        self._trans_seq = 0     # transitions consumed
        self.t_start_ns = 0     # the loop's monotonic start (status t_start_ns), for transition times
        self._sync()

    def write_meta(self, meta: dict | None = None) -> None:
        """Write the metadata record (with ``meta`` added); once. The supervisor calls it when
        the loop has published its effective limits (the caps), not before."""
        if self.meta_written:
            return
        for k, v in (meta or {}).items():
            self._info[k] = v if isinstance(v, str) else json.dumps(v)
        self._w.write_metadata(META_NAME, self._info)
        self.meta_written = True

    def set_shape(self, shape: scn.ToolShape) -> None:
        """Draw the proxy as ``shape`` from now on (a client's Hello arrived); the file keeps it
        as a metadata record (:data:`SHAPE_META_NAME`) for a replay (``hapticproxy view``)."""
        self.shape = shape
        self._w.write_metadata(SHAPE_META_NAME, {"boxes": json.dumps([[list(c), list(q), list(z)]
                                                                      for c, q, z in shape.boxes]),
                                                 "source": shape.source})

    def _sync(self) -> None:
        self._f.flush()
        os.fsync(self._f.fileno())

    def start_at(self, head: int, contact_seq: int = 0, transition_seq: int = 0) -> None:
        """Record from ring row ``head`` (contact row ``contact_seq``, transition ``transition_seq``)
        on; what came before is not part of this recording."""
        self._read = self.start_row = int(head)
        self._contact_seq = self.start_contact = int(contact_seq)
        self._trans_seq = int(transition_seq)

    def _log_ns(self, t_s: float) -> int:
        return self.t0_epoch_ns + int(round(t_s * 1e9)) if t_s == t_s else self.t0_epoch_ns

    def drain(self, shared: SharedState) -> int:
        """Copy the new contact rows, transitions and telemetry rows; returns the telemetry rows."""
        items, self._contact_seq, lost = _contacts_since(shared, self._contact_seq)
        self.contacts_lost += lost
        for it in items:
            self.add_contacts(*it)
        if self.t_start_ns == 0:
            self.t_start_ns = int(shared.status[ST["t_start_ns"]])
        for seq, t_ns, frm, to, reason, detail in shared.transitions_since(self._trans_seq):
            self._trans_seq = seq
            self.add_transition((t_ns - self.t_start_ns) * 1e-9, frm, to, reason, detail)
        self._read, head, lost = shared.catch_up(self._read)
        self.rows_lost += lost
        n = head - self._read
        if n <= 0:
            return 0
        # only complete rows, none the loop rewrote while they were copied (it runs on): the
        # others are counted as lost and dropped
        chunk = shared.rows(self._read, head)
        self.rows_lost += n - len(chunk)
        self._read = head
        self.add_rows(chunk)
        return n

    def add_rows(self, rows: np.ndarray) -> None:
        """Telemetry rows (structured ``TEL_DTYPE`` or flat float64[n, NTEL])."""
        flat = rows if rows.dtype == np.float64 else flat_rows(rows)
        chans = self._step_ch
        t0 = self.t0_epoch_ns
        for k, (t, msgs) in enumerate(self._steps.encode(flat)):
            ns = t0 + int(round(t * 1e9)) if t == t else t0
            for ch, data in zip(chans, msgs):
                ch.log(data, ns)
            if t >= self._next_scene_t:
                self._add_scene(flat[k], t, ns)
            self._pending += 1
            if self._pending >= self.flush_rows:
                self.flush()

    def add_contacts(self, hdr, key, pos, nrm, sep) -> None:
        msg = contacts_message(hdr, key, pos, nrm, sep)
        self._ch["/contacts"].log(self._enc.encode(msg), self._log_ns(msg.t_s))
        self.contacts_written += 1
        self._recent.append((msg.t_s, np.array(pos, dtype=float), np.array(nrm, dtype=float),
                             np.array(sep, dtype=float)))

    def _add_scene(self, row: np.ndarray, t: float, ns: int) -> None:
        """The 3-D scene at the row's instant: the newest contact update applied by then."""
        self._next_scene_t = t + self._scene_period_s
        recent = self._recent
        i = 0
        while i < len(recent) and recent[i][0] <= t:
            i += 1
        if i:
            self._contacts_now = recent[i - 1][1:]
            del recent[:i]
        frame = scene_frame(row, self._contacts_now)
        self._tf.log(scn.foxglove_transforms(frame, ns), log_time=ns)
        self._dev_pose.log(scn.foxglove_pose(frame.device_pose, ns), log_time=ns)
        self._prx_pose.log(scn.foxglove_pose(frame.proxy_pose, ns), log_time=ns)
        self._scene.log(scn.foxglove_scene(frame, self.shape, ns), log_time=ns)
        self.scenes_written += 1

    def add_transition(self, t_s: float, frm: int, to: int, reason: int, detail: float) -> None:
        msg = transition_message(t_s, frm, to, reason, detail)
        self._ch["/transitions"].log(self._enc.encode(msg), self._log_ns(t_s))
        self.transitions_written += 1

    def flush(self) -> None:
        """Close the chunk in progress and put it on disk."""
        self._w.flush()
        self._sync()
        self.rows_written += self._pending
        self._pending = 0
        self.chunks += 1

    def close(self) -> None:
        if self._f.closed:
            return
        self.write_meta()  # never a recording without its metadata record
        self.flush()
        self._w.close()
        self._sync()
        self._f.close()


_STEP_ENCODER: StepEncoder | None = None


def _step_encoder() -> StepEncoder:
    global _STEP_ENCODER
    if _STEP_ENCODER is None:
        _STEP_ENCODER = StepEncoder()
    return _STEP_ENCODER


def _contacts_since(shared: SharedState, seq: int):
    head = int(shared.contact_head[0])
    items, new_seq = shared.contact_rows_since(seq)
    lost = max(0, head - seq - len(items)) if head > seq else 0
    return items, new_seq, lost


def dump_ring(shared: SharedState, path: str | Path, *, rate_hz: float, config: dict | None = None,
              t0_epoch_ns: int = 0, meta: dict | None = None, shape: scn.ToolShape | None = None) -> int:
    """Write what the rings hold now (oldest first) as a recording, the proxy drawn as ``shape``
    (the engaged client's tool; None: its kind's); returns the telemetry rows."""
    head = int(shared.head[0])
    n = min(head, shared.ring_rows)
    w = McapRecorder(path, rate_hz=rate_hz, config=config, t0_epoch_ns=t0_epoch_ns, flush_rows=max(16, n),
                     meta=meta, shape=shape)
    w.start_at(head - n, 0, 0)
    w.drain(shared)
    w.close()
    return n


# ---------------------------------------------------------------------------- reading
@dataclass
class Recording:
    """What ``read`` returns. ``tel``: the telemetry rows (``TEL_DTYPE``; ``rows`` the same as
    float64[n, NTEL]); ``contacts``: one dict per model update; ``transitions``: ``Transition``s."""

    meta: dict
    tel: np.ndarray
    contacts: list = field(default_factory=list)
    transitions: list = field(default_factory=list)
    torn_bytes: int = 0
    chunks: int = 0

    @property
    def rows(self) -> np.ndarray:
        return flat_rows(self.tel)


def is_mcap(path: str | Path) -> bool:
    with open(path, "rb") as f:
        return f.read(8) == b"\x89MCAP0\r\n"


def read(path: str | Path) -> Recording:
    """Every message in the complete part of a recording (a torn tail is ignored and measured)."""
    from mcap.exceptions import McapError
    from mcap.records import Footer, Message
    from mcap.stream_reader import StreamReader

    path = Path(path)
    if not is_mcap(path):
        raise ValueError(f"{path}: not an MCAP file")
    size = path.stat().st_size
    channels: dict[int, str] = {}
    meta: dict = {}
    decoders = {topic: msgspec.json.Decoder(tp) for topic, (_, tp) in TOPICS.items()}
    msgs: dict[str, list] = {t: [] for t in TOPICS}
    good = 0
    chunks = 0
    with open(path, "rb") as f:
        reader = StreamReader(f, skip_magic=False, emit_chunks=False)
        last_msg_at = -1
        try:
            for rec in reader.records:
                _take(rec, channels, msgs, decoders, meta)
                at = f.tell()
                if isinstance(rec, Message) and at != last_msg_at:
                    chunks += 1  # a chunk's messages are yielded after it was read whole
                    last_msg_at = at
                good = size if isinstance(rec, Footer) else at  # the closing magic follows the footer
        except (McapError, EOFError, ValueError, OSError, struct.error, msgspec.DecodeError):
            pass  # a torn tail: everything before it was read
    tel = _rows_from(msgs)
    contacts = [{"t_s": c.t_s, "env_time_s": c.env_time_s, "update": c.update, "count": c.count,
                 "min_separation_m": c.min_separation_m,
                 "key": np.array([k.key for k in c.contacts], dtype=np.int64).reshape(-1, 3),
                 "position_m": np.array([[k.position.x, k.position.y, k.position.z] for k in c.contacts],
                                        dtype=float).reshape(-1, 3),
                 "normal": np.array([[k.normal.x, k.normal.y, k.normal.z] for k in c.contacts],
                                    dtype=float).reshape(-1, 3),
                 "separation_m": np.array([k.separation_m for k in c.contacts], dtype=float)}
                for c in msgs["/contacts"]]
    return Recording(meta=meta, tel=tel, contacts=contacts, transitions=msgs["/transitions"],
                     torn_bytes=size - good, chunks=chunks)


def _take(rec, channels, msgs, decoders, meta) -> None:
    from mcap.records import Channel, Message, Metadata

    if isinstance(rec, Message):
        topic = channels.get(rec.channel_id)
        if topic in decoders:
            msgs[topic].append(decoders[topic].decode(rec.data))
    elif isinstance(rec, Channel):
        channels[rec.id] = rec.topic
    elif isinstance(rec, Metadata) and rec.name == SHAPE_META_NAME:
        try:
            meta["tool_shape"] = {"boxes": json.loads(rec.metadata["boxes"]), "source": rec.metadata["source"]}
        except (KeyError, ValueError):
            pass
    elif isinstance(rec, Metadata) and rec.name == META_NAME:
        m = dict(rec.metadata)
        for k in ("rate_hz", "t0_epoch_ns", "config"):
            if k in m:
                try:
                    m[k] = json.loads(m[k])
                except ValueError:
                    pass
        for k, v in list(m.items()):
            if k not in ("format", "started_utc", "rate_hz", "t0_epoch_ns", "config") and isinstance(v, str):
                try:
                    m[k] = json.loads(v)
                except ValueError:
                    pass
        meta.update(m)


def _nan(v) -> float:
    return math.nan if v is None else float(v)


def _rows_from(msgs: dict) -> np.ndarray:
    n = min(len(msgs[t]) for t in STEP_TOPICS)
    out = np.full(n, np.nan, dtype=TEL_DTYPE)
    if n == 0:
        return out
    flat = out.view(np.float64).reshape(n, NTEL)

    def put(o, v3):
        flat[i, o] = _nan(v3.x)
        flat[i, o + 1] = _nan(v3.y)
        flat[i, o + 2] = _nan(v3.z)

    for i, (d, p, c, e, lp) in enumerate(zip(*(msgs[t] for t in STEP_TOPICS))):
        if not (d.t_s == p.t_s == c.t_s == e.t_s == lp.t_s):
            raise ValueError(f"recording: step messages out of step at row {i} (t_s {d.t_s} vs {lp.t_s})")
        for o, m in ((_D, d), (_P, p)):
            put(o, m.pose.position)
            q = m.pose.orientation
            flat[i, o + 3:o + 7] = (_nan(q.w), _nan(q.x), _nan(q.y), _nan(q.z))
            put(o + 7, m.twist.linear)
            put(o + 10, m.twist.angular)
        for o, w in ((_HAND, d.hand_wrench), (_CPL, p.coupling_wrench), (_CMD, c.wrench), (_ENV, e.wrench)):
            put(o, w.force)
            put(o + 3, w.torque)
        flat[i, _T] = lp.t_s
        flat[i, _LATE] = _nan(lp.lateness_us)
        flat[i, _COMP] = _nan(lp.compute_us)
        flat[i, _STATE] = lp.state
        flat[i, _GAIN] = _nan(lp.gain)
        flat[i, _NC] = lp.contacts
        flat[i, _UPD] = lp.updates
        flat[i, _SEQ] = i  # the ring's seqlock number is not recorded: a row's number in the file
        flat[i, _EHAND] = _nan(lp.energy_hand_j)
        flat[i, _TANK] = _nan(lp.tank_j)
    return out


def read_rows(path: str | Path) -> tuple[dict, np.ndarray]:
    """``(meta, rows)`` like the ``.hpt`` reader: meta with ``fields``, ``rate_hz``, ``config``,
    ``torn_bytes``, ``chunks``; rows float64[n, NTEL] (columns ``shm.TEL``)."""
    from .shm import TEL_FIELDS

    rec = read(path)
    meta = dict(rec.meta)
    meta.update(fields=list(TEL_FIELDS), torn_bytes=rec.torn_bytes, chunks=rec.chunks, blocks=rec.chunks,
                contacts=len(rec.contacts), transitions=len(rec.transitions))
    return meta, rec.rows

