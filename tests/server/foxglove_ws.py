"""A minimal client of the Foxglove WebSocket protocol, offering both names of the subprotocol:
``foxglove.sdk.v1`` (the Foxglove SDK server accepts only this name since it renamed
``foxglove.websocket.v1``; the messages are the same) and ``foxglove.websocket.v1``,
on the standard library alone: the handshake, JSON control messages, subscriptions and binary
message data (opcode 1: subscription id u32, log time u64, payload). Tests use it as a viewer."""
from __future__ import annotations

import base64
import json
import os
import socket
import struct
import time

SUBPROTOCOLS = ("foxglove.sdk.v1", "foxglove.websocket.v1")


class FoxgloveClient:
    def __init__(self, host: str, port: int, timeout_s: float = 5.0) -> None:
        self.sock = socket.create_connection((host, port), timeout=timeout_s)
        key = base64.b64encode(os.urandom(16)).decode()
        self.sock.sendall((f"GET / HTTP/1.1\r\nHost: {host}:{port}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
                           f"Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n"
                           f"Sec-WebSocket-Protocol: {', '.join(SUBPROTOCOLS)}\r\n\r\n").encode())
        head = b""
        while b"\r\n\r\n" not in head:
            chunk = self.sock.recv(4096)
            if not chunk:
                raise ConnectionError("closed during the handshake")
            head += chunk
        head, self._buf = head.split(b"\r\n\r\n", 1)
        lines = head.decode("latin-1").split("\r\n")
        if " 101 " not in lines[0]:
            raise ConnectionError(f"handshake refused: {lines[0]}")
        self.headers = {k.strip().lower(): v.strip() for k, v in (ln.split(":", 1) for ln in lines[1:] if ":" in ln)}
        self.channels: dict[int, dict] = {}
        self.server_info: dict | None = None
        self.subs: dict[int, int] = {}  # subscription id -> channel id

    def _read(self, n: int) -> bytes:
        while len(self._buf) < n:
            chunk = self.sock.recv(65536)
            if not chunk:
                raise ConnectionError("closed")
            self._buf += chunk
        out, self._buf = self._buf[:n], self._buf[n:]
        return out

    def frame(self) -> tuple[int, bytes]:
        """The next whole message: (opcode, payload); answers pings."""
        data, op0 = b"", None
        while True:
            b0, b1 = self._read(2)
            op, fin = b0 & 0x0F, b0 & 0x80
            n = b1 & 0x7F
            if n == 126:
                n = struct.unpack(">H", self._read(2))[0]
            elif n == 127:
                n = struct.unpack(">Q", self._read(8))[0]
            mask = self._read(4) if b1 & 0x80 else None
            payload = self._read(n)
            if mask:
                payload = bytes(c ^ mask[i % 4] for i, c in enumerate(payload))
            if op == 9:
                self._send(10, payload)
                continue
            if op == 8:
                raise ConnectionError("server closed the connection")
            if op != 0:
                op0 = op
            data += payload
            if fin:
                return op0, data

    def _send(self, op: int, payload: bytes) -> None:
        mask = os.urandom(4)
        n = len(payload)
        head = bytes([0x80 | op])
        if n < 126:
            head += bytes([0x80 | n])
        elif n < 65536:
            head += bytes([0x80 | 126]) + struct.pack(">H", n)
        else:
            head += bytes([0x80 | 127]) + struct.pack(">Q", n)
        self.sock.sendall(head + mask + bytes(c ^ mask[i % 4] for i, c in enumerate(payload)))

    def send_json(self, obj: dict) -> None:
        self._send(1, json.dumps(obj).encode())

    def subscribe(self, topic: str, sub_id: int) -> int:
        ch = next(c for c in self.channels.values() if c["topic"] == topic)
        self.send_json({"op": "subscribe", "subscriptions": [{"id": sub_id, "channelId": ch["id"]}]})
        self.subs[sub_id] = ch["id"]
        return ch["id"]

    def poll(self, until, timeout_s: float = 10.0):
        """Read messages until ``until(kind, obj)`` is true (kind "json" with a dict, or "message"
        with (subscription id, log time ns, payload)); returns that object."""
        t_end = time.monotonic() + timeout_s
        while time.monotonic() < t_end:
            op, data = self.frame()
            if op == 1:
                msg = json.loads(data)
                if msg.get("op") == "serverInfo":
                    self.server_info = msg
                elif msg.get("op") == "advertise":
                    for c in msg["channels"]:
                        self.channels[c["id"]] = c
                if until("json", msg):
                    return msg
            elif op == 2 and data and data[0] == 1:
                sub, t_ns = struct.unpack_from("<IQ", data, 1)
                item = (sub, t_ns, data[13:])
                if until("message", item):
                    return item
        raise TimeoutError("nothing matched in time")

    def close(self) -> None:
        try:
            self._send(8, b"")
        except OSError:
            pass
        self.sock.close()
