"""Fault injection for datagram links (user-space stand-ins for ``tc netem``): test tools only.

One model of a bad network, :class:`Impairment`, applied in two places:

- :class:`ImpairingRelay`, a UDP relay on loopback between an environment client (or a device
  program) and a UDP server::

      server = open_transport("udp://127.0.0.1:0", role="server")
      with ImpairingRelay(server.local_address,
                          c2s=Impairment(loss=0.05, seed=1),
                          s2c=Impairment(delay_s=0.002, jitter_s=0.001, seed=2)) as relay:
          relay.start()                                   # background thread
          client = open_transport(relay.url, role="client")

  The relay listens on one UDP port (``relay.url``). Each client source address gets its own
  upstream socket, so the server still sees one distinct peer per client, and replies travel
  back through the same impairments (``s2c``) to the client they belong to.
- :class:`ImpairedTransport`, a wrapper around any open
  :class:`~hapticproxy.protocol.transport.Transport` that impairs the *messages* it sends and
  receives (where no relay fits, e.g. Zenoh: a stream link never loses, duplicates or reorders a
  datagram by itself, but the publisher's queue may drop one and a router may duplicate or
  reorder across links)::

      inner = open_transport("zenoh://127.0.0.1:7447/s", role="client")
      client = ImpairedTransport(inner, send=Impairment(loss=0.3, seed=1), recv=Impairment(delay_s=0.02, seed=2))

  Delayed and held datagrams are released when they are due, on the next ``send`` or
  ``recv_into`` (an endpoint that polls every step releases them within a step).

Per direction, every datagram goes through these stages, in order, each decided by that
direction's own seeded ``random.Random`` (so a given seed and arrival order reproduce the same
decisions, and :meth:`Impairment.plan` can predict them offline); :class:`_Direction` is the
one implementation both tools use:

1. **loss**: uniform (``loss``) or bursty with a two-state Gilbert-Elliott chain
   (``burst=GilbertElliott(p_good_to_bad, p_bad_to_good, loss_in_good, loss_in_bad)``: state
   transition first, then loss with the new state's probability; mean burst length
   ``1 / p_bad_to_good`` for ``loss_in_bad=1``);
2. **corruption** (``corrupt``): one random bit of one random byte flipped;
3. **duplication** (``duplicate``): one extra copy, scheduled like the original;
4. **reordering** (``reorder``): the datagram is held back and released right after the next
   datagram of the same flow (one adjacent swap each), or after ``reorder_hold_s`` if none comes;
5. **delay**: ``delay_s`` plus uniform jitter in ``[-jitter_s, +jitter_s]`` (never negative);
   jitter larger than the gap between datagrams reorders them too, as in netem.

Counters per direction (:class:`ImpairmentCounters`, plain ints) say exactly what was done.

Timing comes from an injectable ``clock`` (seconds, default ``time.monotonic``), and the relay can
be driven by hand with :meth:`ImpairingRelay.step` instead of :meth:`ImpairingRelay.start`, which
makes delay and jitter testable without wall-clock thresholds. :mod:`.impair_tcp` injects the
faults a stream link (TCP) can suffer.
"""
from __future__ import annotations

import heapq
import itertools
import random
import select
import socket
import threading
import time
from collections.abc import Callable
from dataclasses import MISSING, dataclass, field, fields

from ..protocol.transport.base import Peer, Transport

__all__ = ["Decision", "GilbertElliott", "Impairment", "ImpairedTransport", "ImpairingRelay", "ImpairmentCounters"]

MAX_DATAGRAM_BYTES = 65535
_DEFAULT_RCVBUF_BYTES = 4 * 1024 * 1024
_IDLE_WAIT_S = 0.005  # background loops: longest select() wait when nothing is scheduled
_PUMP_MAX = 256  # datagrams an ImpairedTransport takes from its inner transport per call


def _check_probability(name: str, value: float) -> float:
    v = float(value)
    if not 0.0 <= v <= 1.0:
        raise ValueError(f"{name} must be a probability in [0, 1], got {value!r}")
    return v


def _check_nonnegative(name: str, value: float) -> float:
    v = float(value)
    if not v >= 0.0:
        raise ValueError(f"{name} must be >= 0, got {value!r}")
    return v


def _probability(default=MISSING):
    """A field holding a probability in [0, 1] (checked by :func:`_check_fields`)."""
    return field(default=default, metadata={"check": _check_probability})


def _nonnegative(default=MISSING):
    """A field holding a number >= 0 (checked by :func:`_check_fields`)."""
    return field(default=default, metadata={"check": _check_nonnegative})


def _check_fields(obj, prefix: str = "") -> None:
    """Run the check each field of the dataclass ``obj`` declares, in field order; the
    ``ValueError`` names the field (after ``prefix``)."""
    for f in fields(obj):
        check = f.metadata.get("check")
        if check is not None:
            check(prefix + f.name, getattr(obj, f.name))


@dataclass(frozen=True)
class GilbertElliott:
    """Two-state bursty loss: a good and a bad state with their own loss probabilities."""

    p_good_to_bad: float = _probability()
    p_bad_to_good: float = _probability()
    loss_in_good: float = _probability(0.0)
    loss_in_bad: float = _probability(1.0)

    def __post_init__(self) -> None:
        _check_fields(self, "burst.")

    @property
    def mean_loss(self) -> float:
        """Stationary loss probability of the chain."""
        total = self.p_good_to_bad + self.p_bad_to_good
        if total == 0:
            return self.loss_in_good
        pi_bad = self.p_good_to_bad / total
        return (1 - pi_bad) * self.loss_in_good + pi_bad * self.loss_in_bad


@dataclass(frozen=True)
class Decision:
    """What the relay does with one datagram (see :meth:`Impairment.plan`)."""

    lost: bool
    corrupt_at: tuple[int, int] | None  # (byte index, bit) flipped, or None
    copies: int  # 1, or 2 when duplicated (0 when lost)
    hold: bool  # reordered: released after the next datagram of the flow
    delays_s: tuple[float, ...]  # one per copy


@dataclass(frozen=True)
class Impairment:
    """What to do to one direction of traffic. All probabilities are per datagram."""

    loss: float = _probability(0.0)
    burst: GilbertElliott | None = None
    corrupt: float = _probability(0.0)
    duplicate: float = _probability(0.0)
    reorder: float = _probability(0.0)
    reorder_hold_s: float = _nonnegative(0.05)
    delay_s: float = _nonnegative(0.0)
    jitter_s: float = _nonnegative(0.0)
    seed: int = 0

    def __post_init__(self) -> None:
        _check_fields(self)
        if self.burst is not None and self.loss:
            raise ValueError("give either loss (uniform) or burst (Gilbert-Elliott), not both")

    def decider(self) -> Callable[[int], Decision]:
        """A stateful function ``decide(nbytes) -> Decision`` fed by this seed's random stream.

        The relay uses one per direction; calling it offline with the same sizes in the same
        order reproduces the relay's decisions exactly.
        """
        rng = random.Random(self.seed)
        bad = False
        burst = self.burst

        def decide(nbytes: int) -> Decision:
            nonlocal bad
            # Always draw the same number of variates per datagram so that one stage's outcome
            # does not shift the random stream seen by the others.
            u_state, u_loss, u_corrupt, u_byte, u_bit, u_dup, u_reorder = (rng.random() for _ in range(7))
            u_delays = (rng.random(), rng.random())
            if burst is not None:
                if bad:
                    bad = u_state >= burst.p_bad_to_good
                else:
                    bad = u_state < burst.p_good_to_bad
                lost = u_loss < (burst.loss_in_bad if bad else burst.loss_in_good)
            else:
                lost = u_loss < self.loss
            if lost:
                return Decision(True, None, 0, False, ())
            corrupt_at = None
            if nbytes > 0 and u_corrupt < self.corrupt:
                corrupt_at = (min(int(u_byte * nbytes), nbytes - 1), min(int(u_bit * 8), 7))
            copies = 2 if u_dup < self.duplicate else 1
            hold = u_reorder < self.reorder
            delays = tuple(
                max(0.0, self.delay_s + (2.0 * u - 1.0) * self.jitter_s) for u in u_delays[:copies]
            )
            return Decision(False, corrupt_at, copies, hold, delays)

        return decide

    def plan(self, sizes: list[int]) -> list[Decision]:
        """Decisions for datagrams of these sizes arriving in this order (for tests)."""
        decide = self.decider()
        return [decide(n) for n in sizes]


class Counters:
    """Event counts as plain ints (the names are the subclass's ``__slots__``)."""

    __slots__ = ()

    def __init__(self) -> None:
        for name in self.__slots__:
            setattr(self, name, 0)

    def as_dict(self) -> dict[str, int]:
        return {name: getattr(self, name) for name in self.__slots__}

    def __repr__(self) -> str:
        return f"{type(self).__name__}(" + ", ".join(f"{k}={v}" for k, v in self.as_dict().items()) + ")"


class ImpairmentCounters(Counters):
    """What one direction did."""

    __slots__ = ("received", "forwarded", "lost", "corrupted", "duplicated", "reordered", "send_errors")


class _Direction:
    """One direction's stages: its seeded decisions (``decide``, replaceable, e.g. by a wrapper
    that silences the link), its counters, the datagram held back per flow for reordering and
    the queue of scheduled sends. ``target`` is whatever the owner needs to send one datagram."""

    def __init__(self, impairment: Impairment) -> None:
        self.impairment = impairment
        self.decide = impairment.decider()
        self.counters = ImpairmentCounters()
        self._queue: list = []  # heap of (due_s, tiebreak, payload, target)
        self._held: dict = {}   # flow -> (release_s, payload, delays_s, target)
        self._tie = itertools.count()

    def admit(self, payload: bytes, target, now: float, flow=None) -> None:
        counters = self.counters
        counters.received += 1
        d = self.decide(len(payload))
        if d.lost:
            counters.lost += 1
            return
        if d.corrupt_at is not None:
            i, bit = d.corrupt_at
            mutable = bytearray(payload)
            mutable[i] ^= 1 << bit
            payload = bytes(mutable)
            counters.corrupted += 1
        if d.copies > 1:
            counters.duplicated += d.copies - 1
        held = self._held.pop(flow, None)
        if held is None and d.hold:
            counters.reordered += 1
            self._held[flow] = (now + self.impairment.reorder_hold_s, payload, d.delays_s, target)
            return
        self._schedule(now, payload, d.delays_s, target)
        if held is not None:
            # released right after the datagram that overtook it (with its own delays)
            self._schedule(now, held[1], held[2], held[3])

    def _schedule(self, now: float, payload: bytes, delays_s, target) -> None:
        for delay in delays_s:
            heapq.heappush(self._queue, (now + delay, next(self._tie), payload, target))

    def release_held(self, now: float) -> None:
        """Held datagrams that nothing overtook within ``reorder_hold_s`` go as they are."""
        for flow, held in list(self._held.items()):
            if held[0] <= now:
                del self._held[flow]
                self._schedule(now, held[1], held[2], held[3])

    def pop_due(self, now: float):
        """The next ``(payload, target)`` due by ``now``, or None."""
        q = self._queue
        if q and q[0][0] <= now:
            _, _, payload, target = heapq.heappop(q)
            return payload, target
        return None

    def next_due(self) -> float | None:
        times = [h[0] for h in self._held.values()]
        if self._queue:
            times.append(self._queue[0][0])
        return min(times) if times else None

    def pending(self) -> int:
        return len(self._queue) + len(self._held)


class _SelectLoop:
    """A background thread that waits on sockets (or until the next scheduled send) and calls
    :meth:`step`; subclasses give ``_readable()``, ``_next_due()``, ``step()`` and
    ``_close_sockets()``, and call ``_init_loop()`` in their constructor."""

    _thread_name = "impair"

    def _init_loop(self) -> None:
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._closed = False

    def start(self):
        """Run in a background thread until :meth:`close`."""
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name=self._thread_name, daemon=True)
            self._thread.start()
        return self

    def _run(self) -> None:
        while not self._stop.is_set():
            with self._lock:
                readable = self._readable()
                due = self._next_due()
            wait = _IDLE_WAIT_S if due is None else min(_IDLE_WAIT_S, max(0.0, due - self.clock()))
            try:
                select.select(readable, [], [], wait)
            except (OSError, ValueError):
                if self._stop.is_set():
                    break
                continue
            if self._stop.is_set():
                break
            self.step()

    def close(self) -> None:
        """Stop the thread (if any) and close every socket. Idempotent."""
        if self._closed:
            return
        self._closed = True
        self._stop.set()
        if self._thread is not None:
            self._thread.join(5)
        with self._lock:
            self._close_sockets()

    def __enter__(self):
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class ImpairingRelay(_SelectLoop):
    """A UDP relay on ``listen`` that forwards to ``server`` through two :class:`Impairment` s.

    Args:
        server: ``(host, port)`` of the UDP server to relay to.
        c2s: impairment of client -> server datagrams (default: none).
        s2c: impairment of server -> client datagrams (default: none).
        listen: ``(host, port)`` the relay binds for clients (default ``127.0.0.1``, any port).
        clock: time source in seconds (inject a fake one to drive delays by hand).
        rcvbuf_bytes: requested ``SO_RCVBUF`` of the relay's sockets.
    """

    _thread_name = "impairing-relay"

    def __init__(
        self,
        server: tuple[str, int],
        c2s: Impairment | None = None,
        s2c: Impairment | None = None,
        listen: tuple[str, int] = ("127.0.0.1", 0),
        clock: Callable[[], float] = time.monotonic,
        rcvbuf_bytes: int = _DEFAULT_RCVBUF_BYTES,
    ) -> None:
        self._init_loop()
        self.server = (str(server[0]), int(server[1]))
        self.c2s = _Direction(c2s or Impairment())
        self.s2c = _Direction(s2c or Impairment())
        self.clock = clock
        self._rcvbuf_bytes = rcvbuf_bytes
        self._front = self._socket()
        self._front.bind(listen)
        self.address: tuple[str, int] = self._front.getsockname()[:2]
        self._upstream: dict[tuple, socket.socket] = {}  # client address -> socket to server
        self._client_of: dict[socket.socket, tuple] = {}
        self._buf = bytearray(MAX_DATAGRAM_BYTES)

    @property
    def url(self) -> str:
        """``udp://HOST:PORT`` a client opens to go through the relay."""
        return f"udp://{self.address[0]}:{self.address[1]}"

    def step(self) -> int:
        """Read every waiting datagram, then send everything due by ``clock()``; never blocks.

        Returns the number of datagrams sent. Drive a relay by hand with this (and a fake
        clock) instead of :meth:`start`.
        """
        with self._lock:
            self._read_all()
            return self._send_due()

    def pending(self) -> int:
        """Datagrams scheduled or held but not yet sent."""
        return self.c2s.pending() + self.s2c.pending()

    # ------------------------------------------------------------------ internals
    def _socket(self) -> socket.socket:
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, self._rcvbuf_bytes)
        except OSError:
            pass  # keep the OS default; the relay still works, bursts may overflow sooner
        s.setblocking(False)
        return s

    def _readable(self) -> list:
        return [self._front, *self._upstream.values()]

    def _next_due(self) -> float | None:
        dues = [d for d in (self.c2s.next_due(), self.s2c.next_due()) if d is not None]
        return min(dues) if dues else None

    def _close_sockets(self) -> None:
        for s in list(self._upstream.values()):
            s.close()
        self._upstream.clear()
        self._client_of.clear()
        self._front.close()

    def _read_all(self) -> None:
        buf = self._buf
        while True:  # client -> server
            try:
                n, client = self._front.recvfrom_into(buf)
            except (BlockingIOError, InterruptedError):
                break
            except OSError:
                break
            up = self._upstream.get(client)
            if up is None:
                up = self._socket()
                up.connect(self.server)
                self._upstream[client] = up
                self._client_of[up] = client
            self.c2s.admit(bytes(buf[:n]), (up, None), self.clock(), flow=client)
        for up, client in list(self._client_of.items()):  # server -> each client
            while True:
                try:
                    n = up.recv_into(buf)
                except (BlockingIOError, InterruptedError):
                    break
                except OSError:  # ICMP from a server that is not (yet) listening
                    break
                self.s2c.admit(bytes(buf[:n]), (self._front, client), self.clock(), flow=client)

    def _send_due(self) -> int:
        now = self.clock()
        sent = 0
        for direction in (self.c2s, self.s2c):
            direction.release_held(now)
            while (item := direction.pop_due(now)) is not None:
                payload, (sock, dest) = item
                try:
                    if dest is None:
                        sock.send(payload)
                    else:
                        sock.sendto(payload, dest)
                    direction.counters.forwarded += 1
                    sent += 1
                except OSError:
                    direction.counters.send_errors += 1
        return sent


class ImpairedTransport(Transport):
    """``inner`` with impairments on its send (``send``) and receive (``recv``) directions.

    ``counters_send`` / ``counters_recv`` (:class:`ImpairmentCounters`) say what was done;
    attributes the wrapper does not have (``local_address``, ``fileno``, ...) are the inner
    transport's.
    """

    def __init__(self, inner: Transport, send: Impairment | None = None, recv: Impairment | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        super().__init__(inner.role, inner.max_packet_bytes)
        self.inner = inner
        self.scheme = inner.scheme
        self.clock = clock
        self._tx = _Direction(send or Impairment())
        self._rx = _Direction(recv or Impairment())
        self.impair_send, self.counters_send = self._tx.impairment, self._tx.counters
        self.impair_recv, self.counters_recv = self._rx.impairment, self._rx.counters
        self._buf = bytearray(inner.max_packet_bytes)

    @property
    def default_peer(self) -> Peer | None:
        return self.inner.default_peer

    @property
    def url(self) -> str:
        return self.inner.url

    def describe(self) -> str:
        return f"impaired {self.inner.describe()}"

    def __getattr__(self, name: str):  # e.g. local_address, peer_ready, fileno
        if name == "inner":
            raise AttributeError(name)
        return getattr(self.inner, name)

    def pending(self) -> int:
        """Datagrams scheduled or held, both directions, not yet released."""
        return self._tx.pending() + self._rx.pending()

    def _pump(self) -> None:
        now = self.clock()
        self._tx.release_held(now)
        self._rx.release_held(now)
        while (item := self._tx.pop_due(now)) is not None:
            payload, peer = item
            if self.inner.send(payload, peer):
                self._tx.counters.forwarded += 1
            else:
                self._tx.counters.send_errors += 1
        buf = self._buf
        for _ in range(_PUMP_MAX):
            n, peer = self.inner.recv_into(buf)
            if peer is None:
                break
            self._rx.admit(bytes(buf[:n]), peer, now)

    # ------------------------------------------------------------------ backend hooks
    def _send(self, payload, peer: Peer | None) -> bool:
        self._tx.admit(bytes(payload), peer, self.clock())
        self._pump()
        return True  # like a network: a lost datagram was still "sent"

    def _recv_into(self, buffer) -> tuple[int, Peer | None]:
        self._pump()
        item = self._rx.pop_due(self.clock())
        if item is None:
            return 0, None
        payload, peer = item
        n = len(payload)
        buffer[:n] = payload
        self._rx.counters.forwarded += 1
        return n, peer

    def _close(self) -> None:
        self.inner.close()
