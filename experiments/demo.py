"""``hapticproxy demo``: the main job, headless, on loopback with embedded defaults.

Starts the haptics server (its loop in its own process, the simulated planar device) and the
pymunk environment client (the paper's Fig. 12 testbed) over UDP on loopback, runs the paper's
static-contact experiment (the hand pushes the tool onto the bottom wall with 0.5 N) for a few
seconds, prints a summary (haptic rate achieved, environment rate, contacts, where the wall was
felt vs where it is, final force) and writes a plot and the telemetry recording.
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from ..protocol.logs import doc_summary


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="hapticproxy demo", description=doc_summary(__doc__))
    p.add_argument("--out", default=os.path.join("out", "demo"), help="output folder (default: out/demo)")
    p.add_argument("--seconds", type=float, default=5.0, help="wall-clock seconds of the experiment (default 5)")
    p.add_argument("--rate", type=float, default=512.0, help="haptic rate [Hz] (default: the paper's 512)")
    p.add_argument("--engine", choices=("pymunk", "stub"), default="pymunk",
                   help="the environment client's engine (default pymunk; stub needs no physics library)")
    args = p.parse_args(argv)
    if not args.seconds >= 2.0:
        print("hapticproxy demo: --seconds must be >= 2", file=sys.stderr)
        return 2
    from .static_contact import PUSH_N, plot_static_contact, run_static_contact

    os.makedirs(args.out, exist_ok=True)
    rec = os.path.join(args.out, "static_contact.mcap")
    t0 = time.perf_counter()
    try:
        res = run_static_contact(seconds=args.seconds, rate_hz=args.rate, engine=args.engine, record=rec,
                                 log=lambda m: print(f"demo: {m}", file=sys.stderr))
    except (RuntimeError, ValueError) as exc:
        print(f"hapticproxy demo: {exc}", file=sys.stderr)
        return 1
    png = plot_static_contact(res, os.path.join(args.out, "static_contact.png"),
                              f"static contact, {args.engine} testbed, {res.rate_hz:g} Hz, LM with epsilon 5 mm, "
                              f"four-channel")
    err_mm = (res.felt_y_com_m - res.wall_y_com_m) * 1e3
    print(f"static contact ({args.engine} testbed, {args.seconds:g} s): haptic {res.achieved_rate_hz:.1f} Hz "
          f"(target {res.rate_hz:g}, lateness p99 {res.lateness_p99_us} us), environment {res.env_rate_hz:.1f} Hz "
          f"({res.updates} updates), contacts {res.contacts_final} (max {res.contacts_max}); "
          f"wall felt at y_COM {res.felt_y_com_m * 1e3:.1f} mm, it is at {res.wall_y_com_m * 1e3:.1f} mm "
          f"({err_mm:+.1f} mm); final force {res.final_force_n:+.3f} N against a {PUSH_N:g} N push; "
          f"{'settled' if res.settled else 'NOT settled'}, faults {res.faults}; plot {png}, telemetry {rec} "
          f"({time.perf_counter() - t0:.1f} s)")
    return 0 if res.faults == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
