"""``hapticproxy devices [--json]``: the haptic devices connected here (driver, model, serial, the
``[device]`` lines that pick each), and the vendor drivers installed that find nothing."""
from __future__ import annotations

import argparse
import sys

from ..protocol.jsonout import print_json
from ..protocol.logs import doc_summary


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="hapticproxy devices", description=doc_summary(__doc__).split(": ", 1)[1])
    p.add_argument("--json", action="store_true", help="print a JSON list of rows")
    p.add_argument("--touch-name", action="append", default=None, metavar="NAME",
                   help="an OpenHaptics device name to look for (repeatable; default: \"Default Device\")")
    p.add_argument("--service", default="ws://127.0.0.1:10001", help="the Haply Inverse Service's URL to ask")
    args = p.parse_args(argv)
    from ..server.devices.detect import detect

    rows = detect(touch_names=tuple(args.touch_name or ("Default Device",)), service_url=args.service)
    if args.json:
        print_json(rows, sort_keys=True)
        return 0
    lines = []
    for r in rows:
        what = " ".join(str(r[k]) for k in ("model",) if r.get(k))
        ids = ", ".join(f"{k} {r[k]}" for k in ("serial", "port", "name", "via") if r.get(k))
        extra = r.get("why") or r.get("fix") or (f"[device] {r['config']}" if r.get("config") else "")
        lines.append(f"{r['driver']:<15} {r['status']:<30} {what:<10} {ids}" + (f"  ({extra})" if extra else ""))
    sys.stdout.write("\n".join(lines) + "\n")
    return 0
