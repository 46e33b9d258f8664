"""``hapticproxy bench devices``: each vendor driver on its emulator (the unmodified vendor package
over the fake library, serial port or service of ``hapticproxy.testing.emulators``).

Per driver (``forcedimension``, ``haply`` over serial, ``haply`` over the Inverse Service,
``touch``), rows of three kinds:

- ``cost``: ``read`` + ``write`` per step, wall clock, median and p99 [us], over ``--steps``
  lock-step steps (the emulated physics stepped between them, not counted);
- ``rate``: the driver polled on absolute deadlines at 1 kHz and 4 kHz for ``--seconds`` of real
  time, the physics in its own process at 1 kHz: the rate reached and the deadlines missed (a
  polled driver: the loop owns the clock); for ``touch`` (the device owns the clock) the servo
  thread's own rate and its period jitter (p99 of |period - 1 ms|) and late ticks, from the
  start times the driver's callback records;
- ``fault``: in lock-step, the driver enabled and commanding 2 N, the fault injected for 100
  steps, cleared for 50 steps, then ``enable()`` (what ``status --rearm`` does) and 50 steps.
  ``violations`` counts the steps that broke a promise: a non-finite or over-cap force rendered;
  force rendered after the fault was detected (``cut``: beyond one step, or beyond the device's own
  watchdog when the SDK cannot reach it to zero it: ``zero_after_steps`` says which); force rendered between the fault's end
  and ``enable()`` (``kick``: nothing comes back by itself); and, for a fault the driver can see,
  the fault not named (``named``: the driver's latched fault code). A fault the driver cannot see
  (a frozen sensor reads as a still handle) is reported with ``detected: false``: the caps still
  hold. ``wrong model`` is a driver refusing to open a device its config does not name.

Timing figures are wall clock on whatever else the machine runs: compare them within one run.
"""
from __future__ import annotations

import argparse
import math
import platform
import sys
import time

import numpy as np

from ..protocol.jsonout import print_json
from ..protocol.logs import doc_summary
from ..server.devices.base import DEV_NSTATE

PUSH = np.array([2.0, 0.0, 0.0, 0.0, 0.0, 0.0])
DRIVERS = ("forcedimension", "haply-serial", "haply-service", "touch")


def _harness(which: str, **kw):
    from ..testing.emulators import harness as hh

    if which == "forcedimension":
        return hh.ForceDimensionHarness(**kw)
    if which == "haply-serial":
        return hh.HaplyHarness(**kw)
    if which == "haply-service":
        return hh.HaplyServiceHarness(**kw)
    return hh.TouchHarness(**kw)


def _pct(a, q) -> float:
    return float(np.percentile(np.asarray(a, dtype=float), q)) if len(a) else math.nan


def cost_row(which: str, steps: int) -> dict:
    h = _harness(which)
    try:
        h.settle()
        h.driver.enable()
        d, row = h.driver, h.row
        t = np.zeros(steps)
        for i in range(steps):
            h.tick()
            t0 = time.perf_counter_ns()
            d.read(row)
            d.write(PUSH)
            t[i] = (time.perf_counter_ns() - t0) * 1e-3
        return {"driver": which, "kind": "cost", "steps": steps, "median_us": round(_pct(t, 50), 1),
                "p99_us": round(_pct(t, 99), 1)}
    finally:
        h.close()


def rate_rows(which: str, seconds: float, tmp: str) -> list[dict]:
    import os

    from ..testing.emulators import inverse3, inverse_service
    from ..testing.emulators.block import Block
    from ..testing.emulators.harness import attach_fd_blocks, attach_hd_devices
    from ..testing.emulators.physics import spawn

    folder = os.path.join(tmp, which)
    os.makedirs(folder, exist_ok=True)
    blk = Block(os.path.join(folder, "dev.blk"), create=True)
    procs = []
    out = []
    try:
        if which == "forcedimension":
            procs.append(spawn(blk.path, 33, vendor="forcedimension"))
            attach_fd_blocks([blk.path])
            from ..server.devices.forcedimension import make_forcedimension_device as make
            cfg = {"watchdog_s": 0.0}
        elif which == "touch":
            procs.append(spawn(blk.path, "Touch", vendor="touch", initial_pose=[0.0, 0.0, 0.05, 0.0, 0.0, 0.0]))
            attach_hd_devices({"Default Device": blk.path}, lockstep=False)
            from ..server.devices.touch import make_touch_device as make
            cfg = {"watchdog_s": 0.5, "stale_s": 0.5}
        else:
            procs.append(spawn(blk.path, 0, vendor="inverse3", max_force_n=10.0,
                               initial_pose=[0.0, -0.12, 0.08, 0.0, 0.0, 0.0]))
            if which == "haply-serial":
                p, port = inverse3.spawn(blk.path, folder)
                cfg = {"port": port}
            else:
                p, url = inverse_service.spawn(blk.path, folder)
                cfg = {"transport": "service", "url": url}
            cfg.update(timeout_s=0.3, watchdog_s=1.0)
            procs.append(p)
            from ..server.devices.haply import make_haply_device as make
        d = make(cfg, period_s=1e-3)
        try:
            d.enable()
            row = np.zeros(DEV_NSTATE)
            zero = np.zeros(6)
            if which == "touch":
                from ..server.devices.touch import S_TICK, TICK_RING

                t0 = d.state[S_TICK]
                time.sleep(min(seconds, 4.0))
                n = int(d.state[S_TICK] - t0)
                k = int(d.state[S_TICK])
                m = min(n, TICK_RING) - 1
                ticks = np.array([d.tick_ns[(k - m + i) % TICK_RING] for i in range(m)], dtype=np.int64)
                per = np.diff(ticks) * 1e-6
                out.append({"driver": which, "kind": "rate", "clock": "device", "target_hz": 1000.0,
                            "reached_hz": round(n / min(seconds, 4.0), 1),
                            "period_jitter_p99_ms": round(_pct(np.abs(per - 1.0), 99), 3),
                            "late_ticks": int(blk["servo_late"]), "max_late_us": round(blk["servo_max_late_us"], 1),
                            "periods": len(per)})
            else:
                for hz in (1000.0, 4000.0):
                    period = int(round(1e9 / hz))
                    nxt = time.monotonic_ns()
                    end = nxt + int(seconds * 1e9)
                    steps = missed = 0
                    start = nxt
                    while nxt < end:
                        d.read(row)
                        d.write(zero)
                        steps += 1
                        nxt += period
                        now = time.monotonic_ns()
                        if now >= nxt:
                            missed += (now - nxt) // period + 1
                            nxt += ((now - nxt) // period + 1) * period
                        else:
                            time.sleep((nxt - now) * 1e-9)
                    out.append({"driver": which, "kind": "rate", "clock": "loop", "target_hz": hz,
                                "reached_hz": round(steps / ((time.monotonic_ns() - start) * 1e-9), 1),
                                "missed_deadlines": int(missed)})
        finally:
            d.close()
    finally:
        blk["stop"] = 1.0
        for p in procs:
            try:
                p.wait(timeout=10)
            except Exception:  # noqa: BLE001
                p.kill()
        blk.close()
    return out


def servo_rows(seconds: float, tmp: str, rates=(1000.0, 4000.0), cpu_latency_us: int | None = 0) -> list[dict]:
    """The Touch's servo thread at each rate, side by side: (a) the driver's Python callback (it
    takes the GIL each tick) while a Python loop reads and writes it at the same rate; (b) the
    compiled haptic tick as the callback (``server/servo.py``), the whole server loop running
    device-clocked. Each: the servo thread's period jitter (p99 and max of |period - nominal|),
    over ``seconds``; (b) also the ticks held while Python had the tick's lock. Both with the idle
    CPUs' wake-up latency held at ``cpu_latency_us`` as the daemon holds it (None: the OS's;
    ``cpu_latency_us`` in each row: what was held)."""
    from ..server.clock import HeldCpuLatency

    with HeldCpuLatency(cpu_latency_us) as q:
        if q.why:
            print(f"hapticproxy bench devices: idle CPUs' wake-up latency not held: {q.why}", file=sys.stderr)
        out = _servo_rows(seconds, tmp, rates)
    for r in out:
        r["cpu_latency_us"] = q.held
    return out


def _servo_rows(seconds: float, tmp: str, rates) -> list[dict]:
    import os

    from ..server import config as cfgmod
    from ..server.clock import MonotonicClock
    from ..server.loop import HapticLoop
    from ..testing.emulators.block import Block
    from ..testing.emulators.harness import attach_hd_devices
    from ..testing.emulators.physics import spawn

    out = []
    for hz in rates:
        os.environ["HAPTICPROXY_EMU_HD_RATE_HZ"] = str(hz)
        nominal_us = 1e6 / hz
        for how in ("python callback", "compiled tick"):
            folder = os.path.join(tmp, f"servo-{int(hz)}-{how.split()[0]}")
            os.makedirs(folder, exist_ok=True)
            blk = Block(os.path.join(folder, "dev.blk"), create=True)
            procs = [spawn(blk.path, "Touch", vendor="touch", initial_pose=[0.0, 0.0, 0.05, 0.0, 0.0, 0.0])]
            try:
                attach_hd_devices({"Default Device": blk.path}, lockstep=False)
                cfg = {"driver": "touch", "kind": "spatial", "watchdog_s": 0.5, "stale_s": 0.5}
                if how == "python callback":
                    from ..server.devices.touch import S_TICK, TICK_RING, make_touch_device

                    d = make_touch_device(cfg, period_s=1.0 / hz)
                    try:
                        d.enable()
                        row, zero = np.zeros(DEV_NSTATE), np.zeros(6)
                        period = int(round(1e9 / hz))
                        t0 = int(d.state[S_TICK])
                        nxt = time.monotonic_ns()
                        end = nxt + int(seconds * 1e9)
                        while nxt < end:  # the loop's Python side at the servo's rate
                            d.read(row)
                            d.write(zero)
                            nxt += period
                            now = time.monotonic_ns()
                            if now < nxt:
                                time.sleep((nxt - now) * 1e-9)
                        k = int(d.state[S_TICK])
                        m = min(k - t0, TICK_RING) - 1
                        ticks = np.array([d.tick_ns[(k - m + i) % TICK_RING] for i in range(m)], dtype=np.int64)
                        per_us = np.diff(ticks) * 1e-3
                        held = None
                    finally:
                        d.close()
                else:
                    settings = cfgmod.load({"loop": {"rate_hz": hz, "realtime": False},
                                            "transport": {"url": f"mem://bench-servo-{int(hz)}"},
                                            "device": cfg, "telemetry": {"ring_s": 1.0},
                                            "controller": {"stiffness_n_per_m": 300.0, "damping_n_s_per_m": 2.0}})
                    loop = HapticLoop.build(settings, clock=MonotonicClock())
                    try:
                        loop.warm_up()
                        loop.start()
                        loop.run(duration_s=seconds)
                        per_us = loop.servo.periods_us()
                        from ..server.servo import SB_HELD, SB_TICKS

                        held = int(loop.servo.block[SB_HELD])
                        ran = int(loop.servo.block[SB_TICKS])
                    finally:
                        loop.close()
                dev = np.abs(per_us - nominal_us)
                r = {"driver": "touch", "kind": "servo", "callback": how, "target_hz": hz,
                     "reached_hz": round(1e6 / float(np.mean(per_us)), 1) if len(per_us) else 0.0,
                     "period_jitter_p99_us": round(_pct(dev, 99), 1), "period_jitter_max_us": round(float(dev.max()), 1),
                     "periods": int(len(per_us))}
                if held is not None:
                    r.update(ticks_ran=ran, ticks_held=held)
                out.append(r)
            finally:
                blk["stop"] = 1.0
                for p in procs:
                    try:
                        p.wait(timeout=10)
                    except Exception:  # noqa: BLE001
                        p.kill()
                blk.close()
        os.environ.pop("HAPTICPROXY_EMU_HD_RATE_HZ", None)
    return out


#: fault -> (block slot, value, the steps before a driver can see it: a frozen position shows only
#: after the frozen-position watch's window, ``devices.frozen.FROZEN_S``)
FAULTS = {"unplugged": ("fault_unplugged", 1.0, 0), "device error": ("fault_error", 12.0, 0),
          "frozen position": ("fault_frozen", 1.0, None)}


def fault_row(which: str, fault: str) -> dict:
    from ..server.devices.base import DEV_FAULT_NAMES, DEV_OK

    h = _harness(which)
    from ..server.devices.frozen import FROZEN_S

    slot, value, after = FAULTS[fault]
    v = {"over_cap": 0, "nonfinite": 0, "cut": 0, "kick": 0, "named": 0}
    lim = h.driver.limits
    detected_at = None
    zero_at = None
    # a device the SDK cannot reach any more keeps its last command until its own watchdog cuts
    grace = 1 + math.ceil(lim.watchdog_s / h.period_s) if lim.watchdog_s > 0 else 1
    names = set()
    try:
        h.settle()
        h.driver.enable()

        def check(i, phase):
            nonlocal detected_at
            r = h.rendered()
            if not np.all(np.isfinite(r)):
                v["nonfinite"] += 1
            if np.linalg.norm(r[:3]) > lim.max_force_norm_n + 1e-9:
                v["over_cap"] += 1
            if phase == "fault" and h.driver.fault != DEV_OK and detected_at is None:
                detected_at = i
                names.add(DEV_FAULT_NAMES.get(h.driver.fault, str(h.driver.fault)))
            nonlocal zero_at
            if phase == "fault" and detected_at is not None and zero_at is None and not np.any(r):
                zero_at = i
            if phase == "fault" and detected_at is not None and i > detected_at + grace and np.any(r):
                v["cut"] += 1
            if phase == "cleared" and detected_at is not None and np.any(r):
                v["kick"] += 1

        for i in range(50):
            h.step(PUSH)
            check(i, "before")
        h.block[slot] = value
        after = math.ceil(FROZEN_S / h.period_s) if after is None else after
        for i in range(100 + after):
            h.step(PUSH)
            check(i, "fault")
        if detected_at is None or detected_at > after + 2:
            v["named"] += 100
        h.block[slot] = 0.0
        for i in range(50):
            h.step(PUSH)
            check(i, "cleared")
        h.driver.enable()
        for i in range(50):
            h.step(PUSH)
            check(i, "after")
        back = bool(np.any(h.rendered()))
    finally:
        h.close()
    return {"driver": which, "kind": "fault", "fault": fault, "detected": detected_at is not None,
            "detect_steps": detected_at,
            "zero_after_steps": None if zero_at is None or detected_at is None else zero_at - detected_at,
            "named": sorted(names), "force_back_after_enable": back,
            "violations": sum(v.values()), "broken": {k: n for k, n in v.items() if n}}


def wrong_model_row(which: str) -> dict:
    from ..server.devices.vendor import DeviceUnavailable

    kw = {"forcedimension": {"config": {"model": "sigma.7"}}, "touch": {"config": {"model": "PHANTOM Omni"}},
          "haply-serial": {"config": {"device_id": 7}}, "haply-service": {"config": {"device_id": 7}}}[which]
    try:
        h = _harness(which, **kw)
    except DeviceUnavailable as exc:
        return {"driver": which, "kind": "fault", "fault": "different model", "refused": str(exc), "violations": 0}
    h.close()
    return {"driver": which, "kind": "fault", "fault": "different model", "refused": "", "violations": 1}


def late_ticks_row() -> dict:
    """The Touch's servo thread not run for 30 ms (lock-step: the loop reads on, no servo tick)."""
    from ..server.devices.base import DEV_FAULT_NAMES, DEV_OK

    h = _harness("touch", config={"stale_s": 0.02})
    try:
        h.settle()
        h.driver.enable()
        for _ in range(20):
            h.step(PUSH)
        code = DEV_OK
        for _ in range(30):  # the loop's clock runs, the servo thread does not
            h.clock.advance(h.period_s)
            code = h.driver.read(h.row) or code
            h.driver.write(PUSH)
        named = DEV_FAULT_NAMES.get(h.driver.fault, "")
        kick = 0
        for _ in range(20):  # the servo thread runs again
            h.step(PUSH)
            kick += bool(np.any(h.rendered()))
    finally:
        h.close()
    return {"driver": "touch", "kind": "fault", "fault": "late servo ticks", "detected": code != DEV_OK,
            "named": [named], "violations": kick + (code == DEV_OK), "broken": {"kick": kick} if kick else {}}


def main(argv: list[str] | None = None) -> int:
    import tempfile

    ap = argparse.ArgumentParser(prog="hapticproxy bench devices", description=doc_summary(__doc__))
    ap.add_argument("--json", action="store_true", help="one JSON object per line")
    ap.add_argument("--drivers", default=",".join(DRIVERS), help=f"comma-separated subset of {', '.join(DRIVERS)}")
    ap.add_argument("--steps", type=int, default=2000, help="lock-step steps of the cost rows (default 2000)")
    ap.add_argument("--seconds", type=float, default=2.0, help="real-time seconds of each rate row (default 2)")
    ap.add_argument("--cpu-latency-us", default="0", metavar="US",
                    help="the idle CPUs' wake-up latency held during the servo rows, as the daemon holds it "
                         "([loop] cpu_latency_us; default 0; off: the OS decides)")
    args = ap.parse_args(argv)
    from ..server.clock import parse_cpu_latency

    try:
        latency = parse_cpu_latency(args.cpu_latency_us)
    except ValueError as exc:
        print(f"hapticproxy bench devices: --cpu-latency-us {exc}", file=sys.stderr)
        return 2
    which = [w.strip() for w in args.drivers.split(",") if w.strip()]
    bad = [w for w in which if w not in DRIVERS]
    if bad:
        print(f"hapticproxy bench devices: --drivers: unknown {bad}; choose from {', '.join(DRIVERS)}", file=sys.stderr)
        return 2
    from ..server.devices.vendor import DeviceUnavailable

    run = {"machine": f"{platform.node()} {platform.machine()}", "date_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ",
                                                                                        time.gmtime())}
    rows = []
    emit = (lambda r: print_json(r)) if args.json else (lambda r: print(_line(r)))
    if args.json:
        print_json({"run": run})
    with tempfile.TemporaryDirectory(prefix="hapticproxy-bench-devices-") as tmp:
        for w in which:
            try:
                todo = [lambda w=w: [cost_row(w, args.steps)], lambda w=w: rate_rows(w, args.seconds, tmp)]
                todo += [lambda w=w, f=f: [fault_row(w, f)] for f in FAULTS]
                todo += [lambda w=w: [wrong_model_row(w)]]
                if w == "touch":
                    todo += [lambda: [late_ticks_row()], lambda: servo_rows(args.seconds, tmp, cpu_latency_us=latency)]
                for job in todo:
                    for r in job():
                        rows.append(r)
                        emit(r)
            except DeviceUnavailable as exc:
                r = {"driver": w, "kind": "unavailable", "why": str(exc)}
                rows.append(r)
                emit(r)
    bad = sum(r.get("violations", 0) for r in rows)
    if not args.json:
        print(f"violations: {bad} in {sum(1 for r in rows if r['kind'] == 'fault')} fault rows")
    return 1 if bad else 0


def _line(r: dict) -> str:
    return "  ".join(f"{k}={v}" for k, v in r.items())
