"""``hapticproxy experiment NAME --out DIR``: the paper's experiments and the speed/accuracy trade-off.

    hapticproxy experiment fig6  --out out/fig6      # 1-DOF peg, proxy deformation vs none
    hapticproxy experiment fig9  --out out/fig9      # 1-DOF peg, epsilon 5 mm vs active geometry
    hapticproxy experiment fig14 --out out/fig14     # static contact: where the wall is felt
    hapticproxy experiment fig16 --out out/fig16     # the tight hole: drift and rotation
    hapticproxy experiment fig17 --out out/fig17     # the tight hole at k = 15000 N/m: stability
    hapticproxy experiment tradeoff --out out/trade  # the speed / accuracy sweep, Pareto plot
    hapticproxy experiment rates --out out/rates     # only the sweep's real-time achieved-rate runs
    hapticproxy experiment fidelity --out out/fid    # the felt surface before / after (issue 15), simulated
    hapticproxy experiment literal --out out/lit     # the paper's eq. 6 read literally (its Fig. 14 numbers)
    hapticproxy experiment zwidth --out out/zw       # Z-width: the renderable wall (K, B) per rate and device kind
    hapticproxy experiment lighttools --out out/lt   # tools of 5 g - 2 kg, moments from 1e-7, every kind, at rest on a floor
    hapticproxy experiment all --out out/exp         # every one of them, a folder each

``--quick``: the short version (shorter runs, fewer seeds and configurations). ``--mode``:
``realtime`` (default for the figures: the real server process at 512 Hz, the client over UDP
on 127.0.0.1) or ``simulated`` (the same stack in simulated time, deterministic). Figs. 6 and 9
run the 1-DOF peg (1-DOF device, peg engine, 20 ms delay), Figs. 14-17 the planar testbed. Each writes PNG plots and
``metrics.json`` (keyed by method) into ``--out`` and prints a one-line summary per method.
``zwidth`` also takes ``--layer on|off`` (the passivity layer, where the server has one),
``--velocity device|difference`` (what the controller reads) and ``--json`` (its summary on stdout);
``lighttools`` takes ``--json`` too (every run's row on stdout). Exit status 0, 2 on bad arguments, 1 when a run fails.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from ..protocol.logs import doc_summary

NAMES = ("fig6", "fig9", "fig14", "fig16", "fig17", "tradeoff", "rates", "fidelity", "literal", "zwidth",
         "lighttools")


def _summary(name: str, res: dict) -> list[str]:
    keys = {
        "fig6": ("unstable", "peak_excursion_mm", "growth"),
        "fig9": ("unstable", "both_walls_fraction", "force_on_fraction", "peak_excursion_mm"),
        "fig14": ("felt_wall_mm", "wall_error_mm", "limit_cycle_amplitude_mm", "limit_cycle_rotation_deg", "settled"),
        "fig16": ("drift_mm", "x_travel_mm", "rotation_deg", "unstable"),
        "fig17": ("drift_mm", "x_travel_mm", "rotation_deg", "energy_injected_mj", "unstable"),
    }[name]
    lines = []
    for method, m in res.items():
        vals = ", ".join(f"{k} {m.get(k)}" for k in keys)
        lines.append(f"{name} {method:<12} {vals}")
    return lines


def run_one(name: str, out: str, *, mode: str, quick: bool, log, layer: str | None = None,
            velocity: str = "device") -> dict:
    if name == "tradeoff":
        from .tradeoff import run_tradeoff

        return run_tradeoff(out, quick=quick, log=log)
    if name == "rates":
        from .tradeoff import run_rates

        return run_rates(out, quick=quick, log=log)
    if name == "fidelity":
        from .fidelity import run_fidelity

        return run_fidelity(out, quick=quick, log=log)
    if name == "zwidth":
        from .zwidth import run_zwidth

        return run_zwidth(out, quick=quick, layer=layer, velocity=velocity, log=log)
    if name == "lighttools":
        from .lighttools import run_lighttools

        return run_lighttools(out, quick=quick, log=log)
    if name == "literal":
        from .figures import paper_literal

        return paper_literal(out, quick=quick, log=log)
    from .figures import FIGURES

    return FIGURES[name](out, mode=mode, quick=quick, log=log)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="hapticproxy experiment", description=doc_summary(__doc__))
    p.add_argument("name", choices=NAMES + ("all",), help="which experiment")
    p.add_argument("--out", required=True, help="output folder (created)")
    p.add_argument("--quick", action="store_true", help="the short version")
    p.add_argument("--mode", choices=("realtime", "simulated"), default="realtime",
                   help="figures: the real server in real time (default) or simulated time")
    p.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    p.add_argument("--layer", choices=("on", "off"), default=None,
                   help="zwidth: with or without the passivity layer (default off: the bare hold; ignored, with a "
                        "note, where the server has no [passivity] settings)")
    p.add_argument("--json", action="store_true", help="zwidth, lighttools: print the summary as JSON on stdout")
    p.add_argument("--velocity", choices=("device", "difference"), default=None,
                   help="zwidth: the velocity the controller reads: the device's (default) or the backward difference "
                        "of its positions (Colgate and Schenkel's wall)")
    args = p.parse_args(argv)
    if (args.layer is not None or args.velocity) and args.name not in ("zwidth", "all"):
        p.error("--layer and --velocity apply to the zwidth experiment only")
    if args.json and args.name not in ("zwidth", "lighttools", "all"):
        p.error("--json applies to the zwidth and lighttools experiments only")
    names = tuple(n for n in NAMES if n != "rates") if args.name == "all" else (args.name,)
    log = None if args.quiet else (lambda msg: print(f"experiment: {msg}", file=sys.stderr, flush=True))
    status = 0
    for name in names:
        out = os.path.join(args.out, name) if args.name == "all" else args.out
        t0 = time.perf_counter()
        started = time.time() - 1.0  # files older than this run are not its plots
        try:
            res = run_one(name, out, mode=args.mode, quick=args.quick, log=log, layer=args.layer,
                          velocity=args.velocity or "device")
        except (RuntimeError, ValueError, OSError) as exc:
            print(f"hapticproxy experiment {name}: {exc}", file=sys.stderr)
            status = 1
            continue
        if name == "rates":
            for r in res["realtime_rates"]:
                print(f"rates {r['rate_hz']:g} Hz: " + (f"failed: {r['error']}" if "error" in r else
                      f"achieved {r['achieved_rate_hz']:.1f} Hz, missed {r['missed_deadlines']}, compute p99 "
                      f"{r['compute_us'].get('p99')} us"))
        elif name == "fidelity":
            from .fidelity import tables_md

            print(tables_md(res))
        elif name == "literal":
            from .figures import literal_md

            print(literal_md(res["rows"]))
        elif name == "zwidth":
            from .zwidth import summary_json

            if args.json:
                print(summary_json(res))
            else:
                if res["layer_note"]:
                    print(f"zwidth: {res['layer_note']}")
                for line in res["verdicts"]:
                    print(line)
        elif name == "lighttools":
            from .lighttools import summary_json

            print(summary_json(res) if args.json else "\n".join(res["summary"]))
        elif name == "tradeoff":
            print(f"tradeoff: {len(res['rows'])} configurations; table {os.path.join(out, 'tradeoff.md')}, "
                  f"stable region {os.path.join(out, 'stable_region.md')}, Pareto plot {os.path.join(out, 'pareto.png')}")
        else:
            for line in _summary(name, res):
                print(line)
        what = {"tradeoff": "tradeoff.json, tables", "rates": "rates.json, rates.md",
                "fidelity": "fidelity.json, fidelity.md", "literal": "literal.json, literal.md",
                "zwidth": "zwidth.json", "lighttools": "lighttools.json"}.get(name, "metrics.json")
        # name the plots this run wrote (a quick fidelity run writes none)
        plots = sorted(f for f in os.listdir(out) if f.endswith(".png")
                       and os.path.getmtime(os.path.join(out, f)) >= started)
        drawn = f" and {len(plots)} plot{'s' if len(plots) != 1 else ''} ({', '.join(plots)})" if plots else ""
        print(f"{name}: wrote {out}/{what}{drawn} ({time.perf_counter() - t0:.1f} s)",
              file=sys.stderr if args.json else sys.stdout)
    return status


if __name__ == "__main__":
    sys.exit(main())
