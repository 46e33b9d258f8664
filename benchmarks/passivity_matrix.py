"""``hapticproxy bench passivity --matrix N``: the energy ledger's largest excess over N random runs
(issue 31, "Measure", first item), with the passivity layer on (the claim) and off (the same
run, for comparison).

Each run is drawn from the matrix by its seed (``draw``: reproducible, run ``i`` of seed ``s`` is
the same whatever ``N``):

- **engine and scene**: the shipped engines that step in this process without a network, ``stub``
  (scenes testbed, hole, wall, piston), ``pymunk`` (testbed, hole, wall, push) and ``peg1d`` (its
  1-DOF peg, on a 1-DOF device), or the adversarial engine (``testing/adversarial_engine.py``:
  floor jumps up to 5 cm, flipped normals, a block driven into the tool); the adversary in half
  of the runs;
- **engine rate** uniform in 20-120 Hz (the stub's rate wanders +-10 % around it, as it does);
- **network**: one-way delay uniform in 0-300 ms, jitter uniform in 0-min(50 ms, delay), loss
  uniform in 0-20 %, both directions (ContactUpdates and ProxyStates), through the impairing
  relay's own model (``testing/impair.py``: :class:`ImpairedTransport` around the client's
  ``mem://`` transport, on the simulated clock);
- **hand** on the simulated device: ``push``, a pure force (``[device.hand] type = "constant"``,
  0.3-2 N, its direction drawn within 60 deg of the scene's walls) or ``grip``, an impedance hand
  (100-600 N/m, 2-10 N s/m, 0.1 kg) whose target moves at 0.05-0.2 m/s into the scene's walls
  (5-30 mm past the adversary's floor) and holds there; both start at the engagement.

The server is the real one in simulated time: ``HapticLoop`` with its defaults (1 kHz, four-channel
controller, deformation policy, epsilon prediction and lead), the ``sim`` device, the protocol over
``mem://``, the engine stepped by ``experiments.harness.SimEnvClient`` between haptic steps.

Per run and layer setting, two ledgers of the energy the device gave the hand (net: given less
what the hand put in, since the start):

- **books**: the server's own (``control.CS_EHAND``) against what the layer may give
  (``passivity``: the initial budget, plus what the declared device damping dissipated and what
  engines granted, ``TS_DAMPED`` and ``TS_GRANTED``): ``excess_books_j`` is the largest
  ``E_hand - (H0 + damped + granted)`` over the run (0 or less: within the budget);
- **independent**: the same quantity from the recording alone (the raw device state row the
  loop read each step and the command it wrote), paired in numpy here
  (``sum f_k . (x_{k+1} - x_k)`` plus the torque over the rotation vector): ``excess_indep_j``.

A run counts as **over** when either excess is above 1 mJ (the issue's goal: none with the
layer on). ``summary`` counts, per layer setting, runs, runs over, the largest excesses, faults,
and runs that never engaged.
"""
from __future__ import annotations

import math
import tempfile
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

ENGINES = {"stub": ("testbed", "hole", "wall", "piston"), "pymunk": ("testbed", "hole", "wall", "push"),
           "peg1d": ("peg1d",), "adversary": ("adversary",)}
HANDS = ("push", "grip")
GOAL_J = 1e-3
EPSILON_M = 0.005
CAPACITY = 16
_NS = 1_000_000_000
#: the hole scene's device starts turned by 90 deg (the peg rests in the hole; as the experiments)
HOLE_THETA = math.pi / 2


@dataclass(frozen=True)
class Case:
    """One run of the matrix (everything but the layer setting)."""

    seed: int
    index: int
    engine: str
    scene: str
    env_rate_hz: float
    delay_ms: float
    jitter_ms: float
    loss: float
    hand: str
    force_n: float           # push: the force; grip: 0
    angle_deg: float         # the push's or the grip target's direction from the scene's "down"
    grip_k_n_per_m: float
    grip_b_n_s_per_m: float
    grip_speed_m_per_s: float
    grip_depth_m: float      # how far past the wall the target goes


def draw(seed: int, index: int) -> Case:
    """Run ``index`` of the matrix seeded ``seed`` (see the module docstring)."""
    rng = np.random.default_rng([int(seed), int(index)])
    if rng.random() < 0.5:
        engine = "adversary"
    else:
        engine = ("stub", "pymunk", "peg1d")[int(rng.integers(3))]
    scenes = ENGINES[engine]
    scene = scenes[int(rng.integers(len(scenes)))]
    delay = float(rng.uniform(0.0, 300.0))
    return Case(seed=int(seed), index=int(index), engine=engine, scene=scene,
                env_rate_hz=float(rng.uniform(20.0, 120.0)), delay_ms=delay,
                jitter_ms=float(rng.uniform(0.0, min(50.0, delay))), loss=float(rng.uniform(0.0, 0.2)),
                hand=HANDS[int(rng.integers(2))], force_n=float(rng.uniform(0.3, 2.0)),
                angle_deg=float(rng.uniform(-60.0, 60.0)), grip_k_n_per_m=float(rng.uniform(100.0, 600.0)),
                grip_b_n_s_per_m=float(rng.uniform(2.0, 10.0)), grip_speed_m_per_s=float(rng.uniform(0.05, 0.2)),
                grip_depth_m=float(rng.uniform(0.005, 0.03)))


def _make_engine(case: Case, seconds: float):
    if case.engine == "stub":
        from ..clients.stub_engine import StubEngine

        return StubEngine(seed=case.index, rate_range_hz=(0.9 * case.env_rate_hz, 1.1 * case.env_rate_hz))
    if case.engine == "pymunk":
        from ..clients.pymunk_engine import PymunkEngine

        return PymunkEngine(rate_hz=case.env_rate_hz)
    if case.engine == "peg1d":
        from ..clients.peg_engine import PegEngine

        return PegEngine(rate_hz=case.env_rate_hz)
    from ..testing.adversarial_engine import AdversarialEngine

    return AdversarialEngine(seed=case.seed * 1_000_003 + case.index, rate_hz=case.env_rate_hz, seconds=seconds)


def _hand_config(case: Case) -> tuple[str, dict]:
    """The device kind and its ``[device.hand]`` table. The scenes' walls are at +y (the paper's
    "down", 124 mm from the start) and, for the 1-DOF peg, both ways along x; the adversary's
    floor is at -y (1 mm below its tool)."""
    if case.engine == "peg1d":
        sign = 1.0 if case.angle_deg >= 0 else -1.0
        if case.hand == "push":
            return "1dof", {"type": "constant", "wrench": [sign * case.force_n]}
        reach = case.grip_depth_m
        return "1dof", _grip(case, [sign * reach], [0.0])
    a = math.radians(case.angle_deg)
    down = -1.0 if case.engine == "adversary" else 1.0
    d = (math.sin(a), down * math.cos(a))
    if case.hand == "push":
        return "planar", {"type": "constant", "wrench": [case.force_n * d[0], case.force_n * d[1], 0.0]}
    reach = (0.001 + case.grip_depth_m) if case.engine == "adversary" else (0.124 + case.grip_depth_m)
    th = 0.0
    if case.scene == "hole":
        reach = case.grip_depth_m  # starts resting in the hole, the handle turned by 90 deg
        th = HOLE_THETA
    return "planar", _grip(case, [reach * d[0], reach * d[1], th], [0.0, 0.0, th])


def _grip(case: Case, end: list, start: list) -> dict:
    dist = math.sqrt(sum((a - b) ** 2 for a, b in zip(end[:2], start[:2])))
    t_end = max(0.05, dist / case.grip_speed_m_per_s)
    return {"type": "impedance", "stiffness_n_per_m": case.grip_k_n_per_m, "damping_n_s_per_m": case.grip_b_n_s_per_m,
            "mass_kg": 0.1, "target": {"type": "waypoints", "points": [[0.0] + list(start), [t_end] + list(end)]}}


def independent_ledger(dev: np.ndarray, cmd: np.ndarray) -> np.ndarray:
    """The energy given to the hand up to each step, from the recording alone: ``dev`` (n, 7) the
    raw device pose read at each step (x y z qw qx qy qz, device frame), ``cmd`` (n, 6) the command
    written at it (force, torque, device frame; held until the next). Returns (n,) cumulative J
    (entry k: through the period that ended at step k)."""
    n = len(dev)
    out = np.zeros(n)
    if n < 2:
        return out
    dx = np.diff(dev[:, :3], axis=0)
    w = np.einsum("ij,ij->i", cmd[:-1, :3], dx)
    # rotation vector of q_{k+1} conj(q_k)
    a, b = dev[1:, 3:7], dev[:-1, 3:7]
    bw, bv = b[:, 0], -b[:, 1:]
    aw, av = a[:, 0], a[:, 1:]
    qw = aw * bw - np.einsum("ij,ij->i", av, bv)
    qv = aw[:, None] * bv + bw[:, None] * av + np.cross(av, bv)
    flip = qw < 0
    qw = np.where(flip, -qw, qw)
    qv = np.where(flip[:, None], -qv, qv)
    vn = np.linalg.norm(qv, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        scale = np.where(vn > 1e-15, 2.0 * np.arctan2(vn, qw) / vn, 0.0)
    w += scale * np.einsum("ij,ij->i", cmd[:-1, 3:6], qv)
    ok = np.all(np.isfinite(dev), axis=1)
    w = np.where(ok[1:] & ok[:-1] & np.all(np.isfinite(cmd[:-1]), axis=1), w, 0.0)
    out[1:] = np.cumsum(w)
    return out


def run_case(case: Case, layer: bool, seconds: float = 3.0, *, budget_j: float | None = None, trace: bool = False,
             settings_over: dict | None = None) -> dict:
    """One run of ``case`` with the layer on or off; the row it reports (module docstring). With
    ``trace``: the row's ``trace`` holds per step the raw device pose and twist, the command, both
    ledgers, the tank level and the layer's factor (numpy arrays; for a closer look at one run).
    ``settings_over``: config sections merged over the run's (a counterfactual, e.g. another
    ``safety.force_rate_n_per_s``)."""
    from ..experiments.harness import SimEnvClient
    from ..protocol.session import ClientEndpoint
    from ..server import config as cfgmod
    from ..server import control as ctl
    from ..server import passivity as pv
    from ..server.clock import SimClock
    from ..server.loop import HapticLoop
    from ..server.shm import ST
    from ..testing.impair import Impairment, ImpairedTransport

    url = f"mem://passivity-matrix-{case.seed}-{case.index}-{int(layer)}"
    kind, hand = _hand_config(case)
    nd = 3 if kind == "1dof" else 2
    dev = {"driver": "sim", "kind": kind, "workspace_min_m": [-0.3] * nd, "workspace_max_m": [0.3] * nd,
           "hand": hand}
    if case.scene == "hole":
        dev.update({"initial_pose": [0.0, 0.0, HOLE_THETA], "rotation_limit_rad": HOLE_THETA + 1.0})
    table = {"transport": {"url": url}, "status": {"address": "127.0.0.1:1"}, "device": dev,
             "passivity": {"enabled": bool(layer)}, "telemetry": {"ring_s": 1.0}}
    if budget_j is not None:
        table["passivity"]["initial_budget_j"] = budget_j
    for section, keys in (settings_over or {}).items():
        table[section] = {**table.get(section, {}), **keys}
    settings = cfgmod.load(table)
    budget_j = float(settings["passivity"]["initial_budget_j"])  # the books' H0, whatever set it
    clock = SimClock(start_ns=_NS)
    loop = HapticLoop.build(settings, clock=clock)
    engine = _make_engine(case, seconds + 1.0)
    env = None
    try:
        loop.warm_up()
        loop.start()
        env = SimEnvClient(engine, url, clock, scene=case.scene, epsilon_m=EPSILON_M, max_contacts=CAPACITY)
        now_s = lambda: clock.now_ns() * 1e-9  # noqa: E731
        imp = dict(delay_s=case.delay_ms * 1e-3, jitter_s=case.jitter_ms * 1e-3, loss=case.loss)
        base = (case.seed * 1_000_003 + case.index) * 2
        env.tr = ImpairedTransport(env.tr, send=Impairment(seed=base, **imp), recv=Impairment(seed=base + 1, **imp),
                                   clock=now_s)
        env.ep = ClientEndpoint(env.tr.send, env.hello)
        n = int(round(seconds * settings.rate_hz))
        devs = np.zeros((n, 13))
        tank = np.zeros((n, 2))
        ctrl_out = np.zeros((n, 6))  # the controller's wrench before the layer (world)
        cmds = np.zeros((n, 6))
        ehand = np.zeros(n)
        allow = np.zeros(n)   # H0 + damped + granted, as the layer books them
        engaged_at = -1
        crash = ""
        i = 0
        held_steps = 0        # steps whose model held back a constraint's advance (set-position modulation)
        held_status = 0       # the most contacts held back the status ever showed
        status, ST_HELD = loop.shared.status, ST["held"]
        for i in range(n):
            env.service()
            try:
                loop.step()
            except Exception as exc:  # noqa: BLE001 - the loop itself failed: recorded, the run ends
                crash = f"{type(exc).__name__}: {exc}"
                break
            c = loop.ctrl
            cs = c.cs
            devs[i] = loop.dev[:13]
            tank[i] = cs[ctl.CS_TANK + pv.TS_TANK], cs[ctl.CS_TANK + pv.TS_BETA]
            ctrl_out[i] = cs[ctl.CS_CMDW:ctl.CS_CMDW + 6]
            cmds[i] = c.cmd[:6]
            ehand[i] = cs[ctl.CS_EHAND]
            allow[i] = (c.tp[pv.TP_H0] + cs[ctl.CS_TANK + pv.TS_DAMPED] + cs[ctl.CS_TANK + pv.TS_GRANTED])
            if engaged_at < 0 and loop.updates > 0:
                engaged_at = i
            model = loop.proto.model
            if model is not None and model.held > 0:
                held_steps += 1
            held_status = max(held_status, int(status[ST_HELD]))
        else:
            i = n
        devs, cmds, ehand, allow, tank = devs[:i], cmds[:i], ehand[:i], allow[:i], tank[:i]
        indep = independent_ledger(devs[:, :7], cmds)
        c = loop.ctrl
        ts = c.ts
        cnt = c.counters()
        row = asdict(case)
        row.update({
            "layer": "on" if layer else "off", "seconds": seconds, "steps": int(i), "budget_j": budget_j,
            "engaged_s": engaged_at / settings.rate_hz if engaged_at >= 0 else None,
            "updates": int(loop.updates), "given_max_j": float(ehand.max(initial=0.0)),
            "given_max_indep_j": float(indep.max(initial=0.0)),
            "excess_books_j": float(np.max(ehand - allow, initial=-budget_j)),
            "excess_indep_j": float(np.max(indep - allow, initial=-budget_j)),
            "ledger_gap_j": float(np.max(np.abs(indep - ehand), initial=0.0)),
            "granted_j": float(ts[pv.TS_GRANTED]), "damped_j": float(ts[pv.TS_DAMPED]),
            "tank_low_j": float(ts[pv.TS_LOW]), "limited_steps": int(cnt["passivity_limited"]),
            "held_steps": held_steps, "held_status_max": held_status,
            "faults": int(loop.faults_total), "last_reason": str(loop.last_reason), "crash": crash,
            "events": list(getattr(engine, "stats", {}).items()) and dict(engine.stats),
        })
        row["over"] = over(row["excess_books_j"], row["excess_indep_j"])
        if trace:
            row["trace"] = {"dev": devs, "cmd": cmds, "ehand_j": ehand, "indep_j": indep, "allowed_j": allow,
                            "tank_j": tank[:, 0], "beta": tank[:, 1], "controller_world": ctrl_out[:i]}
        return row
    finally:
        if env is not None:
            env.close()
        engine.close()
        loop.close()


def over(excess_books_j: float, excess_indep_j: float) -> bool:
    """A run is over the goal when either ledger's excess is above 1 mJ."""
    return bool(max(excess_books_j, excess_indep_j) > GOAL_J)


def summary(rows: list[dict]) -> dict:
    """Per layer setting: runs, runs over the budget plus 1 mJ (either ledger), the largest
    excesses, the largest gap between the two ledgers, faults and runs that never engaged."""
    out = {}
    for r in rows:
        s = out.setdefault(r["layer"], {"runs": 0, "runs_over_1mj": 0, "max_excess_books_j": -math.inf,
                                        "max_excess_indep_j": -math.inf, "max_given_j": 0.0, "max_ledger_gap_j": 0.0,
                                        "runs_with_faults": 0, "never_engaged": 0, "crashed": 0})
        s["runs"] += 1
        s["runs_over_1mj"] += int(r["over"])
        s["max_excess_books_j"] = max(s["max_excess_books_j"], r["excess_books_j"])
        s["max_excess_indep_j"] = max(s["max_excess_indep_j"], r["excess_indep_j"])
        s["max_given_j"] = max(s["max_given_j"], r["given_max_j"], r["given_max_indep_j"])
        s["max_ledger_gap_j"] = max(s["max_ledger_gap_j"], r["ledger_gap_j"])
        s["runs_with_faults"] += int(r["faults"] > 0)
        s["never_engaged"] += int(r["engaged_s"] is None)
        s["crashed"] += int(bool(r["crash"]))
    return out


def worst(rows: list[dict], layer: str, k: int = 5) -> list[dict]:
    """The ``k`` runs with the largest excess (either ledger) with the layer ``layer``."""
    sel = [r for r in rows if r["layer"] == layer]
    return sorted(sel, key=lambda r: -max(r["excess_books_j"], r["excess_indep_j"]))[:k]


def line(r: dict) -> str:
    """One run as a line (its parameters and both ledgers)."""
    h = (f"push {r['force_n']:.2f} N at {r['angle_deg']:+.0f} deg" if r["hand"] == "push" else
         f"grip {r['grip_k_n_per_m']:.0f} N/m {r['grip_depth_m'] * 1e3:.0f} mm past at {r['angle_deg']:+.0f} deg")
    return (f"#{r['index']} {r['engine']}/{r['scene']} {r['env_rate_hz']:.0f} Hz, delay {r['delay_ms']:.0f} ms "
            f"+-{r['jitter_ms']:.0f}, loss {100 * r['loss']:.0f} %, {h}, layer {r['layer']}: excess books "
            f"{1e3 * r['excess_books_j']:+.2f} mJ, independent {1e3 * r['excess_indep_j']:+.2f} mJ (given at most "
            f"{1e3 * r['given_max_j']:.2f} mJ, budget {1e3 * r['budget_j']:g}), limited {r['limited_steps']} of "
            f"{r['steps']} steps, faults {r['faults']}" + (f", CRASH {r['crash']}" if r["crash"] else ""))


def run_matrix(n: int, seed: int = 0, seconds: float = 3.0, *, on_row=None, only=None,
               settings_over: dict | None = None) -> list[dict]:
    """``n`` cases (or the run numbers ``only``), each with the layer off and on; ``on_row(row)``
    after each; ``settings_over`` as :func:`run_case` takes it."""
    rows = []
    for i in (only if only is not None else range(n)):
        case = draw(seed, i)
        for layer in (False, True):
            r = run_case(case, layer, seconds, settings_over=settings_over)
            rows.append(r)
            if on_row is not None:
                on_row(r)
    return rows
