"""An impairing UDP relay for fault injection on loopback (user-space stand-in for ``tc netem``).

Put it between an environment client and a UDP server::

    server = open_transport("udp://127.0.0.1:0", role="server")
    with ImpairingRelay(server.local_address,
                        c2s=Impairment(loss=0.05, seed=1),
                        s2c=Impairment(delay_s=0.002, jitter_s=0.001, seed=2)) as relay:
        relay.start()                                   # background thread
        client = open_transport(relay.url, role="client")

The relay listens on one UDP port (``relay.url``). Each client source address gets its own
upstream socket, so the server still sees one distinct peer per client, and replies travel back
through the same impairments (``s2c``) to the client they belong to.

Per direction, every datagram goes through these stages, in order, each decided by that
direction's own seeded ``random.Random`` (so a given seed and arrival order reproduce the same
decisions, and :meth:`Impairment.plan` can predict them offline):

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

Timing comes from an injectable ``clock`` (seconds, default ``time.monotonic``) and the relay
can be driven by hand with :meth:`ImpairingRelay.step` instead of :meth:`start`, which makes
delay and jitter testable without wall-clock thresholds.
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
from dataclasses import dataclass

MAX_DATAGRAM_BYTES = 65535
_DEFAULT_RCVBUF_BYTES = 4 * 1024 * 1024
_IDLE_WAIT_S = 0.005  # background loop: longest select() wait when nothing is scheduled


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


@dataclass(frozen=True)
class GilbertElliott:
    """Two-state bursty loss: a good and a bad state with their own loss probabilities."""

    p_good_to_bad: float
    p_bad_to_good: float
    loss_in_good: float = 0.0
    loss_in_bad: float = 1.0

    def __post_init__(self) -> None:
        for name in ("p_good_to_bad", "p_bad_to_good", "loss_in_good", "loss_in_bad"):
            _check_probability(f"burst.{name}", getattr(self, name))

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

    loss: float = 0.0
    burst: GilbertElliott | None = None
    corrupt: float = 0.0
    duplicate: float = 0.0
    reorder: float = 0.0
    reorder_hold_s: float = 0.05
    delay_s: float = 0.0
    jitter_s: float = 0.0
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("loss", "corrupt", "duplicate", "reorder"):
            _check_probability(name, getattr(self, name))
        for name in ("reorder_hold_s", "delay_s", "jitter_s"):
            _check_nonnegative(name, getattr(self, name))
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


class ImpairmentCounters:
    """What one direction of the relay did, as plain ints."""

    __slots__ = ("received", "forwarded", "lost", "corrupted", "duplicated", "reordered", "send_errors")

    def __init__(self) -> None:
        for name in self.__slots__:
            setattr(self, name, 0)

    def as_dict(self) -> dict[str, int]:
        return {name: getattr(self, name) for name in self.__slots__}

    def __repr__(self) -> str:
        return "ImpairmentCounters(" + ", ".join(f"{k}={v}" for k, v in self.as_dict().items()) + ")"


class _Direction:
    def __init__(self, impairment: Impairment) -> None:
        self.impairment = impairment
        self.decide = impairment.decider()
        self.counters = ImpairmentCounters()


class ImpairingRelay:
    """A UDP relay on ``listen`` that forwards to ``server`` through two :class:`Impairment` s.

    Args:
        server: ``(host, port)`` of the UDP server to relay to.
        c2s: impairment of client -> server datagrams (default: none).
        s2c: impairment of server -> client datagrams (default: none).
        listen: ``(host, port)`` the relay binds for clients (default ``127.0.0.1``, any port).
        clock: time source in seconds (inject a fake one to drive delays by hand).
        rcvbuf_bytes: requested ``SO_RCVBUF`` of the relay's sockets.
    """

    def __init__(
        self,
        server: tuple[str, int],
        c2s: Impairment | None = None,
        s2c: Impairment | None = None,
        listen: tuple[str, int] = ("127.0.0.1", 0),
        clock: Callable[[], float] = time.monotonic,
        rcvbuf_bytes: int = _DEFAULT_RCVBUF_BYTES,
    ) -> None:
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
        # Scheduled sends: (due_s, tiebreak, socket, destination or None, payload).
        self._queue: list = []
        self._tiebreak = itertools.count()
        # Reordering: per flow (direction, client): (release deadline, payload, decision, socket,
        # destination, direction) of the datagram held back.
        self._held: dict[tuple, tuple] = {}
        self._buf = bytearray(MAX_DATAGRAM_BYTES)
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._closed = False

    # ------------------------------------------------------------------ public API

    @property
    def url(self) -> str:
        """``udp://HOST:PORT`` a client opens to go through the relay."""
        return f"udp://{self.address[0]}:{self.address[1]}"

    def start(self) -> "ImpairingRelay":
        """Run the relay in a background thread until :meth:`close`."""
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name="impairing-relay", daemon=True)
            self._thread.start()
        return self

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
        return len(self._queue) + len(self._held)

    def close(self) -> None:
        """Stop the thread (if any) and close every socket. Idempotent."""
        if self._closed:
            return
        self._closed = True
        self._stop.set()
        if self._thread is not None:
            self._thread.join(5)
        with self._lock:
            for s in list(self._upstream.values()):
                s.close()
            self._upstream.clear()
            self._client_of.clear()
            self._front.close()

    def __enter__(self) -> "ImpairingRelay":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ internals

    def _socket(self) -> socket.socket:
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, self._rcvbuf_bytes)
        except OSError:
            pass  # keep the OS default; the relay still works, bursts may overflow sooner
        s.setblocking(False)
        return s

    def _run(self) -> None:
        while not self._stop.is_set():
            with self._lock:
                sockets = [self._front, *self._upstream.values()]
                due = self._queue[0][0] if self._queue else None
                if self._held:
                    hold_due = min(h[0] for h in self._held.values())
                    due = hold_due if due is None else min(due, hold_due)
            wait = _IDLE_WAIT_S if due is None else min(_IDLE_WAIT_S, max(0.0, due - self.clock()))
            try:
                select.select(sockets, [], [], wait)
            except (OSError, ValueError):
                if self._stop.is_set():
                    break
                continue
            if self._stop.is_set():
                break
            self.step()

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
            self._admit(self.c2s, ("c2s", client), bytes(buf[:n]), up, None)
        for up, client in list(self._client_of.items()):  # server -> each client
            while True:
                try:
                    n = up.recv_into(buf)
                except (BlockingIOError, InterruptedError):
                    break
                except OSError:  # ICMP from a server that is not (yet) listening
                    break
                self._admit(self.s2c, ("s2c", client), bytes(buf[:n]), self._front, client)

    def _admit(self, direction: _Direction, flow: tuple, payload: bytes, sock: socket.socket, dest) -> None:
        counters = direction.counters
        counters.received += 1
        d = direction.decide(len(payload))
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
        now = self.clock()
        held = self._held.pop(flow, None)
        if held is None and d.hold:
            counters.reordered += 1
            self._held[flow] = (now + direction.impairment.reorder_hold_s, payload, d, sock, dest, direction)
            return
        self._schedule(now, payload, d, sock, dest)
        if held is not None:
            # Released right after the datagram that overtook it (same delays as its own).
            _, held_payload, held_d, hsock, hdest, _ = held
            self._schedule(now, held_payload, held_d, hsock, hdest)

    def _schedule(self, now: float, payload: bytes, d: Decision, sock: socket.socket, dest) -> None:
        for delay in d.delays_s:
            heapq.heappush(self._queue, (now + delay, next(self._tiebreak), sock, dest, payload))

    def _send_due(self) -> int:
        now = self.clock()
        for flow, held in list(self._held.items()):
            if held[0] <= now:  # nothing overtook it in time: release it as it is
                del self._held[flow]
                _, payload, d, sock, dest, _ = held
                self._schedule(now, payload, d, sock, dest)
        sent = 0
        queue = self._queue
        while queue and queue[0][0] <= now:
            _, _, sock, dest, payload = heapq.heappop(queue)
            direction = self.s2c if dest is not None else self.c2s
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
