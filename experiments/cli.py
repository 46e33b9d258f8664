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
``lighttools`` takes ``--json`` too (every run's row on stdout). ``tradeoff --region-only`` runs only
the stable-region grid (``--region-controllers 'four_channel;direct'``, ``--region-rates 512,1000,4000``:
a part of it; ``--layer on|off``: with or without the passivity layer, else the server's default) and
prints its table. Exit status 0, 2 on bad arguments, 1 when a run fails.
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


def _names(text: str) -> tuple[str, ...]:
    """``--region-controllers``: row names separated by ';' (the names hold commas)."""
    names = tuple(n.strip() for n in text.split(";") if n.strip())
    if not names:
        raise argparse.ArgumentTypeError("expected row names separated by ';', e.g. 'four_channel;direct'")
    return names


def _rates(text: str) -> tuple[float, ...]:
    """``--region-rates``: haptic rates in Hz separated by ','."""
    try:
        rates = tuple(float(r) for r in text.split(",") if r.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected rates in Hz separated by ',', e.g. 512,1000,4000; got {text!r}")
    if not rates:
        raise argparse.ArgumentTypeError("expected rates in Hz separated by ',', e.g. 512,1000,4000")
    return rates


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
            velocity: str = "device", damping_credit: float | None = None, input_credit: float | None = None,
            budget_j: float | None = None, region_only: bool = False,
            region_controllers=None, region_rates=None) -> dict:
    if name == "tradeoff":
        from .tradeoff import run_region, run_tradeoff

        if region_only:
            return run_region(out, quick=quick, log=log, controllers=region_controllers, rates=region_rates,
                              layer=layer)
        return run_tradeoff(out, quick=quick, log=log)
    if name == "rates":
        from .tradeoff import run_rates

        return run_rates(out, quick=quick, log=log)
    if name == "fidelity":
        from .fidelity import run_fidelity

        return run_fidelity(out, quick=quick, log=log)
    if name == "zwidth":
        from .zwidth import run_zwidth

        return run_zwidth(out, quick=quick, layer=layer, velocity=velocity, damping_credit=damping_credit,
                          input_credit=input_credit, budget_j=budget_j, log=log)
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
                   help="zwidth, tradeoff --region-only: with or without the passivity layer (zwidth: default off, "
                        "the bare hold; ignored, with a note, where the server has no [passivity] settings; the "
                        "region: the server's default unless given)")
    p.add_argument("--json", action="store_true", help="zwidth, lighttools: print the summary as JSON on stdout")
    p.add_argument("--velocity", choices=("device", "difference"), default=None,
                   help="zwidth: the velocity the controller reads: the device's (default) or the backward difference "
                        "of its positions (Colgate and Schenkel's wall)")
    p.add_argument("--damping-credit", type=float, default=None, metavar="SHARE",
                   help="zwidth, with --layer on: the share 0-1 of the device's damping the layer's tank credits "
                        "([passivity] damping_credit; default 1)")
    p.add_argument("--input-credit", type=float, default=None, metavar="SHARE",
                   help="zwidth, with --layer on: the share (0, 1] of the hand's input the tank keeps "
                        "([passivity] input_credit; default 1; 0.45 with --budget-j 0.002: the walls setting)")
    p.add_argument("--budget-j", type=float, default=None, metavar="J",
                   help="zwidth, with --layer on: the tank at start ([passivity] initial_budget_j; default 0.01)")
    p.add_argument("--region-only", action="store_true",
                   help="tradeoff: only the stable-region grid (writes stable_region.json, .md, .png)")
    p.add_argument("--region-controllers", type=_names, default=None, metavar="ROW[;ROW...]",
                   help="tradeoff --region-only: only these rows of the grid (their names, ';'-separated)")
    p.add_argument("--region-rates", type=_rates, default=None, metavar="HZ[,HZ...]",
                   help="tradeoff --region-only: only these haptic rates of the grid (comma-separated)")
    args = p.parse_args(argv)
    if (args.region_only or args.region_controllers or args.region_rates) and args.name != "tradeoff":
        p.error("--region-only, --region-controllers and --region-rates apply to the tradeoff experiment only")
    if (args.region_controllers or args.region_rates) and not args.region_only:
        p.error("--region-controllers and --region-rates need --region-only")
    if args.region_only:
        from .tradeoff import region_rows

        try:
            region_rows(args.region_controllers, args.region_rates, quick=args.quick)
        except ValueError as exc:
            p.error(str(exc))
    if args.velocity and args.name not in ("zwidth", "all"):
        p.error("--velocity applies to the zwidth experiment only")
    if args.layer is not None and args.name not in ("zwidth", "all") and not args.region_only:
        p.error("--layer applies to the zwidth experiment and tradeoff --region-only only")
    if args.damping_credit is not None and (args.name != "zwidth" or args.layer != "on"):
        p.error("--damping-credit applies to the zwidth experiment with --layer on only")
    if args.damping_credit is not None and not 0.0 <= args.damping_credit <= 1.0:
        p.error(f"--damping-credit: expected a share in [0, 1], got {args.damping_credit}")
    for flag, v in (("--input-credit", args.input_credit), ("--budget-j", args.budget_j)):
        if v is not None and (args.name != "zwidth" or args.layer != "on"):
            p.error(f"{flag} applies to the zwidth experiment with --layer on only")
    if args.input_credit is not None and not 0.0 < args.input_credit <= 1.0:
        p.error(f"--input-credit: expected a share in (0, 1], got {args.input_credit}")
    if args.budget_j is not None and not 0.0 <= args.budget_j <= 10.0:
        p.error(f"--budget-j: expected J in [0, 10], got {args.budget_j}")
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
                          velocity=args.velocity or "device", damping_credit=args.damping_credit,
                          input_credit=args.input_credit, budget_j=args.budget_j,
                          region_only=args.region_only, region_controllers=args.region_controllers,
                          region_rates=args.region_rates)
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
        elif name == "tradeoff" and args.region_only:
            from .tradeoff import region_md

            print(region_md(res["stable_region"]))
        elif name == "tradeoff":
            print(f"tradeoff: {len(res['rows'])} configurations; table {os.path.join(out, 'tradeoff.md')}, "
                  f"stable region {os.path.join(out, 'stable_region.md')}, Pareto plot {os.path.join(out, 'pareto.png')}")
        else:
            for line in _summary(name, res):
                print(line)
        what = {"tradeoff": "stable_region.json, stable_region.md" if args.region_only else "tradeoff.json, tables", "rates": "rates.json, rates.md",
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
