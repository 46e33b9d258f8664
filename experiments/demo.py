"""``hapticproxy demo``: the main job.

Until the server daemon and the environment clients exist (issues 4 and 5), the demo runs the
paper's 1-DOF peg-in-hole (Figs. 5-6) headless on the real local model: the same peg, delay,
stiffness and hand force under the ``rigid`` policy (no proxy deformation) and under proxy
deformation. It writes a PNG plot and prints a one-line summary.
"""
from __future__ import annotations

import argparse
import os
import sys
import time


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="hapticproxy demo", description=__doc__.splitlines()[0])
    parser.add_argument("--out", default=os.path.join("out", "demo"), help="output folder (default: out/demo)")
    parser.add_argument("--seconds", type=float, default=5.0, help="simulated time per run (default 5)")
    args = parser.parse_args(argv)
    if not args.seconds > 1.0:
        print("hapticproxy demo: --seconds must be > 1", file=sys.stderr)
        return 2

    from .peg1d import (FIG6_DAMPING_N_S_PER_M, FIG6_DELAY_S, FIG6_FORCE_AMPLITUDE_N, FIG6_FORCE_HZ,
                        FIG6_MASS_KG, FIG6_STIFFNESS_N_PER_M, plot_runs, simulate_peg1d)

    t0 = time.perf_counter()
    runs = [simulate_peg1d(policy, duration_s=args.seconds) for policy in ("rigid", "deformation")]
    os.makedirs(args.out, exist_ok=True)
    path = os.path.join(args.out, "fig6_peg_in_hole.png")
    setup = (f"{FIG6_MASS_KG:g} kg peg, K={FIG6_STIFFNESS_N_PER_M:g} N/m, B={FIG6_DAMPING_N_S_PER_M:g} N s/m, "
             f"{FIG6_DELAY_S * 1e3:g} ms delay, {FIG6_FORCE_AMPLITUDE_N:g} N at {FIG6_FORCE_HZ:g} Hz, 1 kHz")
    plot_runs(runs, path, f"1-DOF peg-in-hole (paper Fig. 6): {setup}")
    rigid, deform = runs
    print(f"fig6 peg-in-hole ({setup}): rigid {'UNSTABLE' if rigid.unstable else 'bounded'} "
          f"(peak {abs(rigid.x_hand_m).max() * 1e3:.1f} mm, growth x{rigid.growth:.1f}), "
          f"deformation {'UNSTABLE' if deform.unstable else 'bounded'} "
          f"(peak {abs(deform.x_hand_m).max() * 1e3:.2f} mm, growth x{deform.growth:.2f}); "
          f"plot {path}; {time.perf_counter() - t0:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
