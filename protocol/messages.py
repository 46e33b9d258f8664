"""Protocol v1 message declarations: the single source of truth.

Every message is declared here exactly once, as data (:class:`MessageSpec` holding ordered
:class:`FieldSpec` rows). The codec (:mod:`hapticproxy.protocol.codec`) compiles its encoders,
decoders and validators from these declarations, and :mod:`hapticproxy.protocol.spec` renders the
message tables of ``SPEC.md`` from them; a test checks that the two agree byte for byte.

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

Minor-version rule: a later minor may only append fields at the end of a message, each with a
default (``FieldSpec.since_minor > 0`` requires ``default is not REQUIRED``).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from enum import IntEnum
from typing import Any

#: Major version this code speaks. A different major fails closed in the handshake.
PROTOCOL_MAJOR = 1
#: Highest minor version of :data:`PROTOCOL_MAJOR` this code speaks. 1.1 appended
#: ``ContactUpdate.tool_joint_position`` (a linkage engine's joint positions); 1.2 appended
#: ``ProxyState.server_state`` (whether the proxy is being rendered).
PROTOCOL_MINOR = 2


class _Required:
    """Sentinel: the field has no default (present since minor 0)."""

    def __repr__(self) -> str:  # shows up in SPEC.md tables
        return "required"


REQUIRED: Any = _Required()


class MessageType(IntEnum):
    """Wire type ids (the third header element)."""

    HELLO = 1
    WELCOME = 2
    REJECT = 3
    CONTACT_UPDATE = 4
    PROXY_STATE = 5
    HEARTBEAT = 6
    BYE = 7
    ERROR = 8


class ToolKind(IntEnum):
    """``Hello.tool_kind``: how the proxy may move."""

    ONE_DOF = 1  # "1dof": translation along Hello.axis only
    PLANAR = 2  # "planar": translation in world x-y, rotation about +z
    SPATIAL = 3  # "spatial": free rigid body, 6 DOF
    LINKAGE = 4  # "linkage": kinematic tree in Hello.links, the hand holds Hello.held_link


#: Short names used in docs and configs.
TOOL_KIND_NAMES = {
    ToolKind.ONE_DOF: "1dof",
    ToolKind.PLANAR: "planar",
    ToolKind.SPATIAL: "spatial",
    ToolKind.LINKAGE: "linkage",
}


class ServerState(IntEnum):
    """``ProxyState.server_state``: what the server does with the proxy it reports.

    An engine follows the proxy while it is ``ENGAGED``; in every other state the proxy is held
    where it is (not driven by the device), so an engine may keep its tool still.
    """

    UNKNOWN = 0  # not reported (a 1.0 / 1.1 server): assume engaged
    IDLE = 1  # no session drives the model; nothing is rendered
    ENGAGED = 2  # the proxy is rendered to the device (also while the force ramps in)
    FADING = 3  # the force fades to zero (environment silent, session ended, stopping); proxy held
    FAULT = 4  # output off after a fault; proxy held; it recovers by itself or by a re-arm


class JointType(IntEnum):
    """Joint of a linkage link to its parent (``Hello.links[i].joint_type``)."""

    ROOT = 0  # link 0 only: no joint, the floating base whose pose is the tool pose
    REVOLUTE = 1  # rotation by q rad about joint_axis
    PRISMATIC = 2  # translation by q m along joint_axis


class ErrorCode(IntEnum):
    """Codes carried by ``Error``, ``Reject`` and ``Bye``, and by :class:`ProtocolError`.

    1-19: the packet itself is bad (decoder); 20-39: the packet does not fit the session;
    40-59: handshake refusals (``Reject``); 60-79: reasons for ``Bye``.
    """

    OVERSIZE = 1  # packet longer than max_packet_bytes (checked before unpacking)
    MALFORMED = 2  # not one complete msgpack object, or a msgpack limit was exceeded
    BAD_HEADER = 3  # not an array starting with the 5 header integers
    UNKNOWN_MAJOR = 4  # header major version not spoken here
    UNKNOWN_TYPE = 5  # header type id not declared
    MISSING_FIELD = 6  # fewer fields than the message requires
    WRONG_TYPE = 7  # a field has the wrong msgpack type
    NON_FINITE = 8  # NaN or infinity in a float field
    OUT_OF_RANGE = 9  # a number outside its declared range (incl. negative mass/inertia)
    NOT_UNIT = 10  # normal / axis / quaternion not unit within UNIT_TOLERANCE
    BAD_SHAPE = 11  # array or bin of the wrong length
    TOO_MANY_CONTACTS = 12  # more contacts than max_contacts (codec) or the granted capacity
    DUPLICATE_KEY = 13  # the same contact key twice in one ContactUpdate
    BAD_TREE = 14  # linkage tree inconsistent (parents, held link, joint types)
    BAD_MAC = 15  # shared-secret mode: tag missing or wrong
    UNKNOWN_SESSION = 20  # header session id not known to the receiver
    BAD_TOKEN = 21  # header token does not match the session
    WRONG_PEER = 22  # packet for a session from a peer other than the one that did the handshake
    STALE = 23  # sequence number older than the newest accepted
    DUPLICATE = 24  # sequence number equal to the newest accepted
    UNEXPECTED = 25  # message type not valid in this direction or session state
    UNSUPPORTED_VERSION = 40  # no common major version
    UNSUPPORTED_TOOL = 41  # tool kind the server cannot simulate
    UNSUPPORTED_UNITS = 42  # Hello.units is not "SI"
    SERVER_FULL = 43  # no free session slot
    INVALID_HELLO = 44  # Hello decoded but its content is refused
    BYE_NORMAL = 60  # orderly shutdown requested by the sender
    BYE_TIMEOUT = 61  # the sender heard nothing within silence_timeout_s
    BYE_SHUTDOWN = 62  # the sender's process is stopping


#: Tolerance on unit vectors and quaternions: | |x| - 1 | <= UNIT_TOLERANCE.
UNIT_TOLERANCE = 1e-6
#: Bound on the magnitude of every float (after the finite check). Generous for metres, newtons
#: and seconds, and it keeps squares far from overflow so validation can never warn.
MAX_ABS_FLOAT = 1e9


@dataclass(frozen=True)
class FieldSpec:
    """One field of a message, in wire order.

    ``type`` is one of the wire types of SPEC.md ("Wire types"): ``u8 u16 u32 u64 i32 f64 str``;
    ``f64[k]`` (msgpack array of k numbers); ``pose``, ``inertia``, ``version``, ``links``;
    ``bin f64[k]`` / ``bin f64[J]`` / ``bin f64[n*8]`` / ``bin i64[n*3]`` (packed little-endian).
    ``check`` names an extra validation: ``unit`` (vector of norm 1), ``pos`` (> 0), ``nonneg``
    (>= 0), ``enum`` (value in ``enum``), ``psd`` (inertia), ``contact_count`` etc.
    """

    name: str
    type: str
    unit: str = "-"
    frame: str = "-"
    sign: str = ""
    doc: str = ""
    default: Any = REQUIRED
    since_minor: int = 0
    check: str = ""
    enum: type[IntEnum] | None = None


@dataclass(frozen=True)
class ColumnSpec:
    """One column of a packed contact array (see ``ContactUpdate.contact_data``)."""

    name: str  # attribute of the decoded ContactUpdate
    width: int  # float64 (or int64) values per contact
    unit: str
    frame: str
    sign: str
    doc: str


@dataclass(frozen=True)
class MessageSpec:
    name: str
    type_id: MessageType
    direction: str  # "client -> server", "server -> client", "both"
    realtime: bool  # carries a per-type sequence number (newest wins)
    doc: str
    fields: tuple[FieldSpec, ...]
    #: Messages whose layout is frozen across majors so any version can read them (handshake).
    frozen_prefix: int = 0

    def field_index(self, name: str) -> int:
        for i, f in enumerate(self.fields):
            if f.name == name:
                return i
        raise KeyError(f"{self.name} has no field {name!r}")


# ----------------------------------------------------------------------------------- header
#: Every packet is a msgpack array: these 5 header integers, then the message's fields in order.
HEADER: tuple[FieldSpec, ...] = (
    FieldSpec("major", "u16", doc="protocol major version of this packet's layout"),
    FieldSpec("minor", "u16", doc="protocol minor version the sender speaks (informative)"),
    FieldSpec("type_id", "u8", doc="message type id (table above)"),
    FieldSpec("session_id", "u32", doc="session id granted by Welcome; 0 in Hello and Reject"),
    FieldSpec("token", "u64", doc="session token granted by Welcome (random, secret to the session); 0 in Hello and Reject"),
)
HEADER_LEN = len(HEADER)

# ------------------------------------------------------------------------- linkage records
#: One link of a ``linkage`` tool: a msgpack array of these fields, in order. Links are listed
#: parents first (``parent < own index``); link 0 is the root (floating base, ``parent = -1``,
#: ``joint_type = 0``); every other link hangs from its parent by one joint.
LINK_FIELDS: tuple[FieldSpec, ...] = (
    FieldSpec("mass_kg", "f64", "kg", check="pos", doc="link mass, > 0"),
    FieldSpec("com_m", "f64[3]", "m", "link", doc="centre of mass in the link frame"),
    FieldSpec("inertia_kg_m2", "inertia", "kg m^2", "link, about the com",
              doc="[Ixx, Iyy, Izz, Ixy, Ixz, Iyz], symmetric positive semi-definite"),
    FieldSpec("parent", "i32", doc="index of the parent link, -1 for link 0 only, else 0 <= parent < own index"),
    FieldSpec("joint_type", "u8", check="enum", enum=JointType,
              doc="0 root (link 0 only), 1 revolute, 2 prismatic"),
    FieldSpec("joint_axis", "f64[3]", "-", "link", check="unit",
              sign="positive q: right-handed rotation about / translation along +axis",
              doc="unit joint axis in this link's frame (ignored for the root)"),
    FieldSpec("joint_origin", "pose", "m, quaternion", "parent link",
              doc="pose of this link's frame in the parent's frame at q = 0 (root: identity)"),
)

# ------------------------------------------------------------------------ contact columns
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

_VERSION_DOC = "[major, minor]"

# ------------------------------------------------------------------------------ messages
HELLO = MessageSpec(
    "Hello", MessageType.HELLO, "client -> server", False,
    "Opens a session. Resent by the client every hello_retry_s until Welcome or Reject arrives. "
    "The header and the first three fields are frozen across majors so any server can answer.",
    (
        FieldSpec("client_nonce", "u64", doc="random, non-zero; echoed in Welcome/Reject to match the reply"),
        FieldSpec("version_min", "version", doc=_VERSION_DOC + " lowest version the client speaks"),
        FieldSpec("version_max", "version", doc=_VERSION_DOC + " highest version the client speaks; header major/minor = this"),
        FieldSpec("engine", "str", doc="engine name and version, free text (<= max_str_len bytes)"),
        FieldSpec("units", "str", doc='must be "SI"'),
        FieldSpec("tool_kind", "u8", check="enum", enum=ToolKind,
                  doc="1 = 1dof, 2 = planar, 3 = spatial, 4 = linkage"),
        FieldSpec("mass_kg", "f64", "kg", check="pos", doc="rigid tool mass, > 0 (linkage: total, informative)"),
        FieldSpec("com_m", "f64[3]", "m", "tool", doc="centre of mass in the tool frame"),
        FieldSpec("inertia_kg_m2", "inertia", "kg m^2", "tool, about the com",
                  doc="[Ixx, Iyy, Izz, Ixy, Ixz, Iyz], symmetric PSD; 1dof may send zeros"),
        FieldSpec("axis", "f64[3]", "-", "world", check="unit",
                  sign="positive motion along +axis", doc="1dof translation axis, unit; others send [1, 0, 0]"),
        FieldSpec("epsilon_m", "f64", "m", check="nonneg", doc="requested epsilon of active geometry, >= 0"),
        FieldSpec("max_contacts", "u16", check="pos", doc="requested contact capacity per ContactUpdate, >= 1"),
        FieldSpec("env_rate_hz", "f64", "Hz", check="pos", doc="nominal simulation step rate (informative, > 0)"),
        FieldSpec("links", "links", "-", "-", doc="linkage: link records (table Link), 1..max_links; other kinds: []"),
        FieldSpec("held_link", "u16", doc="linkage: index of the link the hand holds; other kinds: 0"),
    ),
    frozen_prefix=3,
)

WELCOME = MessageSpec(
    "Welcome", MessageType.WELCOME, "server -> client", False,
    "Accepts a Hello. Its header carries the new session's session_id and token (both non-zero; "
    "the only handshake message with non-zero ones): the client puts them in the header of every "
    "later packet. Repeated (same content) if the same Hello arrives again.",
    (
        FieldSpec("client_nonce", "u64", doc="the Hello's client_nonce"),
        FieldSpec("version", "version", doc=_VERSION_DOC + " chosen version, used by both sides from now on"),
        FieldSpec("haptic_rate_hz", "f64", "Hz", check="pos", doc="server haptic step rate"),
        FieldSpec("epsilon_m", "f64", "m", check="nonneg", doc="granted epsilon: the engine inflates the tool by this"),
        FieldSpec("max_contacts", "u16", check="pos", doc="granted capacity; a ContactUpdate with more is rejected"),
        FieldSpec("heartbeat_interval_s", "f64", "s", check="pos",
                  doc="send a Heartbeat when nothing else was sent for this long"),
        FieldSpec("silence_timeout_s", "f64", "s", check="pos",
                  doc="a side that hears nothing valid for this long ends the session (Bye 61)"),
        FieldSpec("server_name", "str", doc="free text"),
    ),
)

REJECT = MessageSpec(
    "Reject", MessageType.REJECT, "server -> client", False,
    "Refuses a Hello. Layout frozen across majors.",
    (
        FieldSpec("client_nonce", "u64", doc="the Hello's client_nonce (0 if it could not be read)"),
        FieldSpec("code", "u16", doc="ErrorCode, 40-59"),
        FieldSpec("reason", "str", doc="human-readable reason"),
        FieldSpec("version_min", "version", doc=_VERSION_DOC + " lowest version the server speaks"),
        FieldSpec("version_max", "version", doc=_VERSION_DOC + " highest version the server speaks"),
    ),
    frozen_prefix=5,
)

CONTACT_UPDATE = MessageSpec(
    "ContactUpdate", MessageType.CONTACT_UPDATE, "client -> server", True,
    "All current contacts, sent after every simulation step. A contact absent from the update "
    "leaves the server's local model. n = 0 is valid (no contact).",
    (
        FieldSpec("seq", "u64", check="pos", doc="1, 2, 3, ... per session; newest wins"),
        FieldSpec("env_time_s", "f64", "s", doc="simulation time of this step (engine clock)"),
        FieldSpec("tool_pose", "bin f64[7]", "m, quaternion", "world",
                  doc="engine's (virtual) tool pose at env_time_s: x y z qw qx qy qz; the pose the contacts "
                      "were computed at (the server locates the reported features on the tool with it)"),
        FieldSpec("contact_count", "u16", doc="n, 0 <= n <= granted max_contacts"),
        FieldSpec("contact_keys", "bin i64[n*3]", "-", "-",
                  doc="n keys, row-major: (tool_link, env_body, feature) per contact; unique"),
        FieldSpec("contact_data", "bin f64[n*8]", "see Contact columns", "world",
                  doc="structure of arrays: position n*3, normal n*3, separation n, v_constr n"),
        FieldSpec("tool_joint_position", "bin f64[J]", "rad or m", "-", default=b"", since_minor=1,
                  doc="linkage: the engine's joint positions at env_time_s (links 1..L-1 in link order; with "
                      "tool_pose, the root's: the configuration the contacts were computed at); others: empty "
                      "or absent"),
    ),
)

PROXY_STATE = MessageSpec(
    "ProxyState", MessageType.PROXY_STATE, "server -> client", True,
    "Acknowledges a ContactUpdate with the proxy state, sent in the haptic step that applied it "
    "(at most one per accepted ContactUpdate).",
    (
        FieldSpec("seq", "u64", check="pos", doc="server's own sequence, 1, 2, 3, ...; newest wins"),
        FieldSpec("ack_seq", "u64", doc="seq of the newest ContactUpdate applied, 0 if none yet"),
        FieldSpec("server_time_s", "f64", "s", doc="server clock at the haptic step, since the session began"),
        FieldSpec("proxy_pose", "bin f64[7]", "m, quaternion", "world", doc="proxy tool-frame pose"),
        FieldSpec("proxy_twist", "bin f64[6]", "m/s, rad/s", "world",
                  doc="velocity of the tool-frame origin (3), angular velocity (3)"),
        FieldSpec("wrench", "bin f64[6]", "N, N m", "world",
                  sign="acts on the tool", doc="force (3) at the tool-frame origin, torque (3) about it, that the environment may apply to its tool"),
        FieldSpec("joint_position", "bin f64[J]", "rad or m", "-",
                  doc="linkage: q of links 1..L-1 in link order; others: empty"),
        FieldSpec("joint_velocity", "bin f64[J]", "rad/s or m/s", "-", doc="linkage: dq/dt, same order; others: empty"),
        FieldSpec("joint_effort", "bin f64[J]", "N m or N", "-", sign="positive along +q",
                  doc="linkage: joint effort the environment may apply; others: empty"),
        FieldSpec("server_state", "u8", check="enum", enum=ServerState, default=0, since_minor=2,
                  doc="ServerState: 1 idle, 2 engaged, 3 fading, 4 fault (0: not reported); follow the proxy "
                      "only while engaged: otherwise it is held and not rendered"),
    ),
)

HEARTBEAT = MessageSpec(
    "Heartbeat", MessageType.HEARTBEAT, "both", True,
    "Keeps a quiet session alive: sent when nothing else was sent for heartbeat_interval_s.",
    (
        FieldSpec("seq", "u64", check="pos", doc="per sender, 1, 2, 3, ...; its own sequence"),
        FieldSpec("time_s", "f64", "s", doc="sender's clock (informative)"),
    ),
)

BYE = MessageSpec(
    "Bye", MessageType.BYE, "both", False,
    "Ends the session. Sent 3 times in a row (one may be lost); the receiver ends the session "
    "at the first and counts the repeats as unknown-session packets.",
    (
        FieldSpec("code", "u16", doc="ErrorCode 60-79"),
        FieldSpec("reason", "str", doc="human-readable reason"),
    ),
)

ERROR = MessageSpec(
    "Error", MessageType.ERROR, "both", False,
    "Reports a packet the sender received and dropped. Rate-limited (at most error_rate_per_s per "
    "session); never answered with another Error.",
    (
        FieldSpec("code", "u16", doc="ErrorCode 1-39"),
        FieldSpec("field", "str", doc="name of the offending field, '' if none"),
        FieldSpec("detail", "str", doc="human-readable detail"),
        FieldSpec("ref_type", "u8", doc="type id of the dropped packet, 0 if unknown"),
        FieldSpec("ref_seq", "u64", doc="its seq if it had one, else 0"),
    ),
)

MESSAGES: tuple[MessageSpec, ...] = (HELLO, WELCOME, REJECT, CONTACT_UPDATE, PROXY_STATE, HEARTBEAT, BYE, ERROR)
MESSAGES_BY_ID: dict[int, MessageSpec] = {int(m.type_id): m for m in MESSAGES}


def check_declarations(messages: tuple[MessageSpec, ...] = MESSAGES) -> None:
    """Raise ``ValueError`` if a declaration breaks the versioning rules (run by the tests)."""
    ids = set()
    for m in messages:
        if m.type_id in ids:
            raise ValueError(f"{m.name}: duplicate type id {int(m.type_id)}")
        ids.add(m.type_id)
        names = [f.name for f in m.fields]
        if len(names) != len(set(names)):
            raise ValueError(f"{m.name}: duplicate field names")
        last_minor = 0
        for f in m.fields:
            if f.since_minor < last_minor:
                raise ValueError(f"{m.name}.{f.name}: fields must be in order of since_minor (append only)")
            last_minor = f.since_minor
            if f.since_minor > 0 and f.default is REQUIRED:
                raise ValueError(f"{m.name}.{f.name}: a field added in minor {f.since_minor} needs a default")
            if f.check == "enum" and f.enum is None:
                raise ValueError(f"{m.name}.{f.name}: check 'enum' needs enum")
