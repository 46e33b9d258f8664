"""``hapticproxy status``: ask a running server for its live figures (or to re-arm, stop, dump).

The supervisor answers JSON requests on its status address (UDP, default 127.0.0.1:9871):
``{"cmd": "status"}`` (default), ``"rearm"``, ``"stop"``, ``"reset_stats"``, ``{"cmd": "dump",
"path": FILE}`` (write the telemetry ring to FILE).
"""
from __future__ import annotations

import argparse
import json
import socket
import sys

DEFAULT_ADDRESS = "127.0.0.1:9871"


def query(address: str = DEFAULT_ADDRESS, request: dict | None = None, timeout_s: float = 1.0) -> dict:
    """Send one request; return the reply. Raises ``TimeoutError`` when nothing answers."""
    host, _, port = address.rpartition(":")
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.settimeout(timeout_s)
        s.sendto(json.dumps(request or {"cmd": "status"}).encode(), (host, int(port)))
        try:
            data, _ = s.recvfrom(65536)
        except (socket.timeout, ConnectionRefusedError):
            raise TimeoutError(f"no server answering on {address}") from None
    return json.loads(data)


def _fault_name(code) -> str:
    from .lifecycle import FAULT_TEXT, Fault

    try:
        f = Fault(int(code))
    except ValueError:
        return str(code)
    return "none" if f == Fault.NONE else f"{f.name.lower()}: {FAULT_TEXT[f]}"


def _device_fault_name(code) -> str:
    from .devices.base import DEV_FAULT_NAMES

    return DEV_FAULT_NAMES.get(int(code), str(code))


def format_status(s: dict) -> str:
    lat = s.get("lateness_us", {})
    comp = s.get("compute_us", {})
    period_us = s.get("period_ns", 0) / 1000 or float("nan")
    rate = 1e6 / period_us if period_us == period_us else float("nan")
    lines = [
        f"state        {s.get('loop_state')}  (fault: {_fault_name(s.get('fault', 0))}, device fault: "
        f"{_device_fault_name(s.get('device_fault', 0))}; stall trips {int(s.get('stall_trips', 0))}, "
        f"recovered {int(s.get('stall_recoveries', 0))})",
        f"rate         {rate:.0f} Hz, {int(s.get('steps', 0))} steps, overruns {int(s.get('overruns', 0))}, "
        f"missed deadlines {int(s.get('missed_deadlines', 0))}",
        f"lateness us  p50 {lat.get('p50')}  p99 {lat.get('p99')}  p99.9 {lat.get('p999')}  "
        f"max {s.get('lateness_max_us', 0):.1f}",
        f"compute us   p50 {comp.get('p50')}  p99 {comp.get('p99')}  max {s.get('compute_max_us', 0):.1f}",
        f"rt sched     {'yes' if s.get('rt_scheduling') else 'no'}  (spin {s.get('spin_ns', 0) / 1000:.0f} us)",
        f"session      {int(s.get('session_id', 0))}  updates {int(s.get('updates', 0))}  acks {int(s.get('acks_sent', 0))}  "
        f"env rate {s.get('env_rate_hz', 0):.1f} Hz  silence {s.get('env_silence_ms', -1):.0f} ms",
        f"contacts     {int(s.get('contacts', 0))}  dropped packets {int(s.get('dropped_packets', 0))}  "
        f"stale/duplicate {int(s.get('stale_or_duplicate', 0))}",
        f"watchdog     {('ok', 'environment silent: fading', 'session ended: fading')[int(s.get('watchdog', 0))]}"
        f"  gain {s.get('gain', 0):.3f}  saturated {int(s.get('saturated', 0))}  rate-limited {int(s.get('rate_limited', 0))}",
    ]
    for why in s.get("outside_stable_region") or ():
        lines.append(f"WARNING      outside the stable region (safety.allow_outside_stable_region): {why}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="hapticproxy status", description=__doc__.splitlines()[0])
    p.add_argument("--address", default=DEFAULT_ADDRESS, help="the server's status address HOST:PORT")
    p.add_argument("--json", action="store_true", help="print the raw JSON")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--rearm", action="store_true", help="clear a fault: forces ramp back in")
    g.add_argument("--stop", action="store_true", help="stop the server cleanly")
    g.add_argument("--reset-stats", action="store_true", help="reset the timing histograms")
    g.add_argument("--dump", metavar="FILE", help="write the telemetry ring to FILE")
    p.add_argument("--timeout", type=float, default=1.0)
    args = p.parse_args(argv)
    req = {"cmd": "status"}
    if args.rearm:
        req = {"cmd": "rearm"}
    elif args.stop:
        req = {"cmd": "stop"}
    elif args.reset_stats:
        req = {"cmd": "reset_stats"}
    elif args.dump:
        req = {"cmd": "dump", "path": args.dump}
    try:
        reply = query(args.address, req, args.timeout)
    except (TimeoutError, OSError, ValueError) as exc:
        print(f"hapticproxy status: {exc}", file=sys.stderr)
        return 1
    if "error" in reply:
        print(f"hapticproxy status: {reply['error']}", file=sys.stderr)
        return 1
    if args.json or req["cmd"] != "status":
        print(json.dumps(reply, indent=None if not args.json else 1, sort_keys=True))
    else:
        print(format_status(reply))
    return 0
