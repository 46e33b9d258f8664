"""Zenoh transport (``zenoh://HOST:PORT/SESSION``), eclipse-zenoh 1.x.

This is the only module of ``hapticproxy.protocol`` that imports ``zenoh``, and it is imported
only when a ``zenoh://`` endpoint is opened.

Key expressions (``SESSION`` is the URL path, default ``default``; ``CLIENT`` is the client's
Zenoh session id, ``ZenohId`` as lowercase hex, which is also the peer id the server sees):

==========================================  =============  ==============================
key expression                              publisher      subscriber
==========================================  =============  ==============================
``hapticproxy/SESSION/c2s/CLIENT``          client         server (``hapticproxy/SESSION/c2s/*``)
``hapticproxy/SESSION/s2c/CLIENT``          server         that client only
==========================================  =============  ==============================

Each sample's payload is exactly one protocol datagram, the same bytes UDP carries; nothing is
added (no attachment, the encoding left at its default).

Deployment modes:

- ``mode=peer`` (default, embedded): the server's Zenoh session listens on
  ``PROTOCOL/HOST:PORT`` (``tcp/127.0.0.1:7447`` style) and each client session connects to that
  endpoint directly. Multicast and gossip scouting are off, so two processes find each other only
  through the explicit endpoint: nothing is discovered on, or leaked to, the LAN.
- ``mode=client``: both sides are Zenoh *clients* of a router (``zenohd``) at ``HOST:PORT``;
  use it across machines, with the router's config carrying TLS / authentication
  (``deploy/zenoh/``).
- ``config=PATH`` loads a Zenoh JSON5 file as the base configuration (TLS certificates,
  user/password, buffer sizes); mode, endpoints and scouting are then set from the URL on top.

Latency choices (measured with ``hapticproxy bench transport``): publishers are declared with
``express=True`` (the message bypasses the batching queue and leaves at once),
``CongestionControl.DROP`` (a slow link drops our newest-wins traffic instead of blocking the
haptic thread) and ``Priority.REAL_TIME``, whose TX queue is raised from Zenoh's 2 batches to
16 (:data:`TX_QUEUE_REAL_TIME_BATCHES`): a burst of up to 16 datagrams is queued, beyond that
Zenoh may drop datagrams after :data:`WAIT_BEFORE_DROP_US` without telling the publisher (so no
counter can see them; the session layer's sequence numbers do). Shared memory is off
(payloads are far below its 3 kB threshold; it would only reserve a pool). Zenoh's RX pool is
cut to one worker (:data:`DEFAULT_ZENOH_RUNTIME`, applied unless the process sets
``ZENOH_RUNTIME`` itself; Zenoh reads that variable once, when its runtime first starts, so it
is process-wide).

``lowlatency=True`` switches the unicast transport to Zenoh's low-latency mode (QoS lanes and
batching off; both ends must agree, and the server's :attr:`url` carries it). Its ``put``
serialises and writes to the socket in the calling thread instead of handing the message to
Zenoh's TX thread, which is what makes it faster; the price is that a put can block while the
peer's socket buffer is full (a peer whose Zenoh runtime is frozen, until the link lease, 10 s by
default, expires), where the default mode drops after :data:`WAIT_BEFORE_DROP_US`. So it stays
opt-in.

Measured on the 2-vCPU development VM (KVM, shared with other work: medians of 4 runs of
``hapticproxy bench transport --json``, 5,000 exchanges each, update -> ack round trip p50,
back-to-back / paced at 1 kHz): UDP 9.0 / 14.6 us; Zenoh default mode 104 / 156 us; Zenoh
``lowlatency=true`` 41 / 73 us (with its Zenoh threads pinned off the pollers' CPUs, the bench's
default for that row). With Zenoh's default pools and floating threads (4 runs before these
changes) the low-latency row measured 91 / 95 us; the one-worker RX pool alone brought it to
49 / 72 (4 runs), the pinning steadied the back-to-back figure. The default mode did not change
measurably (back-to-back p50s 73-126 us with either pool). Zenoh p99 was at most 357 us in
every run.

Why Zenoh stays above 3x UDP here: ``python -m hapticproxy.benchmarks.zenoh_floor`` runs the same
ping/pong with the ``zenoh`` package alone. With this module's settings, low-latency mode and
Zenoh's threads pinned off the pollers it measured a p50 of 31-40 us (6 runs) against 7.7 us for
raw UDP and 8.0 us for raw TCP sockets: the floor is about 4x UDP before this module adds
anything (run alternately with the bench, the bench's low-latency row was within a few us of
it; ``recv_into`` costs 2.1 us, of which ``try_recv`` 0.45). Per direction a Zenoh put costs
3.1 us in the caller (serialise and write) and the receiver's Zenoh RX thread must be woken by
epoll and hand the sample to the ring: besides the 8 us of the TCP round trip itself, roughly
9 us per direction is that wake-up and routing, twice per round trip, on a machine whose two
cores both run busy pollers. The default mode adds a hand-over to Zenoh's TX thread per put
(floor 58-82 us). A callback subscriber (no ring) is no faster (55-72 us: the callback must
take the GIL).

Receiving: each subscriber uses a ``zenoh.handlers.RingChannel(ring_capacity)`` which Zenoh's
own threads fill; :meth:`recv_into` only calls ``try_recv()``, so no Python callback ever runs
and the haptic thread never blocks. A full ring drops its *oldest* sample, which Zenoh does not
report, so ``counters.dropped_overflow`` stays 0 for this backend.

Start-up: the client constructor waits (up to ``connect_timeout_s``) until its publisher is
matched by the server's subscriber, so its first datagram is not published into the void. Its
own reply subscriber is declared before that, on the same link, so the server learns of it
before the client's first datagram arrives; :meth:`ZenohTransport.peer_ready` lets a server
check that a reply to a given peer has a matched subscriber.
"""
from __future__ import annotations

import json
import os
import re
import socket
import time

from .base import DEFAULT_MAX_PACKET_BYTES, Peer, Transport, TransportError

KEY_PREFIX = "hapticproxy"
DEFAULT_SESSION = "default"
DEFAULT_RING_CAPACITY = 256
DEFAULT_CONNECT_TIMEOUT_S = 5.0
#: Zenoh TX queue depth for our priority, in batches (= datagrams, since we publish express):
#: the largest burst one endpoint can send before Zenoh's congestion control may drop (silently:
#: Zenoh does not report it to the publisher). 16 is the maximum Zenoh accepts.
TX_QUEUE_REAL_TIME_BATCHES = 16
#: How long a put may wait for room in a full TX queue before the datagram is dropped.
WAIT_BEFORE_DROP_US = 100
#: Zenoh thread pools this module asks for unless the process sets ``ZENOH_RUNTIME`` itself:
#: one RX worker instead of Zenoh's two, so a received datagram is read, decoded and put in the
#: ring by the thread that epoll woke, with no hand-over to a second worker. Measured with
#: ``hapticproxy bench transport`` on the 2-vCPU VM (module docstring): low-latency mode
#: back-to-back p50 91 -> 49 us; the default mode unchanged within the noise.
DEFAULT_ZENOH_RUNTIME = "(rx: (worker_threads: 1))"
#: Bound on distinct client ids a server remembers (and keeps a reply publisher for); beyond it
#: the table is cleared and rebuilt from traffic, so a flood of fake ids cannot grow memory.
MAX_REMEMBERED_PEERS = 1024

_MODES = ("peer", "client")
_FORBIDDEN_KEY_CHARS = set("/*$?#")


def c2s_key(session: str, client_id: str) -> str:
    """Key expression a client publishes on (and the server receives from)."""
    return f"{KEY_PREFIX}/{session}/c2s/{client_id}"


def s2c_key(session: str, client_id: str) -> str:
    """Key expression the server replies on to one client."""
    return f"{KEY_PREFIX}/{session}/s2c/{client_id}"


def _check_chunk(name: str, value: str) -> str:
    if not isinstance(value, str) or not value or _FORBIDDEN_KEY_CHARS & set(value):
        raise ValueError(f"{name} must be a non-empty key chunk without any of '/*$?#', got {value!r}")
    return value


def _free_tcp_port(host: str) -> int:
    # Zenoh 1.x has no Python API reporting the port an ephemeral listener got, so pick one
    # ourselves. The small race (someone else takes it before Zenoh binds) is retried by caller.
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return s.getsockname()[1]


#: Name prefixes of the threads Zenoh's runtimes start (``rx-0``, ``tx-0``, ...).
ZENOH_THREAD_PREFIXES = ("rx-", "tx-", "app-", "acc-", "net-")


def zenoh_thread_ids() -> list[int]:
    """Linux thread ids of this process's Zenoh runtime threads (empty elsewhere, or before the
    first session starts them). For placing them, e.g. ``os.sched_setaffinity(tid, cpus)`` to
    keep them off the core a busy-polling haptic thread owns: see the module docstring."""
    out = []
    try:
        tasks = os.listdir("/proc/self/task")
    except OSError:
        return out
    for tid in tasks:
        try:
            with open(f"/proc/self/task/{tid}/comm") as f:
                name = f.read().strip()
        except OSError:  # the thread ended meanwhile
            continue
        if name.startswith(ZENOH_THREAD_PREFIXES):
            out.append(int(tid))
    return out


def _endpoint(protocol: str, host: str, port: int) -> str:
    if ":" in host and not host.startswith("["):
        host = f"[{host}]"
    return f"{protocol}/{host}:{port}"


_RUST_SOURCE = re.compile(r"\s*\bat \S+\.rs:\d+\.?")


def zenoh_reason(exc: BaseException | None) -> str:
    """Zenoh's error text on one line, without the Rust source locations it appends (``at
    /root/.cargo/.../unicast.rs:338.``): what a user reads, not where in Zenoh it was raised."""
    text = " ".join(str(exc).split()) if exc is not None else "unknown error"
    return _RUST_SOURCE.sub("", text).strip() or type(exc).__name__


class ZenohTransport(Transport):
    """A Zenoh endpoint speaking the datagram contract over pub/sub.

    Args:
        host, port: peer mode: server listens / client connects there (server ``port`` 0 = pick
            a free one, see :attr:`url`); client mode: the router's address (both roles).
        session: the session name in the key expressions (no ``/*$?#``).
        role: ``"server"`` or ``"client"``.
        max_packet_bytes: datagram size limit enforced on send and receive.
        mode: ``"peer"`` (default, direct loopback link) or ``"client"`` (via a router).
        protocol: Zenoh link protocol for the endpoint (``tcp``, ``tls``, ``quic``, ...).
        config: path of a Zenoh JSON5 config file used as the base.
        ring_capacity: samples buffered per subscriber before the oldest is dropped.
        connect_timeout_s: how long the constructor may wait to reach the other side.
        express: publish without batching (lower latency; default ``True``).
        lowlatency: Zenoh unicast low-latency mode (QoS off); both ends must match.
    """

    scheme = "zenoh"

    def __init__(
        self,
        host: str,
        port: int,
        session: str = DEFAULT_SESSION,
        role: str = "server",
        max_packet_bytes: int = DEFAULT_MAX_PACKET_BYTES,
        mode: str = "peer",
        protocol: str = "tcp",
        config: str | None = None,
        ring_capacity: int = DEFAULT_RING_CAPACITY,
        connect_timeout_s: float = DEFAULT_CONNECT_TIMEOUT_S,
        express: bool = True,
        lowlatency: bool = False,
    ) -> None:
        super().__init__(role, max_packet_bytes)
        self._closed = True  # until the session exists
        if not isinstance(host, str) or not host:
            raise ValueError(f"host must be a non-empty string, got {host!r}")
        try:
            port = int(port)
        except (TypeError, ValueError):
            raise ValueError(f"port must be an integer, got {port!r}") from None
        if not 0 <= port <= 65535:
            raise ValueError(f"port must be in 0..65535, got {port}")
        if mode not in _MODES:
            raise ValueError(f"mode must be 'peer' or 'client', got {mode!r}")
        if port == 0 and not (mode == "peer" and role == "server"):
            raise ValueError("port 0 (pick a free port) is only valid for a peer-mode server")
        if not isinstance(protocol, str) or not protocol.isalnum():
            raise ValueError(f"protocol must be a Zenoh link protocol name like 'tcp', got {protocol!r}")
        self.session_name = _check_chunk("session", session)
        ring_capacity = int(ring_capacity)
        if ring_capacity < 1:
            raise ValueError(f"ring_capacity must be >= 1, got {ring_capacity}")
        connect_timeout_s = float(connect_timeout_s)
        if not connect_timeout_s > 0:
            raise ValueError(f"connect_timeout_s must be > 0, got {connect_timeout_s}")
        if config is not None and not os.path.isfile(config):
            raise ValueError(f"config file not found: {config!r}")

        # Zenoh reads ZENOH_RUNTIME when its runtime first starts (the first session of the
        # process); a deployment's own setting, even an empty "()", always wins.
        os.environ.setdefault("ZENOH_RUNTIME", DEFAULT_ZENOH_RUNTIME)
        import zenoh  # lazy: the only zenoh import in hapticproxy.protocol

        self._zenoh = zenoh
        self.mode = mode
        self.protocol = protocol
        self.host = host
        self.ring_capacity = ring_capacity
        self.express = bool(express)
        self.lowlatency = bool(lowlatency)
        self.connect_timeout_s = connect_timeout_s
        self._config_path = config
        self._session = None
        self._sub = None
        self._pub = None  # client: its one publisher
        self._publishers: dict[str, object] = {}  # server: reply publisher per client id
        self._peer_by_key: dict[str, str] = {}  # server: received key -> client id
        self._c2s_prefix = f"{KEY_PREFIX}/{self.session_name}/c2s/"

        attempts = 5 if port == 0 else 1
        last_exc: Exception | None = None
        for _ in range(attempts):
            self.port = _free_tcp_port(host) if port == 0 else port
            try:
                self._session = zenoh.open(self._build_config())
                break
            except zenoh.ZError as exc:
                last_exc = exc
        if self._session is None:
            raise TransportError(f"could not open Zenoh session ({self.describe()}): {zenoh_reason(last_exc)}")
        self._closed = False
        try:
            self._declare()
        except BaseException:
            self.close()
            raise

    # ------------------------------------------------------------------ set-up

    def _build_config(self):
        zenoh = self._zenoh
        cfg = zenoh.Config.from_file(self._config_path) if self._config_path else zenoh.Config()
        endpoint = _endpoint(self.protocol, self.host, self.port)
        timeout_ms = int(self.connect_timeout_s * 1000)
        cfg.insert_json5("mode", json.dumps(self.mode))
        # Explicit endpoints only: no multicast discovery, no gossip-relayed peers.
        cfg.insert_json5("scouting/multicast/enabled", "false")
        cfg.insert_json5("scouting/gossip/enabled", "false")
        if self.mode == "peer" and self.role == "server":
            cfg.insert_json5("listen/endpoints", json.dumps([endpoint]))
            cfg.insert_json5("connect/endpoints", "[]")
        else:
            cfg.insert_json5("listen/endpoints", "[]")
            cfg.insert_json5("connect/endpoints", json.dumps([endpoint]))
            # Fail the open (clear error) instead of retrying in the background forever.
            cfg.insert_json5("connect/timeout_ms", str(timeout_ms))
            cfg.insert_json5("connect/exit_on_failure", "true")
        cfg.insert_json5("transport/shared_memory/enabled", "false")
        # Our samples travel at REAL_TIME priority, whose queue defaults to 2 batches (with
        # express, 2 datagrams): a burst of 3 while Zenoh's TX thread is descheduled lost the
        # 3rd (seen in the contract tests on a loaded 2-core box). 16 is Zenoh's maximum.
        cfg.insert_json5("transport/link/tx/queue/size/real_time", str(TX_QUEUE_REAL_TIME_BATCHES))
        # A put into a full queue waits this long before dropping (default 1000 us, i.e. a whole
        # 1 kHz haptic step); newest-wins traffic is better served by dropping sooner.
        cfg.insert_json5(
            "transport/link/tx/queue/congestion_control/drop/wait_before_drop", str(WAIT_BEFORE_DROP_US)
        )
        if self.lowlatency:
            cfg.insert_json5("transport/unicast/lowlatency", "true")
            cfg.insert_json5("transport/unicast/qos/enabled", "false")
        return cfg

    def _publisher(self, key: str):
        zenoh = self._zenoh
        return self._session.declare_publisher(
            key,
            congestion_control=zenoh.CongestionControl.DROP,
            priority=zenoh.Priority.REAL_TIME,
            express=self.express,
        )

    def _declare(self) -> None:
        zenoh = self._zenoh
        session = self._session
        if self.role == "server":
            self._sub = session.declare_subscriber(
                self._c2s_prefix + "*", zenoh.handlers.RingChannel(self.ring_capacity)
            )
            self.client_id = ""
            return
        self.client_id = str(session.zid())
        # Subscriber first: its declaration precedes our first datagram on the same link.
        self._sub = session.declare_subscriber(
            s2c_key(self.session_name, self.client_id), zenoh.handlers.RingChannel(self.ring_capacity)
        )
        self._pub = self._publisher(c2s_key(self.session_name, self.client_id))
        deadline = time.monotonic() + self.connect_timeout_s
        while not self._pub.matching_status.matching:
            if time.monotonic() > deadline:
                raise TransportError(
                    f"no Zenoh server subscribed to {c2s_key(self.session_name, self.client_id)!r} "
                    f"within {self.connect_timeout_s} s ({self.describe()})"
                )
            time.sleep(0.001)

    # ------------------------------------------------------------------ properties

    @property
    def default_peer(self) -> Peer | None:
        return self.server_peer if self.role == "client" else None

    @property
    def server_peer(self) -> str:
        """The client's one peer id: ``"zenoh:SESSION"``."""
        return f"zenoh:{self.session_name}"

    @property
    def endpoint(self) -> str:
        """The Zenoh endpoint this side listens on (peer server) or connects to."""
        return _endpoint(self.protocol, self.host, self.port)

    @property
    def url(self) -> str:
        """A URL a client can open to reach this endpoint (mode and protocol included)."""
        host = f"[{self.host}]" if ":" in self.host else self.host
        query = []
        if self.mode != "peer":
            query.append(f"mode={self.mode}")
        if self.protocol != "tcp":
            query.append(f"protocol={self.protocol}")
        if self.lowlatency:
            query.append("lowlatency=true")
        return f"zenoh://{host}:{self.port}/{self.session_name}" + ("?" + "&".join(query) if query else "")

    def describe(self) -> str:
        return f"zenoh {self.mode} {self.endpoint} session={self.session_name}"

    def peer_ready(self, peer: Peer) -> bool:
        """Server: ``True`` if a reply to ``peer`` currently has a matching subscriber."""
        if self.role != "server":
            return self._pub is not None and self._pub.matching_status.matching
        pub = self._publishers.get(peer)  # type: ignore[arg-type]
        if pub is None:
            if peer not in self._publishers and peer not in self._peer_by_key.values():
                return False
            pub = self._publishers[peer] = self._publisher(s2c_key(self.session_name, peer))  # type: ignore[arg-type]
        return pub.matching_status.matching

    # ------------------------------------------------------------------ backend hooks

    def _send(self, payload: bytes | bytearray | memoryview, peer: Peer | None) -> bool:
        if isinstance(payload, memoryview):
            payload = payload.tobytes()  # zenoh takes bytes/bytearray only
        if self.role == "client":
            if peer is not None and peer != self.server_peer:
                raise ValueError(f"a Zenoh client can only send to its server {self.server_peer!r}, not {peer!r}")
            pub = self._pub
        else:
            pub = self._publishers.get(peer)  # type: ignore[arg-type]
            if pub is None:
                # Only reply to clients we have heard from: a peer id is a client's ZenohId.
                if peer not in self._peer_by_key.values():
                    return False
                pub = self._publishers[peer] = self._publisher(s2c_key(self.session_name, peer))  # type: ignore[arg-type]
        try:
            pub.put(payload)
        except self._zenoh.ZError:
            return False
        return True

    def _recv_into(self, buffer: bytearray | memoryview) -> tuple[int, Peer | None]:
        sub = self._sub
        limit = self.max_packet_bytes
        counters = self.counters
        while True:
            sample = sub.try_recv()
            if sample is None:
                return 0, None
            zbytes = sample.payload
            n = len(zbytes)
            if counters.drop_arrival(n, limit):
                continue
            if self.role == "client":
                peer = self.server_peer
            else:
                key = str(sample.key_expr)
                peer = self._peer_by_key.get(key)
                if peer is None:
                    peer = key[len(self._c2s_prefix):]
                    if len(self._peer_by_key) >= MAX_REMEMBERED_PEERS:
                        self._peer_by_key.clear()
                        self._publishers.clear()
                    self._peer_by_key[key] = peer
            buffer[:n] = zbytes.to_bytes()
            return n, peer

    def _close(self) -> None:
        session, self._session = self._session, None
        self._publishers.clear()
        self._pub = None
        self._sub = None
        if session is not None:
            try:
                session.close()
            except Exception:  # closing twice or a dead runtime: nothing left to release
                pass
