"""The safety filter's and the fault policy's rows of ``hapticproxy bench faults``.

Each row runs the server's own loop (``HapticLoop``: the compiled tick, the controller, the model,
the safety filter, the lifecycle) with the simulated device and an engine behind the real protocol
(``experiments.harness.SimEnvClient``), in simulated time: deterministic, so a row shows the
promise itself and not the machine's load. The last row (``accurate`` at 4 kHz beside a loaded
machine) runs the real server in real time, as it must.

Every row checks, at every step of the telemetry (``cmd`` the wrench written to the device,
``gain`` the safety filter's gain after the step), the filter's contract (``server/safety.py``):
finite; the force's norm within the cap and every component within it, the torque's likewise;
no change of the force vector larger than the rate limit (the torque's its own) unless the gain
fell (a fade may take force away faster only by what the gain drops); while the gain falls, every
component between zero and its previous value scaled like the gain (a pushing hand never gets
more from a fade); while it rises, the norm growing by at most the ramp's step. Each row adds its
own promise (``broken`` names the broken ones with counts; ``violations`` is their sum):

- **torque caps and torque rate, spatial device**: the pybullet cube pushed onto the floor and
  twisted with 2 N m about every axis (four times the 0.5 N m cap);
- **norm cap, spatial device pushed along a diagonal**: 12 N down and 12 N sideways onto the floor;
- **norm cap, 1-DOF device on a diagonal axis**: the device's axis (1, 1, 0) / sqrt 2 in the world,
  the hand pushing 14 N along it into the peg's wall (a cap per component let 14.1 N through);
- **fade envelope under a pushing hand**: the engine silent for 400 ms while a 3 N hand keeps
  pushing harder (3 N plus 5 N/s);
- **a device fault 5 s after a recovered stall**: a 80 ms stall of the loop (the device's watchdog
  is 50 ms) recovers by itself; 5 s later the device reports its watchdog: that one latches
  (fault ``device``, zero output until the re-arm);
- **idle speed**: the handle thrown at 3 m/s (its limit is 2) before any client came: no fault, a
  client then engages as usual;
- **flipped normals under a pushing hand**: the first two updates that carry the wall's contacts
  report its normals reversed as the hand starts pressing the peg onto it: the true normals that
  follow are taken (at most two refusals per reversed update: the model once refused every one
  after them), the proxy stays on the wall (no more than 2 mm beyond where it rests), the hand is
  never pulled towards the wall from a second after the first contact on (by more than 0.05 N),
  and the wall carries the push (0.5 N within 0.02 N);
- **accurate on a loaded machine**: ``--preset accurate`` (4 kHz) with two processes burning both
  cores: the loop never latches on stalls (``stalls_repeated``), whatever it misses.
"""
from __future__ import annotations

import copy
import math
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field

import numpy as np

TOL = 1e-9


@dataclass
class SafetyCase:
    name: str
    kind: str
    spec: dict = field(default_factory=dict)


def cases() -> list[SafetyCase]:
    return [
        SafetyCase("torque caps and torque rate, spatial device (2 N m twist)", "torque"),
        SafetyCase("norm cap, spatial device pushed along a diagonal (12 N down, 12 N sideways)", "diagonal"),
        SafetyCase("norm cap, 1-DOF device on a diagonal axis (14 N along it)", "axis1d"),
        SafetyCase("fade envelope under a pushing hand (engine silent 400 ms, 3 N + 5 N/s)", "fade"),
        SafetyCase("device fault 5 s after a recovered stall: latches", "late-fault"),
        SafetyCase("idle speed (handle at 3 m/s before a client): no latch", "idle-speed"),
        SafetyCase("flipped normals as a pushing hand presses the tool onto the floor", "flipped"),
        SafetyCase("accurate (4 kHz) on a loaded machine: no stall latch", "accurate"),
    ]


# ------------------------------------------------------------------------------ the contract
def check_filter(rows: np.ndarray, lim: dict, broken: dict) -> None:
    """The safety filter's contract on telemetry rows (flat, ``shm.TEL`` columns)."""
    from ..server.shm import TEL

    f = rows[:, [TEL["cmd_fx"], TEL["cmd_fy"], TEL["cmd_fz"]]]
    t = rows[:, [TEL["cmd_tx"], TEL["cmd_ty"], TEL["cmd_tz"]]]
    g = rows[:, TEL["gain"]]
    F, T = lim["force_cap_n"], lim["torque_cap_n_m"]
    rf, rt = lim["rate_limit_n_per_step"], lim["torque_rate_n_m_per_step"]
    ramp = lim["ramp_per_step"]

    def mark(name, mask):
        k = int(np.count_nonzero(mask))
        if k:
            broken[name] = broken.get(name, 0) + k

    fin = np.isfinite(f).all(axis=1) & np.isfinite(t).all(axis=1)
    mark("non-finite", ~fin)
    f, t = np.nan_to_num(f), np.nan_to_num(t)
    nf, nt = np.linalg.norm(f, axis=1), np.linalg.norm(t, axis=1)
    mark("force norm over the cap", nf > F + TOL)
    mark("torque norm over the cap", nt > T + TOL)
    mark("over gain x cap", (nf > g * F + TOL) | (nt > g * T + TOL))
    df = np.linalg.norm(np.diff(f, axis=0), axis=1)
    dt = np.linalg.norm(np.diff(t, axis=0), axis=1)
    g0, g1 = g[:-1], g[1:]
    falling = g1 < g0
    shrink = np.where(falling, g1 / np.where(g0 > 0, g0, 1.0), 1.0)
    mark("force step over the rate limit", ~falling & (df > rf + TOL))
    mark("torque step over its rate limit", ~falling & (dt > rt + TOL))
    nf0, nt0 = nf[:-1], nt[:-1]
    mark("fade faster than the gain allows",
         falling & ((df > rf + (1 - shrink) * nf0 + TOL) | (dt > rt + (1 - shrink) * nt0 + TOL)))
    prev = np.hstack([f[:-1], t[:-1]])
    cur = np.hstack([f[1:], t[1:]])
    env = np.abs(prev) * shrink[:, None] + TOL
    mark("a fade pushed harder than its envelope",
         falling & ((np.abs(cur) > env) | (cur * prev < -TOL)).any(axis=1))
    rising = g1 > g0
    mark("a ramp grew faster than its slope", rising & ((nf[1:] > nf0 + F * ramp + TOL) | (nt[1:] > nt0 + T * ramp + TOL)))


def _limits(loop) -> dict:
    from ..server import safety as sf

    sp = loop.ctrl.sp
    return {"force_cap_n": float(sp[sf.SP_FMAX]), "torque_cap_n_m": float(sp[sf.SP_TMAX]),
            "rate_limit_n_per_step": float(sp[sf.SP_FRATE]), "torque_rate_n_m_per_step": float(sp[sf.SP_TRATE]),
            "ramp_per_step": float(sp[sf.SP_RAMP])}


# ------------------------------------------------------------------------------ simulated runs
class SimRun:
    """The loop, the simulated device and an engine in simulated time (``experiments.harness``)."""

    def __init__(self, spec, folder: str) -> None:
        from pathlib import Path

        from ..experiments.harness import Misreport, SimEnvClient
        from ..server import config as cfgmod
        from ..server.clock import SimClock
        from ..server.loop import HapticLoop

        self.spec = spec
        url = f"mem://bench-safety-{os.getpid()}-{id(self)}"
        self.settings = cfgmod.load(spec.settings_dict(url, None, Path(folder)))
        self.clock = SimClock(start_ns=1_000_000_000)
        self.loop = HapticLoop.build(self.settings, clock=self.clock)
        self.loop.warm_up()
        self.loop.start()
        self.env = SimEnvClient(spec.make_engine(), url, self.clock, scene=spec.scene, epsilon_m=spec.epsilon_m,
                                max_contacts=spec.capacity,
                                misreport=Misreport(spec.misreport, spec.misreport_from_s, spec.misreport_every))
        self.env_on = True
        self.rows: list = []

    def run(self, seconds: float, on_step=None) -> None:
        sh = self.loop.shared
        for i in range(int(round(seconds * self.settings.rate_hz))):
            if self.env_on:
                self.env.service()
            if on_step is not None:
                on_step(i)
            self.loop.step()
            self.rows.append(sh.ring[(int(sh.head[0]) - 1) % sh.ring_rows].copy())

    def close(self) -> None:
        self.env.close()
        self.env.engine.close()
        self.loop.close()

    def table(self) -> np.ndarray:
        return np.array(self.rows)


def self_rate(r) -> float:
    """A second of steps of this run."""
    return r.settings.rate_hz


def _reasons(loop) -> list[str]:
    from ..server.lifecycle import Reason

    return [Reason(r[4]).name.lower() for r in loop.shared.transitions_since(0)]


def run_case(case: SafetyCase, bf=None) -> dict:
    """One row; ``bf``: the ``bench_faults`` module (its real-time rig: the ``accurate`` row needs it)."""
    t0 = time.monotonic()
    row = {"case": case.name, "mode": "real time" if case.kind == "accurate" else "simulated time"}
    broken: dict = {}
    try:
        if case.kind == "accurate":
            _accurate(row, broken, bf)
        else:
            with tempfile.TemporaryDirectory(prefix="hp-safety-") as folder:
                _simulated(case, row, broken, folder)
    except Exception as exc:  # noqa: BLE001 - a row that could not run says why
        row["error"] = f"{type(exc).__name__}: {exc}"
        broken["did not run"] = 1
    row["broken"] = broken
    row["violations"] = int(sum(broken.values()))
    row["seconds"] = round(time.monotonic() - t0, 1)
    return row


def _simulated(case: SafetyCase, row: dict, broken: dict, folder: str) -> None:
    from ..experiments.harness import Hand, RunSpec
    from ..server.lifecycle import Fault
    from ..server.shm import TEL

    spec = RunSpec.for_method("LM5", rate_hz=1000.0, seconds=8.0, contact_frame="engine")  # the server's default
    if case.kind in ("torque", "diagonal"):
        # pybullet's peg scene: a gripping hand takes the peg down into its square hole (0.5 mm of
        # clearance) in 1.5 s, then twists it about z (torque) or pulls it down and sideways
        # (force along a diagonal); the hole's walls and floor hold the peg, the coupling
        # stretches, the command meets the cap and stays there
        last = [0.0, 0.0, -0.05, 0.0, 0.0, 0.6] if case.kind == "torque" else [0.1, 0.0, -0.15, 0.0, 0.0, 0.0]
        grip = {"type": "impedance", "start": "server", "stiffness_n_per_m": 40.0 if case.kind == "torque" else 150.0,
                "damping_n_s_per_m": 5.0, "rot_stiffness_n_m_per_rad": 3.0, "rot_damping_n_m_s_per_rad": 0.05,
                "target": {"type": "waypoints", "points": [[0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
                                                           [1.5, 0.0, 0.0, -0.05, 0.0, 0.0, 0.0],
                                                           [3.0, 0.0, 0.0, -0.05, 0.0, 0.0, 0.0], [4.0, *last]]}}
        # (the rigid update policy and stiff contacts hold the peg in its hole: with deformation
        # the sustained twist lets the proxy turn 0.57 rad inside the hole, a finding of its own)
        spec = spec.but(engine="pybullet", scene="peg", device_kind="spatial", capacity=16, policy="rigid",
                        stiffness_n_per_m=20000.0, env_rate_hz=(60.0, 60.0), device=(("hand", grip),))
    elif case.kind == "axis1d":
        a = 1.0 / math.sqrt(2.0)
        spec = spec.but(engine="peg1d", scene="peg1d", device_kind="1dof", capacity=4,
                        hand=Hand("constant", (14.0, 0.0, 0.0), start_s=0.5), env_rate_hz=(60.0, 60.0),
                        device=(("axis", [a, a, 0.0]), ("max_force_n", 20.0)))
    elif case.kind == "flipped":
        spec = spec.but(engine="pymunk", scene="testbed", env_rate_hz=(60.0, 60.0), misreport="flip-hold",
                        misreport_from_s=0.45, hand=Hand("constant", (0.0, 0.5, 0.0), start_s=0.5))
    else:
        spec = spec.but(engine="pymunk", scene="testbed", env_rate_hz=(60.0, 60.0),
                        hand=Hand("constant", (0.0, 3.0 if case.kind == "fade" else 0.5, 0.0), start_s=0.5))
    r = SimRun(spec, folder)
    try:
        loop, dev = r.loop, r.loop.device
        lim = _limits(loop)
        row.update(force_cap_n=lim["force_cap_n"], torque_cap_n_m=lim["torque_cap_n_m"])
        if case.kind == "flipped":
            flips = {"n": 0}
            mr = r.env.misreport
            apply = mr.apply

            def two_flips(env_time_s, keys, normal, n):  # only the first two updates that touch
                if n and flips["n"] < 2 and env_time_s >= mr.from_s:
                    flips["n"] += 1
                    apply(env_time_s, keys, normal, n)

            mr.apply = two_flips
        if case.kind == "idle-speed":
            r.env_on = False
            r.run(0.2)
            st = dev._st
            from ..server.devices.layout import DST_TWIST

            for k in range(50):  # thrown: 3 m/s for 50 ms
                st[DST_TWIST] = 3.0
                r.run(0.001)
            r.run(0.5)
            row["speed_trips"] = loop.ctrl.counters()["speed_trips"]
            if loop.state_name == "fault":
                broken["latched while idle"] = 1
            r.env_on = True
            r.run(3.0)
            if loop.state_name != "engaged":
                broken["a client did not engage after it"] = 1
        elif case.kind == "fade":
            r.run(4.0)
            n0 = len(r.rows)
            r.env_on = False
            push = {"t": 0}

            tab = dev._tab  # the hand's steps: rows (t_s, fx, fy, tz); the last one holds from 0.5 s

            def harder(i):
                push["t"] += 1
                tab[-1, 2] = 3.0 + 5.0 * push["t"] * 1e-3  # the hand pushes harder and harder

            r.run(0.4, on_step=harder)
            r.env_on = True
            r.run(2.0)
            rows = r.table()
            g = rows[n0:n0 + 400, TEL["gain"]]
            row["gain_at_end_of_silence"] = round(float(g[-1]), 3)
            if g[-1] > 0.0:
                broken["no fade"] = 1
        elif case.kind == "late-fault":
            r.run(3.0)
            r.clock.stall(80_000_000)
            r.run(1.0)
            if loop.state_name != "engaged":
                broken["the stall did not recover"] = 1
            r.run(5.0)
            from ..server.devices.base import DEV_FAULT_WATCHDOG
            from ..server.devices.layout import DC_FAULT

            dev._ctl[DC_FAULT] = DEV_FAULT_WATCHDOG
            n0 = len(r.rows)
            r.run(2.0)
            after = r.table()[n0 + 2:]
            row["fault"] = Fault(loop.fault).name.lower()
            if loop.fault != Fault.DEVICE:
                broken["did not latch"] = 1
            if np.any(after[:, [TEL["cmd_fx"], TEL["cmd_fy"], TEL["cmd_tz"]]] != 0.0):
                broken["force while latched"] = int(np.count_nonzero(np.any(
                    after[:, [TEL["cmd_fx"], TEL["cmd_fy"], TEL["cmd_tz"]]] != 0.0, axis=1)))
        else:
            r.run(spec.hand.start_s + spec.seconds)
        rows = r.table()
        check_filter(rows, lim, broken)
        f = rows[:, [TEL["cmd_fx"], TEL["cmd_fy"], TEL["cmd_fz"]]]
        t = rows[:, [TEL["cmd_tx"], TEL["cmd_ty"], TEL["cmd_tz"]]]
        row["max_force_norm_n"] = round(float(np.max(np.linalg.norm(f, axis=1))), 4)
        row["max_torque_norm_n_m"] = round(float(np.max(np.linalg.norm(t, axis=1))), 4)
        row["max_force_step_n"] = round(float(np.max(np.linalg.norm(np.diff(f, axis=0), axis=1))), 4)
        row["max_torque_step_n_m"] = round(float(np.max(np.linalg.norm(np.diff(t, axis=0), axis=1))), 4)
        if case.kind in ("torque", "diagonal", "axis1d"):
            cap_hit = np.max(np.linalg.norm(t if case.kind == "torque" else f, axis=1))
            cap = lim["torque_cap_n_m"] if case.kind == "torque" else lim["force_cap_n"]
            row["cap_reached"] = bool(cap_hit >= 0.99 * cap)
            if not row["cap_reached"]:
                broken["the case did not reach the cap (it proves nothing)"] = 1
        if case.kind == "flipped":
            low = rows[:, TEL["proxy_y"]]
            row["flips_sent"] = flips["n"]
            row["flips_refused"] = int(loop.model.counters()["flips_refused"]) if loop.model is not None else 0
            # the hand pushes +y onto the wall: a pull is cmd_fy > 0. The impact itself swings the
            # command both ways for a moment (the same without flips); from a second after the
            # first contact on, the device never pulls the hand towards the wall
            fy = rows[:, TEL["cmd_fy"]]
            touch = np.nonzero(rows[:, TEL["contacts"]] > 0)[0]
            after = fy[touch[0] + int(self_rate(r)):] if len(touch) else fy
            row["max_pull_n"] = round(float(max(0.0, np.max(after))), 4)
            rest = np.median(low[-500:])
            row["proxy_fell_mm"] = round(float(np.max(low) - rest) * 1e3, 3)
            row["final_force_n"] = round(float(-np.mean(fy[-500:])), 4)
            if row["max_pull_n"] > 0.05:
                broken["the hand was pulled"] = 1
            if row["proxy_fell_mm"] > 2.0:
                broken["the proxy fell through the floor"] = 1
            if abs(row["final_force_n"] - 0.5) > 0.02:
                broken["the floor does not carry the push"] = 1
            # the true normals after the two reversed ones are taken: refusing them (the model once
            # refused 439 true normals after 2 reversed ones here) leaves it without the floor
            if row["flips_refused"] > 2 * row["flips_sent"]:
                broken["true normals refused after reversed ones"] = row["flips_refused"]
        row["faults"] = int(loop.faults_total)
        row["transitions"] = _reasons(loop)[-6:]
    finally:
        r.close()


# ------------------------------------------------------------------------------ real time
def _accurate(row: dict, broken: dict, bf) -> None:
    """``--preset accurate`` at 4 kHz beside two processes that burn both cores, with a client."""
    from ..server import config as cfgmod
    from ..server.daemon import Supervisor
    from ..server.lifecycle import Fault

    burn = "import time\nt = time.time() + 30\nwhile time.time() < t: pass\n"
    hogs = [subprocess.Popen([sys.executable, "-c", burn]) for _ in range(2)]
    url = f"udp://127.0.0.1:{bf._port()}"
    data = copy.deepcopy(bf.settings_for(url, seconds=10.0).data)
    data["preset"] = "accurate"
    data["loop"] = {"rate_hz": 4000.0, "realtime": True}
    data["telemetry"] = {"ring_s": 12.0}
    data.pop("model", None)  # the preset's model (64 contacts)
    settings = cfgmod.load(data)
    sup = Supervisor(settings)
    client = None
    try:
        sup.start()
        client = bf._ThreadClient("pymunk", url).start()
        t_end = time.monotonic() + 8.0
        while time.monotonic() < t_end:
            sup._serve_status(0.05)
        snap = sup.status()
        head = int(sup.shared.head[0])
        n = min(head, sup.ring_rows)
        rows = sup.shared.ring[np.arange(head - n, head) % sup.ring_rows].copy()
    finally:
        if client is not None:
            client.close()
        sup.close()
        for h in hogs:
            h.kill()
            h.wait()
    row.update(spin_us=round(float(snap.get("spin_ns", 0)) * 1e-3, 1), missed_deadlines=snap.get("missed_deadlines"),
               stall_trips=snap.get("stall_trips"), stall_recoveries=snap.get("stall_recoveries"),
               fault=snap.get("fault"), rate_hz=4000.0, load="2 processes burning the 2 cores")
    if snap.get("fault") == Fault.STALLS_REPEATED.name.lower() or "stalls_repeated" in str(snap.get("fault")):
        broken["stall trips latched"] = 1
    from ..server.tick import SPIN_MAX_SHARE

    if float(snap.get("spin_ns", 0)) > SPIN_MAX_SHARE * 250_000:
        broken["spin over its share of the period"] = 1
    lim = {"force_cap_n": float(snap["force_cap_n"]), "torque_cap_n_m": float(snap["torque_cap_n_m"]),
           "rate_limit_n_per_step": float(snap["rate_limit_n_per_step"]),
           "torque_rate_n_m_per_step": float(settings["safety"]["torque_rate_n_m_per_s"]) / 4000.0,
           "ramp_per_step": (1.0 / 4000.0) / float(settings["safety"]["ramp_in_s"])}
    check_filter(rows, lim, broken)
