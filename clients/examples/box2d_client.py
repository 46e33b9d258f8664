#!/usr/bin/env python3
"""A hapticproxy environment client for Box2D, written from ``protocol/SPEC.md`` alone.

    python clients/examples/box2d_client.py --connect udp://127.0.0.1:9870

The scene is planar: a box tool (60 x 30 mm, 0.2 kg) held 2 mm above a floor whose surface is
y = 0, and a loose box on the floor 0.1 m to the right. Box2D steps its own world at 60 Hz; the
tool is a dynamic body without gravity, driven towards the newest rendered proxy by a
velocity-level drive (SPEC 8.4); after every step the client reports the contacts of the tool
inflated by the granted epsilon (SPEC 8.6, 8.7) in one ContactUpdate.

It needs Python, numpy, msgpack and Box2D (``pip install box2d``) and nothing of hapticproxy:
the wire format is coded here from SPEC sections 3-5 and 9. It is an example, not a package
module: nothing imports it. Exit status 0 after ``--duration`` or Ctrl-C, 1 when the server
rejects the session, 2 for bad arguments.

Mapping notes (SPEC 8.7), as they apply to Box2D:
- Units: Box2D is tuned for objects of 0.1-10 of its units and keeps a 0.005-unit contact slop
  and a 0.01-unit polygon skin; the world is built in centimetres (``SCALE`` units per metre) so
  those are 0.05 mm and 0.1 mm. Everything on the wire is SI. The skin counts as part of every
  surface: the floor's polygon lies one skin below y = 0, the tool's polygon one skin inside
  its 60 x 30 mm.
- Contacts: ``b2CollidePolygons`` on a query-only copy of the tool's polygon whose radius is the
  skin plus epsilon (the solver never sees the inflation). Box2D's world manifold gives the
  midpoints between the two (inflated) surfaces and a normal from the tool to the environment:
  the normal is negated, and the midpoint moved by half the separation onto the environment.
  Feature ids are Box2D's ``b2ContactID.key`` (tool-side and environment-side vertex/face
  indices); the body id is the environment body's index in this scene.
"""
from __future__ import annotations

import argparse
import math
import secrets
import socket
import sys
import time

import Box2D
import msgpack
import numpy as np

SCALE = 100.0  # Box2D units per metre (1 unit = 1 cm)
SKIN_U = Box2D.b2_polygonRadius  # Box2D's polygon skin [units]
TOOL_HALF_M = (0.030, 0.015)  # the tool's outer half sizes [m]
TOOL_MASS_KG = 0.2
TOOL_START_M = (0.0, TOOL_HALF_M[1] + 0.002)  # 2 mm above the floor
FLOOR_HALF_M = (0.30, 0.05)
LOOSE_HALF_M = (0.02, 0.02)
LOOSE_AT_M = (0.12, LOOSE_HALF_M[1])
MAX_SPEED_M_PER_S = 1.0  # the drive's cap (Box2D moves at most 2 units per step anyway)
EXTRAPOLATE_MAX_S = 0.1

# ----------------------------------------------------------------------------- protocol (SPEC)
MAJOR, MINOR = 1, 2
HELLO, WELCOME, REJECT, CONTACT_UPDATE, PROXY_STATE, HEARTBEAT, BYE, ERROR = range(1, 9)
TOOL_PLANAR = 2
ENGAGED, UNKNOWN = 2, 0
# Error codes (SPEC 9)
MALFORMED, BAD_HEADER, UNKNOWN_MAJOR, UNKNOWN_TYPE, MISSING_FIELD, WRONG_TYPE, NON_FINITE = 2, 3, 4, 5, 6, 7, 8
OUT_OF_RANGE, NOT_UNIT, BAD_SHAPE, UNEXPECTED = 9, 10, 11, 25
BYE_NORMAL, BYE_TIMEOUT = 60, 61
MAX_PACKET_BYTES = 8192
FLOAT_BOUND = 1e9
UNIT_TOL = 1e-6
HELLO_RETRY_S = 0.25
RECONNECT_DELAY_S = 1.0
ERRORS_PER_S = 10.0
_NAMES = {HELLO: "Hello", WELCOME: "Welcome", REJECT: "Reject", CONTACT_UPDATE: "ContactUpdate",
          PROXY_STATE: "ProxyState", HEARTBEAT: "Heartbeat", BYE: "Bye", ERROR: "Error"}


class Bad(Exception):
    """A received packet that fails validation: ``code`` and ``field`` as in SPEC 7 and 9."""

    def __init__(self, code: int, field: str, detail: str) -> None:
        super().__init__(detail)
        self.code, self.field = code, field


def _is_int(v) -> bool:
    return type(v) is int  # a bool is never an int (SPEC 3, wire types)


def _f64(v, name: str) -> float:
    if type(v) not in (float, int):
        raise Bad(WRONG_TYPE, name, f"{name} must be a number")
    v = float(v)
    if not math.isfinite(v):
        raise Bad(NON_FINITE, name, f"{name} is not finite")
    if abs(v) > FLOAT_BOUND:
        raise Bad(OUT_OF_RANGE, name, f"{name} beyond 1e9")
    return v


def _bin_f64(v, k: int | None, name: str) -> np.ndarray:
    if type(v) is not bytes:
        raise Bad(WRONG_TYPE, name, f"{name} must be a bin")
    if (k is not None and len(v) != 8 * k) or len(v) % 8:
        raise Bad(BAD_SHAPE, name, f"{name} has {len(v)} bytes")
    a = np.frombuffer(v, "<f8")
    if not np.all(np.isfinite(a)):
        raise Bad(NON_FINITE, name, f"{name} is not finite")
    if a.size and np.max(np.abs(a)) > FLOAT_BOUND:
        raise Bad(OUT_OF_RANGE, name, f"{name} beyond 1e9")
    return a


def parse(data: bytes) -> tuple[list, int, int, int]:
    """One datagram -> (fields after the header, type_id, session_id, token). Raises Bad, with
    ``.header`` set when the header could be read (so the packet can be attributed)."""
    if len(data) > MAX_PACKET_BYTES:
        raise Bad(1, "", "oversize")
    try:
        obj = msgpack.unpackb(data, raw=False, use_list=True, max_bin_len=MAX_PACKET_BYTES, max_str_len=256,
                              max_array_len=64, max_map_len=0, max_ext_len=0)
    except Exception as exc:  # noqa: BLE001 - any msgpack failure is a malformed packet
        raise Bad(MALFORMED, "", f"not one msgpack object: {exc}") from None
    if type(obj) is not list or len(obj) < 5 or not all(_is_int(x) and x >= 0 for x in obj[:5]):
        raise Bad(BAD_HEADER, "", "not an array starting with 5 header integers")
    major, _minor, type_id, session_id, token = obj[:5]
    header = (type_id, session_id, token)
    if major != MAJOR:
        err = Bad(UNKNOWN_MAJOR, "major", f"major {major}")
        err.header = header
        raise err
    return obj[5:], type_id, session_id, token


def pack(type_id: int, session_id: int, token: int, *fields) -> bytes:
    return msgpack.packb([MAJOR, MINOR, type_id, session_id, token, *fields], use_bin_type=True)


def decode_proxy_state(f: list, last_sent_seq: int) -> dict:
    """SPEC 9 ProxyState fields (after the header), validated (SPEC 7 step 5)."""
    if len(f) < 9:
        raise Bad(MISSING_FIELD, "", f"{len(f)} fields")
    seq, ack = f[0], f[1]
    if not (_is_int(seq) and seq >= 1 and _is_int(ack) and ack >= 0):
        raise Bad(OUT_OF_RANGE, "seq", "seq/ack_seq")
    if ack > last_sent_seq:
        raise Bad(UNEXPECTED, "ack_seq", "acknowledges an update never sent")
    _f64(f[2], "server_time_s")
    pose = _bin_f64(f[3], 7, "proxy_pose")
    if abs(float(np.linalg.norm(pose[3:])) - 1.0) > UNIT_TOL:
        raise Bad(NOT_UNIT, "proxy_pose", "quaternion not unit")
    twist = _bin_f64(f[4], 6, "proxy_twist")
    _bin_f64(f[5], 6, "wrench")  # the hand's wrench: already in the proxy's motion, not applied (SPEC 8.4)
    for i, name in ((6, "joint_position"), (7, "joint_velocity"), (8, "joint_effort")):
        _bin_f64(f[i], None, name)
    state = f[9] if len(f) > 9 else UNKNOWN  # 1.2; absent from a 1.0/1.1 server: treat as engaged
    if not (_is_int(state) and 0 <= state <= 4):
        raise Bad(OUT_OF_RANGE, "server_state", "server_state")
    return dict(seq=seq, ack_seq=ack, pose=pose.copy(), twist=twist.copy(), state=state)


# ----------------------------------------------------------------------------------- the world
def _box(body, half_m, **kw):
    hx, hy = half_m
    return body.CreatePolygonFixture(box=(hx * SCALE - SKIN_U, hy * SCALE - SKIN_U), **kw)


class World:
    """The Box2D world: floor (body 1), loose box (body 2), the tool (not an environment body)."""

    def __init__(self) -> None:
        self.world = Box2D.b2World(gravity=(0.0, -9.81 * SCALE), doSleep=True)
        floor = self.world.CreateStaticBody(position=(0.0, -FLOOR_HALF_M[1] * SCALE))
        _box(floor, FLOOR_HALF_M, friction=0.5)
        loose = self.world.CreateDynamicBody(position=(LOOSE_AT_M[0] * SCALE, LOOSE_AT_M[1] * SCALE))
        _box(loose, LOOSE_HALF_M, density=0.5, friction=0.5)
        #: environment bodies by the id sent as env_body
        self.env = {1: floor, 2: loose}
        hx, hy = TOOL_HALF_M
        area_u2 = (2 * hx * SCALE) * (2 * hy * SCALE)
        self.tool = self.world.CreateDynamicBody(position=(TOOL_START_M[0] * SCALE, TOOL_START_M[1] * SCALE),
                                                 bullet=True)
        self.tool_fixture = _box(self.tool, TOOL_HALF_M, density=TOOL_MASS_KG / area_u2, friction=0.5)
        self.tool.gravityScale = 0.0  # the proxy's motion already has every load (SPEC 8.4)
        self.tool.linearDamping = self.tool.angularDamping = 0.0
        self.query = Box2D.b2PolygonShape(box=(hx * SCALE - SKIN_U, hy * SCALE - SKIN_U))
        self.epsilon_m = 0.0
        self.time_s = 0.0

    @staticmethod
    def hello_tool() -> dict:
        """The tool as the Hello describes it: tool frame = the box's centre = its COM."""
        hx, hy = TOOL_HALF_M
        izz = TOOL_MASS_KG * ((2 * hx) ** 2 + (2 * hy) ** 2) / 12.0
        return dict(mass_kg=TOOL_MASS_KG, com_m=[0.0, 0.0, 0.0], inertia_kg_m2=[izz, izz, izz, 0.0, 0.0, 0.0])

    def set_epsilon(self, epsilon_m: float) -> None:
        self.epsilon_m = float(epsilon_m)
        self.query.radius = SKIN_U + self.epsilon_m * SCALE

    def tool_pose(self) -> np.ndarray:
        p, a = self.tool.position, self.tool.angle
        return np.array([p.x / SCALE, p.y / SCALE, 0.0, math.cos(a / 2), 0.0, 0.0, math.sin(a / 2)])

    def drive(self, target: np.ndarray | None, twist: np.ndarray | None, dt: float) -> None:
        """Velocity-level drive towards ``target`` (x y z qw qx qy qz, SI), the twist fed
        forward; ``None``: hold the tool where it is."""
        tool = self.tool
        if target is None:
            tool.linearVelocity = (0.0, 0.0)
            tool.angularVelocity = 0.0
            return
        p = tool.position
        vx = twist[0] + (target[0] - p.x / SCALE) / dt
        vy = twist[1] + (target[1] - p.y / SCALE) / dt
        speed = math.hypot(vx, vy)
        if speed > MAX_SPEED_M_PER_S:
            vx, vy = vx * MAX_SPEED_M_PER_S / speed, vy * MAX_SPEED_M_PER_S / speed
        theta = 2.0 * math.atan2(target[6], target[3])
        err = (theta - tool.angle + math.pi) % (2 * math.pi) - math.pi
        tool.linearVelocity = (vx * SCALE, vy * SCALE)
        tool.angularVelocity = twist[5] + err / dt

    def step(self, dt: float) -> None:
        self.world.Step(dt, 8, 3)
        self.time_s += dt

    def contacts(self, max_contacts: int):
        """The epsilon-inflated tool's contacts: keys (n, 3), c_p (n, 3), normal (n, 3), d (n,),
        v_constr (n,), SI, at most ``max_contacts`` (the deepest)."""
        rows = {}
        eps_u = self.epsilon_m * SCALE
        xf_t = self.tool.transform
        r_t = self.query.radius
        for body_id, body in self.env.items():
            for fx in body.fixtures:
                m = Box2D.b2Manifold()
                Box2D.b2CollidePolygons(m, self.query, xf_t, fx.shape, body.transform)
                if m.pointCount == 0:
                    continue
                r_e = fx.shape.radius
                wm = Box2D.b2WorldManifold()
                wm.Initialize(m, xf_t, r_t, body.transform, r_e)
                n_te = np.array(wm.normal)  # Box2D: from the tool (A) to the environment (B)
                if m.type_ == Box2D.b2Manifold.e_faceA:  # the tool's face is the reference
                    plane, normal, ref, inc = m.localPoint, m.localNormal, self.tool, body
                else:  # e_faceB: the environment's face is the reference
                    plane, normal, ref, inc = m.localPoint, m.localNormal, body, self.tool
                n_ref = np.array(ref.GetWorldVector(normal))
                p_ref = np.array(ref.GetWorldPoint(plane))
                for i in range(m.pointCount):
                    mp = m.points[i]
                    clip = np.array(inc.GetWorldPoint(mp.localPoint))
                    s_u = float(np.dot(clip - p_ref, n_ref)) - r_t - r_e  # inflated separation [units]
                    n = -n_te  # SPEC: from the environment towards the tool
                    mid = np.array(wm.points[i])
                    c_u = mid - 0.5 * s_u * n  # the midpoint moved onto the environment (SPEC 8.7)
                    v = body.GetLinearVelocityFromWorldPoint((float(c_u[0]), float(c_u[1])))
                    d_m = (s_u + eps_u) / SCALE  # the real tool's separation (SPEC 8.6)
                    key = (0, body_id, int(mp.id.key))
                    if key not in rows or d_m < rows[key][2]:
                        rows[key] = (c_u / SCALE, n, d_m, float(np.dot((v.x, v.y), n)) / SCALE)
        ordered = sorted(rows.items(), key=lambda kv: kv[1][2])[:max_contacts]
        k = len(ordered)
        keys = np.array([kv[0] for kv in ordered], dtype="<i8").reshape(k, 3)
        pos = np.zeros((k, 3))
        nor = np.zeros((k, 3))
        for i, (_, (c, n, _, _)) in enumerate(ordered):
            pos[i, :2] = c
            nor[i, :2] = n / np.linalg.norm(n)
        d = np.array([kv[1][2] for kv in ordered], dtype="<f8")
        v = np.array([kv[1][3] for kv in ordered], dtype="<f8")
        return keys, pos, nor, d, v


# ------------------------------------------------------------------------------------ the client
def _advance(pose: np.ndarray, twist: np.ndarray, a_s: float) -> np.ndarray:
    """The planar pose advanced by the twist for a_s seconds (SPEC 8.4: extrapolate the target)."""
    out = pose.copy()
    out[:2] += twist[:2] * a_s
    theta = 2.0 * math.atan2(pose[6], pose[3]) + twist[5] * a_s
    out[3], out[6] = math.cos(theta / 2), math.sin(theta / 2)
    return out


class Client:
    def __init__(self, host: str, port: int, *, epsilon_m: float, max_contacts: int, rate_hz: float,
                 log) -> None:
        self.addr = (socket.gethostbyname(host), port)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setblocking(False)
        self.epsilon_m, self.max_contacts, self.rate_hz = epsilon_m, max_contacts, rate_hz
        self.log = log
        self.world = World()
        self.state = "idle"  # idle | handshaking | established | waiting
        self.rejected = ""
        self.next_attempt = 0.0
        self.contacts_seen = 0

    # ---------------------------------------------------------------- sending
    def send(self, packet: bytes) -> None:
        try:
            self.sock.sendto(packet, self.addr)
        except OSError:
            pass  # a lost datagram is the protocol's normal case
        self.last_tx = time.monotonic()

    def start(self) -> None:
        self.nonce = secrets.randbits(64) or 1
        tool = World.hello_tool()
        self.hello = pack(HELLO, 0, 0, self.nonce, [1, 0], [MAJOR, MINOR], f"box2d {Box2D.__version__} example",
                          "SI", TOOL_PLANAR, tool["mass_kg"], tool["com_m"], tool["inertia_kg_m2"], [1.0, 0.0, 0.0],
                          self.epsilon_m, self.max_contacts, self.rate_hz, [], 0)
        self.state = "handshaking"
        self.session_id = self.token = 0
        self.seq = self.hb_seq = 0
        self.proxy_seq = self.hb_rx_seq = 0
        self.proxy = None  # newest accepted ProxyState
        self.target = None  # the drive's target: (pose, twist, arrival time), or None (hold)
        self.sent_at = {}
        self.rtt_s = 0.0
        self.error_tokens = ERRORS_PER_S
        self.error_time = time.monotonic()
        self.send(self.hello)
        self.next_hello = time.monotonic() + HELLO_RETRY_S

    def close(self, code: int, reason: str) -> None:
        if self.state == "established":
            for _ in range(3):
                self.send(pack(BYE, self.session_id, self.token, code, reason))
        self.state = "waiting"
        self.next_attempt = time.monotonic() + RECONNECT_DELAY_S

    def error(self, err: Bad, ref_type: int, ref_seq: int = 0) -> None:
        """Answer an invalid packet of our session (rate-limited, never an Error with an Error)."""
        if ref_type == ERROR:
            return
        now = time.monotonic()
        self.error_tokens = min(ERRORS_PER_S, self.error_tokens + (now - self.error_time) * ERRORS_PER_S)
        self.error_time = now
        if self.error_tokens < 1.0:
            return
        self.error_tokens -= 1.0
        self.send(pack(ERROR, self.session_id, self.token, err.code, err.field[:64], str(err)[:200],
                       ref_type if 0 <= ref_type <= 255 else 0, ref_seq))

    # ---------------------------------------------------------------- receiving
    def receive_all(self) -> None:
        while True:
            try:
                data, addr = self.sock.recvfrom(65536)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                return
            self.receive(data, addr)

    def receive(self, data: bytes, addr) -> None:
        if addr != self.addr:
            return  # not the server
        try:
            fields, tid, sid, token = parse(data)
        except Bad as err:
            header = getattr(err, "header", None)
            if header and self.state == "established" and header[1:] == (self.session_id, self.token):
                self.error(err, header[0])
            return
        if tid in (WELCOME, REJECT):
            self.on_handshake(tid, sid, token, fields)
            return
        if self.state != "established" or (sid, token) != (self.session_id, self.token):
            return  # not provably from our session: dropped, never answered
        try:
            if tid == PROXY_STATE:
                ps = decode_proxy_state(fields, self.seq)
                if ps["seq"] <= self.proxy_seq:
                    return  # duplicate or stale: newest wins
                self.proxy_seq = ps["seq"]
                self.last_rx = time.monotonic()
                self.on_proxy(ps)
            elif tid == HEARTBEAT:
                if len(fields) < 2 or not (_is_int(fields[0]) and fields[0] >= 1):
                    raise Bad(MISSING_FIELD, "seq", "Heartbeat")
                _f64(fields[1], "time_s")
                if fields[0] > self.hb_rx_seq:
                    self.hb_rx_seq = fields[0]
                    self.last_rx = time.monotonic()
            elif tid == BYE:
                self.log(f"server ended the session (Bye {fields[0] if fields else '?'}: "
                         f"{fields[1] if len(fields) > 1 else ''}); reconnecting in {RECONNECT_DELAY_S:g} s")
                self.state = "waiting"
                self.next_attempt = time.monotonic() + RECONNECT_DELAY_S
            elif tid == ERROR:
                self.last_rx = time.monotonic()
                self.log(f"server Error {fields[:3]}")
            elif tid in _NAMES:
                raise Bad(UNEXPECTED, "type_id", f"{_NAMES[tid]} is not sent to a client")
            else:
                raise Bad(UNKNOWN_TYPE, "type_id", f"type {tid}")
        except Bad as err:
            self.error(err, tid, fields[0] if fields and _is_int(fields[0]) else 0)

    def on_handshake(self, tid: int, sid: int, token: int, f: list) -> None:
        if self.state != "handshaking" or not f or f[0] != self.nonce:
            return  # a repeated Welcome, or someone else's
        if tid == REJECT:
            self.rejected = f"code {f[1]}: {f[2]}" if len(f) > 2 else "rejected"
            self.state = "rejected"
            return
        if len(f) < 8 or sid == 0 or token == 0 or not isinstance(f[1], list) or f[1][0] != MAJOR:
            return
        self.session_id, self.token = sid, token
        eps, self.granted, hb, silence = float(f[3]), int(f[4]), float(f[5]), float(f[6])
        self.heartbeat_s, self.silence_s = hb, silence
        self.world.set_epsilon(eps)
        self.state = "established"
        self.last_rx = time.monotonic()
        note = f[11] if len(f) > 11 else ""
        self.log(f"session {sid:#010x} with {f[7]!r}: version {f[1][0]}.{f[1][1]}, epsilon {eps * 1e3:g} mm, "
                 f"max {self.granted} contacts" + (f" ({note})" if note else ""))

    def on_proxy(self, ps: dict) -> None:
        now = time.monotonic()
        sent = self.sent_at.pop(ps["ack_seq"], None)
        if sent is not None:
            self.rtt_s = now - sent
        if ps["state"] in (ENGAGED, UNKNOWN):  # follow only what the server renders (SPEC 8.4)
            self.target = (ps["pose"], ps["twist"], now)
        elif self.target is not None:
            self.target = None  # not rendered: the tool is held where it is
            self.log(f"server_state {ps['state']}: holding the tool")

    # ---------------------------------------------------------------- the step
    def tick(self, dt: float) -> None:
        w = self.world
        if self.target is None:
            w.drive(None, None, dt)
        else:
            pose, twist, arrival = self.target
            a = min(EXTRAPOLATE_MAX_S, self.rtt_s / 2 + (time.monotonic() - arrival) + dt)
            w.drive(_advance(pose, twist, a), twist, dt)
        w.step(dt)
        keys, pos, nor, d, v = w.contacts(self.granted)
        n = keys.shape[0]
        self.contacts_seen = max(self.contacts_seen, n)
        self.seq += 1
        data = b"".join(np.ascontiguousarray(a, "<f8").tobytes() for a in (pos, nor, d, v))
        self.send(pack(CONTACT_UPDATE, self.session_id, self.token, self.seq, w.time_s, w.tool_pose().tobytes(),
                       n, keys.tobytes(), data))
        self.sent_at[self.seq] = time.monotonic()
        if len(self.sent_at) > 256:
            self.sent_at.pop(min(self.sent_at))

    def run(self, duration_s: float | None) -> int:
        dt = 1.0 / self.rate_hz
        t_end = None if duration_s is None else time.monotonic() + duration_s
        next_step = time.monotonic()
        self.start()
        while t_end is None or time.monotonic() < t_end:
            self.receive_all()
            now = time.monotonic()
            if self.state == "rejected":
                self.log(f"server refused the session: {self.rejected}")
                return 1
            if self.state == "waiting":
                if now >= self.next_attempt:
                    self.start()
            elif self.state == "handshaking":
                if now >= self.next_hello:
                    self.send(self.hello)
                    self.next_hello = now + HELLO_RETRY_S
            elif self.state == "established":
                if now - self.last_rx >= self.silence_s:
                    self.log(f"server silent for {self.silence_s:g} s; reconnecting")
                    self.close(BYE_TIMEOUT, "no valid packet within silence_timeout_s")
                    continue
                if now >= next_step:
                    self.tick(dt)
                    next_step += dt
                    if now - next_step > 0.25:  # far behind (a stall): restart the schedule
                        next_step = now
                elif now - self.last_tx >= self.heartbeat_s:
                    self.hb_seq += 1
                    self.send(pack(HEARTBEAT, self.session_id, self.token, self.hb_seq, self.world.time_s))
            time.sleep(0.001)
        self.close(BYE_NORMAL, "client stopping")
        return 0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description="A Box2D environment client for hapticproxy (an example).")
    p.add_argument("--connect", default="udp://127.0.0.1:9870", help="server address, udp://HOST:PORT")
    p.add_argument("--epsilon", type=float, default=0.005, help="epsilon to request [m] (default 0.005)")
    p.add_argument("--max-contacts", type=int, default=8, help="contact capacity to request (default 8)")
    p.add_argument("--rate", type=float, default=60.0, help="engine step rate [Hz] (default 60, at least 20)")
    p.add_argument("--duration", type=float, default=None, help="stop after this many seconds")
    p.add_argument("--quiet", action="store_true", help="no messages on stderr")
    args = p.parse_args(argv)
    url = args.connect[len("udp://"):] if args.connect.startswith("udp://") else args.connect
    host, _, port = url.rpartition(":")
    if "://" in url or not host or not port.isdigit():
        p.error(f"--connect: expected udp://HOST:PORT, got {args.connect!r}")
    if not (math.isfinite(args.epsilon) and 0 <= args.epsilon < 0.1):
        p.error("--epsilon: metres in [0, 0.1)")
    if not 20 <= args.rate <= 1000 or not 1 <= args.max_contacts <= 64:
        p.error("--rate in [20, 1000] Hz, --max-contacts in [1, 64]")

    def log(msg: str) -> None:
        if not args.quiet:
            print(f"box2d_client: {msg}", file=sys.stderr, flush=True)

    client = Client(host, int(port), epsilon_m=args.epsilon, max_contacts=args.max_contacts, rate_hz=args.rate,
                    log=log)
    try:
        code = client.run(args.duration)
    except KeyboardInterrupt:
        client.close(BYE_NORMAL, "client interrupted")
        code = 0
    log(f"stopped: {client.seq} updates in the last session, up to {client.contacts_seen} contacts")
    return code


if __name__ == "__main__":
    sys.exit(main())
