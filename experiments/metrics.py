"""The figures' metrics, computed from a :class:`~hapticproxy.experiments.harness.Trace`.

Every metric is defined here once (EXPERIMENTS.md quotes these definitions). Conventions: the
world frame of ``clients/scenes.py`` (+y towards the bottom wall), lengths in mm, angles in deg,
forces in N, energies in mJ; "the device" is the device handle mapped into the world (= the
peg's COM, see ``harness``); time windows are counted back from the end of the run, and "during
the hand" means from the moment the scripted hand starts pushing to the end of the run.
"""
from __future__ import annotations

import math

import numpy as np

from ..clients.scenes import IN_HOLE_POSE, WALL_CONTACT_Y_COM_M

#: Where the bottom wall is, as the peg's y_COM touching it (the paper's 124 mm).
WALL_Y_MM = WALL_CONTACT_Y_COM_M * 1e3
#: The peg resting in the tight hole (x, y [mm], angle [deg]).
HOLE_X_MM, HOLE_Y_MM, HOLE_DEG = IN_HOLE_POSE[0] * 1e3, IN_HOLE_POSE[1] * 1e3, math.degrees(IN_HOLE_POSE[2])

#: Windows [s] at the end of a run.
FELT_WINDOW_S = 1.0       # where the wall is felt: mean over the last second
CYCLE_WINDOW_S = 2.0      # limit cycle and injected energy: the last two seconds
#: Settled: the device moves less than this over the limit-cycle window (half peak-to-peak).
SETTLED_MM = 0.1
SETTLED_DEG = 0.1
#: Unstable (hole experiments): the rendered wrench did net positive work on the device over the
#: last two seconds (the interaction is active: it feeds the motion instead of absorbing the
#: hand's work) by more than this [mJ] (a tolerance far below the tens of mJ a shaken peg
#: exchanges), or the device reached its rotation end-stop.
ACTIVE_TOLERANCE_MJ = 1.0
ENDSTOP_DEG = 56.0
#: ... or the device's COM went this far from the hole: the 80 mm peg is out of it (a run-away).
LEFT_HOLE_MM = 50.0
#: Shaking periods averaged at the start (after one period of transient) and at the end.
GROWTH_PERIODS = 3


def _after(tr, t0: float) -> np.ndarray:
    return tr.t_s >= t0


def _last(tr, seconds: float) -> np.ndarray:
    return tr.t_s >= tr.t_s[-1] - seconds


def force_step_max_n(tr) -> float:
    """Largest change of the force written to the device between two consecutive haptic steps,
    over the time the hand acts: max_k |(fx, fy)[k] - (fx, fy)[k-1]| [N] (after the safety
    filter: what the device was asked to render; the rate limit bounds it by
    ``force_rate_n_per_s / rate_hz``)."""
    sel = _after(tr, tr.hand_start_s)
    f = tr.cmd[sel, :2]
    if len(f) < 2:
        return 0.0
    return float(np.max(np.linalg.norm(np.diff(f, axis=0), axis=1)))


def env_force_step_max_n(tr) -> float:
    """The same for the local model's output before the controller and the safety filter (the
    environment wrench at the hand point, impulsive steps of eq. 12 included) [N]."""
    sel = _after(tr, tr.hand_start_s)
    f = tr.env[sel, :2]
    if len(f) < 2:
        return 0.0
    return float(np.max(np.linalg.norm(np.diff(f, axis=0), axis=1)))


def penalty_jump_max_n(tr) -> float | None:
    """Simulated runs: the largest change of the model's penalty + friction force across a
    haptic step in which a model update was applied [N] -- the discontinuity at model updates
    that proxy deformation removes (None in real-time runs: not recorded)."""
    if tr.penalty is None or tr.update_step is None:
        return None
    sel = _after(tr, tr.hand_start_s)[1:] & tr.update_step[1:]
    if not np.any(sel):
        return 0.0
    d = np.linalg.norm(np.diff(tr.penalty[:, :2], axis=0), axis=1)
    return float(np.max(d[sel]))


def injected_energy_mj(tr, seconds: float = CYCLE_WINDOW_S) -> float:
    """Net work the wrench written to the device did on the device over the last ``seconds``:
    sum_k (F_cmd . v_dev)[k] dt [mJ] (force and torque). Positive: the interaction gave the
    user energy over that window (it sustains or grows a motion: active); zero for a device at
    rest; negative: it absorbed energy (passive). The device and proxy start at the same angle
    in every experiment, so the device frame of the command is the world's."""
    sel = _last(tr, seconds)
    p = np.sum(tr.cmd[sel] * tr.dev_vel[sel], axis=1)
    return float(np.sum(p) * tr.dt_s * 1e3)


def common_metrics(tr) -> dict:
    """Accuracy-independent facts of every run: mode, rates, faults, safety counters."""
    out = {
        "mode": tr.mode,
        "engine": tr.spec.engine,
        "contact_frame": tr.spec.contact_frame,
        "controller": tr.spec.controller,
        "policy": tr.spec.policy,
        "epsilon_mm": tr.spec.epsilon_m * 1e3,
        "stiffness_n_per_m": tr.spec.stiffness_n_per_m,
        "damping_n_s_per_m": tr.spec.damping_n_s_per_m,
        "haptic_rate_hz": tr.rate_hz,
        "achieved_rate_hz": round(tr.achieved_rate_hz, 2),
        "env_rate_hz": round(tr.env_rate_hz, 1),
        "model_updates": int(tr.updates[-1]),
        "faults": tr.faults,
        "model_nonfinite": tr.model_nonfinite,
        "loop_exception": tr.extra.get("loop_exception", "") or None,
        "rate_limited_steps": tr.rate_limited,
        "saturated_steps": tr.saturated,
        "force_step_max_n": round(force_step_max_n(tr), 4),
        "env_force_step_max_n": round(env_force_step_max_n(tr), 3),
        "energy_injected_mj": round(injected_energy_mj(tr), 4),
    }
    pj = penalty_jump_max_n(tr)
    if pj is not None:
        out["penalty_jump_max_n"] = round(pj, 4)
    if tr.compute_us:
        out["compute_us"] = {k: tr.compute_us.get(k) for k in ("p50", "p99", "max")}
    if tr.lateness_us:
        out["lateness_us"] = {k: tr.lateness_us.get(k) for k in ("p50", "p99", "max")}
    return out


def static_contact_metrics(tr) -> dict:
    """Fig. 14 (the hand pushes the peg onto the bottom wall with 0.5 N).

    - ``felt_wall_mm``: where the wall is felt: the device's y_COM averaged over the last
      second, when it rests (or cycles) against the wall [mm]; the wall is at 124 mm
      (``wall_mm``); ``wall_error_mm`` = felt - 124 (positive: felt beyond the wall).
    - ``first_contact_mm``: the device's y_COM at the first haptic step with a local contact
      (where the model learnt of the wall).
    - ``max_depth_mm``: the deepest the device went, max y_COM - 124 mm.
    - ``limit_cycle_amplitude_mm``: half the peak-to-peak of the device's y_COM over the last
      two seconds (0 for a device at rest); ``limit_cycle_rotation_deg``: the same for its angle.
    - ``settled``: both amplitudes below 0.1 mm and 0.1 deg.
    - ``final_force_n``: the y force written to the device, mean of the last 0.5 s (-0.5 N
      balances the push).
    """
    y = tr.dev[:, 1] * 1e3
    th = np.degrees(tr.dev[:, 2])
    felt = float(np.mean(y[_last(tr, FELT_WINDOW_S)]))
    cyc = _last(tr, CYCLE_WINDOW_S)
    amp = 0.5 * float(np.ptp(y[cyc]))
    rot = 0.5 * float(np.ptp(th[cyc]))
    touched = np.nonzero(tr.contacts > 0)[0]
    out = {
        "wall_mm": WALL_Y_MM,
        "felt_wall_mm": round(felt, 2),
        "wall_error_mm": round(felt - WALL_Y_MM, 2),
        "first_contact_mm": round(float(y[touched[0]]), 2) if len(touched) else None,
        "max_depth_mm": round(float(np.max(y)) - WALL_Y_MM, 2),
        "limit_cycle_amplitude_mm": round(amp, 3),
        "limit_cycle_rotation_deg": round(rot, 3),
        "settled": bool(amp < SETTLED_MM and rot < SETTLED_DEG),
        "final_force_n": round(float(np.mean(tr.cmd[_last(tr, 0.5), 1])), 3),
    }
    out.update(common_metrics(tr))
    return out


def _period_energy(tr, t_start: float, period_s: float, n_periods: int, from_end: bool) -> float:
    """Mean kinetic energy of the device over ``n_periods`` whole shaking periods [J]."""
    m, izz = tr.extra.get("device_mass_kg", 0.4), tr.extra.get("device_izz_kg_m2", 1e-3)
    ke = 0.5 * m * (tr.dev_vel[:, 0] ** 2 + tr.dev_vel[:, 1] ** 2) + 0.5 * izz * tr.dev_vel[:, 2] ** 2
    span = n_periods * period_s
    if from_end:
        sel = tr.t_s >= tr.t_s[-1] - span
    else:
        sel = (tr.t_s >= t_start) & (tr.t_s < t_start + span)
    return float(np.mean(ke[sel])) if np.any(sel) else float("nan")


def hole_metrics(tr) -> dict:
    """Figs. 16 and 17 (the peg, rotated 90 deg, in the exactly fitting hole, shaken along x by
    the hand's sinusoidal force). Over the time the hand acts:

    - ``drift_mm``: the largest distance of the device's COM from the in-hole position
      (0, 134 mm) [mm] (the static compliance F/k is part of it: 1 N / 4000 N/m = 0.25 mm).
    - ``x_travel_mm``: peak-to-peak of the device's x (how far the hole lets it move across).
    - ``y_drift_mm``: the device's mean y over the last second minus 134 mm (+: deeper).
    - ``rotation_deg``: the largest |angle - 90 deg| of the device.
    - ``energy_growth``: the device's kinetic energy averaged over the last three shaking
      periods divided by that over three periods after the first one (informative: a stable
      forced response repeats itself, about 1; the drift that proxy deformation allows also
      makes it grow, boundedly).
    - ``energy_injected_mj``: the net work of the rendered wrench on the device over the last
      two seconds (see :func:`injected_energy_mj`; negative: the interaction absorbs).
    - ``unstable``: a fault or non-finite value stopped the rendering, or the interaction was
      active (``energy_injected_mj`` > 1 mJ: it feeds the motion), or the device reached its
      rotation end-stop (more than 56 deg from where it started; the hole allows about none), or
      its COM went more than 50 mm from the hole (``drift_mm``: the 80 mm peg is out of it).
      The drift that proxy deformation allows (the paper's "several mm and up to 20 deg") is
      not instability.
    """
    sel = _after(tr, tr.hand_start_s)
    x = tr.dev[sel, 0] * 1e3
    y = tr.dev[sel, 1] * 1e3
    th = np.degrees(tr.dev[sel, 2])
    dist = np.hypot(x - HOLE_X_MM, y - HOLE_Y_MM)
    rot = np.abs(th - HOLE_DEG)
    period = 1.0 / tr.spec.hand.frequency_hz if tr.spec.hand.frequency_hz > 0 else 1.0
    e0 = _period_energy(tr, tr.hand_start_s + period, period, GROWTH_PERIODS, False)
    e1 = _period_energy(tr, 0.0, period, GROWTH_PERIODS, True)
    growth = e1 / e0 if e0 > 0 else float("inf") if e1 > 0 else 1.0
    endstop = float(np.max(rot)) > ENDSTOP_DEG
    out = {
        "drift_mm": round(float(np.max(dist)), 3),
        "x_travel_mm": round(float(np.ptp(x)), 3),
        "y_drift_mm": round(float(np.mean(tr.dev[_last(tr, 1.0), 1]) * 1e3 - HOLE_Y_MM), 3),
        "rotation_deg": round(float(np.max(rot)), 3),
        "energy_growth": round(float(growth), 3),
    }
    out.update(common_metrics(tr))
    out["unstable"] = bool(tr.faults > 0 or tr.model_nonfinite > 0 or endstop or out["drift_mm"] > LEFT_HOLE_MM
                           or out["energy_injected_mj"] > ACTIVE_TOLERANCE_MJ)
    return out


#: The felt surface is "where it is" within this [mm] (issue 15's goal, after recovery).
SURFACE_BAND_MM = 0.5


def felt_surface_metrics(tr, *, surface_m: float, axis: int, push_n: float, sign: float = 1.0) -> dict:
    """Where a surface pushed against by the hand's constant ``push_n`` is felt (issue 15): the
    device's coordinate ``axis`` against the true surface, ``sign`` the direction of the push
    (+1: the push moves the device towards +axis). Positions in mm, along the push.

    - ``surface_error_mm``: the device position averaged over the last second, minus the true
      surface, minus the penalty penetration the push needs (push / (k n), n the contacts
      touching at the end of the run): 0 when the wall is felt exactly where it is; positive:
      beyond it (the proxy deformed and kept it).
    - ``surface_reached_s``: time from the arrival (the first step after the hand started at
      which the device is within 0.5 mm of that position, or beyond it) until it is within
      0.5 mm for good (``inf``: never).
    - ``recovery_force_step_max_n``: the largest penalty force the recovery itself added in one
      step (at a fixed pose: k x the distance recovered; its bound is the force rate x the
      period); ``recovery_command_step_max_n``: the largest change of the command written to the
      device between two steps while the model was recovering (impacts at other contacts
      included); ``recovery_penalty_step_max_n``: the same for the model's penalty force;
      ``recovery_energy_mj``: the work the recovery did on the proxy. 0 if it never recovered.
    """
    k = tr.spec.stiffness_n_per_m
    n_touch = max(1, int(tr.extra.get("touching_contacts", 1)))
    rest_mm = (surface_m + sign * push_n / (k * n_touch)) * 1e3
    pos = tr.dev_xyz if tr.dev_xyz is not None else tr.dev
    x = sign * (pos[:, axis] * 1e3 - rest_mm)
    err = float(np.mean(x[_last(tr, FELT_WINDOW_S)]))
    arrived = np.nonzero((tr.t_s >= tr.hand_start_s) & (x >= -SURFACE_BAND_MM))[0]
    reached = math.inf
    if len(arrived):
        i0 = int(arrived[0])
        out_band = np.nonzero(np.abs(x[i0:]) > SURFACE_BAND_MM)[0]
        if not len(out_band):
            reached = 0.0
        elif i0 + int(out_band[-1]) + 1 < len(x):
            reached = float(tr.t_s[i0 + int(out_band[-1]) + 1] - tr.t_s[i0])
    rec = tr.recovering if tr.recovering is not None else np.zeros(len(tr.t_s), dtype=np.int64)
    during = (rec[1:] > 0)
    cmd = tr.cmd_xyz if tr.cmd_xyz is not None else tr.cmd[:, :2]
    fstep = np.linalg.norm(np.diff(cmd, axis=0), axis=1)
    pstep = (np.linalg.norm(np.diff(tr.penalty[:, :2], axis=0), axis=1) if tr.penalty is not None
             else np.zeros_like(fstep))
    own = tr.recovery_step_n if tr.recovery_step_n is not None else np.zeros(len(tr.t_s))
    return {
        "surface_error_mm": round(err, 3),
        "surface_reached_s": round(reached, 3) if math.isfinite(reached) else "inf",
        "recovery_force_step_max_n": round(float(np.max(own)), 4),
        "recovery_command_step_max_n": round(float(np.max(fstep[during])) if np.any(during) else 0.0, 4),
        "recovery_penalty_step_max_n": round(float(np.max(pstep[during])) if np.any(during) else 0.0, 4),
        "recovery_energy_mj": round(1e3 * float(tr.extra.get("recovery_energy_j", 0.0)), 3),
    }
