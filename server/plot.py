"""``hapticproxy plot FILE``: PNG plots of a recording (MCAP, or a legacy ``.hpt``).

What is drawn follows the device kind (from the recording's metadata, else its config): a 1-DOF
device its position and force along its axis; a planar one x, y and the rotation about z; a
spatial one x, y, z and the rotation about each axis (rotation vector). Four PNGs:

- ``<stem>_trajectory.png``: device and proxy on every axis the kind moves in;
- ``<stem>_forces.png``: the command to the device, the environment (local model) wrench and the
  position channel, with the force / torque caps as lines; the axis range is the command's and
  the caps' (an environment spike beyond it is clipped and marked, so it cannot hide the
  command);
- ``<stem>_state.png``: loop state, gain, contacts (and each update's deepest penetration);
- ``<stem>_timing.png``: wake-up lateness and compute time.

Every axis spans at least a minimum (0.5 mm, 0.5 deg, 0.01 N, 1e-3 N m): numerical noise (a
1e-13 deg rotation) is drawn as the flat line it is, not blown up to fill the axis.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from ..protocol.logs import doc_summary

MIN_SPAN = {"mm": 0.5, "deg": 0.5, "N": 0.01, "N m": 1e-3}


def _set_min_span(ax, values, span: float) -> None:
    v = np.asarray(values, dtype=float)
    v = v[np.isfinite(v)]
    if len(v) == 0:
        return
    lo, hi = float(v.min()), float(v.max())
    if hi - lo < span:
        mid = 0.5 * (hi + lo)
        ax.set_ylim(mid - span / 2, mid + span / 2)


def _rotvec_deg(q: np.ndarray) -> np.ndarray:
    """Rotation vectors (deg) of quaternions w x y z, rows."""
    q = np.asarray(q, dtype=float)
    q = q * np.where(q[:, :1] < 0, -1.0, 1.0)  # the short way round
    w = np.clip(q[:, 0], -1.0, 1.0)
    s = np.sqrt(np.maximum(0.0, 1.0 - w * w))
    ang = 2 * np.arctan2(s, w)
    k = np.where(s > 1e-12, ang / np.where(s > 1e-12, s, 1.0), 2.0)
    return np.degrees(q[:, 1:] * k[:, None])


def _kind(meta: dict, cols: dict, rows: np.ndarray) -> str:
    k = meta.get("device_kind") or (meta.get("config") or {}).get("device", {}).get("kind")
    if k in ("1dof", "planar", "spatial"):
        return k
    moved = lambda n: n in cols and np.nanmax(np.abs(rows[:, cols[n]])) > 0  # noqa: E731
    if moved("dev_z") or moved("dev_qx") or moved("dev_qy"):
        return "spatial"
    return "planar"


def _caps(meta: dict) -> tuple[float | None, float | None]:
    saf = (meta.get("config") or {}).get("safety", {})
    f = meta.get("force_cap_n", saf.get("max_force_n"))
    t = meta.get("torque_cap_n_m", saf.get("max_torque_n_m"))
    return (float(f) if f is not None else None), (float(t) if t is not None else None)


def plot_recording(path: str | Path, out_dir: str | Path | None = None) -> list[Path]:
    """Write the PNGs (see the module docstring); returns their paths."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from . import recording, telemetry
    from .lifecycle import LOOP_STATES

    path = Path(path)
    contacts = []
    if recording.is_mcap(path):
        rec = recording.read(path)
        meta, rows = dict(rec.meta), rec.rows
        cols = {name: i for i, name in enumerate(recording_fields())}
        contacts = rec.contacts
    else:
        meta, rows = telemetry.read(path)
        cols = {name: i for i, name in enumerate(meta["fields"])}
    out = Path(out_dir) if out_dir else path.parent
    out.mkdir(parents=True, exist_ok=True)
    if len(rows) == 0:
        raise ValueError(f"{path}: no complete telemetry in the file")
    col = lambda n: rows[:, cols[n]] if n in cols else np.full(len(rows), np.nan)  # noqa: E731
    t0 = col("t_s")[0]
    t = col("t_s") - t0
    kind = _kind(meta, cols, rows)
    fcap, tcap = _caps(meta)
    rate = meta.get("rate_hz")
    title = f"{path.name} ({kind} device{f', {rate:g} Hz' if isinstance(rate, (int, float)) else ''})"
    written = []

    def save(fig, name):
        p = out / f"{path.stem}_{name}.png"
        fig.savefig(p, dpi=110)
        plt.close(fig)
        written.append(p)

    # ------------------------------------------------------------------ trajectories
    dq = np.column_stack([col(f"dev_{a}") for a in ("qw", "qx", "qy", "qz")])
    pq = np.column_stack([col(f"proxy_{a}") for a in ("qw", "qx", "qy", "qz")])
    if kind == "1dof":
        axis = np.asarray((meta.get("config") or {}).get("device", {}).get("axis", (1.0, 0.0, 0.0)), dtype=float)
        axis = axis / (np.linalg.norm(axis) or 1.0)
        dev_s = np.column_stack([col(f"dev_{a}") for a in "xyz"]) @ axis
        prx_s = np.column_stack([col(f"proxy_{a}") for a in "xyz"]) @ axis
        panels = [("along the axis [mm]", dev_s * 1e3, prx_s * 1e3, "mm")]
    else:
        lin = ("x", "y") if kind == "planar" else ("x", "y", "z")
        panels = [(f"{a} [mm]", col(f"dev_{a}") * 1e3, col(f"proxy_{a}") * 1e3, "mm") for a in lin]
        if kind == "planar":
            panels.append(("rotation about z [deg]", np.degrees(np.unwrap(2 * np.arctan2(dq[:, 3], dq[:, 0]))),
                           np.degrees(np.unwrap(2 * np.arctan2(pq[:, 3], pq[:, 0]))), "deg"))
        else:
            rd, rp = _rotvec_deg(dq), _rotvec_deg(pq)
            panels += [(f"rotation about {a} [deg]", rd[:, i], rp[:, i], "deg") for i, a in enumerate("xyz")]
    fig, axes = plt.subplots(len(panels), 1, figsize=(9, 2.2 * len(panels) + 1), sharex=True, squeeze=False)
    for ax, (label, d, p, unit) in zip(axes[:, 0], panels):
        ax.plot(t, d, label="device")
        ax.plot(t, p, "--", label="proxy hand point")
        ax.set_ylabel(label)
        _set_min_span(ax, np.r_[d, p], MIN_SPAN[unit])
        ax.legend(loc="best", fontsize=8)
        ax.grid(alpha=0.3)
    axes[-1, 0].set_xlabel("time [s]")
    fig.suptitle(f"{title}: trajectories")
    fig.tight_layout()
    save(fig, "trajectory")

    # ------------------------------------------------------------------ forces
    if kind == "1dof":
        f3 = lambda pre: np.column_stack([col(f"{pre}_{a}") for a in ("fx", "fy", "fz")]) @ axis  # noqa: E731
        fpanels = [("force along the axis [N]", f3("cmd"), f3("env"), f3("couple"), fcap, "N")]
    else:
        comps = ("fx", "fy", "tz") if kind == "planar" else ("fx", "fy", "fz", "tx", "ty", "tz")
        fpanels = []
        for a in comps:
            unit = "N m" if a.startswith("t") else "N"
            fpanels.append((f"{a} [{unit}]", col(f"cmd_{a}"), col(f"env_{a}"), col(f"couple_{a}"),
                            tcap if unit == "N m" else fcap, unit))
    # the position channel acts on the proxy only while the device drives it (engaged): idle,
    # fading, in fault or stopping the proxy is held, and the stretch the hand builds is not applied
    driven = col("loop_state") == LOOP_STATES.index("engaged")
    fig, axes = plt.subplots(len(fpanels), 1, figsize=(9, 2.2 * len(fpanels) + 1), sharex=True, squeeze=False)
    for ax, (label, cmd, env, cpl, cap, unit) in zip(axes[:, 0], fpanels):
        ax.plot(t, cmd, label="command to the device", lw=1.4, zorder=3)
        ax.plot(t, np.where(driven, cpl, np.nan), ":", label="position channel on the proxy (while engaged)", zorder=2)
        # the range the command and the caps need, plus a margin; the model's force keeps to it
        ref = cmd[np.isfinite(cmd)]
        lo, hi = (float(ref.min()), float(ref.max())) if len(ref) else (0.0, 0.0)
        if cap:
            lo, hi = min(lo, -cap if lo < 0 else lo), max(hi, cap if hi > 0 else hi)
        span = max(hi - lo, MIN_SPAN[unit])
        ylo, yhi = lo - 0.1 * span, hi + 0.1 * span
        if hi - lo < MIN_SPAN[unit]:
            mid = 0.5 * (hi + lo)
            ylo, yhi = mid - 0.6 * MIN_SPAN[unit], mid + 0.6 * MIN_SPAN[unit]
        envc = np.clip(env, ylo, yhi)
        ax.plot(t, envc, "--", label="environment (local model)", zorder=1, alpha=0.8)
        spikes = np.isfinite(env) & ((env > yhi) | (env < ylo))
        if spikes.any():
            ax.plot(t[spikes], envc[spikes], "^", ms=3, color="C1", label=f"environment beyond the axis "
                    f"({int(spikes.sum())} steps, max |{np.nanmax(np.abs(env[spikes])):.3g}| {unit})")
        if cap:
            for c in (cap, -cap):
                if ylo <= c <= yhi:
                    ax.axhline(c, color="k", lw=0.8, ls="-.")
            ax.text(0.995, 0.02, f"cap +-{cap:g} {unit}", transform=ax.transAxes, ha="right", va="bottom", fontsize=7)
        ax.set_ylim(ylo, yhi)
        ax.set_ylabel(label)
        ax.legend(loc="upper left", fontsize=7)
        ax.grid(alpha=0.3)
    axes[-1, 0].set_xlabel("time [s]")
    fig.suptitle(f"{title}: forces\n(command: device frame; environment and position channel: world)", fontsize=10)
    fig.tight_layout()
    save(fig, "forces")

    # ------------------------------------------------------------------ state, gain, contacts
    fig, axes = plt.subplots(3, 1, figsize=(9, 6.5), sharex=True)
    st = col("loop_state")
    axes[0].step(t, st, where="post")
    axes[0].set_yticks(range(len(LOOP_STATES)), LOOP_STATES, fontsize=7)
    axes[0].set_ylim(-0.5, len(LOOP_STATES) - 0.5)
    axes[0].set_ylabel("state")
    axes[1].plot(t, col("gain"))
    axes[1].set_ylim(-0.05, 1.05)
    axes[1].set_ylabel("gain")
    axes[2].step(t, col("contacts"), where="post", label="contacts in the model")
    axes[2].set_ylabel("contacts")
    if contacts:
        ct = np.array([c["t_s"] for c in contacts]) - t0
        pen = np.array([max(0.0, -(c["min_separation_m"] if c["min_separation_m"] is not None else 0.0))
                        for c in contacts]) * 1e3
        ax2 = axes[2].twinx()
        ax2.plot(ct, pen, ".", ms=3, color="C3", label="deepest penetration per update")
        ax2.set_ylabel("penetration [mm]", color="C3")
        ax2.set_ylim(0.0, max(MIN_SPAN["mm"], 1.1 * float(pen.max()) if len(pen) else 0.0))
    for ax in axes:
        ax.grid(alpha=0.3)
    axes[2].legend(loc="upper left", fontsize=8)
    axes[-1].set_xlabel("time [s]")
    fig.suptitle(f"{title}: state, gain, contacts")
    fig.tight_layout()
    save(fig, "state")

    # ------------------------------------------------------------------ timing
    fig, axes = plt.subplots(2, 1, figsize=(9, 6))
    late, comp = col("lateness_us"), col("compute_us")
    axes[0].plot(t, late, ",", label="wake-up lateness")
    axes[0].plot(t, comp, ",", label="step compute")
    axes[0].set_ylabel("us")
    axes[0].set_yscale("symlog", linthresh=10)
    axes[0].legend(loc="best", fontsize=8, markerscale=20)
    axes[0].set_xlabel("time [s]")
    fl = late[np.isfinite(late)]
    axes[1].hist(np.clip(fl, 0, 500), bins=100, log=True)
    if len(fl):
        axes[1].set_xlabel(f"lateness [us] (clipped at 500; p99 {np.percentile(fl, 99):.1f}, max {fl.max():.0f})")
    fig.suptitle(f"{title}: timing")
    fig.tight_layout()
    save(fig, "timing")
    return written


def recording_fields():
    from .shm import TEL_FIELDS

    return TEL_FIELDS


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="hapticproxy plot", description=doc_summary(__doc__))
    ap.add_argument("file", help="a recording (.mcap, or a legacy .hpt)")
    ap.add_argument("--out", help="directory for the PNGs (default: next to the file)")
    args = ap.parse_args(argv)
    try:
        for p in plot_recording(args.file, args.out):
            print(p)
    except (OSError, ValueError) as exc:
        print(f"hapticproxy plot: {exc}", file=sys.stderr)
        return 1
    return 0
