"""``hapticproxy status``: ask a running server for its live figures (or to re-arm, stop, dump).

The supervisor answers JSON requests on its status address (UDP, default 127.0.0.1:9871):
``{"cmd": "status"}`` (default), ``"rearm"``, ``"stop"``, ``"reset_stats"``, ``{"cmd": "dump",
"path": FILE}`` (write the rings to the MCAP file FILE, an absolute path: it is resolved here,
on the caller's side; the server creates no directory). ``--watch``: a live terminal view.

With an HMAC key configured (``transport.hmac_key_file``; give the same config with
``--config`` or the key file with ``--key-file``) every request carries ``ts``, a ``nonce`` and
``mac`` = HMAC-SHA256 over the request's canonical JSON without ``mac``; the server refuses
unsigned, wrongly signed, stale (over ``AUTH_WINDOW_S``) or replayed requests. Replies are strict
JSON: integers as integers, a value not known as ``null``.
"""
from __future__ import annotations

import argparse
import hashlib
import hmac
import json
import os
import secrets
import socket
import sys
import time

from ..protocol.logs import doc_summary
from ..protocol.jsonout import print_json

DEFAULT_ADDRESS = "127.0.0.1:9871"
#: A signed request older (or newer) than this is refused; its nonce is remembered twice as long.
AUTH_WINDOW_S = 30.0


def canonical(req: dict) -> bytes:
    return json.dumps({k: v for k, v in req.items() if k != "mac"}, sort_keys=True, separators=(",", ":"),
                      allow_nan=False).encode()


def request_mac(key: bytes, req: dict) -> str:
    return hmac.new(key, canonical(req), hashlib.sha256).hexdigest()


def sign(req: dict, key: bytes | None) -> dict:
    if key is None:
        return req
    req = dict(req, ts=time.time(), nonce=secrets.token_hex(12))
    req["mac"] = request_mac(key, req)
    return req


def query(address: str = DEFAULT_ADDRESS, request: dict | None = None, timeout_s: float = 1.0,
          key: bytes | None = None) -> dict:
    """Send one request (signed with ``key`` when given); return the reply. Raises
    ``TimeoutError`` when nothing answers."""
    host, _, port = address.rpartition(":")
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.settimeout(timeout_s)
        s.sendto(json.dumps(sign(request or {"cmd": "status"}, key)).encode(), (host, int(port)))
        try:
            data, _ = s.recvfrom(65536)
        except (socket.timeout, ConnectionRefusedError):
            raise TimeoutError(f"no server answering on {address}") from None
    return json.loads(data)


def _fault_name(code) -> str:
    from .lifecycle import FAULT_TEXT, Fault

    try:
        f = Fault(int(code or 0))
    except ValueError:
        return str(code)
    return "none" if f == Fault.NONE else f"{f.name.lower()}: {FAULT_TEXT[f]}"


def _device_fault_name(code) -> str:
    from .devices.base import DEV_FAULT_NAMES

    return DEV_FAULT_NAMES.get(int(code or 0), str(code))


def _set(s: dict, key: str) -> bool:
    """A status field whose -1 means "none" holds a value (a status from before the field: none)."""
    v = s.get(key)
    return v is not None and v >= 0


def _f(v, fmt: str = ".1f", none: str = "-") -> str:
    return none if v is None else format(v, fmt)


def _what_the_hand_feels(s: dict) -> list[str]:
    """The device and the proxy (hand point, world, mm), the command against the caps, the
    contacts of the last update: what a person at the device feels."""
    lt = s.get("latest") or {}
    out = []
    dp, pp, cmd = lt.get("device_pose"), lt.get("proxy_pose"), lt.get("command")
    # three decimals: the micrometre, so two positions equal in --json print equal here
    mm = lambda p: " ".join(f"{a} {1e3 * (v or 0.0):+9.3f}" for a, v in zip("xyz", p[:3]))  # noqa: E731
    if dp and pp:
        out.append(f"device mm    {mm(dp)}    proxy mm {mm(pp)}")
    if cmd:
        f = " ".join(f"{a} {v or 0.0:+.3f}" for a, v in zip(("fx", "fy", "fz"), cmd[:3]))
        t = " ".join(f"{a} {v or 0.0:+.4f}" for a, v in zip(("tx", "ty", "tz"), cmd[3:6]))
        out.append(f"command      {f} N (cap {_f(s.get('force_cap_n'), 'g')})   {t} N m (cap "
                   f"{_f(s.get('torque_cap_n_m'), 'g')})")
    lu = s.get("last_update")
    if lu:
        out.append(f"last update  {lu.get('count', 0)} contacts, deepest penetration "
                   f"{1e3 * (lu.get('penetration_m') or 0.0):.3f} mm")
    return out


def _device_line(info: dict) -> str:
    """What the device is, from its DeviceInfo (model, serial, DOF, force, clock)."""
    from .devices.base import DeviceInfo

    try:
        names = {f for f in DeviceInfo.__dataclass_fields__}
        return DeviceInfo(**{k: (tuple(v) if isinstance(v, list) else v) for k, v in info.items() if k in names}).summary()
    except (TypeError, ValueError):
        return str(info.get("model", "?"))


def format_status(s: dict) -> str:
    lat = s.get("lateness_us") or {}
    comp = s.get("compute_us") or {}
    rate = s.get("rate_hz") or 0
    wd = s.get("watchdog") or 0
    silence = s.get("env_silence_ms")
    lines = [
        f"server       {s.get('url', '?')}  {s.get('tool_kind', '?')} tool on a {s.get('device_kind', '?')} device  "
        f"(config {s.get('config_source', '?')})",
        *([f"device       {_device_line(s['device_info'])}"] if s.get("device_info") else []),
        f"state        {s.get('loop_state')}  (fault: {_fault_name(s.get('fault', 0))}, device fault: "
        f"{_device_fault_name(s.get('device_fault', 0))}; stall trips {s.get('stall_trips', 0)}, "
        f"recovered {s.get('stall_recoveries', 0)})",
        f"rate         {rate:.0f} Hz, {s.get('steps', 0)} steps, overruns {s.get('overruns', 0)}, "
        f"missed deadlines {s.get('missed_deadlines', 0)}"
        + (f", held ticks {s.get('servo_held', 0)} (the tick's lock was Python's)" if s.get("servo_ticks") else ""),
        f"lateness us  p50 {lat.get('p50')}  p99 {lat.get('p99')}  p99.9 {lat.get('p999')}  "
        f"max {_f(s.get('lateness_max_us'))}",
        f"compute us   p50 {comp.get('p50')}  p99 {comp.get('p99')}  max {_f(s.get('compute_max_us'))}",
        f"rt sched     {'yes' if s.get('rt_scheduling') else 'no'}  (spin {(s.get('spin_ns') or 0) / 1000:.0f} us; "
        + (f"idle CPUs wake within {s['cpu_latency_us']:.0f} us" if _set(s, "cpu_latency_us")
           else "idle CPU wake-up latency not held")
        + (f"; clock thread on CPU {s['clock_cpu']:.0f})" if _set(s, "clock_cpu") else ")"),
        f"session      {s.get('session_id', 0)}  updates {s.get('updates', 0)}  acks {s.get('acks_sent', 0)}  "
        f"env rate {_f(s.get('env_rate_hz'))} Hz  silence "
        f"{'no update yet' if silence is None else f'{silence:.0f} ms'}",
        f"contacts     {s.get('contacts', 0)}  dropped packets {s.get('dropped_packets', 0)}  "
        f"stale/duplicate {s.get('stale_or_duplicate', 0)}",
        f"refused      out of the scene's bounds {s.get('refused_out_of_bounds', 0)}  unusable contacts "
        f"{s.get('refused_unusable', 0)}  sequence jumps {s.get('refused_seq_jump', 0)}  reversed normals "
        f"{s.get('flips_refused', 0)} (taken {s.get('flips_taken', 0)})  (renumbered keys continued "
        f"{s.get('rekeyed', 0)})  proxy diverged {s.get('diverged', 0)}",
        f"fidelity     recovering {s.get('recovering', 0)} contacts, held back {s.get('held', 0)} (work on the hand "
        f"{1e3 * (s.get('recovery_energy_j') or 0.0):.1f} mJ)  engine told epsilon "
        f"{1e3 * (s.get('advised_epsilon_m') or 0.0):.1f} mm, lead {1e3 * (s.get('advised_lead_s') or 0.0):.1f} ms",
        f"watchdog     {('ok', 'environment silent: fading', 'session ended: fading')[wd] if 0 <= wd < 3 else wd}"
        f"  gain {_f(s.get('gain'), '.3f')}  saturated {s.get('saturated', 0)}  rate-limited {s.get('rate_limited', 0)}",
        f"hand port    energy given to the hand {1e3 * (s.get('energy_hand_j') or 0.0):+.2f} mJ since start"
        f" (negative: taken from it); tank {1e3 * (s.get('tank_j') or 0.0):.2f} mJ (lowest "
        f"{1e3 * (s.get('tank_low_j') or 0.0):.2f}), limited {s.get('passivity_limited', 0)} steps",
    ]
    for why in s.get("outside_stable_region") or ():
        lines.append(f"WARNING      outside the stable region (safety.allow_outside_stable_region): {why}")
    for what in s.get("lowered") or ():
        lines.append(f"lowered      {what}")
    lines[2:2] = _what_the_hand_feels(s)
    tr = s.get("last_transition")
    if tr:
        lines.append(f"last change  {tr.get('from')} -> {tr.get('to')}: {tr.get('text')}")
    if s.get("telemetry_file"):
        lines.append(f"recording    {s['telemetry_file']} ({s.get('telemetry_rows_written', 0)} rows on disk)")
    if s.get("live"):
        lines.append(f"live view    {s['live']}")
    return "\n".join(lines)


def format_reply(req: dict, reply: dict, address: str) -> str:
    """One line saying what a request other than ``status`` did (``--json``: the reply itself)."""
    cmd = req["cmd"]
    if cmd == "rearm":
        return (f"re-arm requested on {address}: a latched fault clears and the force ramps back in "
                f"(`hapticproxy status` shows the state)")
    if cmd == "stop":
        return f"stop requested on {address}: forces ramp down, then the server exits"
    if cmd == "reset_stats":
        return f"timing statistics reset on {address}"
    if cmd == "dump":
        return f"wrote {reply.get('rows', 0)} telemetry rows to {reply.get('path', req.get('path'))}"
    return str(reply)


def load_key(config: str | None, key_file: str | None) -> tuple[bytes | None, str | None]:
    """(HMAC key, status address from the config) for the command line's options; the
    environment (``HAPTICPROXY_HMAC_KEY_FILE`` / ``HAPTICPROXY_HMAC_KEY``) when neither names one."""
    from ..protocol.session import load_hmac_key

    address = None
    if config:
        from . import config as cfgmod

        settings = cfgmod.load(config)
        address = settings["status"]["address"]
        key_file = key_file or settings["transport"]["hmac_key_file"] or None
    return load_hmac_key(key_file), address


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="hapticproxy status", description=doc_summary(__doc__))
    p.add_argument("--address", help=f"the server's status address HOST:PORT (default: the config's, or {DEFAULT_ADDRESS})")
    p.add_argument("--config", help="the server's config file: its status address and HMAC key file")
    p.add_argument("--key-file", help="the HMAC key file (hex) of a server that authenticates requests")
    p.add_argument("--json", action="store_true", help="print the server's reply as strict JSON")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--rearm", action="store_true", help="clear a fault: forces ramp back in")
    g.add_argument("--stop", action="store_true", help="stop the server cleanly")
    g.add_argument("--reset-stats", action="store_true", help="reset the timing histograms")
    g.add_argument("--dump", metavar="FILE", help="write the telemetry and contact rings to the MCAP file FILE")
    g.add_argument("--watch", action="store_true", help="a live terminal view (q quits)")
    p.add_argument("--interval", type=float, default=0.2, help="--watch: seconds between updates")
    p.add_argument("--timeout", type=float, default=1.0,
                   help="seconds to wait for the server's answer (default 1; --watch: per poll)")
    args = p.parse_args(argv)
    try:
        key, cfg_address = load_key(args.config, args.key_file)
    except (OSError, ValueError) as exc:
        print(f"hapticproxy status: {exc}", file=sys.stderr)
        return 2
    address = args.address or cfg_address or DEFAULT_ADDRESS
    if args.watch:
        from .watch import run_watch

        return run_watch(address, query, key=key, interval_s=args.interval, timeout_s=args.timeout)
    req = {"cmd": "status"}
    if args.rearm:
        req = {"cmd": "rearm"}
    elif args.stop:
        req = {"cmd": "stop"}
    elif args.reset_stats:
        req = {"cmd": "reset_stats"}
    elif args.dump:
        req = {"cmd": "dump", "path": os.path.abspath(args.dump)}  # the caller's path, resolved here
    try:
        reply = query(address, req, args.timeout, key=key)
    except (TimeoutError, OSError, ValueError) as exc:
        print(f"hapticproxy status: {exc}", file=sys.stderr)
        return 1
    if "error" in reply:
        print(f"hapticproxy status: {reply['error']}", file=sys.stderr)
        return 1
    if args.json:
        print_json(reply, indent=1, sort_keys=True)
        return 0
    if req["cmd"] != "status":
        print(format_reply(req, reply, address), flush=True)
        return 0
    try:
        print(format_status(reply), flush=True)
    except BrokenPipeError:
        # `status | head`: the reader left; nothing more to say, and no traceback at exit
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    return 0
