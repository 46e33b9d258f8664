"""``hapticproxy convert IN OUT.mcap``: a legacy ``.hpt`` recording, or an MCAP recording that
lost its summary in a crash (PlotJuggler wants one), as a complete MCAP file."""
from __future__ import annotations

import argparse
import os
import sys


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="hapticproxy convert", description=__doc__.splitlines()[0])
    ap.add_argument("src", help="the recording to read (.hpt or .mcap)")
    ap.add_argument("dst", help="the MCAP file to write (must not exist; its directory must)")
    args = ap.parse_args(argv)
    from .recording import convert

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
