"""Render the generated parts of SPEC.md from the message declarations.

``python -m hapticproxy.protocol.spec --write`` rewrites the blocks between the marker comments
in ``protocol/SPEC.md``; ``--check`` exits 1 if SPEC.md is out of date (a test does the same).
Nothing outside the markers is touched.
"""
from __future__ import annotations

import argparse
import sys
from enum import IntEnum
from pathlib import Path

import msgpack
import numpy as np

from . import devlink as dl
from .codec import Codec, Limits
from .messages import (
    CONTACT_COLUMNS,
    CONTACT_FLOATS,
    HEADER,
    KEY_COLUMNS,
    LINK_FIELDS,
    MAX_ABS_FLOAT,
    MESSAGES,
    PROTOCOL_MAJOR,
    PROTOCOL_MINOR,
    REQUIRED,
    TOOL_KIND_NAMES,
    UNIT_TOLERANCE,
    ErrorCode,
    FieldDoc,
    JointType,
    ServerState,
    ToolKind,
)
from .session import HMAC_TAG_BYTES, ClientConfig, ServerConfig

SPEC_PATH = Path(__file__).with_name("SPEC.md")
BLOCKS = ("tables", "example", "devlink")


def _begin(name: str) -> str:
    return f"<!-- BEGIN GENERATED: {name} (python -m hapticproxy.protocol.spec --write) -->"


def _end(name: str) -> str:
    return f"<!-- END GENERATED: {name} -->"


def _cell(text: object) -> str:
    return str(text).replace("|", "\\|").replace("\n", " ") or " "


def _table(head: list[str], rows: list[list[object]]) -> str:
    out = ["| " + " | ".join(head) + " |", "|" + "|".join(" --- " for _ in head) + "|"]
    out += ["| " + " | ".join(_cell(c) for c in row) + " |" for row in rows]
    return "\n".join(out)


def _field_rows(fields: tuple[FieldDoc, ...], first_index: int) -> list[list[object]]:
    rows = []
    for i, f in enumerate(fields):
        rule = {"pos": "> 0", "nonneg": ">= 0", "unit": "unit", "enum": "enum"}.get(f.check, "")
        d = f.default
        default = ("required" if d is REQUIRED else str(int(d)) if isinstance(d, IntEnum)
                   else f"{d:g}" if isinstance(d, float) else repr(d))
        rows.append([first_index + i, f"`{f.name}`", f"`{f.type}`", f.unit, f.frame, f.sign or " ", rule or " ",
                     f"{PROTOCOL_MAJOR}.{f.since_minor}", default, f.doc])
    return rows


_FIELD_HEAD = ["#", "field", "wire type", "unit", "frame", "sign", "rule", "since", "default", "meaning"]
_DEFAULTS_HEAD = ["name", "default", "meaning"]


def _enum_table(enum: type[IntEnum], head: list[str], docs: dict, name=lambda v: v.name.lower()) -> str:
    """One row per member of ``enum``, in order: its value, ``name(member)`` and its ``docs`` entry
    (a member without one is a KeyError, so a new member cannot go undocumented)."""
    return _table(head, [[int(v), name(v), docs[v]] for v in enum])


def _attribute_rows(defaults: object, docs: dict[str, str]) -> list[list[object]]:
    """Rows of a defaults table: each attribute named in ``docs``, its value in ``defaults``, its meaning."""
    return [[name, getattr(defaults, name), doc] for name, doc in docs.items()]


def render_tables() -> str:
    parts = [f"Protocol version of these tables: **{PROTOCOL_MAJOR}.{PROTOCOL_MINOR}**.", ""]
    parts += ["### Message types", ""]
    parts.append(_table(["type_id", "message", "direction", "sequence-numbered", "fields", "purpose"], [
        [int(m.type_id), f"`{m.name}`", m.direction, "yes" if m.realtime else "no", len(m.fields), m.doc]
        for m in MESSAGES]))
    parts += ["", "### Header (elements 0-4 of every packet)", ""]
    parts.append(_table(_FIELD_HEAD, _field_rows(HEADER, 0)))
    for m in MESSAGES:
        parts += ["", f"### {m.name} (type_id {int(m.type_id)}, {m.direction})", "", m.doc, ""]
        if m.frozen_prefix:
            parts += [f"Frozen across major versions: header and fields {HEADER.__len__()}-{len(HEADER) + m.frozen_prefix - 1}.", ""]
        parts.append(_table(_FIELD_HEAD, _field_rows(m.fields, len(HEADER))))
    parts += ["", "### Link record (one element of `Hello.links`, a msgpack array)", ""]
    parts.append(_table(_FIELD_HEAD, _field_rows(LINK_FIELDS, 0)))
    parts += ["", "### Contact columns", "",
              "`contact_keys`: n rows of these int64, row-major (24 bytes per contact):", ""]
    parts.append(_table(["int64 #", "column", "meaning"], [[i, f"`{c.name}`", c.doc] for i, c in enumerate(KEY_COLUMNS)]))
    parts += ["", f"`contact_data`: {CONTACT_FLOATS} float64 per contact as a structure of arrays: each column "
              "block holds all n contacts before the next block starts.", ""]
    rows, offset = [], 0
    for c in CONTACT_COLUMNS:
        rows.append([f"`{c.name}`", f"{offset} n" if offset else "0", f"n x {c.width}" if c.width > 1 else "n",
                     c.unit, c.frame, c.sign or " ", c.doc])
        offset += c.width
    parts.append(_table(["block", "first float64 (index)", "shape", "unit", "frame", "sign", "meaning"], rows))
    parts += ["", "### Enumerations", ""]
    parts.append(_enum_table(ToolKind, ["tool_kind", "name", "meaning"], _TOOL_KIND_DOCS,
                             lambda k: f"`{TOOL_KIND_NAMES[k]}`"))
    parts += [""]
    parts.append(_enum_table(JointType, ["joint_type", "name", "q"], _JOINT_TYPE_DOCS))
    parts += [""]
    parts.append(_enum_table(ServerState, ["server_state", "name", "meaning"], _STATE_DOCS))
    parts += ["", "### Error codes (Error.code, Reject.code, Bye.code)", ""]
    parts.append(_enum_table(ErrorCode, ["code", "name", "meaning"], _CODE_DOCS, lambda c: f"`{c.name}`"))
    parts += ["", "### Limits and defaults (this implementation; a peer may choose its own limits)", ""]
    parts.append(_table(_DEFAULTS_HEAD, _attribute_rows(Limits(), {
        "max_packet_bytes": "larger datagrams are dropped before any unpacking (plus the HMAC tag in HMAC mode)",
        "max_contacts": "decoder bound on contact_count; the granted capacity is <= this",
        "max_str_bytes": "longest UTF-8 string (msgpack max_str_len)",
        "max_links": "most links in Hello.links and values in a joint array",
        "max_bin_bytes": "msgpack max_bin_len (derived)",
        "max_array_len": "msgpack max_array_len (derived); maps and ext types: none allowed",
    }) + [
        ["unit tolerance", f"{UNIT_TOLERANCE:g}", "| \\|x\\| - 1 | for normals, axes, quaternions"],
        ["float bound", f"{MAX_ABS_FLOAT:g}", "every float must be finite with \\|x\\| <= this"],
        ["HMAC tag", f"{HMAC_TAG_BYTES} bytes", "truncated HMAC-SHA256 appended in shared-secret mode"],
    ] + _attribute_rows(ServerConfig(), {
        "haptic_rate_hz": "server default, reported in Welcome",
        "heartbeat_interval_s": "server default, granted in Welcome",
        "silence_timeout_s": "server default, granted in Welcome",
        "error_rate_per_s": "Error replies per session (token bucket, same burst)",
        "workspace_extent_m": "server default scene bound, granted in Welcome (1.2)",
        "max_constraint_speed_m_per_s": "server default scene bound, granted in Welcome (1.2)",
        "max_separation_m": "server default scene bound, granted in Welcome (1.2)",
        "max_seq_jump": "largest forward jump of a seq the server accepts (else Error SEQ_JUMP)",
    }) + _attribute_rows(ClientConfig(), {
        "hello_retry_s": "client resends Hello this often while handshaking",
    })))
    return "\n".join(parts)


_TOOL_KIND_DOCS = {
    ToolKind.ONE_DOF: "translation along Hello.axis only",
    ToolKind.PLANAR: "translation in world x-y, rotation about +z",
    ToolKind.SPATIAL: "free rigid body (6 DOF)",
    ToolKind.LINKAGE: "kinematic tree in Hello.links; the hand holds Hello.held_link",
}

_JOINT_TYPE_DOCS = {
    JointType.ROOT: "none (link 0 only, floating base = tool pose)",
    JointType.REVOLUTE: "rad, right-handed about joint_axis",
    JointType.PRISMATIC: "m, along joint_axis",
}


_STATE_DOCS = {
    ServerState.UNKNOWN: "not reported (a 1.0 or 1.1 server); treat as engaged",
    ServerState.IDLE: "no session drives the model; nothing is rendered",
    ServerState.ENGAGED: "the proxy is rendered to the device, also while the force ramps in: follow it",
    ServerState.FADING: "the force fades to zero (environment silent, session ending, server stopping); the proxy is held",
    ServerState.FAULT: "output off after a fault; the proxy is held until the server recovers or is re-armed",
}

_CODE_DOCS = {
    ErrorCode.OVERSIZE: "datagram longer than max_packet_bytes; dropped before unpacking",
    ErrorCode.MALFORMED: "not exactly one msgpack object, a msgpack limit exceeded, bad UTF-8, map or ext present",
    ErrorCode.BAD_HEADER: "not an array starting with 5 unsigned header integers; or a Welcome with session_id/token 0",
    ErrorCode.UNKNOWN_MAJOR: "header major not spoken by the receiver (a Hello is answered by Reject UNSUPPORTED_VERSION)",
    ErrorCode.UNKNOWN_TYPE: "type_id not in the message table",
    ErrorCode.MISSING_FIELD: "fewer fields than required (fields added in later minors take their defaults)",
    ErrorCode.WRONG_TYPE: "a field has the wrong msgpack type (e.g. str for int, array for bin; bool is never an int)",
    ErrorCode.NON_FINITE: "NaN or infinity in a float",
    ErrorCode.OUT_OF_RANGE: "number outside its range: seq 0, negative mass or inertia, non-PSD inertia, unknown enum, float bound",
    ErrorCode.NOT_UNIT: "normal, axis or quaternion not unit within the tolerance",
    ErrorCode.BAD_SHAPE: "array or bin of the wrong length; string too long",
    ErrorCode.TOO_MANY_CONTACTS: "contact_count above max_contacts or above the granted capacity",
    ErrorCode.DUPLICATE_KEY: "the same contact key twice in one ContactUpdate",
    ErrorCode.BAD_TREE: "linkage tree inconsistent (root, parents, held_link) or links sent for a rigid tool",
    ErrorCode.BAD_MAC: "HMAC mode: tag missing or wrong (never answered)",
    ErrorCode.UNKNOWN_SESSION: "header session_id not known (never answered)",
    ErrorCode.BAD_TOKEN: "header token wrong for the session (never answered)",
    ErrorCode.WRONG_PEER: "right session and token from another source address (never answered)",
    ErrorCode.STALE: "seq older than the newest accepted in its stream (dropped, counted)",
    ErrorCode.DUPLICATE: "seq equal to the newest accepted (dropped, counted)",
    ErrorCode.UNEXPECTED: "message not valid in this direction or state",
    ErrorCode.OUT_OF_BOUNDS: "a value outside the scene bounds granted in Welcome (workspace, constraint speed, separation)",
    ErrorCode.UNUSABLE: "a contact the session's tool cannot have: a z normal on a planar tool, a tool link other than 0 on a rigid tool or beyond the linkage, joint positions for a rigid tool or of the wrong count",
    ErrorCode.SEQ_JUMP: "seq more than max_seq_jump ahead of the newest accepted (refused, so one bad seq cannot make every later packet stale)",
    ErrorCode.UNSUPPORTED_VERSION: "Reject: no common major version",
    ErrorCode.UNSUPPORTED_TOOL: "Reject: the server cannot simulate this tool kind",
    ErrorCode.UNSUPPORTED_UNITS: "Reject: units is not \"SI\"",
    ErrorCode.SERVER_FULL: "Reject: no free session slot",
    ErrorCode.INVALID_HELLO: "Reject: the Hello failed validation (reason names the field)",
    ErrorCode.BYE_NORMAL: "Bye: orderly end",
    ErrorCode.BYE_TIMEOUT: "Bye: nothing valid heard for silence_timeout_s",
    ErrorCode.BYE_SHUTDOWN: "Bye: the sender's process is stopping",
}


# ------------------------------------------------------------------------------ example
EXAMPLE = dict(
    session_id=0x12345678, token=0x0123456789ABCDEF, seq=42, env_time_s=1.25,
    tool_pose=(0.0, 0.0, 0.1, 1.0, 0.0, 0.0, 0.0),
    keys=[[0, 7, 1], [0, 7, 2]],
    position_m=[[0.1, 0.0, 0.0], [-0.1, 0.0, 0.0]],
    normal=[[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]],
    separation_m=[0.002, -0.001],
    v_constr_m_per_s=[0.0, 0.05],
)


def example_packet() -> bytes:
    e = EXAMPLE
    return Codec().encode_contact_update(
        e["session_id"], e["token"], e["seq"], e["env_time_s"], e["tool_pose"], np.array(e["keys"], np.int64),
        np.array(e["position_m"]), np.array(e["normal"]), np.array(e["separation_m"]), np.array(e["v_constr_m_per_s"]))


def _hexdump(data: bytes) -> str:
    lines = []
    for i in range(0, len(data), 16):
        chunk = data[i:i + 16]
        lines.append(f"{i:04x}  " + " ".join(f"{b:02x}" for b in chunk))
    return "\n".join(lines)


def render_example() -> str:
    e = EXAMPLE
    pkt = example_packet()
    obj = msgpack.unpackb(pkt)
    names = [h.name for h in HEADER] + ["seq", "env_time_s", "tool_pose", "contact_count", "contact_keys", "contact_data"]
    rows = [["-", "array header", pkt[:1].hex(), f"fixarray of {len(obj)} elements"]]
    offset = 1
    for name, value in zip(names, obj):
        enc = msgpack.packb(value, use_bin_type=True)
        assert pkt[offset:offset + len(enc)] == enc
        if isinstance(value, bytes):
            shown = f"{enc[:3].hex() if enc[0] == 0xc5 else enc[:2].hex()} + {len(value)} bytes"
            meaning = {"tool_pose": "bin8, 7 float64 LE: x y z qw qx qy qz",
                       "contact_keys": "bin8, 2 x 3 int64 LE", "contact_data": "bin8, 16 float64 LE"}[name]
        else:
            shown = enc.hex()
            meaning = f"{value!r}"
        rows.append([offset, f"`{name}`", shown, meaning])
        offset += len(enc)
    assert offset == len(pkt)
    data = np.frombuffer(obj[10], "<f8")
    lines = [
        "A ContactUpdate with two contacts, as `hapticproxy` encodes it (any msgpack encoder that follows the "
        "wire-type rules produces an equally valid packet; integers may use any width):",
        "",
        "```text",
        f"session_id = {e['session_id']:#x}, token = {e['token']:#x}, seq = {e['seq']}, env_time_s = {e['env_time_s']}",
        f"tool_pose  = {list(e['tool_pose'])}",
        f"keys       = {e['keys']}",
        f"position_m = {e['position_m']}",
        f"normal     = {e['normal']}",
        f"separation_m = {e['separation_m']}, v_constr_m_per_s = {e['v_constr_m_per_s']}",
        "```",
        "",
        f"The {len(pkt)} bytes:",
        "",
        "```text",
        _hexdump(pkt),
        "```",
        "",
        _table(["offset", "element", "bytes (hex)", "meaning"], rows),
        "",
        "`contact_data` as float64, in order: " + ", ".join(f"{x:g}" for x in data.tolist()),
        "(positions x y z of contact 0 then 1; normals; separations; constraint velocities).",
    ]
    return "\n".join(lines)


# ------------------------------------------------------------------ the remote-device link
DEVLINK_EXAMPLE = dict(flags=dl.F_ENABLE, device_session=1_700_000_000_500_000_000,
                       server_session=1_700_000_000_000_000_000, epoch=1, engagements=1, seq=42, state_seq=41,
                       wrench=(0.5, -0.25, 0.0, 0.0, 0.0, 0.01))


_DEVICE_KIND_DOCS = {
    dl.DeviceKind.ONE_DOF: "translation along the device's axis only",
    dl.DeviceKind.PLANAR: "translation in world x-y, rotation about +z",
    dl.DeviceKind.SPATIAL: "6 DOF",
}


def render_devlink() -> str:
    """SPEC's tables of the remote-device link, from :mod:`.devlink`'s declaration."""
    parts = [f"Layout versions of these tables: STATE **{dl.STATE.version}**, COMMAND **{dl.COMMAND.version}** "
             f"(magic `{dl.MAGIC.decode()}`); STATE version {dl.STATE_V1.version} ({dl.STATE_V1.size} bytes) is the "
             f"same header and the row's first {dl.ROW_FLOATS_V1} floats. Every integer and float is little-endian, "
             "with no padding other than the declared pad bytes.", ""]
    parts.append(_table(["type", "datagram", "direction", "bytes", "purpose"], [
        [int(d.type_id), f"`{d.name}`", d.direction, d.size, d.doc] for d in dl.DATAGRAMS]))
    for d in dl.DATAGRAMS:
        parts += ["", f"#### {d.name} (type {int(d.type_id)}, {d.direction}, {d.size} bytes)", ""]
        parts.append(_table(["offset", "bytes", "wire type", "field", "unit", "meaning"], [
            [d.offsets[f.name], f.size, f.wire, " " if f.padding else f"`{f.name}`", f.unit, f.doc]
            for f in d.fields]))
    parts += ["", "#### Flags", ""]
    parts.append(_table(["datagram", "bit", "name", "meaning"], [
        ["STATE", 0, "`F_ARMED`", "the device's output is armed (it renders the commanded wrench)"],
        ["COMMAND", 0, "`F_ENABLE`", "render this wrench; clear: zero the output now (not a fault)"],
        ["both", "1-15", "-", "zero when sent, ignored when received"]]))
    parts += ["", "#### The state row (STATE.state, float64)", ""]
    parts.append(_table(["floats", "column", "unit", "meaning"], [
        [f"{c.start}" if c.width == 1 else f"{c.start}-{c.start + c.width - 1}", f"`{c.name}`", c.unit, c.doc]
        for c in dl.ROW_COLUMNS]))
    parts += ["", "#### Enumerations", ""]
    parts.append(_enum_table(dl.DeviceKind, ["kind", "name", "meaning"], _DEVICE_KIND_DOCS,
                             lambda k: f"`{dl.KIND_NAMES[k]}`"))
    parts += [""]
    parts.append(_enum_table(dl.DeviceFault, ["fault", "name", "meaning"], dl.FAULT_DOCS))
    parts += ["", "#### Defaults (this implementation)", ""]
    parts.append(_table(_DEFAULTS_HEAD, [
        ["listen port", dl.DEFAULT_PORT, "UDP port of the server driver (`[device] listen`)"],
        ["link_timeout_s", dl.DEFAULT_LINK_TIMEOUT_S, "server driver: no STATE for this long -> link fault"],
        ["watchdog_s", dl.DEFAULT_WATCHDOG_S, "device program: armed and no command accepted for this long -> zero, latched"],
        ["max datagram bytes", dl.MAX_DATAGRAM_BYTES, "longer datagrams are dropped unread (counted as malformed)"],
        ["max drain", dl.MAX_DRAIN, "datagrams one poll reads at most (a flood cannot stretch a step)"]]))
    from .device_conformance import DEVICE_RULES, SERVER_RULES

    parts += ["", "#### Conformance rules (`hapticproxy protocol check-device`, `check-device-server`)", ""]
    parts.append(_table(["check-device rule", "what the device program must do"],
                        [[f"`{k}`", v] for k, v in DEVICE_RULES.items()]))
    parts += [""]
    parts.append(_table(["check-device-server rule", "what the server driver must do"],
                        [[f"`{k}`", v] for k, v in SERVER_RULES.items()]))
    pkt = dl.COMMAND.pack(**DEVLINK_EXAMPLE)
    e = DEVLINK_EXAMPLE
    parts += ["", "#### Example: one COMMAND", "", "```text",
              f"flags = {e['flags']} (enable), device_session = {e['device_session']}, server_session = "
              f"{e['server_session']}",
              f"epoch = {e['epoch']}, engagements = {e['engagements']}, seq = {e['seq']}, state_seq = {e['state_seq']}",
              f"wrench = {list(e['wrench'])}", "```", "", f"The {len(pkt)} bytes:", "", "```text", _hexdump(pkt), "```"]
    return "\n".join(parts)


RENDERERS = {"tables": render_tables, "example": render_example, "devlink": render_devlink}


def render_block(name: str) -> str:
    return f"{_begin(name)}\n{RENDERERS[name]()}\n{_end(name)}"


def extract_block(text: str, name: str) -> str:
    start, end = text.find(_begin(name)), text.find(_end(name))
    if start < 0 or end < start:
        raise ValueError(f"SPEC.md has no generated block {name!r} (markers missing)")
    return text[start:end + len(_end(name))]


def updated_spec(text: str) -> str:
    for name in BLOCKS:
        text = text.replace(extract_block(text, name), render_block(name))
    return text


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m hapticproxy.protocol.spec",
                                     description="Regenerate or check the generated blocks of protocol/SPEC.md.")
    group = parser.add_mutually_exclusive_group()
    group.add_argument("--write", action="store_true", help="rewrite the blocks in SPEC.md")
    group.add_argument("--check", action="store_true", help="exit 1 if SPEC.md is out of date")
    args = parser.parse_args(argv)
    text = SPEC_PATH.read_text(encoding="utf-8")
    new = updated_spec(text)
    if args.write:
        if new != text:
            SPEC_PATH.write_text(new, encoding="utf-8")
            print(f"updated {SPEC_PATH}")
        else:
            print(f"{SPEC_PATH} already up to date")
        return 0
    if args.check:
        if new != text:
            print(f"{SPEC_PATH} is out of date: run python -m hapticproxy.protocol.spec --write", file=sys.stderr)
            return 1
        print(f"{SPEC_PATH} is up to date")
        return 0
    print(render_tables())
    print()
    print(render_example())
    return 0


if __name__ == "__main__":
    sys.exit(main())
