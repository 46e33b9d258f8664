"""``hapticproxy plot FILE``: PNG plots of a telemetry recording (trajectories, forces, timing)."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np


def plot_recording(path: str | Path, out_dir: str | Path | None = None) -> list[Path]:
    """Write ``<stem>_trajectory.png``, ``<stem>_forces.png`` and ``<stem>_timing.png``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .telemetry import read

    meta, rows = read(path)
    path = Path(path)
    out = Path(out_dir) if out_dir else path.parent
    out.mkdir(parents=True, exist_ok=True)
    if len(rows) == 0:
        raise ValueError(f"{path}: no complete telemetry block")
    f = {name: i for i, name in enumerate(meta["fields"])}
    t = rows[:, f["t_s"]] - rows[0, f["t_s"]]
    written = []

    fig, axes = plt.subplots(3, 1, figsize=(9, 8), sharex=True)
    for ax, a in zip(axes[:2], ("x", "y")):
        ax.plot(t, rows[:, f[f"dev_{a}"]] * 1e3, label="device (world)")
        ax.plot(t, rows[:, f[f"proxy_{a}"]] * 1e3, "--", label="proxy hand point")
        ax.set_ylabel(f"{a} [mm]")
        ax.legend(loc="best", fontsize=8)
    th_d = 2 * np.degrees(np.arctan2(rows[:, f["dev_qz"]], rows[:, f["dev_qw"]]))
    th_p = 2 * np.degrees(np.arctan2(rows[:, f["proxy_qz"]], rows[:, f["proxy_qw"]]))
    axes[2].plot(t, th_d, label="device")
    axes[2].plot(t, th_p, "--", label="proxy")
    axes[2].set_ylabel("rotation about z [deg]")
    axes[2].set_xlabel("time [s]")
    fig.suptitle(f"{path.name}: trajectories")
    p = out / f"{path.stem}_trajectory.png"
    fig.savefig(p, dpi=110)
    plt.close(fig)
    written.append(p)

    fig, axes = plt.subplots(3, 1, figsize=(9, 8), sharex=True)
    for ax, a in zip(axes, ("fx", "fy", "tz")):
        ax.plot(t, rows[:, f[f"cmd_{a}"]], label="command to the device")
        ax.plot(t, rows[:, f[f"env_{a}"]], "--", label="environment (local model)")
        ax.plot(t, rows[:, f[f"couple_{a}"]], ":", label="position channel on the proxy")
        ax.set_ylabel(f"{a} [{'N m' if a == 'tz' else 'N'}]")
        ax.legend(loc="best", fontsize=8)
    axes[-1].set_xlabel("time [s]")
    fig.suptitle(f"{path.name}: forces")
    p = out / f"{path.stem}_forces.png"
    fig.savefig(p, dpi=110)
    plt.close(fig)
    written.append(p)

    fig, axes = plt.subplots(2, 1, figsize=(9, 6))
    axes[0].plot(t, rows[:, f["lateness_us"]], ",", label="wake-up lateness")
    axes[0].plot(t, rows[:, f["compute_us"]], ",", label="step compute")
    axes[0].set_ylabel("us")
    axes[0].set_yscale("symlog", linthresh=10)
    axes[0].legend(loc="best", fontsize=8)
    axes[0].set_xlabel("time [s]")
    late = rows[:, f["lateness_us"]]
    axes[1].hist(np.clip(late, 0, 500), bins=100, log=True)
    axes[1].set_xlabel(f"lateness [us] (clipped at 500; p99 {np.percentile(late, 99):.1f}, max {late.max():.0f})")
    fig.suptitle(f"{path.name}: timing at {meta.get('rate_hz')} Hz")
    fig.tight_layout()
    p = out / f"{path.stem}_timing.png"
    fig.savefig(p, dpi=110)
    plt.close(fig)
    written.append(p)
    return written


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="hapticproxy plot", description=__doc__)
    ap.add_argument("file", help="telemetry recording (.hpt)")
    ap.add_argument("--out", help="directory for the PNGs (default: next to the file)")
    args = ap.parse_args(argv)
    try:
        for p in plot_recording(args.file, args.out):
            print(p)
    except (OSError, ValueError) as exc:
        print(f"hapticproxy plot: {exc}", file=sys.stderr)
        return 1
    return 0
