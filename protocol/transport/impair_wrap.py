"""Impair the *messages* of any transport (fault injection where no relay fits, e.g. Zenoh).

:class:`~.impair.ImpairingRelay` impairs UDP on the wire; a stream link (Zenoh over TCP or TLS)
never loses, duplicates or reorders a datagram by itself, but the publisher's queue may drop one
and a router may duplicate or reorder across links. ``ImpairedTransport`` wraps an open
endpoint and applies the same seeded :class:`~.impair.Impairment` stages (loss uniform or
bursty, corruption, duplication, reordering, delay and jitter) to what it sends and to what it
receives, so the session layer above sees exactly what a bad network would give it::

    inner = open_transport("zenoh://127.0.0.1:7447/s", role="client")
    client = ImpairedTransport(inner, send=Impairment(loss=0.3, seed=1), recv=Impairment(delay_s=0.02, seed=2))

Delayed and held datagrams are released when they are due, on the next ``send`` or ``recv_into``
(an endpoint that polls every step releases them within a step). Decisions come from each
direction's own seeded stream, in the order datagrams are handled, as for the relay.
``counters_send`` / ``counters_recv`` (:class:`~.impair.ImpairmentCounters`) say what was done.
"""
from __future__ import annotations

import heapq
import itertools
import time
from collections.abc import Callable

from .base import Peer, Transport
from .impair import Impairment, ImpairmentCounters

_PUMP_MAX = 256  # datagrams taken from the inner transport per call (bounded like a drain)


class ImpairedTransport(Transport):
    """``inner`` with impairments on its send (``send``) and receive (``recv``) directions."""

    def __init__(self, inner: Transport, send: Impairment | None = None, recv: Impairment | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        super().__init__(inner.role, inner.max_packet_bytes)
        self.inner = inner
        self.scheme = inner.scheme
        self.clock = clock
        self.impair_send = send or Impairment()
        self.impair_recv = recv or Impairment()
        self._decide_tx = self.impair_send.decider()
        self._decide_rx = self.impair_recv.decider()
        self.counters_send = ImpairmentCounters()
        self.counters_recv = ImpairmentCounters()
        self._tx: list = []  # (due, tiebreak, payload, peer)
        self._rx: list = []
        self._held_tx = None  # (release_s, payload, peer, delays)
        self._held_rx = None
        self._tie = itertools.count()
        self._buf = bytearray(inner.max_packet_bytes)

    # ------------------------------------------------------------------ delegation
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

    # ------------------------------------------------------------------ decisions
    def _admit(self, decide, impairment: Impairment, counters: ImpairmentCounters, queue: list, held_attr: str,
               payload: bytes, peer: Peer, now: float) -> None:
        counters.received += 1
        d = decide(len(payload))
        if d.lost:
            counters.lost += 1
            return
        if d.corrupt_at is not None:
            i, bit = d.corrupt_at
            b = bytearray(payload)
            b[i] ^= 1 << bit
            payload = bytes(b)
            counters.corrupted += 1
        if d.copies > 1:
            counters.duplicated += d.copies - 1
        held = getattr(self, held_attr)
        setattr(self, held_attr, None)
        if held is None and d.hold:
            counters.reordered += 1
            setattr(self, held_attr, (now + impairment.reorder_hold_s, payload, peer, d.delays_s))
            return
        for delay in d.delays_s:
            heapq.heappush(queue, (now + delay, next(self._tie), payload, peer))
        if held is not None:  # released right after the datagram that overtook it
            for delay in held[3]:
                heapq.heappush(queue, (now + delay, next(self._tie), held[1], held[2]))

    def _release_held(self, now: float) -> None:
        for attr, queue in (("_held_tx", self._tx), ("_held_rx", self._rx)):
            held = getattr(self, attr)
            if held is not None and held[0] <= now:
                setattr(self, attr, None)
                for delay in held[3]:
                    heapq.heappush(queue, (now + delay, next(self._tie), held[1], held[2]))

    def _flush_tx(self, now: float) -> None:
        q = self._tx
        while q and q[0][0] <= now:
            _, _, payload, peer = heapq.heappop(q)
            if self.inner.send(payload, peer):
                self.counters_send.forwarded += 1
            else:
                self.counters_send.send_errors += 1

    def _pump(self) -> None:
        now = self.clock()
        self._release_held(now)
        self._flush_tx(now)
        buf = self._buf
        for _ in range(_PUMP_MAX):
            n, peer = self.inner.recv_into(buf)
            if peer is None:
                break
            self._admit(self._decide_rx, self.impair_recv, self.counters_recv, self._rx, "_held_rx",
                        bytes(buf[:n]), peer, now)

    def pending(self) -> int:
        """Datagrams scheduled or held, both directions, not yet released."""
        return len(self._tx) + len(self._rx) + (self._held_tx is not None) + (self._held_rx is not None)

    # ------------------------------------------------------------------ backend hooks
    def _send(self, payload, peer: Peer | None) -> bool:
        now = self.clock()
        self._admit(self._decide_tx, self.impair_send, self.counters_send, self._tx, "_held_tx", bytes(payload),
                    peer, now)
        self._pump()
        return True  # like a network: a lost datagram was still "sent"

    def _recv_into(self, buffer) -> tuple[int, Peer | None]:
        self._pump()
        q = self._rx
        if q and q[0][0] <= self.clock():
            _, _, payload, peer = heapq.heappop(q)
            n = len(payload)
            buffer[:n] = payload
            self.counters_recv.forwarded += 1
            return n, peer
        return 0, None

    def _close(self) -> None:
        self.inner.close()


__all__ = ["ImpairedTransport"]
