"""Protocol v1 session layer: transport-agnostic server and client endpoints.

Both endpoints work on whole datagrams (``bytes``) and an opaque ``peer`` id, so they run over any
transport of :mod:`hapticproxy.protocol.transport` (or a test loopback). They never block and
their receive path never raises on bad input: every dropped packet is counted in
:class:`SessionCounters` (and, where a session exists and the packet is attributable to it, answered
by a rate-limited ``Error``). Time is passed in explicitly (``now_ns``, a monotonic clock in ns)
so the haptic loop owns the clock and tests need no sleeping.

Server loop, once per haptic step (the paper's section V)::

    for data, peer in transport.drain():
        update = server.receive(data, peer, now_ns)      # ContactUpdate | None
        if update is not None:
            model.update(update.keys, ...)               # newest-wins and the bounds already enforced
            server.send_proxy_state(update.session_id, now_ns, pose, twist, wrench)
    server.poll(now_ns)                                  # heartbeats, silence timeouts
    fade = server.sessions[sid].silence_ns(now_ns)       # how long the environment is silent

Environment client, once per simulation step::

    client.send_contacts(now_ns, env_time_s, tool_pose, keys, position_m, normal, separation_m, v_constr)
    while (got := transport.recv()) is not None:
        state = client.receive(got[0], got[1], now_ns)   # ProxyState | None
    client.poll(now_ns)                                  # Hello retries, heartbeats, timeouts
"""
from __future__ import annotations

import hmac
import logging
import os
import secrets
import time
from collections.abc import Callable, Hashable
from dataclasses import InitVar, dataclass, field

import numpy as np

from .codec import (
    Bye,
    Codec,
    ContactUpdate,
    Error,
    Heartbeat,
    Hello,
    Limits,
    ProtocolError,
    ProxyState,
    Reject,
    Welcome,
)
from .messages import MAX_ABS_FLOAT, PROTOCOL_MAJOR, PROTOCOL_MINOR, UNIT_TOLERANCE

#: the server's session layer (refusals): in the loop process, whose log lines the supervisor's
#: terminal shows ("hapticproxy loop: ...")
_log = logging.getLogger("hapticproxy.loop")
from .vocab import TOOL_KIND_NAMES, ErrorCode, MessageType, ToolKind

__all__ = [
    "ClientConfig",
    "ClientEndpoint",
    "ClientState",
    "HMAC_KEY_ENV",
    "HMAC_KEY_FILE_ENV",
    "HMAC_TAG_BYTES",
    "MacFramer",
    "ServerConfig",
    "ServerEndpoint",
    "ServerSession",
    "SessionCounters",
    "load_hmac_key",
]

Peer = Hashable
_NS = 1_000_000_000
_NO_JOINTS = np.zeros(0)
_NO_JOINTS.flags.writeable = False

# ------------------------------------------------------------------------ shared secret
#: Bytes of HMAC-SHA256 appended to every datagram in shared-secret mode (truncated tag, 128 bit).
HMAC_TAG_BYTES = 16
#: Environment variable holding the key as hex (at least 32 hex digits = 16 bytes).
HMAC_KEY_ENV = "HAPTICPROXY_HMAC_KEY"
#: Environment variable holding the path of a key file (hex key on its first line).
HMAC_KEY_FILE_ENV = "HAPTICPROXY_HMAC_KEY_FILE"
_MIN_KEY_BYTES = 16


def _parse_key(text: str, where: str) -> bytes:
    try:
        key = bytes.fromhex(text.strip())
    except ValueError:
        raise ValueError(f"HMAC key from {where} must be hex digits") from None
    if len(key) < _MIN_KEY_BYTES:
        raise ValueError(f"HMAC key from {where} must be at least {_MIN_KEY_BYTES} bytes ({2 * _MIN_KEY_BYTES} hex digits)")
    return key


def load_hmac_key(path: str | os.PathLike | None = None, *, environ: dict | None = None) -> bytes | None:
    """The shared secret for HMAC mode, or ``None`` if none is configured.

    Sources, first match wins: the key file ``path`` (from the caller's config file, never from
    the command line), the file named by ``$HAPTICPROXY_HMAC_KEY_FILE``, the hex key in
    ``$HAPTICPROXY_HMAC_KEY``. A key file holds the key as hex on its first line; it should be
    readable by its owner only (a warning-free refusal is not attempted: permissions are the
    deployer's job, but group/other-readable files are rejected with ``ValueError``).
    """
    env = os.environ if environ is None else environ
    if path is None:
        path = env.get(HMAC_KEY_FILE_ENV) or None
    if path is not None:
        st = os.stat(path)
        if st.st_mode & 0o077:
            raise ValueError(f"HMAC key file {os.fspath(path)!r} must not be readable by group or others (chmod 600)")
        with open(path, encoding="ascii") as fh:
            return _parse_key(fh.readline(), f"file {os.fspath(path)!r}")
    text = env.get(HMAC_KEY_ENV)
    if text:
        return _parse_key(text, f"${HMAC_KEY_ENV}")
    return None



def _unwrap(endpoint, data):
    """The common front of both endpoints' receive paths: size check, HMAC check, decode.
    Returns the message, a counted ProtocolError, or None when the datagram was dropped (and
    counted) before decoding."""
    c = endpoint.counters
    if len(data) > endpoint._max_datagram:
        c.oversize += 1
        endpoint.codec.counters.count(ErrorCode.OVERSIZE)
        return None
    if endpoint._mac is not None:
        packet = endpoint._mac.open(data)
        if packet is None:
            c.bad_mac += 1
            return None
        data = packet
    msg = endpoint.codec.try_decode(data)
    if isinstance(msg, ProtocolError):
        c.decode_errors += 1
    return msg

class MacFramer:
    """Shared-secret framing: ``datagram = packet || HMAC-SHA256(key, packet)[:16]``."""

    __slots__ = ("_key",)

    def __init__(self, key: bytes) -> None:
        if not isinstance(key, (bytes, bytearray)) or len(key) < _MIN_KEY_BYTES:
            raise ValueError(f"HMAC key must be at least {_MIN_KEY_BYTES} bytes")
        self._key = bytes(key)

    def seal(self, packet: bytes) -> bytes:
        return packet + hmac.digest(self._key, packet, "sha256")[:HMAC_TAG_BYTES]

    def open(self, datagram) -> bytes | None:
        """The packet if the tag verifies, else ``None``."""
        if len(datagram) <= HMAC_TAG_BYTES:
            return None
        packet = bytes(datagram[:-HMAC_TAG_BYTES])
        tag = hmac.digest(self._key, packet, "sha256")[:HMAC_TAG_BYTES]
        if not hmac.compare_digest(tag, bytes(datagram[-HMAC_TAG_BYTES:])):
            return None
        return packet


# ----------------------------------------------------------------------------- counters
class SessionCounters:
    """Plain-int counters of one endpoint (decoder rejections live in ``endpoint.codec.counters``).

    received / accepted: datagrams handed to ``receive`` / that changed state or were returned.
    Drops: ``decode_errors`` (see codec counters for the code), ``bad_mac``, ``oversize``,
    ``unknown_session``, ``bad_token``, ``wrong_peer``, ``stale``, ``duplicate``, ``unexpected``
    (type not valid for this side or state), ``capacity_exceeded`` (more contacts than granted).
    ``seq_jump``: a seq more than ``max_seq_jump`` ahead of the newest accepted (refused with
    ``Error`` SEQ_JUMP naming ``seq``). ContactUpdates refused before they reach the model:
    ``out_of_bounds`` (outside the scene bounds granted in Welcome; by reason
    ``oob_workspace``, ``oob_speed``, ``oob_separation``) and ``unusable`` (contacts the session's
    tool cannot have; by reason ``unusable_normal_z``, ``unusable_tool_link``,
    ``unusable_joints``), each answered with ``Error`` naming the field.
    ``lost``: sequence numbers skipped (gaps; informative, those packets may still arrive late
    and are then counted stale). Sent: ``sent``, ``errors_sent``, ``errors_suppressed`` (over the
    Error rate limit), ``welcomes_sent``, ``rejects_sent``, ``byes_sent``, ``heartbeats_sent``,
    ``hellos_sent``. Events: ``hello_repeats``, ``sessions_opened``, ``sessions_closed``,
    ``timeouts``, ``byes_received``, ``errors_received``.
    """

    __slots__ = (
        "received", "accepted", "decode_errors", "bad_mac", "oversize", "unknown_session", "bad_token",
        "wrong_peer", "stale", "duplicate", "lost", "unexpected", "capacity_exceeded", "seq_jump",
        "out_of_bounds", "oob_workspace", "oob_speed", "oob_separation",
        "unusable", "unusable_normal_z", "unusable_tool_link", "unusable_joints", "sent", "errors_sent",
        "errors_suppressed", "welcomes_sent", "rejects_sent", "byes_sent", "heartbeats_sent", "hellos_sent",
        "hello_repeats", "sessions_opened", "sessions_closed", "timeouts", "byes_received", "errors_received",
    )

    def __init__(self) -> None:
        for name in self.__slots__:
            setattr(self, name, 0)

    def as_dict(self) -> dict[str, int]:
        return {name: getattr(self, name) for name in self.__slots__}

    @property
    def dropped(self) -> int:
        """All datagrams dropped for any reason."""
        return (self.decode_errors + self.bad_mac + self.oversize + self.unknown_session + self.bad_token
                + self.wrong_peer + self.stale + self.duplicate + self.unexpected + self.capacity_exceeded
                + self.seq_jump + self.out_of_bounds + self.unusable)

    def __repr__(self) -> str:
        return "SessionCounters(" + ", ".join(f"{k}={v}" for k, v in self.as_dict().items() if v) + ")"


class _RateLimit:
    """Token bucket: at most ``rate_per_s`` events per second, bursts of ``burst``."""

    __slots__ = ("rate_per_ns", "burst", "tokens", "last_ns")

    def __init__(self, rate_per_s: float, burst: float, now_ns: int) -> None:
        self.rate_per_ns = rate_per_s / _NS
        self.burst = burst
        self.tokens = burst
        self.last_ns = now_ns

    def take(self, now_ns: int) -> bool:
        self.tokens = min(self.burst, self.tokens + (now_ns - self.last_ns) * self.rate_per_ns)
        self.last_ns = now_ns
        if self.tokens >= 1.0:
            self.tokens -= 1.0
            return True
        return False


class _SeqWindow:
    """Newest-wins acceptance of one sequence stream."""

    __slots__ = ("newest",)

    def __init__(self) -> None:
        self.newest = 0

    def jumps(self, seq: int, max_jump: int) -> bool:
        """Whether ``seq`` lies more than ``max_jump`` ahead of the newest accepted: refused, so
        one bad seq (say 2^64-1) cannot make every later packet of the session stale."""
        return seq - self.newest > max_jump

    def accept(self, seq: int, counters: SessionCounters) -> bool:
        newest = self.newest
        if seq > newest:
            counters.lost += seq - newest - 1
            self.newest = seq
            return True
        if seq == newest:
            counters.duplicate += 1
        else:
            counters.stale += 1
        return False


def _now(now_ns: int | None) -> int:
    return time.monotonic_ns() if now_ns is None else now_ns


# ------------------------------------------------------------------------------- server
_max_reduce = np.maximum.reduce
_abs = np.abs


@dataclass(frozen=True)
class ServerConfig:
    """What the server grants and how it polices sessions."""

    haptic_rate_hz: float = 1000.0
    max_epsilon_m: float = 0.01  # granted epsilon = min(requested, this)
    max_contacts: int = 64  # granted capacity = min(requested, this, limits.max_contacts)
    heartbeat_interval_s: float = 0.1
    silence_timeout_s: float = 1.0
    max_sessions: int = 1
    error_rate_per_s: float = 10.0  # Error replies per session, token bucket of the same burst
    supported_tools: frozenset = frozenset(ToolKind)
    server_name: str = "hapticproxy"
    limits: Limits = field(default_factory=Limits)
    #: The server's own check of a decoded Hello's content (e.g. a linkage its model cannot
    #: hold): returns "" to accept, or the reason to refuse it with Reject INVALID_HELLO.
    hello_check: Callable[[Hello], str] | None = None
    #: Scene bounds, told to the client in Welcome (1.2) and enforced on every ContactUpdate
    #: before it reaches the model (Error OUT_OF_BOUNDS naming the field): every contact
    #: position and the tool pose's position within +-workspace_extent_m of the origin on each
    #: axis, |v_constr| <= max_constraint_speed_m_per_s, |separation| <= max_separation_m.
    workspace_extent_m: float = 10.0
    max_constraint_speed_m_per_s: float = 10.0
    max_separation_m: float = 1.0
    #: Largest forward jump of a sequence number (a gap of lost packets); a larger one is
    #: refused with Error SEQ_JUMP naming seq.
    max_seq_jump: int = 1 << 16
    #: Told in Welcome: the server's force fades when no ContactUpdate was applied for this long
    #: (its ``safety.watchdog_s``); 0: not told.
    update_watchdog_s: float = 0.0

    def __post_init__(self) -> None:
        for name in ("haptic_rate_hz", "heartbeat_interval_s", "silence_timeout_s", "error_rate_per_s",
                     "workspace_extent_m", "max_constraint_speed_m_per_s", "max_separation_m"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and np.isfinite(v) and v > 0):
                raise ValueError(f"ServerConfig.{name} must be a finite number > 0, got {v!r}")
        if not (isinstance(self.max_epsilon_m, (int, float)) and 0 <= self.max_epsilon_m < 1):
            raise ValueError(f"ServerConfig.max_epsilon_m must be in [0, 1) m, got {self.max_epsilon_m!r}")
        if not (isinstance(self.max_contacts, int) and 1 <= self.max_contacts <= self.limits.max_contacts):
            raise ValueError(f"ServerConfig.max_contacts must be in [1, limits.max_contacts={self.limits.max_contacts}]")
        for name in ("workspace_extent_m", "max_constraint_speed_m_per_s", "max_separation_m"):
            if getattr(self, name) > MAX_ABS_FLOAT:
                raise ValueError(f"ServerConfig.{name} must be <= {MAX_ABS_FLOAT:g}, got {getattr(self, name)!r}")
        if not (isinstance(self.max_seq_jump, int) and self.max_seq_jump >= 1):
            raise ValueError(f"ServerConfig.max_seq_jump must be an int >= 1, got {self.max_seq_jump!r}")
        if not (isinstance(self.max_sessions, int) and self.max_sessions >= 1):
            raise ValueError(f"ServerConfig.max_sessions must be an int >= 1, got {self.max_sessions!r}")
        if self.silence_timeout_s <= self.heartbeat_interval_s:
            raise ValueError("ServerConfig.silence_timeout_s must exceed heartbeat_interval_s")


@dataclass(slots=True, eq=False, repr=False)
class ServerSession:
    """One client's session on the server. Read-only for the server loop. Opened at ``now_ns``
    (its clocks start there); its Error replies are paced at ``error_rate_per_s``."""

    session_id: int
    token: int
    peer: Peer
    hello: Hello
    welcome: Welcome
    welcome_packet: bytes
    now_ns: InitVar[int]
    error_rate_per_s: InitVar[float]
    opened_ns: int = field(init=False)
    last_rx_ns: int = field(init=False)
    last_tx_ns: int = field(init=False)
    #: newest ContactUpdate accepted (= what ProxyState acks)
    contact_seq: _SeqWindow = field(init=False, default_factory=_SeqWindow)
    heartbeat_seq: _SeqWindow = field(init=False, default_factory=_SeqWindow)
    proxy_seq: int = field(init=False, default=0)  # last ProxyState seq sent
    heartbeat_tx_seq: int = field(init=False, default=0)
    errors: _RateLimit = field(init=False)
    planar: bool = field(init=False)
    #: links a contact may name (tool_link < this) and joint positions an update may carry
    n_links: int = field(init=False)
    n_joints: int = field(init=False)
    #: (workspace_extent_m, max_constraint_speed_m_per_s, max_separation_m) of the Welcome
    bounds: tuple[float, float, float] = field(init=False)
    #: ``fast(cols, normal, keys, extent_m, speed_m_per_s, separation_m, n_links, planar) -> bool``:
    #: may vouch for an update's contacts before :meth:`check_update`'s own rules (the server's
    #: kernel, ``ServerEndpoint(update_check=...)``); ``False`` leaves the decision to them
    update_check: Callable | None = None

    def __post_init__(self, now_ns: int, error_rate_per_s: float) -> None:
        self.opened_ns = self.last_rx_ns = self.last_tx_ns = now_ns
        self.errors = _RateLimit(error_rate_per_s, error_rate_per_s, now_ns)
        kind = self.hello.tool_kind
        self.planar = kind == ToolKind.PLANAR
        self.n_links = len(self.hello.links) if kind == ToolKind.LINKAGE else 1
        self.n_joints = max(0, self.n_links - 1)
        w = self.welcome
        # floats, whatever the config held: the server's bounds kernel has one signature
        self.bounds = (float(w.workspace_extent_m), float(w.max_constraint_speed_m_per_s), float(w.max_separation_m))

    # the grant, as the Welcome sent it
    @property
    def version(self) -> tuple[int, int]:
        return self.welcome.version

    @property
    def epsilon_m(self) -> float:
        return self.welcome.epsilon_m

    @property
    def max_contacts(self) -> int:
        return self.welcome.max_contacts

    def check_update(self, msg: ContactUpdate) -> tuple[str, str, str] | None:
        """Why the model could not take this update: ``(counter, field, detail)``, or ``None``.
        A fixed handful of ufunc reductions whatever n is (each column block's extremes; the
        tool links'; a planar tool's normal z), unless :attr:`update_check` vouches for the
        contacts first."""
        extent, speed, sep = self.bounds
        x, y, z = msg.tool_pose.tolist()[:3]
        if not (-extent <= x <= extent and -extent <= y <= extent and -extent <= z <= extent):
            return "oob_workspace", "tool_pose", f"position ({x:g}, {y:g}, {z:g}) m outside +-{extent:g} m"
        joints = msg.tool_joint_position.shape[0]
        if joints and joints != self.n_joints:
            return ("unusable_joints", "tool_joint_position",
                    f"{joints} joint positions for a tool with {self.n_joints} joints")
        n = msg.contact_count
        if not n:
            return None
        # the decoder's (column blocks, n) view of contact_data: rows 0-2 hold the 3n position
        # values, 3-5 the normals, 6 separation, 7 v_constr (then any blocks of a later minor)
        cols = msg.contact_columns
        fast = self.update_check
        if fast is not None and fast(cols, msg.normal, msg.keys, extent, speed, sep, self.n_links, self.planar):
            return None
        if cols.shape[0] != 8:
            cols = cols[:8]
        top = _max_reduce(_abs(cols), 1).tolist()  # per block: the largest magnitude
        worst = max(top[0], top[1], top[2])
        if worst > extent:
            return "oob_workspace", "contact_data.position_m", f"|component| {worst:g} m > {extent:g} m"
        if top[7] > speed:
            return ("oob_speed", "contact_data.v_constr_m_per_s",
                    f"|v_constr| {top[7]:g} m/s > max_constraint_speed_m_per_s {speed:g}")
        if top[6] > sep:
            return "oob_separation", "contact_data.separation_m", f"|separation| {top[6]:g} m > max_separation_m {sep:g}"
        # one reduction: as uint64 a negative link is huge, so max < n_links checks both ends
        links = msg.keys[:, 0]
        if int(_max_reduce(links.view(np.uint64))) >= self.n_links:
            bad = int(links[(links < 0) | (links >= self.n_links)][0])
            return ("unusable_tool_link", "contact_keys.tool_link",
                    f"tool_link must be in 0..{self.n_links - 1} for this tool, got {bad}")
        if self.planar:
            worst = float(_max_reduce(_abs(msg.normal[:, 2])))
            if worst > UNIT_TOLERANCE:
                return ("unusable_normal_z", "contact_data.normal",
                        f"a planar tool's normals lie in the x-y plane, got |n_z| = {worst:g}")
        return None

    @property
    def acked_seq(self) -> int:
        """seq of the newest ContactUpdate accepted (0 before the first)."""
        return self.contact_seq.newest

    def silence_ns(self, now_ns: int) -> int:
        """Time since the last valid packet from the client, in ns (the loop fades forces on it)."""
        return now_ns - self.last_rx_ns

    def __repr__(self) -> str:
        return f"ServerSession(id={self.session_id}, peer={self.peer!r}, tool={self.hello.tool_kind.name})"


class ServerEndpoint:
    """The haptics server's side of protocol v1 (see module docstring for the loop).

    ``send(data, peer)`` is called for every outgoing datagram (e.g. ``transport.send``); its
    return value is ignored (a lost datagram is the protocol's normal case).
    """

    def __init__(self, send: Callable[[bytes, Peer], object], config: ServerConfig | None = None, *,
                 hmac_key: bytes | None = None, codec: Codec | None = None, update_check=None,
                 update_parser=None) -> None:
        self.config = config or ServerConfig()
        self.codec = codec or Codec(self.config.limits)
        #: may vouch for a ContactUpdate's contacts (see ``ServerSession.check_update``)
        self._update_check = update_check
        #: may decode and vouch for a whole ContactUpdate datagram of the session that sent the
        #: last one accepted (the server's kernel, ``server/ingest.py``): ``parser(data)`` returns
        #: the update only when it is sure the codec and that session would accept it (``None``:
        #: not sure, and they decide as always); ``parser.expect(session, max_seq_jump)`` names
        #: the session, ``parser.accepted(seq)`` tells it the newest seq. Never with HMAC framing.
        self._parser = update_parser if hmac_key is None else None
        self._expected: ServerSession | None = None
        self.counters = SessionCounters()
        self.sessions: dict[int, ServerSession] = {}
        self._send = send
        self._mac = MacFramer(hmac_key) if hmac_key is not None else None
        self._max_datagram = self.codec.limits.max_packet_bytes + (HMAC_TAG_BYTES if self._mac else 0)
        self._hb_ns = int(self.config.heartbeat_interval_s * _NS)
        self._timeout_ns = int(self.config.silence_timeout_s * _NS)
        self._rx_len = 0  # length of the datagram being handled (a Reject never exceeds it)
        self._refusal_logged_s = -1e9  # when a refusal was last logged (monotonic s)
        self._refusals_unlogged = 0

    # -------------------------------------------------------------------------- sending
    def _emit(self, packet: bytes, peer: Peer) -> None:
        if self._mac is not None:
            packet = self._mac.seal(packet)
        self.counters.sent += 1
        self._send(packet, peer)

    def send_proxy_state(self, session_id: int, now_ns: int | None, proxy_pose, proxy_twist, wrench,
                         joint_position=None, joint_velocity=None, joint_effort=None,
                         server_time_s: float | None = None, server_state: int = 0, epsilon_m: float = 0.0,
                         lead_s: float = 0.0, ack_seq: int | None = None, trusted: bool = False,
                         inputs=None) -> bool:
        """Acknowledge with the proxy state: ``ack_seq`` the seq of the ContactUpdate it answers
        (default: the newest accepted; a server that answers an update a step after applying it
        passes that update's seq, as newer ones may have arrived meanwhile). ``inputs``: the
        device's buttons, gripper angle and gripper rate as its state row holds them (NaN: not
        reported; ``None``: no device inputs), sent as the 1.3 fields (``Codec.encode_proxy_state``).

        Poses/twists/wrenches as in SPEC.md (world frame; pose x y z qw qx qy qz). Returns
        ``False`` if the session does not exist (e.g. it just timed out). Raises ``ValueError``
        on a malformed value (the server's own bug, not the network's).
        """
        s = self.sessions.get(session_id)
        if s is None:
            return False
        now = _now(now_ns)
        s.proxy_seq += 1
        empty = _NO_JOINTS
        packet = self.codec.encode_proxy_state(
            s.session_id, s.token, s.proxy_seq, s.contact_seq.newest if ack_seq is None else ack_seq,
            (now - s.opened_ns) / _NS if server_time_s is None else server_time_s,
            proxy_pose, proxy_twist, wrench,
            empty if joint_position is None else joint_position,
            empty if joint_velocity is None else joint_velocity,
            empty if joint_effort is None else joint_effort, server_state, epsilon_m=epsilon_m, lead_s=lead_s,
            trusted=trusted, inputs=inputs)
        self._emit(packet, s.peer)
        s.last_tx_ns = now
        return True

    def close(self, session_id: int, code: ErrorCode = ErrorCode.BYE_SHUTDOWN, reason: str = "",
              now_ns: int | None = None) -> bool:
        """Send Bye (3 times) and forget the session. ``False`` if it did not exist."""
        s = self.sessions.pop(session_id, None)
        if s is None:
            return False
        packet = self.codec.encode(Bye(code=code, reason=reason, session_id=s.session_id, token=s.token))
        for _ in range(3):
            self._emit(packet, s.peer)
        self.counters.byes_sent += 1
        self.counters.sessions_closed += 1
        return True

    def close_all(self, reason: str = "server stopping", now_ns: int | None = None) -> None:
        for sid in list(self.sessions):
            self.close(sid, ErrorCode.BYE_SHUTDOWN, reason, now_ns)

    def poll(self, now_ns: int | None = None) -> None:
        """Timers: Heartbeat to quiet sessions, Bye(timeout) to silent ones. Call every step."""
        now = _now(now_ns)
        for s in list(self.sessions.values()):
            if now - s.last_rx_ns >= self._timeout_ns:
                self.counters.timeouts += 1
                self.close(s.session_id, ErrorCode.BYE_TIMEOUT, "no valid packet within silence_timeout_s", now)
            elif now - s.last_tx_ns >= self._hb_ns:
                s.heartbeat_tx_seq += 1
                self._emit(self.codec.encode(Heartbeat(seq=s.heartbeat_tx_seq, time_s=(now - s.opened_ns) / _NS,
                                                       session_id=s.session_id, token=s.token)), s.peer)
                self.counters.heartbeats_sent += 1
                s.last_tx_ns = now

    # -------------------------------------------------------------------------- receiving
    def receive(self, data, peer: Peer, now_ns: int | None = None) -> ContactUpdate | None:
        """Handle one datagram. Returns a ContactUpdate newer than any before it in its session
        (``.session_id`` says which), else ``None``. Never raises on bad input."""
        c = self.counters
        c.received += 1
        try:
            return self._receive(data, peer, _now(now_ns))
        except Exception:  # noqa: BLE001 - last line of defence: the haptic loop must survive
            c.decode_errors += 1
            return None

    def _receive(self, data, peer: Peer, now: int) -> ContactUpdate | None:
        c = self.counters
        self._rx_len = len(data)
        s = self._expected
        if s is not None and self._rx_len <= self._max_datagram:
            msg = self._parser(data)
            if msg is not None and peer == s.peer and self.sessions.get(s.session_id) is s:
                # every rule below held (the kernel checked them)
                self.codec.counters.decoded += 1
                return self._accept_update(s, msg, now)
        msg = _unwrap(self, data)
        if msg is None:
            return None
        if isinstance(msg, ProtocolError):
            self._on_decode_error(msg, peer, now)
            return None
        tid = msg.TYPE_ID
        if tid == MessageType.HELLO:
            self._on_hello(msg, peer, now)
            return None
        s = self.sessions.get(msg.session_id)
        if s is None:
            c.unknown_session += 1
            return None
        if msg.token != s.token:
            c.bad_token += 1
            return None
        if peer != s.peer:
            c.wrong_peer += 1
            return None
        if tid == MessageType.CONTACT_UPDATE:
            if msg.keys.shape[0] > s.max_contacts:
                c.capacity_exceeded += 1
                self._error(s, now, ErrorCode.TOO_MANY_CONTACTS, "contact_count",
                            f"{msg.keys.shape[0]} contacts > granted max_contacts {s.max_contacts}", tid, msg.seq)
                return None
            if s.contact_seq.jumps(msg.seq, self.config.max_seq_jump):
                c.seq_jump += 1
                self._error(s, now, ErrorCode.SEQ_JUMP, "seq", f"{msg.seq} is more than {self.config.max_seq_jump} "
                            f"ahead of the newest accepted {s.contact_seq.newest}", tid, msg.seq)
                return None
            why = s.check_update(msg)
            if why is not None:
                counter, field_name, detail = why
                group = "out_of_bounds" if counter.startswith("oob") else "unusable"
                setattr(c, counter, getattr(c, counter) + 1)
                setattr(c, group, getattr(c, group) + 1)
                self._error(s, now, ErrorCode.OUT_OF_BOUNDS if group == "out_of_bounds" else ErrorCode.UNUSABLE,
                            field_name, detail, tid, msg.seq)
                return None
            return self._accept_update(s, msg, now)
        if tid == MessageType.HEARTBEAT:
            if s.heartbeat_seq.jumps(msg.seq, self.config.max_seq_jump):
                c.seq_jump += 1
                self._error(s, now, ErrorCode.SEQ_JUMP, "seq", f"{msg.seq} is more than {self.config.max_seq_jump} "
                            f"ahead of the newest accepted {s.heartbeat_seq.newest}", tid, msg.seq)
                return None
            if s.heartbeat_seq.accept(msg.seq, c):
                s.last_rx_ns = now
                c.accepted += 1
            return None
        if tid == MessageType.BYE:
            self.sessions.pop(s.session_id, None)
            c.byes_received += 1
            c.sessions_closed += 1
            c.accepted += 1
            return None
        if tid == MessageType.ERROR:
            c.errors_received += 1
            s.last_rx_ns = now
            c.accepted += 1
            return None
        c.unexpected += 1  # Welcome, Reject, ProxyState: server-to-client only
        self._error(s, now, ErrorCode.UNEXPECTED, "type_id", f"{type(msg).__name__} is not sent to a server", tid, 0)
        return None

    def _accept_update(self, s: ServerSession, msg: ContactUpdate, now: int) -> ContactUpdate | None:
        """A ContactUpdate that kept every rule: newest wins (else ``None``, counted stale or
        duplicate); the parser, if any, expects this session's next ones."""
        if not s.contact_seq.accept(msg.seq, self.counters):
            return None
        s.last_rx_ns = now
        self.counters.accepted += 1
        parser = self._parser
        if parser is not None:
            if self._expected is s:
                parser.accepted(msg.seq)
            else:
                self._expected = s  # its next updates take the parser's path
                parser.expect(s, self.config.max_seq_jump)
        return msg

    def _error(self, s: ServerSession, now: int, code: ErrorCode, field_name: str, detail: str,
               ref_type: int, ref_seq: int) -> None:
        if ref_type == MessageType.ERROR:
            return  # never answer an Error with an Error
        if not s.errors.take(now):
            self.counters.errors_suppressed += 1
            return
        msg = Error(code=code, field=field_name[:64], detail=detail[:200], ref_type=ref_type, ref_seq=ref_seq,
                    session_id=s.session_id, token=s.token)
        self._emit(self.codec.encode(msg), s.peer)
        self.counters.errors_sent += 1
        s.last_tx_ns = now

    def _on_decode_error(self, err: ProtocolError, peer: Peer, now: int) -> None:
        if err.type_id == MessageType.HELLO and (err.client_nonce or err.field == "client_nonce"):
            code = ErrorCode.UNSUPPORTED_VERSION if err.code == ErrorCode.UNKNOWN_MAJOR else ErrorCode.INVALID_HELLO
            self._reject(peer, err.client_nonce, code, str(err))
            return
        # Answer only packets provably from a session: right session, token and peer.
        s = self.sessions.get(err.session_id)
        if s is not None and err.token == s.token and peer == s.peer:
            self._error(s, now, err.code, err.field, err.detail, err.type_id, err.seq)

    def _log_refusal(self, peer: Peer, code: ErrorCode, reason: str) -> None:
        """One log line per refused Hello, at most one a second (a flood of Hellos must not become
        a flood of lines: the ones between are counted in the next line), so the server's operator
        sees what a client was told (a wrong tool kind, an old version, a full server)."""
        now = time.monotonic()
        if now - self._refusal_logged_s < 1.0:
            self._refusals_unlogged += 1
            return
        more = f" ({self._refusals_unlogged} more refused since the last line)" if self._refusals_unlogged else ""
        _log.warning("refused a client at %s: %s: %s%s", peer, code.name, reason, more)
        self._refusal_logged_s = now
        self._refusals_unlogged = 0

    def _reject(self, peer: Peer, nonce: int, code: ErrorCode, reason: str) -> None:
        # A Reject is never larger than the datagram it answers (no amplification, even for a
        # truncated Hello): the reason is shortened to fit, and without room for the rest no
        # Reject is sent (counted in errors_suppressed).
        room = self._rx_len
        reason = reason[:120]
        self._log_refusal(peer, code, reason)
        packet = self.codec.encode(Reject(client_nonce=nonce, code=code, reason=reason))
        if len(packet) > room:
            cut = max(0, len(reason.encode("utf-8")) - (len(packet) - room))
            reason = reason.encode("utf-8")[:cut].decode("utf-8", "ignore")
            packet = self.codec.encode(Reject(client_nonce=nonce, code=code, reason=reason))
            if len(packet) > room:
                self.counters.errors_suppressed += 1
                return
        self._emit(packet, peer)
        self.counters.rejects_sent += 1

    def _on_hello(self, hello: Hello, peer: Peer, now: int) -> None:
        c = self.counters
        cfg = self.config
        for s in self.sessions.values():
            if s.peer == peer:
                if s.hello.client_nonce == hello.client_nonce:
                    # Our Welcome was lost (or is in flight): repeat it, same session.
                    c.hello_repeats += 1
                    self._emit(s.welcome_packet, peer)
                    c.welcomes_sent += 1
                    return
                # Same peer, new nonce: the client restarted; its old session is dead.
                self.sessions.pop(s.session_id)
                c.sessions_closed += 1
                break
        vmin, vmax = hello.version_min, hello.version_max
        if not (vmin[0] <= PROTOCOL_MAJOR <= vmax[0]) or vmin > vmax:
            self._reject(peer, hello.client_nonce, ErrorCode.UNSUPPORTED_VERSION,
                         f"server speaks {PROTOCOL_MAJOR}.0-{PROTOCOL_MAJOR}.{PROTOCOL_MINOR}, "
                         f"client {vmin[0]}.{vmin[1]}-{vmax[0]}.{vmax[1]}")
            return
        if hello.units != "SI":
            self._reject(peer, hello.client_nonce, ErrorCode.UNSUPPORTED_UNITS, f"units must be 'SI', got {hello.units!r}")
            return
        if hello.tool_kind not in cfg.supported_tools:
            self._reject(peer, hello.client_nonce, ErrorCode.UNSUPPORTED_TOOL,
                         f"tool kind {TOOL_KIND_NAMES[hello.tool_kind]} not supported by this server "
                         f"(it simulates {', '.join(TOOL_KIND_NAMES[k] for k in sorted(cfg.supported_tools))})")
            return
        # the cheap refusal first: a flood of Hellos at a full server must not cost a check each
        if len(self.sessions) >= cfg.max_sessions:
            self._reject(peer, hello.client_nonce, ErrorCode.SERVER_FULL, f"all {cfg.max_sessions} session slots in use")
            return
        if cfg.hello_check is not None:
            why = cfg.hello_check(hello)
            if why:
                self._reject(peer, hello.client_nonce, ErrorCode.INVALID_HELLO, why)
                return
        minor = min(PROTOCOL_MINOR, vmax[1]) if vmax[0] == PROTOCOL_MAJOR else PROTOCOL_MINOR
        session_id = 0
        while session_id == 0 or session_id in self.sessions:
            session_id = secrets.randbits(32)
        token = 0
        while token == 0:
            token = secrets.randbits(64)
        epsilon = float(min(hello.epsilon_m, cfg.max_epsilon_m))
        max_contacts = min(hello.max_contacts, cfg.max_contacts, self.codec.limits.max_contacts)
        notes = []
        if epsilon < hello.epsilon_m:
            notes.append(f"epsilon_m capped at {epsilon:g} m (requested {hello.epsilon_m:g} m)")
        if max_contacts < hello.max_contacts:
            notes.append(f"max_contacts capped at {max_contacts} (requested {hello.max_contacts})")
        welcome = Welcome(
            client_nonce=hello.client_nonce, version=(PROTOCOL_MAJOR, minor), haptic_rate_hz=float(cfg.haptic_rate_hz),
            epsilon_m=epsilon, max_contacts=max_contacts,
            heartbeat_interval_s=float(cfg.heartbeat_interval_s), silence_timeout_s=float(cfg.silence_timeout_s),
            server_name=cfg.server_name, workspace_extent_m=float(cfg.workspace_extent_m),
            max_constraint_speed_m_per_s=float(cfg.max_constraint_speed_m_per_s),
            max_separation_m=float(cfg.max_separation_m), note="; ".join(notes),
            update_watchdog_s=float(cfg.update_watchdog_s), session_id=session_id, token=token)
        packet = self.codec.encode(welcome)
        self.sessions[session_id] = ServerSession(session_id, token, peer, hello, welcome, packet, now,
                                                  cfg.error_rate_per_s, self._update_check)
        c.sessions_opened += 1
        self._emit(packet, peer)
        c.welcomes_sent += 1


# ------------------------------------------------------------------------------- client
class ClientState:
    IDLE = "idle"  # start() not called yet
    HANDSHAKING = "handshaking"  # Hello sent, waiting for Welcome / Reject
    ESTABLISHED = "established"  # Welcome received
    REJECTED = "rejected"  # Reject received (see .reject)
    CLOSED = "closed"  # Bye sent or received, or silence timeout


@dataclass(frozen=True)
class ClientConfig:
    hello_retry_s: float = 0.25  # resend Hello this often until Welcome / Reject
    hello_attempts: int = 0  # give up (state CLOSED) after this many; 0 = keep trying
    error_rate_per_s: float = 10.0
    limits: Limits = field(default_factory=Limits)


class ClientEndpoint:
    """The environment engine's side of protocol v1 (see module docstring for the loop).

    ``send(data)`` is called for every outgoing datagram (e.g. ``transport.send``). ``hello``
    describes the tool; its ``client_nonce`` is replaced by a fresh random one at ``start()``.
    """

    def __init__(self, send: Callable[[bytes], object], hello: Hello, config: ClientConfig | None = None, *,
                 hmac_key: bytes | None = None, codec: Codec | None = None) -> None:
        self.config = config or ClientConfig()
        self.codec = codec or Codec(self.config.limits)
        self.counters = SessionCounters()
        self.hello = hello
        self.state = ClientState.IDLE
        self.last_error: Error | None = None
        self.server_peer: Peer | None = None
        self._send = send
        self._mac = MacFramer(hmac_key) if hmac_key is not None else None
        self._max_datagram = self.codec.limits.max_packet_bytes + (HMAC_TAG_BYTES if self._mac else 0)
        self._hello_packet = b""
        self._next_hello_ns = 0
        self.last_tx_ns = 0
        self._contact_tx_seq = 0
        self._heartbeat_tx_seq = 0
        self._errors = _RateLimit(self.config.error_rate_per_s, self.config.error_rate_per_s, 0)
        self._new_session(0)

    def _new_session(self, now: int) -> None:
        """What a session starts from (at construction, and at every ``start()``): no answer yet,
        no ids, ProxyStates and Heartbeats numbered from 1 again, no Hello sent, heard at ``now``."""
        self.welcome: Welcome | None = None
        self.reject: Reject | None = None
        self.bye: Bye | None = None
        self.session_id = 0
        self.token = 0
        self._proxy_seq = _SeqWindow()
        self._heartbeat_seq = _SeqWindow()
        self._hello_sent = 0
        self._opened_ns = now
        self.last_rx_ns = now

    # ------------------------------------------------------------------------ properties
    @property
    def established(self) -> bool:
        return self.state == ClientState.ESTABLISHED

    @property
    def contact_seq(self) -> int:
        """seq of the last ContactUpdate sent."""
        return self._contact_tx_seq

    def silence_ns(self, now_ns: int) -> int:
        """Time since the last valid packet from the server, in ns."""
        return now_ns - self.last_rx_ns

    # -------------------------------------------------------------------------- sending
    def _emit(self, packet: bytes, now: int) -> None:
        if self._mac is not None:
            packet = self._mac.seal(packet)
        self.counters.sent += 1
        self.last_tx_ns = now
        self._send(packet)

    def start(self, now_ns: int | None = None) -> None:
        """Send the Hello (again with a fresh nonce if called after a close)."""
        now = _now(now_ns)
        nonce = 0
        while nonce == 0:
            nonce = secrets.randbits(64)
        self.hello.client_nonce = nonce
        self._hello_packet = self.codec.encode(self.hello)  # ValueError names a bad tool field
        self.state = ClientState.HANDSHAKING
        self._new_session(now)
        self._send_hello(now)

    def _send_hello(self, now: int) -> None:
        self._emit(self._hello_packet, now)
        self._hello_sent += 1
        self.counters.hellos_sent += 1
        self._next_hello_ns = now + int(self.config.hello_retry_s * _NS)

    def send_contacts(self, now_ns: int | None, env_time_s: float, tool_pose, keys: np.ndarray,
                      position_m: np.ndarray, normal: np.ndarray, separation_m: np.ndarray,
                      v_constr_m_per_s: np.ndarray, *, check: bool = False, tool_joint_position=None,
                      work_on_tool_j: float = 0.0) -> int:
        """Send one ContactUpdate (arrays as in :meth:`Codec.encode_contact_update`; a linkage
        engine adds its joint positions; ``work_on_tool_j``: the work the engine's world did on its
        tool since its previous update, granted to the server's passivity layer, SPEC 8.11). Returns its seq, or 0 if the session is not established
        (nothing sent). ``ValueError`` on shapes, dtypes or more contacts than the granted
        capacity."""
        if self.state != ClientState.ESTABLISHED:
            return 0
        if keys.shape[0] > self.welcome.max_contacts:
            raise ValueError(f"keys: {keys.shape[0]} contacts > granted max_contacts {self.welcome.max_contacts}")
        self._contact_tx_seq += 1
        packet = self.codec.encode_contact_update(
            self.session_id, self.token, self._contact_tx_seq, env_time_s, tool_pose, keys, position_m, normal,
            separation_m, v_constr_m_per_s, check=check, tool_joint_position=tool_joint_position,
            work_on_tool_j=work_on_tool_j)
        self._emit(packet, _now(now_ns))
        return self._contact_tx_seq

    def close(self, code: ErrorCode = ErrorCode.BYE_NORMAL, reason: str = "", now_ns: int | None = None) -> None:
        """Send Bye (3 times) if established; state becomes CLOSED."""
        now = _now(now_ns)
        if self.state == ClientState.ESTABLISHED:
            packet = self.codec.encode(Bye(code=code, reason=reason, session_id=self.session_id, token=self.token))
            for _ in range(3):
                self._emit(packet, now)
            self.counters.byes_sent += 1
            self.counters.sessions_closed += 1
        self.state = ClientState.CLOSED

    def poll(self, now_ns: int | None = None) -> None:
        """Timers: Hello retries, Heartbeat when quiet, silence timeout. Call every step."""
        now = _now(now_ns)
        if self.state == ClientState.HANDSHAKING:
            if now >= self._next_hello_ns:
                attempts = self.config.hello_attempts
                if attempts and self._hello_sent >= attempts:
                    self.counters.timeouts += 1
                    self.state = ClientState.CLOSED
                else:
                    self._send_hello(now)
        elif self.state == ClientState.ESTABLISHED:
            w = self.welcome
            if now - self.last_rx_ns >= int(w.silence_timeout_s * _NS):
                self.counters.timeouts += 1
                self.close(ErrorCode.BYE_TIMEOUT, "no valid packet within silence_timeout_s", now)
            elif now - self.last_tx_ns >= int(w.heartbeat_interval_s * _NS):
                self._heartbeat_tx_seq += 1
                self._emit(self.codec.encode(Heartbeat(seq=self._heartbeat_tx_seq, time_s=(now - self._opened_ns) / _NS,
                                                       session_id=self.session_id, token=self.token)), now)
                self.counters.heartbeats_sent += 1

    # -------------------------------------------------------------------------- receiving
    def receive(self, data, peer: Peer = None, now_ns: int | None = None) -> ProxyState | None:
        """Handle one datagram from the server. Returns a ProxyState newer than any before it,
        else ``None`` (Welcome/Reject/Bye/Error update ``state`` and the matching attribute).
        Never raises on bad input."""
        self.counters.received += 1
        try:
            return self._receive(data, peer, _now(now_ns))
        except Exception:  # noqa: BLE001 - last line of defence
            self.counters.decode_errors += 1
            return None

    def _receive(self, data, peer: Peer, now: int) -> ProxyState | None:
        c = self.counters
        msg = _unwrap(self, data)
        if msg is None:
            return None
        if isinstance(msg, ProtocolError):
            if (self.state == ClientState.ESTABLISHED and msg.session_id == self.session_id
                    and msg.token == self.token and peer == self.server_peer and msg.type_id != MessageType.ERROR
                    and self._errors.take(now)):
                self._emit(self.codec.encode(Error(code=msg.code, field=msg.field[:64], detail=msg.detail[:200],
                                                   ref_type=msg.type_id, ref_seq=msg.seq,
                                                   session_id=self.session_id, token=self.token)), now)
                c.errors_sent += 1
            return None
        tid = msg.TYPE_ID
        if tid in (MessageType.WELCOME, MessageType.REJECT):
            if self.state != ClientState.HANDSHAKING or msg.client_nonce != self.hello.client_nonce:
                # A repeated Welcome after we are established is normal (our Hello was resent).
                if self.state == ClientState.ESTABLISHED and tid == MessageType.WELCOME and msg.session_id == self.session_id:
                    c.duplicate += 1
                else:
                    c.unexpected += 1
                return None
            if tid == MessageType.REJECT:
                self.reject = msg
                self.state = ClientState.REJECTED
                c.accepted += 1
                return None
            if msg.version[0] != PROTOCOL_MAJOR or msg.max_contacts < 1:
                c.unexpected += 1
                return None
            self.welcome = msg
            self.session_id, self.token = msg.session_id, msg.token
            self.server_peer = peer
            self.state = ClientState.ESTABLISHED
            self.last_rx_ns = now
            self._opened_ns = now
            self._errors = _RateLimit(self.config.error_rate_per_s, self.config.error_rate_per_s, now)
            c.sessions_opened += 1
            c.accepted += 1
            return None
        if self.state != ClientState.ESTABLISHED:
            c.unknown_session += 1
            return None
        if msg.session_id != self.session_id:
            c.unknown_session += 1
            return None
        if msg.token != self.token:
            c.bad_token += 1
            return None
        if peer != self.server_peer:
            c.wrong_peer += 1
            return None
        if tid == MessageType.PROXY_STATE:
            if msg.ack_seq > self._contact_tx_seq:
                c.unexpected += 1  # acknowledges something never sent
                return None
            if not self._proxy_seq.accept(msg.seq, c):
                return None
            self.last_rx_ns = now
            c.accepted += 1
            return msg
        if tid == MessageType.HEARTBEAT:
            if self._heartbeat_seq.accept(msg.seq, c):
                self.last_rx_ns = now
                c.accepted += 1
            return None
        if tid == MessageType.BYE:
            self.bye = msg
            self.state = ClientState.CLOSED
            c.byes_received += 1
            c.sessions_closed += 1
            c.accepted += 1
            return None
        if tid == MessageType.ERROR:
            self.last_error = msg
            self.last_rx_ns = now
            c.errors_received += 1
            c.accepted += 1
            return None
        c.unexpected += 1  # Hello, ContactUpdate: client-to-server only
        return None
