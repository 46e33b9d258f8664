"""In-memory transport (``mem://NAME``): deterministic datagrams within one process, for tests.

A server endpoint registers ``NAME`` in a process-wide table; client endpoints opened on the same
``NAME`` attach to it. Nothing is ever lost, duplicated or reordered except by queue overflow:
each endpoint's inbox holds at most ``queue_capacity`` datagrams and, like a ring channel, an
arrival into a full inbox evicts the *oldest* waiting datagram (counted in the receiver's
``counters.dropped_overflow``), because for newest-wins traffic the newest is the one to keep.

Peer ids: the server sees each client as an ``int`` (1, 2, ... in attach order, never reused for a
name while its server lives); a client's only peer is the string ``"mem://NAME"``.

Deliveries copy the payload (``bytes(payload)``), so a sender may reuse its buffer at once, as
with a socket. Thread-safe enough for a server and clients on different threads (``deque`` append
and popleft are atomic); each endpoint itself is still owned by one thread.
"""
from __future__ import annotations

import itertools
import threading
from collections import deque

from .base import DEFAULT_MAX_PACKET_BYTES, Peer, Transport, TransportError

DEFAULT_QUEUE_CAPACITY = 1024

_registry: dict[str, "MemTransport"] = {}
_registry_lock = threading.Lock()
_auto_names = itertools.count(1)


def _check_name(name: str) -> str:
    if not isinstance(name, str) or not name or "/" in name or "?" in name:
        raise ValueError(f"mem transport name must be a non-empty string without '/' or '?', got {name!r}")
    return name


class MemTransport(Transport):
    """One endpoint of an in-process datagram bus named ``name``.

    Args:
        name: bus name (``mem://NAME``); a server must be opened before its clients.
        role: ``"server"`` (registers the name; raises ``TransportError`` if already taken) or
            ``"client"`` (attaches; raises ``TransportError`` if no server has the name).
        max_packet_bytes: datagram size limit enforced on send and receive.
        queue_capacity: datagrams this endpoint's inbox holds before evicting the oldest.
    """

    scheme = "mem"
    url_form = "name"

    def __init__(
        self,
        name: str,
        role: str = "server",
        max_packet_bytes: int = DEFAULT_MAX_PACKET_BYTES,
        queue_capacity: int = DEFAULT_QUEUE_CAPACITY,
    ) -> None:
        super().__init__(role, max_packet_bytes)
        self.name = _check_name(name)
        try:
            capacity = int(queue_capacity)
        except (TypeError, ValueError):
            raise ValueError(f"queue_capacity must be an integer, got {queue_capacity!r}") from None
        if capacity < 1:
            raise ValueError(f"queue_capacity must be >= 1, got {capacity}")
        self.queue_capacity = capacity
        self._inbox: deque[tuple[bytes, Peer]] = deque()
        self._server: MemTransport | None = None
        self._clients: dict[int, MemTransport] = {}
        self._client_ids = itertools.count(1)
        self._client_id = 0
        self._server_peer = f"mem://{self.name}"
        with _registry_lock:
            if role == "server":
                if self.name in _registry:
                    self._closed = True
                    raise TransportError(f"mem://{self.name} already has a server")
                _registry[self.name] = self
            else:
                server = _registry.get(self.name)
                if server is None:
                    self._closed = True
                    raise TransportError(f"no mem server named {self.name!r} (open the server first)")
                self._server = server
                self._client_id = next(server._client_ids)
                server._clients[self._client_id] = self

    @classmethod
    def pair(cls, name: str | None = None, **kwargs: object) -> tuple["MemTransport", "MemTransport"]:
        """A connected ``(server, client)`` pair on ``name`` (a fresh unique name if ``None``)."""
        if name is None:
            name = f"pair-{next(_auto_names)}"
        server = cls(name, "server", **kwargs)  # type: ignore[arg-type]
        try:
            client = cls(name, "client", **kwargs)  # type: ignore[arg-type]
        except BaseException:
            server.close()
            raise
        return server, client

    @property
    def default_peer(self) -> Peer | None:
        return self._server_peer if self.role == "client" else None

    @property
    def url(self) -> str:
        """``mem://NAME``: what a client opens to reach this bus's server."""
        return f"{self.scheme}://{self.name}"

    @property
    def client_id(self) -> int:
        """This client's peer id as the server sees it (0 for a server)."""
        return self._client_id

    def pending(self) -> int:
        """Datagrams waiting in this endpoint's inbox (tests use it to assert counts)."""
        return len(self._inbox)

    def describe(self) -> str:
        return f"mem://{self.name}" + (f"#{self._client_id}" if self.role == "client" else "")

    def _deliver(self, payload: bytes, peer: Peer) -> None:
        inbox = self._inbox
        if len(inbox) >= self.queue_capacity:
            inbox.popleft()
            self.counters.dropped_overflow += 1
        inbox.append((payload, peer))

    def _send(self, payload: bytes | bytearray | memoryview, peer: Peer | None) -> bool:
        if self.role == "client":
            if peer is not None and peer != self._server_peer:
                return False
            server = self._server
            if server is None or server._closed:
                return False
            server._deliver(bytes(payload), self._client_id)
            return True
        target = self._clients.get(peer)  # type: ignore[arg-type]
        if target is None or target._closed:
            return False
        target._deliver(bytes(payload), self._server_peer)
        return True

    def _recv_into(self, buffer: bytearray | memoryview) -> tuple[int, Peer | None]:
        inbox = self._inbox
        limit = self.max_packet_bytes
        while inbox:
            payload, peer = inbox.popleft()
            n = len(payload)
            if self.counters.drop_arrival(n, limit):
                continue
            buffer[:n] = payload
            return n, peer
        return 0, None

    def _close(self) -> None:
        self._inbox.clear()
        with _registry_lock:
            if self.role == "server":
                if _registry.get(self.name) is self:
                    del _registry[self.name]
                for client in self._clients.values():
                    client._server = None
                self._clients.clear()
            elif self._server is not None:
                self._server._clients.pop(self._client_id, None)
                self._server = None
