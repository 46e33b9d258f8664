"""UDP transport (``udp://HOST:PORT``): the server listens, the environment client connects.

- Server: binds ``HOST:PORT`` (``PORT`` 0 lets the OS pick a free port; read the result from
  :attr:`UdpTransport.local_address` or :attr:`UdpTransport.url`). Peer ids are the ``(host,
  port)`` source addresses of received datagrams, exactly as ``recvfrom`` reports them, and are
  what :meth:`~hapticproxy.protocol.transport.base.Transport.send` takes to reply.
- Client: ``connect()``s its socket to ``HOST:PORT`` (the kernel then filters out datagrams from
  any other source) and binds an ephemeral local port on the matching interface. Its one peer is
  the server address.
- Both sockets are non-blocking: a receive with nothing waiting returns at once, a send into a
  full socket buffer fails (counted in ``send_errors``) instead of stalling a haptic step.
- Oversize detection uses ``MSG_TRUNC`` (Linux): the kernel reports the datagram's real length
  even though it copies at most ``max_packet_bytes``, so a truncated datagram is never mistaken
  for a whole one. Without ``MSG_TRUNC`` (non-Linux) we read into a buffer one byte larger than
  the limit, which detects the same thing.
- ``rcvbuf_bytes`` / ``sndbuf_bytes`` request ``SO_RCVBUF`` / ``SO_SNDBUF``; the kernel caps the
  request (``net.core.rmem_max``) and Linux reports double the granted value. The granted values
  are exposed as :attr:`UdpTransport.rcvbuf_bytes_granted` / ``sndbuf_bytes_granted`` so a
  deployment can check them. A receive buffer only needs to bridge one haptic step plus a hiccup;
  newest-wins traffic gains nothing from a deep queue of stale datagrams.
- A connected client socket surfaces ICMP port-unreachable (server not running) as
  ``ConnectionRefusedError`` on the next call; it is counted (``send_errors`` or
  ``recv_errors``), never raised.
"""
from __future__ import annotations

import select
import socket
import sys

from .base import DEFAULT_MAX_PACKET_BYTES, Peer, Transport

#: Requested socket buffer sizes: about 190 full 1.3 kB contact updates, far more than a 1 ms
#: step can accumulate, small enough that the kernel default maximum usually grants it.
DEFAULT_RCVBUF_BYTES = 256 * 1024
DEFAULT_SNDBUF_BYTES = 256 * 1024

_MSG_TRUNC = getattr(socket, "MSG_TRUNC", 0) if sys.platform.startswith("linux") else 0


def _family_for(host: str) -> socket.AddressFamily:
    return socket.AF_INET6 if ":" in host else socket.AF_INET


def _check_port(port: object) -> int:
    try:
        p = int(port)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise ValueError(f"port must be an integer, got {port!r}") from None
    if not 0 <= p <= 65535:
        raise ValueError(f"port must be in 0..65535, got {p}")
    return p


def _check_buf(name: str, value: object) -> int | None:
    if value is None:
        return None
    try:
        n = int(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be an integer, got {value!r}") from None
    if n < 0:
        raise ValueError(f"{name} must be >= 0 (0 keeps the OS default), got {n}")
    return n or None


#: Empty or oversize datagrams one ``recv_into`` call discards at most before returning.
_MAX_DISCARDS = 64

class UdpTransport(Transport):
    """A non-blocking UDP endpoint.

    Args:
        host: server: the address to bind (tests and the embedded default use ``127.0.0.1``);
            client: the server's address.
        port: server: the port to bind (0 = any free port); client: the server's port (>= 1).
        role: ``"server"`` or ``"client"``.
        max_packet_bytes: datagram size limit enforced on send and receive.
        rcvbuf_bytes, sndbuf_bytes: requested socket buffer sizes (``None``/0 = OS default).
    """

    scheme = "udp"
    url_form = "host:port"

    def __init__(
        self,
        host: str,
        port: int,
        role: str = "server",
        max_packet_bytes: int = DEFAULT_MAX_PACKET_BYTES,
        rcvbuf_bytes: int | None = DEFAULT_RCVBUF_BYTES,
        sndbuf_bytes: int | None = DEFAULT_SNDBUF_BYTES,
    ) -> None:
        super().__init__(role, max_packet_bytes)
        self._closed = True  # until the socket exists, so __del__/close do nothing
        if not isinstance(host, str) or not host:
            raise ValueError(f"host must be a non-empty string, got {host!r}")
        port = _check_port(port)
        if role == "client" and port == 0:
            raise ValueError("port must be >= 1 for a UDP client (the server's port)")
        rcvbuf = _check_buf("rcvbuf_bytes", rcvbuf_bytes)
        sndbuf = _check_buf("sndbuf_bytes", sndbuf_bytes)
        sock = socket.socket(_family_for(host), socket.SOCK_DGRAM)
        try:
            if rcvbuf:
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
            if sndbuf:
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, sndbuf)
            if role == "server":
                sock.bind((host, port))
            else:
                sock.connect((host, port))
            sock.setblocking(False)
        except BaseException:
            sock.close()
            raise
        self._sock = sock
        # Most haptic steps find nothing waiting: poll(0) says so without the exception a
        # non-blocking recv raises (a few us per step on a cold cache); where there is no poll,
        # the recv alone decides.
        self._ready = None
        if hasattr(select, "poll"):
            p = select.poll()
            p.register(sock.fileno(), select.POLLIN)
            self._ready = p.poll
        self._closed = False
        self._peer: Peer | None = sock.getpeername() if role == "client" else None
        self.local_address: tuple = sock.getsockname()
        self.rcvbuf_bytes_granted = sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)
        self.sndbuf_bytes_granted = sock.getsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF)
        # Read size: with MSG_TRUNC the kernel tells the true length; without it one spare byte
        # distinguishes "exactly max_packet_bytes" from "longer, truncated".
        self._read_bytes = self.max_packet_bytes if _MSG_TRUNC else self.max_packet_bytes + 1
        if not _MSG_TRUNC:
            self._scratch = bytearray(self._read_bytes)
            self._scratch_view = memoryview(self._scratch)

    # ------------------------------------------------------------------ properties

    @property
    def default_peer(self) -> Peer | None:
        return self._peer

    @property
    def url(self) -> str:
        """``udp://HOST:PORT`` of the server side: a server's bound address, a client's server."""
        addr = self._peer if self.role == "client" else self.local_address
        host, port = addr[0], addr[1]  # type: ignore[index]
        if ":" in host:
            host = f"[{host}]"
        return f"udp://{host}:{port}"

    def fileno(self) -> int:
        """The socket's descriptor, for callers that want to ``select``/``poll`` on it."""
        return self._sock.fileno()

    def describe(self) -> str:
        if self.role == "client" and self._peer is not None:
            return f"udp {self.local_address[0]}:{self.local_address[1]} -> {self._peer[0]}:{self._peer[1]}"
        return self.url

    # ------------------------------------------------------------------ backend hooks

    def _send(self, payload: bytes | bytearray | memoryview, peer: Peer | None) -> bool:
        try:
            if self.role == "client":
                if peer is not None and peer != self._peer:
                    raise ValueError(f"a UDP client can only send to its server {self._peer!r}, not {peer!r}")
                self._sock.send(payload)
            else:
                self._sock.sendto(payload, peer)  # type: ignore[arg-type]
        except OSError:
            # EAGAIN (buffer full), ECONNREFUSED (ICMP from a dead server), EHOSTUNREACH, ...:
            # the datagram is lost; the caller sees False and the send_errors counter.
            return False
        except TypeError:
            raise ValueError(f"peer must be a (host, port) address as received, got {peer!r}") from None
        return True

    def _recv_into(self, buffer: bytearray | memoryview) -> tuple[int, Peer | None]:
        ready = self._ready
        if ready is not None and not ready(0):
            return 0, None
        sock = self._sock
        limit = self.max_packet_bytes
        if not _MSG_TRUNC and len(buffer) < self._read_bytes:
            target = self._scratch  # one spare byte needed; copy out below
        else:
            target = buffer
        read_bytes = self._read_bytes
        counters = self.counters
        # Bounded: a flood of empty or oversize datagrams must not hold one call (and with it a
        # haptic step) without limit; after _MAX_DISCARDS of them this call reports nothing and
        # the next call goes on.
        for _ in range(_MAX_DISCARDS):
            try:
                if self.role == "client":
                    n = sock.recv_into(target, read_bytes, _MSG_TRUNC)
                    peer = self._peer
                else:
                    n, peer = sock.recvfrom_into(target, read_bytes, _MSG_TRUNC)
            except (BlockingIOError, InterruptedError):
                return 0, None
            except ConnectionRefusedError:
                # An earlier send drew ICMP port-unreachable; the error is consumed, try again.
                counters.recv_errors += 1
                continue
            except OSError:
                # Transient or per-datagram errors alike: report nothing this call rather than spin.
                counters.recv_errors += 1
                return 0, None
            if counters.drop_arrival(n, limit):
                continue
            if target is not buffer:
                buffer[:n] = target[:n]
            return n, peer
        return 0, None

    def _close(self) -> None:
        self._sock.close()
