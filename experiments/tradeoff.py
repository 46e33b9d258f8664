"""``hapticproxy experiment tradeoff``: the speed / accuracy trade-off of the server's settings.

One configuration = the server's settings that matter (haptic rate, contact stiffness and
damping, epsilon, contact cap, controller, update policy, kernel) and the environment's rate.
Each is run on two scenarios in **simulated time** (``harness.run_simulated``: the real loop,
device, controller, model and protocol in one process on a ``SimClock``, the stub engine
stepped on its own schedule; deterministic per seed), each with several engine seeds:

- ``wall``: the Fig. 14 push (0.5 N onto the testbed's bottom wall, the peg starting at rest
  124 mm away): ``wall_error_mm`` = |felt wall - 124 mm| (mean over seeds; see
  ``metrics.static_contact_metrics``), ``limit_cycle_mm`` (largest over seeds),
  ``surface_reached_s`` (mean over seeds: from the first contact until the device stays within
  0.5 mm of the true surface; see ``metrics.felt_surface_metrics``; a run that never gets there
  counts as its remaining time), ``recovery_energy_mj`` (largest);
- ``hole``: the Fig. 16 shaking (1 N sin(5 pi t) on the peg in the exactly fitting hole):
  ``drift_mm``, ``rotation_deg`` (mean over seeds; see ``metrics.hole_metrics``);

and over both: ``force_step_max_n`` (the largest force step written to the device in one
haptic step), ``penalty_jump_max_n`` (the largest jump of the model's penalty force at a model
update), ``energy_injected_mj`` (the largest net work of the rendered wrench on the device over
the last 2 s of a run: > 0 is an active interaction), ``unstable`` (any run faulted, went
non-finite, or the hole run was unstable by ``metrics.hole_metrics``).

Cost, measured for real on this machine: ``step_us_p50`` / ``p99`` (wall-clock time of one
``HapticLoop.step`` in this process: transport poll, model update and acknowledgement when one
arrived, device, the controller + model + safety kernel, telemetry; never waiting, the clock is
simulated), ``model_us_p50`` (the model kernel alone, numba) and ``numpy_model_us_p50`` (the
plain-numpy reference step on the same states), and ``cpu_load_pct`` = ``step_us_p50`` x rate
(percent of one core the loop's work takes). Rows with ``kernel = numpy`` are the numba rows
with the model kernel's cost replaced by the numpy reference's (the reference computes the
same step: its accuracy is the numba row's; ``numpy_matches_numba`` checks it on a model-only
run); ``feasible`` says whether the step's p99 fits in the period.

The achieved rate is measured in **real time**: one run of the wall scenario per haptic rate on
the real server process (``harness.run_realtime``), reporting the achieved rate, missed
deadlines and the loop's own compute-time percentiles.

Sweeps (one dimension at a time around the base: 1 kHz, stiffness 4000 N/m with the paper's
damping ratio b = 7.5 ms x k, epsilon 5 mm, 16 contacts, the stub at 30-60 Hz, four-channel,
deformation with the model's default deformation recovery, the server's default ``engine``
contact frame, no advice to the engine; the ``recovery`` and ``advice`` dimensions vary those) and a grid for the stable region
(the largest stable stiffness at each haptic rate for each controller, with the paper's
damping ratio, and for the four-channel controller also with a fixed b = 30 N s/m). Writes
``tradeoff.json`` (every row), ``tradeoff.md`` (the table), ``stable_region.json``,
``stable_region.md``, ``pareto.png`` and ``stable_region.png``.

``--region-only`` (:func:`run_region`) runs only the stable-region grid (``--region-controllers``,
``--region-rates``: a part of it) and writes only the ``stable_region.*`` files. The region runs
with the server's current defaults (:func:`region_settings`, recorded in ``stable_region.json``):
the passivity layer as configured by default (``--layer on|off``: with or without it), the
model's default integrator, the controller's coupling damping as engagement sets it for the peg.
"""
from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from . import metrics as M
from .harness import Hand, RunFailed, RunSpec, run_realtime, run_simulated

#: The paper's contact damping per stiffness (30 N s/m at 4000 N/m; 100 at 15000).
DAMPING_PER_STIFFNESS_S = 0.0075
#: Simulated time (s after the hand starts) of the two scenarios.
WALL_SECONDS, HOLE_SECONDS = 3.5, 4.0
QUICK_WALL_SECONDS, QUICK_HOLE_SECONDS = 3.0, 3.0
REGION_HOLE_SECONDS = 6.0
HAND_START_S = 0.6


@dataclass(frozen=True)
class Config:
    rate_hz: float = 1000.0
    stiffness_n_per_m: float = 4000.0
    epsilon_m: float = 0.005
    capacity: int = 16
    env_rate_hz: tuple = (30.0, 60.0)
    controller: str = "four_channel"
    policy: str = "deformation"
    contact_frame: str = "engine"
    kernel: str = "numba"
    #: None: the paper's ratio (DAMPING_PER_STIFFNESS_S x k); a number: this damping whatever k
    damping_fixed_n_s_per_m: float | None = None
    #: deformation recovery speed [m/s]: None = the model's default, 0 = off (the paper's eq. 5)
    recovery_speed_m_per_s: float | None = None
    #: what the server tells the engine (``server/prediction.py``): "none" (the paper: the engine
    #: uses the granted epsilon, ``epsilon_m``), "epsilon" (the epsilon to use next, up to
    #: ``epsilon_m``), "epsilon+lead" (and the lead it extrapolates the proxy's pose by)
    advice: str = "none"
    #: the passivity layer: None = the server's default ``[passivity] enabled``; "on" / "off"
    layer: str | None = None

    @property
    def damping_n_s_per_m(self) -> float:
        if self.damping_fixed_n_s_per_m is not None:
            return float(self.damping_fixed_n_s_per_m)
        return DAMPING_PER_STIFFNESS_S * self.stiffness_n_per_m

    def spec(self, scenario: str, seed: int, quick: bool) -> RunSpec:
        common = dict(controller=self.controller, policy=self.policy, epsilon_m=self.epsilon_m,
                      contact_frame=self.contact_frame, rate_hz=self.rate_hz,
                      stiffness_n_per_m=self.stiffness_n_per_m, damping_n_s_per_m=self.damping_n_s_per_m,
                      capacity=self.capacity, env_rate_hz=tuple(self.env_rate_hz), seed=seed, engine="stub",
                      method="custom",
                      recovery=() if self.recovery_speed_m_per_s is None else
                      (("speed_m_per_s", float(self.recovery_speed_m_per_s)),),
                      predict_epsilon=self.advice in ("epsilon", "epsilon+lead"), lead=self.advice == "epsilon+lead",
                      passivity=() if self.layer is None else (("enabled", self.layer == "on"),))
        if scenario == "wall":
            return RunSpec(scene="testbed", hand=Hand("constant", (0.0, 0.5, 0.0), start_s=HAND_START_S),
                           seconds=QUICK_WALL_SECONDS if quick else WALL_SECONDS, **common)
        if scenario == "hole_long":  # the stable-region test: Fig. 16's shaking, longer
            return RunSpec(scene="hole", hand=Hand("sinusoid", (1.0, 0.0, 0.0), 2.5, HAND_START_S),
                           seconds=QUICK_HOLE_SECONDS if quick else REGION_HOLE_SECONDS, **common)
        return RunSpec(scene="hole", hand=Hand("sinusoid", (1.0, 0.0, 0.0), 2.5, HAND_START_S),
                       seconds=QUICK_HOLE_SECONDS if quick else HOLE_SECONDS, **common)

    def label(self) -> str:
        lo, hi = self.env_rate_hz
        env = f"{lo:g}" if lo == hi else f"{lo:g}-{hi:g}"
        b = "" if self.damping_fixed_n_s_per_m is None else f" b={self.damping_fixed_n_s_per_m:g}"
        rec = "" if self.recovery_speed_m_per_s is None else f" rec={self.recovery_speed_m_per_s * 1e3:g}mm/s"
        adv = "" if self.advice == "none" else f" advice={self.advice}"
        lay = "" if self.layer is None else f" layer={self.layer}"
        return (f"{self.controller}/{self.policy} {self.rate_hz:g} Hz k={self.stiffness_n_per_m:g}{b} "
                f"eps={self.epsilon_m * 1e3:g}mm cap={self.capacity} env={env} Hz{rec}{adv}{lay} {self.kernel}")


BASE = Config()

#: One dimension at a time around BASE: (dimension, field, values).
SWEEPS = (
    ("haptic rate", "rate_hz", (256.0, 512.0, 1000.0, 2000.0, 4000.0, 8000.0)),
    ("environment rate", "env_rate_hz", ((10.0, 10.0), (20.0, 20.0), (30.0, 30.0), (30.0, 60.0), (60.0, 60.0),
                                         (120.0, 120.0), (240.0, 240.0))),
    ("epsilon", "epsilon_m", (0.0, 0.001, 0.002, 0.005, 0.010)),
    ("stiffness", "stiffness_n_per_m", (1000.0, 2000.0, 4000.0, 10000.0, 20000.0, 50000.0, 100000.0)),
    ("contact cap", "capacity", (1, 2, 4, 8, 16, 32, 64)),
    ("recovery", "recovery_speed_m_per_s", (0.0, 0.0125, None, 0.05)),
    # the server's advice to the engine, with the epsilon it may grant (a field dict per value)
    ("advice", None, ({"advice": "epsilon", "epsilon_m": 0.005}, {"advice": "epsilon", "epsilon_m": 0.010},
                      {"advice": "epsilon", "epsilon_m": 0.040}, {"advice": "epsilon+lead", "epsilon_m": 0.040},
                      {"advice": "epsilon+lead", "epsilon_m": 0.040, "recovery_speed_m_per_s": 0.0})),
)
QUICK_SWEEPS = (
    ("haptic rate", "rate_hz", (512.0, 2000.0)),
    ("epsilon", "epsilon_m", (0.0, 0.005)),
    ("stiffness", "stiffness_n_per_m", (4000.0, 20000.0)),
    ("recovery", "recovery_speed_m_per_s", (0.0, None)),
    ("advice", None, ({"advice": "epsilon+lead", "epsilon_m": 0.040},)),
)
#: Candidate presets (rate, contacts, epsilon): the old ones and the neighbours worth a look.
CANDIDATES = ((512.0, 16, 0.005), (1000.0, 16, 0.005), (1000.0, 32, 0.005), (2000.0, 32, 0.005),
              (2000.0, 64, 0.005), (4000.0, 32, 0.005), (4000.0, 64, 0.005), (512.0, 16, 0.010),
              (1000.0, 32, 0.010), (2000.0, 32, 0.010), (2000.0, 64, 0.010), (4000.0, 32, 0.010),
              (4000.0, 64, 0.010))
#: ... and with the server's advice (predicted epsilon up to the cap, the lead), recovery on
ADVICE_CANDIDATES = ((512.0, 16, 0.040), (1000.0, 32, 0.040), (2000.0, 32, 0.040), (4000.0, 64, 0.040),
                     (1000.0, 32, 0.020))
#: The stable-region grid: controllers (with the model settings), rates, stiffnesses.
REGION_CONTROLLERS = (
    ("four_channel", dict(controller="four_channel", policy="deformation", epsilon_m=0.005)),
    ("four_channel, b = 30 N s/m", dict(controller="four_channel", policy="deformation", epsilon_m=0.005,
                                        damping_fixed_n_s_per_m=30.0)),
    ("coupler", dict(controller="coupler", policy="deformation", epsilon_m=0.005)),
    ("direct", dict(controller="direct", policy="deformation", epsilon_m=0.005)),
    ("IR (direct, rigid, eps 0, eq. 1)", dict(controller="direct", policy="rigid", epsilon_m=0.0, contact_frame="proxy")),
)
REGION_RATES = (256.0, 512.0, 1000.0, 2000.0, 4000.0, 8000.0)
REGION_STIFFNESS = (1000.0, 2000.0, 4000.0, 10000.0, 20000.0, 50000.0, 100000.0, 200000.0, 500000.0, 1000000.0)
QUICK_REGION_RATES = (512.0, 2000.0)
QUICK_REGION_STIFFNESS = (4000.0, 20000.0)
REALTIME_RATES = (256.0, 512.0, 1000.0, 2000.0, 4000.0, 8000.0)
SEEDS = (1, 2, 3, 4, 5, 6)
REGION_SEEDS = (1, 2, 3)
QUICK_SEEDS = (1,)
#: Every this many haptic steps the model step is timed alone (numba and numpy).
MODEL_TIMING_EVERY = 25


def _refusal(why: str) -> bool:
    """The model refused the contact parameters (a Reject in the handshake, or at engagement)."""
    return "contact." in why and ("Reject" in why or why.startswith("ValueError"))


def _p(a, q) -> float | None:
    return None if a is None or len(a) == 0 else round(float(np.percentile(a, q)), 3)


def evaluate(cfg: Config, *, seeds=SEEDS, quick: bool = False, scenarios=("wall", "hole"),
             model_timing_every: int = MODEL_TIMING_EVERY) -> dict:
    """Run ``cfg`` on the scenarios over ``seeds`` (simulated time); one row of the table.
    ``model_timing_every`` 0: no model-step timing (the stable region uses no cost column; the
    timing runs on copies of the state, so it changes no other column)."""
    row: dict = {"label": cfg.label(), **{k: v for k, v in asdict(cfg).items()}}
    row["env_rate_hz"] = list(cfg.env_rate_hz)
    row["damping_n_s_per_m"] = cfg.damping_n_s_per_m
    step_us, model_us, numpy_us = [], [], []
    walls, holes = [], []
    t0 = time.perf_counter()
    failed: list[str] = []
    for sc in scenarios:
        for seed in seeds:
            try:
                tr = run_simulated(cfg.spec(sc, seed, quick), model_timing_every=model_timing_every)
            except RunFailed as exc:  # e.g. the model refused the contact parameters at engagement
                failed.append(exc.loop_exception or str(exc))
                continue
            step_us.append(tr.step_us)
            if tr.model_numba_us is not None:
                model_us.append(tr.model_numba_us)
                numpy_us.append(tr.model_numpy_us)
            if sc == "wall":
                w = M.static_contact_metrics(tr)
                w.update(M.felt_surface_metrics(tr, surface_m=M.WALL_Y_MM / 1e3, axis=1, push_n=0.5))
                if w["surface_reached_s"] == "inf":
                    w["surface_reached_s"] = float(tr.t_s[-1] - tr.t_s[int(np.argmax(tr.contacts > 0))])
                walls.append(w)
            else:
                holes.append(M.hole_metrics(tr))
    allm = walls + holes
    if not allm:
        row.update(unstable=True, refused=any(_refusal(e) for e in failed),
                   loop_exceptions=sorted(set(failed)), faults=len(failed), energy_injected_mj=None,
                   step_us_p50=None, step_us_p99=None, cpu_load_pct=None, feasible=False, seeds=list(seeds))
        return row
    if walls:
        errs = [abs(w["wall_error_mm"]) for w in walls]
        row["wall_error_mm"] = round(float(np.mean(errs)), 3)
        row["wall_error_max_mm"] = round(float(np.max(errs)), 3)
        row["limit_cycle_mm"] = round(float(max(w["limit_cycle_amplitude_mm"] for w in walls)), 3)
        row["limit_cycle_deg"] = round(float(max(w["limit_cycle_rotation_deg"] for w in walls)), 3)
        row["surface_reached_s"] = round(float(np.mean([w["surface_reached_s"] for w in walls])), 3)
        row["recovery_energy_mj"] = round(float(max(w["recovery_energy_mj"] for w in walls)), 3)
        row["recovery_force_step_max_n"] = round(float(max(w["recovery_force_step_max_n"] for w in walls)), 4)
    if holes:
        row["drift_mm"] = round(float(np.mean([h["drift_mm"] for h in holes])), 3)
        row["drift_max_mm"] = round(float(np.max([h["drift_mm"] for h in holes])), 3)
        row["rotation_deg"] = round(float(np.mean([h["rotation_deg"] for h in holes])), 3)
    row["force_step_max_n"] = round(float(max(m["force_step_max_n"] for m in allm)), 4)
    row["penalty_jump_max_n"] = round(float(max(m.get("penalty_jump_max_n") or 0.0 for m in allm)), 4)
    row["energy_injected_mj"] = round(float(max(m["energy_injected_mj"] for m in allm)), 3)
    row["faults"] = int(sum(m["faults"] + m["model_nonfinite"] for m in allm)) + len(failed)
    row["loop_exceptions"] = sorted({m["loop_exception"] for m in allm if m.get("loop_exception")} | set(failed))
    # the server refused the contact parameters for this tool at this rate (in the handshake)
    row["refused"] = any(_refusal(e) for e in row["loop_exceptions"])
    row["unstable"] = bool(row["faults"] > 0 or any(h["unstable"] for h in holes))
    st = np.concatenate(step_us)
    row["step_us_p50"] = _p(st, 50)
    row["step_us_p99"] = _p(st, 99)
    mu = np.concatenate(model_us) if model_us else None
    nu = np.concatenate(numpy_us) if numpy_us else None
    row["model_us_p50"] = _p(mu, 50)
    row["numpy_model_us_p50"] = _p(nu, 50)
    row["numpy_model_us_p99"] = _p(nu, 99)
    row["cpu_load_pct"] = round(row["step_us_p50"] * cfg.rate_hz * 1e-4, 3)
    row["feasible"] = bool(row["step_us_p99"] < 1e6 / cfg.rate_hz)
    row["seeds"] = list(seeds)
    row["sim_seconds"] = round(time.perf_counter() - t0, 2)
    return row


def numpy_row(row: dict) -> dict:
    """The numba row with the model kernel's cost replaced by the numpy reference's (same
    accuracy: the reference computes the same step)."""
    out = dict(row)
    out["kernel"] = "numpy"
    out["label"] = row["label"].replace("numba", "numpy")
    if row.get("numpy_model_us_p50") is None:
        return out
    extra50 = row["numpy_model_us_p50"] - row["model_us_p50"]
    extra99 = (row["numpy_model_us_p99"] or row["numpy_model_us_p50"]) - row["model_us_p50"]
    out["step_us_p50"] = round(row["step_us_p50"] + extra50, 3)
    out["step_us_p99"] = round(row["step_us_p99"] + extra99, 3)
    out["cpu_load_pct"] = round(out["step_us_p50"] * row["rate_hz"] * 1e-4, 3)
    out["feasible"] = bool(out["step_us_p99"] < 1e6 / row["rate_hz"])
    out["cost_projected"] = True
    return out


def _reference_step_method(self, hand_wrench):
    """``LocalModel.step`` computed by the plain-numpy reference (the model's arrays overwritten)."""
    from ..server.model.reference import reference_step

    hand = np.zeros(6)
    hand[:self.hand_dim] = np.asarray(hand_wrench, dtype=float).ravel()[:self.hand_dim]
    par, st, C, CI, cnt = self.arrays()
    st2, C2, CI2, cnt2 = reference_step(self.kind, par, st, C, CI, cnt, hand)
    st[:] = st2
    C[:] = C2
    CI[:] = CI2
    cnt[:] = cnt2
    return self._fenv


def _planar_cage_step_differences(steps: int) -> tuple[float, float]:
    """A planar proxy in a cage of 8 contacts replaced every 16 steps (half the keys new, as
    ``bench model`` does), pushed by a rotating hand wrench. Every step is computed by the
    numba kernel and, from the same state, by the numpy reference; returns the largest
    differences of the new configuration and of the rendered wrench."""
    from ..benchmarks.bench_model import make_tool, random_contacts
    from ..server.model import ContactParams, LocalModel
    from ..server.model.layout import S_FENV, S_Q
    from ..server.model.reference import reference_step

    rng = np.random.default_rng(3)
    model = LocalModel(make_tool("planar"), ContactParams(4000.0, 30.0, 0.0, 0.4, 0.3), period_s=1e-3, capacity=16)
    hand = np.zeros(6)
    base = 0
    dq = df = 0.0
    for i in range(steps):
        if i % 16 == 0:
            base += 4
            model.update(*random_contacts(model, 8, rng, base))
        a = 2 * math.pi * i / 500.0
        hand[:3] = (2.0 * math.cos(a), 2.0 * math.sin(a), 0.01 * math.sin(a))
        par, st, C, CI, cnt = model.arrays()
        st2 = reference_step(model.kind, par, st, C, CI, cnt, hand)[0]
        model.step(hand[:3])
        dq = max(dq, float(np.max(np.abs(st[S_Q:S_Q + 3] - st2[S_Q:S_Q + 3]))))
        df = max(df, float(np.max(np.abs(st[S_FENV:S_FENV + 3] - st2[S_FENV:S_FENV + 3]))))
    return dq, df


def numpy_matches_numba(seconds: float = 4.0) -> dict:
    """The kernels compute the same step: (1) the 1-DOF peg of Fig. 9 (LM5) run once with the
    numba kernel and once with every step computed by the plain-numpy reference (largest
    differences of the trajectories); (2) a planar proxy in a cage of changing contacts, every
    step computed both ways from the same state (largest per-step differences: a closed loop of
    random contacts would amplify rounding differences, so trajectories are not compared)."""
    from ..server.model import LocalModel

    from .peg1d import simulate_peg1d

    a = simulate_peg1d("deformation", duration_s=seconds, haptic_hz=512.0, epsilon_m=0.005)
    orig_step = LocalModel.step
    LocalModel.step = _reference_step_method
    try:
        b = simulate_peg1d("deformation", duration_s=seconds, haptic_hz=512.0, epsilon_m=0.005)
    finally:
        LocalModel.step = orig_step
    n = int(seconds * 500)
    dq, df = _planar_cage_step_differences(n)
    return {"peg1d_steps": len(a.t_s), "peg1d_max_position_difference_m": float(np.max(np.abs(a.x_hand_m - b.x_hand_m))),
            "peg1d_max_force_difference_n": float(np.max(np.abs(a.f_env_n - b.f_env_n))),
            "planar_cage_steps": n, "planar_step_max_q_difference": dq, "planar_step_max_wrench_difference": df}


def realtime_rates(rates=REALTIME_RATES, seconds: float = 3.0, log=None) -> list[dict]:
    """The achieved rate on the real server process (the wall scenario, BASE otherwise)."""
    out = []
    for r in rates:
        if log:
            log(f"tradeoff: real-time run at {r:g} Hz")
        spec = replace(BASE, rate_hz=r).spec("wall", 1, True).but(seconds=seconds, hand=Hand(
            "constant", (0.0, 0.5, 0.0), start_s=1.5))
        try:
            tr = run_realtime(spec)
        except RuntimeError as exc:
            out.append({"rate_hz": r, "error": str(exc)})
            continue
        steps = len(tr.t_s)
        out.append({"rate_hz": r, "achieved_rate_hz": round(tr.achieved_rate_hz, 2),
                    "missed_deadlines": tr.extra["missed_deadlines"], "overruns": tr.extra["overruns"],
                    "steps": steps, "compute_us": tr.compute_us, "lateness_us": tr.lateness_us,
                    "env_rate_hz": round(tr.env_rate_hz, 1), "rt_scheduling": tr.extra["rt_scheduling"],
                    "faults": tr.faults})
    return out


def run_rates(out, *, quick: bool = False, log=None) -> dict:
    """``hapticproxy experiment rates``: only the real-time achieved-rate runs of the trade-off."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    rt = realtime_rates(rates=(512.0, 4000.0) if quick else REALTIME_RATES, log=log)
    (out / "rates.json").write_text(json.dumps(rt, indent=1, default=float) + "\n")
    (out / "rates.md").write_text(table_md([], rt).strip() + "\n")
    return {"realtime_rates": rt}


def region_rows(controllers=None, rates=None, *, quick: bool = False) -> tuple[tuple, tuple]:
    """The stable-region grid's controller rows (``REGION_CONTROLLERS`` entries) and rates, all of
    them or the ones named (``controllers``: row names, ``rates``: haptic rates in Hz, each on the
    grid). A name or rate not on the grid: ``ValueError`` naming it and what there is."""
    grid_rates = QUICK_REGION_RATES if quick else REGION_RATES
    rows = REGION_CONTROLLERS
    if controllers:
        names = [n for n, _ in REGION_CONTROLLERS]
        unknown = [c for c in controllers if c not in names]
        if unknown:
            raise ValueError(f"region controllers: {', '.join(map(repr, unknown))} not in the grid; "
                             f"expected some of {', '.join(map(repr, names))}")
        rows = tuple(r for r in REGION_CONTROLLERS if r[0] in controllers)
    out_rates = grid_rates
    if rates:
        unknown = [r for r in rates if float(r) not in grid_rates]
        if unknown:
            raise ValueError(f"region rates: {', '.join(f'{r:g}' for r in unknown)} Hz not in the grid; "
                             f"expected some of {', '.join(f'{r:g}' for r in grid_rates)}")
        out_rates = tuple(r for r in grid_rates if r in {float(x) for x in rates})
    return rows, out_rates


def region_settings(layer: str | None = None) -> dict:
    """What the stable region runs with besides its grid: the server's current defaults, read
    from the code (the config's ``[passivity] enabled``, ``LocalModel``'s integrator, the
    controller's configured coupling damping that ``stability.coupling_damping_for_tool`` raises
    for a heavy tool at engagement), and what the harness sets (``harness.RunSpec.settings_dict``)."""
    from ..server import config as cfgmod
    from ..server.model.model import LocalModel, ToolSpec

    d = cfgmod.load({"safety": {"allow_outside_stable_region": True}})
    # the server builds its models without naming an integrator: a model built so says which
    integrator = LocalModel(ToolSpec.planar(0.25, 1e-3), warm=False).integrator
    enabled = bool(d["passivity"]["enabled"]) if layer is None else layer == "on"
    return {"passivity_enabled": enabled, "layer": "default" if layer is None else layer,
            "passivity": {k: v for k, v in dict(d["passivity"]).items() if k != "enabled"},
            "integrator": integrator,
            "coupling_damping": "the configured [controller] damping, raised for a heavy tool at engagement "
                                "(stability.coupling_damping_for_tool)",
            "controller_damping_n_s_per_m": float(d["controller"]["damping_n_s_per_m"]),
            "device": "simulated planar device, stepped once per haptic period (no zero-order hold)",
            "force_rate_n_per_s": 1000.0, "engine": "stub 30-60 Hz", "tool": "the testbed's 0.25 kg peg"}


def stable_region(*, quick: bool, seeds, log=None, controllers=None, rates=None, layer: str | None = None) -> list[dict]:
    """The stable band of contact stiffness per (controller, rate): stiffness ascending; a
    stiffness is stable when no run of ``evaluate`` (the wall push and 6 s of Fig. 16's
    shaking, every seed) is unstable. Too soft a hole also fails (the 1 N shaking turns the
    peg and walks it out of the hole), so the band has a lower end too. ``largest stable``: the
    top of the first contiguous band of stable stiffnesses; the scan stops after two unstable
    stiffnesses in a row above a stable one. ``controllers``, ``rates``: only those rows and
    rates of the grid (:func:`region_rows`); ``layer``: "on" / "off" the passivity layer (None: the
    server's default)."""
    if layer not in (None, "on", "off"):
        raise ValueError(f"layer: expected on, off or None (the server's default), got {layer!r}")
    rows, rates = region_rows(controllers, rates, quick=quick)
    ks = QUICK_REGION_STIFFNESS if quick else REGION_STIFFNESS
    out = []
    for name, kw in rows:
        for r in rates:
            tried = []
            lo = hi = None
            bad_run = 0
            t0 = time.perf_counter()
            for k in ks:
                cfg = replace(BASE, rate_hz=r, stiffness_n_per_m=k, layer=layer, **kw)
                row = evaluate(cfg, seeds=seeds, quick=quick, scenarios=("wall", "hole_long"), model_timing_every=0)
                tried.append({"stiffness_n_per_m": k, "unstable": row["unstable"], "refused": row["refused"],
                              "energy_injected_mj": row["energy_injected_mj"], "drift_mm": row.get("drift_mm"),
                              "rotation_deg": row.get("rotation_deg"), "wall_error_mm": row.get("wall_error_mm"),
                              "limit_cycle_mm": row.get("limit_cycle_mm"), "loop_exceptions": row["loop_exceptions"]})
                if row["unstable"]:
                    bad_run += 1
                    if lo is not None and bad_run >= 2:
                        break
                else:
                    bad_run = 0
                    if lo is None:
                        lo = hi = k
                    elif hi is not None and all(not t["unstable"] for t in tried if t["stiffness_n_per_m"] >= lo):
                        hi = k
            refused = next((t["stiffness_n_per_m"] for t in tried if t["refused"]), None)
            wall_s = round(time.perf_counter() - t0, 1)
            if log:
                log(f"tradeoff: stable region {name} {r:g} Hz: stable from {lo} to {hi} N/m"
                    f"{f'; refused from {refused:g} N/m' if refused else ''} ({wall_s:g} s)")
            out.append({"controller": name, "rate_hz": r, "smallest_stable_stiffness_n_per_m": lo,
                        "largest_stable_stiffness_n_per_m": hi, "smallest_refused_stiffness_n_per_m": refused,
                        "wall_s": wall_s, "tried": tried})
    return out


def run_region(out, *, quick: bool = False, log=None, controllers=None, rates=None, layer: str | None = None) -> dict:
    """``hapticproxy experiment tradeoff --region-only``: only the stable-region grid (all of it,
    or the ``controllers`` rows and ``rates`` named), with the server's current defaults
    (:func:`region_settings`; ``layer`` "off": without the passivity layer, as measured before it). Writes ``stable_region.json``, ``stable_region.md`` and
    ``stable_region.png``. Returns ``{"stable_region": [...], "settings": {...}, ...}``."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    seeds = QUICK_SEEDS if quick else REGION_SEEDS
    t0 = time.perf_counter()
    region = stable_region(quick=quick, seeds=seeds, log=log, controllers=controllers, rates=rates, layer=layer)
    res = {"mode": "simulated time", "quick": quick, "seeds": list(seeds),
           "damping_per_stiffness_s": DAMPING_PER_STIFFNESS_S, "settings": region_settings(layer),
           "wall_s": round(time.perf_counter() - t0, 1), "stable_region": region}
    (out / "stable_region.json").write_text(json.dumps(res, indent=1, default=float) + "\n")
    (out / "stable_region.md").write_text(region_md(region) + "\n")
    plot_region(region, out / "stable_region.png")
    return res


def pareto_front(rows: list[dict], cost: str, err: str) -> list[dict]:
    """Stable rows not dominated in (cost, error): nothing else is both cheaper and better."""
    cand = [r for r in rows if not r["unstable"] and r.get(err) is not None and r.get("feasible", True)]
    cand.sort(key=lambda r: (r[cost], r[err]))
    front, best = [], math.inf
    for r in cand:
        if r[err] < best - 1e-9:
            front.append(r)
            best = r[err]
    return front


def run_tradeoff(out, *, quick: bool = False, log=None, realtime: bool = True) -> dict:
    """The whole trade-off (``quick``: the short version; ``realtime``: also the real-time
    achieved-rate runs). Returns ``{"rows": [...], "stable_region": [...], ...}``."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    seeds = QUICK_SEEDS if quick else SEEDS
    rows: list[dict] = []
    cache: dict[Config, dict] = {}

    def ev(cfg: Config, dimension: str) -> dict:
        if cfg not in cache:
            if log:
                log(f"tradeoff: {dimension}: {cfg.label()}")
            cache[cfg] = evaluate(cfg, seeds=seeds, quick=quick)
        r = dict(cache[cfg])
        r["dimension"] = dimension
        return r

    for dim, fld, values in (QUICK_SWEEPS if quick else SWEEPS):
        for v in values:
            rows.append(ev(replace(BASE, **(v if fld is None else {fld: v})), dim))
    # numba vs numpy: every haptic-rate row again with the numpy reference's cost
    for r in [r for r in rows if r["dimension"] == "haptic rate"]:
        nr = numpy_row(r)
        nr["dimension"] = "kernel"
        rows.append(nr)
        r2 = dict(r)
        r2["dimension"] = "kernel"
        rows.append(r2)
    if not quick:
        for rate, cap, eps in CANDIDATES:
            rows.append(ev(replace(BASE, rate_hz=rate, capacity=cap, epsilon_m=eps), "preset candidate"))
        for rate, cap, eps in ADVICE_CANDIDATES:
            rows.append(ev(replace(BASE, rate_hz=rate, capacity=cap, epsilon_m=eps, advice="epsilon+lead"),
                           "preset candidate"))
    region = stable_region(quick=quick, seeds=QUICK_SEEDS if quick else REGION_SEEDS, log=log)
    rt = realtime_rates(rates=(512.0, 4000.0) if quick else REALTIME_RATES, log=log) if realtime else []
    check = numpy_matches_numba(2.0 if quick else 4.0)
    res = {"mode": "simulated time (accuracy, step cost); real time (achieved rate)", "base": asdict(BASE),
           "damping_per_stiffness_s": DAMPING_PER_STIFFNESS_S, "seeds": list(seeds), "quick": quick,
           "rows": rows, "stable_region": region, "realtime_rates": rt, "numpy_matches_numba": check,
           "pareto_wall": [r["label"] for r in pareto_front(rows, "cpu_load_pct", "wall_error_mm")],
           "pareto_hole": [r["label"] for r in pareto_front(rows, "cpu_load_pct", "drift_mm")]}
    (out / "tradeoff.json").write_text(json.dumps(res, indent=1, default=float) + "\n")
    (out / "tradeoff.md").write_text(table_md(rows, rt) + "\n")
    (out / "stable_region.json").write_text(json.dumps(
        {"mode": "simulated time", "quick": quick, "seeds": list(QUICK_SEEDS if quick else REGION_SEEDS),
         "damping_per_stiffness_s": DAMPING_PER_STIFFNESS_S, "settings": region_settings(),
         "stable_region": region}, indent=1, default=float) + "\n")
    (out / "stable_region.md").write_text(region_md(region) + "\n")
    plot_pareto(rows, out / "pareto.png")
    plot_region(region, out / "stable_region.png")
    return res


# ------------------------------------------------------------------------------ outputs
_COLS = (("dimension", "{}"), ("label", "{}"), ("wall_error_mm", "{:.2f}"), ("surface_reached_s", "{:.2f}"),
         ("recovery_energy_mj", "{:.1f}"), ("limit_cycle_mm", "{:.2f}"),
         ("drift_mm", "{:.2f}"), ("rotation_deg", "{:.2f}"), ("force_step_max_n", "{:.3f}"),
         ("penalty_jump_max_n", "{:.2f}"), ("energy_injected_mj", "{:.2f}"), ("unstable", "{}"),
         ("step_us_p50", "{:.1f}"), ("step_us_p99", "{:.1f}"), ("model_us_p50", "{:.2f}"),
         ("cpu_load_pct", "{:.2f}"), ("feasible", "{}"))


def _fmt(fmt: str, v) -> str:
    if v is None:
        return "-"
    if isinstance(v, bool):
        return "yes" if v else "no"
    try:
        return fmt.format(v)
    except (ValueError, TypeError):
        return str(v)


def table_md(rows: list[dict], rt: list[dict]) -> str:
    head = "| " + " | ".join(c for c, _ in _COLS) + " |"
    sep = "| " + " | ".join("---" if c in ("dimension", "label") else "---:" for c, _ in _COLS) + " |"
    lines = [head, sep] if rows else []
    for r in rows:
        lines.append("| " + " | ".join(_fmt(f, r.get(c)) for c, f in _COLS) + " |")
    if rt:
        lines += ["", "| rate (Hz) | achieved (Hz) | missed | compute p50 / p99 / max (us) | lateness p99 (us) | SCHED_FIFO |",
                  "| ---: | ---: | ---: | --- | ---: | --- |"]
        for r in rt:
            if "error" in r:
                lines.append(f"| {r['rate_hz']:g} | failed: {r['error']} | | | | |")
                continue
            c = r["compute_us"]
            lines.append(f"| {r['rate_hz']:g} | {r['achieved_rate_hz']:.1f} | {r['missed_deadlines']} | "
                         f"{c.get('p50')} / {c.get('p99')} / {c.get('max')} | {r['lateness_us'].get('p99')} | "
                         f"{'yes' if r['rt_scheduling'] else 'no'} |")
    return "\n".join(lines)


def region_md(region: list[dict]) -> str:
    rates = sorted({r["rate_hz"] for r in region})
    ctrls = list(dict.fromkeys(r["controller"] for r in region))
    lines = ["| controller | " + " | ".join(f"{r:g} Hz" for r in rates) + " |",
             "| --- | " + " | ".join("---:" for _ in rates) + " |"]
    for c in ctrls:
        cells = []
        for r in rates:
            e = next(x for x in region if x["controller"] == c and x["rate_hz"] == r)
            lo, hi = e["smallest_stable_stiffness_n_per_m"], e["largest_stable_stiffness_n_per_m"]
            ref = e.get("smallest_refused_stiffness_n_per_m")
            cell = "none" if hi is None else f"{lo:g} - **{hi:g}**"
            cells.append(cell + (f" (refused from {ref:g})" if ref else ""))
        lines.append(f"| {c} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


FLOOR_MM = 0.01


def short_label(r: dict) -> str:
    """What sets a row apart from the base configuration, for the plot."""
    out = []
    if r["rate_hz"] != BASE.rate_hz:
        out.append(f"{r['rate_hz']:g} Hz")
    if r["stiffness_n_per_m"] != BASE.stiffness_n_per_m:
        out.append(f"k {r['stiffness_n_per_m']:g}")
    if r["epsilon_m"] != BASE.epsilon_m:
        out.append(f"eps {r['epsilon_m'] * 1e3:g} mm")
    if r["capacity"] != BASE.capacity:
        out.append(f"cap {r['capacity']}")
    if tuple(r["env_rate_hz"]) != BASE.env_rate_hz:
        lo, hi = r["env_rate_hz"]
        out.append(f"env {lo:g} Hz" if lo == hi else f"env {lo:g}-{hi:g} Hz")
    if r.get("kernel", "numba") != "numba":
        out.append(r["kernel"])
    if r.get("recovery_speed_m_per_s") is not None:
        v = r["recovery_speed_m_per_s"]
        out.append("no recovery" if v == 0 else f"recovery {v * 1e3:g} mm/s")
    if r.get("advice", "none") != "none":
        out.append(r["advice"])
    return ", ".join(out) or "base (1 kHz, k 4000, eps 5 mm, cap 16, env 30-60 Hz)"


def plot_pareto(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    dims = list(dict.fromkeys(r["dimension"] for r in rows))
    cmap = plt.get_cmap("tab10")
    fig, axes = plt.subplots(1, 2, figsize=(13, 5.5), layout="constrained")
    for ax, err, name in ((axes[0], "wall_error_mm", "|felt wall - wall| [mm] (Fig. 14 push)"),
                          (axes[1], "drift_mm", "drift in the tight hole [mm] (Fig. 16 shaking)")):
        for i, d in enumerate(dims):
            rs = [r for r in rows if r["dimension"] == d and r.get(err) is not None and r.get("cpu_load_pct") is not None]
            ok = [r for r in rs if not r["unstable"]]
            bad = [r for r in rs if r["unstable"]]
            ax.scatter([r["cpu_load_pct"] for r in ok], [max(r[err], FLOOR_MM) for r in ok], s=22, color=cmap(i % 10),
                       label=d)
            ax.scatter([r["cpu_load_pct"] for r in bad], [max(r[err], FLOOR_MM) for r in bad], s=40, marker="x",
                       color=cmap(i % 10))
        front = pareto_front(rows, "cpu_load_pct", err)
        ax.plot([r["cpu_load_pct"] for r in front], [max(r[err], FLOOR_MM) for r in front], "k--", lw=0.8,
                label="Pareto front")
        for r in front:
            ax.annotate(short_label(r), (r["cpu_load_pct"], max(r[err], FLOOR_MM)), fontsize=6.5,
                        xytext=(4, 2), textcoords="offset points")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("cost: CPU load of the haptic loop [% of one core] (step p50 x rate)")
        ax.set_ylabel(name)
        ax.set_title(f"values below {FLOOR_MM:g} mm drawn at {FLOOR_MM:g} mm", fontsize=8)
        ax.grid(alpha=0.3, which="both")
    axes[0].legend(fontsize=7, loc="upper right")
    fig.suptitle("Speed / accuracy trade-off (simulated time; x: unstable)", fontsize=10)
    fig.savefig(path, dpi=90)
    plt.close(fig)


def plot_region(region: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from matplotlib.ticker import FixedLocator, NullLocator

    fig, ax = plt.subplots(figsize=(7.5, 5), layout="constrained")
    controllers = list(dict.fromkeys(r["controller"] for r in region))
    for i, c in enumerate(controllers):
        es = sorted((r for r in region if r["controller"] == c), key=lambda r: r["rate_hz"])
        # wide lines and big markers first, so a controller with the same region stays visible
        ax.plot([e["rate_hz"] for e in es], [e["largest_stable_stiffness_n_per_m"] or np.nan for e in es],
                marker="osD^v"[i % 5], ms=9 - 1.2 * i, lw=4 - 0.6 * i, alpha=0.85, label=c)
    ax.set_xscale("log")
    ax.set_yscale("log")
    # the rates swept, as plain numbers (log minor labels overlap on this span)
    rates = sorted({r["rate_hz"] for r in region})
    ax.xaxis.set_major_locator(FixedLocator(rates))
    ax.xaxis.set_minor_locator(NullLocator())
    ax.set_xticks(rates, [f"{r:g}" for r in rates])
    ax.set_xlabel("haptic rate [Hz]")
    ax.set_ylabel("largest stable contact stiffness [N/m]")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8, title="controller (damping b = 7.5 ms x k unless given)", title_fontsize=7)
    ax.set_title("Stable region (simulated time, stub 30-60 Hz, wall push + 6 s of 1 N hole shaking)", fontsize=9)
    fig.savefig(path, dpi=90)
    plt.close(fig)
