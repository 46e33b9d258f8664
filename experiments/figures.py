"""The paper's experiments: Figs. 6 and 9 (the 1-DOF peg, on the local model alone, as the
paper's own simulations) and Figs. 14, 16 and 17 (the planar testbed on the real server loop).

Each ``figN(out, mode=..., quick=...)`` runs the figure's methods, writes PNG plots like the
paper's figure and ``metrics.json`` (an object keyed by method) into ``out``, and returns the
metrics. Set-ups (the paper's, and this project's choices where the paper gives none):

- Fig. 14: the peg starts at rest at the origin of the Fig. 12 testbed; the hand pushes with
  F = (0, 0.5 N, 0) towards the bottom wall (met at y_COM = 124 mm); k = 4000 N/m,
  b = 30 N s/m, e = 0; haptic 512 Hz; the stub engine (Vortex-style, 30-60 Hz, variable).
- Fig. 16: the peg rotated 90 deg rests in the exactly fitting bottom hole; the hand shakes it
  with F = (1 N sin(5 pi t), 0, 0) (2.5 Hz); k = 4000, b = 30.
- Fig. 17: as Fig. 16 with k = 15000 N/m, b = 100 N s/m, 3 N. The paper runs only LM0 and LM5
  (the IR is unstable there); we run the IR too, to measure that.
- Methods: IR (direct coupling, no deformation, epsilon 0), LM0 (four-channel, deformation,
  epsilon 0), LM5 (the same, epsilon 5 mm). Contact frame: ``proxy`` (the paper's eq. 1) for
  the reproductions; Fig. 14 also reports this project's ``engine`` frame.

Modes: ``realtime`` (the real server process at 512 Hz, the client over UDP on 127.0.0.1; one
trial per method, as in the paper) and ``simulated`` (the same stack in simulated time,
deterministic). In real-time mode every method is also run in simulated time over several
engine seeds (the environment's variable step makes a single trial a dice roll), reported
under ``"simulated_seeds"`` with min / mean / max.
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from . import metrics as M
from .harness import METHODS, Hand, RunSpec, Trace, run

COLORS = {"IR": "tab:red", "LM0": "tab:blue", "LM5": "tab:green"}
#: device time at which the hand starts: after the session engaged and the force ramped in
HAND_START_S = {"realtime": 1.5, "simulated": 0.6}
SEEDS = tuple(range(1, 11))
QUICK_SEEDS = (1, 2)


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def write_json(path: Path, obj) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(obj, indent=1, sort_keys=False, default=_json_default) + "\n")


def _json_default(o):
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, (np.floating,)):
        return float(o)
    if isinstance(o, np.bool_):
        return bool(o)
    raise TypeError(f"not JSON serialisable: {type(o)}")


def _seed_stats(specs: list[RunSpec], fn, keys: tuple[str, ...]) -> dict:
    """Run ``specs`` in simulated time; min / mean / max of ``keys`` (booleans: how many true)."""
    vals: dict[str, list] = {k: [] for k in keys}
    for s in specs:
        m = fn(run(s, "simulated"))
        for k in keys:
            vals[k].append(m[k])
    out: dict = {"seeds": [s.seed for s in specs], "mode": "simulated"}
    for k, v in vals.items():
        if v and isinstance(v[0], bool):
            out[k] = {"true": int(sum(v)), "of": len(v)}
        else:
            a = np.asarray(v, dtype=float)
            out[k] = {"min": round(float(a.min()), 3), "mean": round(float(a.mean()), 3), "max": round(float(a.max()), 3)}
    return out


def _log(log, msg):
    if log:
        log(msg)


# ---------------------------------------------------------------------------------- Fig. 14
def fig14_spec(method: str, mode: str, quick: bool, **kw) -> RunSpec:
    return RunSpec.for_method(method, scene="testbed", hand=Hand("constant", (0.0, 0.5, 0.0), start_s=HAND_START_S[mode]),
                              seconds=4.5 if quick else 6.0, stiffness_n_per_m=4000.0, damping_n_s_per_m=30.0,
                              rate_hz=512.0, **kw)


def fig14(out, *, mode: str = "realtime", quick: bool = False, log=None) -> dict:
    """Static contact: where the wall is felt, settling vs limit cycle (paper Fig. 14)."""
    out = Path(out)
    variants = [("proxy", "stub"), ("engine", "stub")] + ([] if quick else [("proxy", "pymunk"), ("engine", "pymunk")])
    traces: dict[tuple, Trace] = {}
    for frame, engine in variants:
        for m in METHODS:
            spec = fig14_spec(m, mode, quick, contact_frame=frame, engine=engine,
                              env_rate_hz=(30.0, 60.0) if engine == "stub" else (60.0, 60.0))
            _log(log, f"fig14 {m} ({engine}, {frame} frame, {mode})")
            traces[(frame, engine, m)] = run(spec, mode)
    res: dict = {}
    for m in METHODS:
        entry = M.static_contact_metrics(traces[("proxy", "stub", m)])
        entry["engine_frame"] = M.static_contact_metrics(traces[("engine", "stub", m)])
        if not quick:
            entry["pymunk"] = M.static_contact_metrics(traces[("proxy", "pymunk", m)])
            entry["pymunk_engine_frame"] = M.static_contact_metrics(traces[("engine", "pymunk", m)])
        if mode == "realtime":
            seeds = QUICK_SEEDS if quick else SEEDS
            keys = ("felt_wall_mm", "limit_cycle_amplitude_mm", "limit_cycle_rotation_deg", "settled")
            entry["simulated_seeds"] = _seed_stats(
                [fig14_spec(m, "simulated", quick, seed=s) for s in seeds], M.static_contact_metrics, keys)
            entry["simulated_seeds_engine_frame"] = _seed_stats(
                [fig14_spec(m, "simulated", quick, seed=s, contact_frame="engine") for s in seeds],
                M.static_contact_metrics, keys)
        res[m] = entry
    plot_fig14({m: traces[("proxy", "stub", m)] for m in METHODS}, res, out / "fig14.png",
               "Fig. 14 (reproduction): static contact, stub engine 30-60 Hz, paper's eq. 1 (proxy frame)")
    plot_fig14({m: traces[("engine", "stub", m)] for m in METHODS}, {m: res[m]["engine_frame"] for m in METHODS},
               out / "fig14_engine_frame.png", "Fig. 14, this project's engine contact frame, stub engine 30-60 Hz")
    if not quick:
        plot_fig14({m: traces[("proxy", "pymunk", m)] for m in METHODS}, {m: res[m]["pymunk"] for m in METHODS},
                   out / "fig14_pymunk.png", "Fig. 14, pymunk testbed 60 Hz, paper's eq. 1 (proxy frame)")
    write_json(out / "metrics.json", res)
    return res


def plot_fig14(traces: dict[str, Trace], res: dict, path: Path, title: str) -> None:
    plt = _plt()
    fig, axes = plt.subplots(3, 1, figsize=(8.5, 9.5), sharex=True)
    for m, tr in traces.items():
        t = tr.t_s - tr.hand_start_s
        r = res[m] if "felt_wall_mm" in res[m] else res[m]
        lab = f"{m}: felt at {r['felt_wall_mm']:.1f} mm, cycle {r['limit_cycle_amplitude_mm']:.2f} mm / {r['limit_cycle_rotation_deg']:.2f} deg"
        axes[0].plot(t, tr.dev[:, 1] * 1e3, color=COLORS[m], lw=1.0, label=lab)
        axes[1].plot(t, tr.dev[:, 1] * 1e3, color=COLORS[m], lw=1.0)
        axes[2].plot(t, np.degrees(tr.dev[:, 2]), color=COLORS[m], lw=1.0)
    for ax in axes[:2]:
        ax.axhline(M.WALL_Y_MM, color="k", lw=0.8, ls="--")
    axes[0].set_ylabel("device y_COM [mm]")
    axes[0].set_title("(a) device trajectory towards the wall (dashed: the wall, y_COM = 124 mm)", fontsize=9)
    axes[0].legend(fontsize=7.5, loc="lower right")
    axes[1].set_ylim(M.WALL_Y_MM - 30, M.WALL_Y_MM + 15)
    axes[1].set_ylabel("device y_COM [mm]")
    axes[1].set_title("(b) at the wall: settling (LM) or a limit cycle", fontsize=9)
    lo, hi = axes[2].get_ylim()
    axes[2].set_ylim(min(lo, -1.0), max(hi, 1.0))
    axes[2].set_ylabel("device angle [deg]")
    axes[2].set_xlabel("time since the hand started pushing [s]")
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)


# ---------------------------------------------------------------------------- Figs. 16, 17
def hole_spec(method: str, mode: str, quick: bool, *, stiff: bool, **kw) -> RunSpec:
    k, b, amp = (15000.0, 100.0, 3.0) if stiff else (4000.0, 30.0, 1.0)
    secs = (6.0 if quick else 10.0) if stiff else 6.0
    return RunSpec.for_method(method, scene="hole", hand=Hand("sinusoid", (amp, 0.0, 0.0), 2.5, HAND_START_S[mode]),
                              seconds=secs, stiffness_n_per_m=k, damping_n_s_per_m=b, rate_hz=512.0, **kw)


def _hole_figure(name: str, out, *, mode: str, quick: bool, stiff: bool, log=None) -> dict:
    out = Path(out)
    traces = {}
    for m in METHODS:
        _log(log, f"{name} {m} ({mode})")
        traces[m] = run(hole_spec(m, mode, quick, stiff=stiff), mode)
    res = {}
    for m, tr in traces.items():
        entry = M.hole_metrics(tr)
        if mode == "realtime":
            seeds = QUICK_SEEDS if quick else SEEDS
            entry["simulated_seeds"] = _seed_stats(
                [hole_spec(m, "simulated", quick, stiff=stiff, seed=s) for s in seeds], M.hole_metrics,
                ("drift_mm", "x_travel_mm", "rotation_deg", "energy_growth", "unstable"))
        res[m] = entry
    k = traces["IR"].spec.stiffness_n_per_m
    amp = traces["IR"].spec.hand.wrench[0]
    plot_hole(traces, res, out / f"{name}.png",
              f"{'Fig. 17' if stiff else 'Fig. 16'} (reproduction): peg in the tight hole, k = {k:g} N/m, "
              f"F = {amp:g} N sin(5 pi t), stub engine 30-60 Hz, 512 Hz")
    write_json(out / "metrics.json", res)
    return res


def fig16(out, *, mode: str = "realtime", quick: bool = False, log=None) -> dict:
    """Tight virtual space, k = 4000 N/m: drift and rotation in the hole (paper Fig. 16)."""
    return _hole_figure("fig16", out, mode=mode, quick=quick, stiff=False, log=log)


def fig17(out, *, mode: str = "realtime", quick: bool = False, log=None) -> dict:
    """The same at k = 15000 N/m, b = 100, 3 N: stable or not (paper Fig. 17)."""
    return _hole_figure("fig17", out, mode=mode, quick=quick, stiff=True, log=log)


def plot_hole(traces: dict[str, Trace], res: dict, path: Path, title: str) -> None:
    plt = _plt()
    fig = plt.figure(figsize=(11, 8))
    gs = fig.add_gridspec(3, 2, width_ratios=(1, 1.6))
    ax_xy = fig.add_subplot(gs[:, 0])
    ax_x = fig.add_subplot(gs[0, 1])
    ax_y = fig.add_subplot(gs[1, 1], sharex=ax_x)
    ax_th = fig.add_subplot(gs[2, 1], sharex=ax_x)
    for m, tr in traces.items():
        t = tr.t_s - tr.hand_start_s
        sel = t >= 0
        x = tr.dev[:, 0] * 1e3
        y = tr.dev[:, 1] * 1e3
        th = np.degrees(tr.dev[:, 2]) - M.HOLE_DEG
        r = res[m]
        lab = (f"{m}: drift {r['drift_mm']:.1f} mm, rot {r['rotation_deg']:.1f} deg"
               f"{', UNSTABLE' if r['unstable'] else ''}")
        ax_xy.plot(x[sel], y[sel], color=COLORS[m], lw=0.8, label=lab)
        ax_x.plot(t, x, color=COLORS[m], lw=0.8)
        ax_y.plot(t, y, color=COLORS[m], lw=0.8)
        ax_th.plot(t, th, color=COLORS[m], lw=0.8)
    ax_xy.plot([M.HOLE_X_MM], [M.HOLE_Y_MM], "k+", ms=14, mew=1.5, label="the peg's COM in the hole (0, 134 mm)")
    ax_xy.set_xlabel("device x [mm]")
    ax_xy.set_ylabel("device y_COM [mm] (down = deeper)")
    ax_xy.set_title("(a) device path in the plane", fontsize=9)
    ax_xy.legend(fontsize=7, loc="upper left")
    ext = max(max(float(np.max(np.abs(tr.dev[:, 0] * 1e3 - M.HOLE_X_MM))),
                  float(np.max(np.abs(tr.dev[:, 1] * 1e3 - M.HOLE_Y_MM)))) for tr in traces.values())
    lim = max(3.0, min(80.0, 1.25 * ext))
    ax_xy.set_xlim(M.HOLE_X_MM - lim, M.HOLE_X_MM + lim)
    ax_xy.set_ylim(M.HOLE_Y_MM + lim, M.HOLE_Y_MM - lim)  # +y (deeper) downwards, as in Fig. 12
    ax_x.set_ylabel("x [mm]")
    ax_y.set_ylabel("y_COM [mm]")
    ax_th.set_ylabel("angle - 90 [deg]")
    ax_th.set_xlabel("time since the hand started [s]")
    ax_x.set_title("(b) device x, y and rotation", fontsize=9)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)


# ------------------------------------------------------------------------------ Figs. 6, 9
#: The paper's Fig. 6/9 simulation: 1 kg peg, 20 ms delay, K 10000, B 15, 5 N at 1 Hz (our
#: choice: the paper's frequency is garbled); the same 512 Hz as the other experiments.
PEG_RATE_HZ = 512.0
PEG_SECONDS = 20.0
PEG_QUICK_SECONDS = 8.0
#: Unstable (1-DOF peg): the hand's excursion over the last quarter of the run exceeds 1.5x
#: that over the second quarter (it keeps growing), or exceeds 100 mm (ten peg widths), or the
#: model refused a non-finite step.
PEG_GROWTH_LIMIT = 1.5
PEG_RUNAWAY_MM = 100.0


#: A run is stopped once the hand is this far from the hole (it has run away; see peg1d).
PEG_STOP_M = 1.0


def peg_metrics(run_, duration_s: float) -> dict:
    """Metrics of a 1-DOF peg run (Figs. 6 and 9). x is the hand (= proxy) position, 0 = the
    peg centred in the hole; positive penetrates the right wall.

    - ``peak_excursion_mm``: max |x| over the run; ``excursion_last_mm``: over the last quarter.
    - ``growth``: max |x| over the last quarter / over the second quarter.
    - ``unstable``: growth > 1.5, or max |x| > 100 mm, or a non-finite step (a run whose hand
      went 1 m away is stopped there: ``stopped_at_s``; ``growth`` is then not computed).
    - ``both_walls_fraction``: fraction of haptic steps with both walls in the local model.
    - ``force_on_fraction``: fraction of steps with an environment force above 1 % of the hand
      force amplitude (the hole is felt); ``force_switches_per_s``: on/off transitions per s.
    - ``max_env_force_n``: the largest environment force (impulsive steps included).
    """
    t = run_.t_s
    T = float(duration_s)
    x = np.abs(run_.x_hand_m) * 1e3
    stopped = float(t[-1]) < T - 2 * (t[1] - t[0])
    q2 = (t >= T / 4) & (t < T / 2)
    q4 = t >= 3 * T / 4
    if stopped or not np.any(q2) or not np.any(q4):
        e2 = e4 = growth = float("nan")
    else:
        e2 = float(np.max(x[q2]))
        e4 = float(np.max(x[q4]))
        growth = e4 / e2 if e2 > 0 else (float("inf") if e4 > 0 else 1.0)
    peak = float(np.max(x))
    on = np.abs(run_.f_env_n) > 0.01 * max(1e-9, float(np.max(np.abs(run_.f_hand_n))))
    finite = bool(np.all(np.isfinite(run_.x_hand_m)))
    unstable = bool(run_.nonfinite > 0 or not finite or stopped or growth > PEG_GROWTH_LIMIT or peak > PEG_RUNAWAY_MM)
    return {
        "mode": "simulated (model only)",
        "policy": run_.policy,
        "epsilon_mm": run_.epsilon_m * 1e3,
        "peak_excursion_mm": _fin(peak),
        "excursion_last_mm": _fin(e4),
        "growth": _fin(growth),
        "unstable": unstable,
        "both_walls_fraction": round(float(np.mean(run_.contacts == 2)), 4),
        "force_on_fraction": round(float(np.mean(on)), 4),
        "force_switches_per_s": round(float(np.count_nonzero(np.diff(on.astype(np.int8)))) / T, 2),
        "max_env_force_n": _fin(float(np.max(np.abs(run_.f_env_n)))),
        "stopped_at_s": round(float(t[-1]), 3) if stopped else None,
        "model_updates": run_.updates,
        "collisions": run_.collisions,
        "nonfinite": run_.nonfinite,
    }


def _fin(v: float, nd: int = 3):
    """JSON-safe: huge values (a run-away simulation reaches 1e80) are kept as they are, in
    scientific notation; infinities and NaN become strings."""
    if not math.isfinite(v):
        return str(v)
    return float(f"{v:.{nd + 3}g}") if abs(v) >= 1e6 else round(v, nd)


def fig6(out, *, quick: bool = False, log=None, **_) -> dict:
    """Proxy deformation and stability (paper Fig. 6): 1-DOF peg, active geometry (epsilon 0),
    direct coupling; ``rigid`` (no deformation) vs ``deformation``."""
    from .peg1d import simulate_peg1d

    out = Path(out)
    secs = PEG_QUICK_SECONDS if quick else PEG_SECONDS
    runs = {}
    for pol in ("rigid", "deformation"):
        _log(log, f"fig6 {pol}")
        runs[pol] = simulate_peg1d(pol, duration_s=secs, haptic_hz=PEG_RATE_HZ, epsilon_m=0.0, runaway_m=PEG_STOP_M)
    res = {pol: peg_metrics(r, secs) for pol, r in runs.items()}
    # also: both walls always reported (a complete local geometry), as in the model's own tests
    for pol in ("rigid", "deformation"):
        res[pol]["both_walls_reported"] = peg_metrics(
            simulate_peg1d(pol, duration_s=secs, haptic_hz=PEG_RATE_HZ, epsilon_m=None, runaway_m=PEG_STOP_M), secs)
    plot_peg(runs, res, out / "fig6.png", "Fig. 6 (reproduction): 1-DOF peg, 1 kg, 20 ms delay, K = 10000 N/m, "
             "B = 15 N s/m, 5 N at 1 Hz, 512 Hz, active geometry", force=False)
    write_json(out / "metrics.json", res)
    return res


def fig9(out, *, quick: bool = False, log=None, **_) -> dict:
    """Epsilon-active geometry and the tight hole (paper Fig. 9): 1-DOF peg with proxy
    deformation, active geometry (LM0) vs epsilon = 5 mm (LM5); the IR (no deformation,
    epsilon 0) for reference."""
    from .peg1d import simulate_peg1d

    out = Path(out)
    secs = PEG_QUICK_SECONDS if quick else PEG_SECONDS
    cases = {"IR": ("rigid", 0.0), "LM0": ("deformation", 0.0), "LM5": ("deformation", 0.005)}
    runs = {}
    for m, (pol, eps) in cases.items():
        _log(log, f"fig9 {m}")
        runs[m] = simulate_peg1d(pol, duration_s=secs, haptic_hz=PEG_RATE_HZ, epsilon_m=eps, runaway_m=PEG_STOP_M)
    res = {m: peg_metrics(r, secs) for m, r in runs.items()}
    plot_peg({m: runs[m] for m in ("LM0", "LM5")}, res, out / "fig9.png",
             "Fig. 9 (reproduction): 1-DOF peg with proxy deformation, active (LM0) vs epsilon = 5 mm (LM5)", force=True)
    write_json(out / "metrics.json", res)
    return res


def plot_peg(runs: dict, res: dict, path: Path, title: str, force: bool) -> None:
    plt = _plt()
    nrow = 3 if force else 1
    fig, axes = plt.subplots(nrow, len(runs), figsize=(5.2 * len(runs), 2.8 * nrow + 0.6), squeeze=False, sharex=True)
    for j, (name, r) in enumerate(runs.items()):
        m = res[name]
        t = r.t_s
        sel = t <= min(t[-1], 8.0)
        x = r.x_hand_m * 1e3
        lim = 25.0
        ax = axes[0, j]
        ax.plot(t[sel], np.clip(x[sel], -lim, lim), lw=0.7)
        ax.axhline(0, color="k", lw=0.5)
        ax.set_ylim(-lim, lim)
        ax.set_ylabel("hand x [mm]")
        ax.set_title(f"{name}: {'UNSTABLE' if m['unstable'] else 'bounded'}, peak |x| "
                     f"{m['peak_excursion_mm'] if isinstance(m['peak_excursion_mm'], str) else format(m['peak_excursion_mm'], '.3g')} mm",
                     fontsize=9)
        if force:
            ax = axes[1, j]
            ax.step(t[sel], r.contacts[sel], where="post", lw=0.7)
            ax.set_ylim(-0.2, 2.2)
            ax.set_ylabel("walls in the model")
            ax.set_title(f"both walls {100 * m['both_walls_fraction']:.0f} % of the time", fontsize=9)
            ax = axes[2, j]
            ax.plot(t[sel], np.clip(r.f_env_n[sel], -30, 30), lw=0.7)
            ax.set_ylabel("environment force [N]")
            ax.set_title(f"force on {100 * m['force_on_fraction']:.0f} % of the time, "
                         f"{m['force_switches_per_s']:.1f} on/off per s", fontsize=9)
        axes[-1, j].set_xlabel("time [s]")
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)


FIGURES = {"fig6": fig6, "fig9": fig9, "fig14": fig14, "fig16": fig16, "fig17": fig17}
