"""Protocol v1 codec: msgpack envelope, packed contact arrays, bounded and validating decoder.

Compiled at import from the declarations in :mod:`hapticproxy.protocol.messages`; see SPEC.md
for the wire format. Public surface:

- message classes :class:`Hello`, :class:`Welcome`, :class:`Reject`, :class:`ContactUpdate`,
  :class:`ProxyState`, :class:`Heartbeat`, :class:`Bye`, :class:`Error` (generated from the
  declarations; keyword constructors; ``session_id``/``token`` header attributes default to 0);
- :class:`Codec` (limits + counters): ``encode(msg) -> bytes``,
  ``encode_contact_update(...) -> bytes`` (fast path from arrays), ``decode(data) -> Message``
  (raises :class:`ProtocolError`), ``try_decode(data) -> Message | ProtocolError`` (never raises,
  counts every rejection);
- module-level ``encode`` / ``decode`` / ``try_decode`` on a default :class:`Codec`.

Hot-path design (why it looks the way it does): a ContactUpdate is one msgpack array whose
contact vectors travel as two packed little-endian ``bin`` blobs, so decoding is one
``msgpack.unpackb`` (with every Unpacker limit set, after a length check), read-only
``np.frombuffer`` views shaped by per-count subarray dtypes (no copy beyond msgpack's), and a
fixed handful of vectorised checks regardless of the number of contacts: one ``vdot`` for
finite and bounded values, a square and two gemvs for unit normals, one set of n 24-byte
strings for unique keys. With numpy, each call costs a few hundred ns whatever n is, so the
design counts calls (``hapticproxy bench codec``).
"""
from __future__ import annotations

import math
import struct
import threading
from dataclasses import dataclass
from typing import Any

import msgpack
import numpy as np

from .messages import (
    BYE,
    CONTACT_COLUMNS,
    CONTACT_FLOATS,
    CONTACT_UPDATE,
    ERROR,
    HEADER_LEN,
    HEARTBEAT,
    HELLO,
    KEY_INTS,
    LINK_FIELDS,
    MAX_ABS_FLOAT,
    MESSAGES,
    PROTOCOL_MAJOR,
    PROTOCOL_MINOR,
    PROXY_STATE,
    REJECT,
    REQUIRED,
    UNIT_TOLERANCE,
    WELCOME,
    ErrorCode,
    FieldSpec,
    JointType,
    MessageSpec,
    MessageType,
    ServerState,
    ToolKind,
)

__all__ = [
    "Bye",
    "Codec",
    "CodecCounters",
    "ContactUpdate",
    "Error",
    "Heartbeat",
    "Hello",
    "Limits",
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
_INT_RANGES = {
    "u8": (0, 0xFF),
    "u16": (0, 0xFFFF),
    "u32": (0, 0xFFFF_FFFF),
    "u64": (0, _U64_MAX),
    "i32": (-(1 << 31), (1 << 31) - 1),
}
# |n|^2 bounds equivalent to | |n| - 1 | <= UNIT_TOLERANCE, so no sqrt on the hot path.
_UNIT_SQ_LO = (1.0 - UNIT_TOLERANCE) ** 2
_UNIT_SQ_HI = (1.0 + UNIT_TOLERANCE) ** 2
_MAX_ABS = MAX_ABS_FLOAT
_POSE = struct.Struct("<7d")
_QUAT = struct.Struct("<4d")


# ------------------------------------------------------------------------------- limits
@dataclass(frozen=True)
class Limits:
    """Decoder bounds, all checked before or while unpacking (never after building big objects).

    ``max_packet_bytes`` is compared with ``len(data)`` before anything is unpacked; the others
    become msgpack ``Unpacker`` limits (``max_bin_len``, ``max_array_len``, ``max_str_len``,
    ``max_map_len = 0``, ``max_ext_len = 0``) so an oversize element aborts the unpacking itself.
    """

    max_packet_bytes: int = 8192
    max_contacts: int = 64
    max_str_bytes: int = 256
    max_links: int = 32

    def __post_init__(self) -> None:
        for name in ("max_packet_bytes", "max_contacts", "max_str_bytes", "max_links"):
            value = getattr(self, name)
            if type(value) is not int or value < 1:
                raise ValueError(f"Limits.{name} must be a positive int, got {value!r}")
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
    the session layer can attribute the error and answer with a rate-limited ``Error``.
    """

    def __init__(self, code: ErrorCode, field: str, detail: str) -> None:
        super().__init__(f"{code.name}: {field or 'packet'}: {detail}")
        self.code = code
        self.field = field
        self.detail = detail
        self.type_id = 0
        self.major = 0
        self.session_id = 0
        self.token = 0
        self.seq = 0
        self.client_nonce = 0
        self.version_min: tuple[int, int] | None = None
        self.version_max: tuple[int, int] | None = None


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


# ------------------------------------------------------------------------ message classes
class Message:
    """Base of the generated message classes. Header attributes: ``session_id``, ``token``,
    ``minor`` (the sender's minor version), ``unknown_fields`` (trailing fields ignored)."""

    __slots__ = ("session_id", "token", "minor", "unknown_fields")
    SPEC: MessageSpec
    TYPE_ID: int
    _ATTRS: tuple[str, ...] = ()

    def __eq__(self, other: object) -> bool:
        if type(other) is not type(self):
            return NotImplemented
        for name in self._ATTRS + ("session_id", "token"):
            a, b = getattr(self, name), getattr(other, name)
            if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
                if not np.array_equal(np.asarray(a), np.asarray(b)):
                    return False
            elif a != b:
                return False
        return True

    __hash__ = None  # type: ignore[assignment]

    def __repr__(self) -> str:
        inner = ", ".join(f"{n}={getattr(self, n)!r}" for n in self._ATTRS)
        return f"{type(self).__name__}({inner}, session_id={self.session_id}, token={self.token})"


def _attr_names(spec: MessageSpec) -> tuple[str, ...]:
    if spec is CONTACT_UPDATE:
        # The packed bins are exposed as their columns.
        return ("seq", "env_time_s", "tool_pose", "keys") + tuple(c.name for c in CONTACT_COLUMNS) + (
            "tool_joint_position",)
    return tuple(f.name for f in spec.fields)


# Convenience defaults of the Python constructors (not wire defaults: every v1.0 field is
# required on the wire). They make a rigid-tool Hello a short call.
_PY_DEFAULTS: dict[str, dict[str, Any]] = {
    "Hello": {
        "version_min": (PROTOCOL_MAJOR, 0),
        "version_max": (PROTOCOL_MAJOR, PROTOCOL_MINOR),
        "units": "SI",
        "com_m": (0.0, 0.0, 0.0),
        "inertia_kg_m2": (0.0, 0.0, 0.0, 0.0, 0.0, 0.0),
        "axis": (1.0, 0.0, 0.0),
        "epsilon_m": 0.0,
        "env_rate_hz": 60.0,
        "links": (),
        "held_link": 0,
        "engine": "",
    },
    "Welcome": {"server_name": "hapticproxy"},
    "Reject": {"version_min": (PROTOCOL_MAJOR, 0), "version_max": (PROTOCOL_MAJOR, PROTOCOL_MINOR)},
    "ContactUpdate": {"tool_joint_position": np.zeros(0)},
    "ProxyState": {
        "joint_position": np.zeros(0),
        "joint_velocity": np.zeros(0),
        "joint_effort": np.zeros(0),
    },
    "Bye": {"reason": ""},
    "Error": {"field": "", "detail": "", "ref_type": 0, "ref_seq": 0},
}


def _make_class(spec: MessageSpec) -> type[Message]:
    attrs = _attr_names(spec)
    defaults = dict(_PY_DEFAULTS.get(spec.name, {}))
    for f in spec.fields:
        if f.default is not REQUIRED:
            defaults.setdefault(f.name, f.default)
    required = [a for a in attrs if a not in defaults]
    optional = [a for a in attrs if a in defaults]
    # Generated __init__ (like dataclasses do) keeps construction cheap on the decode path.
    params = ", ".join(["self", "*"] + required + [f"{a}=_d_{a}" for a in optional]
                       + ["session_id=0", "token=0", f"minor={PROTOCOL_MINOR}", "unknown_fields=0"])
    body = "\n".join(f"    self.{a} = {a}" for a in attrs + ("session_id", "token", "minor", "unknown_fields"))
    namespace = {f"_d_{a}": defaults[a] for a in optional}
    exec(f"def __init__({params}):\n{body}\n", namespace)  # noqa: S102 - source built from declarations
    doc = f"{spec.name} ({spec.direction}): {spec.doc}\n\nAttributes: " + ", ".join(attrs)
    cls = type(spec.name, (Message,), {
        "__slots__": attrs,
        "__init__": namespace["__init__"],
        "__doc__": doc,
        "SPEC": spec,
        "TYPE_ID": int(spec.type_id),
        "_ATTRS": attrs,
        "__module__": __name__,
    })
    return cls


Hello = _make_class(HELLO)
Welcome = _make_class(WELCOME)
Reject = _make_class(REJECT)
ContactUpdate = _make_class(CONTACT_UPDATE)
ProxyState = _make_class(PROXY_STATE)
Heartbeat = _make_class(HEARTBEAT)
Bye = _make_class(BYE)
Error = _make_class(ERROR)
ContactUpdate.n_contacts = property(lambda self: self.keys.shape[0])  # type: ignore[attr-defined]
ContactUpdate.n_contacts.__doc__ = "number of contacts n (rows of keys)"

MESSAGE_CLASSES: dict[int, type[Message]] = {
    c.TYPE_ID: c for c in (Hello, Welcome, Reject, ContactUpdate, ProxyState, Heartbeat, Bye, Error)
}


# ------------------------------------------------------------------ field validators (decode)
# Each validator takes the unpacked msgpack value and returns the Python value for the message
# attribute, or raises ProtocolError naming the field.

def _v_int(f: FieldSpec, limits: Limits):
    lo, hi = _INT_RANGES[f.type]
    if f.check == "pos":
        lo = max(lo, 1)
    name, enum = f.name, f.enum

    def check(v):
        if type(v) is not int:
            raise _bad(ErrorCode.WRONG_TYPE, name, f"expected an integer, got {type(v).__name__}")
        if not lo <= v <= hi:
            raise _bad(ErrorCode.OUT_OF_RANGE, name, f"{v} not in [{lo}, {hi}]")
        if enum is not None:
            try:
                return enum(v)
            except ValueError:
                raise _bad(ErrorCode.OUT_OF_RANGE, name, f"{v} is not a {enum.__name__}") from None
        return v

    return check


def _float_value(name: str, v: Any) -> float:
    t = type(v)
    if t is float:
        if -_MAX_ABS <= v <= _MAX_ABS:
            return v
        if v != v or v in (math.inf, -math.inf):
            raise _bad(ErrorCode.NON_FINITE, name, f"{v!r} is not finite")
        raise _bad(ErrorCode.OUT_OF_RANGE, name, f"|{v!r}| > {_MAX_ABS:g}")
    if t is int:  # some encoders (JavaScript) pack integral doubles as ints
        if -_MAX_ABS <= v <= _MAX_ABS:
            return float(v)
        raise _bad(ErrorCode.OUT_OF_RANGE, name, f"|{v}| > {_MAX_ABS:g}")
    raise _bad(ErrorCode.WRONG_TYPE, name, f"expected a number, got {t.__name__}")


def _v_float(f: FieldSpec, limits: Limits):
    name, chk = f.name, f.check

    def check(v):
        x = _float_value(name, v)
        if chk == "pos" and not x > 0.0:
            raise _bad(ErrorCode.OUT_OF_RANGE, name, f"{x!r} must be > 0")
        if chk == "nonneg" and not x >= 0.0:
            raise _bad(ErrorCode.OUT_OF_RANGE, name, f"{x!r} must be >= 0")
        return x

    return check


def _v_str(f: FieldSpec, limits: Limits):
    name = f.name
    max_bytes = limits.max_str_bytes

    def check(v):
        if type(v) is not str:
            raise _bad(ErrorCode.WRONG_TYPE, name, f"expected a string, got {type(v).__name__}")
        if len(v) * 4 > max_bytes and len(v.encode("utf-8", "surrogatepass")) > max_bytes:
            raise _bad(ErrorCode.BAD_SHAPE, name, f"longer than max_str_bytes {max_bytes} (UTF-8)")
        return v

    return check


def _float_list(name: str, v: Any, k: int) -> list[float]:
    if type(v) is not list:
        raise _bad(ErrorCode.WRONG_TYPE, name, f"expected an array of {k} numbers, got {type(v).__name__}")
    if len(v) != k:
        raise _bad(ErrorCode.BAD_SHAPE, name, f"expected {k} numbers, got {len(v)}")
    return [_float_value(f"{name}[{i}]", x) for i, x in enumerate(v)]


def _check_unit(name: str, xs) -> None:
    norm = math.sqrt(math.fsum(x * x for x in xs))
    if not abs(norm - 1.0) <= UNIT_TOLERANCE:
        raise _bad(ErrorCode.NOT_UNIT, name, f"norm {norm!r} is not 1 within {UNIT_TOLERANCE:g}")


def _check_inertia(name: str, xs) -> None:
    ixx, iyy, izz, ixy, ixz, iyz = xs
    if min(ixx, iyy, izz) < 0.0:
        raise _bad(ErrorCode.OUT_OF_RANGE, name, f"negative moment of inertia in {xs}")
    eig = np.linalg.eigvalsh(np.array([[ixx, ixy, ixz], [ixy, iyy, iyz], [ixz, iyz, izz]]))
    scale = max(1.0, abs(float(eig[-1])))
    if eig[0] < -1e-9 * scale:
        raise _bad(ErrorCode.OUT_OF_RANGE, name, f"inertia not positive semi-definite (eigenvalue {float(eig[0])!r})")
    # No triangle-inequality check: planar and 1-DOF tools legitimately send only Izz or zeros.


def _v_floats(f: FieldSpec, limits: Limits):
    name = f.name
    kind = f.type
    k = {"pose": 7, "inertia": 6}.get(kind) or int(kind[kind.index("[") + 1:-1])
    chk = f.check

    def check(v):
        xs = _float_list(name, v, k)
        if kind == "pose":
            _check_unit(name + ".quaternion", xs[3:])
        elif kind == "inertia":
            _check_inertia(name, xs)
        elif chk == "unit":
            _check_unit(name, xs)
        return tuple(xs)

    return check


def _v_version(f: FieldSpec, limits: Limits):
    name = f.name

    def check(v):
        if type(v) is not list or len(v) != 2:
            raise _bad(ErrorCode.BAD_SHAPE if type(v) is list else ErrorCode.WRONG_TYPE, name,
                       "expected [major, minor]")
        for x in v:
            if type(x) is not int or not 0 <= x <= 0xFFFF:
                raise _bad(ErrorCode.OUT_OF_RANGE, name, f"version parts must be u16, got {v!r}")
        return (v[0], v[1])

    return check


def _v_bin_f64(f: FieldSpec, limits: Limits):
    name = f.name
    kind = f.type
    fixed = None if kind.endswith("[J]") else int(kind[kind.index("[") + 1:-1])
    max_len = limits.max_links
    is_pose = kind == "bin f64[7]"

    def check(v):
        if type(v) is not bytes:
            raise _bad(ErrorCode.WRONG_TYPE, name, f"expected bin, got {type(v).__name__}")
        nb = len(v)
        if nb % 8:
            raise _bad(ErrorCode.BAD_SHAPE, name, f"{nb} bytes is not a whole number of float64")
        k = nb >> 3
        if fixed is not None and k != fixed:
            raise _bad(ErrorCode.BAD_SHAPE, name, f"expected {fixed} float64, got {k}")
        if fixed is None and k > max_len:
            raise _bad(ErrorCode.BAD_SHAPE, name, f"{k} values > max_links {max_len}")
        a = _ndarray((k,), _F8, v)
        if k and not _vdot(a, a) <= _MAX_ABS_SQ:  # sufficient test first, exact one on failure
            _check_float_array(name, a)
        if is_pose:
            qw, qx, qy, qz = _QUAT.unpack_from(v, 24)
            qn = qw * qw + qx * qx + qy * qy + qz * qz
            if not _UNIT_SQ_LO <= qn <= _UNIT_SQ_HI:
                raise _bad(ErrorCode.NOT_UNIT, name + ".quaternion",
                           f"|q| = {math.sqrt(qn)!r} is not 1 within {UNIT_TOLERANCE:g}")
        return a

    return check


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


_unpackb = msgpack.unpackb
_ndarray = np.ndarray
_frombuffer = np.frombuffer
_KEY_DT = np.dtype((_I8, (KEY_INTS,)))
_ONES3 = np.ones(3)
_ONES3.flags.writeable = False
_new = object.__new__
_minimum = np.minimum.reduce
_maximum = np.maximum.reduce
_vdot = np.vdot
_dot = np.dot
_MAX_ABS_SQ = MAX_ABS_FLOAT * MAX_ABS_FLOAT
# tol on |n|^2 - 1, the tighter of the two sides of the |n| window, squared.
_UNIT_SQ_DEV2 = min(1.0 - (1.0 - UNIT_TOLERANCE) ** 2, (1.0 + UNIT_TOLERANCE) ** 2 - 1.0) ** 2


def _v_links(f: FieldSpec, limits: Limits):
    name = f.name
    max_links = limits.max_links
    link_checks = [(lf.name, _validator(lf, limits)) for lf in LINK_FIELDS]
    nlf = len(LINK_FIELDS)

    def check(v):
        if type(v) is not list:
            raise _bad(ErrorCode.WRONG_TYPE, name, f"expected an array of links, got {type(v).__name__}")
        if len(v) > max_links:
            raise _bad(ErrorCode.BAD_SHAPE, name, f"{len(v)} links > max_links {max_links}")
        out = []
        for i, rec in enumerate(v):
            if type(rec) is not list:
                raise _bad(ErrorCode.WRONG_TYPE, f"{name}[{i}]", "expected a link record array")
            if len(rec) < nlf:
                raise _bad(ErrorCode.MISSING_FIELD, f"{name}[{i}].{LINK_FIELDS[len(rec)].name}", "missing")
            link = {}
            for j, (lname, lcheck) in enumerate(link_checks):
                try:
                    link[lname] = lcheck(rec[j])
                except ProtocolError as exc:
                    raise _bad(exc.code, f"{name}[{i}].{exc.field}", exc.detail) from None
            out.append(link)
        _check_tree(name, out)
        return tuple(out)

    return check


def _check_tree(name: str, links: list[dict]) -> None:
    for i, link in enumerate(links):
        parent, jt = link["parent"], link["joint_type"]
        if i == 0:
            if parent != -1 or jt != JointType.ROOT:
                raise _bad(ErrorCode.BAD_TREE, f"{name}[0]", "link 0 must be the root: parent -1, joint_type 0")
        else:
            if not 0 <= parent < i:
                raise _bad(ErrorCode.BAD_TREE, f"{name}[{i}].parent",
                           f"parent {parent} must be an earlier link (0 <= parent < {i})")
            if jt == JointType.ROOT:
                raise _bad(ErrorCode.BAD_TREE, f"{name}[{i}].joint_type", "only link 0 may be the root")


def _check_hello(msg) -> None:
    """Cross-field rules of Hello that no single field can check."""
    kind = msg.tool_kind
    links = msg.links
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


_POST_CHECKS = {"Hello": _check_hello}


def _validator(f: FieldSpec, limits: Limits):
    t = f.type
    if t in _INT_RANGES:
        return _v_int(f, limits)
    if t == "f64":
        return _v_float(f, limits)
    if t == "str":
        return _v_str(f, limits)
    if t in ("pose", "inertia") or t.startswith("f64["):
        return _v_floats(f, limits)
    if t == "version":
        return _v_version(f, limits)
    if t.startswith("bin f64[") and t != "bin f64[n*8]":
        return _v_bin_f64(f, limits)
    if t == "links":
        return _v_links(f, limits)
    raise ValueError(f"no validator for wire type {t!r} ({f.name})")


# ------------------------------------------------------------------ field encoders (encode)
def _encoder(f: FieldSpec):
    """Python attribute value -> msgpack-ready value (types coerced; shapes checked by the
    validator that runs on the result)."""
    t = f.type
    name = f.name
    if t in _INT_RANGES:
        def enc(v):
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)):
                raise ValueError(f"{name}: expected an integer, got {v!r}")
            return int(v)
        return enc
    if t == "f64":
        return float
    if t == "str":
        def enc_s(v):
            if not isinstance(v, str):
                raise ValueError(f"{name}: expected a string, got {v!r}")
            return v
        return enc_s
    if t in ("pose", "inertia", "version") or t.startswith("f64["):
        conv = int if t == "version" else float
        return lambda v: [conv(x) for x in np.asarray(v).ravel().tolist()]
    if t.startswith("bin f64["):
        def enc_bin(v):
            if type(v) is np.ndarray and v.dtype == _F8:
                return v.tobytes()  # C order, whatever the strides
            return np.asarray(v, dtype=_F8).tobytes()
        return enc_bin
    if t == "links":
        link_enc = [_encoder(lf) for lf in LINK_FIELDS]

        def enc_links(v):
            out = []
            for link in v:
                if isinstance(link, dict):
                    rec = [e(link[lf.name]) for e, lf in zip(link_enc, LINK_FIELDS)]
                else:
                    rec = [e(x) for e, x in zip(link_enc, link)]
                out.append(rec)
            return out
        return enc_links
    raise ValueError(f"no encoder for wire type {t!r} ({name})")


# ------------------------------------------------------------------------------- the codec
class _DecodeScratch(threading.local):
    """One thread's ContactUpdate decode plans (``plans[n]``, see ``Codec._cu_plan``) and the
    (2, max_contacts) unit-normal scratch they view."""

    def __init__(self, max_contacts: int) -> None:
        self.plans: list[tuple | None] = [None] * (max_contacts + 1)
        self.unit = np.ones((2, max_contacts))


_EMPTY = np.zeros(0)
_SERVER_STATES = frozenset(int(v) for v in ServerState)
_EMPTY.flags.writeable = False


class Codec:
    """Encoder/decoder with its :class:`Limits` and :class:`CodecCounters`.

    One per endpoint (not thread-safe: counters and the packer are per instance). ``specs``
    defaults to the v1 declarations; tests pass modified declarations to exercise versioning.
    """

    def __init__(self, limits: Limits | None = None, *, specs: tuple[MessageSpec, ...] = MESSAGES,
                 minor: int = PROTOCOL_MINOR) -> None:
        self.limits = limits or Limits()
        self.counters = CodecCounters()
        self.minor = minor
        self._packer = msgpack.Packer(use_bin_type=True, autoreset=True)
        self._pack = self._packer.pack
        lim = self.limits
        self._specs = {int(s.type_id): s for s in specs}
        self._classes = {}
        self._decoders = {}
        self._encoders = {}
        for tid, spec in self._specs.items():
            cls = MESSAGE_CLASSES[tid]
            if tuple(f.name for f in spec.fields) != tuple(f.name for f in cls.SPEC.fields):
                # A test declaration with extra fields: a class for it.
                cls = _make_class(spec)
            self._classes[tid] = cls
            if spec is CONTACT_UPDATE:
                self._decoders[tid] = self._decode_contact_update
            elif spec is PROXY_STATE:
                self._decoders[tid] = self._decode_proxy_state
            elif spec.type_id in (MessageType.CONTACT_UPDATE, MessageType.PROXY_STATE):
                raise ValueError(f"a modified {spec.name} declaration needs its own decoder")
            else:
                self._decoders[tid] = self._generic_decoder(spec, cls)
            self._encoders[tid] = [(f.name, _encoder(f), _validator(f, lim)) for f in spec.fields] \
                if spec.type_id != MessageType.CONTACT_UPDATE else None
        self._empty_f = np.zeros((0, 3))
        self._empty_f.flags.writeable = False
        self._empty_1 = np.zeros(0)
        self._empty_1.flags.writeable = False
        self._empty_k = np.zeros((0, 3), dtype=np.int64)
        self._empty_k.flags.writeable = False
        lim = self.limits
        self._max_packet_bytes = lim.max_packet_bytes
        self._max_bin_len = lim.max_bin_bytes
        self._max_str_len = lim.max_str_bytes
        self._max_array_len = lim.max_array_len
        self._max_contacts = lim.max_contacts
        self._max_links = lim.max_links
        self._proxy_cls = ProxyState
        # Per-thread ContactUpdate decode plans, one per contact count n, built on first use
        # (see _cu_plan; a Struct per n is O(n) to compile, so an eager table would cost
        # O(max_contacts^2) at construction). Per thread because a plan holds a scratch row
        # the validation writes: two threads sharing one codec (say the module-level one)
        # must never validate against each other's numbers.
        self._cu_local = _DecodeScratch(lim.max_contacts)
        # The hand-written ContactUpdate decoder matches the v1 declaration only.
        self._cu_fast = self._specs.get(int(MessageType.CONTACT_UPDATE)) is CONTACT_UPDATE

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
        if len(data) > self._max_packet_bytes:
            raise _bad(ErrorCode.OVERSIZE, "", f"{len(data)} bytes > max_packet_bytes {self._max_packet_bytes}")
        try:
            # Explicit keywords: a **kwargs expansion costs more than the unpacking itself.
            obj = _unpackb(data, max_bin_len=self._max_bin_len, max_str_len=self._max_str_len,
                           max_array_len=self._max_array_len, max_map_len=0, max_ext_len=0)
        except Exception as exc:  # noqa: BLE001 - any msgpack failure, incl. limits and bad UTF-8
            raise _bad(ErrorCode.MALFORMED, "", f"{type(exc).__name__}: {exc}") from None
        if type(obj) is not list or len(obj) < HEADER_LEN:
            raise _bad(ErrorCode.BAD_HEADER, "", "packet must be an array of at least 5 header integers")
        major, minor, type_id, session_id, token = obj[0], obj[1], obj[2], obj[3], obj[4]
        if not (type(major) is int and type(minor) is int and type(type_id) is int
                and type(session_id) is int and type(token) is int
                and 0 <= major <= 0xFFFF and 0 <= minor <= 0xFFFF and 0 <= type_id <= 0xFF
                and 0 <= session_id <= 0xFFFF_FFFF and 0 <= token <= _U64_MAX):
            raise _bad(ErrorCode.BAD_HEADER, "", "header must be [major u16, minor u16, type_id u8, session_id u32, token u64]")
        try:
            if type_id == 4 and major == 1 and self._cu_fast:
                msg = self._decode_contact_update(obj)
                msg.minor = minor
                msg.session_id = session_id
                msg.token = token
                self.counters.decoded += 1
                return msg
            else:
                decoder = self._decoders.get(type_id)
                if decoder is None:
                    raise _bad(ErrorCode.UNKNOWN_TYPE, "type_id", f"unknown message type id {type_id}")
                if major != PROTOCOL_MAJOR:
                    self._foreign_major(obj, major, type_id)
                if type_id == MessageType.WELCOME and not (session_id and token):
                    raise _bad(ErrorCode.BAD_HEADER, "session_id", "Welcome must carry a non-zero session_id and token")
                msg = decoder(obj)
        except ProtocolError as exc:
            exc.type_id, exc.major, exc.session_id, exc.token = type_id, major, session_id, token
            first = obj[HEADER_LEN] if len(obj) > HEADER_LEN else None
            if type(first) is int and 0 <= first <= _U64_MAX:
                if exc.seq == 0 and type_id in (MessageType.CONTACT_UPDATE, MessageType.PROXY_STATE, MessageType.HEARTBEAT):
                    exc.seq = first
                elif exc.client_nonce == 0 and type_id == MessageType.HELLO:
                    exc.client_nonce = first  # lets the server answer a bad Hello with Reject
            raise
        msg.minor = minor
        msg.session_id = session_id
        msg.token = token
        self.counters.decoded += 1
        return msg

    def _foreign_major(self, obj: list, major: int, type_id: int) -> None:
        if type_id == MessageType.REJECT:
            return  # Reject's layout is frozen: readable whatever its major.
        err = _bad(ErrorCode.UNKNOWN_MAJOR, "major", f"major version {major} not supported (this side speaks {PROTOCOL_MAJOR})")
        if type_id == MessageType.HELLO:
            # Hello's first three fields are frozen so the server can answer with Reject.
            f = obj[HEADER_LEN:HEADER_LEN + 3]
            if len(f) == 3 and type(f[0]) is int and 0 <= f[0] <= _U64_MAX:
                err.client_nonce = f[0]
                try:
                    err.version_min = _v_version(HELLO.fields[1], self.limits)(f[1])
                    err.version_max = _v_version(HELLO.fields[2], self.limits)(f[2])
                except ProtocolError:
                    pass
        raise err

    def _fields(self, obj: list, spec: MessageSpec) -> tuple[list, int]:
        """The message's field values (defaults filled in) and the number of unknown trailing ones."""
        values = obj[HEADER_LEN:]
        n = len(values)
        known = len(spec.fields)
        if n < known:
            missing = spec.fields[n]
            if missing.default is REQUIRED:
                raise _bad(ErrorCode.MISSING_FIELD, missing.name, f"{spec.name} needs {known} fields, got {n}")
            values = values + [f.default for f in spec.fields[n:]]
            return values, 0
        extra = n - known
        if extra:
            self.counters.unknown_trailing_fields += extra
            self.counters.packets_with_unknown_fields += 1
        return values, extra

    def _generic_decoder(self, spec: MessageSpec, cls: type[Message]):
        checks = tuple((f, _validator(f, self.limits)) for f in spec.fields)
        names = tuple(f.name for f in spec.fields)
        fields = self._fields
        post = _POST_CHECKS.get(spec.name)

        def decode(obj: list) -> Message:
            values, extra = fields(obj, spec)
            kwargs = {}
            for (f, check), v in zip(checks, values):
                if f.since_minor and v is f.default:
                    kwargs[f.name] = v  # defaults are trusted (declared here)
                else:
                    kwargs[f.name] = check(v)
            msg = cls(**kwargs)
            msg.unknown_fields = extra
            if post is not None:
                post(msg)
            return msg

        del names
        return decode

    def _decode_contact_update(self, obj: list) -> Message:
        # Hand-specialised for speed (the server decodes one per environment step); field
        # order is the declaration's (messages.CONTACT_UPDATE), checked at Codec construction.
        nf = len(obj) - HEADER_LEN
        joints = self._empty_1
        if nf != 6:
            if nf < 6:
                raise _bad(ErrorCode.MISSING_FIELD, CONTACT_UPDATE.fields[nf].name, f"ContactUpdate needs 6 fields, got {nf}")
            # 1.1: tool_joint_position (a linkage engine's joint positions), then any later fields
            jb = obj[11]
            if type(jb) is not bytes:
                raise _bad(ErrorCode.WRONG_TYPE, "tool_joint_position", f"expected bin, got {type(jb).__name__}")
            if len(jb) % 8 or len(jb) > 8 * self._max_links:
                raise _bad(ErrorCode.BAD_SHAPE, "tool_joint_position",
                           f"expected a multiple of 8 bytes, at most max_links float64, got {len(jb)} bytes")
            if jb:
                joints = _frombuffer(jb)
                if not _vdot(joints, joints) <= _MAX_ABS_SQ:
                    _check_float_array("tool_joint_position", joints)
            extra = nf - 7
            if extra:
                self.counters.unknown_trailing_fields += extra
                self.counters.packets_with_unknown_fields += 1
        else:
            extra = 0
        seq, t, pose_b, n, kb, db = obj[5:11]
        if type(seq) is not int or not 0 < seq <= _U64_MAX:
            if type(seq) is not int:
                raise _bad(ErrorCode.WRONG_TYPE, "seq", f"expected an integer, got {type(seq).__name__}")
            raise _bad(ErrorCode.OUT_OF_RANGE, "seq", f"{seq} not in [1, 2^64-1]")
        if type(t) is not float or not -_MAX_ABS <= t <= _MAX_ABS:
            t = _float_value("env_time_s", t)
        if type(pose_b) is not bytes or len(pose_b) != 56:
            if type(pose_b) is not bytes:
                raise _bad(ErrorCode.WRONG_TYPE, "tool_pose", f"expected bin, got {type(pose_b).__name__}")
            raise _bad(ErrorCode.BAD_SHAPE, "tool_pose", f"expected 56 bytes (7 float64), got {len(pose_b)}")
        px, py, pz, qw, qx, qy, qz = _POSE.unpack(pose_b)
        qn = qw * qw + qx * qx + qy * qy + qz * qz
        if not (-_MAX_ABS <= px <= _MAX_ABS and -_MAX_ABS <= py <= _MAX_ABS and -_MAX_ABS <= pz <= _MAX_ABS
                and _UNIT_SQ_LO <= qn <= _UNIT_SQ_HI):
            _check_float_array("tool_pose", _ndarray((7,), _F8, pose_b))
            raise _bad(ErrorCode.NOT_UNIT, "tool_pose.quaternion", f"|q| = {math.sqrt(qn)!r} is not 1 within {UNIT_TOLERANCE:g}")
        if type(n) is not int or not 0 <= n <= self._max_contacts:
            if type(n) is not int:
                raise _bad(ErrorCode.WRONG_TYPE, "contact_count", f"expected an integer, got {type(n).__name__}")
            if n < 0:
                raise _bad(ErrorCode.OUT_OF_RANGE, "contact_count", f"{n} < 0")
            raise _bad(ErrorCode.TOO_MANY_CONTACTS, "contact_count", f"{n} > max_contacts {self._max_contacts}")
        if type(kb) is not bytes or len(kb) != 24 * n:
            if type(kb) is not bytes:
                raise _bad(ErrorCode.WRONG_TYPE, "contact_keys", f"expected bin, got {type(kb).__name__}")
            raise _bad(ErrorCode.BAD_SHAPE, "contact_keys", f"expected {24 * n} bytes for {n} contacts, got {len(kb)}")
        if type(db) is not bytes:
            raise _bad(ErrorCode.WRONG_TYPE, "contact_data", f"expected bin, got {type(db).__name__}")
        nd = len(db)
        if nd != 64 * n:
            # A later minor may append whole column blocks (n float64 each) after the known ones.
            if n == 0 or nd < 64 * n or nd % (8 * n):
                raise _bad(ErrorCode.BAD_SHAPE, "contact_data",
                           f"expected {64 * n} bytes ({CONTACT_FLOATS} float64 per contact) for {n} contacts, got {nd}")
            more = nd // (8 * n) - CONTACT_FLOATS
            if not extra:
                self.counters.packets_with_unknown_fields += 1
            extra += more
            self.counters.unknown_trailing_fields += more
        msg = _new(ContactUpdate)
        msg.seq = seq
        msg.env_time_s = t
        msg.tool_pose = _frombuffer(pose_b)
        msg.tool_joint_position = joints
        msg.unknown_fields = extra
        if n == 0:
            msg.keys = self._empty_k
            msg.position_m = self._empty_f
            msg.normal = self._empty_f
            msg.separation_m = self._empty_1
            msg.v_constr_m_per_s = self._empty_1
            return msg
        plan = self._cu_local.plans[n] or self._cu_plan(n)
        key_struct, col_dt, pn_dt, scratch, sq, unit_margin = plan
        # Read-only views of the packet's bytes, shaped by the dtype (a per-n subarray dtype:
        # frombuffer yields (blocks, n) or (2, n, 3) directly, with no reshape call). Rows of
        # cols: 0-5 the position and normal blocks (each n x 3, row-major), 6 separation,
        # 7 v_constr, then any column blocks a later minor appended.
        cols = _frombuffer(db, col_dt)
        f = cols if nd == 64 * n else cols[:CONTACT_FLOATS]
        # Finite and bounded, all floats in one BLAS call: sum of squares <= MAX_ABS^2 implies
        # every |x| <= MAX_ABS (NaN fails the comparison; vdot, unlike ndarray.dot, raises no
        # FP warning on overflow). Only when this sufficient test fails does the exact
        # per-element check run (and raise).
        if not _vdot(f, f) <= _MAX_ABS_SQ:
            _check_float_array("contact_data", f.reshape(-1))
        pn = _frombuffer(db, pn_dt, 2)
        normal = pn[1]
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
        msg.keys = _frombuffer(kb, _KEY_DT)
        msg.position_m = pn[0]
        msg.normal = normal
        msg.separation_m = cols[6]
        msg.v_constr_m_per_s = cols[7]
        return msg

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

    def _decode_proxy_state(self, obj: list) -> Message:
        # Hand-specialised like ContactUpdate (field order of messages.PROXY_STATE): the six
        # float bins are validated as one array, then handed out as views of it.
        nf = len(obj) - HEADER_LEN
        if nf < 9:
            raise _bad(ErrorCode.MISSING_FIELD, PROXY_STATE.fields[nf].name, f"ProxyState needs 9 fields, got {nf}")
        # 1.2: server_state, then any later fields
        state = 0
        if nf > 9:
            state = obj[14]
            if type(state) is not int:
                raise _bad(ErrorCode.WRONG_TYPE, "server_state", f"expected an integer, got {type(state).__name__}")
            if state not in _SERVER_STATES:
                raise _bad(ErrorCode.OUT_OF_RANGE, "server_state", f"{state} is not a ServerState")
        extra = nf - 10 if nf > 10 else 0
        if extra:
            self.counters.unknown_trailing_fields += extra
            self.counters.packets_with_unknown_fields += 1
        seq, ack, t, pose_b, tw_b, wr_b, jq_b, jv_b, je_b = obj[5:14]
        for name, v, lo in (("seq", seq, 1), ("ack_seq", ack, 0)):
            if type(v) is not int:
                raise _bad(ErrorCode.WRONG_TYPE, name, f"expected an integer, got {type(v).__name__}")
            if not lo <= v <= _U64_MAX:
                raise _bad(ErrorCode.OUT_OF_RANGE, name, f"{v} not in [{lo}, 2^64-1]")
        if type(t) is not float or not -_MAX_ABS <= t <= _MAX_ABS:
            t = _float_value("server_time_s", t)
        for name, v, nb in (("proxy_pose", pose_b, 56), ("proxy_twist", tw_b, 48), ("wrench", wr_b, 48)):
            if type(v) is not bytes:
                raise _bad(ErrorCode.WRONG_TYPE, name, f"expected bin, got {type(v).__name__}")
            if len(v) != nb:
                raise _bad(ErrorCode.BAD_SHAPE, name, f"expected {nb // 8} float64, got {len(v)} bytes")
        nj = len(jq_b) if type(jq_b) is bytes else -1
        for name, v in (("joint_position", jq_b), ("joint_velocity", jv_b), ("joint_effort", je_b)):
            if type(v) is not bytes:
                raise _bad(ErrorCode.WRONG_TYPE, name, f"expected bin, got {type(v).__name__}")
            if len(v) != nj or nj % 8 or nj > 8 * self._max_links:
                raise _bad(ErrorCode.BAD_SHAPE, name,
                           f"joint arrays must hold the same number (<= max_links) of float64, got {len(v)} bytes")
        allb = b"".join((pose_b, tw_b, wr_b, jq_b, jv_b, je_b))
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
        msg = _new(self._proxy_cls)
        msg.seq = seq
        msg.ack_seq = ack
        msg.server_time_s = t
        msg.proxy_pose = a[0:7]
        msg.proxy_twist = a[7:13]
        msg.wrench = a[13:19]
        msg.joint_position = a[19:19 + j]
        msg.joint_velocity = a[19 + j:19 + 2 * j]
        msg.joint_effort = a[19 + 2 * j:]
        msg.server_state = state
        msg.unknown_fields = extra
        return msg

    # ------------------------------------------------------------------------ encoding
    def encode(self, msg: Message) -> bytes:
        """Encode any message (header from ``msg.session_id`` / ``msg.token``). Values are
        validated with the decoder's own rules; a bad value raises ``ValueError`` naming it."""
        tid = msg.TYPE_ID
        if tid == MessageType.CONTACT_UPDATE:
            return self.encode_contact_update(
                msg.session_id, msg.token, msg.seq, msg.env_time_s, msg.tool_pose, msg.keys,
                msg.position_m, msg.normal, msg.separation_m, msg.v_constr_m_per_s, check=True,
                tool_joint_position=msg.tool_joint_position)
        if tid == MessageType.PROXY_STATE:
            return self.encode_proxy_state(
                msg.session_id, msg.token, msg.seq, msg.ack_seq, msg.server_time_s, msg.proxy_pose, msg.proxy_twist,
                msg.wrench, msg.joint_position, msg.joint_velocity, msg.joint_effort, msg.server_state)
        encoders = self._encoders.get(tid)
        if encoders is None:
            raise ValueError(f"message type {type(msg).__name__} not declared in this codec")
        out = [PROTOCOL_MAJOR, self.minor, tid, _u(msg.session_id, "session_id", 0xFFFF_FFFF), _u(msg.token, "token", _U64_MAX)]
        for name, enc, check in encoders:
            value = enc(getattr(msg, name))
            check(value)  # raises ProtocolError (a ValueError) naming the field
            out.append(value)
        self.counters.encoded += 1
        return self._pack(out)

    def encode_proxy_state(self, session_id: int, token: int, seq: int, ack_seq: int, server_time_s: float,
                           proxy_pose, proxy_twist, wrench, joint_position=_EMPTY, joint_velocity=_EMPTY,
                           joint_effort=_EMPTY, server_state: int = 0) -> bytes:
        """Encode a ProxyState from arrays (the server's acknowledgement). Every value rule of the
        decoder is applied (one vectorised test); ``ValueError`` names the bad field."""
        bins = []
        for name, v, k in (("proxy_pose", proxy_pose, 7), ("proxy_twist", proxy_twist, 6), ("wrench", wrench, 6),
                           ("joint_position", joint_position, -1), ("joint_velocity", joint_velocity, -1),
                           ("joint_effort", joint_effort, -1)):
            if type(v) is not np.ndarray or v.dtype != _F8:
                v = np.asarray(v, dtype=_F8)
            if v.ndim != 1 or (k > 0 and v.shape[0] != k):
                raise ValueError(f"{name} must be {k if k > 0 else 'J'} float64 values, got shape {v.shape}")
            bins.append(v.tobytes())
        packet = self._pack([PROTOCOL_MAJOR, self.minor, 5, _u(session_id, "session_id", 0xFFFF_FFFF),
                             _u(token, "token", _U64_MAX), _u(seq, "seq", _U64_MAX), _u(ack_seq, "ack_seq", _U64_MAX),
                             float(server_time_s)] + bins + ([int(server_state)] if self.minor >= 2 else []))
        # The decoder's value rules, on all six arrays at once.
        allb = b"".join(bins)
        a = _ndarray((len(allb) >> 3,), _F8, allb)
        if not _vdot(a, a) <= _MAX_ABS_SQ:
            _check_float_array("ProxyState arrays", a)
        qw, qx, qy, qz = _QUAT.unpack_from(allb, 24)
        if not _UNIT_SQ_LO <= qw * qw + qx * qx + qy * qy + qz * qz <= _UNIT_SQ_HI:
            raise ValueError("proxy_pose: quaternion is not unit within 1e-6")
        if not len(bins[3]) == len(bins[4]) == len(bins[5]) <= 8 * self._max_links:
            raise ValueError("joint_position, joint_velocity, joint_effort must have the same length <= max_links")
        if not -_MAX_ABS <= float(server_time_s) <= _MAX_ABS:
            raise ValueError(f"server_time_s must be finite, got {server_time_s!r}")
        if seq < 1:
            raise ValueError("seq must be >= 1")
        if int(server_state) not in _SERVER_STATES:
            raise ValueError(f"server_state must be a ServerState, got {server_state!r}")
        self.counters.encoded += 1
        return packet

    def encode_contact_update(self, session_id: int, token: int, seq: int, env_time_s: float, tool_pose,
                              keys: np.ndarray, position_m: np.ndarray, normal: np.ndarray,
                              separation_m: np.ndarray, v_constr_m_per_s: np.ndarray, *, check: bool = False,
                              tool_joint_position=None) -> bytes:
        """Encode a ContactUpdate straight from arrays (the environment client's hot path).

        ``keys`` int64 (n, 3); ``position_m``, ``normal`` float64 (n, 3); ``separation_m``,
        ``v_constr_m_per_s`` float64 (n,); ``tool_pose`` 7 floats (x y z qw qx qy qz);
        ``tool_joint_position`` (1.1, linkages): the engine's joint positions, J floats, appended
        only when J > 0 (so a rigid tool's packet is the 1.0 layout). Shapes and dtypes are always
        checked (``ValueError`` naming the array). ``check=True`` also applies every value rule of
        the decoder (finite, unit normals, unique keys), at about the decoder's cost; without it a
        bad value is caught by the receiver instead.
        """
        n = keys.shape[0] if isinstance(keys, np.ndarray) else -1
        if n < 0 or keys.shape != (n, 3) or keys.dtype != _I8:
            raise ValueError(f"keys must be an int64 array of shape (n, 3), got {_describe(keys)}")
        if n > self.limits.max_contacts:
            raise ValueError(f"keys: {n} contacts > max_contacts {self.limits.max_contacts}")
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
        if tool_joint_position is not None and len(tool_joint_position):
            jq = np.asarray(tool_joint_position, dtype=_F8)
            if jq.ndim != 1 or jq.shape[0] > self.limits.max_links:
                raise ValueError(f"tool_joint_position must be at most {self.limits.max_links} float64 values, "
                                 f"got shape {jq.shape}")
            fields.append(jq.tobytes())
        packet = self._pack(fields)
        if check:
            saved = self.counters
            self.counters = CodecCounters()  # a self-check must not count as traffic
            try:
                self._decode(packet)
            except ProtocolError as exc:
                raise ValueError(f"ContactUpdate.{exc.field}: {exc.detail}") from None
            finally:
                self.counters = saved
        self.counters.encoded += 1
        return packet


def _u(v: Any, name: str, hi: int) -> int:
    if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or not 0 <= int(v) <= hi:
        raise ValueError(f"{name} must be an integer in [0, {hi}], got {v!r}")
    return int(v)


def _describe(a: Any) -> str:
    if isinstance(a, np.ndarray):
        return f"{a.dtype} array of shape {a.shape}"
    return type(a).__name__


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
