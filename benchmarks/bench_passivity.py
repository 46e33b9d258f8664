"""``hapticproxy bench passivity``: the energy the server gives the hand against an adversarial
engine, with the passivity layer (``server/passivity.py``) on and off.

The scene (simulated time, the model level: ``LocalModel``, the controller kernel as the loop
calls it, the ``sim`` planar device with its simulated hand): a 40 x 40 mm box tool rests on a
floor y = h(t) under the hand's push. The engine (analytic, 60 Hz, optionally delayed) reports
the floor's contacts from the proxy's pose, its own tool lifted out of the floor as a rigid
engine holds it; now and then (every 0.4-0.8 s, seeded) the floor jumps 5-20 mm up into the
resting tool and stays there: every jump stores energy in the penalty springs and the
deformation recovery lifts the tool onto the jumped surface, so the hand is lifted by what the
floor rose (the issue's adversarial engine). Two hands: ``push``, a pure
force (``[device.hand] type = "constant"``, 1 N down), and ``grip``, an impedance hand holding
the handle 3 mm below where it started (300 N/m, 5 N s/m, 0.1 kg: about 0.9 N down).

Per run: ``given_max_j``, the largest net energy the device's port gave the hand at any instant
(the ledger, ``control.port_energy``: what the hand was given less what it put in, since the
start); ``budget_j``, the layer's initial budget; ``excess_j = max(0, given_max_j - budget_j)``
(the layer's promise: no more than its budget, plus what leaks through the hold and the rate
limit); the tank's lowest level; the steps the layer limited; ``rise_mm``, how far the hand was
lifted above where it rested before the first jump (what a user feels of the jumps).

``--matrix N``: the issue's matrix instead (``benchmarks/passivity_matrix.py``: N seeded random
runs on the shipped engines and an adversarial one, 20-120 Hz, 0-300 ms of delay with jitter and
loss, two hands, layer off and on; ``--only`` reruns chosen runs, ``--set`` a setting over them).
``--walls``: undamped walls at 5x Colgate and Schenkel's bound on each device kind (:func:`wall`).
"""
from __future__ import annotations

import argparse
import json
import math
import platform
import sys
import time

import numpy as np

from ..protocol.jsonout import print_json
from ..protocol.logs import doc_summary

HANDS = ("push", "grip")
HALF_M = 0.02
ENGINE_HZ = 60.0
EPSILON_M = 0.005


def _floor_schedule(seed: int, seconds: float):
    """[(t_s, jump_m)] of a run: the first jump after 0.5 s of rest, the last 0.3 s before the end."""
    rng = np.random.default_rng(seed)
    out, t = [], 0.5
    while t < seconds - 0.3:
        out.append((t, float(rng.uniform(0.005, 0.020))))
        t += float(rng.uniform(0.4, 0.8))
    return out


def run(hand: str, layer: bool, seed: int = 0, seconds: float = 4.0, rate_hz: float = 1000.0,
        delay_ms: float = 0.0, budget_j: float = 0.01) -> dict:
    """One run (see the module docstring); the row it reports."""
    from ..server import config as cfg
    from ..server import control as ctl
    from ..server import passivity as pv
    from ..server.devices.base import empty_state
    from ..server.devices.sim import make_sim_device
    from ..server.model import ContactParams, LocalModel, ToolSpec

    if hand not in HANDS:
        raise ValueError(f"hand: {hand!r} is not one of {', '.join(HANDS)}")
    settings = cfg.load({"loop": {"rate_hz": rate_hz}, "device": {"driver": "sim", "kind": "planar"},
                         "passivity": {"enabled": layer, "initial_budget_j": budget_j,
                                       "max_tank_j": max(0.05, budget_j)}})
    mc = settings["model"]
    dt = 1.0 / rate_hz
    tool = ToolSpec.planar(0.4, 0.4 * (2 * HALF_M) ** 2 / 6)
    m = LocalModel(tool, ContactParams(mc["stiffness_n_per_m"], mc["damping_n_s_per_m"], mc["restitution"],
                                       mc["mu_static"], mc["mu_kinetic"]),
                   period_s=dt, policy=mc["policy"], epsilon_m=EPSILON_M, capacity=8,
                   recovery_speed_m_per_s=mc["recovery_speed_m_per_s"])
    m.reset([0.0, HALF_M + 0.0005, 0.0])
    if hand == "push":
        hcfg = {"type": "constant", "wrench": [0.0, -1.0, 0.0], "start": "server"}
    else:
        hcfg = {"type": "impedance", "stiffness_n_per_m": 300.0, "damping_n_s_per_m": 5.0, "mass_kg": 0.1,
                "target": {"type": "constant", "pose": [0.0, -0.003, 0.0]}, "start": "server"}
    device = make_sim_device({"kind": "planar", "hand": hcfg}, period_s=dt, clock_ns=lambda: 0)
    c = ctl.Controller(settings, "planar", device.limits)
    device.enable()
    row = empty_state()
    device.read(row)
    c.set_offset(*ctl.index_offset("planar", row[:7], m.hand_state()[:7]))
    c.cs[ctl.CS_GAIN] = c.cs[ctl.CS_TARGET] = 1.0
    kargs = m.kernel_args()
    body = np.array([[-HALF_M, -HALF_M, 0.0], [HALF_M, -HALF_M, 0.0]])
    jumps = _floor_schedule(seed, seconds)
    every = max(1, int(round(rate_hz / ENGINE_HZ)))
    delay_steps = int(round(delay_ms * 1e-3 * rate_hz))
    pending: list = []  # (apply at step, update arguments)
    given_max = -math.inf
    rest_y = None
    rise = 0.0
    n = int(round(seconds * rate_hz))
    rc_bad = 0
    for i in range(n):
        t = i * dt
        h = sum(d for up, d in jumps if up <= t)
        if i % every == 0:  # the engine computes from the proxy it has been told about
            q = m.q.copy()
            R = np.array([[math.cos(q[2]), -math.sin(q[2]), 0.0], [math.sin(q[2]), math.cos(q[2]), 0.0], [0, 0, 1.0]])
            pts = np.array([q[0], q[1], 0.0]) + body @ R.T
            low = float(np.min(pts[:, 1]))
            if low < h:
                q[1] += h - low
                pts[:, 1] += h - low
            keys, cp, nrm, sep = [], [], [], []
            for j, p in enumerate(pts):
                if p[1] - h <= EPSILON_M:
                    keys.append((0, 1, j))
                    cp.append((p[0], h, 0.0))
                    nrm.append((0.0, 1.0, 0.0))
                    sep.append(p[1] - h)
            k = len(keys)
            pending.append((i + delay_steps, (np.array(keys, dtype=np.int64).reshape(k, 3), np.array(cp).reshape(k, 3),
                                              np.array(nrm).reshape(k, 3), np.array(sep).reshape(k), np.zeros(k), q)))
        while pending and pending[0][0] <= i:
            _, (keys, cp, nrm, sep, vc, q) = pending.pop(0)
            m.update(keys, cp, nrm, sep, vc, tool_q=q)
        device.read(row)
        rc = ctl.haptic_step(c.cp, c.cs, c.cc, row, c.cmd, 1, *kargs, c.hand, c.R, c.c)
        device.write(c.cmd)
        if rc != ctl.RC_OK:
            rc_bad += 1
        e = float(c.cs[ctl.CS_EHAND])
        given_max = max(given_max, e)
        y = float(c.cs[ctl.CS_DPOSE + 1])
        if jumps and t < jumps[0][0]:
            rest_y = y
        elif rest_y is not None:
            rise = max(rise, y - rest_y)
    ts = c.cs[ctl.CS_TANK:ctl.CS_TANK + pv.NTS]
    return {"hand": hand, "layer": "on" if layer else "off", "seed": seed, "seconds": seconds, "rate_hz": rate_hz,
            "delay_ms": delay_ms, "jumps": len(jumps), "budget_j": budget_j, "given_max_j": given_max,
            "given_end_j": float(c.cs[ctl.CS_EHAND]), "excess_j": max(0.0, given_max - budget_j),
            "tank_low_j": float(ts[pv.TS_LOW]), "tank_end_j": float(ts[pv.TS_TANK]),
            "limited_steps": int(c.cc[ctl.CC_TANK + pv.TC_LIMITED]), "steps": n, "faults": rc_bad,
            "rise_mm": 1e3 * rise}


WALL_FACTOR = 5.0
WALL_RATES_HZ = (512.0, 1000.0, 4000.0)
WALL_CONTROLLERS = ("direct", "four_channel")


def wall(kind: str, rate_hz: float, layer: bool, controller: str = "direct", factor: float = WALL_FACTOR,
         budget_j: float | None = None, input_credit: float | None = None) -> dict:
    """An undamped wall (B = 0) ``factor`` times Colgate and Schenkel's bound, ``K = factor 2 b / T``
    with ``b`` the ``kind`` device's default physical damping (``experiments.zwidth.device_physics``),
    rendered on that device with its physical damping set to 0 (translation and rotation): the
    z-width rig (``experiments.zwidth.run_point``: a constant 1 N push from 2 mm off the wall, a
    continuous device behind the hold), the layer on or off. ``ptp_1s_mm``: the handle's peak to
    peak 1-1.5 s after contact along the normal (the issue's goal with the layer: below 0.1 mm).
    ``budget_j``: the layer's initial budget, ``input_credit`` the share of the hand's input its
    tank keeps (None: the config's defaults)."""
    from ..experiments import zwidth as zw

    _, b = zw.device_physics(kind, rate_hz)
    k = factor * 2.0 * b * rate_hz
    device = {"damping_n_s_per_m": 0.0}
    if kind != "1dof":
        device["rot_damping_n_m_s_per_rad"] = 0.0
    table = {"enabled": bool(layer)}
    if budget_j is not None:
        table["initial_budget_j"] = float(budget_j)
    if input_credit is not None:
        table["input_credit"] = float(input_credit)
    verdict, reason, contact_s, ptp, fptp, _, ptp_1s = zw.run_point(
        kind, rate_hz, k, 0.0, controller=controller, layer_table={"passivity": table}, device=device)
    from ..server import config as cfg

    pas = cfg.load({"passivity": table})["passivity"]
    budget = pas["initial_budget_j"]
    return {"kind": kind, "rate_hz": rate_hz, "controller": controller, "layer": "on" if layer else "off",
            "bound_device_b_n_s_per_m": b, "stiffness_n_per_m": k, "wall_damping_n_s_per_m": 0.0,
            "device_damping_n_s_per_m": 0.0, "budget_j": budget, "input_credit": pas["input_credit"], "contact_s": contact_s, "ptp_1s_mm": 1e3 * ptp_1s,
            "ptp_window_mm": 1e3 * ptp, "force_ptp_window_n": fptp, "verdict": verdict, "reason": reason,
            "below_0_1mm": bool(1e3 * ptp_1s < 0.1)}


def _wall_line(r: dict) -> str:
    return (f"wall {r['kind']:>7} {r['rate_hz']:.0f} Hz {r['controller']:>12} layer {r['layer']:>3}: K "
            f"{r['stiffness_n_per_m']:g} N/m (5 x 2 b / T, b = {r['bound_device_b_n_s_per_m']:g}; device b = 0, B = 0), "
            f"budget {1e3 * r['budget_j']:g} mJ, credit {r['input_credit']:g}, p-p 1 s after contact {r['ptp_1s_mm']:.4g} mm, over {zw_window()} "
            f"{r['ptp_window_mm']:.4g} mm, force p-p {r['force_ptp_window_n']:.3g} N: {r['verdict']}"
            + (f" ({r['reason']})" if r["reason"] else ""))


def zw_window() -> str:
    from ..experiments import zwidth as zw

    return f"{zw.WINDOW_START_S:g}-{zw.WINDOW_END_S:g} s"


def _line(r: dict) -> str:
    return (f"{r['hand']:>4} layer {r['layer']:>3} seed {r['seed']} delay {r['delay_ms']:.0f} ms: {r['jumps']} jumps, "
            f"given at most {1e3 * r['given_max_j']:+.2f} mJ (budget {1e3 * r['budget_j']:.1f}, excess "
            f"{1e3 * r['excess_j']:.2f}), tank low {1e3 * r['tank_low_j']:+.2f} mJ, limited {r['limited_steps']} "
            f"of {r['steps']} steps, hand lifted {r['rise_mm']:.2f} mm, faults {r['faults']}")


def summary(rows: list[dict]) -> dict:
    """Per hand and layer setting: runs, the largest excess and the largest energy given."""
    out = {}
    for r in rows:
        k = f"{r['hand']}/{r['layer']}"
        s = out.setdefault(k, {"runs": 0, "max_excess_j": 0.0, "max_given_j": -math.inf, "runs_over_1mj": 0})
        s["runs"] += 1
        s["max_excess_j"] = max(s["max_excess_j"], r["excess_j"])
        s["max_given_j"] = max(s["max_given_j"], r["given_max_j"])
        s["runs_over_1mj"] += int(r["excess_j"] > 1e-3)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="hapticproxy bench passivity", description=doc_summary(__doc__))
    ap.add_argument("--json", action="store_true", help="one JSON object per line")
    ap.add_argument("--seeds", type=int, default=3, help="floor schedules per hand and layer setting (default 3)")
    ap.add_argument("--seconds", type=float, default=4.0, help="simulated seconds per run (default 4)")
    ap.add_argument("--delays-ms", default="0,100", help="engine delays to run, comma-separated (default 0,100)")
    ap.add_argument("--hands", default=",".join(HANDS), help=f"comma-separated subset of {', '.join(HANDS)}")
    ap.add_argument("--walls", action="store_true",
                    help="instead: undamped walls at 5x Colgate and Schenkel's bound, each device kind, layer off and on")
    ap.add_argument("--wall-rates", default=",".join(f"{r:g}" for r in WALL_RATES_HZ),
                    help="haptic rates of the walls, Hz, comma-separated (default 512,1000,4000)")
    ap.add_argument("--wall-budgets", default="",
                    help="walls with the layer on: initial budgets to run, J, comma-separated (default: the config's)")
    ap.add_argument("--wall-credits", default="",
                    help="walls with the layer on: the tank's input credits to run, 0-1, comma-separated (default: "
                         "the config's)")
    ap.add_argument("--matrix", type=int, default=0, metavar="N",
                    help="instead: N random runs of the matrix (benchmarks/passivity_matrix.py), layer off and on")
    ap.add_argument("--matrix-seed", type=int, default=0, help="the matrix's seed (default 0)")
    ap.add_argument("--matrix-seconds", type=float, default=3.0, help="simulated seconds per matrix run (default 3)")
    ap.add_argument("--only", default="", metavar="I,J,...",
                    help="matrix: run only these run numbers of the seed's matrix (e.g. the worst ones again)")
    ap.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                    help="matrix: a server setting over the run's (a counterfactual; repeatable), e.g. "
                         "passivity.low_level_j=0.01")
    ap.add_argument("--worst", type=int, default=5, help="matrix: the worst runs printed per layer setting (default 5)")
    args = ap.parse_args(argv)
    if args.matrix:
        return _matrix(args)
    if args.walls:
        return _walls(args)
    hands = [h.strip() for h in args.hands.split(",") if h.strip()]
    bad = [h for h in hands if h not in HANDS]
    if bad or args.seeds < 1 or not args.seconds > 1.0:
        why = f"--hands: unknown {bad}; choose from {', '.join(HANDS)}" if bad else (
            "--seeds: at least 1" if args.seeds < 1 else "--seconds: more than 1 (the first jump is at 0.5 s)")
        print(f"hapticproxy bench passivity: {why}", file=sys.stderr)
        return 2
    try:
        delays = [float(d) for d in args.delays_ms.split(",") if d.strip()]
    except ValueError:
        print(f"hapticproxy bench passivity: --delays-ms: numbers in ms, got {args.delays_ms!r}", file=sys.stderr)
        return 2
    emit = (lambda r: print_json(r)) if args.json else (lambda r: print(_line(r)))
    if args.json:
        print_json({"run": {"machine": f"{platform.node()} {platform.machine()}",
                            "date_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}})
    rows = []
    for hand in hands:
        for delay in delays:
            for layer in (False, True):
                for seed in range(args.seeds):
                    r = run(hand, layer, seed, args.seconds, delay_ms=delay)
                    rows.append(r)
                    emit(r)
    s = summary(rows)
    if args.json:
        print_json({"summary": s})
    else:
        for k, v in s.items():
            print(f"{k}: {v['runs']} runs, largest excess {1e3 * v['max_excess_j']:.2f} mJ, largest energy given "
                  f"{1e3 * v['max_given_j']:.2f} mJ, runs over budget + 1 mJ {v['runs_over_1mj']}")
    return 0


def _walls(args) -> int:
    try:
        rates = [float(r) for r in args.wall_rates.split(",") if r.strip()]
    except ValueError:
        rates = []
    if not rates or not all(math.isfinite(r) and 100.0 <= r <= 20000.0 for r in rates):
        print(f"hapticproxy bench passivity: --wall-rates: rates in Hz (100-20000), got {args.wall_rates!r}",
              file=sys.stderr)
        return 2
    try:
        budgets = [float(b) for b in args.wall_budgets.split(",") if b.strip()] or [None]
    except ValueError:
        budgets = []
    if not budgets or not all(b is None or (math.isfinite(b) and 0.0 <= b <= 0.05) for b in budgets):
        print(f"hapticproxy bench passivity: --wall-budgets: energies in J (0-0.05), got {args.wall_budgets!r}",
              file=sys.stderr)
        return 2
    try:
        credits = [float(k) for k in args.wall_credits.split(",") if k.strip()] or [None]
    except ValueError:
        credits = []
    if not credits or not all(k is None or 0.0 < k <= 1.0 for k in credits):
        print(f"hapticproxy bench passivity: --wall-credits: shares in (0, 1], got {args.wall_credits!r}",
              file=sys.stderr)
        return 2
    if args.json:
        print_json({"run": {"machine": f"{platform.node()} {platform.machine()}",
                            "date_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "walls": True}})
    for kind in ("1dof", "planar", "spatial"):
        for rate in rates:
            for controller in WALL_CONTROLLERS:
                for layer, budget, credit in [(False, None, None)] + [(True, b, k) for b in budgets for k in credits]:
                    r = wall(kind, rate, layer, controller, budget_j=budget, input_credit=credit)
                    print_json({"wall": r}) if args.json else print(_wall_line(r))
    return 0


def _matrix(args) -> int:
    from . import passivity_matrix as pm

    if args.matrix < 1 or not args.matrix_seconds >= 1.0 or args.worst < 0:
        why = ("--matrix: at least 1 run" if args.matrix < 1 else
               "--matrix-seconds: at least 1 (the handshake through 300 ms of delay comes first)"
               if not args.matrix_seconds >= 1.0 else "--worst: 0 or more")
        print(f"hapticproxy bench passivity: {why}", file=sys.stderr)
        return 2
    over: dict = {}
    for item in args.set:
        key, eq, value = item.partition("=")
        section, dot, name = key.partition(".")
        try:
            v = json.loads(value)
        except ValueError:
            v = value
        if not (eq and dot and section and name):
            print(f"hapticproxy bench passivity: --set: SECTION.KEY=VALUE, got {item!r}", file=sys.stderr)
            return 2
        over.setdefault(section, {})[name] = v
    try:
        only = [int(i) for i in args.only.split(",") if i.strip()]
    except ValueError:
        only = [-1]
    if any(i < 0 for i in only):
        print(f"hapticproxy bench passivity: --only: run numbers >= 0, got {args.only!r}", file=sys.stderr)
        return 2
    if args.json:
        print_json({"run": {"machine": f"{platform.node()} {platform.machine()}",
                            "date_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
                            "matrix": args.matrix, "seed": args.matrix_seed, "seconds": args.matrix_seconds,
                            "only": only, "set": over}})
    try:
        rows = pm.run_matrix(args.matrix, args.matrix_seed, args.matrix_seconds, only=only or None,
                             settings_over=over or None,
                             on_row=(lambda r: print_json({"matrix_run": r})) if args.json else None)
    except Exception as exc:  # a --set the config refuses: its one line
        from ..server.config import ConfigError

        if not isinstance(exc, ConfigError):
            raise
        print(f"hapticproxy bench passivity: --set: {exc}", file=sys.stderr)
        return 2
    s = pm.summary(rows)
    worst = {layer: pm.worst(rows, layer, args.worst) for layer in ("on", "off")}
    if args.json:
        print_json({"summary": s, "worst": {k: [r["index"] for r in v] for k, v in worst.items()}})
        return 0
    for layer in ("on", "off"):
        v = s[layer]
        print(f"layer {layer}: {v['runs']} runs, over budget + 1 mJ {v['runs_over_1mj']}, largest excess "
              f"{1e3 * v['max_excess_books_j']:+.2f} mJ (books) {1e3 * v['max_excess_indep_j']:+.2f} mJ (independent), "
              f"largest energy given {1e3 * v['max_given_j']:.2f} mJ, ledgers differ by at most "
              f"{1e3 * v['max_ledger_gap_j']:.3g} mJ, runs with faults {v['runs_with_faults']}, never engaged "
              f"{v['never_engaged']}, crashed {v['crashed']}")
        for r in worst[layer]:
            print("  " + pm.line(r))
    return 0


if __name__ == "__main__":
    sys.exit(main())
