"""The datagram transport interface shared by every backend (mem, udp, zenoh).

Modelled on python-can's ``BusABC``: one small object per endpoint that moves whole messages
(``bytes``) and nothing else. Encoding, sessions, sequence numbers and authentication live in the
layers above; every backend carries exactly the same message bytes.

Semantics (the contract ``tests/protocol/test_transport_contract.py`` checks for every backend):

- **Datagrams.** A payload sent is either received whole and byte-exact, or not at all. Payloads
  may be lost, duplicated or reordered (UDP does all three; the in-memory and Zenoh backends
  happen not to, but callers must not rely on that). Newest-wins and duplicate rejection are the
  session layer's job (sequence numbers), not the transport's.
- **Roles.** A ``"server"`` endpoint listens and may talk to many peers: :meth:`Transport.send`
  needs the ``peer`` a datagram came from. A ``"client"`` endpoint has exactly one peer (the
  server) and ``peer`` may be omitted.
- **Peer ids** are opaque hashables, stable for the life of the remote endpoint: UDP gives the
  ``(host, port)`` source address, mem an ``int`` client number, Zenoh the client's id string.
- **Never blocks.** :meth:`Transport.recv_into` returns ``(0, None)`` at once when nothing is
  waiting, so a 1-4 kHz haptic step can poll at its start. It copies into a caller-owned buffer,
  so an empty poll allocates nothing and a datagram costs no payload-sized allocation on mem and
  UDP (only the small result tuple, plus the source-address tuple on a UDP server); Zenoh
  necessarily creates a sample and a ``bytes`` copy of its payload per datagram.
- **Size limit.** ``max_packet_bytes`` is enforced on both sides: an oversize send is refused
  (returns ``False``) and an oversize arrival is discarded; both are counted, never raised, so a
  bad packet cannot stop a haptic loop.
- **Counters** are plain ``int`` attributes of :attr:`Transport.counters` (see
  :class:`TransportCounters`); nothing is dropped without a count.
- ``close()`` is idempotent; using a closed transport raises :class:`TransportClosedError`.
"""
from __future__ import annotations

import abc
from collections.abc import Hashable
from typing import Any

#: Default datagram size limit. A 32-contact ContactUpdate is about 1.3 kB, 64 contacts about
#: 2.6 kB; 8 KiB leaves room for future fields while staying far below the 65,507-byte UDP
#: ceiling (large datagrams fragment off loopback, and every lost fragment loses the datagram).
DEFAULT_MAX_PACKET_BYTES = 8192

#: Hard ceiling shared by all backends: the largest IPv4 UDP payload.
MAX_DATAGRAM_BYTES = 65507

#: Upper bound on datagrams read by one :meth:`Transport.drain` call, so a flood cannot stretch
#: a haptic step without limit; whatever is left is read on the next step.
DEFAULT_DRAIN_MAX_PACKETS = 256

ROLES = ("server", "client")

Peer = Hashable


class TransportError(Exception):
    """Base class of transport failures that are the caller's to handle (not per-packet)."""


class TransportClosedError(TransportError):
    """The transport was used after :meth:`Transport.close`."""


class TransportCounters:
    """Per-transport event counts, plain ints (cheap to bump on the hot path, easy to report).

    - ``sent`` / ``received``: datagrams handed to / taken from the backend successfully.
    - ``bytes_sent`` / ``bytes_received``: their payload bytes.
    - ``dropped_oversize_send``: sends refused because the payload exceeded ``max_packet_bytes``.
    - ``dropped_oversize_recv``: arrivals discarded because they exceeded ``max_packet_bytes``.
    - ``send_errors``: sends the backend failed (socket buffer full, peer gone, unknown peer,
      ICMP port-unreachable reported on a connected UDP socket, ...).
    - ``recv_errors``: errors reported by the backend while receiving (datagram not lost by us,
      e.g. an ICMP error surfaced on a UDP socket).
    - ``dropped_overflow``: datagrams the backend's own queue discarded because it was full
      (mem and Zenoh ring channels; for UDP the kernel drops silently and we cannot count).
    - ``dropped_empty``: zero-length arrivals discarded (only a foreign sender makes them).
    - ``superseded``: datagrams read by :meth:`Transport.drain_into` /
      :meth:`Transport.drain` (``newest_per_peer=True``) but not handed back because a later
      one from the same peer arrived in the same drain.
    """

    __slots__ = (
        "sent",
        "received",
        "bytes_sent",
        "bytes_received",
        "dropped_oversize_send",
        "dropped_oversize_recv",
        "send_errors",
        "recv_errors",
        "dropped_overflow",
        "dropped_empty",
        "superseded",
    )

    def __init__(self) -> None:
        for name in self.__slots__:
            setattr(self, name, 0)

    @property
    def dropped_oversize(self) -> int:
        """Oversize datagrams refused on send plus discarded on receive."""
        return self.dropped_oversize_send + self.dropped_oversize_recv

    def drop_arrival(self, n_bytes: int, limit: int) -> bool:
        """Whether an arrival of ``n_bytes`` is discarded, counted: longer than ``limit``
        (``dropped_oversize_recv``) or empty (``dropped_empty``). Every backend's receive rule."""
        if n_bytes > limit:
            self.dropped_oversize_recv += 1
            return True
        if n_bytes == 0:
            self.dropped_empty += 1
            return True
        return False

    def as_dict(self) -> dict[str, int]:
        return {name: getattr(self, name) for name in self.__slots__}

    def __repr__(self) -> str:
        inner = ", ".join(f"{k}={v}" for k, v in self.as_dict().items())
        return f"TransportCounters({inner})"


def check_max_packet_bytes(value: Any) -> int:
    try:
        n = int(value)
    except (TypeError, ValueError):
        raise ValueError(f"max_packet_bytes must be an integer, got {value!r}") from None
    if not 1 <= n <= MAX_DATAGRAM_BYTES:
        raise ValueError(f"max_packet_bytes must be in 1..{MAX_DATAGRAM_BYTES}, got {n}")
    return n


def check_role(role: Any) -> str:
    if role not in ROLES:
        raise ValueError(f"role must be 'server' or 'client', got {role!r}")
    return role


class Transport(abc.ABC):
    """One datagram endpoint. Subclasses implement ``_send``, ``_recv_into`` and ``_close``.

    Not thread-safe: one thread (the haptic loop, or the client's loop) owns an endpoint.
    """

    #: URL scheme of the backend ("mem", "udp", "zenoh").
    scheme: str = ""
    #: What the URL after ``scheme://`` holds: ``"host:port/name"`` (the name, the URL's path, is
    #: optional), ``"host:port"`` (no path) or ``"name"`` (no address: an in-process bus). The
    #: constructor takes those of ``host``, ``port``, ``name`` it declares, and ``role``.
    url_form: str = "host:port/name"

    def __init__(self, role: str, max_packet_bytes: int = DEFAULT_MAX_PACKET_BYTES) -> None:
        self.role = check_role(role)
        self.max_packet_bytes = check_max_packet_bytes(max_packet_bytes)
        self.counters = TransportCounters()
        self._closed = False
        # Scratch buffer for recv()/drain(): one allocation per transport, not per call.
        self._scratch = bytearray(self.max_packet_bytes)
        self._scratch_view = memoryview(self._scratch)

    # ------------------------------------------------------------------ public API

    @property
    def closed(self) -> bool:
        return self._closed

    @property
    def default_peer(self) -> Peer | None:
        """The one peer of a client endpoint (``None`` for servers)."""
        return None

    def send(self, payload: bytes | bytearray | memoryview, peer: Peer | None = None) -> bool:
        """Send one datagram; return ``True`` if the backend accepted it.

        ``peer`` is required for servers (the id a received datagram came with) and optional for
        clients (it must then be the server's id, :attr:`default_peer`). Returns ``False`` (and
        counts it) for an oversize payload or a backend failure; a send that returned ``True``
        may still be lost in the network. Never blocks.
        """
        if self._closed:
            raise TransportClosedError(f"{self.scheme} transport is closed")
        n = len(payload)
        if n == 0:
            raise ValueError("payload must not be empty (nbytes == 0 means 'nothing waiting')")
        if n > self.max_packet_bytes:
            self.counters.dropped_oversize_send += 1
            return False
        if peer is None:
            if self.role == "server":
                raise ValueError("peer is required when sending from a server transport")
        if self._send(payload, peer):
            self.counters.sent += 1
            self.counters.bytes_sent += n
            return True
        self.counters.send_errors += 1
        return False

    def recv_into(self, buffer: bytearray | memoryview) -> tuple[int, Peer | None]:
        """Copy the next waiting datagram into ``buffer``; return ``(nbytes, peer)``.

        Returns ``(0, None)`` immediately when nothing is waiting; ``nbytes == 0`` means exactly
        that, because empty datagrams are refused on send and discarded (counted in
        ``dropped_empty``) on arrival. ``buffer`` must hold at least ``max_packet_bytes``.
        Oversize arrivals are discarded, counted, and the next datagram is tried (a backend may
        bound how many it discards in one call, UDP at 64, and then return ``(0, None)``: the
        next call goes on, so a flood of junk cannot hold a haptic step).
        """
        if self._closed:
            raise TransportClosedError(f"{self.scheme} transport is closed")
        if len(buffer) < self.max_packet_bytes:
            raise ValueError(
                f"buffer must hold max_packet_bytes={self.max_packet_bytes} bytes, has {len(buffer)}"
            )
        nbytes, peer = self._recv_into(buffer)
        if peer is not None:
            self.counters.received += 1
            self.counters.bytes_received += nbytes
        return nbytes, peer

    def recv(self) -> tuple[bytes, Peer] | None:
        """Convenience: the next waiting datagram as ``(bytes, peer)``, or ``None``. Allocates."""
        nbytes, peer = self.recv_into(self._scratch)
        if peer is None:
            return None
        return bytes(self._scratch[:nbytes]), peer

    def drain_into(
        self, buffer: bytearray | memoryview, max_packets: int = DEFAULT_DRAIN_MAX_PACKETS
    ) -> tuple[int, Peer | None, int]:
        """Read everything waiting (up to ``max_packets``) and keep only the last arrival.

        Returns ``(nbytes, peer, count)``: the newest datagram in ``buffer`` and how many were
        read (``count - 1`` were superseded and are counted in ``counters.superseded``).
        ``(0, None, 0)`` if nothing was waiting. Copies payloads without creating ``bytes``
        objects, but *arrival* order is not
        send order on UDP and it ignores which peer sent what: use it on a client (one peer)
        where the session layer re-checks the sequence number; servers with several peers want
        :meth:`drain` with ``newest_per_peer=True``.
        """
        if max_packets < 1:
            raise ValueError(f"max_packets must be >= 1, got {max_packets}")
        # Receive into our scratch buffer, not the caller's: a backend may write an oversize
        # datagram into the buffer before discarding it, which would clobber the newest so far.
        scratch = self._scratch
        scratch_view = self._scratch_view
        count = 0
        nbytes, peer = 0, None
        while count < max_packets:
            n, p = self.recv_into(scratch)
            if p is None:
                break
            count += 1
            nbytes, peer = n, p
            buffer[:n] = scratch_view[:n]  # a view slice: one payload copy, no bytes object
        if count > 1:
            self.counters.superseded += count - 1
        return nbytes, peer, count

    def drain(
        self, newest_per_peer: bool = False, max_packets: int = DEFAULT_DRAIN_MAX_PACKETS
    ) -> list[tuple[bytes, Peer]]:
        """Read everything waiting (up to ``max_packets``) as a list of ``(bytes, peer)``.

        ``newest_per_peer=False``: all of them, in arrival order (let the session layer pick by
        sequence number, the robust choice when UDP reorders). ``True``: only the last arrival
        from each peer, ordered by that arrival; the rest are counted in
        ``counters.superseded``. Allocates; meant for the start of a step, not an inner loop.
        """
        if max_packets < 1:
            raise ValueError(f"max_packets must be >= 1, got {max_packets}")
        out: list[tuple[bytes, Peer]] = []
        for _ in range(max_packets):
            item = self.recv()
            if item is None:
                break
            out.append(item)
        if newest_per_peer and len(out) > 1:
            last: dict[Peer, tuple[bytes, Peer]] = {}
            for item in out:
                last.pop(item[1], None)  # re-insert so dict order follows the latest arrival
                last[item[1]] = item
            self.counters.superseded += len(out) - len(last)
            out = list(last.values())
        return out

    def close(self) -> None:
        """Release the endpoint. Idempotent."""
        if self._closed:
            return
        self._closed = True
        self._close()

    def __enter__(self) -> "Transport":
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    def __del__(self) -> None:  # pragma: no cover - best effort, not the documented way
        try:
            if not self._closed:
                self.close()
        except Exception:
            pass

    def __repr__(self) -> str:
        state = "closed" if self._closed else "open"
        return f"<{type(self).__name__} {self.role} {self.describe()} {state}>"

    @property
    def url(self) -> str:
        """A URL reaching the server side of this link (a server's own, a client's server's)."""
        raise NotImplementedError

    def describe(self) -> str:
        """A short human-readable address, for logs and reports."""
        return ""

    # ------------------------------------------------------------------ backend hooks

    @abc.abstractmethod
    def _send(self, payload: bytes | bytearray | memoryview, peer: Peer | None) -> bool:
        """Hand one datagram (size already checked) to the backend; ``False`` on failure."""

    @abc.abstractmethod
    def _recv_into(self, buffer: bytearray | memoryview) -> tuple[int, Peer | None]:
        """Next datagram within ``max_packet_bytes`` into ``buffer`` or ``(0, None)``.

        Must discard (and count in ``dropped_oversize_recv`` / ``dropped_empty``) oversize and
        empty arrivals itself and keep going, and must never block.
        """

    @abc.abstractmethod
    def _close(self) -> None:
        """Release backend resources (called once)."""
