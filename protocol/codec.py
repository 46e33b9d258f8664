"""Protocol v1 codec: msgspec decoding of the Struct declarations plus a vectorised numpy pass.

See SPEC.md for the wire format and :mod:`hapticproxy.protocol.messages` for the declarations.
Public surface:

- message classes :class:`Hello`, :class:`Welcome`, :class:`Reject`, :class:`ContactUpdate`,
  :class:`ProxyState`, :class:`Heartbeat`, :class:`Bye`, :class:`Error` (msgspec Structs; keyword
  constructors; ``session_id``/``token`` header attributes default to 0);
- :class:`Codec` (limits + counters): ``encode(msg) -> bytes``,
  ``encode_contact_update(...)`` / ``encode_proxy_state(...)`` (fast paths from arrays),
  ``decode(data) -> Message`` (raises :class:`ProtocolError`), ``try_decode(data) -> Message |
  ProtocolError`` (never raises, counts every rejection);
- module-level ``encode`` / ``decode`` / ``try_decode`` on a default :class:`Codec`.

Decoding: the datagram length is checked first; the array header and the first three header
integers are read from the first bytes to pick the message's msgspec decoder, which checks every
type, range, enum and fixed length the declaration states in one C pass. What msgspec cannot
express runs after it, vectorised: finite-and-bounded float bins (one ``vdot``), unit normals
(a square and two gemvs), unique contact keys (one set of n 24-byte strings), quaternions,
inertia, linkage trees and the :class:`Limits`. A msgspec error is mapped to the
:class:`ErrorCode` and the field it names (the error path re-reads the packet to tell a
non-finite value from an out-of-range one).
"""
from __future__ import annotations

import dataclasses
import math
import re
import struct
import threading
from dataclasses import dataclass
from typing import Any

import msgpack
import msgspec
import numpy as np

from .messages import (
    CONTACT_FLOATS,
    HEADER_LEN,
    INPUT_BUTTONS,
    INPUT_GRIPPER,
    INPUT_GRIPPER_RATE,
    KEY_INTS,
    MAX_ABS_FLOAT,
    MESSAGE_CLASSES,
    PROTOCOL_MAJOR,
    PROTOCOL_MINOR,
    UNIT_TOLERANCE,
    Bye,
    ContactUpdate,
    Error,
    Heartbeat,
    Hello,
    Link,
    Message,
    ProxyState,
    Reject,
    Welcome,
    device_inputs_fields,
    fields_of,
)
from .vocab import ErrorCode, JointType, MessageType, ServerState, ToolKind

__all__ = [
    "Bye",
    "Codec",
    "CodecCounters",
    "ContactUpdate",
    "Error",
    "Heartbeat",
    "Hello",
    "Limits",
    "Link",
    "Message",
    "MESSAGE_CLASSES",
    "ProtocolError",
    "ProxyState",
    "Reject",
    "Welcome",
    "decode",
    "encode",
    "try_decode",
]

_F8 = np.dtype("<f8")
_I8 = np.dtype("<i8")
_U64_MAX = (1 << 64) - 1
# |n|^2 bounds equivalent to | |n| - 1 | <= UNIT_TOLERANCE, so no sqrt on the hot path.
_UNIT_SQ_LO = (1.0 - UNIT_TOLERANCE) ** 2
_UNIT_SQ_HI = (1.0 + UNIT_TOLERANCE) ** 2
# tol on |n|^2 - 1, the tighter of the two sides of the |n| window, squared.
_UNIT_SQ_DEV2 = min(1.0 - _UNIT_SQ_LO, _UNIT_SQ_HI - 1.0) ** 2
_MAX_ABS = MAX_ABS_FLOAT
_MAX_ABS_SQ = MAX_ABS_FLOAT * MAX_ABS_FLOAT
_POSE = struct.Struct("<7d")
_QUAT = struct.Struct("<4d")


# ------------------------------------------------------------------------------- limits
@dataclass(frozen=True)
class Limits:
    """Decoder bounds. ``max_packet_bytes`` is compared with ``len(data)`` before anything is
    decoded; strings, contact counts, links and joint arrays are bounded by the others; a
    top-level array longer than ``max_array_len`` or a contact bin longer than ``max_bin_bytes``
    is refused as ``MALFORMED``; maps and ext types are never valid."""

    max_packet_bytes: int = 8192
    max_contacts: int = 64
    max_str_bytes: int = 256
    max_links: int = 32

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):  # every bound, so a new one is checked too
            value = getattr(self, f.name)
            if type(value) is not int or value < 1:
                raise ValueError(f"Limits.{f.name} must be a positive int, got {value!r}")
        if self.max_packet_bytes > 65507:
            raise ValueError(f"Limits.max_packet_bytes must be <= 65507 (UDP), got {self.max_packet_bytes}")
        if self.max_contacts > 0xFFFF:
            raise ValueError(f"Limits.max_contacts must be <= 65535, got {self.max_contacts}")

    @property
    def max_bin_bytes(self) -> int:
        # The largest bin is contact_data; a future minor may append columns, bounded by the packet.
        return min(self.max_packet_bytes, max(self.max_contacts * CONTACT_FLOATS * 8, 3 * self.max_links * 8, 64))

    @property
    def max_array_len(self) -> int:
        # Longest array: the top-level one (header + fields + some future trailing fields) or links.
        return max(64, self.max_links)


# ------------------------------------------------------------------------------- errors
class ProtocolError(ValueError):
    """A packet was rejected. ``code`` (:class:`ErrorCode`) says why, ``field`` names the field.

    Header values are filled in when the header could be read (``type_id``, ``session_id``,
    ``token``; ``seq`` and ``client_nonce`` when the message has them and they were read), so
    the session layer can attribute the error and answer with a rate-limited ``Error`` (or a
    ``Reject`` for a Hello whose nonce could be read, even a truncated one).
    """

    # What the decoder could read of the packet: class-level defaults (0: not read), set on the
    # instance only where the decoder attributes the error.
    type_id: int = 0
    major: int = 0
    session_id: int = 0
    token: int = 0
    seq: int = 0
    client_nonce: int = 0
    #: a foreign-major Hello's offered version range, when readable
    version_min: tuple[int, int] | None = None
    version_max: tuple[int, int] | None = None

    def __init__(self, code: ErrorCode, field: str, detail: str) -> None:
        super().__init__(f"{code.name}: {field or 'packet'}: {detail}")
        self.code = code
        self.field = field
        self.detail = detail


class CodecCounters:
    """Plain-int counters of one :class:`Codec`: one per rejection code (lower-case
    :class:`ErrorCode` name, e.g. ``non_finite``), plus ``decoded`` (packets accepted),
    ``encoded``, ``unknown_trailing_fields`` (total unknown trailing fields ignored) and
    ``packets_with_unknown_fields``."""

    _CODES = tuple(c for c in ErrorCode if c < 20)
    __slots__ = ("decoded", "encoded", "rejected", "unknown_trailing_fields", "packets_with_unknown_fields") + tuple(
        c.name.lower() for c in _CODES
    )

    def __init__(self) -> None:
        for name in self.__slots__:
            setattr(self, name, 0)

    def count(self, code: ErrorCode) -> None:
        self.rejected += 1
        name = code.name.lower()
        if name in self.__slots__:
            setattr(self, name, getattr(self, name) + 1)

    def as_dict(self) -> dict[str, int]:
        return {name: getattr(self, name) for name in self.__slots__}

    def __repr__(self) -> str:
        return "CodecCounters(" + ", ".join(f"{k}={v}" for k, v in self.as_dict().items() if v) + ")"


def _bad(code: ErrorCode, field: str, detail: str) -> ProtocolError:
    return ProtocolError(code, field, detail)


# ------------------------------------------------------------- msgspec errors -> ErrorCode
_PATH = re.compile(r"^(.*?)(?: - at `\$((?:\[\d+\])*)`)?$", re.S)
_INDEX = re.compile(r"\[(\d+)\]")


def _field_path(cls: type, indices: list[int]) -> tuple[str, str]:
    """The field name a msgspec error path names (``links[1].com_m[2]``) and the wire type of
    the innermost declared field reached (``"header"`` for the 5 header integers)."""
    name, wire, tp = "", "", cls
    first = True
    for i in indices:
        if isinstance(tp, type) and issubclass(tp, msgspec.Struct):
            if issubclass(tp, Message) and first:
                if i < HEADER_LEN:
                    return "", "header"
                i -= HEADER_LEN
            docs = fields_of(tp)
            if i >= len(docs):
                break
            f = docs[i]
            name = f.name if not name else f"{name}.{f.name}"
            wire, tp = f.type, f.py_type
        elif wire == "version":
            break  # a version's parts are not named on their own
        elif wire == "links":
            name, tp, wire = f"{name}[{i}]", Link, "link"
        else:
            name = f"{name}[{i}]"
            wire = "element"
        first = False
    return name, wire


def _value_at(obj, indices: list[int]):
    for i in indices:
        if type(obj) is not list or i >= len(obj):
            return None
        obj = obj[i]
    return obj


def _from_msgspec(exc: Exception, cls: type, data) -> ProtocolError:
    text = str(exc)
    m = _PATH.match(text)
    what, path = (m.group(1), m.group(2) or "") if m else (text, "")
    indices = [int(x) for x in _INDEX.findall(path)]
    if indices and indices[0] < HEADER_LEN:
        return _bad(ErrorCode.BAD_HEADER, "", "header must be [major u16, minor u16, type_id u8, session_id u32, token u64]")
    name, wire = _field_path(cls, indices)
    if what.startswith("Expected `array` of at least length"):
        # a short nested record: name the first missing field
        got = int(what.rsplit(" ", 1)[-1])
        sub = fields_of(Link) if wire == "link" else ()
        missing = sub[got].name if got < len(sub) else ""
        return _bad(ErrorCode.MISSING_FIELD, f"{name}.{missing}" if missing else name, what)
    if wire == "version":
        if what.startswith("Expected `array`, got"):
            return _bad(ErrorCode.WRONG_TYPE, name, "expected [major, minor]")
        if what.startswith("Expected `array` of length"):
            return _bad(ErrorCode.BAD_SHAPE, name, "expected [major, minor]")
        return _bad(ErrorCode.OUT_OF_RANGE, name, f"version parts must be u16 ({what})")
    if what.startswith(("Expected `array` of length", "Expected `bytes` of length", "Expected `str` of length")):
        return _bad(ErrorCode.BAD_SHAPE, name, what)
    if what.startswith("Expected `") and ", got `" in what:
        got = what.rsplit("`", 2)[-2]
        if got in ("object", "ext"):
            return _bad(ErrorCode.MALFORMED, "", "maps and ext types are not allowed")
        return _bad(ErrorCode.WRONG_TYPE, name, what)
    if what.startswith("Expected `") or what.startswith("Invalid enum value"):
        value = _value_at(_unpack_plain(data), indices)
        if type(value) is float and not math.isfinite(value):
            return _bad(ErrorCode.NON_FINITE, name, f"{value!r} is not finite")
        return _bad(ErrorCode.OUT_OF_RANGE, name, what)
    return _bad(ErrorCode.MALFORMED, "", what)


def _unpack_plain(data):
    try:
        return msgpack.unpackb(data)
    except Exception:  # noqa: BLE001
        return None


# ------------------------------------------------------------------ prefix reading
def _read_int(data, p: int) -> tuple[int | None, int]:
    """One msgpack integer at ``data[p]`` and the position after it (None if not an int)."""
    if p >= len(data):
        return None, p
    b = data[p]
    if b < 0x80:
        return b, p + 1
    if b >= 0xE0:
        return b - 0x100, p + 1
    width = {0xCC: 1, 0xCD: 2, 0xCE: 4, 0xCF: 8, 0xD0: 1, 0xD1: 2, 0xD2: 4, 0xD3: 8}.get(b)
    if width is None or p + 1 + width > len(data):
        return None, p
    return int.from_bytes(data[p + 1:p + 1 + width], "big", signed=b >= 0xD0), p + 1 + width


def _read_prefix(data, k: int) -> list[int]:
    """The leading integers (at most k) of a packet whose first element is an array, as far as
    they can be read; used to attribute a packet that does not decode (e.g. a truncated Hello)."""
    if not len(data):
        return []
    b = data[0]
    if 0x90 <= b <= 0x9F:
        p = 1
    elif b == 0xDC:
        p = 3
    elif b == 0xDD:
        p = 5
    else:
        return []
    out = []
    while len(out) < k:
        v, p = _read_int(data, p)
        if v is None:
            break
        out.append(v)
    return out


# ------------------------------------------------------------------------- value checks
def _check_float_array(name: str, a: np.ndarray) -> None:
    # Two NaN-propagating reductions decide finite-and-bounded for the whole array at once.
    lo = _minimum(a)
    hi = _maximum(a)
    if lo >= -_MAX_ABS and hi <= _MAX_ABS:
        return
    bad = np.flatnonzero(~np.isfinite(a))
    if bad.size:
        raise _bad(ErrorCode.NON_FINITE, name, f"non-finite value at flat index {int(bad[0])}")
    i = int(np.argmax(np.abs(a)))
    raise _bad(ErrorCode.OUT_OF_RANGE, name, f"|value| > {_MAX_ABS:g} at flat index {i}")


def _check_unit(name: str, xs) -> None:
    norm = math.sqrt(math.fsum(x * x for x in xs))
    if not abs(norm - 1.0) <= UNIT_TOLERANCE:
        raise _bad(ErrorCode.NOT_UNIT, name, f"norm {norm!r} is not 1 within {UNIT_TOLERANCE:g}")


def _check_inertia(name: str, xs) -> None:
    ixx, iyy, izz, ixy, ixz, iyz = xs
    if min(ixx, iyy, izz) < 0.0:
        raise _bad(ErrorCode.OUT_OF_RANGE, name, f"negative moment of inertia in {tuple(xs)}")
    eig = np.linalg.eigvalsh(np.array([[ixx, ixy, ixz], [ixy, iyy, iyz], [ixz, iyz, izz]]))
    scale = max(1.0, abs(float(eig[-1])))
    if eig[0] < -1e-9 * scale:
        raise _bad(ErrorCode.OUT_OF_RANGE, name, f"inertia not positive semi-definite (eigenvalue {float(eig[0])!r})")
    # No triangle-inequality check: planar and 1-DOF tools legitimately send only Izz or zeros.


def _check_str(name: str, v: str, max_bytes: int) -> None:
    if len(v) * 4 > max_bytes and len(v.encode("utf-8", "surrogatepass")) > max_bytes:
        raise _bad(ErrorCode.BAD_SHAPE, name, f"longer than max_str_bytes {max_bytes} (UTF-8)")


def _check_bin_f64(name: str, v: bytes, max_values: int) -> np.ndarray:
    nb = len(v)
    if nb % 8:
        raise _bad(ErrorCode.BAD_SHAPE, name, f"{nb} bytes is not a whole number of float64")
    if nb > 8 * max_values:
        raise _bad(ErrorCode.BAD_SHAPE, name, f"{nb >> 3} values > max_links {max_values}")
    a = _frombuffer(v) if nb else _EMPTY
    if nb and not _vdot(a, a) <= _MAX_ABS_SQ:  # sufficient test first, exact one on failure
        _check_float_array(name, a)
    return a


_frombuffer = np.frombuffer
_ndarray = np.ndarray
_KEY_DT = np.dtype((_I8, (KEY_INTS,)))
_ONES3 = np.ones(3)
_ONES3.flags.writeable = False
_minimum = np.minimum.reduce
_maximum = np.maximum.reduce
_vdot = np.vdot
_EMPTY = np.zeros(0)
_EMPTY.flags.writeable = False
#: no device inputs reported (``encode_proxy_state(inputs=None)``)
_NO_INPUTS = np.full(3, np.nan)
_NO_INPUTS.flags.writeable = False
_EMPTY_3 = np.zeros((0, 3))
_EMPTY_3.flags.writeable = False
_EMPTY_K = np.zeros((0, 3), dtype=np.int64)
_EMPTY_K.flags.writeable = False
_EMPTY_COLS = np.zeros((CONTACT_FLOATS, 0))
_EMPTY_COLS.flags.writeable = False
_SERVER_STATES = frozenset(int(v) for v in ServerState)


# ----------------------------------------------------------------- per-message post-passes
# What msgspec cannot state: each takes (codec, decoded message) and raises ProtocolError.
def _post_hello(codec: Codec, msg: Hello) -> None:
    if msg.session_id or msg.token:
        raise _bad(ErrorCode.BAD_HEADER, "session_id" if msg.session_id else "token",
                   "a Hello carries session_id 0 and token 0")
    lim = codec.limits
    _check_str("engine", msg.engine, lim.max_str_bytes)
    _check_str("units", msg.units, lim.max_str_bytes)
    _check_inertia("inertia_kg_m2", msg.inertia_kg_m2)
    _check_unit("axis", msg.axis)
    links = msg.links
    if len(links) > lim.max_links:
        raise _bad(ErrorCode.BAD_SHAPE, "links", f"{len(links)} links > max_links {lim.max_links}")
    for i, ln in enumerate(links):
        _check_inertia(f"links[{i}].inertia_kg_m2", ln.inertia_kg_m2)
        _check_unit(f"links[{i}].joint_axis", ln.joint_axis)
        _check_unit(f"links[{i}].joint_origin.quaternion", ln.joint_origin[3:])
    for i, ln in enumerate(links):
        if i == 0:
            if ln.parent != -1 or ln.joint_type != JointType.ROOT:
                raise _bad(ErrorCode.BAD_TREE, "links[0]", "link 0 must be the root: parent -1, joint_type 0")
        else:
            if not 0 <= ln.parent < i:
                raise _bad(ErrorCode.BAD_TREE, f"links[{i}].parent",
                           f"parent {ln.parent} must be an earlier link (0 <= parent < {i})")
            if ln.joint_type == JointType.ROOT:
                raise _bad(ErrorCode.BAD_TREE, f"links[{i}].joint_type", "only link 0 may be the root")
    kind = msg.tool_kind
    ixx, iyy, izz = msg.inertia_kg_m2[:3]
    if kind == ToolKind.LINKAGE:
        if not links:
            raise _bad(ErrorCode.BAD_TREE, "links", "a linkage tool needs at least one link")
        if not msg.held_link < len(links):
            raise _bad(ErrorCode.BAD_TREE, "held_link", f"{msg.held_link} is not a link index (< {len(links)})")
    else:
        if links:
            raise _bad(ErrorCode.BAD_TREE, "links", f"only a linkage tool has links (tool_kind {int(kind)})")
        if msg.held_link != 0:
            raise _bad(ErrorCode.BAD_TREE, "held_link", "must be 0 for a rigid tool")
        if kind == ToolKind.PLANAR and not izz > 0.0:
            raise _bad(ErrorCode.OUT_OF_RANGE, "inertia_kg_m2", "a planar tool needs Izz > 0")
        if kind == ToolKind.SPATIAL and not min(ixx, iyy, izz) > 0.0:
            raise _bad(ErrorCode.OUT_OF_RANGE, "inertia_kg_m2", "a spatial tool needs Ixx, Iyy, Izz > 0")


def _post_welcome(codec: Codec, msg: Welcome) -> None:
    if not (msg.session_id and msg.token):
        raise _bad(ErrorCode.BAD_HEADER, "session_id", "Welcome must carry a non-zero session_id and token")
    _check_str("server_name", msg.server_name, codec.limits.max_str_bytes)
    _check_str("note", msg.note, codec.limits.max_str_bytes)


def _post_strings(*names: str):
    def post(codec: Codec, msg) -> None:
        for n in names:
            _check_str(n, getattr(msg, n), codec.limits.max_str_bytes)
    return post


_POST = {
    Hello: _post_hello,
    Welcome: _post_welcome,
    Reject: _post_strings("reason"),
    Bye: _post_strings("reason"),
    Error: _post_strings("field", "detail"),
}


# ------------------------------------------------------------------------ encoding helpers
def _u(v: Any, name: str, hi: int) -> int:
    if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or not 0 <= int(v) <= hi:
        raise ValueError(f"{name} must be an integer in [0, {hi}], got {v!r}")
    return int(v)


def _describe(a: Any) -> str:
    if isinstance(a, np.ndarray):
        return f"{a.dtype} array of shape {a.shape}"
    return type(a).__name__


def _to_wire(wire: str, name: str):
    """A converter from a Python attribute value to the value msgspec encodes (shape and range
    are then checked by decoding the packet)."""
    if wire.startswith("bin"):
        def enc_bin(v):
            if type(v) is bytes:
                return v
            if type(v) is np.ndarray and v.dtype == _F8:
                return v.tobytes()  # C order, whatever the strides
            return np.asarray(v, dtype=_F8).tobytes()
        return enc_bin
    if wire in ("pose", "inertia", "version") or wire.startswith("f64["):
        conv = int if wire == "version" else float
        return lambda v: [conv(x) for x in np.asarray(v).ravel().tolist()]
    if wire == "links":
        return lambda v: [ln if type(ln) is Link else Link(**ln) if isinstance(ln, dict) else Link(*ln) for ln in v]
    if wire == "str":
        def enc_s(v):
            if not isinstance(v, str):
                raise ValueError(f"{name}: expected a string, got {v!r}")
            return v
        return enc_s
    if wire == "f64":
        def enc_f(v):
            if isinstance(v, (bool, str)) or not isinstance(v, (int, float, np.integer, np.floating)):
                raise ValueError(f"{name}: expected a number, got {v!r}")
            return float(v)
        return enc_f

    def enc_i(v):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)):
            raise ValueError(f"{name}: expected an integer, got {v!r}")
        return int(v)
    return enc_i


def _enc_hook(obj):
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, np.floating):
        return float(obj)
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    raise NotImplementedError(f"cannot encode {type(obj).__name__}")


class _DecodeScratch(threading.local):
    """One thread's ContactUpdate decode plans (``plans[n]``, see ``Codec._cu_plan``) and the
    (2, max_contacts) unit-normal scratch they view."""

    def __init__(self, max_contacts: int) -> None:
        self.plans: list[tuple | None] = [None] * (max_contacts + 1)
        self.unit = np.ones((2, max_contacts))


class _Layout:
    """How one message class is decoded and encoded by a codec."""

    __slots__ = ("cls", "decoder", "names", "required", "known", "post", "encoders", "since")

    def __init__(self, cls: type[Message]) -> None:
        docs = fields_of(cls)
        self.cls = cls
        self.decoder = msgspec.msgpack.Decoder(cls)
        self.names = tuple(f.name for f in docs)
        self.required = sum(1 for f in docs if f.since_minor == 0)  # wire-required: every minor-0 field
        self.known = len(docs)
        self.since = tuple(f.since_minor for f in docs)
        post = None
        for base, fn in _POST.items():
            if issubclass(cls, base):
                post = fn
        self.post = post
        self.encoders = tuple((f.name, _to_wire(f.type, f.name)) for f in docs)


# ------------------------------------------------------------------------------- the codec
class Codec:
    """Encoder/decoder with its :class:`Limits` and :class:`CodecCounters`.

    One per endpoint (not thread-safe: counters are per instance; decode scratch is per
    thread). ``messages`` defaults to the v1 declarations; tests pass extended Structs to
    exercise versioning. ``minor`` is the minor version this side writes (header and layout).
    """

    def __init__(self, limits: Limits | None = None, *, messages=None, minor: int = PROTOCOL_MINOR,
                 contact_check=None, proxy_state_packer=None) -> None:
        self.limits = limits or Limits()
        #: ``proxy_state_packer(minor, session_id, token, seq, ack_seq, server_time_s, pose, twist,
        #: wrench, joint_position, joint_velocity, joint_effort, server_state, epsilon_m, lead_s,
        #: has_state, inputs, has_inputs) -> bytes | None``: may pack a trusted ProxyState (the same bytes as this
        #: codec's; ``None``: not sure, and this codec packs it, naming any bad field)
        self._ps_packer = proxy_state_packer
        #: ``contact_check(cols, normal, keys) -> bool``: may vouch that a ContactUpdate's
        #: contacts keep every value rule (then the numpy rules are skipped); ``False`` means
        #: "not sure", never "invalid" (see :meth:`_check_contacts`)
        self._contact_check = contact_check
        self.counters = CodecCounters()
        self.minor = minor
        self._encoder = msgspec.msgpack.Encoder(enc_hook=_enc_hook)
        self._enc = self._encoder.encode
        classes = dict(MESSAGE_CLASSES)
        for cls in messages or ():
            classes[int(cls.TYPE_ID)] = cls
        self._layouts = {tid: _Layout(cls) for tid, cls in classes.items()}
        for tid, lay in self._layouts.items():
            if tid in (MessageType.CONTACT_UPDATE, MessageType.PROXY_STATE) and lay.cls is not MESSAGE_CLASSES[tid]:
                raise ValueError(f"a modified {lay.cls.__name__} declaration needs its own decoder")
        lim = self.limits
        self._max_packet_bytes = lim.max_packet_bytes
        self._max_bin_len = lim.max_bin_bytes
        self._max_array_len = lim.max_array_len
        self._max_contacts = lim.max_contacts
        self._max_links = lim.max_links
        cu = self._layouts[MessageType.CONTACT_UPDATE]
        ps = self._layouts[MessageType.PROXY_STATE]
        self._cu_decode = cu.decoder.decode
        self._ps_decode = ps.decoder.decode
        self._cu_minor_fields = sum(1 for s in cu.since if s <= minor)
        self._ps_has_state = minor >= 2
        self._ps_has_inputs = minor >= 3
        # Per-thread ContactUpdate decode plans, one per contact count n, built on first use
        # (see _cu_plan). Per thread because a plan holds a scratch row the validation writes:
        # two threads sharing one codec must never validate against each other's numbers.
        self._cu_local = _DecodeScratch(lim.max_contacts)

    # ------------------------------------------------------------------------ decoding
    def try_decode(self, data) -> Message | ProtocolError:
        """Decode and validate one packet; never raises. Returns the message, or the
        :class:`ProtocolError` (already counted in :attr:`counters`)."""
        try:
            return self._decode(data)
        except ProtocolError as exc:
            self.counters.count(exc.code)
            return exc
        except Exception as exc:  # noqa: BLE001 - the receive path must never raise
            err = _bad(ErrorCode.MALFORMED, "", f"unexpected {type(exc).__name__}: {exc}")
            self.counters.count(err.code)
            return err

    def decode(self, data) -> Message:
        """Like :meth:`try_decode` but raises the :class:`ProtocolError` (a ``ValueError``)."""
        out = self.try_decode(data)
        if isinstance(out, ProtocolError):
            raise out
        return out

    def _decode(self, data) -> Message:
        n = len(data)
        if n > self._max_packet_bytes:
            raise _bad(ErrorCode.OVERSIZE, "", f"{n} bytes > max_packet_bytes {self._max_packet_bytes}")
        # The array header and the first three header integers, read from the first bytes when
        # they are the usual one-byte forms; anything else takes the general path.
        b = data[0] if n else 0
        if 0x95 <= b <= 0x9F and n > 3:
            count, p = b - 0x90, 1
        elif b == 0xDC and n > 5:
            count, p = (data[1] << 8) | data[2], 3
        else:
            count = p = 0
        if p and data[p] < 0x80 and data[p + 1] < 0x80 and data[p + 2] < 0x80:
            major, type_id = data[p], data[p + 2]
        else:
            count, major, type_id = self._general_header(data)
        if count > self._max_array_len:
            raise _bad(ErrorCode.MALFORMED, "", f"array of {count} elements > max_array_len {self._max_array_len}")
        try:
            if type_id == 4 and major == 1:
                return self._decode_contact_update(data, count)
            if type_id == 5 and major == 1:
                return self._decode_proxy_state(data, count)
            lay = self._layouts.get(type_id)
            if lay is None:
                raise _bad(ErrorCode.UNKNOWN_TYPE, "type_id", f"unknown message type id {type_id}")
            if major != PROTOCOL_MAJOR and type_id != MessageType.REJECT:  # Reject's layout is frozen
                self._foreign_major(data, major, type_id)
            msg = self._decode_generic(lay, data, count)
        except ProtocolError as exc:
            if exc.code == ErrorCode.MALFORMED or (exc.code == ErrorCode.BAD_HEADER and not exc.field):
                self._attribute_prefix(exc, data)  # not a readable packet: a Hello's nonce at most
            else:
                self._attribute(exc, data, type_id, major)
            raise
        self.counters.decoded += 1
        return msg

    def _general_header(self, data) -> tuple[int, int, int]:
        """The header of a packet whose first bytes are not the common forms, with the checks
        (and verdicts) of a full unpack: not one msgpack object -> MALFORMED, no 5-integer
        header -> BAD_HEADER."""
        try:
            obj = msgpack.unpackb(data, max_bin_len=self._max_bin_len, max_str_len=self._max_packet_bytes,
                                  max_array_len=self._max_array_len, max_map_len=0, max_ext_len=0)
        except Exception as exc:  # noqa: BLE001 - any msgpack failure, incl. limits and bad UTF-8
            err = _bad(ErrorCode.MALFORMED, "", f"{type(exc).__name__}: {exc}")
            self._attribute_prefix(err, data)
            raise err from None
        if type(obj) is not list or len(obj) < HEADER_LEN:
            raise _bad(ErrorCode.BAD_HEADER, "", "packet must be an array of at least 5 header integers")
        major, minor, type_id, session_id, token = obj[:HEADER_LEN]
        if not (type(major) is int and type(minor) is int and type(type_id) is int
                and type(session_id) is int and type(token) is int
                and 0 <= major <= 0xFFFF and 0 <= minor <= 0xFFFF and 0 <= type_id <= 0xFF
                and 0 <= session_id <= 0xFFFF_FFFF and 0 <= token <= _U64_MAX):
            raise _bad(ErrorCode.BAD_HEADER, "", "header must be [major u16, minor u16, type_id u8, session_id u32, token u64]")
        return len(obj), major, type_id

    def _attribute(self, exc: ProtocolError, data, type_id: int, major: int) -> None:
        """Fill in what the session layer needs to answer a rejected packet."""
        ints = _read_prefix(data, HEADER_LEN + 1)
        exc.type_id, exc.major = type_id, major
        if len(ints) >= HEADER_LEN:
            sid, tok = ints[3], ints[4]
            if 0 <= sid <= 0xFFFF_FFFF and 0 <= tok <= _U64_MAX:
                exc.session_id, exc.token = sid, tok
        if len(ints) > HEADER_LEN and 0 <= ints[HEADER_LEN] <= _U64_MAX:
            first = ints[HEADER_LEN]
            if exc.seq == 0 and type_id in (MessageType.CONTACT_UPDATE, MessageType.PROXY_STATE, MessageType.HEARTBEAT):
                exc.seq = first
            elif exc.client_nonce == 0 and type_id == MessageType.HELLO:
                exc.client_nonce = first  # lets the server answer a bad Hello with Reject

    def _attribute_prefix(self, exc: ProtocolError, data) -> None:
        # A packet that is not one msgpack object (e.g. a truncated datagram) is attributed
        # only when it is a Hello whose nonce can be read: the server then answers with Reject.
        ints = _read_prefix(data, HEADER_LEN + 1)
        if len(ints) > HEADER_LEN and ints[2] == MessageType.HELLO and 0 < ints[HEADER_LEN] <= _U64_MAX:
            exc.type_id, exc.major, exc.client_nonce = int(MessageType.HELLO), ints[0], ints[HEADER_LEN]

    def _foreign_major(self, data, major: int, type_id: int) -> None:
        err = _bad(ErrorCode.UNKNOWN_MAJOR, "major", f"major version {major} not supported (this side speaks {PROTOCOL_MAJOR})")
        if type_id == MessageType.HELLO:
            # Hello's first three fields are frozen so the server can answer with Reject.
            obj = _unpack_plain(data)
            f = obj[HEADER_LEN:HEADER_LEN + 3] if type(obj) is list else []
            if len(f) == 3 and type(f[0]) is int and 0 <= f[0] <= _U64_MAX:
                err.client_nonce = f[0]
                ok = all(type(v) is list and len(v) == 2 and all(type(x) is int and 0 <= x <= 0xFFFF for x in v)
                         for v in f[1:])
                if ok:
                    err.version_min, err.version_max = tuple(f[1]), tuple(f[2])
        raise err

    @staticmethod
    def _refused(exc: Exception, cls: type, data) -> ProtocolError:
        if isinstance(exc, msgspec.ValidationError):
            return _from_msgspec(exc, cls, data)
        # truncated, trailing bytes, bad UTF-8, ...
        return _bad(ErrorCode.MALFORMED, "", f"{type(exc).__name__}: {exc}")

    def _known_fields(self, lay: _Layout, count: int) -> int:
        """Check the field count against the declaration; returns the unknown trailing ones."""
        nf = count - HEADER_LEN
        if nf < lay.required:
            raise _bad(ErrorCode.MISSING_FIELD, lay.names[nf] if nf >= 0 else "",
                       f"{lay.cls.__name__} needs {lay.required} fields, got {nf}")
        extra = nf - lay.known
        if extra > 0:
            self.counters.unknown_trailing_fields += extra
            self.counters.packets_with_unknown_fields += 1
            return extra
        return 0

    def _decode_generic(self, lay: _Layout, data, count: int) -> Message:
        extra = self._known_fields(lay, count)
        try:
            msg = lay.decoder.decode(data)
        except Exception as exc:  # noqa: BLE001 - mapped to the code and field it names
            raise self._refused(exc, lay.cls, data) from None
        if extra:
            msg.unknown_fields = extra
        if lay.post is not None:
            lay.post(self, msg)
        return msg

    def _decode_contact_update(self, data, count: int) -> ContactUpdate:
        # The server decodes one per environment step: msgspec has checked the types, ranges and
        # the pose's length; the rest is a fixed handful of vectorised checks whatever n is.
        nf = count - HEADER_LEN
        if nf != 6:
            extra = self._known_fields(self._layouts[4], count)
        else:
            extra = 0
        try:
            msg = self._cu_decode(data)
        except Exception as exc:  # noqa: BLE001 - mapped to the code and field it names
            raise self._refused(exc, ContactUpdate, data) from None
        jb = msg.tool_joint_position
        msg.tool_joint_position = _check_bin_f64("tool_joint_position", jb, self._max_links) if jb else _EMPTY
        pose_b = msg.tool_pose
        px, py, pz, qw, qx, qy, qz = _POSE.unpack(pose_b)
        qn = qw * qw + qx * qx + qy * qy + qz * qz
        if not (-_MAX_ABS <= px <= _MAX_ABS and -_MAX_ABS <= py <= _MAX_ABS and -_MAX_ABS <= pz <= _MAX_ABS
                and _UNIT_SQ_LO <= qn <= _UNIT_SQ_HI):
            _check_float_array("tool_pose", _ndarray((7,), _F8, pose_b))
            raise _bad(ErrorCode.NOT_UNIT, "tool_pose.quaternion", f"|q| = {math.sqrt(qn)!r} is not 1 within {UNIT_TOLERANCE:g}")
        n = msg.contact_count
        if n > self._max_contacts:
            raise _bad(ErrorCode.TOO_MANY_CONTACTS, "contact_count", f"{n} > max_contacts {self._max_contacts}")
        kb = msg.contact_keys
        if len(kb) != 24 * n:
            raise _bad(ErrorCode.BAD_SHAPE, "contact_keys", f"expected {24 * n} bytes for {n} contacts, got {len(kb)}")
        db = msg.contact_data
        nd = len(db)
        if nd != 64 * n:
            # A later minor may append whole column blocks (n float64 each) after the known ones.
            if nd > self._max_bin_len:
                raise _bad(ErrorCode.MALFORMED, "", f"bin of {nd} bytes > max_bin_len {self._max_bin_len}")
            if n == 0 or nd < 64 * n or nd % (8 * n):
                raise _bad(ErrorCode.BAD_SHAPE, "contact_data",
                           f"expected {64 * n} bytes ({CONTACT_FLOATS} float64 per contact) for {n} contacts, got {nd}")
            more = nd // (8 * n) - CONTACT_FLOATS
            if not extra:
                self.counters.packets_with_unknown_fields += 1
            extra += more
            self.counters.unknown_trailing_fields += more
        msg.tool_pose = _frombuffer(pose_b)
        if extra:
            msg.unknown_fields = extra
        if n == 0:
            msg.keys = _EMPTY_K
            msg.position_m = _EMPTY_3
            msg.normal = _EMPTY_3
            msg.separation_m = _EMPTY
            msg.v_constr_m_per_s = _EMPTY
            msg.contact_columns = _EMPTY_COLS
            self.counters.decoded += 1
            return msg
        plan = self._cu_local.plans[n] or self._cu_plan(n)
        col_dt, pn_dt = plan[1], plan[2]
        # Read-only views of the packet's bytes, shaped by the dtype (a per-n subarray dtype:
        # frombuffer yields (blocks, n) or (2, n, 3) directly, with no reshape call). Rows of
        # cols: 0-5 the position and normal blocks (each n x 3, row-major), 6 separation,
        # 7 v_constr, then any column blocks a later minor appended.
        cols = _frombuffer(db, col_dt)
        pn = _frombuffer(db, pn_dt, 2)
        normal = pn[1]
        keys = _frombuffer(kb, _KEY_DT)
        fast = self._contact_check
        if fast is None or not fast(cols, normal, keys):
            self._check_contacts(cols, normal, kb, n, nd, plan)
        msg.keys = keys
        msg.position_m = pn[0]
        msg.normal = normal
        msg.separation_m = cols[6]
        msg.v_constr_m_per_s = cols[7]
        msg.contact_columns = cols
        self.counters.decoded += 1
        return msg

    def _check_contacts(self, cols, normal, kb, n: int, nd: int, plan: tuple) -> None:
        """The value rules of contact_data and contact_keys (raises the ProtocolError naming the
        first broken one). A ``contact_check`` the codec was given may vouch for a packet first
        (the server's kernel, ``server/ingest.py``); these rules decide whenever it does not."""
        key_struct, _col_dt, _pn_dt, scratch, sq, unit_margin = plan
        f = cols if nd == 64 * n else cols[:CONTACT_FLOATS]
        # Finite and bounded, all floats in one BLAS call: sum of squares <= MAX_ABS^2 implies
        # every |x| <= MAX_ABS (NaN fails the comparison; vdot, unlike ndarray.dot, raises no
        # FP warning on overflow). Only when this sufficient test fails does the exact
        # per-element check run (and raise).
        if not _vdot(f, f) <= _MAX_ABS_SQ:
            _check_float_array("contact_data", f.reshape(-1))
        # Unit normals: the rule is | |n_i| - 1 | <= UNIT_TOLERANCE for every i, i.e. s_i = |n_i|^2
        # in [_UNIT_SQ_LO, _UNIT_SQ_HI]. s_i goes into scratch row 0 ((n*n) @ [1,1,1]: a square
        # and a gemv, cheaper than vecdot/einsum; no overflow since every |x| <= MAX_ABS now).
        # Sufficient test: sum_i (s_i - 1)^2 <= d^2, d the distance from 1 to the nearer end of
        # that window. For n <= 64 one more gemv of the (2, n) scratch (row 1 all ones) gives
        # a = sum s_i^2 and b = sum s_i; q = a - 2b + n is that sum up to rounding, which is at
        # most (n + 3) u (a + 2b + n) (u = 2^-53: two dot products of n terms in any order, then
        # two scalar operations), so q plus twice that bound <= d^2 is the test. For larger n
        # the bound would eat the budget, so the deviations are formed and summed directly.
        # Either way, when the sufficient test fails, the exact per-contact test on the same
        # s_i decides.
        (normal * normal).dot(_ONES3, sq)
        if unit_margin:
            a, b = scratch.dot(sq).tolist()
            unit_ok = (a - 2.0 * b) + n + unit_margin * (a + 2.0 * b + n) <= _UNIT_SQ_DEV2
        else:
            dev = sq - 1.0
            unit_ok = dev.dot(dev) <= _UNIT_SQ_DEV2
        if not unit_ok and not (_minimum(sq) >= _UNIT_SQ_LO and _maximum(sq) <= _UNIT_SQ_HI):
            i = int(np.argmax(np.abs(sq - 1.0)))
            raise _bad(ErrorCode.NOT_UNIT, "contact_data.normal",
                       f"contact {i}: |n| = {math.sqrt(float(sq[i]))!r} is not 1 within {UNIT_TOLERANCE:g}")
        # Unique keys, exactly: n 24-byte strings into a set.
        if n > 1 and len(set(key_struct.unpack(kb))) != n:
            raise _bad(ErrorCode.DUPLICATE_KEY, "contact_keys", "the same (tool_link, env_body, feature) key appears twice")

    def _cu_plan(self, n: int) -> tuple:
        """What decoding n contacts needs, built once per n and thread (1 <= n <= max_contacts)."""
        local = self._cu_local
        # Row 0 receives |n_i|^2, row 1 stays all ones: one gemv of this (2, n) block with
        # row 0 yields (sum |n_i|^4, sum |n_i|^2).
        scratch = local.unit[:, :n]
        margin = 2.0 * (n + 3) * 2.0 ** -53
        plan = (
            struct.Struct(f"{8 * KEY_INTS}s" * n),  # n keys as n bytes objects
            np.dtype((_F8, (n,))),  # contact_data as (column blocks, n)
            np.dtype((_F8, (n, 3))),  # its first two blocks as (2, n, 3)
            scratch,
            scratch[0],
            # The identity test's rounding-bound factor, or 0.0 (direct test) where the bound at
            # s_i = 1 would leave less than 1e-13 of the tol^2 budget (n > 64).
            margin if _UNIT_SQ_DEV2 - margin * 4.0 * n >= 1e-13 else 0.0,
        )
        local.plans[n] = plan
        return plan

    def _decode_proxy_state(self, data, count: int) -> ProxyState:
        # The six float bins are validated as one array, then handed out as views of it.
        extra = self._known_fields(self._layouts[5], count)
        try:
            msg = self._ps_decode(data)
        except Exception as exc:  # noqa: BLE001 - mapped to the code and field it names
            raise self._refused(exc, ProxyState, data) from None
        jq_b, jv_b, je_b = msg.joint_position, msg.joint_velocity, msg.joint_effort
        nj = len(jq_b)
        for name, v in (("joint_position", jq_b), ("joint_velocity", jv_b), ("joint_effort", je_b)):
            if len(v) != nj or nj % 8 or nj > 8 * self._max_links:
                raise _bad(ErrorCode.BAD_SHAPE, name,
                           f"joint arrays must hold the same number (<= max_links) of float64, got {len(v)} bytes")
        pose_b = msg.proxy_pose
        allb = b"".join((pose_b, msg.proxy_twist, msg.wrench, jq_b, jv_b, je_b))
        a = _ndarray((len(allb) >> 3,), _F8, allb)
        if not _vdot(a, a) <= _MAX_ABS_SQ:
            for name, lo, hi in (("proxy_pose", 0, 7), ("proxy_twist", 7, 13), ("wrench", 13, 19)):
                _check_float_array(name, a[lo:hi])
            _check_float_array("joint arrays", a[19:])
        qw, qx, qy, qz = _QUAT.unpack_from(pose_b, 24)
        qn = qw * qw + qx * qx + qy * qy + qz * qz
        if not _UNIT_SQ_LO <= qn <= _UNIT_SQ_HI:
            raise _bad(ErrorCode.NOT_UNIT, "proxy_pose.quaternion", f"|q| = {math.sqrt(qn)!r} is not 1 within {UNIT_TOLERANCE:g}")
        j = nj >> 3
        msg.proxy_pose = a[0:7]
        msg.proxy_twist = a[7:13]
        msg.wrench = a[13:19]
        msg.joint_position = a[19:19 + j]
        msg.joint_velocity = a[19 + j:19 + 2 * j]
        msg.joint_effort = a[19 + 2 * j:]
        if extra:
            msg.unknown_fields = extra
        self.counters.decoded += 1
        return msg

    # ------------------------------------------------------------------------ encoding
    def encode(self, msg: Message) -> bytes:
        """Encode any message (header from ``msg.session_id`` / ``msg.token``, this codec's
        major and minor). Values are validated with the decoder's own rules; a bad value raises
        ``ValueError`` naming the field."""
        tid = msg.TYPE_ID
        if tid == MessageType.CONTACT_UPDATE:
            keys = getattr(msg, "keys", None)
            if keys is None:  # built from its wire fields: decode the columns first
                msg = self._self_check(self.encode_contact_update_bins(msg), "ContactUpdate")
            return self.encode_contact_update(
                msg.session_id, msg.token, msg.seq, msg.env_time_s, msg.tool_pose, msg.keys,
                msg.position_m, msg.normal, msg.separation_m, msg.v_constr_m_per_s, check=True,
                tool_joint_position=msg.tool_joint_position, work_on_tool_j=msg.work_on_tool_j)
        if tid == MessageType.PROXY_STATE:
            fl = int(msg.device_inputs)
            inputs = (msg.buttons if fl & INPUT_BUTTONS else math.nan,
                      msg.gripper_angle_rad if fl & INPUT_GRIPPER else math.nan,
                      msg.gripper_velocity_rad_per_s if fl & INPUT_GRIPPER_RATE else math.nan)
            return self.encode_proxy_state(
                msg.session_id, msg.token, msg.seq, msg.ack_seq, msg.server_time_s, msg.proxy_pose, msg.proxy_twist,
                msg.wrench, msg.joint_position, msg.joint_velocity, msg.joint_effort, msg.server_state,
                epsilon_m=msg.epsilon_m, lead_s=msg.lead_s, inputs=inputs)
        lay = self._layouts.get(int(tid))
        if lay is None or not isinstance(msg, lay.cls):
            raise ValueError(f"message type {type(msg).__name__} not declared in this codec")
        out = [PROTOCOL_MAJOR, self.minor, int(tid), _u(msg.session_id, "session_id", 0xFFFF_FFFF),
               _u(msg.token, "token", _U64_MAX)]
        for (name, enc), since in zip(lay.encoders, lay.since):
            if since <= self.minor:
                out.append(enc(getattr(msg, name)))
        packet = self._enc(out)
        self._self_check(packet, type(msg).__name__)
        self.counters.encoded += 1
        return packet

    def _self_check(self, packet: bytes, name: str) -> Message:
        saved = self.counters
        self.counters = CodecCounters()  # a self-check must not count as traffic
        try:
            return self._decode(packet)
        except ProtocolError as exc:
            raise ValueError(f"{name}.{exc.field or 'packet'}: {exc.code.name}: {exc.detail}") from None
        finally:
            self.counters = saved

    def encode_contact_update_bins(self, msg: ContactUpdate) -> bytes:
        """The packet of a ContactUpdate built from its wire fields (``contact_keys`` /
        ``contact_data`` bins), unchecked."""
        fields = [PROTOCOL_MAJOR, self.minor, 4, _u(msg.session_id, "session_id", 0xFFFF_FFFF),
                  _u(msg.token, "token", _U64_MAX), msg.seq, float(msg.env_time_s),
                  np.asarray(msg.tool_pose, _F8).tobytes(), msg.contact_count, bytes(msg.contact_keys),
                  bytes(msg.contact_data)]
        grant = float(msg.work_on_tool_j)
        if (len(msg.tool_joint_position) or (grant != 0.0 and self._cu_minor_fields > 7)) and self._cu_minor_fields > 6:
            fields.append(np.asarray(msg.tool_joint_position, _F8).tobytes())
        if grant != 0.0 and self._cu_minor_fields > 7:
            fields.append(grant)
        return self._enc(fields)

    def encode_proxy_state(self, session_id: int, token: int, seq: int, ack_seq: int, server_time_s: float,
                           proxy_pose, proxy_twist, wrench, joint_position=_EMPTY, joint_velocity=_EMPTY,
                           joint_effort=_EMPTY, server_state: int = 0, *, epsilon_m: float = 0.0,
                           lead_s: float = 0.0, trusted: bool = False, inputs=None) -> bytes:
        """Encode a ProxyState from arrays (the server's acknowledgement). Every value rule of the
        decoder is applied (one vectorised test); ``ValueError`` names the bad field.

        ``inputs``: the device's inputs as the device state row holds them (3 floats: the buttons'
        bit mask, the gripper's angle and rate; NaN where the device does not report one), or
        ``None`` (none reported); encoded as 1.3's ``buttons``, ``gripper_angle_rad``,
        ``gripper_velocity_rad_per_s`` and ``device_inputs`` (:func:`device_inputs_fields`).

        ``trusted``: the caller's own state in float64 arrays of the right shapes (the server
        loop's kernel output: its pose quaternion is unit by construction, the session ids and
        sequence numbers its own); only finiteness and the float bound are checked, so the haptic
        step that acknowledges an update pays for packing, not for re-validating what it built."""
        if trusted and self._ps_packer is not None:
            packet = self._ps_packer(self.minor, session_id, token, seq, ack_seq, server_time_s, proxy_pose,
                                     proxy_twist, wrench, joint_position, joint_velocity, joint_effort,
                                     server_state, epsilon_m, lead_s, self._ps_has_state, inputs,
                                     self._ps_has_inputs)
            if packet is not None:
                self.counters.encoded += 1
                return packet
        if trusted:
            bins = (proxy_pose.tobytes(), proxy_twist.tobytes(), wrench.tobytes(), joint_position.tobytes(),
                    joint_velocity.tobytes(), joint_effort.tobytes())
            allb = b"".join(bins)  # one finiteness test of all of them (a vdot costs ~1 us, even of 0 values)
            a = _ndarray((len(allb) >> 3,), _F8, allb)
            t = float(server_time_s)
            if _vdot(a, a) <= _MAX_ABS_SQ and -_MAX_ABS <= t <= _MAX_ABS:
                fields = [PROTOCOL_MAJOR, self.minor, 5, session_id, token, seq, ack_seq, t, *bins]
                if self._ps_has_state:
                    fields += (int(server_state), float(epsilon_m), float(lead_s))
                if self._ps_has_inputs:
                    fields += device_inputs_fields(_NO_INPUTS if inputs is None else inputs)
                packet = self._enc(fields)
                self.counters.encoded += 1
                return packet
            # not finite, or out of bounds: the checked path names the field
        bins = []
        for name, v, k in (("proxy_pose", proxy_pose, 7), ("proxy_twist", proxy_twist, 6), ("wrench", wrench, 6),
                           ("joint_position", joint_position, -1), ("joint_velocity", joint_velocity, -1),
                           ("joint_effort", joint_effort, -1)):
            if type(v) is bytes:
                v = _frombuffer(v)
            elif type(v) is not np.ndarray or v.dtype != _F8:
                v = np.asarray(v, dtype=_F8)
            if v.ndim != 1 or (k > 0 and v.shape[0] != k):
                raise ValueError(f"{name} must be {k if k > 0 else 'J'} float64 values, got shape {v.shape}")
            bins.append(v.tobytes())
        # The decoder's value rules, on all six arrays at once.
        allb = b"".join(bins)
        a = _ndarray((len(allb) >> 3,), _F8, allb)
        if not _vdot(a, a) <= _MAX_ABS_SQ:
            try:
                _check_float_array("ProxyState arrays", a)
            except ProtocolError as exc:
                raise ValueError(f"ProxyState arrays: {exc.detail}") from None
        qw, qx, qy, qz = _QUAT.unpack_from(allb, 24)
        if not _UNIT_SQ_LO <= qw * qw + qx * qx + qy * qy + qz * qz <= _UNIT_SQ_HI:
            raise ValueError("proxy_pose: quaternion is not unit within 1e-6")
        if not len(bins[3]) == len(bins[4]) == len(bins[5]) <= 8 * self._max_links:
            raise ValueError("joint_position, joint_velocity, joint_effort must have the same length <= max_links")
        t = float(server_time_s)
        if not -_MAX_ABS <= t <= _MAX_ABS:
            raise ValueError(f"server_time_s must be finite, got {server_time_s!r}")
        if isinstance(seq, bool) or not isinstance(seq, (int, np.integer)) or not 1 <= seq <= _U64_MAX:
            raise ValueError("seq must be an integer >= 1")
        state = int(server_state)
        if state not in _SERVER_STATES:
            raise ValueError(f"server_state must be a ServerState, got {server_state!r}")
        eps, lead = float(epsilon_m), float(lead_s)
        if not (0.0 <= eps <= _MAX_ABS and 0.0 <= lead <= _MAX_ABS):
            raise ValueError(f"epsilon_m and lead_s must be finite and >= 0, got {epsilon_m!r}, {lead_s!r}")
        fields = [PROTOCOL_MAJOR, self.minor, 5, _u(session_id, "session_id", 0xFFFF_FFFF), _u(token, "token", _U64_MAX),
                  int(seq), _u(ack_seq, "ack_seq", _U64_MAX), t, *bins]
        if self._ps_has_state:
            fields += (state, eps, lead)
        if self._ps_has_inputs:
            if inputs is not None and len(inputs) != 3:
                raise ValueError(f"inputs must be 3 numbers (buttons, gripper angle, gripper rate), got {len(inputs)}")
            fields += device_inputs_fields(_NO_INPUTS if inputs is None else inputs)
        packet = self._enc(fields)
        self.counters.encoded += 1
        return packet

    def encode_contact_update(self, session_id: int, token: int, seq: int, env_time_s: float, tool_pose,
                              keys: np.ndarray, position_m: np.ndarray, normal: np.ndarray,
                              separation_m: np.ndarray, v_constr_m_per_s: np.ndarray, *, check: bool = False,
                              tool_joint_position=None, work_on_tool_j: float = 0.0) -> bytes:
        """Encode a ContactUpdate straight from arrays (the environment client's hot path).

        ``keys`` int64 (n, 3); ``position_m``, ``normal`` float64 (n, 3); ``separation_m``,
        ``v_constr_m_per_s`` float64 (n,); ``tool_pose`` 7 floats (x y z qw qx qy qz);
        ``tool_joint_position`` (1.1, linkages): the engine's joint positions, J floats, appended
        only when J > 0 (so a rigid tool's packet is the 1.0 layout); ``work_on_tool_j`` (1.4): the
        work the engine did on its tool since its previous update, appended (after an empty
        ``tool_joint_position`` for a rigid tool) only when it is not 0. Shapes and dtypes are always
        checked (``ValueError`` naming the array). ``check=True`` also applies every value rule of
        the decoder (finite, unit normals, unique keys), at about the decoder's cost; without it a
        bad value is caught by the receiver instead.
        """
        n = keys.shape[0] if isinstance(keys, np.ndarray) else -1
        if n < 0 or keys.shape != (n, 3) or keys.dtype != _I8:
            raise ValueError(f"keys must be an int64 array of shape (n, 3), got {_describe(keys)}")
        if n > self._max_contacts:
            raise ValueError(f"keys: {n} contacts > max_contacts {self._max_contacts}")
        for name, a, shape in (("position_m", position_m, (n, 3)), ("normal", normal, (n, 3)),
                               ("separation_m", separation_m, (n,)), ("v_constr_m_per_s", v_constr_m_per_s, (n,))):
            if not isinstance(a, np.ndarray) or a.shape != shape or a.dtype != _F8:
                raise ValueError(f"{name} must be a float64 array of shape {shape}, got {_describe(a)}")
        if isinstance(tool_pose, np.ndarray):
            if tool_pose.shape != (7,):
                raise ValueError(f"tool_pose must have 7 values, got shape {tool_pose.shape}")
            pose_b = tool_pose.astype(_F8, copy=False).tobytes()
        else:
            if len(tool_pose) != 7:
                raise ValueError(f"tool_pose must have 7 values, got {len(tool_pose)}")
            pose_b = _POSE.pack(*tool_pose)
        data = b"".join((position_m.tobytes(), normal.tobytes(), separation_m.tobytes(), v_constr_m_per_s.tobytes()))
        fields = [PROTOCOL_MAJOR, self.minor, 4, session_id, token, seq, float(env_time_s), pose_b, n, keys.tobytes(), data]
        grant = float(work_on_tool_j)
        has_joints = tool_joint_position is not None and len(tool_joint_position)
        if (has_joints or (grant != 0.0 and self._cu_minor_fields > 7)) and self._cu_minor_fields > 6:
            jq = np.asarray(tool_joint_position if has_joints else (), dtype=_F8)
            if jq.ndim != 1 or jq.shape[0] > self._max_links:
                raise ValueError(f"tool_joint_position must be at most {self._max_links} float64 values, "
                                 f"got shape {jq.shape}")
            fields.append(jq.tobytes())
        if grant != 0.0 and self._cu_minor_fields > 7:
            if not (math.isfinite(grant) and 0.0 <= grant <= MAX_ABS_FLOAT):
                raise ValueError(f"work_on_tool_j must be a finite number of J >= 0, got {grant!r}")
            fields.append(grant)
        try:
            packet = self._enc(fields)
        except (TypeError, OverflowError) as exc:
            raise ValueError(f"ContactUpdate header or seq: {exc}") from None
        if check:
            self._self_check(packet, "ContactUpdate")
        self.counters.encoded += 1
        return packet


_DEFAULT = Codec()


def encode(msg: Message) -> bytes:
    """Encode with a module-level default :class:`Codec` (limits :class:`Limits`())."""
    return _DEFAULT.encode(msg)


def decode(data) -> Message:
    """Decode with the module-level default :class:`Codec`; raises :class:`ProtocolError`."""
    return _DEFAULT.decode(data)


def try_decode(data) -> Message | ProtocolError:
    """Decode with the module-level default :class:`Codec`; never raises."""
    return _DEFAULT.try_decode(data)
