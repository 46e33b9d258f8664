"""The shared vocabulary of protocol v1, defined once: message types, tool kinds, joint types,
server states, error codes, and the names SPEC.md and the configs use for them.

Both the server and the clients import these (``server`` and ``clients`` never import each other).
Every enumeration has one name map in each direction: ``TOOL_KIND_NAMES[ToolKind.PLANAR] ==
"planar"`` and ``TOOL_KINDS_BY_NAME["planar"] is ToolKind.PLANAR``; likewise for joint types and
server states. The values are the wire values.
"""
from __future__ import annotations

from enum import IntEnum

__all__ = [
    "ErrorCode",
    "JOINT_TYPES_BY_NAME",
    "JOINT_TYPE_NAMES",
    "JointType",
    "MessageType",
    "SERVER_STATES_BY_NAME",
    "SERVER_STATE_NAMES",
    "ServerState",
    "TOOL_KINDS_BY_NAME",
    "TOOL_KIND_NAMES",
    "ToolKind",
]


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


#: SPEC's (and the configs') name of each tool kind.
TOOL_KIND_NAMES: dict[ToolKind, str] = {
    ToolKind.ONE_DOF: "1dof",
    ToolKind.PLANAR: "planar",
    ToolKind.SPATIAL: "spatial",
    ToolKind.LINKAGE: "linkage",
}
#: The tool kind of each name (the inverse of :data:`TOOL_KIND_NAMES`).
TOOL_KINDS_BY_NAME: dict[str, ToolKind] = {v: k for k, v in TOOL_KIND_NAMES.items()}


#: The rigid tool kinds by name, which are also the device kinds (a linkage rides on a planar or
#: a spatial device).
RIGID_TOOL_KINDS: tuple[str, ...] = ("1dof", "planar", "spatial")
DEVICE_KINDS: tuple[str, ...] = RIGID_TOOL_KINDS

#: Update policies of the local model (``[model] policy``): ``rigid`` replaces the geometry at
#: each update (the intermediate-representation baseline, the paper's eq. 1); ``lm0`` deforms the
#: proxy without epsilon-active geometry; ``lm`` deforms with it (eqs. 4-6); ``deformation`` is
#: another name for ``lm``.
POLICIES: tuple[str, ...] = ("rigid", "lm0", "lm", "deformation")
#: Controllers between the device and the proxy (``[controller] type``).
CONTROLLERS: tuple[str, ...] = ("four_channel", "coupler", "direct")


class JointType(IntEnum):
    """Joint of a linkage link to its parent (``Hello.links[i].joint_type``)."""

    ROOT = 0  # link 0 only: no joint, the floating base whose pose is the tool pose
    REVOLUTE = 1  # rotation by q rad about joint_axis
    PRISMATIC = 2  # translation by q m along joint_axis


#: SPEC's name of each joint type ("root", "revolute", "prismatic").
JOINT_TYPE_NAMES: dict[JointType, str] = {j: j.name.lower() for j in JointType}
#: The joint type of each name (the inverse of :data:`JOINT_TYPE_NAMES`).
JOINT_TYPES_BY_NAME: dict[str, JointType] = {v: k for k, v in JOINT_TYPE_NAMES.items()}


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


#: SPEC's name of each server state ("unknown", "idle", "engaged", "fading", "fault").
SERVER_STATE_NAMES: dict[ServerState, str] = {s: s.name.lower() for s in ServerState}
#: The server state of each name (the inverse of :data:`SERVER_STATE_NAMES`).
SERVER_STATES_BY_NAME: dict[str, ServerState] = {v: k for k, v in SERVER_STATE_NAMES.items()}


class ErrorCode(IntEnum):
    """Codes carried by ``Error``, ``Reject`` and ``Bye``, and by ``ProtocolError``.

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
    OUT_OF_BOUNDS = 26  # a value outside the scene bounds the server granted in Welcome
    UNUSABLE = 27  # a contact the session's tool cannot have (z normal on a planar tool, ...)
    SEQ_JUMP = 28  # sequence number too far ahead of the newest accepted
    UNSUPPORTED_VERSION = 40  # no common major version
    UNSUPPORTED_TOOL = 41  # tool kind the server cannot simulate
    UNSUPPORTED_UNITS = 42  # Hello.units is not "SI"
    SERVER_FULL = 43  # no free session slot
    INVALID_HELLO = 44  # Hello decoded but its content is refused
    BYE_NORMAL = 60  # orderly shutdown requested by the sender
    BYE_TIMEOUT = 61  # the sender heard nothing within silence_timeout_s
    BYE_SHUTDOWN = 62  # the sender's process is stopping
