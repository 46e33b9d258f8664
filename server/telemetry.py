"""The legacy ``.hpt`` telemetry recordings, and ``read`` for any recording.

Recordings are written in MCAP now (``recording``: what ``serve --record`` and ``status --dump``
write); ``read(path)`` reads either kind as ``(meta, rows)``, rows float64[n, NTEL] in the
``shm.TEL`` columns, and ``hapticproxy convert IN.hpt OUT.mcap`` turns an old file into MCAP.

``.hpt`` file format, little-endian:

- header: the line ``HPTEL1\\n``, then one JSON line (``fields``, ``rate_hz``, ``started_utc``,
  ``config``) ending in ``\\n``;
- blocks: ``b"BLK1"``, ``uint32 rows``, ``uint32 crc32`` of the payload, then ``rows * len(fields)``
  float64 values, row-major.

Each block is written whole, flushed and fsync'ed before the next one starts, so after a crash of
the loop process (or of the supervisor) a reader gets every complete block; a torn last block is
detected (short or wrong CRC) and ignored.
"""
from __future__ import annotations

import json
import os
import struct
import time
import zlib
from pathlib import Path

import numpy as np

from .shm import TEL_FIELDS, SharedState, flat_rows

MAGIC = b"HPTEL1\n"
BLOCK = b"BLK1"
_BH = struct.Struct("<4sII")


class TelemetryWriter:
    """Appends blocks of rows to a recording; ``drain(shared)`` copies what the loop wrote since."""

    def __init__(self, path: str | Path, *, rate_hz: float, config: dict | None = None, flush_rows: int = 512,
                 fields=TEL_FIELDS) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.fields = tuple(fields)
        self.flush_rows = int(flush_rows)
        self._f = open(self.path, "wb")
        meta = {"fields": list(self.fields), "rate_hz": rate_hz,
                "started_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "config": config or {}}
        self._f.write(MAGIC + json.dumps(meta).encode() + b"\n")
        self._sync()
        self._pending: list[np.ndarray] = []
        self._pending_rows = 0
        self.rows_written = 0
        self.rows_lost = 0  # overwritten in the ring before the writer could copy them
        self.blocks = 0
        self._read = 0  # ring rows consumed (absolute count)

    def _sync(self) -> None:
        self._f.flush()
        os.fsync(self._f.fileno())

    def start_at(self, head: int) -> None:
        """Record from ring row ``head`` on (rows before it are not part of this recording)."""
        self._read = int(head)

    def drain(self, shared: SharedState) -> int:
        self._read, head, lost = shared.catch_up(self._read)
        self.rows_lost += lost
        n = head - self._read
        if n <= 0:
            return 0
        rows = shared.rows(self._read, head)  # complete rows only (the others: lost)
        self.rows_lost += n - len(rows)
        chunk = flat_rows(rows)
        self._read = head
        self.add(chunk)
        return n

    def add(self, rows: np.ndarray) -> None:
        self._pending.append(np.ascontiguousarray(rows, dtype="<f8"))
        self._pending_rows += len(rows)
        while self._pending_rows >= self.flush_rows:
            data = np.concatenate(self._pending)
            self._write_block(data[: self.flush_rows])
            rest = data[self.flush_rows:]
            self._pending = [rest] if len(rest) else []
            self._pending_rows = len(rest)

    def _write_block(self, data: np.ndarray) -> None:
        payload = np.ascontiguousarray(data, dtype="<f8").tobytes()
        self._f.write(_BH.pack(BLOCK, len(data), zlib.crc32(payload)) + payload)
        self._sync()
        self.rows_written += len(data)
        self.blocks += 1

    def flush(self) -> None:
        """Write what is pending as a (short) block."""
        if self._pending_rows:
            self._write_block(np.concatenate(self._pending))
            self._pending = []
            self._pending_rows = 0

    def close(self) -> None:
        if self._f.closed:
            return
        self.flush()
        self._f.close()


def read(path: str | Path) -> tuple[dict, np.ndarray]:
    """``(meta, rows)`` of a recording, MCAP or ``.hpt``: every complete chunk or block; a torn
    tail is ignored (``meta["torn_bytes"]``). An ``.hpt`` file's rows keep its own columns
    (``meta["fields"]``); an MCAP file's are ``shm.TEL_FIELDS``."""
    from . import recording

    if recording.is_mcap(path):
        return recording.read_rows(path)
    return read_hpt(path)


def read_hpt(path: str | Path) -> tuple[dict, np.ndarray]:
    """``(meta, rows)`` of an ``.hpt`` recording: every complete block; a torn tail is ignored."""
    data = Path(path).read_bytes()
    if not data.startswith(MAGIC):
        raise ValueError(f"{path}: not a hapticproxy telemetry file")
    nl = data.index(b"\n", len(MAGIC))
    meta = json.loads(data[len(MAGIC):nl])
    width = len(meta["fields"])
    off = nl + 1
    blocks = []
    while off + _BH.size <= len(data):
        magic, nrows, crc = _BH.unpack_from(data, off)
        size = nrows * width * 8
        start = off + _BH.size
        if magic != BLOCK or start + size > len(data):
            break
        payload = data[start:start + size]
        if zlib.crc32(payload) != crc:
            break
        blocks.append(np.frombuffer(payload, dtype="<f8").reshape(nrows, width))
        off = start + size
    rows = np.concatenate(blocks) if blocks else np.zeros((0, width))
    meta["blocks"] = len(blocks)
    meta["torn_bytes"] = len(data) - off
    return meta, rows
