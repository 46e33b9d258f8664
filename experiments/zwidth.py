"""Z-width (Colgate and Brown): the (stiffness, damping) region of a virtual wall the server renders
stably, per haptic rate and simulated device kind, against Colgate and Schenkel's passivity bound
(issue 31 item 5).

The rig (simulated time, one process): the server's ``LocalModel`` with the configured update
policy and contact frame, the controller kernel (``control.haptic_step``, as the loop calls it:
coupling, force channel, safety filter with its caps and force-rate limit), the simulated device
of the kind with its default physical parameters (mass, viscous damping b, caps) and the
settings the loop derives from it (``devices.safe.derive``), and an analytic engine at 60 Hz
that reports one contact: the tool's lowest point against the wall y = 0 (normal +y), taken
where the engine's tool stops at the wall (the engine frame), within epsilon 5 mm, so the model
knows the wall before it is touched. The tool is a 40 mm box of the device's own mass, so with
direct coupling the wall acts on the device alone. The contact is a single point under the
centre of mass: the wall's stiffness and damping are the contact's (K, B), one spring, no torque.

The device is stepped ``DEVICE_SUBSTEPS`` times per haptic period under the held command: a
continuous device behind the zero-order hold. (Stepped once per period, the simulated device's
symplectic step keeps a sampled spring's energy exactly and hides the hold's energy leak, K T / 2,
that Colgate and Schenkel's bound is about: an undamped planar wall of 12 kN/m at 1 kHz, three
times the bound, settles that way and keeps a 23 mm cycle with the hold.)

The hand is the worst case of Colgate and Brown's analysis: a constant push of ``PUSH_N`` into
the wall with no mass and no damping of its own (``hand = {type = "constant"}``), starting with
the device ``GAP_M`` off the wall, so the device strikes it at about 0.1 m/s and then rests on it
under the push. Each point is judged over the window ``WINDOW_START_S`` to ``WINDOW_END_S``
after the first contact (the handle reaching the wall), long enough for the impact's bouncing to
give way to the wall's own behaviour (:func:`classify`):

- ``unstable``: a fault, a non-finite value, the device never resting on the wall, or a swing
  above a limit that does not shrink steadily (from one of ``SEGMENTS`` parts of the window to the
  next, by a factor below ``GROWTH_MIN`` each time): the handle more than ``PTP_MAX_M`` peak to peak (the issue's 0.1 mm), or the force
  written to the device more than ``FORCE_PTP_MAX_FRACTION`` of the push (a chatter too small to
  see in position at a stiff wall, felt as a buzz);
- ``ringing``: above a limit but shrinking (stable, lightly damped; near the bound);
- ``settled``: within both limits (a run at rest to rounding for half a second stops early).

The issue's reading, the handle's peak to peak 1-1.5 s after contact, is reported beside it
(``ptp_1s_mm``): just inside the bound a wall still swings more than 0.1 mm then.

Colgate and Schenkel: a wall K, B sampled at period T (zero-order hold) on a device with
physical damping b is passive if ``b > K T / 2 + |B|``; drawn as ``B = b - K T / 2``.

``run_zwidth(out, ...)`` writes ``zwidth_<rate>hz.png`` per rate and ``zwidth.json``; it returns
the summary (``--json`` prints it).
"""
from __future__ import annotations

import json
import math
import os
from dataclasses import asdict, dataclass

import numpy as np

from ..server import config as cfg
from ..server import control as ctl
from ..server import stability
from ..server.devices import safe
from ..server.devices.base import DS_TWIST, empty_state
from ..server.devices.sim import effective_config, make_sim_device
from ..server.model import ContactParams, LocalModel, ToolSpec

KINDS = ("1dof", "planar", "spatial")
#: 0.5 kHz is the ``fast`` preset's 512 Hz, so the preset is measured at its own rate
RATES_HZ = (512.0, 1000.0, 4000.0)
CONTROLLERS = ("direct", "four_channel")
K_GRID_N_PER_M = (100.0, 200.0, 500.0, 1e3, 2e3, 5e3, 1e4, 2e4, 5e4, 1e5, 2e5, 5e5, 1e6)
B_GRID_N_S_PER_M = (0.0, 0.3, 1.0, 3.0, 10.0, 30.0, 100.0, 300.0, 1000.0)
QUICK_K_GRID = (300.0, 3e3, 3e4, 3e5)
QUICK_B_GRID = (0.0, 1.0, 30.0)
PUSH_N = 1.0
GAP_M = 0.002
TOOL_SIZE_M = 0.04
ENGINE_RATE_HZ = 60.0
EPSILON_M = 0.005
#: judged over this window after the first contact: long enough for a wall just beyond the bound to
#: leave the impact's bouncing (which decays for seconds) for its own limit cycle (1.25x the bound:
#: a 0.4 mm p-p cycle from 6 s, still decaying 1-2 s after contact)
WINDOW_START_S = 6.0
WINDOW_END_S = 8.0
#: the issue's transparency reading, reported beside the verdict: p-p 1-1.5 s after contact
EARLY_WINDOW_S = (1.0, 1.5)
#: a run whose handle and force have not moved by more than this over the last half second (at
#: rest on the wall to rounding) is settled and stops there: an unstable wall never rests
REST_M, REST_N = 1e-12, 1e-9
REST_S = 0.5
#: the device's own steps per haptic period (module docstring)
DEVICE_SUBSTEPS = 16
#: the issue's limit cycle: peak to peak of the handle along the normal over the window
PTP_MAX_M = 1e-4
#: force chatter: peak to peak of the command along the normal, as a fraction of the push
FORCE_PTP_MAX_FRACTION = 0.1
#: an oscillation above the limits whose peak to peak shrinks below this ratio from each of
#: ``SEGMENTS`` equal parts of the window to the next is ringing out, not unstable: a lightly
#: damped wall (a bouncing that dies down and flares up again is not)
GROWTH_MIN = 0.9
SEGMENTS = 4
LAYER_CHOICES = ("on", "off")
#: the velocity the controller reads: the simulated device's own (exact), or the backward difference
#: of its positions over one period, as Colgate and Schenkel's wall takes it (and an encoder-only
#: device's driver gives it): a damper then acts half a period late
VELOCITIES = ("device", "difference")


@dataclass
class Point:
    """One (K, B) on one rig: what the window saw and the verdict."""

    stiffness_n_per_m: float
    damping_n_s_per_m: float
    stable: bool                # settled or ringing
    verdict: str                # settled | ringing | unstable (``classify``)
    reason: str
    contact_s: float            # first contact, from the run's start (nan: never)
    ptp_mm: float               # handle along the normal over the window, peak to peak
    force_ptp_n: float          # command along the normal over the window, peak to peak
    growth: float               # the largest ptp ratio of a window segment to the one before (0: no motion)
    ptp_1s_mm: float            # the reading: handle p-p 1-1.5 s after contact
    refused: str                # "" when the server accepts the setting; else the config's reason (the key)
    colgate_schenkel: bool      # inside b > K T / 2 + |B|


def classify(ptp_m: float, force_ptp_n: float, growth: float, push_n: float, *, fault: str = "") -> tuple[str, str]:
    """``(verdict, reason)``: ``settled`` (within both limits over the window), ``ringing`` (above
    a limit but shrinking steadily: ``growth``, the largest ratio of a segment's swing to the one
    before, below ``GROWTH_MIN``; stable, lightly damped) or
    ``unstable`` (a fault, a non-finite value, or above a limit and not shrinking)."""
    if fault:
        return "unstable", fault
    if not (math.isfinite(ptp_m) and math.isfinite(force_ptp_n)):
        return "unstable", "non-finite"
    if ptp_m > PTP_MAX_M:
        why = f"{ptp_m * 1e3:.3g} mm p-p"
    elif force_ptp_n > FORCE_PTP_MAX_FRACTION * push_n:
        why = f"force {force_ptp_n:.3g} N p-p"
    else:
        return "settled", ""
    if growth < GROWTH_MIN:
        return "ringing", f"{why}, shrinking x{growth:.2f}"
    return "unstable", f"limit cycle {why}, x{growth:.2f}"


#: the layer's options a z-width run may set: (its argument, the ``[passivity]`` key, the flag)
LAYER_OPTIONS = (("damping_credit", "damping_credit", "--damping-credit"),
                 ("input_credit", "input_credit", "--input-credit"),
                 ("budget_j", "initial_budget_j", "--budget-j"))


def layer_settings(layer: str | None, damping_credit: float | None = None, input_credit: float | None = None,
                   budget_j: float | None = None) -> tuple[dict, str]:
    """The ``[passivity]`` table for ``--layer`` (and ``--damping-credit``: the share of the
    device's damping the tank credits; ``--input-credit`` and ``--budget-j``: the share of the
    hand's input the tank keeps and the tank at start, the walls setting 0.45 / 0.002) and a
    note: empty table and a note saying the option is ignored when the config has no
    ``[passivity]`` table (the layer not merged). No ``--layer`` is ``off``: the bare hold's
    region, whatever the server's passivity settings (with ``input_credit`` below 1 the layer
    settles walls beyond the bound: EXPERIMENTS.md, passivity)."""
    given = {"damping_credit": damping_credit, "input_credit": input_credit, "budget_j": budget_j}
    for arg, _key, flag in LAYER_OPTIONS:
        if given[arg] is not None and layer != "on":
            raise ValueError(f"{flag}: applies with --layer on only")
    if layer is None:
        table, note = layer_settings("off")
        return table, ("" if table else note)
    if layer not in LAYER_CHOICES:
        raise ValueError(f"--layer: expected on or off, got {layer!r}")
    try:
        has = "passivity" in cfg.load({}).data
    except cfg.ConfigError:  # pragma: no cover - the defaults always load
        has = False
    if not has:
        return {}, (f"--layer {layer} ignored: this server has no [passivity] settings (the passivity layer, "
                    f"issue 31 item 3, is not merged); measured without a layer")
    table = {"passivity": {"enabled": layer == "on"}}
    for arg, key, flag in LAYER_OPTIONS:
        if given[arg] is not None:
            table["passivity"][key] = given[arg]
            try:
                cfg.load(table)
            except cfg.ConfigError as exc:
                raise ValueError(f"{flag}: {exc}") from None
    try:
        cfg.load(table)
    except cfg.ConfigError as exc:
        return {}, f"--layer {layer} ignored: [passivity] does not take 'enabled' ({exc}); measured with its defaults"
    return table, ""


def layer_label(res: dict) -> str:
    """How the plots name the passivity layer's setting of a run (``run_zwidth``'s result)."""
    if res.get("layer") != "on":
        return "passivity layer off"
    label = f"passivity layer on, damping credit {res.get('damping_credit', 1.0):g}"
    if res.get("input_credit") not in (None, 1.0) or res.get("initial_budget_j") not in (None, 0.01):
        label += (f", input credit {res.get('input_credit', 1.0):g}, budget "
                  f"{1e3 * res.get('initial_budget_j', 0.01):g} mJ")
    return label


def device_physics(kind: str, rate_hz: float) -> tuple[float, float]:
    """The simulated device's default moving mass [kg] and translational damping b [N s/m]."""
    c = effective_config({"kind": kind}, period_s=1.0 / rate_hz)
    return float(c["mass_kg"]), float(c["damping_n_s_per_m"])


def colgate_schenkel(k_n_per_m: float, b_n_s_per_m: float, device_b_n_s_per_m: float, rate_hz: float) -> bool:
    """Colgate and Schenkel's passivity condition ``b > K T / 2 + |B|``."""
    return device_b_n_s_per_m > k_n_per_m / (2.0 * rate_hz) + abs(b_n_s_per_m)


def _settings_dict(kind: str, rate_hz: float, controller: str, k: float, b: float, layer_table: dict,
                   allow: bool) -> dict:
    d = {"loop": {"rate_hz": rate_hz}, "controller": {"type": controller},
         "model": {"stiffness_n_per_m": k, "damping_n_s_per_m": b},
         "safety": {"allow_outside_stable_region": allow},
         "device": {"driver": "sim", "kind": kind}}
    d.update(layer_table)
    return d


def refusal(kind: str, rate_hz: float, controller: str, k: float, b: float, layer_table: dict) -> str:
    """The key the server refuses this setting on (config's stable region, or the device's own
    limits via ``safe.derive``), "" when it is accepted."""
    try:
        s = cfg.load(_settings_dict(kind, rate_hz, controller, k, b, layer_table, False))
        dev = make_sim_device({"kind": kind}, period_s=1.0 / rate_hz, clock_ns=lambda: 0)
        safe.derive(s, dev.info)
    except cfg.ConfigError as exc:
        return exc.key
    return ""


def run_point(kind: str, rate_hz: float, k: float, b: float, *, controller: str = "direct",
              layer_table: dict | None = None, push_n: float = PUSH_N, keep_trace: bool = False,
              velocity: str = "device", device: dict | None = None):
    """Render the wall (K = ``k``, B = ``b``) on the ``kind`` device at ``rate_hz`` under the
    constant push; returns ``(verdict, reason, contact_s, ptp_m, force_ptp_n, growth, ptp_1s_m)`` (and the trace of
    the handle's height and the command along the normal when ``keep_trace``). ``device``: keys of the
    simulated device's table over its defaults (``damping_n_s_per_m = 0``: no physical damping); the
    server's settings are derived from that device. ``layer_table`` None: the layer off (the bare
    hold)."""
    layer_table = layer_settings(None)[0] if layer_table is None else layer_table
    settings = cfg.load(_settings_dict(kind, rate_hz, controller, k, b, layer_table, True))
    dt = settings.period_ns * 1e-9
    mass, _ = device_physics(kind, rate_hz)
    push = {"1dof": [-push_n], "planar": [0.0, -push_n, 0.0], "spatial": [0.0, -push_n, 0.0, 0.0, 0.0, 0.0]}[kind]
    dev_cfg = {"kind": kind, "hand": {"type": "constant", "wrench": push, "start": "server"}}
    if kind == "1dof":
        dev_cfg["axis"] = [0.0, 1.0, 0.0]
    extra = dict(device or {})
    dev_cfg.update(extra)
    # the device advances in DEVICE_SUBSTEPS steps per haptic period under the held command: a
    # continuous device behind a zero-order hold (stepped once per period, its symplectic step keeps
    # a sampled spring's energy and hides the hold's energy leak that Colgate and Schenkel bound)
    device = make_sim_device(dev_cfg, period_s=dt / DEVICE_SUBSTEPS, clock_ns=lambda: 0)
    settings = safe.derive(settings, make_sim_device({"kind": kind, **extra}, period_s=dt, clock_ns=lambda: 0).info)
    mc = settings["model"]
    cparams = ContactParams(mc["stiffness_n_per_m"], mc["damping_n_s_per_m"], mc["restitution"], mc["mu_static"],
                            mc["mu_kinetic"])
    half = 0.5 * TOOL_SIZE_M
    if kind == "1dof":
        tool = ToolSpec.one_dof(mass, axis=(0.0, 1.0, 0.0))
        q0 = [half + GAP_M]
    elif kind == "planar":
        tool = ToolSpec.planar(mass, mass * 2 * TOOL_SIZE_M ** 2 / 12)
        q0 = [0.0, half + GAP_M, 0.0]
    else:
        tool = ToolSpec.spatial(mass, (mass * 2 * TOOL_SIZE_M ** 2 / 12,) * 3)
        q0 = [0.0, half + GAP_M, 0.0, 1.0, 0.0, 0.0, 0.0]
    m = LocalModel(tool, cparams, period_s=dt, policy=mc["policy"], epsilon_m=EPSILON_M, capacity=4,
                   recovery_speed_m_per_s=mc["recovery_speed_m_per_s"])
    m.reset(q0)
    c = ctl.Controller(settings, kind, device.limits)
    c.set_moving_figures(device.info)  # as the loop does: the passivity layer's work prediction
    device.enable()
    row = empty_state()
    device.read(row)
    hs = m.hand_state()
    c.set_offset(*ctl.index_offset(kind, row[:7], hs[:7], (0.0, 1.0, 0.0), (0.0, 1.0, 0.0)))
    c.cs[ctl.CS_GAIN] = c.cs[ctl.CS_TARGET] = 1.0   # rendered in full from the first step
    y_dev0 = float(row[1])
    if velocity not in VELOCITIES:
        raise ValueError(f"velocity: expected one of {', '.join(VELOCITIES)}, got {velocity!r}")
    differ = velocity == "difference"
    prev_pos = row[:3].copy()
    kargs = m.kernel_args()
    upd_every = max(1, int(round(rate_hz / ENGINE_RATE_HZ)))
    n_max = int(round((WINDOW_END_S + 1.0) * rate_hz))  # no contact within 1 s: never reached
    ys = np.full(n_max, np.nan)
    fs = np.full(n_max, np.nan)
    contact_i = -1
    end_i = n_max
    fault = ""
    at_rest = False
    rest_n = int(round(REST_S * rate_hz))
    for i in range(n_max):
        if i % upd_every == 0:
            _report_wall(m, half)
        device.read(row)
        if differ:  # the linear velocity from the positions (the rotation's is not the wall's)
            row[DS_TWIST:DS_TWIST + 3] = (row[:3] - prev_pos) / dt
            prev_pos[:] = row[:3]
        rc = ctl.haptic_step(c.cp, c.cs, c.cc, row, c.cmd, 1, *kargs, c.hand, c.R, c.c)
        drc = 0
        for _ in range(DEVICE_SUBSTEPS):
            drc = drc or device.write(c.cmd)
        # the handle's height above the wall (the device mapped onto the proxy's lowest point)
        y = float(row[1]) - y_dev0 + GAP_M
        ys[i] = y
        fs[i] = float(c.cmd[1])
        if rc != 0 or drc != 0:
            fault = f"fault (controller rc {rc}, device {drc})"
            end_i = i + 1
            break
        if not (math.isfinite(y) and math.isfinite(fs[i])):
            fault = "non-finite"
            end_i = i + 1
            break
        if contact_i < 0 and y <= 0.0:
            contact_i = i
            end_i = min(n_max, i + int(round(WINDOW_END_S * rate_hz)))
        if i + 1 >= end_i:
            break
        if contact_i >= 0 and (i - contact_i) % rest_n == 0 and i - contact_i >= rest_n:
            if np.ptp(ys[i + 1 - rest_n:i + 1]) < REST_M and np.ptp(fs[i + 1 - rest_n:i + 1]) < REST_N:
                at_rest = True
                end_i = i + 1
                break
    cnt = c.counters()
    if not fault and (cnt["speed_trips"] or cnt["nonfinite"] or m.counters()["nonfinite"]):
        fault = f"fault (speed trips {cnt['speed_trips']}, non-finite {cnt['nonfinite']})"
    if not fault and contact_i < 0:
        fault = "never reached the wall"
    contact_s = contact_i / rate_hz if contact_i >= 0 else math.nan
    ptp = fptp = growth = ptp_1s = math.nan
    if not fault:
        a0, a1 = (contact_i + int(round(t * rate_hz)) for t in EARLY_WINDOW_S)
        ptp_1s = float(np.ptp(ys[a0:min(a1, end_i)])) if a0 < end_i else 0.0
        a = contact_i + int(round(WINDOW_START_S * rate_hz))
        if at_rest:
            a = end_i - rest_n
        w_y, w_f = ys[a:end_i], fs[a:end_i]
        ptp, fptp = float(np.ptp(w_y)), float(np.ptp(w_f))
        # of the position, or of the force where that is what swings (a stiff wall's chatter)
        growth = _growth(w_y if ptp > PTP_MAX_M else w_f)
    verdict_, reason = classify(ptp, fptp, growth, push_n, fault=fault)
    out = (verdict_, reason, contact_s, ptp, fptp, growth, ptp_1s)
    if keep_trace:
        return out + (ys[:end_i].copy(), fs[:end_i].copy())
    return out


def _growth(sig: np.ndarray) -> float:
    """The largest ratio of one segment's peak to peak to the one before, over ``SEGMENTS`` equal
    segments: below 1 only while every segment swings less than the last (ringing out); a bouncing
    that dies down and flares up again is not."""
    n = len(sig) // SEGMENTS
    if n < 2:
        return 0.0
    p = [float(np.ptp(sig[i * n:(i + 1) * n])) for i in range(SEGMENTS)]
    return max((b / a if a > 0 else (0.0 if b == 0 else math.inf)) for a, b in zip(p, p[1:]))


def _report_wall(m: LocalModel, half: float) -> None:
    """The engine: its tool follows the proxy and stops at the wall; one contact, the tool's
    lowest point under its centre, reported within epsilon."""
    q = m.q.copy()
    low = float(q[0] if m.dof == 1 else q[1]) - half
    if low < 0.0:
        if m.dof == 1:
            q[0] -= low
        else:
            q[1] -= low
        low = 0.0
    if low <= EPSILON_M:
        x = 0.0 if m.dof == 1 else float(q[0])
        z = float(q[2]) if m.dof == 6 else 0.0
        m.update(np.array([[0, 1, 0]], dtype=np.int64), np.array([[x, 0.0, z]]), np.array([[0.0, 1.0, 0.0]]),
                 np.array([low]), np.zeros(1), tool_q=q)
    else:
        m.update(np.zeros((0, 3), dtype=np.int64), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), np.zeros(0),
                 tool_q=q)


def sweep(kind: str, rate_hz: float, *, controller: str = "direct", k_grid=K_GRID_N_PER_M, b_grid=B_GRID_N_S_PER_M,
          layer_table: dict | None = None, velocity: str = "device", log=None) -> list[Point]:
    """Every (K, B) of the grid on one rig."""
    _, dev_b = device_physics(kind, rate_hz)
    pts = []
    for k in k_grid:
        for b in b_grid:
            verdict_, reason, t_c, ptp, fptp, growth, ptp_1s = run_point(kind, rate_hz, k, b, controller=controller,
                                                                         layer_table=layer_table, velocity=velocity)
            pts.append(Point(float(k), float(b), verdict_ != "unstable", verdict_, reason, t_c, ptp * 1e3, fptp, growth,
                             ptp_1s * 1e3,
                             refusal(kind, rate_hz, controller, k, b, layer_table or {}),
                             colgate_schenkel(k, b, dev_b, rate_hz)))
    if log:
        n = sum(p.stable for p in pts)
        log(f"zwidth {controller} {kind} {rate_hz:g} Hz: {n}/{len(pts)} stable")
    return pts


def region_summary(pts: list[Point]) -> dict:
    """Per damping of the grid, the largest stiffness stable with every softer grid stiffness
    stable too (the region's edge); and how the measurement and Colgate-Schenkel agree."""
    edge = {}
    for b in sorted({p.damping_n_s_per_m for p in pts}):
        row = sorted((p for p in pts if p.damping_n_s_per_m == b), key=lambda p: p.stiffness_n_per_m)
        k_ok = None
        for p in row:
            if not p.stable:
                break
            k_ok = p.stiffness_n_per_m
        edge[f"{b:g}"] = k_ok
    cs_in = [p for p in pts if p.colgate_schenkel]
    accepted = [p for p in pts if not p.refused]
    return {
        "stable": sum(p.stable for p in pts), "points": len(pts),
        "largest_stable_stiffness_by_damping": edge,
        "colgate_schenkel_inside": len(cs_in),
        "colgate_schenkel_inside_unstable": sum(not p.stable for p in cs_in),
        "outside_colgate_schenkel_stable": sum(p.stable and not p.colgate_schenkel for p in pts),
        "accepted_by_server": len(accepted),
        "accepted_by_server_unstable": [[p.stiffness_n_per_m, p.damping_n_s_per_m] for p in accepted if not p.stable],
    }


def marks(rate_hz: float, controller: str, generic: bool = False) -> list[tuple[str, float, float, str]]:
    """What the plot marks: the configured contact default, and the stable-region table's bound
    at this rate (``server/stability.py``, the figures the presets quote) with b = 7.5 ms x k and,
    where measured, with b = 30 N s/m. ``(label, K, B, marker)``; ``generic``: labels without
    the numbers (one legend for every panel)."""
    d = cfg.load({}).data["model"]
    out = [(f"config default ({d['stiffness_n_per_m']:g} N/m, {d['damping_n_s_per_m']:g} N s/m)",
            float(d["stiffness_n_per_m"]), float(d["damping_n_s_per_m"]), "*")]
    lim = stability.stable_contact_limits(rate_hz, controller)
    out.append(("stable-region table's bound at this rate, b = 7.5 ms x k (server/stability.py)" if generic else
                f"stable-region table: k_max {lim.k_max_n_per_m:g}, b = 7.5 ms k", lim.k_max_n_per_m,
                lim.b_max_n_s_per_m, "D"))
    kf = stability.fixed_damping_k_max(rate_hz, controller)
    if kf is not None:
        out.append(("stable-region table's bound with b = 30 N s/m (four_channel)" if generic else
                    f"stable-region table, b = 30: k_max {kf:g}", kf, stability.FIXED_DAMPING_N_S_PER_M, "P"))
    return out


def presets_at(rate_hz: float) -> list[str]:
    return [name for name, (table, _) in cfg.PRESETS.items() if float(table["loop"]["rate_hz"]) == rate_hz]


def plot_rate(path: str, rate_hz: float, results: dict, *, note: str = "", velocity: str = "device",
              layer: str = "") -> None:
    """One PNG per rate: a panel per controller and kind, the grid's stable / unstable points,
    the Colgate-Schenkel line and the marks."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ctrls = [c for c in results]
    kinds = list(next(iter(results.values())))
    fig, axes = plt.subplots(len(ctrls), len(kinds), figsize=(5.2 * len(kinds), 4.4 * len(ctrls) + 1.6), squeeze=False)
    b_floor = 0.1  # where B = 0 is drawn on the log axis
    for r, ctrl in enumerate(ctrls):
        for col, kind in enumerate(kinds):
            ax = axes[r][col]
            pts = [Point(**p) for p in results[ctrl][kind]["points"]]
            mass, dev_b = device_physics(kind, rate_hz)
            ys = lambda b: b if b > 0 else b_floor  # noqa: E731
            st = [p for p in pts if p.verdict == "settled"]
            ring = [p for p in pts if p.verdict == "ringing"]
            un = [p for p in pts if not p.stable]
            ax.scatter([p.stiffness_n_per_m for p in st], [ys(p.damping_n_s_per_m) for p in st], marker="o",
                       s=42, facecolors="tab:green", edgecolors="k", linewidths=0.4, label="measured stable (settled)",
                       zorder=3)
            ax.scatter([p.stiffness_n_per_m for p in ring], [ys(p.damping_n_s_per_m) for p in ring], marker="^",
                       s=46, facecolors="orange", edgecolors="k", linewidths=0.4,
                       label="measured stable, still ringing out", zorder=3)
            ax.scatter([p.stiffness_n_per_m for p in un], [ys(p.damping_n_s_per_m) for p in un], marker="x",
                       s=42, color="tab:red", label="measured unstable", zorder=3)
            refused = [p for p in pts if p.refused]
            ax.scatter([p.stiffness_n_per_m for p in refused], [ys(p.damping_n_s_per_m) for p in refused],
                       marker="s", s=110, facecolors="none", edgecolors="0.6", linewidths=0.8,
                       label="refused by the server's config", zorder=2)
            k_cs = np.logspace(1, math.log10(2 * dev_b * rate_hz), 200)
            b_cs = dev_b - k_cs / (2 * rate_hz)
            ok = b_cs > b_floor
            ax.plot(k_cs[ok], b_cs[ok], "b-", lw=1.6,
                    label="Colgate-Schenkel bound b = K T / 2 + |B| (b: the device's damping); passive below it")
            ax.plot([2 * dev_b * rate_hz] * 2, [b_floor * 0.8, b_floor * 1.25], "b-", lw=1.6)
            ax.fill_between(k_cs[ok], b_floor * 0.8, b_cs[ok], color="b", alpha=0.08)
            for label, k, b, mk in marks(rate_hz, ctrl, generic=True):
                ax.scatter([k], [ys(b)], marker=mk, s=130, color="gold", edgecolors="k", linewidths=0.8,
                           label=label, zorder=4)
            ax.set_xscale("log")
            ax.set_yscale("log")
            ax.set_xlim(50, 2e6)
            ax.set_ylim(b_floor * 0.7, 3e3)
            ticks = [b_floor, 1, 10, 100, 1000]
            ax.set_yticks(ticks)
            ax.set_yticklabels(["0"] + [f"{t:g}" for t in ticks[1:]])
            ax.set_xlabel("wall stiffness K [N/m]")
            ax.set_ylabel("wall damping B [N s/m]")
            ax.set_title(f"{ctrl}, {kind} device ({mass:g} kg, b {dev_b:g} N s/m)", fontsize=10)
            ax.grid(True, which="major", alpha=0.3)
    handles: dict = {}
    for ax in axes.flat:
        for h, lab in zip(*ax.get_legend_handles_labels()):
            handles.setdefault(lab, h)
    fig.legend(list(handles.values()), list(handles), loc="lower center", ncol=3, fontsize=8, framealpha=0.9)
    pre = presets_at(rate_hz)
    title = (f"Z-width at {rate_hz:g} Hz (T = {1e3 / rate_hz:.3g} ms)" + (f", preset {', '.join(pre)}" if pre else "")
             + f": constant {PUSH_N:g} N push, no hand mass or damping; unstable = > {PTP_MAX_M * 1e3:g} mm or "
             f"> {FORCE_PTP_MAX_FRACTION * PUSH_N:g} N p-p {WINDOW_START_S:g}-{WINDOW_END_S:g} s after contact and "
             f"not shrinking; velocity: {'the device' + chr(39) + 's' if velocity == 'device' else 'backward difference'}")
    extra = [x for x in (layer, note) if x]
    for line in extra:
        title += "\n" + line
    fig.suptitle(title, fontsize=10)
    fig.tight_layout(rect=(0, 1.1 / (4.4 * len(ctrls) + 1.6), 1, 0.95 - 0.02 * len(extra)))
    fig.savefig(path, dpi=90)
    plt.close(fig)


def verdict(rate_hz: float, results: dict) -> str:
    """One line per rate: per controller and kind, stable/points, and whether the config's
    default contact and the table's bound are inside the measured region."""
    parts = []
    for ctrl, by_kind in results.items():
        for kind, r in by_kind.items():
            s = r["summary"]
            ins = []
            for name, k, b in r["marks"]:
                ins.append(f"{name.split(':')[0].split(' (')[0]} {'stable' if r['marks_stable'][name] else 'UNSTABLE'}")
            parts.append(f"{ctrl}/{kind} {s['stable']}/{s['points']} stable, CS-inside unstable "
                         f"{s['colgate_schenkel_inside_unstable']}/{s['colgate_schenkel_inside']}, accepted-but-unstable "
                         f"{len(s['accepted_by_server_unstable'])}; " + ", ".join(ins))
    return f"zwidth {rate_hz:g} Hz: " + " | ".join(parts)


def run_zwidth(out: str, *, quick: bool = False, kinds=None, rates=None, controllers=None,
               layer: str | None = None, k_grid=None, b_grid=None, plots: bool = True, velocity: str = "device",
               damping_credit: float | None = None, input_credit: float | None = None,
               budget_j: float | None = None, log=None) -> dict:
    """The sweep: every rate x controller x kind x (K, B); PNGs and ``zwidth.json`` in ``out``
    (None: the module's ``KINDS``, ``RATES_HZ``, ``CONTROLLERS`` and grids)."""
    kinds, rates, controllers = kinds or KINDS, rates or RATES_HZ, controllers or CONTROLLERS
    os.makedirs(out, exist_ok=True)
    layer_table, note = layer_settings(layer, damping_credit, input_credit, budget_j)
    if note and log:
        log(note)
    kg = tuple(k_grid or (QUICK_K_GRID if quick else K_GRID_N_PER_M))
    bg = tuple(b_grid or (QUICK_B_GRID if quick else B_GRID_N_S_PER_M))
    res: dict = {"push_n": PUSH_N, "gap_m": GAP_M, "window_s": [WINDOW_START_S, WINDOW_END_S],
                 "ptp_max_mm": PTP_MAX_M * 1e3, "force_ptp_max_n": FORCE_PTP_MAX_FRACTION * PUSH_N,
                 "layer": layer or "off", "layer_note": note, "velocity": velocity,
                 "damping_credit": layer_table.get("passivity", {}).get("damping_credit", 1.0 if layer == "on" else None),
                 "input_credit": layer_table.get("passivity", {}).get("input_credit", 1.0 if layer == "on" else None),
                 "initial_budget_j": layer_table.get("passivity", {}).get("initial_budget_j",
                                                                          0.01 if layer == "on" else None),
                 "rates": {}}
    for rate in rates:
        per_rate: dict = {}
        for ctrl in controllers:
            per_rate[ctrl] = {}
            for kind in kinds:
                pts = sweep(kind, rate, controller=ctrl, k_grid=kg, b_grid=bg, layer_table=layer_table,
                            velocity=velocity, log=log)
                mass, dev_b = device_physics(kind, rate)
                mk = [(label, k, b) for label, k, b, _ in marks(rate, ctrl)]
                # the marked settings measured themselves (they need not lie on the grid)
                mk_stable = {label: run_point(kind, rate, k, b, controller=ctrl, layer_table=layer_table,
                                              velocity=velocity)[0] != "unstable"
                             for label, k, b in mk}
                per_rate[ctrl][kind] = {
                    "device_mass_kg": mass, "device_damping_n_s_per_m": dev_b,
                    "colgate_schenkel_k_max_n_per_m": 2 * dev_b * rate,
                    "points": [asdict(p) for p in pts], "summary": region_summary(pts),
                    "marks": mk, "marks_stable": mk_stable,
                }
        res["rates"][f"{rate:g}"] = per_rate
        res.setdefault("verdicts", []).append(verdict(rate, per_rate))
        if plots:
            path = os.path.join(out, f"zwidth_{rate:g}hz.png")
            plot_rate(path, rate, per_rate, note=note, velocity=velocity, layer=layer_label(res))
            res.setdefault("plots", []).append(path)
    res = _clean(res)
    with open(os.path.join(out, "zwidth.json"), "w") as fh:
        json.dump(res, fh, indent=1, allow_nan=False)
    with open(os.path.join(out, "zwidth.md"), "w") as fh:
        fh.write(tables_md(res))
    return res


def _k(v) -> str:
    return "-" if v is None else f"{v:g}"


def tables_md(res: dict) -> str:
    """Markdown: per rate, the region's edge (the largest grid stiffness stable with every softer
    one stable too) per controller, kind and wall damping; Colgate and Schenkel's K at B = 0;
    whether the marked settings are stable."""
    lines = []
    for rate, per_rate in res["rates"].items():
        first = next(iter(next(iter(per_rate.values())).values()))
        bs = list(first["summary"]["largest_stable_stiffness_by_damping"])
        lines.append(f"**{rate} Hz**: the largest stable wall stiffness K [N/m] per wall damping B [N s/m] "
                     f"(every softer grid K stable too; `-`: none)\n")
        lines.append("| controller, device | CS bound K (B = 0) | " + " | ".join(f"B = {b}" for b in bs)
                     + " | config default | table's bound | table, b = 30 |")
        lines.append("| --- | ---: | " + " | ".join("---:" for _ in bs) + " | --- | --- | --- |")
        for ctrl, by_kind in per_rate.items():
            for kind, r in by_kind.items():
                edge = r["summary"]["largest_stable_stiffness_by_damping"]
                ms = list(r["marks_stable"].values())
                cells = [("stable" if v else "**unstable**") for v in ms] + ["n/a"] * (3 - len(ms))
                lines.append(f"| {ctrl}, {kind} ({r['device_mass_kg']:g} kg, b {r['device_damping_n_s_per_m']:g}) | "
                             f"{r['colgate_schenkel_k_max_n_per_m']:g} | " + " | ".join(_k(edge[b]) for b in bs)
                             + " | " + " | ".join(cells) + " |")
        lines.append("")
    return "\n".join(lines) + "\n"


def _clean(o):
    """JSON without NaN: a value that never existed (no contact, no motion) is null."""
    if isinstance(o, float):
        return o if math.isfinite(o) else None
    if isinstance(o, dict):
        return {k: _clean(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_clean(v) for v in o]
    return o


def summary_json(res: dict) -> str:
    """``--json``: the run's summary (everything but the grid's points, which ``zwidth.json`` holds)."""
    short = {k: v for k, v in res.items() if k != "rates"}
    short["rates"] = {rate: {ctrl: {kind: {k: v for k, v in r.items() if k != "points"} for kind, r in by_kind.items()}
                             for ctrl, by_kind in per_rate.items()} for rate, per_rate in res["rates"].items()}
    return json.dumps(short, indent=1, allow_nan=False)
