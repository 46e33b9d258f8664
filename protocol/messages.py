"""Protocol v1 message declarations: the single source of truth, as msgspec Structs.

Every message is one :class:`msgspec.Struct` with ``array_like=True``: a packet is the msgpack
array of its fields in declaration order, the 5 header integers (:class:`Message`) first. Each
field's annotation carries its wire rule (msgspec ``Meta`` constraints: integer ranges, the float
bound, fixed bin lengths, enums) and its documentation (``Meta.extra``: wire type, unit, frame,
sign, rule, the minor version that added it). The codec (:mod:`hapticproxy.protocol.codec`)
decodes with msgspec and adds a vectorised numpy pass for what msgspec cannot express (unit
normals and quaternions, unique contact keys, linkage trees, packed bins, the codec's limits);
:mod:`hapticproxy.protocol.spec` renders SPEC.md's tables from these declarations.

Conventions fixed here (and in SPEC.md):

- SI units throughout: m, kg, s, N, N m, rad, m/s, rad/s.
- World frame unless a field says otherwise. Every vector on the wire is a 3-vector; planar
  scenes live in the world x-y plane and rotate about +z; a 1-DOF tool translates along a unit
  axis given in ``Hello.axis`` (default +x).
- A pose is position (3) followed by a unit quaternion (w, x, y, z): 7 float64. It is the pose of
  the *tool frame* (for a linkage: of the root link's frame) in the world.
- Contact normal points from the environment towards the tool; separation ``d`` is the real
  tool's separation from the constraint (positive apart, negative penetrating); an engine with
  epsilon-active geometry measures ``s_eps`` on the epsilon-inflated tool and sends
  ``d = s_eps + epsilon``. ``v_constr = n . v(c_p)`` in m/s.
- Contact key: (tool link, environment body, feature), three int64, stable across steps.

Minor-version rule (msgspec's own schema-evolution rule): a later minor only appends fields at
the end of a message, each with a default. Fields of minor 0 are required on the wire even where
the Python constructor offers a convenience default (``Hello(units="SI")``); a field with
``since > 0`` takes its default when a packet of an older minor lacks it.

Decoded values: ``bin f64[...]`` fields hold read-only float64 numpy views of the packet;
``ContactUpdate`` also exposes its packed columns (``keys``, ``position_m``, ``normal``,
``separation_m``, ``v_constr_m_per_s``); ``unknown_fields`` counts trailing fields of a newer
minor that were ignored. Construct with keywords; the header defaults to 0 / this version.
"""
from dataclasses import dataclass
from typing import Annotated, Any, ClassVar

import msgspec
import numpy as np
from msgspec import Meta, Struct

from .vocab import (
    JOINT_TYPE_NAMES,
    JOINT_TYPES_BY_NAME,
    SERVER_STATE_NAMES,
    TOOL_KIND_NAMES,
    TOOL_KINDS_BY_NAME,
    ErrorCode,
    JointType,
    MessageType,
    ServerState,
    ToolKind,
)

__all__ = [
    "Bye", "CONTACT_COLUMNS", "CONTACT_FLOATS", "ContactUpdate", "Error", "ErrorCode", "FieldDoc", "HEADER",
    "HEADER_LEN", "Heartbeat", "Hello", "JointType", "KEY_COLUMNS", "KEY_INTS", "LINK_FIELDS", "Link",
    "MAX_ABS_FLOAT", "MESSAGES", "MESSAGES_BY_ID", "MESSAGE_CLASSES", "Message", "MessageDoc", "MessageType",
    "PROTOCOL_MAJOR", "PROTOCOL_MINOR", "ProxyState", "REQUIRED", "Reject", "ServerState", "ToolKind",
    "UNIT_TOLERANCE", "Welcome", "check_declarations", "fields_of", "INPUT_BUTTONS", "INPUT_GRIPPER",
    "INPUT_GRIPPER_RATE", "device_inputs_fields",
    "TOOL_KIND_NAMES", "TOOL_KINDS_BY_NAME", "JOINT_TYPE_NAMES", "JOINT_TYPES_BY_NAME", "SERVER_STATE_NAMES",
]

#: Major version this code speaks. A different major fails closed in the handshake.
PROTOCOL_MAJOR = 1
#: Highest minor version of :data:`PROTOCOL_MAJOR` this code speaks. 1.1 appended
#: ``ContactUpdate.tool_joint_position`` (a linkage engine's joint positions); 1.2 appended
#: ``ProxyState.server_state`` (whether the proxy is being rendered) and the scene bounds and
#: ``note`` of ``Welcome``; 1.3 appended the device's inputs to ``ProxyState`` (``buttons``,
#: ``gripper_angle_rad``, ``gripper_velocity_rad_per_s``, ``device_inputs``), so a scene can grasp;
#: 1.4 appended ``ContactUpdate.work_on_tool_j`` (the work an engine declares it did on the tool:
#: the energy it grants the server's passivity layer, SPEC 8.11).
PROTOCOL_MINOR = 4
#: Tolerance on unit vectors and quaternions: | |x| - 1 | <= UNIT_TOLERANCE.
UNIT_TOLERANCE = 1e-6
#: Bound on the magnitude of every float (after the finite check). Generous for metres, newtons
#: and seconds, and it keeps squares far from overflow so validation can never warn.
MAX_ABS_FLOAT = 1e9


class _Required:
    """Marker of a wire-required field (SPEC tables print it as ``required``)."""

    def __repr__(self) -> str:
        return "required"


REQUIRED: Any = _Required()


# ------------------------------------------------------------------------- field annotations
def _doc(wire: str, doc: str, unit: str = "-", frame: str = "-", sign: str = "", rule: str = "",
         since: int = 0, **constraints) -> Meta:
    return Meta(description=doc, extra={"wire": wire, "unit": unit, "frame": frame, "sign": sign, "rule": rule,
                                        "since": since}, **constraints)


_F64 = Annotated[float, Meta(ge=-MAX_ABS_FLOAT, le=MAX_ABS_FLOAT)]
_U16 = Annotated[int, Meta(ge=0, le=0xFFFF)]
_INT_RANGES = {"u8": (0, 0xFF), "u16": (0, 0xFFFF), "u32": (0, 0xFFFF_FFFF), "u64": (0, None),
               "i32": (-(1 << 31), (1 << 31) - 1)}


def uint(wire: str, doc: str, *, rule: str = "", since: int = 0, unit: str = "-"):
    """An integer of wire type u8/u16/u32/u64/i32 (``rule="pos"``: >= 1)."""
    lo, hi = _INT_RANGES[wire]
    if rule == "pos":
        lo = 1
    # u64's upper bound is msgpack's own (msgspec cannot state bounds beyond int64)
    return Annotated[int, _doc(wire, doc, unit, rule=rule, since=since, ge=lo, **({} if hi is None else {"le": hi}))]


def f64(doc: str, unit: str = "-", frame: str = "-", sign: str = "", *, rule: str = "", since: int = 0):
    """A float64 (an integer is accepted), finite and within :data:`MAX_ABS_FLOAT`; ``rule``
    ``"pos"`` (> 0) or ``"nonneg"`` (>= 0)."""
    bounds = {"pos": {"gt": 0.0}, "nonneg": {"ge": 0.0}}.get(rule, {"ge": -MAX_ABS_FLOAT})
    return Annotated[float, _doc("f64", doc, unit, frame, sign, rule, since, le=MAX_ABS_FLOAT, **bounds)]


def text(doc: str, *, since: int = 0):
    """A UTF-8 string of at most ``Limits.max_str_bytes`` bytes (checked by the codec)."""
    return Annotated[str, _doc("str", doc, since=since)]


def enum(kind, doc: str, *, wire: str = "u8", since: int = 0):
    return Annotated[kind, _doc(wire, doc, rule="enum", since=since)]


def floats(k: int, wire: str, doc: str, unit: str = "-", frame: str = "-", sign: str = "", *, rule: str = ""):
    """A msgpack array of k numbers (``f64[k]``, ``pose``, ``inertia``)."""
    return Annotated[tuple.__class_getitem__((_F64,) * k), _doc(wire, doc, unit, frame, sign, rule)]


def version(doc: str):
    return Annotated[tuple[_U16, _U16], _doc("version", doc)]


def f64_bin(k: int | str, doc: str, unit: str = "-", frame: str = "-", sign: str = "", *, since: int = 0):
    """A msgpack bin of packed little-endian float64: ``k`` values, or ``"J"`` (joint count,
    <= ``Limits.max_links``). Decoded to a read-only numpy view of the packet."""
    length = {} if isinstance(k, str) else {"min_length": 8 * k, "max_length": 8 * k}
    return Annotated[bytes, _doc(f"bin f64[{k}]", doc, unit, frame, sign, since=since, **length)]


def packed(wire: str, doc: str, unit: str = "-", frame: str = "-"):
    """A bin whose length follows ``contact_count`` (checked by the codec)."""
    return Annotated[bytes, _doc(wire, doc, unit, frame)]


_VERSION_DOC = "[major, minor]"


# --------------------------------------------------------------------------- linkage records
class Link(Struct, array_like=True):
    """One link of a ``linkage`` tool (one element of ``Hello.links``): a msgpack array of these
    fields, in order. Links are listed parents first (``parent < own index``); link 0 is the root
    (floating base, ``parent = -1``, ``joint_type = 0``); every other link hangs from its parent
    by one joint. ``link["mass_kg"]`` reads a field by name as well."""

    mass_kg: f64("link mass, > 0", "kg", rule="pos")
    com_m: floats(3, "f64[3]", "centre of mass in the link frame", "m", "link")
    inertia_kg_m2: floats(6, "inertia", "[Ixx, Iyy, Izz, Ixy, Ixz, Iyz], symmetric positive semi-definite",
                          "kg m^2", "link, about the com")
    parent: uint("i32", "index of the parent link, -1 for link 0 only, else 0 <= parent < own index")
    joint_type: enum(JointType, "0 root (link 0 only), 1 revolute, 2 prismatic")
    joint_axis: floats(3, "f64[3]", "unit joint axis in this link's frame (ignored for the root)", "-", "link",
                       "positive q: right-handed rotation about / translation along +axis", rule="unit")
    joint_origin: floats(7, "pose", "pose of this link's frame in the parent's frame at q = 0 (root: identity)",
                         "m, quaternion", "parent link")

    def __getitem__(self, name: str):
        return getattr(self, name)


# ----------------------------------------------------------------------------------- header
class Message(Struct, array_like=True, kw_only=True, dict=True, eq=False):
    """The 5 header integers every packet starts with; every message adds its fields after them."""

    TYPE_ID: ClassVar[int] = 0
    DIRECTION: ClassVar[str] = ""
    REALTIME: ClassVar[bool] = False  # carries a per-type sequence number (newest wins)
    FROZEN_PREFIX: ClassVar[int] = 0  # fields readable whatever the major (handshake)
    unknown_fields: ClassVar[int] = 0  # set on a decoded message: trailing fields ignored

    major: uint("u16", "protocol major version of this packet's layout") = PROTOCOL_MAJOR
    minor: uint("u16", "protocol minor version the sender speaks (informative)") = PROTOCOL_MINOR
    type_id: uint("u8", "message type id (table above)") = 0
    session_id: uint("u32", "session id granted by Welcome; 0 in Hello and Reject") = 0
    token: uint("u64", "session token granted by Welcome (random, secret to the session); 0 in Hello and Reject") = 0

    def __eq__(self, other: object) -> bool:
        if type(other) is not type(self):
            return NotImplemented
        for name in self.__struct_fields__[3:]:  # minor and the constants are not content
            if not _same(getattr(self, name), getattr(other, name)):
                return False
        return True

    __hash__ = None  # type: ignore[assignment]


def _same(a, b) -> bool:
    if isinstance(a, (np.ndarray, bytes)) or isinstance(b, (np.ndarray, bytes)):
        if isinstance(a, bytes) and isinstance(b, bytes):
            return a == b
        a = np.frombuffer(a, "<f8") if isinstance(a, bytes) else np.asarray(a)
        b = np.frombuffer(b, "<f8") if isinstance(b, bytes) else np.asarray(b)
        return a.shape == b.shape and bool(np.array_equal(a, b))
    if isinstance(a, (tuple, list)) and isinstance(b, (tuple, list)):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    return a == b


# ------------------------------------------------------------------------------ messages
class Hello(Message, kw_only=True):
    """Opens a session. Resent by the client every hello_retry_s until Welcome or Reject arrives.
    The header and the first three fields are frozen across majors so any server can answer."""

    TYPE_ID = MessageType.HELLO
    DIRECTION = "client -> server"
    FROZEN_PREFIX = 3
    type_id: uint("u8", "") = MessageType.HELLO

    client_nonce: uint("u64", "random, non-zero; echoed in Welcome/Reject to match the reply", rule="pos")
    version_min: version(_VERSION_DOC + " lowest version the client speaks") = (PROTOCOL_MAJOR, 0)
    version_max: version(_VERSION_DOC + " highest version the client speaks; header major/minor = the layout "
                         "this Hello is written in") = (PROTOCOL_MAJOR, PROTOCOL_MINOR)
    engine: text("engine name and version, free text (<= max_str_bytes bytes)") = ""
    units: text('must be "SI"') = "SI"
    tool_kind: enum(ToolKind, "1 = 1dof, 2 = planar, 3 = spatial, 4 = linkage")
    mass_kg: f64("rigid tool mass, > 0 (linkage: total, informative)", "kg", rule="pos")
    com_m: floats(3, "f64[3]", "centre of mass in the tool frame", "m", "tool") = (0.0, 0.0, 0.0)
    inertia_kg_m2: floats(6, "inertia", "[Ixx, Iyy, Izz, Ixy, Ixz, Iyz], symmetric PSD; 1dof may send zeros",
                          "kg m^2", "tool, about the com") = (0.0,) * 6
    axis: floats(3, "f64[3]", "1dof translation axis, unit; others send [1, 0, 0]", "-", "world",
                 "positive motion along +axis", rule="unit") = (1.0, 0.0, 0.0)
    epsilon_m: f64("requested epsilon of active geometry, >= 0", "m", rule="nonneg") = 0.0
    max_contacts: uint("u16", "requested contact capacity per ContactUpdate, >= 1", rule="pos")
    env_rate_hz: f64("nominal simulation step rate (informative, > 0)", "Hz", rule="pos") = 60.0
    links: Annotated[tuple[Link, ...], _doc("links", "linkage: link records (table Link), 1..max_links; "
                                                     "other kinds: []")] = ()
    held_link: uint("u16", "linkage: index of the link the hand holds; other kinds: 0") = 0

    def __post_init__(self) -> None:
        links = self.links
        if links and not all(type(ln) is Link for ln in links):
            # dict records (an engine's LinkDescription.record()) or plain sequences
            self.links = tuple(ln if type(ln) is Link else Link(**ln) if isinstance(ln, dict) else Link(*ln)
                               for ln in links)
        elif type(links) is not tuple:
            self.links = tuple(links)


class Welcome(Message, kw_only=True):
    """Accepts a Hello. Its header carries the new session's session_id and token (both non-zero;
    the only handshake message with non-zero ones): the client puts them in the header of every
    later packet. Repeated (same content) if the same Hello arrives again."""

    TYPE_ID = MessageType.WELCOME
    DIRECTION = "server -> client"
    type_id: uint("u8", "") = MessageType.WELCOME

    client_nonce: uint("u64", "the Hello's client_nonce")
    version: version(_VERSION_DOC + " chosen version, used by both sides from now on")
    haptic_rate_hz: f64("server haptic step rate", "Hz", rule="pos")
    epsilon_m: f64("granted epsilon: the engine inflates the tool by this", "m", rule="nonneg")
    max_contacts: uint("u16", "granted capacity; a ContactUpdate with more is rejected", rule="pos")
    heartbeat_interval_s: f64("send a Heartbeat when nothing else was sent for this long", "s", rule="pos")
    silence_timeout_s: f64("a side that hears nothing valid for this long ends the session (Bye 61)", "s", rule="pos")
    server_name: text("free text") = "hapticproxy"
    workspace_extent_m: f64("scene bound: every contact position and the tool pose's position lie within "
                            "+-this of the origin on each axis (else Error OUT_OF_BOUNDS)", "m", "world",
                            rule="pos", since=2) = MAX_ABS_FLOAT
    max_constraint_speed_m_per_s: f64("scene bound: |v_constr| of every contact <= this", "m/s", rule="pos",
                                      since=2) = MAX_ABS_FLOAT
    max_separation_m: f64("scene bound: |separation| of every contact <= this", "m", rule="pos",
                          since=2) = MAX_ABS_FLOAT
    note: text("why a granted value differs from the request (e.g. epsilon capped), '' if none",
               since=2) = ""
    update_watchdog_s: f64("the force fades when no ContactUpdate was applied for this long (Heartbeats keep "
                           "only the session); 0: not told", "s", rule="nonneg", since=2) = 0.0


class Reject(Message, kw_only=True):
    """Refuses a Hello. Layout frozen across majors."""

    TYPE_ID = MessageType.REJECT
    DIRECTION = "server -> client"
    FROZEN_PREFIX = 5
    type_id: uint("u8", "") = MessageType.REJECT

    client_nonce: uint("u64", "the Hello's client_nonce (0 if it could not be read)")
    code: uint("u16", "ErrorCode, 40-59")
    reason: text("human-readable reason")
    version_min: version(_VERSION_DOC + " lowest version the server speaks") = (PROTOCOL_MAJOR, 0)
    version_max: version(_VERSION_DOC + " highest version the server speaks") = (PROTOCOL_MAJOR, PROTOCOL_MINOR)


class ContactUpdate(Message, kw_only=True):
    """All current contacts, sent after every simulation step. A contact absent from the update
    leaves the server's local model. n = 0 is valid (no contact)."""

    TYPE_ID = MessageType.CONTACT_UPDATE
    DIRECTION = "client -> server"
    REALTIME = True
    type_id: uint("u8", "") = MessageType.CONTACT_UPDATE

    seq: uint("u64", "1, 2, 3, ... per session; newest wins", rule="pos")
    env_time_s: f64("simulation time of this step (engine clock)", "s")
    tool_pose: f64_bin(7, "engine's (virtual) tool pose at env_time_s: x y z qw qx qy qz; the pose the contacts "
                          "were computed at (the server locates the reported features on the tool with it)",
                       "m, quaternion", "world")
    contact_count: uint("u16", "n, 0 <= n <= granted max_contacts")
    contact_keys: packed("bin i64[n*3]", "n keys, row-major: (tool_link, env_body, feature) per contact; unique")
    contact_data: packed("bin f64[n*8]", "structure of arrays: position n*3, normal n*3, separation n, v_constr n",
                         "see Contact columns", "world")
    tool_joint_position: f64_bin("J", "linkage: the engine's joint positions at env_time_s (links 1..L-1 in link "
                                      "order; with tool_pose, the root's: the configuration the contacts were "
                                      "computed at); others: empty or absent", "rad or m", since=1) = b""
    work_on_tool_j: f64("the work the engine's world did on its tool since the previous update (an object it "
                        "drives pushing the tool): the energy it grants the server to give the hand beyond what "
                        "the hand put in (SPEC 8.11); 0: none", "J", rule="nonneg", since=4) = 0.0

    @property
    def n_contacts(self) -> int:
        """number of contacts n (rows of keys)"""
        return self.contact_count

    @classmethod
    def from_arrays(cls, *, seq: int, env_time_s: float, tool_pose, keys, position_m, normal, separation_m,
                    v_constr_m_per_s, tool_joint_position=b"", session_id: int = 0, token: int = 0,
                    work_on_tool_j: float = 0.0) -> "ContactUpdate":
        """A ContactUpdate from its columns (``keys`` int64 (n, 3), ``position_m`` / ``normal``
        float64 (n, 3), ``separation_m`` / ``v_constr_m_per_s`` float64 (n,)), packed as on the wire."""
        keys = np.ascontiguousarray(keys, dtype="<i8").reshape(-1, 3)
        cols = [np.ascontiguousarray(a, dtype="<f8") for a in (position_m, normal, separation_m, v_constr_m_per_s)]
        msg = cls(seq=seq, env_time_s=env_time_s, tool_pose=np.asarray(tool_pose, "<f8"), contact_count=keys.shape[0],
                  contact_keys=keys.tobytes(), contact_data=b"".join(a.tobytes() for a in cols),
                  tool_joint_position=np.asarray(tool_joint_position if len(tool_joint_position) else (), "<f8"),
                  session_id=session_id, token=token, work_on_tool_j=work_on_tool_j)
        msg.keys, msg.position_m, msg.normal, msg.separation_m, msg.v_constr_m_per_s = (keys, *cols)
        return msg


class ProxyState(Message, kw_only=True):
    """Acknowledges a ContactUpdate with the proxy state, sent in the haptic step after the one that
    applied it (at most one per accepted ContactUpdate)."""

    TYPE_ID = MessageType.PROXY_STATE
    DIRECTION = "server -> client"
    REALTIME = True
    type_id: uint("u8", "") = MessageType.PROXY_STATE

    seq: uint("u64", "server's own sequence, 1, 2, 3, ...; newest wins", rule="pos")
    ack_seq: uint("u64", "seq of the newest ContactUpdate applied, 0 if none yet")
    server_time_s: f64("server clock at the haptic step, since the session began", "s")
    proxy_pose: f64_bin(7, "proxy tool-frame pose", "m, quaternion", "world")
    proxy_twist: f64_bin(6, "velocity of the tool-frame origin (3), angular velocity (3)", "m/s, rad/s", "world")
    wrench: f64_bin(6, "force (3) at the tool-frame origin, torque (3) about it: what the user applies to the "
                       "proxy (hand plus coupling), already applied by the server; an engine that drives its tool "
                       "by pose does not apply it again (SPEC 8)", "N, N m", "world", "acts on the tool")
    joint_position: f64_bin("J", "linkage: q of links 1..L-1 in link order; others: empty", "rad or m") = b""
    joint_velocity: f64_bin("J", "linkage: dq/dt, same order; others: empty", "rad/s or m/s") = b""
    joint_effort: f64_bin("J", "linkage: the joint efforts of the same wrench (already applied by the server); "
                                "others: empty", "N m or N",
                          sign="positive along +q") = b""
    server_state: enum(ServerState, "ServerState: 1 idle, 2 engaged, 3 fading, 4 fault (0: not reported); follow "
                                    "the proxy only while engaged: otherwise it is held and not rendered",
                       since=2) = ServerState.UNKNOWN
    epsilon_m: f64("the epsilon to inflate the tool by from the next step on: the distance the tool may travel "
                   "before its next update is applied, measured by the server; 0 < it <= Welcome.epsilon_m "
                   "(0: use Welcome.epsilon_m)", "m", rule="nonneg", since=2) = 0.0
    lead_s: f64("track proxy_pose advanced along proxy_twist by lead_s plus the time since this ProxyState "
                "arrived (the server measures the engine tool's lag behind the proxy; 0: track the pose as it "
                "is)", "s", rule="nonneg", since=2) = 0.0
    buttons: uint("u32", "the device's buttons held at the haptic step, a bit mask (bit i: the device's button i); "
                         "0 when none is held or the device has none (device_inputs bit 0)", since=3) = 0
    gripper_angle_rad: f64("the device's gripper opening angle at the haptic step; 0 when it has none "
                           "(device_inputs bit 1)", "rad", since=3) = 0.0
    gripper_velocity_rad_per_s: f64("the gripper's opening rate; 0 when not measured (device_inputs bit 2)", "rad/s",
                                    since=3) = 0.0
    device_inputs: uint("u8", "what the device reports: bit 0 its buttons, bit 1 the gripper's angle, bit 2 the "
                              "gripper's rate (0: none, or a server before 1.3)", since=3) = 0


#: ``ProxyState.device_inputs`` bits: the device reports its buttons, its gripper's angle, its rate.
INPUT_BUTTONS, INPUT_GRIPPER, INPUT_GRIPPER_RATE = 1, 2, 4


def device_inputs_fields(inputs) -> tuple[int, float, float, int]:
    """``(buttons, gripper_angle_rad, gripper_velocity_rad_per_s, device_inputs)`` of the device
    state row's input columns (``inputs``: buttons, gripper angle, gripper rate; NaN where the
    device does not report one, as ``protocol/devlink.py``'s row has them). A value that is NaN,
    not finite within the float bound, or (buttons) outside [0, 2^32) is not reported: 0 and its
    bit clear. ``server/egress.py`` packs the same rule in its kernel."""
    b, g, gr = float(inputs[0]), float(inputs[1]), float(inputs[2])
    flags = 0
    bi = 0
    if 0.0 <= b <= 4294967295.0:
        bi = int(b)
        flags |= INPUT_BUTTONS
    ga = 0.0
    if -MAX_ABS_FLOAT <= g <= MAX_ABS_FLOAT:
        ga = g
        flags |= INPUT_GRIPPER
    gv = 0.0
    if -MAX_ABS_FLOAT <= gr <= MAX_ABS_FLOAT:
        gv = gr
        flags |= INPUT_GRIPPER_RATE
    return bi, ga, gv, flags


class Heartbeat(Message, kw_only=True):
    """Keeps a quiet session alive: sent when nothing else was sent for heartbeat_interval_s."""

    TYPE_ID = MessageType.HEARTBEAT
    DIRECTION = "both"
    REALTIME = True
    type_id: uint("u8", "") = MessageType.HEARTBEAT

    seq: uint("u64", "per sender, 1, 2, 3, ...; its own sequence", rule="pos")
    time_s: f64("sender's clock (informative)", "s")


class Bye(Message, kw_only=True):
    """Ends the session. Sent 3 times in a row (one may be lost); the receiver ends the session
    at the first and counts the repeats as unknown-session packets."""

    TYPE_ID = MessageType.BYE
    DIRECTION = "both"
    type_id: uint("u8", "") = MessageType.BYE

    code: uint("u16", "ErrorCode 60-79")
    reason: text("human-readable reason") = ""


class Error(Message, kw_only=True):
    """Reports a packet the sender received and dropped. Rate-limited (at most error_rate_per_s per
    session); never answered with another Error."""

    TYPE_ID = MessageType.ERROR
    DIRECTION = "both"
    type_id: uint("u8", "") = MessageType.ERROR

    code: uint("u16", "ErrorCode 1-39")
    field: text("name of the offending field, '' if none") = ""
    detail: text("human-readable detail") = ""
    ref_type: uint("u8", "type id of the dropped packet, 0 if unknown") = 0
    ref_seq: uint("u64", "its seq if it had one, else 0") = 0


#: Every message class by type id.
MESSAGE_CLASSES: dict[int, type[Message]] = {
    int(c.TYPE_ID): c for c in (Hello, Welcome, Reject, ContactUpdate, ProxyState, Heartbeat, Bye, Error)}


# ------------------------------------------------------------------ derived descriptions
@dataclass(frozen=True)
class FieldDoc:
    """One field as SPEC.md documents it, read from its Struct annotation."""

    name: str
    type: str  # wire type (SPEC "Wire types")
    unit: str
    frame: str
    sign: str
    doc: str
    default: Any  # REQUIRED for fields of minor 0
    since_minor: int
    check: str  # "pos", "nonneg", "unit", "enum" or ""
    py_type: Any


@dataclass(frozen=True)
class MessageDoc:
    """One message as SPEC.md documents it (derived from its Struct)."""

    name: str
    type_id: MessageType
    direction: str
    realtime: bool
    doc: str
    fields: tuple[FieldDoc, ...]
    frozen_prefix: int
    cls: type

    def field_index(self, name: str) -> int:
        for i, f in enumerate(self.fields):
            if f.name == name:
                return i
        raise KeyError(f"{self.name} has no field {name!r}")


def _meta_of(tp) -> tuple[Any, Meta | None]:
    if getattr(tp, "__metadata__", None):
        metas = [m for m in tp.__metadata__ if isinstance(m, Meta) and m.extra]
        return tp.__origin__, (metas[-1] if metas else None)
    return tp, None


def fields_of(cls: type[Struct]) -> tuple[FieldDoc, ...]:
    """The documented fields of a Struct, in wire order (a message's exclude the header)."""
    out = []
    for info in msgspec.structs.fields(cls):
        tp, meta = _meta_of(info.type)
        extra = meta.extra if meta is not None else {}
        since = extra.get("since", 0)
        out.append(FieldDoc(info.name, extra.get("wire", "?"), extra.get("unit", "-"), extra.get("frame", "-"),
                            extra.get("sign", ""), meta.description if meta is not None else "",
                            REQUIRED if since == 0 else info.default, since, extra.get("rule", ""), tp))
    return tuple(out[HEADER_LEN:] if issubclass(cls, Message) and cls is not Message else out)


def _message_doc(cls: type[Message]) -> MessageDoc:
    return MessageDoc(cls.__name__, MessageType(cls.TYPE_ID), cls.DIRECTION, cls.REALTIME,
                      " ".join(cls.__doc__.split()), fields_of(cls), cls.FROZEN_PREFIX, cls)


HEADER_LEN = 5
#: The header rows (major, minor, type_id, session_id, token).
HEADER: tuple[FieldDoc, ...] = tuple(
    FieldDoc(f.name, f.type, f.unit, f.frame, f.sign, f.doc, REQUIRED, 0, "", f.py_type) for f in fields_of(Message))
LINK_FIELDS: tuple[FieldDoc, ...] = fields_of(Link)
MESSAGES: tuple[MessageDoc, ...] = tuple(_message_doc(c) for c in MESSAGE_CLASSES.values())
MESSAGES_BY_ID: dict[int, MessageDoc] = {int(m.type_id): m for m in MESSAGES}
HELLO, WELCOME, REJECT, CONTACT_UPDATE, PROXY_STATE, HEARTBEAT, BYE, ERROR = MESSAGES


# ------------------------------------------------------------------------ contact columns
@dataclass(frozen=True)
class ColumnSpec:
    """One column of a packed contact array (see ``ContactUpdate.contact_data``)."""

    name: str  # attribute of the decoded ContactUpdate
    width: int  # float64 (or int64) values per contact
    unit: str
    frame: str
    sign: str
    doc: str


#: Columns of ``ContactUpdate.contact_keys`` (int64, per contact, row-major n x 3).
KEY_COLUMNS: tuple[ColumnSpec, ...] = (
    ColumnSpec("tool_link", 1, "-", "-", "", "index of the tool link touching (0 for rigid tools)"),
    ColumnSpec("env_body", 1, "-", "-", "", "engine's id of the environment body"),
    ColumnSpec("feature", 1, "-", "-", "",
               "engine's id of the feature pair (stable across steps while the contact persists)"),
)
#: Column blocks of ``ContactUpdate.contact_data`` (float64), structure of arrays: all
#: positions (n x 3, row-major), then all normals (n x 3), then all separations (n), then all
#: constraint velocities (n). A later minor may append whole column blocks after these.
CONTACT_COLUMNS: tuple[ColumnSpec, ...] = (
    ColumnSpec("position_m", 3, "m", "world", "",
               "c_p, the constraint position: a point on the environment feature"),
    ColumnSpec("normal", 3, "-", "world", "points from the environment towards the tool",
               "n, the constraint normal, unit within 1e-6"),
    ColumnSpec("separation_m", 1, "m", "-",
               "positive apart, negative penetrating",
               "d, the real tool's separation from the constraint; epsilon-active engines send s_eps + epsilon"),
    ColumnSpec("v_constr_m_per_s", 1, "m/s", "world (along n)",
               "positive: the constraint moves towards the tool",
               "n . v(c_p): normal velocity of the environment point"),
)
#: float64 values per contact in contact_data, int64 values per contact in contact_keys.
CONTACT_FLOATS = sum(c.width for c in CONTACT_COLUMNS)
KEY_INTS = len(KEY_COLUMNS)


def check_declarations(classes=tuple(MESSAGE_CLASSES.values())) -> None:
    """Raise ``ValueError`` if a declaration breaks the versioning rules (run by the tests)."""
    ids = set()
    for cls in classes:
        if cls.TYPE_ID in ids:
            raise ValueError(f"{cls.__name__}: duplicate type id {int(cls.TYPE_ID)}")
        ids.add(cls.TYPE_ID)
        names = msgspec.structs.fields(cls)
        if [f.name for f in names[:HEADER_LEN]] != [f.name for f in msgspec.structs.fields(Message)]:
            raise ValueError(f"{cls.__name__}: must start with the 5 header fields")
        if names[2].default != cls.TYPE_ID:
            raise ValueError(f"{cls.__name__}: type_id default must be its TYPE_ID")
        last_minor = 0
        for f, info in zip(fields_of(cls), names[HEADER_LEN:]):
            if f.since_minor < last_minor:
                raise ValueError(f"{cls.__name__}.{f.name}: fields must be in order of since (append only)")
            last_minor = f.since_minor
            if f.since_minor > 0 and info.required:
                raise ValueError(f"{cls.__name__}.{f.name}: a field added in minor {f.since_minor} needs a default")
            if f.type == "?":
                raise ValueError(f"{cls.__name__}.{f.name}: no wire type declared")
