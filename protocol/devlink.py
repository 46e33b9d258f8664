"""The remote-device link (``hapticproxy device`` <-> the ``remote`` device driver), declared once.

Two fixed-layout little-endian datagrams, one per device tick and one per haptic step: STATE
(device -> server) and COMMAND (server -> device). Each is declared here once, as a tuple of
:class:`Field` s; the declaration generates the ``struct`` layouts both sides pack and unpack with
(:class:`Datagram`), and :mod:`hapticproxy.protocol.spec` renders SPEC.md's "Remote-device link"
tables from it. The rules (newest wins, keys, the device's watchdog, link loss, restarts, the
engagement counter) are SPEC.md's appendix; :mod:`hapticproxy.server.devices.remote` implements
both sides and :mod:`hapticproxy.protocol.device_conformance` checks either side of a link.

Why a fixed binary layout rather than msgpack like the environment protocol: the link runs at the
device's rate (1 kHz and up) between two programs that never negotiate anything, so every byte
has one place; a device's own firmware can fill a C struct, and a datagram is validated by its
size, its magic and two bytes before any field is read.

Hot-path use: a sender keeps one buffer per datagram type, writes the constant prefix once
(:meth:`Datagram.new_buffer`), then per datagram packs the variable header with
``datagram.body.pack_into(buf, PREFIX_BYTES, ...)`` (arguments in :attr:`Datagram.body_names`
order) and the float block through a numpy view (:meth:`Datagram.floats`). A receiver unpacks
``datagram.header.unpack_from(buf)`` (:attr:`Datagram.header_names` order) after checking the
size; :meth:`Datagram.pack` / :meth:`Datagram.unpack` are the allocating conveniences for tools
and tests.
"""
from __future__ import annotations

import struct
import threading
import time
from collections import namedtuple
from dataclasses import dataclass
from enum import IntEnum

import numpy as np

__all__ = [
    "COMMAND", "DATAGRAMS", "DEFAULT_LINK_TIMEOUT_S", "DEFAULT_PORT", "DEFAULT_WATCHDOG_S", "Datagram",
    "DeviceFault", "DeviceKind", "F_ARMED", "F_ENABLE", "Field", "MAGIC", "MAX_DATAGRAM_BYTES", "MAX_DRAIN",
    "PREFIX_BYTES", "ROW_COLUMNS", "ROW_FLOATS", "ROW_FLOATS_V1", "STATE", "STATE_V1", "VERSION", "WRENCH_FLOATS",
    "DatagramType", "new_session", "state_datagram_for", "unpack_state",
]

MAGIC = b"HPDV"
#: The newest layout version (the prefix's version byte). Each datagram type has its own: STATE 2
#: (the row with the device's inputs appended), COMMAND 1. A receiver takes the (version, size)
#: pairs it knows and drops anything else (there is no negotiation: a mismatch fails closed, never
#: guesses): a server takes STATE 2 and the STATE 1 of an older device program (the first 20
#: floats of the row, the inputs then unknown: NaN); a device program sends STATE 1 when its
#: device has no inputs (no buttons, no gripper), so a server of the version-1 layout still takes
#: it (:func:`state_datagram_for`).
VERSION = 2
#: The constant prefix of every datagram: magic (4 bytes), version (u8), type (u8).
PREFIX_BYTES = 6


class DatagramType(IntEnum):
    STATE = 1
    COMMAND = 2


class DeviceKind(IntEnum):
    """STATE.kind: what the device can move (the names are the ``[device] kind`` values)."""

    ONE_DOF = 0   # "1dof": translation along its axis
    PLANAR = 1    # "planar": translation in world x-y, rotation about +z
    SPATIAL = 2   # "spatial": 6 DOF


KIND_NAMES: dict[DeviceKind, str] = {DeviceKind.ONE_DOF: "1dof", DeviceKind.PLANAR: "planar",
                                     DeviceKind.SPATIAL: "spatial"}
KINDS_BY_NAME: dict[str, DeviceKind] = {v: k for k, v in KIND_NAMES.items()}


class DeviceFault(IntEnum):
    """STATE.fault: the device's latched fault (the device drivers' status codes, the same values)."""

    OK = 0
    NONFINITE_COMMAND = 1
    WATCHDOG = 2
    DISABLED = 3   # never sent as a fault: an unarmed device reports 0 with the armed flag clear
    LINK = 4       # the server driver's own: no state within its link timeout
    HARDWARE = 5
    FROZEN = 6     # the server's own: the position stopped changing while force was commanded


FAULT_DOCS: dict[DeviceFault, str] = {
    DeviceFault.OK: "no fault",
    DeviceFault.NONFINITE_COMMAND: "a command carried a non-finite wrench: refused, output zero, latched for its key",
    DeviceFault.WATCHDOG: "armed and no command accepted for watchdog_s: output zero, latched for its key",
    DeviceFault.DISABLED: "(a driver's status, not a fault: never sent in STATE)",
    DeviceFault.LINK: "server side only: no STATE within link_timeout_s, or the device restarted",
    DeviceFault.HARDWARE: "the device's own hardware fault (or, server side, a STATE of another kind)",
    DeviceFault.FROZEN: "server side only: the position stayed bit-identical for safety.frozen_s while at least "
                        "safety.frozen_force_n was commanded (a stuck sensor, a hung firmware)",
}

#: STATE.flags bit 0: the device's output is armed (it renders the commanded wrench).
F_ARMED = 1
#: COMMAND.flags bit 0: enable (render the wrench); clear: zero the output now.
F_ENABLE = 1

#: Default time without a STATE after which the server driver reports the link lost [s].
DEFAULT_LINK_TIMEOUT_S = 0.1
#: Default watchdog of a device program: armed and no command for this long -> zero, latched [s].
DEFAULT_WATCHDOG_S = 0.05
#: Default UDP port of the server driver (``[device] listen``).
DEFAULT_PORT = 9872
#: A receiver reads at most this many datagrams per poll (bounds the time a flood can take).
MAX_DRAIN = 512
#: Receive buffer / datagram size limit of both sides: anything longer is dropped unread.
MAX_DATAGRAM_BYTES = 2048


@dataclass(frozen=True)
class RowColumn:
    name: str
    start: int
    width: int
    unit: str
    doc: str


#: The device state row STATE carries (the ``DeviceDriver`` state row of the server's device
#: drivers, world frame, at the handle).
ROW_COLUMNS: tuple[RowColumn, ...] = (
    RowColumn("pose", 0, 7, "m, -", "position x y z, then unit quaternion qw qx qy qz of the handle"),
    RowColumn("twist", 7, 6, "m/s, rad/s", "linear velocity (3), angular velocity (3)"),
    RowColumn("hand", 13, 6, "N, N m", "wrench the user's hand applies to the handle (a force sensor's "
                                       "reading); NaN in all six if the device has no sensor"),
    RowColumn("time", 19, 1, "s", "device clock of this sample"),
    RowColumn("buttons", 20, 1, "-", "the device's buttons as a bit mask (bit i set while button i is held), an "
                                     "integer held in a float64; NaN if the device has no buttons (or in STATE "
                                     "version 1)"),
    RowColumn("gripper", 21, 2, "rad, rad/s", "the gripper's opening angle, then its rate; NaN where the device has "
                                              "no gripper or does not measure the rate"),
)
ROW_FLOATS = 23
#: The row of STATE version 1: the columns before the device's inputs were appended.
ROW_FLOATS_V1 = 20
WRENCH_FLOATS = 6
#: Row columns that must be finite for a STATE to be taken (the hand and the inputs may be NaN:
#: not measured).
ROW_FINITE = ((0, 13), (19, 20))

_WIRE = {"4s": ("bytes[4]", 4), "B": ("u8", 1), "H": ("u16", 2), "I": ("u32", 4), "Q": ("u64", 8),
         "x": ("pad", 1), "d": ("f64", 8)}


@dataclass(frozen=True)
class Field:
    """One field of a datagram: its ``struct`` code (``count`` of them), unit and meaning."""

    name: str
    code: str
    doc: str
    unit: str = "-"
    count: int = 1

    @property
    def fmt(self) -> str:
        return f"{self.count}{self.code}" if self.count > 1 else self.code

    @property
    def size(self) -> int:
        return _WIRE[self.code][1] * self.count

    @property
    def wire(self) -> str:
        base = _WIRE[self.code][0]
        if self.code == "x":
            return f"{self.count} pad bytes"
        return f"{base}[{self.count}]" if self.count > 1 else base

    @property
    def padding(self) -> bool:
        return self.code == "x"


def _prefix(type_doc: str, version: int) -> tuple[Field, ...]:
    return (Field("magic", "4s", 'b"HPDV"'),
            Field("version", "B", f"layout version ({version})"),
            Field("type", "B", type_doc))


class Datagram:
    """A fixed-layout little-endian datagram: the ``struct`` layouts from its fields.

    The last field is the float64 block (the state row, the wrench); everything before it is the
    header (:attr:`header`, with the constant prefix magic/version/type first; :attr:`body` is
    the header without that prefix).
    """

    def __init__(self, name: str, type_id: DatagramType, direction: str, doc: str,
                 fields: tuple[Field, ...], version: int = 1) -> None:
        self.name = name
        #: this layout's version byte
        self.version = int(version)
        self.type_id = DatagramType(type_id)
        self.direction = direction
        self.doc = doc
        self.fields = fields
        *head, block = fields
        if block.code != "d" or any(f.code == "d" for f in head):
            raise ValueError(f"{name}: the float64 block must be the last field, and the only float one")
        if [f.name for f in head[:3]] != ["magic", "version", "type"]:
            raise ValueError(f"{name}: a datagram starts with magic, version, type")
        self.header = struct.Struct("<" + "".join(f.fmt for f in head))
        self.body = struct.Struct("<" + "".join(f.fmt for f in head[3:]))
        self.header_names = tuple(f.name for f in head if not f.padding)
        self.body_names = self.header_names[3:]
        self.block = block
        self.block_offset = self.header.size
        self.size = self.header.size + block.size
        self.offsets: dict[str, int] = {}
        off = 0
        for f in fields:
            self.offsets[f.name] = off
            off += f.size
        assert off == self.size and struct.calcsize(self.header.format) == self.header.size
        self.Decoded = namedtuple(f"{name.title()}Datagram", self.header_names[3:] + (block.name,))

    def __repr__(self) -> str:
        return f"<Datagram {self.name} {self.size} bytes>"

    # -- hot path ------------------------------------------------------------------------------
    def new_buffer(self) -> bytearray:
        """A zeroed buffer of :attr:`size` with the constant prefix written (pack the rest into it)."""
        buf = bytearray(self.size)
        struct.pack_into("<4sBB", buf, 0, MAGIC, self.version, int(self.type_id))
        return buf

    def floats(self, buf) -> np.ndarray:
        """The float64 block of ``buf`` as a writable (for a bytearray) little-endian numpy view."""
        return np.frombuffer(buf, dtype="<f8", count=self.block.count, offset=self.block_offset)

    def prefix_ok(self, magic: bytes, version: int, type_id: int) -> bool:
        return magic == MAGIC and version == self.version and type_id == self.type_id

    # -- conveniences (allocate) ---------------------------------------------------------------
    def pack(self, **values) -> bytes:
        """The datagram of these field values (every header field by name, the block as a
        sequence of :attr:`block`.count floats; padding is zero). ``ValueError`` names a missing
        or unknown field."""
        want = set(self.body_names) | {self.block.name}
        missing, unknown = sorted(want - set(values)), sorted(set(values) - want)
        if missing or unknown:
            raise ValueError(f"{self.name}: missing fields {missing}, unknown fields {unknown}")
        buf = self.new_buffer()
        try:
            self.body.pack_into(buf, PREFIX_BYTES, *(values[n] for n in self.body_names))
        except struct.error as exc:
            raise ValueError(f"{self.name}: {exc}") from None
        block = np.asarray(values[self.block.name], dtype=np.float64)
        if block.shape != (self.block.count,):
            raise ValueError(f"{self.name}.{self.block.name}: expected {self.block.count} floats, got shape {block.shape}")
        self.floats(buf)[:] = block
        return bytes(buf)

    def unpack(self, data) -> "tuple":
        """The fields of a datagram (a namedtuple, the block as a float64 array), or ``ValueError``
        saying why it is not one of this type (size, magic, version, type)."""
        if len(data) != self.size:
            raise ValueError(f"{self.name}: expected {self.size} bytes, got {len(data)}")
        h = self.header.unpack_from(data, 0)
        if not self.prefix_ok(h[0], h[1], h[2]):
            raise ValueError(f"{self.name}: bad prefix (magic {h[0]!r}, version {h[1]}, type {h[2]})")
        block = np.frombuffer(bytes(data), dtype="<f8", count=self.block.count, offset=self.block_offset).copy()
        return self.Decoded(*h[3:], block)


def _state(version: int, floats: int, row_doc: str) -> Datagram:
    return Datagram("STATE", DatagramType.STATE, "device -> server",
                    "The device's state, one per device tick, from the device program's socket.", (
        *_prefix("1 = STATE", version),
        Field("flags", "H", "bit 0 (F_ARMED): the output is armed"),
        Field("device_session", "Q", "the device program's boot epoch", "ns since 1970"),
        Field("server_session", "Q", "echo: server_session of the command key the device is in (0 before any)"),
        Field("epoch", "I", "echo: epoch of that key (0 before any)"),
        Field("period_us", "I", "the device tick", "us"),
        Field("seq", "Q", "state sequence number: 1 for the first datagram of a device session, +1 per datagram"),
        Field("cmd_seq", "Q", "echo: seq of the last command accepted (0 before any)"),
        Field("kind", "B", "device kind (DeviceKind: 0 1dof, 1 planar, 2 spatial)"),
        Field("fault", "B", "the device's latched fault (DeviceFault), 0 if none"),
        Field("pad", "x", "zero", count=6),
        Field("state", "d", row_doc, count=floats),
    ), version=version)


STATE = _state(VERSION, ROW_FLOATS, "the device state row (table below), world frame, at the handle")
#: STATE of layout version 1 (an older device program, or one whose device has no inputs): the
#: same header and the row's first 20 floats (pose, twist, hand, time).
STATE_V1 = _state(1, ROW_FLOATS_V1, "the first 20 floats of the device state row (pose, twist, hand, time)")

COMMAND = Datagram("COMMAND", DatagramType.COMMAND, "server -> device",
                   "The wrench to render, one per haptic step, sent to the address the device's state comes from.", (
    *_prefix("2 = COMMAND", 1),
    Field("flags", "H", "bit 0 (F_ENABLE): render the wrench; clear: zero the output now"),
    Field("device_session", "Q", "the device session this command is for (from its STATE)"),
    Field("server_session", "Q", "the server driver's boot epoch", "ns since 1970"),
    Field("epoch", "I", "+1 at every enable() of the server driver; (server_session, epoch) is the command key"),
    Field("engagements", "I", "sessions the server has engaged so far (wraps at 2^32); each rise starts the "
                              "device program's scripted hand"),
    Field("seq", "Q", "command sequence number: 1 for the first datagram of a server session, +1 per datagram"),
    Field("state_seq", "Q", "echo: the newest state seq the server holds"),
    Field("wrench", "d", "fx fy fz tx ty tz, world, at the handle", "N, N m", count=WRENCH_FLOATS),
))

DATAGRAMS: tuple[Datagram, ...] = (STATE, COMMAND)

# The hot paths (server/devices/remote.py) destructure the headers by position: these are the
# orders they were written against (a change of the declaration must change them too).
assert STATE.header_names == STATE_V1.header_names == ("magic", "version", "type", "flags", "device_session", "server_session", "epoch",
                              "period_us", "seq", "cmd_seq", "kind", "fault")
assert COMMAND.header_names == ("magic", "version", "type", "flags", "device_session", "server_session", "epoch",
                                "engagements", "seq", "state_seq")
assert STATE.size == 240 and STATE_V1.size == 216 and COMMAND.size == 96
assert STATE.block_offset == STATE_V1.block_offset


def unpack_state(data):
    """A STATE of either layout (by its size: version 2, or version 1's 20-float row), decoded;
    ``ValueError`` saying why it is neither."""
    return (STATE_V1 if len(data) == STATE_V1.size else STATE).unpack(data)


def state_datagram_for(has_inputs: bool) -> Datagram:
    """The STATE layout a device program sends: version 2 when its device has inputs (buttons or
    a gripper) to report, else version 1, which every server takes."""
    return STATE if has_inputs else STATE_V1


def row_finite(row: np.ndarray) -> bool:
    """The columns of a state row that must be finite are (pose, twist, time; not the hand)."""
    return bool(np.isfinite(row[0:13]).all() and np.isfinite(row[19]))


_session_lock = threading.Lock()
_last_session = 0


def new_session() -> int:
    """A boot epoch: ns since 1970, strictly increasing within the process (orders restarts)."""
    global _last_session
    with _session_lock:
        _last_session = max(time.time_ns(), _last_session + 1)
        return _last_session
