"""``hapticproxy bench loop``: how well the real server loop keeps its deadlines.

Runs the real server (supervisor + loop process, simulated planar device pushed by a constant
0.5 N hand, the default controller and model) with an environment client sending a ContactUpdate
at 60 Hz over UDP loopback, for ``--seconds``; then, for comparison, the same loop doing the same
work but paced by ``time.sleep`` alone, with none of the tuning (no spin phase, no timer slack,
no real-time scheduling, garbage collector left on). Prints a summary and a table of the update
steps, or with ``--json`` one JSON object:

``rate_hz``, ``seconds``, ``steps``, ``lateness_us`` (``p50``, ``p99``, ``p999``, ``max``: wake-up time
minus the absolute deadline, 1 us bins, upper edges), ``step_us`` (``p50``, ``p99``: poll to device
write), ``missed_fraction`` (steps that finished after the next deadline / steps),
``missed_deadlines`` (whole periods skipped), ``rt_scheduling``, ``spin_us``, ``cpu_latency_us``
(the idle CPUs' wake-up latency held, None when not), ``clock_cpu`` (the clock thread's CPU, None
when not pinned), ``updates``,
``faults``, ``naive_lateness_us`` (``p50``, ``p99``, ``p999``, ``max``), ``naive_missed_fraction``,
``p99_ratio_naive_over_loop``, ``machine``, ``protocol_thread`` (the loop ran a clock thread),
``clock_ticks`` and ``clock_held`` (its ticks run, and held while Python had the tick's lock; None
without one); then ``update_steps`` (per tool kind: the CPU time of
the steps that receive, stage, apply (the tick) and acknowledge (Python, after it), or do none
of these with a model update; ``benchmarks/update_steps.py``), ``apply_p99_max_us``,
``receive_p99_max_us``, ``stage_p99_max_us``, ``p50_over_plain_max`` (the costliest update step's p50 over a plain step's
in the same run), ``budget_us`` (a quarter of a 4 kHz period) and ``within_budget``.
"""
from __future__ import annotations

import argparse
import math
import os
import platform
import socket
import sys
import threading
import time

import numpy as np

from ..protocol.logs import doc_summary
from ..protocol.codec import Hello
from ..protocol.messages import ToolKind
from ..protocol.session import ClientEndpoint
from ..protocol.transport import open_transport
from ..server import config as cfgmod
from ..server.daemon import Supervisor
from ..protocol.jsonout import print_json


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def floor_client(url: str, stop: threading.Event, rate_hz: float, hello: Hello, pose: np.ndarray, contacts,
                 counts: dict) -> None:
    """An environment client until ``stop``: its tool follows the pose of every ProxyState
    (``counts["proxy_states"]``) and at ``rate_hz`` it sends ``contacts(pose, cos, sin)`` ->
    (keys, points, normals, separations), cos and sin of the tool's yaw
    (``counts["updates_sent"]``)."""
    tr = open_transport(url, "client")
    ep = ClientEndpoint(tr.send, hello)
    ep.start()
    period = 1.0 / rate_hz
    nxt = time.monotonic()
    try:
        while not stop.is_set():
            while True:
                item = tr.recv()
                if item is None:
                    break
                ps = ep.receive(item[0], item[1])
                if ps is not None:
                    pose = np.array(ps.proxy_pose, dtype=float)
                    counts["proxy_states"] += 1
            ep.poll()
            if ep.established:
                th = 2 * math.atan2(pose[6], pose[3])
                k, cp, nrm, d = contacts(pose, math.cos(th), math.sin(th))
                ep.send_contacts(None, time.monotonic(), pose, k, cp, nrm, d, np.zeros(len(d)))
                counts["updates_sent"] += 1
            nxt += period
            time.sleep(max(0.0, nxt - time.monotonic()))
        ep.close()
    finally:
        tr.close()


def _client(url: str, stop: threading.Event, rate_hz: float, counts: dict) -> None:
    """A 60 Hz environment: a floor under a planar box tool that follows the proxy."""
    hello = Hello(client_nonce=1, engine="bench-loop floor", tool_kind=ToolKind.PLANAR, mass_kg=0.2,
                  inertia_kg_m2=(2e-4, 2e-4, 2e-4, 0, 0, 0), max_contacts=8, epsilon_m=0.005, env_rate_hz=rate_hz)
    keys = np.array([[0, 1, 0], [0, 1, 1]], dtype=np.int64)
    nrm = np.array([[0.0, 1.0, 0.0], [0.0, 1.0, 0.0]])

    def contacts(pose, c, s):
        pts, seps = [], []
        for bx in (-0.02, 0.02):
            x = pose[0] + c * bx + s * 0.01
            y = pose[1] + s * bx - c * 0.01
            pts.append((x, 0.0, 0.0))
            seps.append(max(y, -0.02))
        cp = np.array(pts)
        d = np.array(seps)
        k = d <= 0.005
        return keys[k], cp[k], nrm[k], d[k]

    floor_client(url, stop, rate_hz, hello, np.array([0.0, 0.05, 0.0, 1.0, 0.0, 0.0, 0.0]), contacts, counts)


def _run(settings: cfgmod.Settings, seconds: float, naive: bool) -> dict:
    sup = Supervisor(settings, duration_s=None, naive=naive)
    stop = threading.Event()
    counts = {"updates_sent": 0, "proxy_states": 0}
    th = None
    try:
        sup.start()
        th = threading.Thread(target=_client, args=(settings["transport"]["url"], stop, 60.0, counts), daemon=True)
        th.start()
        # let the client engage, then measure a clean window
        t0 = time.monotonic()
        while time.monotonic() - t0 < 1.0:
            sup._serve_status(0.05)
        sup.shared.request("reset_stats")
        while time.monotonic() - t0 < 1.2:
            sup._serve_status(0.05)
        t1 = time.monotonic()
        while time.monotonic() - t1 < seconds:
            sup._serve_status(0.05)
        snap = sup.shared.snapshot()
    finally:
        stop.set()
        if th is not None:
            th.join(5)
        sup.close()
    steps = snap["lateness_us"]["count"]
    return {"snap": snap, "steps": steps, "counts": counts}


def run(rate_hz: float, seconds: float, naive_seconds: float, protocol_thread="auto", spin_us="auto",
        cpu_latency_us: int | None = 0, clock_cpu="auto") -> dict:
    def settings(thread=protocol_thread):
        return cfgmod.load({
            "loop": {"rate_hz": rate_hz, "protocol_thread": thread, "spin_us": spin_us,
                     "cpu_latency_us": "off" if cpu_latency_us is None else cpu_latency_us,
                     "clock_cpu": clock_cpu},
            "transport": {"url": f"udp://127.0.0.1:{free_port()}"},
            "status": {"address": f"127.0.0.1:{free_port()}"},
            "device": {"driver": "sim", "kind": "planar", "hand": {"type": "constant", "wrench": [0.0, -0.5, 0.0]}},
            "telemetry": {"ring_s": 2.0},
        })

    real = _run(settings(), seconds, naive=False)
    naive = _run(settings(False), naive_seconds, naive=True) if naive_seconds > 0 else None
    s = real["snap"]
    steps = max(1, real["steps"])
    lat, comp = s["lateness_us"], s["compute_us"]
    out = {
        "rate_hz": rate_hz,
        "seconds": seconds,
        "steps": real["steps"],
        # percentiles from the 1-us histogram (bin upper edges); max is the exact worst case
        "lateness_us": {**{k: lat[k] for k in ("p50", "p99", "p999")}, "max": round(s["lateness_max_us"], 1)},
        "step_us": {**{k: comp[k] for k in ("p50", "p99")}, "max": round(s["compute_max_us"], 1)},
        "missed_fraction": s["overruns"] / steps,
        "missed_deadlines": int(s["missed_deadlines"]),
        "rt_scheduling": bool(s["rt_scheduling"]),
        "spin_us": s["spin_ns"] / 1000.0,
        # the idle CPUs' wake-up latency the loop held the kernel to (None: not held)
        "cpu_latency_us": int(s["cpu_latency_us"]) if s.get("cpu_latency_us", -1) >= 0 else None,
        # the CPU the clock thread ticked on (None: not pinned, or no clock thread)
        "clock_cpu": int(s["clock_cpu"]) if s.get("clock_cpu", -1) >= 0 else None,
        "updates": int(s["updates"]),
        "faults": int(s["faults_total"]),
        # the server's [loop] protocol_thread as it ran: a clock thread's ticks, and those it held
        # (Python had the tick's lock: nothing ticked); None without one
        "protocol_thread": bool(s["servo_ticks"]),
        "clock_ticks": int(s["servo_ticks"]) if s["servo_ticks"] else None,
        "clock_held": int(s["servo_held"]) if s["servo_ticks"] else None,
    }
    if naive is not None:
        n = naive["snap"]
        out["naive_seconds"] = naive_seconds
        out["naive_lateness_us"] = {**{k: n["lateness_us"][k] for k in ("p50", "p99", "p999")},
                                    "max": round(n["lateness_max_us"], 1)}
        out["naive_missed_fraction"] = n["overruns"] / max(1, naive["steps"])
        lp99 = out["lateness_us"]["p99"] or 1.0
        out["p99_ratio_naive_over_loop"] = (n["lateness_us"]["p99"] or 0.0) / lp99
    out["machine"] = f"{platform.machine()} {os.cpu_count()} cpus, {platform.system()} {platform.release()}"
    return out


def main(argv: list[str] | None = None) -> int:
    from . import update_steps

    ap = argparse.ArgumentParser(prog="hapticproxy bench loop", description=doc_summary(__doc__))
    ap.add_argument("--json", action="store_true", help="print one JSON object (default: a summary and a table)")
    ap.add_argument("--rate", type=float, default=1000.0, help="haptic rate [Hz] (default 1000)")
    ap.add_argument("--seconds", type=float, default=60.0, help="measured seconds of the real loop (default 60)")
    ap.add_argument("--naive-seconds", type=float, default=None,
                    help="seconds of the naive comparison loop (default: same as --seconds, at most 20)")
    ap.add_argument("--update-steps", type=int, default=update_steps.STEPS, metavar="N",
                    help="steps per tool kind of the update-step measurement (default %(default)s: about 1,870 "
                         "of each update step, so that a p99 is not one of the few largest of a few hundred; "
                         "0: skip it)")
    ap.add_argument("--update-steps-only", action="store_true", help="only the update-step measurement")
    ap.add_argument("--loop", choices=("auto", "clock-thread", "one-thread"), default="auto",
                    help="the server's [loop] protocol_thread: clock-thread (the tick in a thread of its own, "
                         "the protocol beside it), one-thread (the compiled loop hands steps back to Python), "
                         "auto (the server's default: clock-thread on 2 CPUs or more)")
    ap.add_argument("--spin-us", default="auto", metavar="US",
                    help="the server's [loop] spin_us: the spin before each deadline, us (auto: calibrated; the "
                         "compiled loops cap it at 60 %% of the period)")
    ap.add_argument("--cpu-latency-us", default="0", metavar="US",
                    help="the server's [loop] cpu_latency_us: the idle CPUs' wake-up latency held while it runs, us "
                         "(default 0: idle CPUs poll; off: the OS decides)")
    ap.add_argument("--clock-cpu", default="auto", metavar="CPU",
                    help="the server's [loop] clock_cpu: the clock thread's CPU (auto: the highest; -1: not pinned)")
    args = ap.parse_args(argv)
    if args.clock_cpu != "auto":
        try:
            args.clock_cpu = int(args.clock_cpu)
        except ValueError:
            args.clock_cpu = -2
        if not -1 <= args.clock_cpu <= 1023:
            print("hapticproxy bench loop: --clock-cpu must be auto, -1 or a CPU number", file=sys.stderr)
            return 2
    from ..server.clock import parse_cpu_latency

    try:
        args.cpu_latency_us = parse_cpu_latency(args.cpu_latency_us)
    except ValueError as exc:
        print(f"hapticproxy bench loop: --cpu-latency-us {exc}", file=sys.stderr)
        return 2
    if args.spin_us != "auto":
        try:
            args.spin_us = float(args.spin_us)
        except ValueError:
            args.spin_us = -1.0
        if not 0.0 <= args.spin_us <= 5000.0:
            print("hapticproxy bench loop: --spin-us must be auto or a number of us in [0, 5000]", file=sys.stderr)
            return 2
    if not (100 <= args.rate <= 20000) or not args.seconds > 0:
        print("hapticproxy bench loop: --rate must be in [100, 20000] Hz and --seconds > 0", file=sys.stderr)
        return 2
    if args.update_steps < 0 or (args.update_steps_only and args.update_steps == 0):
        print("hapticproxy bench loop: --update-steps must be >= 0 (0: skip the update-step measurement), and > 0 "
              "with --update-steps-only", file=sys.stderr)
        return 2
    naive_s = min(args.seconds, 20.0) if args.naive_seconds is None else args.naive_seconds
    try:
        res = {} if args.update_steps_only else run(args.rate, args.seconds, naive_s,
                                                       {"auto": "auto", "clock-thread": True, "one-thread": False}[args.loop],
                                                       spin_us=args.spin_us, cpu_latency_us=args.cpu_latency_us,
                                                       clock_cpu=args.clock_cpu)
    except RuntimeError as exc:
        print(f"hapticproxy bench loop: {exc}", file=sys.stderr)
        return 1
    # the steps that receive and apply a model update, per tool kind (in-process, CPU time)
    if args.update_steps:
        res.update(update_steps.run(steps=args.update_steps, rate_hz=args.rate))
    if args.json:
        print_json(res, indent=1)
    else:
        print_report(res)
    return 0


def _us(d: dict | None, k: str) -> str:
    v = None if d is None else d.get(k)
    return "-" if v is None else f"{v:.1f}"


def print_report(res: dict) -> None:
    """What a person at a terminal reads: the real loop's deadlines, then one row per tool kind
    and step type of the update-step measurement, with its p50 over a plain step's."""
    if "steps" in res:
        lat, st = res["lateness_us"], res["step_us"]
        print(f"real loop   {res['rate_hz']:g} Hz for {res['seconds']:g} s: {res['steps']} steps, {res['updates']} updates, "
              f"faults {res['faults']}, real-time scheduling {'yes' if res['rt_scheduling'] else 'no'}, "
              f"spin {res['spin_us']:.0f} us, idle CPUs "
              + ("left to the OS" if res.get("cpu_latency_us") is None else f"wake within {res['cpu_latency_us']} us")
              + ("" if res.get("clock_cpu") is None else f", clock thread on CPU {res['clock_cpu']}"))
        print(f"  lateness us  p50 {_us(lat, 'p50')}  p99 {_us(lat, 'p99')}  p99.9 {_us(lat, 'p999')}  "
              f"max {_us(lat, 'max')};  missed {100 * res['missed_fraction']:.3f} %")
        print(f"  step us      p50 {_us(st, 'p50')}  p99 {_us(st, 'p99')}  max {_us(st, 'max')}")
        if res.get("protocol_thread"):
            held, ticks = res["clock_held"], res["clock_ticks"]
            print(f"  clock thread {ticks} ticks, {held} held while Python had the lock "
                  f"({100 * held / max(1, held + ticks):.3f} %)")
        if "naive_lateness_us" in res:
            nl = res["naive_lateness_us"]
            print(f"  naive loop   lateness p99 {_us(nl, 'p99')} us, missed {100 * res['naive_missed_fraction']:.3f} % "
                  f"(p99 {res['p99_ratio_naive_over_loop']:.1f}x the tuned loop's)")
        print(f"  machine      {res['machine']}")
    rows = res.get("update_steps") or []
    if not rows:
        return
    print(f"update steps, run by Python (thread CPU time, us; {rows[0]['contacts']} contacts every 16 steps, "
          f"simulated time):")
    print("  the tick (device read .. write, accounting) first, then the step's Python part; the tick")
    print("  kernel's own cost called from compiled code, for comparison")
    print(f"  {'tool':<16} {'step':<13} {'n':>5} {'tick p50':>8} {'tick p99':>8} {'step p50':>8} {'step p99':>8} "
          f"{'max':>7} {'p50 / plain':>11}")
    for r in rows:
        for k in ("receive", "stage", "apply", "housekeeping", "other"):
            d = r.get(f"{k}_us")
            if d is None:
                continue
            tk = r.get(f"{k}_tick_us") or {}
            ratio = r.get("p50_over_plain", {}).get(k)
            name = "plain" if k == "other" else k
            print(f"  {r['tool']:<16} {name:<13} {d['n']:>5} {_us(tk, 'p50'):>8} {_us(tk, 'p99'):>8} {_us(d, 'p50'):>8} "
                  f"{_us(d, 'p99'):>8} {_us(d, 'max'):>7} {'' if ratio is None else f'{ratio:.2f}':>11}")
        kc = r.get("tick_kernel_us")
        if kc:
            print(f"  {r['tool']:<16} {'tick kernel':<13} {'':>5} {kc['p50']:>8.2f} {kc['p99']:>8.2f}")
    worst = max(res["apply_p99_max_us"], res["receive_p99_max_us"], res.get("stage_p99_max_us") or 0.0)
    print(f"  the costliest tick's p99: {res['tick_p99_max_us']:.1f} us; the budget (a quarter of a 10 kHz period): "
          f"{res['tick_budget_us']:g} us: {'within' if res['tick_within_budget'] else 'over'}")
    print(f"  the costliest whole step's p99 (tick and Python part): {worst:.1f} us; a quarter of a 4 kHz period: "
          f"{res['budget_us']:g} us: {'within' if res['within_budget'] else 'over'}")
    if "steps" in res and rows:
        plain = res["step_us"]["p50"]
        kern = next((r["tick_kernel_us"]["p50"] for r in rows if r["tool"] == "planar" and r.get("tick_kernel_us")), None)
        if plain and kern:
            print(f"  the real loop's step p50 {plain:.1f} us over the planar tick kernel's p50 {kern:.2f} us: "
                  f"{plain / kern:.2f}x")
