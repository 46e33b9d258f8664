"""``hapticproxy experiment fidelity``: is the surface felt where it is, with any engine? (issue 15)

The felt-surface error (``metrics.felt_surface_metrics``: the device at rest minus the true
surface, beyond the penetration the push needs) before and after this project's additions to the
paper's model, on the whole server loop in simulated time (``harness.run_simulated``), with an
engine tool that lags the proxy by 0, 20 and 40 ms more than it does by itself (every
ProxyState reaches the engine that much later), over several engine seeds:

- ``wall``: the Fig. 14 push at 0.1, 0.5 and 1 N (approach at about 0.1, 0.4 and 0.8 m/s) onto
  the testbed's bottom wall (the stub engine at 30-60 Hz, k = 4000 N/m, b = 30 N s/m, 512 Hz,
  four-channel, the engine contact frame);
- ``peg``: the 1-DOF peg of Figs. 6/9 shaken by 5 N at 1 Hz in its exactly fitting hole (50 Hz
  engine, 20 ms delay, direct coupling): the hole is felt ``peak |x| - 5 N / K`` wider than it
  is (``peg_error_mm``);
- ``box``: a spatial box pushed onto a floor and onto a wall (pybullet at 60 Hz through its
  Engine interface, the simulated spatial device; ``spatial_rows``).

Configurations (``CONFIGS``): ``paper`` (no recovery, the epsilon the method asks for, the
engine follows the proxy as it is told), ``recovery`` (the server's deformation recovery),
``predicted`` (recovery off, the server tells the engine the epsilon to use next, up to a
granted 40 mm), ``all`` (recovery + predicted epsilon + the lead the engine extrapolates by).
Methods: LM0 (epsilon 0: nothing to predict) and LM5 (epsilon 5 mm asked; the predicted
configurations grant up to ``PREDICTED_CAP_M``).

Writes ``fidelity.json`` (every row) and ``fidelity.md`` (the tables).
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from . import figures as F
from . import metrics as M
from .harness import RECOVERY_OFF, Hand, run_simulated

LAGS_S = (0.0, 0.020, 0.040)
PUSHES_N = (0.1, 0.5, 1.0)
SEEDS = (1, 2, 3, 4, 5)
QUICK_SEEDS = (1, 2)
#: the epsilon the predicted configurations may grant (the prediction keeps it small when slow)
PREDICTED_CAP_M = 0.040
#: name -> RunSpec changes (LM0 takes only the recovery: with epsilon 0 there is nothing to predict
#: or lead)
CONFIGS = {
    "paper": {"recovery": RECOVERY_OFF},
    "recovery": {},
    "predicted": {"recovery": RECOVERY_OFF, "predict_epsilon": True, "epsilon_m": PREDICTED_CAP_M},
    "all": {"predict_epsilon": True, "lead": True, "epsilon_m": PREDICTED_CAP_M},
}
LM0_CONFIGS = ("paper", "recovery")
WALL_SECONDS = 5.0


def wall_spec(method: str, config: str, push_n: float, lag_s: float, seed: int):
    kw = dict(CONFIGS[config])
    if method == "LM0":
        kw.pop("predict_epsilon", None)
        kw.pop("lead", None)
        kw.pop("epsilon_m", None)
    return F.fig14_spec(method, "simulated", False, seed=seed, contact_frame="engine").but(
        hand=Hand("constant", (0.0, push_n, 0.0), start_s=F.HAND_START_S["simulated"]), seconds=WALL_SECONDS,
        tool_lag_s=lag_s, **kw)


def _agg(vals: list[float]) -> dict:
    a = np.asarray(vals, dtype=float)
    fin = a[np.isfinite(a)]
    return {"mean": round(float(np.mean(fin)), 3) if len(fin) else "inf",
            "max": round(float(np.max(a)), 3) if np.all(np.isfinite(a)) else "inf"}


def wall_rows(*, seeds=SEEDS, pushes=PUSHES_N, lags=LAGS_S, log=None) -> list[dict]:
    rows = []
    for method in ("LM0", "LM5"):
        for config in (LM0_CONFIGS if method == "LM0" else tuple(CONFIGS)):
            for push in pushes:
                for lag in lags:
                    if log:
                        log(f"fidelity: wall {method} {config} push {push:g} N lag {lag * 1e3:g} ms")
                    err, reached, fstep, pstep, energy, eps, lead, first, settled = [], [], [], [], [], [], [], [], []
                    for seed in seeds:
                        tr = run_simulated(wall_spec(method, config, push, lag, seed))
                        f = M.felt_surface_metrics(tr, surface_m=M.WALL_Y_MM / 1e3, axis=1, push_n=push)
                        s = M.static_contact_metrics(tr)
                        err.append(abs(f["surface_error_mm"]))
                        reached.append(float(f["surface_reached_s"]))
                        fstep.append(s["force_step_max_n"])
                        pstep.append(f["recovery_force_step_max_n"])
                        energy.append(f["recovery_energy_mj"])
                        first.append(s["first_contact_mm"] - M.WALL_Y_MM if s["first_contact_mm"] is not None else math.nan)
                        settled.append(s["settled"])
                        adv = tr.extra.get("advice")
                        if adv:
                            eps.append(adv["epsilon_mm"][1])
                            lead.append(adv["lead_ms"])
                    rows.append({
                        "scenario": "wall", "method": method, "config": config, "push_n": push, "lag_ms": lag * 1e3,
                        "seeds": list(seeds),
                        "surface_error_mm": _agg(err),
                        "within_0_5_mm": int(sum(e <= M.SURFACE_BAND_MM for e in err)),
                        "surface_reached_s": _agg(reached),
                        "reached_within_2_s": int(sum(r <= 2.0 for r in reached)),
                        "first_contact_mm": _agg(first),
                        "settled": int(sum(settled)),
                        "force_step_max_n": round(max(fstep), 4),
                        "recovery_force_step_max_n": round(max(pstep), 4),
                        "recovery_energy_mj": _agg(energy),
                        "epsilon_max_mm": _agg(eps) if eps else None,
                        "lead_ms": _agg(lead) if lead else None,
                    })
    return rows


def peg_rows(*, lags=LAGS_S, quick: bool = False, log=None, passivity: tuple = ()) -> list[dict]:
    """The 1-DOF peg of Figs. 6/9 (deterministic: one run per row); ``passivity``: ``[passivity]``
    keys over the server's defaults."""
    rows = []
    secs = F.PEG_QUICK_SECONDS if quick else F.PEG_SECONDS
    for method, pol, eps in (("LM0", "lm0", 0.0), ("LM5", "deformation", 0.005)):
        for config in (LM0_CONFIGS if method == "LM0" else tuple(CONFIGS)):
            kw = dict(CONFIGS[config])
            if method == "LM0":
                kw = {k: v for k, v in kw.items() if k == "recovery"}
            for lag in lags:
                if log:
                    log(f"fidelity: peg {method} {config} lag {lag * 1e3:g} ms")
                spec = F.peg_spec(method, pol, eps, "simulated", quick).but(tool_lag_s=lag, **kw)
                if passivity:
                    spec = spec.but(passivity=tuple(passivity))
                tr = run_simulated(spec)
                m = F.peg_metrics(F.PegView.of_trace(tr), secs)
                compliance_mm = 5.0 / spec.stiffness_n_per_m * 1e3
                pk = m["peak_excursion_mm"] if isinstance(m["peak_excursion_mm"], float) else math.inf
                last = m["excursion_last_mm"] if isinstance(m["excursion_last_mm"], float) else math.inf
                rows.append({
                    "scenario": "peg", "method": method, "config": config, "lag_ms": lag * 1e3,
                    "peg_error_mm": round(max(0.0, pk - compliance_mm), 3),
                    "peg_error_last_quarter_mm": round(max(0.0, last - compliance_mm), 3),
                    "unstable": m["unstable"], "growth": m["growth"], "both_walls_fraction": m["both_walls_fraction"],
                    "recovery_energy_mj": round(1e3 * tr.extra.get("recovery_energy_j", 0.0), 1),
                    "force_step_max_n": round(M.force_step_max_n(tr), 3),
                    "epsilon_max_mm": (tr.extra.get("advice") or {}).get("epsilon_mm", [None, None])[1],
                })
    return rows


def run_fidelity(out, *, quick: bool = False, log=None, spatial: bool = True) -> dict:
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    seeds = QUICK_SEEDS if quick else SEEDS
    res = {"set_up": __doc__.split("\n\n")[1].replace("\n", " "), "seeds": list(seeds),
           "configs": {k: {kk: (list(vv) if isinstance(vv, tuple) else vv) for kk, vv in v.items()}
                       for k, v in CONFIGS.items()},
           "wall": wall_rows(seeds=seeds, pushes=(0.5,) if quick else PUSHES_N, lags=(0.0, 0.04) if quick else LAGS_S,
                             log=log),
           "peg": peg_rows(lags=(0.0,) if quick else LAGS_S, quick=quick, log=log)}
    if spatial and not quick:
        res["box"] = spatial_rows(log=log)
    F.write_json(out / "fidelity.json", res)
    (out / "fidelity.md").write_text(tables_md(res) + "\n")
    return res


#: The spatial rows: pybullet (``clients/pybullet_engine.py``, through its Engine interface) at
#: 60 Hz, the simulated spatial device (0.3 kg), 1 kHz, k = 4000 N/m, b = 30 N s/m.
SPATIAL_ENV_HZ = 60.0
#: floor: the ``loose`` scene's 40 mm cube (3 mm above the floor; touching at z = 20 mm) lifted
#: by the hand (+z for 0.15 s) and pushed back down with 0.5 N; the variants (the "seeds") lift
#: with 0.8, 1.0, 1.2 N (arrival at 0.3-0.5 m/s)
FLOOR_Z_M = 0.020
FLOOR_LIFTS_N = (0.8, 1.0, 1.2)
#: wall: the ``peg`` scene's 20 x 20 x 60 mm peg carried by an impedance hand (300 N/m) over the
#: block, down beside it and against the block's outer face at x = 50 mm (touching at x = 60 mm),
#: the hand's target 2 mm inside (about 0.6 N); the variants reach the wall in 40, 50, 60 ms
WALL_X_M = 0.060
WALL_APPROACH_S = (0.04, 0.05, 0.06)
SPATIAL_SECONDS = 4.0


def spatial_spec(surface: str, config: str, lag_s: float, variant):
    from .harness import RunSpec

    t0 = F.HAND_START_S["simulated"]
    kw = dict(CONFIGS[config])
    kw.setdefault("epsilon_m", 0.005)
    if surface == "floor":
        hand = {"type": "steps", "steps": [[0.0, [0.0] * 6], [t0, [0.0, 0.0, float(variant), 0.0, 0.0, 0.0]],
                                           [t0 + 0.15, [0.0, 0.0, -0.5, 0.0, 0.0, 0.0]]]}
        scene = "loose"
    else:
        pts = [[t0, 0, 0, 0, 0, 0, 0], [t0 + 0.4, 0.09, 0, 0, 0, 0, 0], [t0 + 0.7, 0.09, 0, -0.045, 0, 0, 0],
               [t0 + 0.7 + float(variant), WALL_X_M - 0.002, 0, -0.045, 0, 0, 0]]
        hand = {"type": "impedance", "stiffness_n_per_m": 300.0, "damping_n_s_per_m": 5.0,
                "target": {"type": "waypoints", "points": pts}}
        scene = "peg"
    return RunSpec(method="LM5", controller="four_channel", policy="deformation", contact_frame="engine",
                   rate_hz=1000.0, stiffness_n_per_m=4000.0, damping_n_s_per_m=30.0, capacity=32, engine="pybullet",
                   scene=scene, env_rate_hz=(SPATIAL_ENV_HZ, SPATIAL_ENV_HZ), hand=Hand("constant", (0.0, 0.0, 0.0), start_s=t0),
                   seconds=SPATIAL_SECONDS, device_kind="spatial", device=(("hand", hand),), tool_lag_s=lag_s,
                   workspace_m=0.25, **kw)


def spatial_rows(*, lags=LAGS_S, log=None) -> list[dict]:
    """The spatial box on a floor and on a wall (pybullet); none when pybullet is not installed.
    The push at rest is measured (the mean force the device renders over the last second)."""
    try:
        import pybullet  # noqa: F401
    except ImportError:
        return []
    rows = []
    for surface, variants in (("floor", FLOOR_LIFTS_N), ("wall", WALL_APPROACH_S)):
        for config in CONFIGS:
            for lag in lags:
                if log:
                    log(f"fidelity: spatial {surface} {config} lag {lag * 1e3:g} ms")
                err, reached, fstep, energy, eps = [], [], [], [], []
                for v in variants:
                    tr = run_simulated(spatial_spec(surface, config, lag, v))
                    axis, surf = (2, FLOOR_Z_M) if surface == "floor" else (0, WALL_X_M)
                    push = float(np.mean(np.abs(tr.cmd_xyz[tr.t_s >= tr.t_s[-1] - 1.0, axis])))
                    f = M.felt_surface_metrics(tr, surface_m=surf, axis=axis, push_n=push, sign=-1.0)
                    err.append(abs(f["surface_error_mm"]))
                    reached.append(float(f["surface_reached_s"]))
                    fstep.append(f["recovery_force_step_max_n"])
                    energy.append(f["recovery_energy_mj"])
                    adv = tr.extra.get("advice")
                    if adv:
                        eps.append(adv["epsilon_mm"][1])
                rows.append({"scenario": "box", "surface": surface, "config": config, "lag_ms": lag * 1e3,
                             "variants": list(variants), "surface_error_mm": _agg(err),
                             "within_0_5_mm": int(sum(e <= M.SURFACE_BAND_MM for e in err)),
                             "surface_reached_s": _agg(reached), "reached_within_2_s": int(sum(r <= 2.0 for r in reached)),
                             "recovery_force_step_max_n": round(max(fstep), 4), "recovery_energy_mj": _agg(energy),
                             "epsilon_max_mm": _agg(eps) if eps else None})
    return rows


def _cell(a) -> str:
    if a is None:
        return "-"
    if isinstance(a, dict):
        return f"{a['mean']} / {a['max']}"
    return str(a)


def tables_md(res: dict) -> str:
    n = len(res["seeds"])
    lines = [f"Wall (Fig. 14 push, stub 30-60 Hz, 512 Hz, engine frame; {n} seeds; mean / max over seeds):", "",
             "| method | config | push (N) | lag (ms) | surface error (mm) | within 0.5 mm | reached (s) | within 2 s "
             "| force step max (N) | recovery step max (N) | recovery energy (mJ) | epsilon max (mm) | lead (ms) |",
             "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for r in res["wall"]:
        lines.append(f"| {r['method']} | {r['config']} | {r['push_n']:g} | {r['lag_ms']:g} | {_cell(r['surface_error_mm'])} | "
                     f"{r['within_0_5_mm']}/{n} | {_cell(r['surface_reached_s'])} | {r['reached_within_2_s']}/{n} | "
                     f"{r['force_step_max_n']:.3f} | {r['recovery_force_step_max_n']:.3f} | "
                     f"{_cell(r['recovery_energy_mj'])} | {_cell(r['epsilon_max_mm'])} | {_cell(r['lead_ms'])} |")
    lines += ["", "1-DOF peg (Figs. 6/9: 5 N at 1 Hz in the exactly fitting hole, 50 Hz engine + 20 ms delay, direct "
              "coupling): how much wider than it is the hole is felt (peak |x| - 5 N / K):", "",
              "| method | config | lag (ms) | hole felt wider by (mm) | last quarter (mm) | unstable | both walls | "
              "recovery energy (mJ) | epsilon max (mm) |",
              "| --- | --- | ---: | ---: | ---: | --- | ---: | ---: | ---: |"]
    for r in res["peg"]:
        lines.append(f"| {r['method']} | {r['config']} | {r['lag_ms']:g} | {r['peg_error_mm']} | {r['peg_error_last_quarter_mm']} | "
                     f"{'yes' if r['unstable'] else 'no'} | {r['both_walls_fraction']} | {r['recovery_energy_mj']} | "
                     f"{r['epsilon_max_mm'] if r['epsilon_max_mm'] is not None else '-'} |")
    if res.get("box"):
        lines += ["", "Spatial box (pybullet 60 Hz, spatial device, 1 kHz; 3 variants; mean / max):", "",
                  "| surface | config | lag (ms) | surface error (mm) | within 0.5 mm | reached (s) | within 2 s | "
                  "recovery step max (N) | recovery energy (mJ) | epsilon max (mm) |",
                  "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
        for r in res["box"]:
            nv = len(r["variants"])
            lines.append(f"| {r['surface']} | {r['config']} | {r['lag_ms']:g} | {_cell(r['surface_error_mm'])} | "
                         f"{r['within_0_5_mm']}/{nv} | {_cell(r['surface_reached_s'])} | {r['reached_within_2_s']}/{nv} | "
                         f"{r['recovery_force_step_max_n']:.3f} | {_cell(r['recovery_energy_mj'])} | "
                         f"{_cell(r['epsilon_max_mm'])} |")
    return "\n".join(lines)
