"""Protocol v1 conformance kit: ``hapticproxy protocol check-client | check-server | check-device``.

``check-client --listen URL`` is a **scripted server** (in the manner of libfranka's mock server):
it waits for the client under test, plays the server's side of SPEC.md against it through a
fixed sequence of scenarios and judges what the client does, from what it sends back. Its
proxy starts where the client's tool is (the first ``ContactUpdate.tool_pose``, as the real
server does), so an engine that follows it stays where it is; the scenarios then move that
proxy along a free direction and back, send stale, duplicate, reordered, wrongly addressed and
invalid ProxyStates whose proxy lies elsewhere (a client that applies one moves towards it),
stop rendering (``server_state`` fading / fault / idle: the client must stop following),
answer with Heartbeats only, fall silent, say Bye (a server restart), and finally refuse the
client's next Hello with a Reject. ``check-client`` judges pose-driven clients: a client whose
tool does not follow the proxy fails ``follow`` and the rules that rely on it.

``check-server --connect URL`` is a **scripted client** against a server implementation: bad
Hellos (each answered by the documented Reject), version ranges, grants and ``Welcome.note``,
acknowledgements and their proxy (the first one at the first update's tool pose), stale,
duplicate, wrongly addressed and invalid updates, the refusals of scene bounds, unusable
contacts and sequence jumps (each an ``Error`` naming the field, the update not acknowledged and
its ``seq`` not consumed), heartbeats, a client restart, Bye and the silence timeout.

Each prints one line per rule (``PASS`` or ``FAIL``; a failing line ends with why, a passing
one says nothing more) and a verdict, and exits 0 if every rule passed, 1 if any failed, 2 on a
usage or set-up error. ``--hmac-key-file`` enables shared-secret mode (the key never goes on
the command line). ``check-device ...`` hands its arguments to the remote-device link's kit
(:mod:`hapticproxy.protocol.device_conformance`).

The module also holds the project's reference peers (:func:`run_reference_client`,
:func:`run_reference_server`): small loops over the session endpoints that pass the kit, show
how a peer drives :mod:`hapticproxy.protocol.session`, and serve other tests as stand-ins.
"""
from __future__ import annotations

import argparse
import importlib
import math
import statistics
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import msgpack
import msgspec
import numpy as np

from .codec import Bye, Codec, ContactUpdate, Error, Heartbeat, Hello, ProtocolError, ProxyState, Reject, Welcome
from .messages import MESSAGE_CLASSES, PROTOCOL_MAJOR, PROTOCOL_MINOR, ErrorCode, MessageType, ServerState, ToolKind
from .session import (
    ClientConfig,
    ClientEndpoint,
    ClientState,
    MacFramer,
    ServerConfig,
    ServerEndpoint,
    ServerSession,
    load_hmac_key,
)
from .transport.base import TransportError

__all__ = ["CLIENT_RULES", "SERVER_RULES", "Report", "check_client", "check_server", "main",
           "run_reference_client", "run_reference_server"]

_NS = 1_000_000_000
IDENTITY = np.array([0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0])
_ZERO6 = np.zeros(6)
_EMPTY = np.zeros(0)
#: SPEC 5: the server fades the force when no ContactUpdate was applied for this long (told in
#: Welcome.update_watchdog_s; the scripted server tells this value), so no client may pause longer
UPDATE_WATCHDOG_S = 0.1
# a poll this much later than the previous one means the checker was not running (its own loop
# sleeps 0.3 ms between polls)
OWN_STALL_S = 0.02
#: ProxyState's element index of ``buttons`` (1.3; ``gripper_angle_rad`` follows it)
_PS_BUTTONS = 5 + [f.name for f in msgspec.structs.fields(ProxyState)[5:]].index("buttons")


def _inputs(seq: int) -> np.ndarray:
    """The device inputs the scripted server reports in ProxyState ``seq``: buttons that change
    every 25 states, a gripper opening and closing (as a device state row holds them)."""
    a = 0.25 + 0.2 * math.sin(0.05 * seq)
    return np.array([float((seq // 25) % 4), a, 0.2 * 0.05 * math.cos(0.05 * seq) * 60.0])


#: states in which a client follows the proxy (UNKNOWN: a 1.0/1.1 server that does not say)
_FOLLOW_STATES = (ServerState.UNKNOWN, ServerState.ENGAGED)

CLIENT_RULES = {
    "hello-valid": "the first packet is a valid Hello (units SI, a range that includes 1.x, nonce != 0, header ids 0)",
    "hello-retry": "an unanswered Hello is resent with the same client_nonce",
    "session-header": "every packet after Welcome carries the granted session_id and token",
    "fields-valid": "every packet decodes and validates (types, finite values, unit normals, unique keys)",
    "usable": "every ContactUpdate lies within the granted scene bounds and suits the tool kind",
    "seq": "ContactUpdate.seq starts at 1 in every session and grows by exactly 1 (loopback: no loss)",
    "env-time": "ContactUpdate.env_time_s never decreases within a session",
    "capacity": "no ContactUpdate has more contacts than granted",
    "rate": "ContactUpdates keep coming: >= 20 Hz, no gap longer than the update watchdog (0.1 s: the force fades)",
    "initial-pose": "while the proxy is held at the client's first tool pose, the tool stays there",
    "follow": "the tool follows an engaged proxy moved along a free direction, and back",
    "proxy-stale": "a ProxyState older than the newest one (seq 1 again) is ignored",
    "proxy-duplicate": "a ProxyState repeating the newest seq is ignored",
    "proxy-reordered": "a ProxyState overtaken by a newer one (seq one below it) is ignored",
    "proxy-address": "ProxyStates with a wrong token or session id are ignored and never answered",
    "proxy-invalid": "invalid datagrams (NaN, non-unit quaternion, truncated, junk, another major) are ignored",
    "error-reply": "an invalid ProxyState of the session is answered with an Error",
    "server-state": "the tool does not follow a proxy that is fading, in fault or idle; it follows again once engaged",
    "device-inputs": "ProxyStates carry the device's buttons and gripper (1.3, changing in every one): a 1.3 client "
                     "follows them and ignores those whose button mask or gripper angle is invalid (a 1.2 client "
                     "ignores the fields: section 6)",
    "heartbeats-only": "with only Heartbeats from the server the client keeps its session and keeps updating",
    "silence-timeout": "a server silent for the granted silence_timeout_s is left with Bye 61, not earlier",
    "reconnect": "after a session ends the client opens a new one (new nonce, seq from 1, tool held at its pose)",
    "bye": "after the server's Bye the client sends nothing more in that session",
    "reject": "after a Reject the client stops sending that Hello and does not flood new ones",
}

SERVER_RULES = {
    "reject-major": "a Hello of an unknown major gets Reject UNSUPPORTED_VERSION (40) with our nonce and its range",
    "reject-units": "a Hello whose units are not SI gets Reject UNSUPPORTED_UNITS (42)",
    "reject-hello": "bad Hellos (nonce 0, ids in the header, long engine string, truncated, NaN mass, "
                    "unknown tool kind) each get Reject INVALID_HELLO (44)",
    "version-range": "a major-1 Hello offering [1.0, 3.0] is accepted with a 1.x Welcome",
    "welcome": "a valid Hello gets a Welcome with our nonce, non-zero ids, version 1.x, grants within the request",
    "welcome-note": "a grant below the request (epsilon 0.05 m asked) is named in Welcome.note",
    "hello-repeat": "the same Hello again gets the same Welcome (same session)",
    "initial-pose": "a session's first ProxyState puts the proxy at its first ContactUpdate's tool_pose",
    "ack": "every ContactUpdate is acknowledged by a ProxyState with ack_seq = its seq (loopback, >= 90 %)",
    "proxy-valid": "every ProxyState decodes, carries our session/token, seq strictly increasing, ack_seq never ahead",
    "ack-latency": "median update-to-acknowledgement time <= 20 ms",
    "server-state": "ProxyState.server_state is reported (1.2) and says engaged while updates flow",
    "stale": "an older ContactUpdate, and a repeat of the newest, are not acknowledged",
    "bad-address": "updates with a wrong token, a wrong session id or from another peer: not acknowledged, never answered",
    "invalid": "an invalid update (NaN) gets Error NON_FINITE, is not acknowledged and does not use up its seq",
    "capacity": "more contacts than granted: Error TOO_MANY_CONTACTS, not acknowledged, seq not used up",
    "out-of-bounds": "tool pose, contact position, |v_constr|, |separation| beyond the Welcome bounds: "
                     "Error OUT_OF_BOUNDS naming the field, not acknowledged, seq not used up",
    "unusable": "contacts the tool cannot have: Error UNUSABLE naming the field, not acknowledged, seq not used up",
    "seq-jump": "a seq far ahead (2^64-1) gets Error SEQ_JUMP naming seq; the session goes on",
    "heartbeat": "a quiet session gets a Heartbeat within 2 heartbeat intervals",
    "heartbeat-session": "Heartbeats alone keep a session for 2 x silence_timeout_s; updates are acknowledged again",
    "restart": "a Hello with a new nonce from the same peer replaces the session (new id, old token dead)",
    "bye": "after our Bye the session is gone: a following ContactUpdate is not acknowledged",
    "silence": "a session silent for silence_timeout_s is ended with Bye 61 (BYE_TIMEOUT), not earlier",
}


@dataclass
class Report:
    """The verdict of one check: a result per rule, in the order of ``rules``."""

    rules: dict[str, str]
    results: dict[str, tuple[bool, str]] = field(default_factory=dict)
    #: why failures are not the peer's to answer for (the checker itself stalled): not passed,
    #: but not a verdict on the peer either
    inconclusive: list[str] = field(default_factory=list)

    def check(self, rule: str, ok: bool, why_not: str = "") -> bool:
        """Record ``rule``: passed, or failed because ``why_not`` (kept only for a failure).
        The first failure of a rule stays; a later pass never overwrites it."""
        if rule not in self.rules:
            raise KeyError(rule)
        if rule in self.results and not self.results[rule][0]:
            return False
        self.results[rule] = (True, "") if ok else (False, why_not or "failed")
        return bool(ok)

    def fail(self, rule: str, why: str) -> bool:
        return self.check(rule, False, why)

    def judged(self, rule: str) -> bool:
        return rule in self.results

    def ok(self, rule: str) -> bool:
        return self.results.get(rule, (False, ""))[0]

    @property
    def failed(self) -> list[str]:
        return [r for r in self.rules if not self.ok(r)]

    @property
    def passed(self) -> bool:
        return not self.failed

    def lines(self) -> list[str]:
        out = []
        width = max(len(r) for r in self.rules)
        for rule, text in self.rules.items():
            ok, why = self.results.get(rule, (False, "not reached"))
            out.append(f"{'PASS' if ok else 'FAIL'}  {rule:<{width}}  {text}" + ("" if ok else f": {why}"))
        bad = self.failed
        if bad and self.inconclusive:
            out.append(f"RESULT: INCONCLUSIVE ({'; '.join(self.inconclusive)})")
        else:
            out.append(f"RESULT: PASS ({len(self.rules)} rules)" if not bad else
                       f"RESULT: FAIL ({len(bad)} of {len(self.rules)} rules: {', '.join(bad)})")
        return out

    @property
    def exit_code(self) -> int:
        """0 passed, 1 failed, 3 inconclusive (run the check again)."""
        return 0 if self.passed else 3 if self.inconclusive else 1


def _open(url: str, role: str):
    from .transport import open_transport  # imported late: keeps `import conformance` light

    return open_transport(url, role=role)


def _quat_angle(a, b) -> float:
    """Angle [rad] between two unit quaternions (w x y z)."""
    d = abs(float(np.dot(a, b)))
    return 2.0 * math.acos(min(1.0, d))


# =========================================================================== check-client
@dataclass
class _Session:
    """One session the scripted server opened (what the client sent in it, what it was sent)."""

    hello: Hello
    peer: object
    session_id: int
    token: int
    welcome: Welcome
    welcome_packet: bytes
    opened: float
    checker: ServerSession
    updates: list = field(default_factory=list)  # (t, ContactUpdate)
    byes: list = field(default_factory=list)  # (t, code)
    errors: list = field(default_factory=list)  # (t, Error)
    late: list = field(default_factory=list)  # (t, type name): packets after the session ended
    heartbeats: int = 0
    proxy_seq: int = 0
    heartbeat_seq: int = 0  # the Heartbeats we sent in it
    last_tx: float = 0.0
    ended: float | None = None  # when a Bye (ours or theirs) ended it
    p0: np.ndarray | None = None  # the first reported tool pose
    j0: np.ndarray = field(default_factory=lambda: _EMPTY)

    def pos(self, t0: float, t1: float = math.inf) -> list[tuple[float, np.ndarray]]:
        return [(t, np.array(u.tool_pose[:3])) for t, u in self.updates if t0 <= t <= t1]


@dataclass
class _Mode:
    """What the scripted server answers to each ContactUpdate."""

    target: Callable[[float], tuple[np.ndarray, np.ndarray]]
    state: int = ServerState.ENGAGED
    decoy: str = ""  # "", "stale", "duplicate", "reordered", "address", "invalid"
    proxy: bool = True  # False: Heartbeats only
    silent: bool = False  # nothing at all


class _ScriptedServer:
    """check-client's stand-in server: one thread, one transport, the scenarios in order."""

    DECOYS_INVALID = ("nan", "quaternion", "truncated", "junk", "major", "direction", "oversize")

    def __init__(self, transport, rep: Report, *, config: ServerConfig, hmac_key: bytes | None, step_m: float,
                 direction, phase_s: float, timeout_s: float) -> None:
        self.t = transport
        self.rep = rep
        self.cfg = config
        self.codec = Codec(config.limits)
        self.mac = MacFramer(hmac_key) if hmac_key else None
        self.step_m = float(step_m)
        self.direction = None if direction is None else np.asarray(direction, dtype=float)
        self.phase_s = float(phase_s)
        self.timeout_s = float(timeout_s)
        self.sessions: list[_Session] = []
        self.sess: _Session | None = None
        self.hellos: list[tuple[float, Hello, object]] = []
        self.mode = _Mode(self._hold)
        self.u = np.array([0.0, 0.0, 1.0])
        self.decoy_pose = IDENTITY.copy()
        self._ids = iter(range(0x5EC0_0001, 0x5EC0_1000))
        self._invalid_i = 0
        self._inputs_i = 0
        self._addr_i = 0
        self.t_follow = 0.5  # seconds the tool took to follow a move half-way (measured)
        self.reject_nonce = 0
        self.reject_at = 0.0
        # (start, end) of intervals the checker itself was not running (the OS descheduled it):
        # a gap between ContactUpdates there is the checker's, not the client's
        self.own_stalls: list[tuple[float, float]] = []
        self._last_poll = None

    # ------------------------------------------------------------------ sending
    def _emit(self, packet: bytes, peer) -> None:
        self.t.send(self.mac.seal(packet) if self.mac else packet, peer)
        if self.sess is not None:
            self.sess.last_tx = time.monotonic()

    def _proxy_packet(self, s: _Session, seq: int, pose, twist, state: int, *, session_id=None, token=None) -> bytes:
        ack = s.updates[-1][1].seq if s.updates else 0
        j = s.j0
        # a pressing hand: what the four-channel server reports (a pose-driven client ignores it)
        wrench = np.concatenate([-0.5 * self.u, np.zeros(3)])
        return self.codec.encode_proxy_state(
            s.session_id if session_id is None else session_id, s.token if token is None else token, seq, ack,
            time.monotonic() - s.opened, pose, twist, wrench, j, np.zeros_like(j), np.zeros_like(j), int(state),
            inputs=_inputs(seq))

    def _invalid_inputs_packet(self, s: _Session, seq: int) -> bytes:
        """A 1.3 ProxyState at the decoy pose whose button mask (beyond u32) or gripper angle (NaN)
        is invalid, by turns."""
        good = self._proxy_packet(s, seq, self.decoy_pose, _ZERO6, ServerState.ENGAGED)
        obj = msgpack.unpackb(good)
        self._inputs_i += 1
        if self._inputs_i % 2:
            obj[_PS_BUTTONS] = 1 << 40
        else:
            obj[_PS_BUTTONS + 1] = math.nan
        return msgpack.packb(obj)

    def _invalid_packet(self, s: _Session, seq: int) -> bytes | None:
        kind = self.DECOYS_INVALID[self._invalid_i % len(self.DECOYS_INVALID)]
        self._invalid_i += 1
        good = self._proxy_packet(s, seq, self.decoy_pose, _ZERO6, ServerState.ENGAGED)
        obj = msgpack.unpackb(good)
        if kind == "nan":  # the pose is the decoy's, the wrench NaN
            obj[10] = np.array([math.nan, 0, 0, 0, 0, 0], "<f8").tobytes()
        elif kind == "quaternion":
            pose = self.decoy_pose.copy()
            pose[3:] *= 1.5
            obj[8] = pose.astype("<f8").tobytes()
        elif kind == "truncated":
            return good[:-9]
        elif kind == "junk":
            return b"\xc1" * 40  # 0xc1 is never used by msgpack
        elif kind == "major":
            obj[0] = PROTOCOL_MAJOR + 1
        elif kind == "direction":  # a ContactUpdate sent to a client: UNEXPECTED
            return self.codec.encode_contact_update(s.session_id, s.token, seq, 0.0, self.decoy_pose,
                                                    np.zeros((0, 3), np.int64), np.zeros((0, 3)), np.zeros((0, 3)),
                                                    np.zeros(0), np.zeros(0))
        elif kind == "oversize":
            return good + bytes(self.cfg.limits.max_packet_bytes + 64)
        return msgpack.packb(obj)

    def _welcome(self, hello: Hello, peer, t: float) -> _Session:
        cfg = self.cfg
        sid = next(self._ids)
        token = 0x7E57_0000_0000_0000 | sid
        vmax = hello.version_max
        minor = min(PROTOCOL_MINOR, vmax[1]) if vmax[0] == PROTOCOL_MAJOR else PROTOCOL_MINOR
        eps = min(hello.epsilon_m, cfg.max_epsilon_m)
        grant = min(hello.max_contacts, cfg.max_contacts)
        note = f"epsilon_m capped at {eps:g} m (requested {hello.epsilon_m:g} m)" if eps < hello.epsilon_m else ""
        w = Welcome(client_nonce=hello.client_nonce, version=(PROTOCOL_MAJOR, minor), haptic_rate_hz=cfg.haptic_rate_hz,
                    epsilon_m=eps, max_contacts=grant, heartbeat_interval_s=cfg.heartbeat_interval_s,
                    silence_timeout_s=cfg.silence_timeout_s, server_name="hapticproxy check-client",
                    workspace_extent_m=cfg.workspace_extent_m,
                    max_constraint_speed_m_per_s=cfg.max_constraint_speed_m_per_s,
                    max_separation_m=cfg.max_separation_m, note=note, session_id=sid, token=token)
        packet = self.codec.encode(w)
        checker = ServerSession(sid, token, peer, hello, w, packet, 0, cfg.error_rate_per_s)
        s = _Session(hello, peer, sid, token, w, packet, t, checker)
        self.sessions.append(s)
        self.sess = s
        self._emit(packet, peer)
        return s

    # ------------------------------------------------------------------ receiving
    def _recv(self):
        got = self.t.recv()
        if got is None:
            return None
        data, peer = got
        if self.mac is not None:
            data = self.mac.open(data)
            if data is None:
                self.rep.fail("fields-valid", "a datagram with a missing or wrong HMAC tag")
                return None
        return data, peer

    def pump(self, seconds: float, until: Callable[[], bool] | None = None) -> bool:
        """Handle traffic for ``seconds`` or until ``until()``; True if ``until`` was met."""
        end = time.monotonic() + seconds
        while True:
            now = time.monotonic()
            if self._last_poll is not None and now - self._last_poll > OWN_STALL_S:
                self.own_stalls.append((self._last_poll, now))
            self._last_poll = now
            if until is not None and until():
                return True
            if now >= end:
                return False
            got = self._recv()
            if got is None:
                s = self.sess
                if (s is not None and s.ended is None and not self.mode.silent
                        and now - s.last_tx >= self.cfg.heartbeat_interval_s):
                    s.heartbeat_seq += 1
                    self._emit(self.codec.encode(Heartbeat(seq=s.heartbeat_seq, time_s=now - s.opened,
                                                           session_id=s.session_id, token=s.token)), s.peer)
                time.sleep(0.0003)
                continue
            self._handle(got[0], got[1], time.monotonic())

    def _session_of(self, msg) -> _Session | None:
        for s in reversed(self.sessions):
            if msg.session_id == s.session_id and msg.token == s.token:
                return s
        return None

    def _handle(self, data, peer, t: float) -> None:
        rep = self.rep
        msg = self.codec.try_decode(data)
        if isinstance(msg, ProtocolError):
            what = MESSAGE_CLASSES[msg.type_id].__name__ if msg.type_id in MESSAGE_CLASSES else "a packet"
            rep.fail("fields-valid", f"{what} refused: {msg}"[:200])
            return
        if isinstance(msg, Hello):
            self.hellos.append((t, msg, peer))
            s = self.sess
            if s is not None and s.ended is None and msg.client_nonce == s.hello.client_nonce:
                self._emit(s.welcome_packet, peer)  # our Welcome crossed a retry: say it again
            return
        s = self._session_of(msg)
        if s is None or peer != s.peer:
            rep.fail("session-header", f"a {type(msg).__name__} with session {msg.session_id:#x}, token "
                                       f"{msg.token:#x} that no session of ours has")
            return
        if isinstance(msg, Bye):
            s.byes.append((t, msg.code))
            if s.ended is None:
                s.ended = t
            return
        if s.ended is not None and t - s.ended > 0.25:
            s.late.append((t, type(msg).__name__))
            return
        if isinstance(msg, Heartbeat):
            s.heartbeats += 1
            return
        if isinstance(msg, Error):
            s.errors.append((t, msg))
            return
        if not isinstance(msg, ContactUpdate):
            rep.fail("fields-valid", f"a {type(msg).__name__} from a client")
            return
        self._on_update(s, msg, t)

    def _on_update(self, s: _Session, cu: ContactUpdate, t: float) -> None:
        rep = self.rep
        prev = s.updates[-1][1] if s.updates else None
        s.updates.append((t, cu))
        expect = 1 if prev is None else prev.seq + 1
        if cu.seq != expect:
            rep.fail("seq", f"session {len(self.sessions)}: seq {cu.seq} after {0 if prev is None else prev.seq}")
        if prev is not None and cu.env_time_s < prev.env_time_s:
            rep.fail("env-time", f"env_time_s went back from {prev.env_time_s:g} to {cu.env_time_s:g} s")
        if cu.n_contacts > s.welcome.max_contacts:
            rep.fail("capacity", f"{cu.n_contacts} contacts > granted {s.welcome.max_contacts}")
        why = s.checker.check_update(cu)
        if why is not None:
            rep.fail("usable", f"{why[1]}: {why[2]}")
        if s.p0 is None:
            s.p0 = np.array(cu.tool_pose)
            j = cu.tool_joint_position
            n_j = max(0, len(s.hello.links) - 1)
            s.j0 = np.array(j) if len(j) == n_j else np.zeros(n_j)
        if s.ended is not None or self.mode.silent or not self.mode.proxy:
            return
        m = self.mode
        pose, twist = m.target(t)
        pose_d = self.decoy_pose
        if m.decoy == "reordered":
            s.proxy_seq += 2
            self._emit(self._proxy_packet(s, s.proxy_seq, pose, twist, m.state), s.peer)
            self._emit(self._proxy_packet(s, s.proxy_seq - 1, pose_d, _ZERO6, ServerState.ENGAGED), s.peer)
            return
        s.proxy_seq += 1
        self._emit(self._proxy_packet(s, s.proxy_seq, pose, twist, m.state), s.peer)
        if m.decoy == "stale" and s.proxy_seq > 2:
            self._emit(self._proxy_packet(s, 1, pose_d, _ZERO6, ServerState.ENGAGED), s.peer)
        elif m.decoy == "duplicate":
            self._emit(self._proxy_packet(s, s.proxy_seq, pose_d, _ZERO6, ServerState.ENGAGED), s.peer)
        elif m.decoy == "address":
            s.proxy_seq += 1
            self._addr_i += 1
            wrong = dict(token=s.token ^ 0x1) if self._addr_i % 2 else dict(session_id=s.session_id ^ 0x1)
            self._emit(self._proxy_packet(s, s.proxy_seq, pose_d, _ZERO6, ServerState.ENGAGED, **wrong), s.peer)
        elif m.decoy == "invalid":
            s.proxy_seq += 1
            bad = self._invalid_packet(s, s.proxy_seq)
            if bad:
                self._emit(bad, s.peer)
        elif m.decoy == "inputs":
            s.proxy_seq += 1
            self._emit(self._invalid_inputs_packet(s, s.proxy_seq), s.peer)

    # ------------------------------------------------------------------ targets and measures
    def _hold(self, t: float):
        s = self.sess
        return (IDENTITY if s is None or s.p0 is None else s.p0), _ZERO6

    def _at(self, offset_m: float) -> np.ndarray:
        pose = self.sess.p0.copy()
        pose[:3] += offset_m * self.u
        return pose

    def _ramp(self, a_m: float, b_m: float, ramp_s: float = 0.2):
        t0 = time.monotonic()
        speed = (b_m - a_m) / ramp_s

        def target(t: float):
            f = (t - t0) / ramp_s
            if f >= 1.0:
                return self._at(b_m), _ZERO6
            return self._at(a_m + (b_m - a_m) * max(f, 0.0)), np.concatenate([speed * self.u, np.zeros(3)])
        return target

    def _static(self, offset_m: float):
        pose = self._at(offset_m)
        return lambda t: (pose, _ZERO6)

    def proj(self, t0: float, t1: float = math.inf) -> list[float]:
        """The tool's displacement along u from the session's first pose, per update in [t0, t1]."""
        s = self.sess
        return [float(np.dot(p - s.p0[:3], self.u)) for _, p in s.pos(t0, t1)]

    def _last_proj(self) -> float:
        s = self.sess
        if not s.updates:
            return 0.0
        return float(np.dot(np.array(s.updates[-1][1].tool_pose[:3]) - s.p0[:3], self.u))

    def _choose_direction(self, s: _Session) -> None:
        cu = s.updates[0][1]
        kind = s.hello.tool_kind
        p0 = s.p0
        if self.direction is not None:
            u = self.direction.copy()
        else:
            u = cu.normal.sum(axis=0) if cu.n_contacts else np.zeros(3)
            planar = kind == ToolKind.PLANAR or (kind == ToolKind.LINKAGE and p0[2] == 0.0
                                                 and p0[4] == 0.0 and p0[5] == 0.0)
            if kind == ToolKind.ONE_DOF:
                axis = np.asarray(s.hello.axis, dtype=float)
                a = float(np.dot(u, axis))
                u = axis * (1.0 if a >= -0.1 else -1.0)
            elif planar:
                u[2] = 0.0
                if np.linalg.norm(u) < 0.1:
                    u = np.array([0.0, 1.0, 0.0])
            elif np.linalg.norm(u) < 0.1:
                u = np.array([0.0, 0.0, 1.0])
        self.u = u / np.linalg.norm(u)
        self.decoy_pose = self._at(self.step_m)

    # ------------------------------------------------------------------ scenarios
    def run(self) -> None:
        rep = self.rep
        if not self._handshake():
            return
        s = self.sess
        if not self.pump(3.0, until=lambda: bool(s.updates)):
            rep.fail("rate", "no ContactUpdate within 3 s of the Welcome")
            return
        try:
            self._scenarios(s)
        finally:
            self._final_rules()

    def _scenarios(self, s: _Session) -> None:
        rep = self.rep
        self._choose_direction(s)
        self._initial_pose(s, "initial-pose")
        if self._follow():
            for decoy, rule in (("stale", "proxy-stale"), ("duplicate", "proxy-duplicate"),
                                ("reordered", "proxy-reordered"), ("address", "proxy-address"),
                                ("invalid", "proxy-invalid")):
                self._decoy(decoy, rule)
            self._server_state()
            self._device_inputs()
        else:
            for rule in ("proxy-stale", "proxy-duplicate", "proxy-reordered", "proxy-address", "proxy-invalid",
                         "error-reply", "server-state", "device-inputs"):
                rep.fail(rule, "not judged: the tool does not follow the proxy (rule follow)")
        self._heartbeats_only()
        self._silence()
        if not self._reconnect():
            rep.fail("bye", "not judged: the client did not reconnect")
            return
        self._server_bye()
        bye_session = self.sess
        if self._reconnect(answer="reject"):
            self._reject()
        late = bye_session.late
        rep.check("bye", not late, f"{len(late)} packets ({late[0][1] if late else ''}) in the session more than "
                                   "0.25 s after the server's Bye")

    def _handshake(self) -> bool:
        rep = self.rep
        if not self.pump(self.timeout_s, until=lambda: bool(self.hellos)):
            rep.fail("hello-valid", f"no Hello within {self.timeout_s:g} s")
            return False
        t0, hello, peer = self.hellos[0]
        problems = []
        if hello.units != "SI":
            problems.append(f"units {hello.units!r}")
        if not (hello.version_min[0] <= PROTOCOL_MAJOR <= hello.version_max[0]) or hello.version_min > hello.version_max:
            problems.append(f"version range {hello.version_min}-{hello.version_max}")
        if hello.session_id or hello.token:
            problems.append("non-zero session_id/token in its header")
        rep.check("hello-valid", not problems, ", ".join(problems))
        if problems:
            return False
        self.pump(3.0, until=lambda: len(self.hellos) > 1)
        if len(self.hellos) < 2:
            rep.fail("hello-retry", "no second Hello within 3 s of an unanswered one")
            retry = hello
        else:
            retry = self.hellos[1][1]
            rep.check("hello-retry", retry.client_nonce == hello.client_nonce,
                      f"the retry has a new nonce {retry.client_nonce:#x} (was {hello.client_nonce:#x})")
        self._welcome(retry, self.hellos[1][2] if len(self.hellos) > 1 else peer, time.monotonic())
        return True

    def _initial_pose(self, s: _Session, rule: str, *, prefix: str = "") -> None:
        """The proxy is held at the first reported pose for one phase: the tool stays there."""
        self.mode = _Mode(self._hold)
        t0 = time.monotonic()
        self.pump(self.phase_s)
        poses = [(t, u.tool_pose) for t, u in s.updates if t >= t0]
        if not poses:
            self.rep.fail(rule, prefix + "no ContactUpdate while the proxy was held")
            return
        tol = self.hold_tol
        worst = max(float(np.linalg.norm(np.asarray(p[:3]) - s.p0[:3])) for _, p in poses)
        turn = max(_quat_angle(np.asarray(p[3:]), s.p0[3:]) for _, p in poses)
        self.rep.check(rule, worst <= tol and turn <= 0.1,
                       prefix + f"the proxy was held at the first tool pose {np.round(s.p0[:3], 4).tolist()} m, the "
                       f"tool moved {worst * 1e3:.1f} mm (tolerance {tol * 1e3:.1f}) and turned {math.degrees(turn):.1f} deg")

    @property
    def hold_tol(self) -> float:
        return 0.35 * self.step_m

    def _move(self, a_m: float, b_m: float, timeout_s: float = 2.0) -> tuple[bool, float]:
        """Move the engaged proxy from a to b along u (a 0.2 s ramp)."""
        return self._reach(self._ramp(a_m, b_m), a_m, b_m, timeout_s)

    def _reach(self, target, from_m: float, to_m: float, timeout_s: float = 2.0,
               state: int = ServerState.ENGAGED) -> tuple[bool, float]:
        """Send the proxy ``target``; wait until the tool, believed at ``from_m`` along u, gets
        90 % of the way to ``to_m``. (passed half-way, seconds to half-way)."""
        self.mode = _Mode(target, state=state)
        t0 = time.monotonic()
        half = 0.5 * (from_m + to_m)
        far = from_m + 0.9 * (to_m - from_m)
        rising = to_m > from_m

        def reached(x: float, mark: float) -> bool:
            return x >= mark if rising else x <= mark

        self.pump(timeout_s, until=lambda: reached(self._last_proj(), far))
        hit = [t for t, x in zip([t for t, _ in self.sess.pos(t0)], self.proj(t0)) if reached(x, half)]
        return bool(hit), (hit[0] - t0) if hit else math.inf

    def _follow(self) -> bool:
        rep = self.rep
        d = self.step_m
        ok_out, t_out = self._move(0.0, d)
        if not ok_out:
            held = self._held_back()
            rep.fail("follow", f"the proxy moved {d * 1e3:g} mm along {np.round(self.u, 3).tolist()}; the tool "
                               f"moved {self._last_proj() * 1e3:.1f} mm in 2 s" + held)
            return False
        ok_back, t_back = self._move(d, 0.0)
        if not ok_back:
            rep.fail("follow", f"the tool followed the proxy out but not back ({self._last_proj() * 1e3:.1f} mm "
                               f"from its start after 2 s)")
            return False
        self.pump(0.2)  # settle at the start
        rep.check("follow", True)
        self.t_follow = max(t_out, t_back)
        return True

    def _held_back(self) -> str:
        cu = self.sess.updates[-1][1]
        if cu.n_contacts and float(np.min(cu.normal @ self.u)) < -0.5:
            return "; a reported contact holds it back: choose a free --direction"
        return ""

    @property
    def decoy_s(self) -> float:
        return min(2.0, max(0.3, 2.0 * self.t_follow + 0.1))

    def _decoy(self, decoy: str, rule: str) -> None:
        s = self.sess
        self.mode = _Mode(self._static(0.0), decoy=decoy)
        t0 = time.monotonic()
        n_err = len(s.errors)
        self.pump(self.decoy_s)
        self.pump(0.05)
        moved = self.proj(t0)
        if not moved:
            self.rep.fail(rule, "no ContactUpdate during the scenario")
            return
        worst = max(moved)
        ok = worst <= self.hold_tol
        what = {"stale": "seq 1", "duplicate": "the newest seq", "reordered": "seq one below the newest",
                "address": "a wrong token or session id", "invalid": "invalid content",
                "inputs": "an invalid button mask or gripper angle"}[decoy]
        self.rep.check(rule, ok, f"the tool moved {worst * 1e3:.1f} mm towards the proxy of ProxyStates with {what}")
        errors = [e for t, e in s.errors[n_err:]]
        if decoy == "address":
            self.rep.check(rule, not errors, f"{len(errors)} Error(s) answered packets of another session")
        if decoy == "invalid":
            ps = [e for e in errors if e.ref_type == MessageType.PROXY_STATE]
            self.rep.check("error-reply", bool(ps), "no Error answered the invalid ProxyStates of the session"
                           + (f" (got {len(errors)} other Error(s))" if errors else ""))

    def _server_state(self) -> None:
        rep = self.rep
        minor = self.sess.welcome.version[1]
        if minor < 2:
            rep.fail("server-state", f"not judged: the client speaks 1.{minor} (server_state is 1.2)")
            return
        tol = self.hold_tol
        for state in (ServerState.FADING, ServerState.FAULT, ServerState.IDLE):
            self.mode = _Mode(self._static(self.step_m), state=state)
            t0 = time.monotonic()
            self.pump(self.decoy_s)
            worst = max(self.proj(t0), default=0.0)
            if worst > tol:
                rep.fail("server-state", f"the tool moved {worst * 1e3:.1f} mm towards a proxy whose server_state is "
                                         f"{state.name.lower()}")
                self._move(self.step_m, 0.0)
                return
        ok, _ = self._reach(self._static(self.step_m), 0.0, self.step_m)  # engaged again, the same proxy
        if not ok:
            rep.fail("server-state", "the tool did not follow the proxy once server_state was engaged again "
                                     f"({self._last_proj() * 1e3:.1f} of {self.step_m * 1e3:g} mm)")
        else:
            rep.check("server-state", True)
        self._move(self.step_m, 0.0)
        self.pump(0.2)

    def _device_inputs(self) -> None:
        """Every ProxyState so far carried changing buttons and gripper values (``_inputs``), and
        the client followed them (rule follow). A 1.3 client must also ignore ProxyStates whose
        inputs are invalid; a 1.2 one reads none of those fields (they trail its layout)."""
        if self.sess.welcome.version[1] < 3:
            self.rep.check("device-inputs", True)
            return
        self._decoy("inputs", "device-inputs")
        # (a client that followed the decoys comes back before the next scenario)
        self.mode = _Mode(self._static(0.0))
        self.pump(self.decoy_s)

    def _heartbeats_only(self) -> None:
        s = self.sess
        self.mode = _Mode(self._static(0.0), proxy=False)
        t0 = time.monotonic()
        span = 2.0 * s.welcome.silence_timeout_s
        n0 = len(s.updates)
        self.pump(span)
        got = len(s.updates) - n0
        problems = []
        if s.byes:
            problems.append(f"it said Bye (code {s.byes[0][1]}) after {s.byes[0][0] - t0:.2f} s")
        rate = self._rate(s)
        if got < max(2, 0.5 * rate * span):
            problems.append(f"{got} ContactUpdates in {span:g} s (about {rate * span:.0f} expected)")
        moved = max((abs(x) for x in self.proj(t0)), default=0.0)
        if moved > self.hold_tol:
            problems.append(f"the tool moved {moved * 1e3:.1f} mm")
        self.rep.check("heartbeats-only", not problems, "; ".join(problems))

    @staticmethod
    def _rate(s: _Session) -> float:
        ts = [t for t, _ in s.updates]
        return (len(ts) - 1) / (ts[-1] - ts[0]) if len(ts) > 2 and ts[-1] > ts[0] else 0.0

    def _silence(self) -> None:
        s = self.sess
        timeout = s.welcome.silence_timeout_s
        if s.byes:
            self.rep.fail("silence-timeout", "not judged: the session had already ended")
            return
        self.mode = _Mode(self._hold, silent=True)
        t_last = s.last_tx
        self.pump(timeout + 1.5, until=lambda: bool(s.byes))
        if not s.byes:
            self.rep.fail("silence-timeout", f"no Bye within {timeout + 1.5:g} s of silence (granted "
                                             f"silence_timeout_s {timeout:g} s)")
            s.ended = time.monotonic()
            return
        t_bye, code = s.byes[0]
        after = t_bye - t_last
        ok = code == ErrorCode.BYE_TIMEOUT and timeout - 0.03 <= after <= timeout + 0.35
        self.rep.check("silence-timeout", ok, f"Bye code {code} {after:.2f} s after the server's last packet "
                                              f"(granted silence_timeout_s {timeout:g} s)")

    def _reconnect(self, answer: str = "welcome") -> bool:
        """Wait for a Hello with a new nonce after the current session ended; answer it."""
        rep = self.rep
        old = self.sess
        nonces = {s.hello.client_nonce for s in self.sessions}
        t0 = time.monotonic()
        n = len(self.hellos)

        def fresh():
            return any(h.client_nonce not in nonces for _, h, _ in self.hellos[n:])

        if not self.pump(5.0, until=fresh):
            rep.fail("reconnect", "no new Hello within 5 s of the end of a session")
            rep.fail("reject", "not judged: the client did not reconnect")
            return False
        t, hello, peer = next(x for x in self.hellos[n:] if x[1].client_nonce not in nonces)
        late = [name for _, name in old.late]
        if answer == "reject":
            self.reject_nonce = hello.client_nonce
            self.reject_at = time.monotonic()
            self.sess = None
            self._emit(self.codec.encode(Reject(client_nonce=hello.client_nonce, code=ErrorCode.SERVER_FULL,
                                                reason="check-client: refusing on purpose (all 1 session slots "
                                                       "in use)")), peer)
            return True
        s = self._welcome(hello, peer, time.monotonic())
        if not self.pump(3.0, until=lambda: bool(s.updates)):
            rep.fail("reconnect", "no ContactUpdate within 3 s of the new session's Welcome")
            return False
        self._initial_pose(s, "reconnect", prefix="new session: ")
        if late:
            rep.fail("reconnect", f"{len(late)} packets of the old session after its end ({late[0]})")
        return True

    def _server_bye(self) -> None:
        s = self.sess
        bye = self.codec.encode(Bye(code=ErrorCode.BYE_SHUTDOWN, reason="check-client: the server restarts",
                                    session_id=s.session_id, token=s.token))
        for _ in range(3):
            self._emit(bye, s.peer)
        s.ended = time.monotonic()
        self.mode = _Mode(self._hold, silent=True)

    def _reject(self) -> None:
        nonce = self.reject_nonce
        t0 = self.reject_at
        self.pump(1.5)
        after = [(t, h) for t, h, _ in self.hellos if t > t0]
        again = [t for t, h in after if h.client_nonce == nonce and t - t0 > 0.3]
        new = [t for t, h in after if h.client_nonce != nonce]
        problems = []
        if again:
            problems.append(f"the rejected Hello was sent {len(again)} more times")
        if len(new) > 2:
            problems.append(f"{len(new)} new Hellos within 1.5 s of the Reject")
        self.rep.check("reject", not problems, "; ".join(problems))

    def _final_rules(self) -> None:
        rep = self.rep
        ups = [(t, u) for s in self.sessions for t, u in s.updates]
        if not ups:
            for rule in ("fields-valid", "usable", "seq", "env-time", "capacity", "rate"):
                rep.fail(rule, "no ContactUpdate received")
            return
        for rule in ("fields-valid", "session-header", "usable", "seq", "env-time", "capacity"):
            rep.check(rule, True)
        main = self.sessions[0]
        rate = self._rate(main)
        gaps = []
        for s in self.sessions:
            ts = [t for t, _ in s.updates if s.ended is None or t <= s.ended]
            gaps += [(b - a, b - a - self._own_stall_within(a, b)) for a, b in zip(ts, ts[1:])]
        # a gap is the client's only net of the time the checker itself was descheduled (datagrams
        # queue in the socket meanwhile and are all stamped on the checker's wake-up)
        raw, gap = max(gaps, key=lambda g: g[1], default=(0.0, 0.0))
        excused = [r for r, net in gaps if r > UPDATE_WATCHDOG_S >= net]
        limit = UPDATE_WATCHDOG_S
        note = f" (net of {(raw - gap) * 1e3:.0f} ms the checker itself was descheduled)" if raw > gap else ""
        if excused:
            note += f"; {len(excused)} longer gap(s), up to {max(excused) * 1e3:.0f} ms, spanned the checker's own stall"
        rep.check("rate", 20.0 <= rate <= self.cfg.haptic_rate_hz and gap <= limit,
                  f"{rate:.1f} Hz, longest gap between ContactUpdates {gap * 1e3:.0f} ms (limit {limit * 1e3:.0f})"
                  + note)

    def _own_stall_within(self, a: float, b: float) -> float:
        return sum(max(0.0, min(b, e) - max(a, s)) for s, e in self.own_stalls)


def check_client(transport, *, duration_s: float = 0.5, hmac_key: bytes | None = None, timeout_s: float = 10.0,
                 config: ServerConfig | None = None, step_m: float = 0.01, direction=None) -> Report:
    """Play the scripted server on ``transport`` (role server) against the first client that
    connects, and judge it (about 15 s with a client that reconnects after 1 s).
    ``duration_s``: how long the proxy is held at the client's first pose (in the first session
    and in the one after it reconnects); the other scenarios last as long as the client took to
    follow a move (twice, at least 0.3 s). ``step_m``: how far the proxy is moved, along
    ``direction``, or else away from the first reported contacts (+y planar, +z spatial, +axis
    1-DOF when there are none). ``config``: the grants (default: 16 contacts, the granted epsilon
    capped at 10 mm, heartbeats every 0.1 s, silence timeout 0.5 s)."""
    if not (math.isfinite(step_m) and 0.001 <= step_m <= 0.1):
        raise ValueError(f"step_m: must be in [0.001, 0.1] m, got {step_m!r}")
    if direction is not None:
        direction = np.asarray(direction, dtype=float)
        if direction.shape != (3,) or not np.all(np.isfinite(direction)) or np.linalg.norm(direction) < 1e-9:
            raise ValueError(f"direction: must be 3 finite numbers, not all zero, got {direction!r}")
    rep = Report(CLIENT_RULES)
    cfg = config or ServerConfig(max_contacts=16, heartbeat_interval_s=0.1, silence_timeout_s=0.5,
                                 update_watchdog_s=UPDATE_WATCHDOG_S)
    _ScriptedServer(transport, rep, config=cfg, hmac_key=hmac_key, step_m=step_m, direction=direction,
                    phase_s=max(0.1, float(duration_s)), timeout_s=timeout_s).run()
    return rep


# =========================================================================== check-server
class _Probe:
    """A bare client socket: raw packets out, decoded packets in (no session logic, on purpose)."""

    def __init__(self, url: str, mac: MacFramer | None) -> None:
        self.t = _open(url, "client")
        self.mac = mac
        self.codec = Codec()
        # A server rightly ends a session its client leaves silent for silence_timeout_s, and a
        # stall of the checker's own process or machine (a garbage collection, a busy CI host)
        # is such a silence: the checker keeps the longest time it sent nothing, to tell that
        # apart from the server's fault.
        self.last_send_s: float | None = None
        self.longest_quiet_s = 0.0

    def send(self, packet: bytes) -> None:
        now = time.monotonic()
        if self.last_send_s is not None:
            self.longest_quiet_s = max(self.longest_quiet_s, now - self.last_send_s)
        self.last_send_s = now
        self.t.send(self.mac.seal(packet) if self.mac else packet)

    def quiet_s(self) -> float:
        """The longest time without a send since the last ``longest_quiet_s`` reset, up to now."""
        if self.last_send_s is None:
            return 0.0
        return max(self.longest_quiet_s, time.monotonic() - self.last_send_s)

    def recv_all(self, wait_s: float, until: Callable[[list], bool] | None = None) -> list:
        """(arrival time, message or ProtocolError) for ``wait_s`` or until ``until(got)``."""
        out, end = [], time.monotonic() + wait_s
        while True:
            got = self.t.recv()
            if got is None:
                # what is queued is read even when the wait is over (after a stall of this
                # process the deadline may already be past while the answers sit in the socket)
                if time.monotonic() >= end:
                    break
                time.sleep(0.0002)
                continue
            data = got[0]
            if self.mac is not None:
                data = self.mac.open(data)
                if data is None:
                    out.append((time.monotonic(), ProtocolError(ErrorCode.BAD_MAC, "", "bad HMAC tag")))
                    continue
            out.append((time.monotonic(), self.codec.try_decode(data)))
            if until is not None and until(out):
                break
        return out

    def close(self) -> None:
        self.t.close()


#: check-server's rules judged in the main session, which the checker keeps alive with its own
#: packets up to the heartbeat rule
_MAIN_SESSION_RULES = ("ack", "ack-latency", "proxy-valid", "initial-pose", "server-state", "stale", "bad-address",
                       "invalid", "capacity", "out-of-bounds", "unusable", "seq-jump", "heartbeat")

#: tool kinds check-server tries, in order, until the server accepts one
_KINDS = (ToolKind.SPATIAL, ToolKind.PLANAR, ToolKind.ONE_DOF)


def _hello(nonce: int, kind: ToolKind = ToolKind.SPATIAL, max_contacts: int = 8, epsilon_m: float = 0.005,
           **kw) -> Hello:
    return Hello(client_nonce=nonce, engine="hapticproxy-conformance", tool_kind=kind, mass_kg=0.2,
                 inertia_kg_m2=(2e-4, 2e-4, 2e-4, 0.0, 0.0, 0.0), max_contacts=max_contacts, epsilon_m=epsilon_m,
                 env_rate_hz=60.0, **kw)


class _ScriptedClient:
    """check-server's stand-in client: the scenarios in order, on raw packets."""

    def __init__(self, url: str, rep: Report, mac: MacFramer | None, duration_s: float, rate_hz: float) -> None:
        self.url = url
        self.rep = rep
        self.mac = mac
        self.duration_s = duration_s
        self.rate_hz = rate_hz
        self.codec = Codec()
        self._nonce = 0xC0FFEE00
        self.kind = ToolKind.SPATIAL
        self.welcome: Welcome | None = None
        self.probe: _Probe | None = None
        self.seq = 0
        self.pose = IDENTITY.copy()
        self.states: list[tuple[float, ProxyState]] = []
        self.others: list = []
        self.hb_seq = 0

    def nonce(self) -> int:
        self._nonce += 1
        return self._nonce

    # ------------------------------------------------------------------ packets
    def _contacts(self, n: int, *, tool_link: int = 0):
        """n contacts of a floor (or wall) under the tool, 2 mm apart: plausible, no force."""
        p = self.pose[:3]
        if self.kind == ToolKind.ONE_DOF:  # a wall at +x
            pos = np.tile(p + [0.012, 0.0, 0.0], (n, 1))
            pos[:, 1] = np.linspace(-0.005, 0.005, n)
            nor = np.tile([-1.0, 0.0, 0.0], (n, 1))
        elif self.kind == ToolKind.PLANAR:  # a floor at -y
            pos = np.column_stack([p[0] + np.linspace(-0.02, 0.02, n), np.full(n, p[1] - 0.012), np.zeros(n)])
            nor = np.tile([0.0, 1.0, 0.0], (n, 1))
        else:  # a floor at -z
            a = np.linspace(0, 2 * math.pi, n, endpoint=False)
            pos = np.column_stack([p[0] + 0.02 * np.cos(a), p[1] + 0.02 * np.sin(a), np.full(n, p[2] - 0.012)])
            nor = np.tile([0.0, 0.0, 1.0], (n, 1))
        keys = np.column_stack([np.full(n, tool_link), np.full(n, 3), np.arange(n)]).astype(np.int64)
        return keys, pos, nor, np.full(n, 0.002), np.zeros(n)

    def cu(self, seq: int, *, session_id=None, token=None, n: int | None = None, poison: str = "",
           pose=None) -> bytes:
        """A ContactUpdate of this session (or addressed as given), ``poison`` naming what is wrong."""
        w = self.welcome
        n = min(w.max_contacts, 3) if n is None else n
        keys, pos, nor, d, v = self._contacts(n, tool_link=1 if poison == "tool_link" else 0)
        pose = self.pose if pose is None else np.array(pose)
        joints = None
        ext = w.workspace_extent_m
        if poison == "nan":
            d[0] = math.nan
        elif poison == "tool_pose":
            pose = pose.copy()
            pose[0] = min(1.5 * ext + 0.1, 9e8)
        elif poison == "position":
            pos[0, 0] = min(1.5 * ext + 0.1, 9e8)
        elif poison == "v_constr":
            v[0] = min(1.5 * w.max_constraint_speed_m_per_s + 0.1, 9e8)
        elif poison == "separation":
            d[0] = min(1.5 * w.max_separation_m + 0.1, 9e8)
        elif poison == "joints":
            joints = np.array([0.1, 0.2])
        elif poison == "normal_z":
            nor[0] = (0.0, 0.6, 0.8)
        packet = self.codec.encode_contact_update(
            w.session_id if session_id is None else session_id, w.token if token is None else token, seq,
            min(seq, 1 << 20) / self.rate_hz, pose, keys, pos, nor, d, v, tool_joint_position=joints)
        return packet

    def collect(self, wait_s: float, until=None) -> list:
        got = self.probe.recv_all(wait_s, until)
        for t, m in got:
            if isinstance(m, ProxyState):
                self.states.append((t, m))
            else:
                self.others.append((t, m))
        return got

    def _hello_exchange(self, probe: _Probe, hello_packet: bytes, nonce: int, wait_s: float = 0.25, tries: int = 4):
        """Send a Hello (resent like a client) until a Welcome or Reject with ``nonce`` comes."""
        for _ in range(tries):
            probe.send(hello_packet)
            for _, m in probe.recv_all(wait_s, until=lambda got: any(
                    isinstance(x[1], (Welcome, Reject)) and x[1].client_nonce == nonce for x in got)):
                if isinstance(m, (Welcome, Reject)) and m.client_nonce == nonce:
                    return m
        return None

    def _bye(self, probe: _Probe, w: Welcome) -> None:
        packet = self.codec.encode(Bye(code=ErrorCode.BYE_NORMAL, reason="check-server", session_id=w.session_id,
                                       token=w.token))
        for _ in range(3):
            probe.send(packet)

    # ------------------------------------------------------------------ scenarios
    def run(self) -> None:
        self._bad_hellos()
        self._version_range()
        self.probe = _Probe(self.url, self.mac)
        try:
            if not self._open_main():
                return
            self._updates()
            self._refusals()
            self._heartbeat()
            # measured after the heartbeat rule, whose own quiet (2 heartbeat intervals and
            # 50 ms) is shorter than the silence timeout unless a server grants less than that
            self._judge_own_stall(_MAIN_SESSION_RULES, self.probe.quiet_s())
            self._restart()
            self.probe.longest_quiet_s = 0.0
            self._heartbeat_session()
            self._judge_own_stall(("heartbeat-session",), self.probe.quiet_s())
            self._bye_rule()
            self._silence()
        finally:
            self.probe.close()

    def _judge_own_stall(self, rules: tuple[str, ...], quiet_s: float) -> None:
        """Failures of ``rules`` are the checker's, not the server's, when the server ended the
        session (its Bye came) after the checker itself had sent nothing for the session's
        silence timeout (less the silence rule's 50 ms): the server was right to end it."""
        w = self.welcome
        failed = [r for r in rules if self.rep.judged(r) and not self.rep.ok(r)]
        byes = [m for _, m in self.others if isinstance(m, Bye) and m.session_id == w.session_id]
        if failed and byes and quiet_s >= w.silence_timeout_s - 0.05:
            self.rep.inconclusive.append(
                f"this checker sent nothing for {quiet_s:.2f} s (its process or machine stalled), not less than the "
                f"session's silence_timeout_s {w.silence_timeout_s:g} s, and the server ended the session "
                f"(Bye {_code_name(byes[0].code)}) as it should: {', '.join(failed)} say nothing about the server; "
                f"run the check again")

    def _one_hello(self, packet: bytes, nonce: int) -> list:
        probe = _Probe(self.url, self.mac)
        try:
            probe.send(packet)
            return [m for _, m in probe.recv_all(0.3, until=lambda got: any(isinstance(x[1], (Reject, Welcome))
                                                                              for x in got))]
        finally:
            probe.close()

    def _bad_hellos(self) -> None:
        rep = self.rep
        codec = self.codec
        # an unknown major: the frozen prefix and a body the server cannot read
        nonce = self.nonce()
        obj = msgpack.unpackb(codec.encode(_hello(nonce)))
        obj[0], obj[6], obj[7], obj[8:] = PROTOCOL_MAJOR + 1, [PROTOCOL_MAJOR + 1, 0], [PROTOCOL_MAJOR + 1, 0], ["v+1"]
        got = self._one_hello(msgpack.packb(obj), nonce)
        rej = [m for m in got if isinstance(m, Reject)]
        rep.check("reject-major", bool(rej) and rej[0].code == ErrorCode.UNSUPPORTED_VERSION
                  and rej[0].client_nonce == nonce and rej[0].version_min[0] <= PROTOCOL_MAJOR <= rej[0].version_max[0],
                  f"got {[_describe(m) for m in got] or 'nothing'}")
        nonce = self.nonce()
        got = self._one_hello(codec.encode(_hello(nonce, units="imperial")), nonce)
        rej = [m for m in got if isinstance(m, Reject)]
        rep.check("reject-units", bool(rej) and rej[0].code == ErrorCode.UNSUPPORTED_UNITS and rej[0].client_nonce == nonce,
                  f"got {[_describe(m) for m in got] or 'nothing'}")
        cases = []
        nonce = self.nonce()
        obj = msgpack.unpackb(codec.encode(_hello(nonce)))
        obj[5] = 0
        cases.append(("nonce 0", msgpack.packb(obj), 0))
        for i, what in ((3, "session_id"), (4, "token")):
            nonce = self.nonce()
            obj = msgpack.unpackb(codec.encode(_hello(nonce)))
            obj[i] = 7
            cases.append((f"{what} 7 in the header", msgpack.packb(obj), nonce))
        nonce = self.nonce()
        obj = msgpack.unpackb(codec.encode(_hello(nonce)))
        obj[8] = "x" * 300
        cases.append(("a 300-byte engine string", msgpack.packb(obj), nonce))
        nonce = self.nonce()
        cases.append(("a truncated Hello", codec.encode(_hello(nonce))[:40], nonce))
        nonce = self.nonce()
        obj = msgpack.unpackb(codec.encode(_hello(nonce)))
        obj[11] = math.nan
        cases.append(("mass NaN", msgpack.packb(obj), nonce))
        nonce = self.nonce()
        obj = msgpack.unpackb(codec.encode(_hello(nonce)))
        obj[10] = 9
        cases.append(("tool kind 9", msgpack.packb(obj), nonce))
        problems = []
        for what, packet, nonce in cases:
            got = self._one_hello(packet, nonce)
            rej = [m for m in got if isinstance(m, Reject)]
            if not (rej and rej[0].code == ErrorCode.INVALID_HELLO and rej[0].client_nonce == nonce) or any(
                    isinstance(m, Welcome) for m in got):
                problems.append(f"{what}: {[_describe(m) for m in got] or 'nothing'}")
        rep.check("reject-hello", not problems, "; ".join(problems)[:300])

    def _version_range(self) -> None:
        probe = _Probe(self.url, self.mac)
        try:
            for kind in _KINDS:
                nonce = self.nonce()
                hello = _hello(nonce, kind, version_min=(1, 0), version_max=(3, 0))
                obj = msgpack.unpackb(self.codec.encode(hello))
                obj[0], obj[1] = PROTOCOL_MAJOR, PROTOCOL_MINOR  # written in the major-1 layout
                m = self._hello_exchange(probe, msgpack.packb(obj), nonce)
                if isinstance(m, Reject) and m.code == ErrorCode.UNSUPPORTED_TOOL:
                    continue
                ok = isinstance(m, Welcome) and m.version[0] == PROTOCOL_MAJOR
                self.rep.check("version-range", ok, f"got {_describe(m) if m is not None else 'nothing'}")
                if isinstance(m, Welcome):
                    self._bye(probe, m)
                return
            self.rep.fail("version-range", "every tool kind was refused as unsupported")
        finally:
            probe.close()

    def _open_main(self) -> bool:
        rep = self.rep
        probe = self.probe
        tried = []
        for kind in _KINDS:
            nonce = self.nonce()
            hello = _hello(nonce, kind, epsilon_m=0.05)
            packet = self.codec.encode(hello)
            m = self._hello_exchange(probe, packet, nonce, tries=8)
            if isinstance(m, Reject) and m.code == ErrorCode.UNSUPPORTED_TOOL:
                tried.append(kind.name.lower())
                continue
            break
        else:
            rep.fail("welcome", f"every tool kind was refused as unsupported ({', '.join(tried)})")
            return False
        w = m
        ok = (isinstance(w, Welcome) and w.session_id != 0 and w.token != 0 and w.version[0] == PROTOCOL_MAJOR
              and w.version[1] <= PROTOCOL_MINOR and 1 <= w.max_contacts <= 8 and 0 <= w.epsilon_m <= 0.05
              and w.haptic_rate_hz > 0 and w.silence_timeout_s > w.heartbeat_interval_s > 0)
        rep.check("welcome", ok, f"got {_describe(w) if w is not None else 'nothing'}")
        if not ok:
            return False
        self.kind, self.welcome = kind, w
        notes = []
        if w.epsilon_m < 0.05 and "epsilon" not in w.note:
            notes.append(f"epsilon granted {w.epsilon_m:g} m of 0.05 m asked")
        if w.max_contacts < 8 and "max_contacts" not in w.note:
            notes.append(f"max_contacts granted {w.max_contacts} of 8 asked")
        rep.check("welcome-note", not notes, "; ".join(notes) + f", note {w.note!r}")
        probe.send(packet)
        again = [m for _, m in probe.recv_all(0.3, until=lambda got: any(isinstance(x[1], Welcome) for x in got))
                 if isinstance(m, Welcome)]
        rep.check("hello-repeat", bool(again) and again[0].session_id == w.session_id and again[0].token == w.token,
                  "no Welcome for the repeated Hello" if not again else
                  f"a new session {again[0].session_id:#x} (was {w.session_id:#x})")
        self.pose = self._start_pose(0.0)
        return True

    def _start_pose(self, shift_m: float) -> np.ndarray:
        pose = IDENTITY.copy()
        if self.kind == ToolKind.ONE_DOF:
            pose[0] = 0.004 + shift_m
        elif self.kind == ToolKind.PLANAR:
            pose[:3] = (0.01 + shift_m, 0.03, 0.0)
            pose[3:] = (math.cos(0.1), 0.0, 0.0, math.sin(0.1))  # turned 0.2 rad about +z
        else:
            pose[:3] = (0.01 + shift_m, -0.02, 0.05)
            pose[3:] = (math.cos(0.1), 0.0, math.sin(0.1), 0.0)
        return pose

    def _updates(self) -> None:
        rep = self.rep
        w = self.welcome
        sent: dict[int, float] = {}
        end = time.monotonic() + self.duration_s
        while time.monotonic() < end:
            self.seq += 1
            sent[self.seq] = time.monotonic()
            self.probe.send(self.cu(self.seq))
            self.collect(1.0 / self.rate_hz)
        self.collect(0.1)
        acked = {}
        for t, m in self.states:
            acked.setdefault(m.ack_seq, t)
        hits = [s for s in sent if s in acked]
        rep.check("ack", len(hits) >= 0.9 * len(sent), f"{len(hits)}/{len(sent)} acknowledged")
        lat = [acked[s] - sent[s] for s in hits]
        med = statistics.median(lat) if lat else math.inf
        rep.check("ack-latency", med <= 0.020, f"median {med * 1e3:.2f} ms")
        self._proxy_valid()
        self._initial_pose_rule(self.states, "")
        minor = w.version[1]
        st = [m.server_state for _, m in self.states]
        if minor >= 2:
            # a server may honestly report a fault (say its loop stalled); otherwise it renders
            rendered = [v for v in st if v != ServerState.FAULT]
            engaged = sum(1 for v in rendered if v == ServerState.ENGAGED)
            rep.check("server-state", bool(st) and all(v != ServerState.UNKNOWN for v in st) and bool(rendered)
                      and engaged >= 0.9 * len(rendered),
                      f"server_state of {len(st)} ProxyStates: {sorted(set(int(v) for v in st))}, engaged {engaged}")
        else:
            rep.fail("server-state", f"not judged: the server chose version 1.{minor} (server_state is 1.2)")

    def _proxy_valid(self) -> None:
        w = self.welcome
        pseqs = [m.seq for _, m in self.states]
        bad = [m for _, m in self.states if m.session_id != w.session_id or m.token != w.token or m.ack_seq > self.seq]
        self.rep.check("proxy-valid", not bad and all(b > a for a, b in zip(pseqs, pseqs[1:])) and bool(self.states),
                       f"{len(bad)} with a wrong header or ack_seq, seqs {pseqs[:6]}")
        errs = [m for _, m in self.others if isinstance(m, ProtocolError)]
        self.rep.check("proxy-valid", not errs, str(errs[0])[:160] if errs else "")

    def _initial_pose_rule(self, states, prefix: str) -> None:
        if not states:
            self.rep.fail("initial-pose", prefix + "no ProxyState")
            return
        first = min(states, key=lambda x: x[1].seq)[1]
        p = np.asarray(first.proxy_pose)
        off = float(np.linalg.norm(p[:3] - self.pose[:3]))
        turn = _quat_angle(p[3:], self.pose[3:])
        self.rep.check("initial-pose", off <= 1e-4 and turn <= 1e-3,
                       prefix + f"the first proxy_pose is {off * 1e3:.2f} mm and {math.degrees(turn):.2f} deg from "
                                f"the first tool_pose")

    def _exchange(self, packet: bytes, wait_s: float = 0.15, probe: _Probe | None = None) -> tuple[list, list]:
        """Send one packet; (ProxyStates, other messages) that came back within ``wait_s``."""
        n_s, n_o = len(self.states), len(self.others)
        self._keepalive()
        (probe or self.probe).send(packet)
        self.collect(wait_s)
        return [m for _, m in self.states[n_s:]], [m for _, m in self.others[n_o:]]

    def _keepalive(self) -> None:
        """A valid Heartbeat: packets a server refuses do not keep the session (only accepted
        ones do), so a run of refusals longer than silence_timeout_s would end it."""
        w = self.welcome
        self.hb_seq += 1
        self.probe.send(self.codec.encode(Heartbeat(seq=self.hb_seq, time_s=0.0, session_id=w.session_id,
                                                    token=w.token)))

    def _acked(self, seq: int, wait_s: float = 0.3) -> bool:
        """Send a valid update with ``seq``: whether it is acknowledged."""
        states, _ = self._exchange(self.cu(seq), wait_s)
        return any(m.ack_seq == seq for m in states)

    def _refused(self, rule: str, packet: bytes, seq: int, code: ErrorCode, field_part: str | None,
                 what: str) -> None:
        """``packet`` (with ``seq``) must be answered by Error ``code`` naming ``field_part``, not
        acknowledged; then the same seq, valid, must be (the refused one did not use it up)."""
        states, others = self._exchange(packet)
        errors = [m for m in others if isinstance(m, Error)]
        problems = []
        if any(m.ack_seq == seq for m in states):
            problems.append("acknowledged")
        if not errors:
            problems.append("no Error")
        elif errors[0].code != code or (field_part is not None and field_part not in errors[0].field):
            e = errors[0]
            problems.append(f"Error {_code_name(e.code)} naming {e.field!r}")
        if rule != "seq-jump" and not self._acked(seq):
            problems.append(f"the same seq, valid, was not acknowledged afterwards")
        self.rep.check(rule, not problems, f"{what}: " + ", ".join(problems))
        self.collect(0.1)  # the Error budget refills (error_rate_per_s)

    def _refusals(self) -> None:
        rep = self.rep
        w = self.welcome
        # an older update and a repeat of the newest
        newest = self.seq
        states, _ = self._exchange(self.cu(max(1, newest - 2)))
        dup_states, _ = self._exchange(self.cu(newest))
        rep.check("stale", newest > 2 and not states and not dup_states,
                  f"{len(states)} ProxyState(s) after an old update, {len(dup_states)} after a repeat of the newest")
        # wrongly addressed: never acknowledged, never answered
        self.seq += 1
        problems = []
        for what, kw in (("a wrong token", dict(token=w.token ^ 0xFFFF)),
                         ("a wrong session id", dict(session_id=w.session_id ^ 0x1))):
            states, others = self._exchange(self.cu(self.seq, **kw))
            answers = states + [m for m in others if not isinstance(m, Heartbeat)]  # heartbeats: the session's own
            if answers:
                problems.append(f"{what}: answered with {[_describe(m) for m in answers]}")
        stranger = _Probe(self.url, self.mac)
        try:
            stranger.send(self.cu(self.seq))
            got = [m for _, m in stranger.recv_all(0.15)]
            self.collect(0.01)
            mine = [m for _, m in self.states if m.ack_seq == self.seq]
            if got or mine:
                problems.append(f"from another peer: {len(mine)} acknowledgement(s), {len(got)} answer(s) to it")
        finally:
            stranger.close()
        rep.check("bad-address", not problems, "; ".join(problems))
        if not self._acked(self.seq):
            rep.fail("bad-address", "the seq of the refused updates was not accepted afterwards")
        self.seq += 1
        self._refused("invalid", self.cu(self.seq, poison="nan"), self.seq, ErrorCode.NON_FINITE, None,
                      "separation NaN")
        self.seq += 1
        n = w.max_contacts + 1
        if n <= self.codec.limits.max_contacts:
            self._refused("capacity", self.cu(self.seq, n=n), self.seq, ErrorCode.TOO_MANY_CONTACTS, None,
                          f"{n} contacts (granted {w.max_contacts})")
        else:
            rep.check("capacity", True)
        if w.version[1] >= 2:
            for poison, fld in (("tool_pose", "tool_pose"), ("position", "position"), ("v_constr", "v_constr"),
                                ("separation", "separation")):
                self.seq += 1
                self._refused("out-of-bounds", self.cu(self.seq, poison=poison), self.seq, ErrorCode.OUT_OF_BOUNDS,
                              fld, f"{poison} beyond the bound")
        else:
            rep.fail("out-of-bounds", f"not judged: the server chose version 1.{w.version[1]} (no scene bounds)")
        cases = [("tool_link", "contact_keys.tool_link", "tool link 1 on a rigid tool"),
                 ("joints", "tool_joint_position", "joint positions for a rigid tool")]
        if self.kind == ToolKind.PLANAR:
            cases.append(("normal_z", "contact_data.normal", "a normal with z on a planar tool"))
        for poison, fld, what in cases:
            self.seq += 1
            self._refused("unusable", self.cu(self.seq, poison=poison), self.seq, ErrorCode.UNUSABLE, fld, what)
        self._refused("seq-jump", self.cu((1 << 64) - 1), (1 << 64) - 1, ErrorCode.SEQ_JUMP, "seq", "seq 2^64-1")
        self.seq += 1
        rep.check("seq-jump", self._acked(self.seq), "the next seq was not acknowledged after the jump")

    def _heartbeat(self) -> None:
        interval = self.welcome.heartbeat_interval_s
        n = len(self.others)
        self.collect(2 * interval + 0.05)
        w = self.welcome
        hbs = [m for _, m in self.others[n:] if isinstance(m, Heartbeat) and m.session_id == w.session_id
               and m.token == w.token]
        self.rep.check("heartbeat", bool(hbs), f"no Heartbeat in {2 * interval + 0.05:.2f} s of quiet")

    def _restart(self) -> None:
        rep = self.rep
        old = self.welcome
        nonce = self.nonce()
        hello = _hello(nonce, self.kind, epsilon_m=0.05)
        m = self._hello_exchange(self.probe, self.codec.encode(hello), nonce)
        if not isinstance(m, Welcome):
            rep.fail("restart", f"a Hello with a new nonce got {_describe(m) if m is not None else 'nothing'}")
            return
        problems = []
        if m.session_id == old.session_id:
            problems.append("the same session id")
        self.welcome = m
        # the old session's token is dead
        states, others = self._exchange(self.cu(self.seq + 1, session_id=old.session_id, token=old.token))
        if states or [o for o in others if isinstance(o, Error)]:
            problems.append("the old session still answers")
        # the new session: its proxy starts at its own first pose (a real server may first let
        # the previous session's force fade out: its updates are acknowledged once it has)
        self.pose = self._start_pose(0.005)
        self.seq = 0
        self.states.clear()
        end = time.monotonic() + 2.0
        while time.monotonic() < end and not self.states:
            self.seq += 1
            self.probe.send(self.cu(self.seq))
            self.collect(1.0 / self.rate_hz)
        if not self.states:
            problems.append("no update of the new session acknowledged within 2 s")
        rep.check("restart", not problems, "; ".join(problems))
        if self.states:
            self._initial_pose_rule(self.states, "new session: ")

    def _heartbeat_session(self) -> None:
        w = self.welcome
        span = 2.0 * w.silence_timeout_s
        end = time.monotonic() + span
        n = len(self.others)
        while time.monotonic() < end:
            self.hb_seq += 1
            self.probe.send(self.codec.encode(Heartbeat(seq=self.hb_seq, time_s=0.0, session_id=w.session_id,
                                                        token=w.token)))
            self.collect(min(w.heartbeat_interval_s / 2, 0.05))
        byes = [m for _, m in self.others[n:] if isinstance(m, Bye)]
        problems = [f"Bye {_code_name(byes[0].code)} while our Heartbeats came"] if byes else []
        acked = False
        for _ in range(30):
            self.seq += 1
            if self._acked(self.seq, wait_s=1.0 / self.rate_hz + 0.02):
                acked = True
                break
        if not acked:
            problems.append("updates after the Heartbeats were not acknowledged")
        self.rep.check("heartbeat-session", not problems, "; ".join(problems))

    def _bye_rule(self) -> None:
        w = self.welcome
        self._bye(self.probe, w)
        self.collect(0.05)
        self.seq += 1
        states, others = self._exchange(self.cu(self.seq))
        self.rep.check("bye", not [m for m in states if m.ack_seq == self.seq], "an update after Bye was acknowledged")

    def _silence(self) -> None:
        nonce = self.nonce()
        t_sent = time.monotonic()
        m = self._hello_exchange(self.probe, self.codec.encode(_hello(nonce, self.kind)), nonce, tries=1, wait_s=0.5)
        if not isinstance(m, Welcome):
            self.rep.fail("silence", f"a new session could not be opened: {_describe(m) if m else 'nothing'}")
            return
        timeout = m.silence_timeout_s
        got = self.probe.recv_all(timeout + 1.0, until=lambda got: any(isinstance(x[1], Bye) for x in got))
        byes = [(t, b) for t, b in got if isinstance(b, Bye)]
        if not byes:
            self.rep.fail("silence", f"no Bye within {timeout + 1.0:g} s of silence (silence_timeout_s {timeout:g})")
            return
        t, b = byes[0]
        after = t - t_sent
        self.rep.check("silence", b.code == ErrorCode.BYE_TIMEOUT and timeout - 0.05 <= after <= timeout + 0.5,
                       f"Bye {_code_name(b.code)} {after:.2f} s after our last packet (silence_timeout_s {timeout:g})")


def _code_name(code: int) -> str:
    return ErrorCode(code).name if code in ErrorCode._value2member_map_ else str(code)


def _describe(m) -> str:
    if isinstance(m, Reject):
        return f"Reject {_code_name(m.code)} ({m.reason[:60]})"
    if isinstance(m, Error):
        return f"Error {_code_name(m.code)} naming {m.field!r}"
    if isinstance(m, Welcome):
        return f"Welcome {m.version[0]}.{m.version[1]} session {m.session_id:#x}"
    if isinstance(m, ProtocolError):
        return f"undecodable ({m.code.name})"
    return type(m).__name__


def check_server(url: str, *, duration_s: float = 1.0, hmac_key: bytes | None = None, rate_hz: float = 60.0) -> Report:
    """Play the scripted client against the server at ``url`` and judge it. ``duration_s``:
    seconds of ContactUpdates at ``rate_hz`` in the acknowledgement scenario."""
    rep = Report(SERVER_RULES)
    _ScriptedClient(url, rep, MacFramer(hmac_key) if hmac_key else None, duration_s, rate_hz).run()
    return rep


# ======================================================================== reference peers
def run_reference_server(transport, stop: threading.Event, *, config: ServerConfig | None = None,
                         hmac_key: bytes | None = None, period_s: float = 0.001,
                         proxy_start: str = "origin") -> ServerEndpoint:
    """The project's reference server loop: a stand-in local model whose proxy stays put and is
    reported engaged. ``proxy_start``: ``"origin"`` (the identity pose; the engine tests' stand-in
    drives a tool onto the origin with it) or ``"first-update"`` (as SPEC says a server does: the
    pose of each session's first ContactUpdate). Runs until ``stop`` is set; returns the endpoint
    (for its counters)."""
    if proxy_start not in ("origin", "first-update"):
        raise ValueError(f"proxy_start: 'origin' or 'first-update', got {proxy_start!r}")
    server = ServerEndpoint(transport.send, config, hmac_key=hmac_key)
    poses: dict[int, np.ndarray] = {}
    while not stop.is_set():
        now = time.monotonic_ns()
        for data, peer in transport.drain():
            update = server.receive(data, peer, now)
            if update is not None:
                sid = update.session_id
                if proxy_start == "origin":
                    pose = IDENTITY
                else:
                    pose = poses.setdefault(sid, np.array(update.tool_pose))
                server.send_proxy_state(sid, now, pose, _ZERO6, _ZERO6, server_state=ServerState.ENGAGED)
        for sid in [s for s in poses if s not in server.sessions]:
            del poses[sid]
        server.poll(now)
        time.sleep(period_s)
    server.close_all()
    return server


_REF_START = np.array([0.04, -0.03, 0.0215, 1.0, 0.0, 0.0, 0.0])
_REF_HALF_M = (0.03, 0.03, 0.02)


def _reference_contacts(pose: np.ndarray, n: int, epsilon_m: float):
    """The reference tool: a box (half sizes _REF_HALF_M) over a floor at z = 0; its n bottom
    vertices (n <= 4; more repeat none) within epsilon, as vertex-face contacts."""
    w, x, y, z = pose[3:]
    R = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                  [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                  [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
    hx, hy, hz = _REF_HALF_M
    corners = np.array([[-hx, -hy, -hz], [hx, -hy, -hz], [hx, hy, -hz], [-hx, hy, -hz]])[:n]
    world = corners @ R.T + pose[:3]
    near = world[:, 2] <= epsilon_m
    idx = np.flatnonzero(near)
    m = idx.shape[0]
    keys = np.column_stack([np.zeros(m), np.ones(m), idx]).astype(np.int64)
    pos = np.column_stack([world[idx, 0], world[idx, 1], np.zeros(m)])
    nor = np.tile([0.0, 0.0, 1.0], (m, 1))
    return keys, pos, nor, world[idx, 2].copy(), np.zeros(m)


def run_reference_client(transport, stop: threading.Event, *, rate_hz: float = 60.0, n_contacts: int = 4,
                         hmac_key: bytes | None = None, duration_s: float | None = None,
                         reconnect_delay_s: float = 1.0) -> ClientEndpoint:
    """The project's reference environment client: a kinematic box tool (spatial) over a floor,
    its up to 4 bottom vertices reported as vertex-face contacts within the granted epsilon,
    stepped at ``rate_hz``. It starts at a pose of its own, holds it until the first ProxyState,
    then takes the newest proxy pose whenever the server renders it (``server_state`` engaged or
    not reported) and holds its pose otherwise; it reconnects ``reconnect_delay_s`` after a
    session ends and gives up on a Reject. Stops on ``stop``, a Reject, or after ``duration_s``
    (then it sends Bye). Returns the last endpoint."""
    hello = _hello(0, max_contacts=n_contacts)
    hello.engine = "hapticproxy-reference-client"
    hello.inertia_kg_m2 = (1e-4, 1e-4, 1e-4, 0.0, 0.0, 0.0)
    cfg = ClientConfig()
    pose = _REF_START.copy()
    client = ClientEndpoint(transport.send, hello, cfg, hmac_key=hmac_key)
    client.start()
    step = 0
    t0 = time.monotonic()
    next_step = t0
    restart_at = None
    while not stop.is_set():
        now = time.monotonic_ns()
        while (got := transport.recv()) is not None:
            state = client.receive(got[0], got[1], now)
            if state is not None and state.server_state in _FOLLOW_STATES:
                pose = np.array(state.proxy_pose)
        if client.state == ClientState.REJECTED:
            break
        if client.state == ClientState.CLOSED:
            if restart_at is None:
                restart_at = time.monotonic() + reconnect_delay_s
            elif time.monotonic() >= restart_at:
                restart_at = None
                client = ClientEndpoint(transport.send, hello, cfg, hmac_key=hmac_key)
                client.start()
            time.sleep(0.002)
            continue
        if duration_s is not None and time.monotonic() - t0 >= duration_s:
            client.close(now_ns=now)
            break
        if time.monotonic() >= next_step:
            if client.established:
                step += 1
                n = min(n_contacts, client.welcome.max_contacts, 4)
                client.send_contacts(now, step / rate_hz, pose, *_reference_contacts(pose, n, client.welcome.epsilon_m))
            next_step += 1.0 / rate_hz
        client.poll(now)
        time.sleep(0.0005)
    return client


# ------------------------------------------------------------------------------ CLI
def _direction(text: str):
    try:
        v = [float(x) for x in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected X,Y,Z, got {text!r}") from None
    if len(v) != 3:
        raise argparse.ArgumentTypeError(f"expected 3 numbers X,Y,Z, got {text!r}")
    return v


def _check_device(argv: list[str]) -> int:
    try:
        mod = importlib.import_module("hapticproxy.protocol.device_conformance")
    except ModuleNotFoundError as exc:
        if exc.name != "hapticproxy.protocol.device_conformance":
            raise
        print("hapticproxy protocol check-device: the remote-device link's conformance kit "
              "(hapticproxy.protocol.device_conformance) is not in this build", file=sys.stderr)
        return 2
    return int(mod.main(argv) or 0)


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] == "check-device":
        return _check_device(argv[1:])
    parser = argparse.ArgumentParser(prog="hapticproxy protocol", description="Protocol v1 conformance kit.")
    sub = parser.add_subparsers(dest="mode", required=True)
    pc = sub.add_parser("check-client", help="play a scripted server and judge the client that connects")
    pc.add_argument("--listen", default="udp://127.0.0.1:9870", help="transport URL to listen on")
    pc.add_argument("--duration", type=float, default=0.5,
                    help="seconds the proxy is held at the client's first pose (default 0.5); the whole check "
                         "takes about 15 s")
    pc.add_argument("--timeout", type=float, default=30.0, help="seconds to wait for the client's Hello")
    pc.add_argument("--step", type=float, default=0.01, help="how far the proxy is moved [m] (default 0.01)")
    pc.add_argument("--direction", type=_direction, default=None,
                    help="X,Y,Z: the direction the proxy is moved in (default: away from the first contacts; "
                         "else +y planar, +z spatial, +axis 1-DOF); it must be free for that distance")
    ps = sub.add_parser("check-server", help="play a scripted client and judge the server")
    ps.add_argument("--connect", default="udp://127.0.0.1:9870", help="transport URL of the server")
    ps.add_argument("--duration", type=float, default=1.0, help="seconds of ContactUpdates to acknowledge")
    sub.add_parser("check-device", help="the remote-device link's kit (arguments: check-device --help)")
    for p in (pc, ps):
        p.add_argument("--hmac-key-file", default=None,
                       help="file holding the shared secret as hex (mode 600); or set HAPTICPROXY_HMAC_KEY[_FILE]")
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:
        return int(exc.code or 0) and 2
    try:
        key = load_hmac_key(args.hmac_key_file)
        if args.mode == "check-client":
            t = _open(args.listen, "server")
            print(f"check-client: listening on {t.url}", flush=True)
            try:
                rep = check_client(t, duration_s=args.duration, hmac_key=key, timeout_s=args.timeout,
                                   step_m=args.step, direction=args.direction)
            finally:
                t.close()
        else:
            rep = check_server(args.connect, duration_s=args.duration, hmac_key=key)
    except (OSError, ValueError, TransportError) as exc:
        print(f"hapticproxy protocol {args.mode}: {exc}", file=sys.stderr)
        return 2
    print("\n".join(rep.lines()))
    return rep.exit_code


if __name__ == "__main__":
    sys.exit(main())
