"""``hapticproxy convert IN OUT.mcap``: a legacy ``.hpt`` recording, or an MCAP recording that
lost its summary in a crash (PlotJuggler wants one), as a complete MCAP file."""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

from ..protocol.logs import doc_summary
from .recording import McapRecorder, _nan, is_mcap, read as read_recording
from .shm import TEL, TEL_DTYPE, TEL_FIELDS, flat_rows
from .telemetry import read_hpt


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="hapticproxy convert", description=doc_summary(__doc__))
    ap.add_argument("src", help="the recording to read (.hpt or .mcap)")
    ap.add_argument("dst", help="the MCAP file to write (must not exist; its directory must)")
    args = ap.parse_args(argv)
    if os.path.exists(args.dst):
        print(f"hapticproxy convert: {args.dst} exists", file=sys.stderr)
        return 1
    if os.path.abspath(args.src) == os.path.abspath(args.dst):
        print("hapticproxy convert: source and destination are the same file", file=sys.stderr)
        return 1
    try:
        out = convert(args.src, args.dst)
    except (OSError, ValueError) as exc:
        print(f"hapticproxy convert: {exc}", file=sys.stderr)
        return 1
    print(f"{args.dst}: {out['rows']} telemetry rows, {out['contacts']} contact updates, "
          f"{out['transitions']} transitions (dropped a torn tail of {out['torn_bytes_dropped']} bytes)")
    return 0


def convert(src: str | Path, dst: str | Path) -> dict:
    """An ``.hpt`` recording, or an MCAP one (e.g. torn: it gets a summary again), as a complete
    MCAP file at ``dst``; returns what was written."""
    src, dst = Path(src), Path(dst)
    if is_mcap(src):
        rec = read_recording(src)
        meta = dict(rec.meta)
        rate = float(meta.pop("rate_hz", 0.0) or 0.0)
        config = meta.pop("config", {}) or {}
        t0 = int(meta.pop("t0_epoch_ns", 0) or 0)
        for k in ("format", "started_utc"):
            meta.pop(k, None)
        w = McapRecorder(dst, rate_hz=rate, config=config, t0_epoch_ns=t0, flush_rows=max(1, len(rec.tel)),
                         meta=meta)
        for c in rec.contacts:
            hdr = np.zeros((), dtype=[("t_s", "f8"), ("env_time_s", "f8"), ("update", "i8"), ("count", "i8")])
            hdr["t_s"], hdr["env_time_s"] = c["t_s"], _nan(c["env_time_s"])
            hdr["update"], hdr["count"] = c["update"], c["count"]
            w.add_contacts(hdr, c["key"], c["position_m"], c["normal"], c["separation_m"])
        for tr in rec.transitions:
            w._ch["/transitions"].log(w._enc.encode(tr), w._log_ns(tr.t_s))
            w.transitions_written += 1
        w.add_rows(rec.tel)
        w.close()
        return {"rows": len(rec.tel), "contacts": len(rec.contacts), "transitions": len(rec.transitions),
                "torn_bytes_dropped": rec.torn_bytes}
    meta, rows = read_hpt(src)
    out = np.full(len(rows), np.nan, dtype=TEL_DTYPE)
    flat = flat_rows(out)
    cols = {name: i for i, name in enumerate(meta["fields"])}
    for name in TEL_FIELDS:
        if name in cols:
            flat[:, TEL[name]] = rows[:, cols[name]]
    t0 = 0
    try:
        t0 = int(time.mktime(time.strptime(meta.get("started_utc", ""), "%Y-%m-%dT%H:%M:%SZ")) - time.timezone) * 10**9
    except ValueError:
        pass
    w = McapRecorder(dst, rate_hz=float(meta.get("rate_hz") or 0.0), config=meta.get("config") or {}, t0_epoch_ns=t0,
                     flush_rows=max(1, len(rows)), meta={"converted_from": src.name})
    w.add_rows(flat)
    w.close()
    return {"rows": len(rows), "contacts": 0, "transitions": 0, "torn_bytes_dropped": meta.get("torn_bytes", 0)}
