"""A user-space impairing TCP proxy (fault injection for stream links such as Zenoh's).

``tc netem`` is not available everywhere we test, and Zenoh carries our datagrams over TCP (or
TLS over TCP), where a lost segment shows up as *delay* (retransmission), never as a lost
datagram. So the faults a stream link can suffer are: delay (and its variation), a stall (the
link delivers nothing for a while, then everything it buffered at once) and a close (the link is
torn down, e.g. a reset). This proxy injects exactly those::

    server = open_transport("zenoh://127.0.0.1:0/s", role="server")   # listens on tcp/127.0.0.1:P
    with ImpairingTcpProxy(("127.0.0.1", P), delay_s=0.02) as proxy:
        proxy.start()
        client = open_transport(f"zenoh://127.0.0.1:{proxy.address[1]}/s", role="client")
        proxy.stall(0.3)        # nothing crosses the link for 300 ms (both directions)
        proxy.reset_links()     # every open connection is reset (RST), new ones are accepted

Each accepted connection gets its own upstream connection; bytes are forwarded in order in both
directions. Per direction, a chunk read at time ``t`` is released at ``max(t + delay +
jitter, previous release)``: jitter varies the delay but never reorders bytes (TCP does not).
While stalled nothing is released (reading goes on, so the senders do not block: the link
"holds" the data, as a congested path with retransmissions does). Timing comes from an
injectable ``clock`` (seconds).

Counters (:attr:`ImpairingTcpProxy.counters`, plain ints): connections accepted / reset /
refused upstream, chunks and bytes per direction, stalls. The background thread is the UDP
relay's (:class:`~.impair._SelectLoop`).
"""
from __future__ import annotations

import collections
import random
import socket
import struct
import time
from collections.abc import Callable

from .impair import Counters, _SelectLoop

_CHUNK = 65536


class TcpProxyCounters(Counters):
    """What the proxy did."""

    __slots__ = ("accepted", "upstream_refused", "reset", "closed", "chunks_c2s", "chunks_s2c", "bytes_c2s",
                 "bytes_s2c", "stalls")


class _Pipe:
    """One direction of one connection: chunks waiting for their release time."""

    __slots__ = ("src", "dst", "queue", "last_due", "name", "eof")

    def __init__(self, src: socket.socket, dst: socket.socket, name: str) -> None:
        self.src = src
        self.dst = dst
        self.queue: collections.deque = collections.deque()  # (due_s, bytes)
        self.last_due = 0.0
        self.name = name
        self.eof = False


class ImpairingTcpProxy(_SelectLoop):
    """Listen on ``listen``; relay every connection to ``upstream`` through the impairments.

    Args:
        upstream: ``(host, port)`` of the real TCP server.
        delay_s: one-way delay added to every chunk, both directions.
        jitter_s: uniform variation of that delay in ``[-jitter_s, +jitter_s]`` (never negative,
            never reordering).
        listen: ``(host, port)`` to bind (default ``127.0.0.1``, any free port).
        seed: seed of the jitter's random stream.
        clock: time source in seconds.
    """

    _thread_name = "impairing-tcp-proxy"

    def __init__(self, upstream: tuple[str, int], *, delay_s: float = 0.0, jitter_s: float = 0.0,
                 listen: tuple[str, int] = ("127.0.0.1", 0), seed: int = 0,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self._init_loop()
        for name, v in (("delay_s", delay_s), ("jitter_s", jitter_s)):
            if not (isinstance(v, (int, float)) and v >= 0.0):
                raise ValueError(f"{name} must be a number >= 0, got {v!r}")
        self.upstream = (str(upstream[0]), int(upstream[1]))
        self.delay_s = float(delay_s)
        self.jitter_s = float(jitter_s)
        self.clock = clock
        self.counters = TcpProxyCounters()
        self._rng = random.Random(seed)
        self._lsock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._lsock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self._lsock.bind(listen)
        self._lsock.listen(64)
        self._lsock.setblocking(False)
        self.address: tuple[str, int] = self._lsock.getsockname()[:2]
        self._pipes: list[_Pipe] = []
        self._pairs: list[tuple[socket.socket, socket.socket]] = []
        self._stalled_until = 0.0

    # ------------------------------------------------------------------ control
    def set_delay(self, delay_s: float, jitter_s: float | None = None) -> None:
        """Change the delay (and jitter) for chunks read from now on."""
        if not delay_s >= 0.0 or (jitter_s is not None and not jitter_s >= 0.0):
            raise ValueError("delay_s and jitter_s must be >= 0")
        with self._lock:
            self.delay_s = float(delay_s)
            if jitter_s is not None:
                self.jitter_s = float(jitter_s)

    def stall(self, seconds: float) -> None:
        """Release nothing, in either direction, for ``seconds`` from now."""
        if not seconds >= 0.0:
            raise ValueError(f"seconds must be >= 0, got {seconds!r}")
        with self._lock:
            self._stalled_until = max(self._stalled_until, self.clock() + float(seconds))
            self.counters.stalls += 1

    @property
    def stalled(self) -> bool:
        return self.clock() < self._stalled_until

    def reset_links(self) -> int:
        """Reset (RST) every open connection, both sides; new connections are still accepted.
        Returns how many connections were reset."""
        with self._lock:
            n = len(self._pairs)
            for a, b in self._pairs:
                for s in (a, b):
                    _abort(s)
            self.counters.reset += n
            self._pairs.clear()
            self._pipes.clear()
        return n

    @property
    def connections(self) -> int:
        return len(self._pairs)

    def _close_sockets(self) -> None:
        for a, b in self._pairs:
            a.close()
            b.close()
        self._pairs.clear()
        self._pipes.clear()
        self._lsock.close()

    # ------------------------------------------------------------------ the loop
    def step(self) -> None:
        """Accept, read what is waiting, release what is due; never blocks (for tests)."""
        with self._lock:
            self._accept()
            self._read()
            self._release()

    def _readable(self) -> list:
        return [self._lsock] + [p.src for p in self._pipes if not p.eof]

    def _next_due(self) -> float | None:
        due = min((p.queue[0][0] for p in self._pipes if p.queue), default=None)
        if due is not None and self._stalled_until > due:
            due = self._stalled_until
        return due

    def _accept(self) -> None:
        while True:
            try:
                down, _ = self._lsock.accept()
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                return
            up = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            try:
                up.settimeout(2.0)
                up.connect(self.upstream)
            except OSError:
                self.counters.upstream_refused += 1
                up.close()
                _abort(down)
                continue
            for s in (down, up):
                s.setblocking(False)
                s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            self.counters.accepted += 1
            self._pairs.append((down, up))
            self._pipes.append(_Pipe(down, up, "c2s"))
            self._pipes.append(_Pipe(up, down, "s2c"))

    def _read(self) -> None:
        now = self.clock()
        for p in list(self._pipes):
            if p.eof:
                continue
            while True:
                try:
                    data = p.src.recv(_CHUNK)
                except (BlockingIOError, InterruptedError):
                    break
                except OSError:
                    self._drop_pair(p.src, reset=True)
                    return
                if not data:
                    p.eof = True
                    p.queue.append((max(now, p.last_due), b""))  # EOF travels in order too
                    break
                delay = self.delay_s
                if self.jitter_s:
                    delay = max(0.0, delay + (2.0 * self._rng.random() - 1.0) * self.jitter_s)
                due = max(now + delay, p.last_due)
                p.last_due = due
                p.queue.append((due, data))
                c = self.counters
                if p.name == "c2s":
                    c.chunks_c2s += 1
                    c.bytes_c2s += len(data)
                else:
                    c.chunks_s2c += 1
                    c.bytes_s2c += len(data)

    def _release(self) -> None:
        now = self.clock()
        if now < self._stalled_until:
            return
        for p in list(self._pipes):
            while p.queue and p.queue[0][0] <= now:
                data = p.queue[0][1]
                if not data:
                    p.queue.popleft()
                    try:
                        p.dst.shutdown(socket.SHUT_WR)
                    except OSError:
                        pass
                    if all(q.eof and not q.queue for q in self._pipes if q.src in (p.src, p.dst)):
                        self._drop_pair(p.src, reset=False)
                    break
                try:
                    n = p.dst.send(data)
                except (BlockingIOError, InterruptedError):
                    break
                except OSError:
                    self._drop_pair(p.src, reset=True)
                    return
                if n < len(data):
                    p.queue[0] = (p.queue[0][0], data[n:])
                    break
                p.queue.popleft()

    def _drop_pair(self, sock: socket.socket, reset: bool) -> None:
        for pair in list(self._pairs):
            if sock in pair:
                self._pairs.remove(pair)
                for s in pair:
                    if reset:
                        _abort(s)
                    else:
                        s.close()
                self._pipes = [p for p in self._pipes if p.src not in pair]
                if reset:
                    self.counters.reset += 1
                else:
                    self.counters.closed += 1


def _abort(s: socket.socket) -> None:
    """Close with SO_LINGER 0: the peer sees a reset, not an orderly close."""
    try:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
    except OSError:
        pass
    try:
        s.close()
    except OSError:
        pass


__all__ = ["ImpairingTcpProxy", "TcpProxyCounters"]
