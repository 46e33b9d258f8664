"""The paper's experiments, all on the real server loop: Figs. 6 and 9 (the 1-DOF peg: the
simulated 1-DOF device, direct coupling, the peg engine) and Figs. 14, 16 and 17 (the planar
testbed: the simulated planar device, the stub or pymunk engine).

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
from .harness import METHODS, RECOVERY_OFF, Hand, RunSpec, Trace, run

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
    felt_wall_sweep(out, quick=quick, log=log)
    return res


#: Fig. 14's felt wall against epsilon and approach speed (simulated time, the server's engine
#: contact frame, LM with epsilon; 0 = LM0): why the wall is felt beyond where it is
FELT_SWEEP_EPS_MM = (0.0, 5.0, 10.0, 15.0)
FELT_SWEEP_FORCE_N = (0.5, 0.1)


def felt_wall_sweep(out, *, quick: bool = False, log=None) -> dict:
    """Where the wall is felt as epsilon grows, for two pushes (approach speeds). A contact the
    engine reports only once the tool touches (``d <= 0``) reaches the model after the proxy
    went on for up to an engine period plus the engine tool's lag; the update rules then deform
    the proxy to just touch there (eq. 4) and keep that while it presses (eq. 5), so the wall is
    felt that much beyond. Predicted in time (epsilon above the travel per engine period) the
    contact is placed at its true geometry (eq. 6). Each row is run without deformation recovery
    (the paper's model: ``felt_wall_mm``) and with the server's default recovery
    (``recovered``). Writes ``felt_wall_sweep.json`` and ``fig14_felt_wall_vs_epsilon.png``;
    returns the rows."""
    out = Path(out)
    seeds = QUICK_SEEDS if quick else SEEDS[:5]
    eps_list = (0.0, 5.0, 10.0) if quick else FELT_SWEEP_EPS_MM
    forces = (0.5,) if quick else FELT_SWEEP_FORCE_N
    rows = []
    for f in forces:
        for e in eps_list:
            _log(log, f"fig14 felt-wall sweep: push {f:g} N, epsilon {e:g} mm")
            felt, first, speed, step_mm, recovered = [], [], [], [], []
            for seed in seeds:
                spec = fig14_spec("LM5", "simulated", True, seed=seed, contact_frame="engine").but(
                    method=f"LM{e:g}", epsilon_m=e / 1e3, policy="lm0" if e == 0 else "deformation",
                    hand=Hand("constant", (0.0, f, 0.0), start_s=HAND_START_S["simulated"]))
                recovered.append(M.static_contact_metrics(run(spec, "simulated"))["felt_wall_mm"])
                tr = run(spec.but(recovery=RECOVERY_OFF), "simulated")
                m = M.static_contact_metrics(tr)
                felt.append(m["felt_wall_mm"])
                first.append(m["first_contact_mm"] if m["first_contact_mm"] is not None else float("nan"))
                i = int(np.argmax(tr.contacts > 0))
                speed.append(float(tr.dev_vel[i, 1]))
                step_mm.append(float(tr.dev_vel[i, 1]) * 1e3 / max(tr.env_rate_hz, 1e-9))
            a = np.asarray(felt)
            rc = np.asarray(recovered)
            rows.append({"push_n": f, "epsilon_mm": e, "seeds": list(seeds),
                         "felt_wall_mm": {"min": round(float(a.min()), 2), "mean": round(float(a.mean()), 2),
                                          "max": round(float(a.max()), 2)},
                         "recovered": {"felt_wall_mm": {"min": round(float(rc.min()), 2), "mean": round(float(rc.mean()), 2),
                                                        "max": round(float(rc.max()), 2)},
                                       "wall_error_mm_mean": round(float(rc.mean()) - M.WALL_Y_MM, 2)},
                         "wall_error_mm_mean": round(float(a.mean()) - M.WALL_Y_MM, 2),
                         "first_contact_mm_mean": round(float(np.nanmean(first)), 2),
                         "approach_speed_m_per_s": round(float(np.mean(speed)), 3),
                         "travel_per_engine_step_mm": round(float(np.mean(step_mm)), 1)})
    res = {"set_up": "Fig. 14 (stub engine 30-60 Hz, k 4000, b 30, 512 Hz, four-channel, deformation, engine "
                     "contact frame), simulated time; epsilon 0 is LM0; felt_wall_mm without deformation recovery "
                     "(the paper's model), recovered: with the server's default recovery", "rows": rows}
    write_json(out / "felt_wall_sweep.json", res)
    plt = _plt()
    fig, ax = plt.subplots(figsize=(7, 4))
    for f in forces:
        rs = [r for r in rows if r["push_n"] == f]
        ax.errorbar([r["epsilon_mm"] for r in rs], [r["felt_wall_mm"]["mean"] for r in rs],
                    yerr=[[r["felt_wall_mm"]["mean"] - r["felt_wall_mm"]["min"] for r in rs],
                          [r["felt_wall_mm"]["max"] - r["felt_wall_mm"]["mean"] for r in rs]],
                    marker="o", capsize=3,
                    label=f"push {f:g} N: approach {rs[0]['approach_speed_m_per_s']:.2f} m/s, "
                          f"{rs[0]['travel_per_engine_step_mm']:.1f} mm per engine step")
        ax.plot([r["epsilon_mm"] for r in rs], [r["recovered"]["felt_wall_mm"]["mean"] for r in rs], ls=":",
                marker="s", label=f"push {f:g} N, with deformation recovery (the server's default)")
    ax.axhline(M.WALL_Y_MM, color="k", ls="--", lw=0.8, label="the wall (y_COM = 124 mm)")
    ax.set_xlabel("epsilon [mm]")
    ax.set_ylabel("felt wall [mm] (mean, min-max over seeds)")
    ax.set_title("Fig. 14: the wall is felt where it is once epsilon covers the travel per engine step", fontsize=9)
    ax.legend(fontsize=7.5)
    fig.tight_layout()
    out.mkdir(parents=True, exist_ok=True)
    fig.savefig(out / "fig14_felt_wall_vs_epsilon.png", dpi=90)
    plt.close(fig)
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
#: The paper's Fig. 6/9 simulation (its Fig. 5b): a 1 kg peg exactly fitting a hole, the hand
#: directly coupled (the device is the tool), K = 10000 N/m, B = 15 N s/m, a 20 ms environment
#: delay, 5 N sinusoidal hand force at 1 Hz (our choice: the paper's frequency is garbled).
#: On the real loop: the simulated 1-DOF device (1 kg, no damping: the peg's mass is the
#: device's, as in direct coupling) at 512 Hz, controller ``direct``; the 1-DOF peg engine
#: (``clients/peg_engine.py``) at 50 Hz over the real protocol; the 20 ms delay is a real one on
#: every client -> server datagram (an impairing UDP relay; a delayed queue in simulated time).
PEG_RATE_HZ = 512.0
PEG_ENV_HZ = 50.0
PEG_DELAY_S = 0.020
PEG_SECONDS = 20.0
PEG_QUICK_SECONDS = 8.0
#: a strong 1-DOF device (our choice): the peg's contact forces (K x 5 mm = 50 N) are rendered
#: uncapped in normal operation, so the caps do not hide an instability; a speed over 5 m/s trips
PEG_DEVICE = (("mass_kg", 1.0), ("damping_n_s_per_m", 0.0), ("max_force_n", 50.0), ("max_speed_m_per_s", 5.0))
PEG_SAFETY = (("max_force_n", 50.0), ("force_rate_n_per_s", 50000.0), ("max_speed_m_per_s", 5.0))
#: Unstable (1-DOF peg): the hand's excursion over the last quarter of the run exceeds 1.5x
#: that over the second quarter (it keeps growing), or exceeds 100 mm (ten peg widths), or the
#: safety layer had to fade the device out (a fault), or the model refused a non-finite step.
PEG_GROWTH_LIMIT = 1.5
PEG_RUNAWAY_MM = 100.0
#: A model-only run is stopped once the hand is this far from the hole (it has run away).
PEG_STOP_M = 1.0
#: fig6: the update policy; fig9: (policy, epsilon) per method. All direct coupling (Fig. 5b).
FIG6_POLICIES = ("rigid", "deformation")
FIG9_METHODS = {"IR": ("rigid", 0.0), "LM0": ("lm0", 0.0), "LM5": ("deformation", 0.005)}
#: the frames every peg figure is run in: the primary is the server's default
PEG_FRAMES = ("engine", "proxy")


def peg_spec(name: str, policy: str, epsilon_m: float, mode: str, quick: bool, *, contact_frame: str = "engine",
             layer: bool | None = None) -> RunSpec:
    """The 1-DOF peg; ``layer`` None: the rigid update (the paper's IR baseline) without the
    passivity layer (``harness.METHODS``), the others with the server's default; else as said."""
    if layer is None:
        layer_keys = (("enabled", False),) if policy == "rigid" else ()
    else:
        layer_keys = (("enabled", bool(layer)),)
    return RunSpec(method=name, controller="direct", policy=policy, epsilon_m=float(epsilon_m), passivity=layer_keys,
                   contact_frame=contact_frame, rate_hz=PEG_RATE_HZ, stiffness_n_per_m=10000.0,
                   damping_n_s_per_m=15.0, capacity=8, engine="peg1d", scene="peg1d",
                   env_rate_hz=(PEG_ENV_HZ, PEG_ENV_HZ), env_delay_s=PEG_DELAY_S,
                   hand=Hand("sinusoid", (5.0, 0.0, 0.0), 1.0, HAND_START_S[mode]),
                   seconds=PEG_QUICK_SECONDS if quick else PEG_SECONDS, workspace_m=0.25,
                   device=PEG_DEVICE, device_kind="1dof", safety=PEG_SAFETY)


class PegView:
    """A 1-DOF peg run as the peg metrics and plots read it: from the hand's start on, x = the
    device (= the tool, direct coupling) position [m], 0 = centred in the hole."""

    def __init__(self, *, policy, epsilon_m, t_s, x_hand_m, f_hand_n, f_env_n, contacts, updates, collisions,
                 nonfinite, faults=0, mode="simulated (model only)", extra=None) -> None:
        self.policy, self.epsilon_m = policy, epsilon_m
        self.t_s, self.x_hand_m, self.f_hand_n, self.f_env_n, self.contacts = t_s, x_hand_m, f_hand_n, f_env_n, contacts
        self.updates, self.collisions, self.nonfinite, self.faults, self.mode = updates, collisions, nonfinite, faults, mode
        self.extra = extra or {}

    @classmethod
    def of_trace(cls, tr: Trace) -> "PegView":
        sel = tr.t_s >= tr.hand_start_s
        t = tr.t_s[sel] - tr.hand_start_s
        model = tr.extra.get("model", {})
        extra = {"contact_frame": tr.spec.contact_frame, "controller": tr.spec.controller,
                 "saturated": tr.saturated, "rate_limited": tr.rate_limited,
                 "achieved_rate_hz": round(tr.achieved_rate_hz, 1), "env_rate_hz": round(tr.env_rate_hz, 1),
                 "env_delay_ms": tr.spec.env_delay_s * 1e3,
                 "max_command_n": round(float(np.max(np.abs(tr.cmd[sel, 0]))), 3)}
        if tr.mode == "realtime":
            extra["lateness_us"] = tr.lateness_us
        return cls(policy=tr.spec.policy, epsilon_m=tr.spec.epsilon_m, t_s=t, x_hand_m=tr.dev[sel, 0],
                   f_hand_n=tr.spec.hand.value(tr.t_s[sel])[:, 0], f_env_n=tr.env[sel, 0],
                   contacts=tr.contacts[sel], updates=int(tr.updates[-1]) - int(tr.updates[sel][0]),
                   collisions=model.get("collisions"), nonfinite=int(tr.model_nonfinite), faults=int(tr.faults),
                   mode=f"{tr.mode} (server loop, 1-DOF device, peg engine over UDP)" if tr.mode == "realtime"
                   else "simulated (server loop, 1-DOF device, peg engine over mem://)", extra=extra)

    @classmethod
    def of_model_run(cls, r) -> "PegView":
        return cls(policy=r.policy, epsilon_m=r.epsilon_m, t_s=r.t_s, x_hand_m=r.x_hand_m, f_hand_n=r.f_hand_n,
                   f_env_n=r.f_env_n, contacts=r.contacts, updates=r.updates, collisions=r.collisions,
                   nonfinite=r.nonfinite)


def peg_metrics(run_: PegView, duration_s: float) -> dict:
    """Metrics of a 1-DOF peg run (Figs. 6 and 9). x is the hand (= tool) position, 0 = the
    peg centred in the hole; positive penetrates the right wall. Time from the hand's start.

    - ``peak_excursion_mm``: max |x| over the run; ``excursion_last_mm``: over the last quarter.
    - ``growth``: max |x| over the last quarter / over the second quarter.
    - ``unstable``: growth > 1.5, or max |x| > 100 mm, or a safety fault, or a non-finite step
      (a model-only run whose hand went 1 m away is stopped there: ``stopped_at_s``).
    - ``both_walls_fraction``: fraction of haptic steps with both walls in the local model.
    - ``force_on_fraction``: fraction of steps with an environment force above 1 % of the hand
      force amplitude (the hole is felt); ``force_switches_per_s``: on/off transitions per s.
    - ``max_env_force_n``: the largest environment force (impulsive steps included), before
      the safety layer; ``max_command_n``: the largest force written to the device.
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
    unstable = bool(run_.nonfinite > 0 or run_.faults > 0 or not finite or stopped or growth > PEG_GROWTH_LIMIT
                    or peak > PEG_RUNAWAY_MM)
    out = {
        "mode": run_.mode,
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
        "faults": run_.faults,
    }
    out.update(run_.extra)
    return out


def _fin(v: float, nd: int = 3):
    """JSON-safe: huge values (a run-away simulation reaches 1e80) are kept as they are, in
    scientific notation; infinities and NaN become strings."""
    if not math.isfinite(v):
        return str(v)
    return float(f"{v:.{nd + 3}g}") if abs(v) >= 1e6 else round(v, nd)


def _peg_figure(name: str, cases: dict, out, *, mode: str, quick: bool, log=None) -> tuple[dict, dict]:
    """Run every case ``name -> (policy, epsilon)`` on the server loop in each contact frame (and,
    in real time, once more in simulated time), plus the local model alone; metrics and views."""
    from .peg1d import simulate_peg1d

    secs = PEG_QUICK_SECONDS if quick else PEG_SECONDS
    res: dict = {}
    views: dict = {}
    for case, (pol, eps) in cases.items():
        entry: dict = {}
        for frame in PEG_FRAMES:
            _log(log, f"{name} {case} ({frame} frame, {mode})")
            v = PegView.of_trace(run(peg_spec(case, pol, eps, mode, quick, contact_frame=frame), mode))
            m = peg_metrics(v, secs)
            views[(frame, case)] = v
            if frame == PEG_FRAMES[0]:
                entry.update(m)
            else:
                entry[f"{frame}_frame"] = m
        if mode == "realtime":
            entry["simulated"] = peg_metrics(PegView.of_trace(run(peg_spec(case, pol, eps, "simulated", quick), "simulated")), secs)
        mo = simulate_peg1d(pol, duration_s=secs, haptic_hz=PEG_RATE_HZ, epsilon_m=eps,
                            runaway_m=PEG_STOP_M)
        entry["model_only"] = peg_metrics(PegView.of_model_run(mo), secs)
        res[case] = entry
    return res, views


def fig6(out, *, mode: str = "realtime", quick: bool = False, log=None) -> dict:
    """Proxy deformation and stability (paper Fig. 6): 1-DOF peg, active geometry (epsilon 0),
    direct coupling; ``rigid`` (no deformation) vs ``deformation``; on the server loop."""
    out = Path(out)
    res, views = _peg_figure("fig6", {p: (p, 0.0) for p in FIG6_POLICIES}, out, mode=mode, quick=quick, log=log)
    # the rigid update once more with the passivity layer on: the runaway is what it stops
    _log(log, f"fig6 rigid with the passivity layer ({mode})")
    res["rigid"]["with_layer"] = peg_metrics(PegView.of_trace(run(peg_spec("rigid", "rigid", 0.0, mode, quick, layer=True),
                                                                   mode)), PEG_QUICK_SECONDS if quick else PEG_SECONDS)
    plot_peg({p: views[("engine", p)] for p in FIG6_POLICIES}, res, out / "fig6.png", f"Fig. 6 (reproduction, server loop, {mode}): 1-DOF peg 1 kg, direct coupling,\n"
             "50 Hz engine + 20 ms delay, K = 10000 N/m, B = 15 N s/m, 5 N at 1 Hz, 512 Hz, active geometry", force=False)
    write_json(out / "metrics.json", res)
    return res


def fig9(out, *, mode: str = "realtime", quick: bool = False, log=None) -> dict:
    """Epsilon-active geometry and the tight hole (paper Fig. 9): 1-DOF peg, direct coupling,
    IR (no deformation, epsilon 0), LM0 (deformation, active geometry), LM5 (epsilon 5 mm)."""
    out = Path(out)
    res, views = _peg_figure("fig9", FIG9_METHODS, out, mode=mode, quick=quick, log=log)
    plot_peg({m: views[("engine", m)] for m in ("LM0", "LM5")}, res, out / "fig9.png",
             f"Fig. 9 (reproduction, server loop, {mode}): 1-DOF peg with proxy deformation,\n"
             "active geometry (LM0) vs epsilon = 5 mm (LM5); 50 Hz engine + 20 ms delay, direct coupling", force=True)
    plot_peg({m: views[("proxy", m)] for m in ("LM0", "LM5")}, {m: res[m]["proxy_frame"] for m in res},
             out / "fig9_proxy_frame.png", f"Fig. 9 with the contacts in the proxy frame (eq. 1 at the proxy's "
             f"current pose), server loop, {mode}:\nthe delayed separations ratchet the walls", force=True)
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
        pk = float(np.max(np.abs(x[sel]))) if np.all(np.isfinite(x[sel])) else 300.0
        lim = 25.0 if pk < 25.0 else min(300.0, 1.1 * pk)
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


# --------------------------------------------------------------- the paper's eq. 6, literally
#: The reading of eq. 6 that gives the paper's Fig. 14 numbers (``RunSpec.reading``; an
#: experiments option, never a server setting): the epsilon-inflated tool rendered, new contacts
#: placed by eq. 6 too. Run without deformation recovery (the paper's model) in both readings.
LITERAL_PUSHES_N = (0.1, 0.5)


def paper_literal(out, *, quick: bool = False, log=None) -> dict:
    """``hapticproxy experiment literal``: Fig. 14 (0.1 and 0.5 N; IR, LM0, LM5; both contact
    frames) and Figs. 16/17 (LM0, LM5) in simulated time over seeds, with the notes' reading of
    the update rules (the server's) and with eq. 6 read literally. Writes ``literal.json`` and
    ``literal.md``; returns the rows."""
    out = Path(out)
    seeds = QUICK_SEEDS if quick else SEEDS[:5]
    rows = []
    for frame in (("proxy",) if quick else ("proxy", "engine")):
        for push in ((0.1,) if quick else LITERAL_PUSHES_N):
            for m in METHODS:
                for reading in ("", "paper-literal"):
                    if m == "IR" and reading:
                        continue                     # the IR never deforms: both readings are eq. 1
                    _log(log, f"literal: fig14 {m} push {push:g} N, {frame} frame, {reading or 'notes'}")
                    specs = [fig14_spec(m, "simulated", quick, seed=s, contact_frame=frame, recovery=RECOVERY_OFF,
                                        reading=reading).but(hand=Hand("constant", (0.0, push, 0.0),
                                                                       start_s=HAND_START_S["simulated"]))
                             for s in seeds]
                    st = _seed_stats(specs, M.static_contact_metrics,
                                     ("felt_wall_mm", "limit_cycle_amplitude_mm", "settled"))
                    rows.append({"figure": "fig14", "method": m, "reading": reading or "notes", "contact_frame": frame,
                                 "push_n": push, **{k: st[k] for k in ("seeds", "felt_wall_mm",
                                                                        "limit_cycle_amplitude_mm", "settled")}})
    for stiff in ((False,) if quick else (False, True)):
        for m in ("LM0", "LM5"):
            for reading in ("", "paper-literal"):
                name = "fig17" if stiff else "fig16"
                _log(log, f"literal: {name} {m} {reading or 'notes'}")
                specs = [hole_spec(m, "simulated", quick, stiff=stiff, seed=s, recovery=RECOVERY_OFF, reading=reading)
                         for s in seeds]
                st = _seed_stats(specs, M.hole_metrics, ("drift_mm", "rotation_deg", "unstable"))
                rows.append({"figure": name, "method": m, "reading": reading or "notes", "contact_frame": "proxy",
                             **{k: st[k] for k in ("seeds", "drift_mm", "rotation_deg", "unstable")}})
    res = {"set_up": "simulated time, stub 30-60 Hz, 512 Hz, no deformation recovery; notes: the server's reading of "
                     "eqs. 4/5/6; paper-literal: eq. 6 read literally (the epsilon-inflated tool rendered, new "
                     "contacts by eq. 6)", "rows": rows}
    write_json(out / "literal.json", res)
    (out / "literal.md").write_text(literal_md(rows) + "\n")
    return res


def _mm(s: dict) -> str:
    return f"{s['min']:.1f} / {s['mean']:.1f} / {s['max']:.1f}"


def literal_md(rows: list[dict]) -> str:
    lines = ["| figure | method | frame | push (N) | reading | felt wall (mm) min / mean / max | settled | cycle max (mm) |",
             "| --- | --- | --- | ---: | --- | ---: | ---: | ---: |"]
    for r in rows:
        if r["figure"] == "fig14":
            lines.append(f"| 14 | {r['method']} | {r['contact_frame']} | {r['push_n']:g} | {r['reading']} | "
                         f"{_mm(r['felt_wall_mm'])} | {r['settled']['true']}/{r['settled']['of']} | "
                         f"{r['limit_cycle_amplitude_mm']['max']:.1f} |")
    lines += ["", "| figure | method | reading | drift (mm) min / mean / max | rotation max (deg) | unstable |",
              "| --- | --- | --- | ---: | ---: | ---: |"]
    for r in rows:
        if r["figure"] != "fig14":
            d = r["drift_mm"]
            drift = _mm(d) if d["max"] < 1e4 else f"{d['min']:.1f} / - / {d['max']:.3g}"
            lines.append(f"| {r['figure'][3:]} | {r['method']} | {r['reading']} | {drift} | "
                         f"{r['rotation_deg']['max']:.3g} | {r['unstable']['true']}/{r['unstable']['of']} |")
    return "\n".join(lines)
