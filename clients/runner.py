"""The engine-neutral environment client loop: one :class:`ClientRunner` drives any :class:`Engine`.

What it does, in one thread (its own, or a background thread of another program)::

    runner = ClientRunner(PymunkEngine(), "udp://127.0.0.1:9870", scene="testbed", epsilon_m=0.005)
    stats = runner.run(stop_event, duration_s=None)      # blocks; runner.stats() from any thread

- **Handshake**: opens the transport (``udp://``, ``zenoh://``, ``mem://``), sends ``Hello`` (the
  scene's tool, the requested epsilon and contact capacity, the engine's nominal rate) and resends
  it every 0.25 s. On ``Welcome`` the engine is inflated by the *granted* epsilon and contacts are
  capped at the *granted* ``max_contacts`` (the engine clusters down to it).
- **Step loop** at the engine's own rate: ``Engine.next_step_s()`` (variable-rate engines) or
  ``1 / SceneInfo.env_rate_hz``. With ``realtime=True`` (default) steps are paced by the wall
  clock (a step late by more than 0.25 s resynchronises instead of bursting); ``realtime=False``
  steps back-to-back (benchmarks, tests) while simulation time still advances by the engine's
  steps. After **every** step one ``ContactUpdate`` is sent (``env_time_s`` = the engine clock,
  never decreasing, also across reconnections). The world stands still while there is no
  session: no proxy means nothing to follow, and no step goes unreported.
- **ProxyState**: every waiting datagram is read before a step; the session layer drops stale and
  duplicate ones by ``seq`` and only the newest of a batch is given to ``Engine.drive_tool``
  (the others are counted as ``proxy_superseded``). Until the first one arrives the tool holds its
  scene start pose.
- **Server state** (``ProxyState.server_state``, protocol 1.2): the tool follows the proxy only
  while the server renders it (``ENGAGED``; ``UNKNOWN``, a 1.0/1.1 server that does not say, counts
  as engaged). When the server says ``IDLE``, ``FADING`` or ``FAULT`` the tool is held where it is
  (``drive_tool`` with the engine's own pose and zero twist and wrench, once; a linkage's joints
  likewise) and the proxy states that follow are not applied (``proxy_held``) until it is engaged
  again, when the newest proxy is followed at once.
- **The device's inputs** (``ProxyState.buttons``, ``gripper_angle_rad``,
  ``gripper_velocity_rad_per_s``, ``device_inputs``, protocol 1.3): handed to
  ``Engine.device_inputs`` with every ProxyState taken, so a scene can grasp while a button is held.
- **Heartbeats and silence**: the session layer sends a ``Heartbeat`` after
  ``heartbeat_interval_s`` without traffic and ends the session (Bye 61) after
  ``silence_timeout_s`` without a valid packet from the server.
- **Reconnecting**: when a session ends (the server's ``Bye``, e.g. it is restarting, or its
  silence), the runner waits ``reconnect_delay_s`` (default 1 s: a server that said Bye hears
  nothing more from this endpoint for that long) and starts again with a fresh transport,
  endpoint and nonce; a handshake unanswered for ``handshake_timeout_s`` also reopens the
  transport (a restarted Zenoh peer or mem bus needs a new link). ``reconnect=False`` makes
  :meth:`ClientRunner.run` return instead.
- **Giving up**: :class:`ClientError` (one line, for the CLI) when the server refuses the
  ``Hello`` (``Reject``: version, tool kind, units; full, before a first session: after one, a
  full server is retried, counted as ``server_full``), or when no session could be opened
  within ``connect_timeout_s`` of the first connection attempt (``None``: keep trying). The time
  before it (building the engine, loading its scene, opening a GUI, ``Engine.warm_up``'s
  compilation) does not count. After a first session the runner keeps trying for as long as it
  runs (a restarting server may compile for minutes); ``stats()["state"]`` tells a caller what it
  is doing, and the log says it every ``connect_timeout_s`` (10 s without one) until a session
  opens again ("no session with URL for 20 s (...); still trying").
- **Its own stalls**: two ContactUpdates further apart than ``STALL_S`` (50 ms: half the
  server's default watchdog, after which the server fades the force) are the client's own stall
  (its engine step, its window or the OS kept it from running): counted (``stalls``,
  ``stall_max_ms``) and logged, the first at once and then at most one line every 5 s with the
  count since the last one.
- **Windows**: an engine with a ``window`` (``--gui``) gets ``window.update(runner)`` after every
  step and on every pass without one (the window limits its own frame rate).
- **Time**: one clock, ``clock_ns`` (default ``time.monotonic_ns``), paces the steps and stamps
  every message. :meth:`ClientRunner.run` is ``start()`` then ``poll()`` until told to stop; a
  caller with its own clock (a simulated one, the tests, the contract suite) calls
  :meth:`~ClientRunner.start`, :meth:`~ClientRunner.poll` and :meth:`~ClientRunner.close` itself.

The runner never owns the engine: closing it (``Engine.close``) is the caller's job.
"""
from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable

import numpy as np

from ..protocol.codec import Hello, Limits
from ..protocol.messages import ErrorCode, ServerState
from ..protocol.vocab import TOOL_KINDS_BY_NAME
from ..protocol.session import ClientConfig, ClientEndpoint, ClientState
from ..protocol.transport import TransportError, open_transport, parse_transport_url

from .engine import ContactBuffer, Engine, SceneInfo
from .geometry import advance_pose

__all__ = ["ClientError", "ClientRunner", "TOOL_KINDS"]

_NS = 1_000_000_000
TOOL_KINDS = TOOL_KINDS_BY_NAME
_RTT_RING = 4096
#: a realtime loop this far behind its schedule restarts the schedule instead of catching up
_RESYNC_NS = 250_000_000
#: a gap between two ContactUpdates of one session longer than this is the client's own stall [s]
STALL_S = 0.05
_STALL_REPORT_NS = 5 * 1_000_000_000
#: how often a client without a session after it had one says it is still trying, by default [s]
_RETRY_REPORT_S = 10.0
#: server states in which the proxy is rendered: the tool follows it
_FOLLOW = frozenset((ServerState.ENGAGED, ServerState.UNKNOWN))
#: the engine's epsilon follows the server's advice when it moves by more than this [m] (a
#: change costs the engine a re-inflation of its tool's query shape)
EPSILON_CHANGE_M = 0.0005
#: the longest lead [s] a server's advice may ask the tool to track ahead by: an engine lags by a
#: few of its steps, and a lead from a broken server must not throw the tool ahead
LEAD_MAX_S = 0.25


class ClientError(Exception):
    """A condition the client cannot recover from; ``str()`` is one line for the user."""


def hello_fields(engine: Engine, info: SceneInfo, epsilon_m: float, max_contacts: int) -> dict:
    """The fields of the Hello (all but ``client_nonce``) that describe ``engine``'s tool in the
    scene it loaded (``info``), asking for ``epsilon_m`` and ``max_contacts``."""
    tool = info.tool
    return dict(
        engine=engine.name[:200], tool_kind=TOOL_KINDS[tool.kind], mass_kg=float(tool.mass_kg),
        com_m=tuple(float(v) for v in tool.com_m), inertia_kg_m2=tuple(float(v) for v in tool.inertia_kg_m2),
        axis=tuple(float(v) for v in (tool.axis if tool.kind == "1dof" else (1.0, 0.0, 0.0))),
        epsilon_m=float(epsilon_m), max_contacts=int(max_contacts), env_rate_hz=float(info.env_rate_hz),
        links=tuple(ln.record() for ln in tool.links) if tool.kind == "linkage" else (),
        held_link=int(tool.held_link) if tool.kind == "linkage" else 0)


class ClientRunner:
    """Runs ``engine`` in ``scene`` against the server at ``url`` (see the module docstring).

    Args:
        engine: an :class:`Engine`; its scene is loaded here (``ValueError`` for an unknown one).
        url: transport URL of the server (``udp://HOST:PORT``, ``zenoh://HOST:PORT/SESSION``,
            ``mem://NAME``); ``ValueError`` if malformed.
        scene: scene name.
        epsilon_m: epsilon to request [m], >= 0 (the server may grant less).
        max_contacts: contact capacity to request, 1..64 (the server may grant less).
        hmac_key: shared secret for HMAC mode (None: plain).
        realtime: pace steps by the wall clock (False: back-to-back).
        reconnect, reconnect_delay_s, handshake_timeout_s, connect_timeout_s: see the module
            docstring.
        transport_options: extra backend options for ``open_transport`` (e.g.
            ``{"connect_timeout_s": 1.0}`` for Zenoh).
        on_step: called as ``on_step(runner)`` after every step (GUI, recording); runs in the
            runner's thread.
        log: called with one-line messages (session opened / ended, held / following); ``None``:
            silent.
        clock_ns: the clock [ns] of pacing and time stamps (default ``time.monotonic_ns``).
        sleep: how :meth:`run` waits [s] (default ``time.sleep``).
    """

    def __init__(self, engine: Engine, url: str, *, scene: str, epsilon_m: float = 0.005, max_contacts: int = 16,
                 hmac_key: bytes | None = None, realtime: bool = True, reconnect: bool = True,
                 reconnect_delay_s: float = 1.0, handshake_timeout_s: float = 5.0,
                 connect_timeout_s: float | None = None, hello_retry_s: float = 0.25,
                 transport_options: dict | None = None, on_step: Callable[["ClientRunner"], None] | None = None,
                 log: Callable[[str], None] | None = None, clock_ns: Callable[[], int] = time.monotonic_ns,
                 sleep: Callable[[float], None] = time.sleep) -> None:
        if not (isinstance(epsilon_m, (int, float)) and not isinstance(epsilon_m, bool) and math.isfinite(epsilon_m)
                and epsilon_m >= 0):
            raise ValueError(f"epsilon_m: must be a finite number >= 0 m, got {epsilon_m!r}")
        limit = Limits().max_contacts
        if not (isinstance(max_contacts, int) and not isinstance(max_contacts, bool) and 1 <= max_contacts <= limit):
            raise ValueError(f"max_contacts: must be an integer in 1..{limit}, got {max_contacts!r}")
        for nm, v in (("reconnect_delay_s", reconnect_delay_s), ("handshake_timeout_s", handshake_timeout_s),
                      ("hello_retry_s", hello_retry_s)):
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"{nm}: must be a finite number > 0 s, got {v!r}")
        if connect_timeout_s is not None and not (math.isfinite(connect_timeout_s) and connect_timeout_s > 0):
            raise ValueError(f"connect_timeout_s: must be a finite number > 0 s or None, got {connect_timeout_s!r}")
        parse_transport_url(url)  # ValueError now, not in the loop
        self.engine = engine
        self.url = url
        self.scene_info = engine.load_scene(scene)  # ValueError naming the choices
        tool = self.scene_info.tool
        if tool.kind not in TOOL_KINDS:
            raise ValueError(f"tool kind {tool.kind!r} not supported by the runner (choose one of {', '.join(TOOL_KINDS)})")
        self.requested_epsilon_m = float(epsilon_m)
        self.requested_max_contacts = max_contacts
        engine.set_epsilon(self.requested_epsilon_m)
        self._hello_fields = hello_fields(engine, self.scene_info, self.requested_epsilon_m, max_contacts)
        #: a linkage's joint positions (sent with every ContactUpdate) and count
        self._linkage = tool.kind == "linkage"
        self._joints = np.zeros(max(0, len(tool.links) - 1))
        Hello(client_nonce=1, **self._hello_fields)  # fail early on a field the codec would refuse
        self.hmac_key = hmac_key
        self.realtime = bool(realtime)
        self.reconnect = bool(reconnect)
        self.reconnect_delay_s = float(reconnect_delay_s)
        self.handshake_timeout_s = float(handshake_timeout_s)
        self.connect_timeout_s = connect_timeout_s
        self.hello_retry_s = float(hello_retry_s)
        self.transport_options = dict(transport_options or {})
        self.on_step = on_step
        self._log = log
        self._clock = clock_ns
        self._sleep = sleep
        self.transport = None
        self.endpoint: ClientEndpoint | None = None
        self.contacts = ContactBuffer(max_contacts)
        self.tool_pose = np.zeros(7)
        self.granted_epsilon_m: float | None = None
        self.epsilon_m = self.requested_epsilon_m  # what the engine inflates its tool by now
        self.granted_max_contacts: int | None = None
        self.last_proxy = None
        #: the tool follows the proxy (the server renders it); False while it is held
        self.following = True
        self._hold_pose = np.zeros(7)
        self._lead_pose = np.zeros(7)
        self._lead_s = 0.0  # the lead followed last [s] (the server's, capped)
        self._hold_zeros6 = np.zeros(6)
        self._hold_zeros_j = np.zeros(len(self._joints))
        self._hold_joints = np.zeros(len(self._joints))
        self.done = False
        self._started = False
        self._sent_ns = np.zeros(_RTT_RING, dtype=np.int64)
        self._lock = threading.Lock()
        self._state = "idle"
        self._error: str | None = None
        self._end_reason = ""
        self._counts = dict.fromkeys((
            "steps", "updates_sent", "proxy_states", "proxy_applied", "proxy_superseded", "proxy_held", "holds",
            "sessions",
            "sessions_ended", "connect_attempts", "transport_errors", "steps_clustered", "contacts_max",
            "stale", "duplicate", "hellos_sent", "heartbeats_sent", "send_failures", "server_full", "stalls"), 0)
        self._stall_max_ns = 0
        self._last_send_ns = 0      # the last ContactUpdate of this session (0: none yet)
        self._stall_report_ns = 0   # when the last stall line was logged
        self._stalls_unreported = 0
        self._stall_worst_ns = 0    # the longest stall since the last line
        self._lost_ns = 0           # when the last session ended (0: in one, or never had one)
        self._lost_reports = 0      # "still trying" lines since then
        self._contacts_last = 0
        self._rtt_last_s = math.nan
        self._rtt_sum_s = 0.0
        self._rtt_n = 0
        self._ever_connected = False

    # ------------------------------------------------------------------------ status
    def stats(self) -> dict:
        """A snapshot (safe to call from another thread): counts, state, grants, last error."""
        with self._lock:
            out = dict(self._counts)
            ep = self.endpoint
            if ep is not None:  # add the live endpoint's counters to those of finished ones
                out["stale"] += ep.counters.stale
                out["duplicate"] += ep.counters.duplicate
                out["hellos_sent"] += ep.counters.hellos_sent
                out["heartbeats_sent"] += ep.counters.heartbeats_sent
            out.update(
                state=self._state, error=self._error, end_reason=self._end_reason, url=self.url,
                engine=self.engine.name, scene=self.scene_info.name, env_time_s=self.engine.time_s,
                contacts_last=self._contacts_last, granted_epsilon_m=self.granted_epsilon_m,
                epsilon_m=self.epsilon_m, lead_s=self._lead_s,
                server_state=self.server_state, following=self.following,
                granted_max_contacts=self.granted_max_contacts,
                rtt_last_ms=self._rtt_last_s * 1e3, stall_max_ms=self._stall_max_ns * 1e-6,
                rtt_mean_ms=(self._rtt_sum_s / self._rtt_n * 1e3) if self._rtt_n else math.nan)
        return out

    @property
    def server_state(self) -> str | None:
        """The server state of the newest ProxyState by name (``"engaged"``, ``"fading"``, ...;
        ``"unknown"`` from a server that does not report it), ``None`` before the first."""
        proxy = self.last_proxy
        if proxy is None:
            return None
        v = int(getattr(proxy, "server_state", 0) or 0)
        return ServerState(v).name.lower() if v in ServerState._value2member_map_ else str(v)

    @property
    def state(self) -> str:
        """"idle", "connecting", "handshaking", "established", "waiting" (to reconnect), "stopped",
        "failed"."""
        return self._state

    # ------------------------------------------------------------------------ the loop
    def run(self, stop: threading.Event | None = None, duration_s: float | None = None,
            max_steps: int | None = None) -> dict:
        """Run until ``stop`` is set, ``duration_s`` of wall time or ``max_steps`` engine steps have
        passed, or (``reconnect=False``) the session ends. Returns :meth:`stats`. Raises
        :class:`ClientError` when the server refuses us or cannot be reached in time."""
        stop = stop or threading.Event()
        try:
            self.start()
            t_end = None if duration_s is None else self._t0 + int(duration_s * _NS)
            while not stop.is_set():
                if t_end is not None and self._clock() >= t_end:
                    self._end_reason = "duration reached"
                    break
                if max_steps is not None and self._counts["steps"] >= max_steps:
                    self._end_reason = "max_steps reached"
                    break
                wait = self.poll()
                if self.done:
                    break
                if wait > 0:
                    self._sleep(min(wait, 0.002))
                elif not self.realtime:
                    self._sleep(0)  # let other threads of the process (a server, a GUI) run
        finally:
            self.close()
        return self.stats()

    def start(self) -> None:
        """Before the first :meth:`poll`: pay the engine's one-time costs (``Engine.warm_up``), then
        start the clocks (the connect timeout counts from here)."""
        self._state = "connecting"
        self.engine.warm_up()  # e.g. JIT compilation: not while the server waits for our updates
        now = self._clock()
        self._t0 = now
        self._connect_deadline = None if self.connect_timeout_s is None else now + int(self.connect_timeout_s * _NS)
        self._next_attempt = now
        self._next_step = now
        self._last_open_error = ""
        self.done = False
        self._started = True

    def poll(self) -> float:
        """One pass of the loop at ``clock_ns()``: (re)connect when due, read the server, step
        the engine when its step is due (``realtime=False``: every pass) and send its
        ContactUpdate, run the session's timers. Returns the time [s] until the next pass has
        anything to do (0: at once). Sets :attr:`done` when the session ended and
        ``reconnect=False``. Raises :class:`ClientError` (see the module docstring)."""
        if not self._started:
            self.start()
        try:
            return self._poll()
        except ClientError as exc:
            self._error = str(exc)
            self._state = "failed"
            self._close_session("client giving up")
            raise

    def close(self) -> None:
        """End the session (Bye) and release the transport; the runner is ``"stopped"`` (or stays
        ``"failed"``)."""
        if self._state != "failed":
            self._close_session("client stopping")
            self._state = "stopped"
        self._started = False

    def _poll(self) -> float:
        clock = self._clock
        now = clock()
        if not self._ever_connected and self._connect_deadline is not None and now >= self._connect_deadline:
            why = f" ({self._last_open_error})" if self._last_open_error else " (is the server running?)"
            raise ClientError(f"no session with {self.url} within {self.connect_timeout_s:g} s{why}")
        if self._lost_ns:
            self._report_retrying(now)
        ep = self.endpoint
        if ep is None:
            if now < self._next_attempt:
                self._update_window()
                return (self._next_attempt - now) / _NS
            try:
                self._open(now)
                self._last_open_error = ""
            except (TransportError, OSError) as exc:
                self._last_open_error = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
                self._counts["transport_errors"] += 1
                self._next_attempt = now + int(self.reconnect_delay_s * _NS)
                self._state = "waiting"
            return 0.0
        was_established = ep.established
        self._receive(ep, now)
        if ep.state == ClientState.ESTABLISHED and not was_established:
            self._on_welcome(ep)
            self._next_step = clock()
        if ep.state == ClientState.REJECTED:
            r = ep.reject
            code = ErrorCode(r.code).name if r.code in ErrorCode._value2member_map_ else str(r.code)
            if r.code == ErrorCode.SERVER_FULL and self._ever_connected and self.reconnect:
                # After a first session the slot is most likely held by this client's own ghost:
                # a Hello of an earlier attempt (another socket) that waited in the server's queue
                # while it restarted. That session times out unheard; try again after the delay.
                self._counts["server_full"] += 1
                self._end_reason = f"server full ({r.reason}); retrying"
                if self._log:
                    self._log(f"server {self.url} is full ({r.reason}); retrying in {self.reconnect_delay_s:g} s")
                self._drop_endpoint()
                self._state = "waiting"
                self._next_attempt = clock() + int(self.reconnect_delay_s * _NS)
                return 0.0
            raise ClientError(f"server {self.url} refused the session: {code}: {r.reason} "
                              f"(server speaks {r.version_min[0]}.{r.version_min[1]}-"
                              f"{r.version_max[0]}.{r.version_max[1]})")
        stepped = False
        if ep.state == ClientState.ESTABLISHED and (not self.realtime or now >= self._next_step):
            dt = self._tick()
            stepped = True
            if self.realtime:
                self._next_step += int(dt * _NS)
                if clock() - self._next_step > _RESYNC_NS:
                    self._next_step = clock()
        ep.poll(clock())
        if ep.state == ClientState.CLOSED:
            handshake_failed = ep.welcome is None
            self._session_over(ep, handshake_failed)
            if not handshake_failed and not self.reconnect:
                self.done = True
                return 0.0
            self._next_attempt = clock() + (0 if handshake_failed else int(self.reconnect_delay_s * _NS))
            return 0.0
        if stepped:
            return 0.0
        self._update_window()
        wait = (self._next_step - clock()) / _NS if ep.established else 0.002
        return max(0.0, wait)

    def _update_window(self) -> None:
        window = getattr(self.engine, "window", None)
        if window is not None:
            window.update(self)

    # ------------------------------------------------------------------------ pieces
    def _open(self, now: int) -> None:
        self._state = "connecting"
        self._counts["connect_attempts"] += 1
        transport = open_transport(self.url, role="client", **self.transport_options)
        attempts = max(1, math.ceil(self.handshake_timeout_s / self.hello_retry_s))
        cfg = ClientConfig(hello_retry_s=self.hello_retry_s, hello_attempts=attempts)
        ep = ClientEndpoint(transport.send, Hello(client_nonce=1, **self._hello_fields), cfg, hmac_key=self.hmac_key)
        with self._lock:
            self.transport, self.endpoint = transport, ep
        ep.start(self._clock())
        self._state = "handshaking"

    def _receive(self, ep: ClientEndpoint, now: int) -> None:
        transport = self.transport
        newest = None
        fresh = 0
        while (got := transport.recv()) is not None:
            state = ep.receive(got[0], got[1], now)
            if state is not None:  # the session layer returns only ProxyStates newer than any before
                newest = state
                fresh += 1
        if newest is None:
            return
        c = self._counts
        c["proxy_states"] += fresh
        c["proxy_superseded"] += fresh - 1
        self.last_proxy = newest
        follow = int(getattr(newest, "server_state", 0) or 0) in _FOLLOW
        engine = self.engine
        # the device's buttons and gripper (protocol 1.3; 0 and none reported from an older server)
        engine.device_inputs(int(getattr(newest, "buttons", 0)), float(getattr(newest, "gripper_angle_rad", 0.0)),
                             float(getattr(newest, "gripper_velocity_rad_per_s", 0.0)),
                             int(getattr(newest, "device_inputs", 0)))
        if follow:
            c["proxy_applied"] += 1
            if self._linkage:
                engine.drive_joints(newest.joint_position, newest.joint_velocity, newest.joint_effort)
            # the server's advice (protocol 1.2): track the proxy advanced by its lead, and inflate
            # the tool by the epsilon it measured (never above the granted one)
            lead = self._lead_s = min(float(getattr(newest, "lead_s", 0.0) or 0.0), LEAD_MAX_S)
            target = newest.proxy_pose if lead <= 0.0 else advance_pose(newest.proxy_pose, newest.proxy_twist, lead,
                                                                           self._lead_pose)
            engine.drive_tool(target, newest.proxy_twist, newest.wrench)
            eps = float(getattr(newest, "epsilon_m", 0.0) or 0.0)
            eps = self.granted_epsilon_m if eps <= 0.0 else min(eps, self.granted_epsilon_m)  # 0: no advice
            if abs(eps - self.epsilon_m) > EPSILON_CHANGE_M:
                engine.set_epsilon(eps)
                self.epsilon_m = eps
            if not self.following and self._log:
                self._log(f"server {self.server_state}: following the proxy again")
        else:
            c["proxy_held"] += 1
            if self.following:
                self._hold()
                if self._log:
                    self._log(f"server {self.server_state}: the proxy is not rendered; holding the tool")
        self.following = follow
        ack = newest.ack_seq
        if ack and ep.contact_seq - ack < _RTT_RING:
            rtt = (self._clock() - int(self._sent_ns[ack % _RTT_RING])) / _NS
            self._rtt_last_s = rtt
            self._rtt_sum_s += rtt
            self._rtt_n += 1

    def _hold(self) -> None:
        """Keep the engine's tool where it is: its own pose (and joints) as the drive's target."""
        engine = self.engine
        self._counts["holds"] += 1
        if self._linkage:
            engine.drive_joints(engine.joint_positions(self._hold_joints), self._hold_zeros_j, self._hold_zeros_j)
        engine.drive_tool(engine.tool_pose(self._hold_pose), self._hold_zeros6, self._hold_zeros6)

    def _on_welcome(self, ep: ClientEndpoint) -> None:
        w = ep.welcome
        self.granted_epsilon_m = w.epsilon_m
        self.granted_max_contacts = w.max_contacts
        self.engine.set_epsilon(w.epsilon_m)
        self.epsilon_m = w.epsilon_m  # until the server advises another one
        if self.contacts.capacity != w.max_contacts:
            self.contacts = ContactBuffer(w.max_contacts)
        self._counts["sessions"] += 1
        self._ever_connected = True
        self._lost_ns = self._lost_reports = 0
        self._last_send_ns = 0
        self.following = True  # until a ProxyState says otherwise
        self._state = "established"
        if self._log:
            # the session id in decimal, as the server's log and `hapticproxy status` print it
            self._log(f"session {ep.session_id} with {w.server_name!r} at {self.url}: epsilon "
                      f"{w.epsilon_m * 1e3:g} mm, max {w.max_contacts} contacts, haptic {w.haptic_rate_hz:g} Hz")

    def _tick(self) -> float:
        """One engine step, its contacts, one ContactUpdate. Returns the step [s]."""
        engine = self.engine
        dt = engine.next_step_s() or 1.0 / self.scene_info.env_rate_hz
        engine.step(dt)
        buf = self.contacts
        cap = self.granted_max_contacts or buf.capacity
        n = engine.contacts(buf, cap)
        if not 0 <= n <= cap:
            raise RuntimeError(f"{engine.name}: contacts() returned {n}, outside 0..{cap}")
        engine.tool_pose(self.tool_pose)
        joints = engine.joint_positions(self._joints) if self._linkage else None
        ep = self.endpoint
        now = self._clock()
        seq = ep.send_contacts(now, engine.time_s, self.tool_pose, buf.keys[:n], buf.position_m[:n],
                               buf.normal[:n], buf.separation_m[:n], buf.v_constr_m_per_s[:n],
                               tool_joint_position=joints)
        c = self._counts
        c["steps"] += 1
        if seq:
            c["updates_sent"] += 1
            self._sent_ns[seq % _RTT_RING] = now
            if self._last_send_ns and now - self._last_send_ns > STALL_S * _NS:
                self._on_stall(now, now - self._last_send_ns)
            self._last_send_ns = now
        self._contacts_last = n
        if n > c["contacts_max"]:
            c["contacts_max"] = n
        if getattr(engine, "contacts_found", n) > n:  # the engine clustered to fit the grant
            c["steps_clustered"] += 1
        if self.on_step is not None:
            self.on_step(self)
        self._update_window()
        return dt

    def _session_over(self, ep: ClientEndpoint, handshake_failed: bool) -> None:
        if handshake_failed:
            self._end_reason = f"no answer to Hello within {self.handshake_timeout_s:g} s"
        elif ep.bye is not None:
            code = ErrorCode(ep.bye.code).name if ep.bye.code in ErrorCode._value2member_map_ else str(ep.bye.code)
            self._end_reason = f"server ended the session (Bye {code}: {ep.bye.reason})"
        else:
            self._end_reason = f"server silent for {ep.welcome.silence_timeout_s:g} s"
        if not handshake_failed:
            self._counts["sessions_ended"] += 1
            self._lost_ns = self._clock()
            self._lost_reports = 0
            if self._log:
                self._log(self._end_reason + ("; reconnecting" if self.reconnect else ""))
        self._drop_endpoint()
        self._state = "waiting" if (self.reconnect or handshake_failed) else "stopped"

    def _on_stall(self, now: int, gap_ns: int) -> None:
        c = self._counts
        c["stalls"] += 1
        self._stall_max_ns = max(self._stall_max_ns, gap_ns)
        self._stalls_unreported += 1
        self._stall_worst_ns = max(self._stall_worst_ns, gap_ns)
        if self._stall_report_ns and now - self._stall_report_ns < _STALL_REPORT_NS:
            return
        if self._log:
            n, worst = self._stalls_unreported, self._stall_worst_ns * 1e-6
            what = (f"client stalled {worst:.0f} ms between two updates" if n == 1 else
                    f"client stalled {n} times since the last report (longest {worst:.0f} ms)")
            self._log(f"{what}: its own engine step, window or the OS kept it from running, and the server "
                      f"fades the force when updates stop for its watchdog (100 ms by default); on a busy "
                      f"machine run the client at a lower priority than the server (nice -n 10 hapticproxy "
                      f"client ...), without --gui, or on another machine ({c['stalls']} stalls so far)")
        self._stall_report_ns = now
        self._stalls_unreported = 0
        self._stall_worst_ns = 0

    def _report_retrying(self, now: int) -> None:
        """After a session ended: a line every ``connect_timeout_s`` (10 s without one) until the
        next session opens, so a client waiting for a server that is gone says so."""
        every = self.connect_timeout_s or _RETRY_REPORT_S
        due = self._lost_ns + int((self._lost_reports + 1) * every * _NS)
        if now < due:
            return
        self._lost_reports += 1
        if self._log:
            why = self._last_open_error or self._end_reason
            self._log(f"no session with {self.url} for {(now - self._lost_ns) / _NS:.0f} s ({why}); still trying "
                      f"every {self.reconnect_delay_s:g} s (Ctrl-C stops)")

    def _drop_endpoint(self) -> None:
        ep, transport = self.endpoint, self.transport
        with self._lock:
            if ep is not None:
                c = self._counts
                c["stale"] += ep.counters.stale
                c["duplicate"] += ep.counters.duplicate
                c["hellos_sent"] += ep.counters.hellos_sent
                c["heartbeats_sent"] += ep.counters.heartbeats_sent
            self.endpoint = self.transport = None
        if transport is not None:
            self._counts["send_failures"] += transport.counters.send_errors
            transport.close()

    def _close_session(self, reason: str) -> None:
        ep = self.endpoint
        if ep is not None and ep.established:
            try:
                ep.close(ErrorCode.BYE_NORMAL, reason, now_ns=self._clock())
            except Exception:  # noqa: BLE001 - a failing Bye must not hide why we stopped
                pass
        self._drop_endpoint()
