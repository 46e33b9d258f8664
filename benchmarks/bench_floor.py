"""``hapticproxy bench floor``: the deadlines this machine keeps with nothing to do in them.

The server's loop cannot keep a deadline the platform does not: a thread that sleeps until an
absolute deadline is woken by the kernel, and in a VM by the host, which may be late however
little the thread does. This benchmark measures that floor with the loop's own wait and no tick:

- **empty tick**: the compiled clock wait of the server's loop (``tick.wait_until_deadline``:
  ``clock_nanosleep`` to ``spin`` before each absolute deadline, then a spin on the clock; whole
  periods missed are skipped) in a thread tuned as the loop process is (SCHED_FIFO 80 when
  granted, 1 ns timer slack, the daemon's calibrated spin, capped at 60 % of the period, on the
  CPU the server's clock thread takes), doing
  nothing at each deadline. Run with the idle CPUs' wake-up latency held at 0 us and left to the
  OS (``--cpu-latency``), alternately, at each ``--rates``;
- **CPU gaps** (``--gap-seconds``): the same thread spinning on the clock for half of each
  second, the gaps between consecutive reads counted (what ``hwlatdetect`` does): time the CPU
  was taken from a thread that never sleeps (an interrupt, another thread, the host);
- the host's **steal** time during each run (``/proc/stat``), where the kernel reports it.

``missed`` is the share of wake-ups at least a period late: a tick that began then would end
after the next deadline (the server's ``bench loop`` counts those steps as missed). Lateness
percentiles are from 1 us bins (upper edges). ``--json``: one object with ``rows`` (one per rate
and latency setting: ``rate_hz``, ``cpu_latency_us`` (None: the OS's), ``spin_us``,
``rt_scheduling``, ``seconds``, ``wakes``, ``skipped`` (whole periods), ``periods``,
``lateness_us`` (``p50``, ``p99``, ``p999``, ``max``), ``missed_fraction``, ``late_over_100us``,
``steal_ms``) and ``gaps`` (per latency setting: ``seconds``, ``reads``, ``over_10us``,
``over_100us``, ``over_250us``, ``over_1ms``, ``miss_floor`` (per rate, "10000", "4000", "1000":
the gaps longer than its period per second over the rate), ``max_us``, ``steal_ms``), ``cpu``
(the CPU the measuring thread ran on, as the server's clock thread: ``[loop] clock_cpu`` auto;
None: not pinned) and ``machine``.

Timing is the machine's: run it on a quiet machine, beside ``bench loop`` for the loop's share.
"""
from __future__ import annotations

import argparse
import os
import platform
import sys
import time

import numpy as np
from numba import njit

from ..protocol.jsonout import print_json
from ..protocol.logs import doc_summary
from ..server import tick
from ..server.clock import (HeldCpuLatency, MonotonicClock, clock_cpus, pin_to_cpu, set_timer_slack_ns,
                            try_realtime)
from ..server.native import monotonic_ns
from ..server.shm import percentiles

#: lateness histogram: 1 us bins to 100 ms, the last bin everything beyond
HIST_BINS = 100_001
#: the CPU-gap detector's spin share of each second (the rest sleeps, far from the kernel's
#: real-time throttling at 95 %)
GAP_SPIN_SHARE = 0.5


# not cached: it inlines tick.py's wait, and numba keys a cache on this file alone
@njit(nogil=True)
def _wait_deadlines(tk, periods, hist):
    """Wait for ``periods`` deadlines from ``tk[TK_DEADLINE_NS]`` on, doing nothing at each.
    Returns ``(wakes, overruns, max_late_ns)``; ``tk[TK_MISSED]`` counts the periods skipped."""
    period = tk[tick.TK_PERIOD_NS]
    end = tk[tick.TK_DEADLINE_NS] + periods * period
    wakes = 0
    overruns = 0
    max_late = 0
    last = hist.shape[0] - 1
    while tk[tick.TK_DEADLINE_NS] < end:
        _now, late, missed = tick.wait_until_deadline(tk)
        wakes += 1
        b = late // 1000
        hist[b if b < last else last] += 1
        if missed > 0:
            overruns += 1
        if late > max_late:
            max_late = late
    return wakes, overruns, max_late


#: the CPU-gap detector's thresholds, us: 10 us, and the periods of 10, 4 and 1 kHz (a gap longer
#: than a period is a deadline missed, however little the tick does)
GAP_THRESHOLDS_US = (10, 100, 250, 1000)


@njit(nogil=True)
def _spin_gaps(duration_ns, thresholds_ns, counts):
    """Read the clock for ``duration_ns``; count the gaps between reads longer than each of
    ``thresholds_ns`` (ascending) in ``counts``. Returns ``(reads, max_gap_ns)``."""
    t0 = monotonic_ns()
    prev = t0
    reads = 0
    max_gap = 0
    lo = thresholds_ns[0]
    while prev - t0 < duration_ns:
        now = monotonic_ns()
        gap = now - prev
        if gap > lo:
            for i in range(thresholds_ns.shape[0]):
                if gap > thresholds_ns[i]:
                    counts[i] += 1
        if gap > max_gap:
            max_gap = gap
        prev = now
        reads += 1
    return reads, max_gap


def steal_ms() -> float | None:
    """The host's steal time over all CPUs so far (``/proc/stat``), ms; None where not reported."""
    try:
        with open("/proc/stat") as f:
            fields = f.readline().split()
        return int(fields[8]) * 1000.0 / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return None


def _delta(a: float | None, b: float | None) -> float | None:
    return None if a is None or b is None else round(b - a, 1)


def empty_tick(rate_hz: float, seconds: float, spin_ns: int) -> dict:
    """One run of the loop's wait at ``rate_hz`` with nothing done at the deadlines (in this thread,
    with whatever scheduling and latency request it holds now)."""
    period = int(round(1e9 / rate_hz))
    tk = tick.new_words(period)
    tk[tick.TK_SPIN_NS] = min(int(spin_ns), int(period * tick.SPIN_MAX_SHARE))
    hist = np.zeros(HIST_BINS, dtype=np.int64)
    periods = max(1, int(round(seconds * rate_hz)))
    start = time.monotonic_ns() + period
    tk[tick.TK_DEADLINE_NS] = start
    s0 = steal_ms()
    wakes, overruns, max_late = _wait_deadlines(tk, periods, hist)
    s1 = steal_ms()
    pct = percentiles(hist)
    lat = {k: pct[k] for k in ("p50", "p99", "p999")}
    lat["max"] = round(max_late / 1000.0, 1)  # exact, not the bin
    return {
        "rate_hz": rate_hz,
        "seconds": seconds,
        "spin_us": tk[tick.TK_SPIN_NS] / 1000.0,
        "wakes": int(wakes),
        "skipped": int(tk[tick.TK_MISSED]),
        "periods": int((tk[tick.TK_DEADLINE_NS] - start) // period),
        "lateness_us": lat,
        "missed_fraction": overruns / max(1, wakes),
        "late_over_100us": int(hist[101:].sum()),
        "steal_ms": _delta(s0, s1),
    }


def cpu_gaps(seconds: float) -> dict:
    """The CPU-gap detector for ``seconds`` of spinning (half of each second spins, half sleeps).
    ``over_*``: the gaps longer than each threshold; ``miss_floor``: for each rate whose period
    is a threshold, those gaps per second over the rate: the share of its deadlines a loop that
    did nothing but wait would miss for them alone."""
    thr = np.array([t * 1000 for t in GAP_THRESHOLDS_US], dtype=np.int64)
    counts = np.zeros(len(thr), dtype=np.int64)
    reads = 0
    max_gap = 0
    s0 = steal_ms()
    left = seconds
    while left > 0:
        spin = min(GAP_SPIN_SHARE, left)
        r, g = _spin_gaps(int(spin * 1e9), thr, counts)
        reads += r
        max_gap = max(max_gap, g)
        left -= spin
        if left > 0:
            time.sleep(1.0 - GAP_SPIN_SHARE)
    out = {"seconds": seconds, "reads": int(reads)}
    out.update({_gap_key(t): int(c) for t, c in zip(GAP_THRESHOLDS_US, counts)})
    out["miss_floor"] = {f"{1e6 / t:g}": round(int(c) / seconds / (1e6 / t), 6)
                         for t, c in zip(GAP_THRESHOLDS_US, counts) if t >= 100}
    out.update(max_us=round(max_gap / 1000.0, 1), steal_ms=_delta(s0, steal_ms()))
    return out


def _gap_key(us: int) -> str:
    return f"over_{us // 1000}ms" if us % 1000 == 0 else f"over_{us}us"


def run(rates: list[float], seconds: float, latencies: list[int | None], spin_us="auto", gap_seconds: float = 0.0,
        rounds: int = 1) -> dict:
    """Every (rate, latency) pair ``rounds`` times, the latency settings alternating within a rate;
    then the CPU-gap detector under each latency setting."""
    clock = MonotonicClock()
    spin_ns = clock.calibrate() if spin_us == "auto" else int(float(spin_us) * 1000)
    set_timer_slack_ns(1)
    try:
        saved = os.sched_getscheduler(0), os.sched_getparam(0)
    except (AttributeError, OSError):
        saved = None
    rt, why = try_realtime()
    saved_cpus = os.sched_getaffinity(0) if hasattr(os, "sched_getaffinity") else set()
    cpu = clock_cpus("auto", saved_cpus)[0]  # where the server's clock thread would tick
    if not pin_to_cpu(cpu):
        cpu = None
    _wait_deadlines(tick.new_words(1_000_000), 0, np.zeros(HIST_BINS, dtype=np.int64))  # compile first
    _spin_gaps(0, np.array(GAP_THRESHOLDS_US, dtype=np.int64), np.zeros(len(GAP_THRESHOLDS_US), dtype=np.int64))
    rows, gaps = [], []
    try:
        for _ in range(rounds):
            for rate in rates:
                for lat in latencies:
                    with _latency(lat) as q:
                        row = empty_tick(rate, seconds, spin_ns)
                    rows.append({**row, "cpu_latency_us": q.held, "rt_scheduling": rt})
        if gap_seconds > 0:
            for lat in latencies:
                with _latency(lat) as q:
                    gaps.append({**cpu_gaps(gap_seconds), "cpu_latency_us": q.held})
    finally:
        if saved is not None:
            try:
                os.sched_setscheduler(0, saved[0], saved[1])
            except OSError:
                pass
        if cpu is not None:
            os.sched_setaffinity(0, saved_cpus)
    return {"rows": rows, "gaps": gaps, "rt_scheduling": rt, "rt_refused": why or None, "cpu": cpu,
            "machine": f"{platform.machine()} {os.cpu_count()} cpus, {platform.system()} {platform.release()}"}


class _latency(HeldCpuLatency):
    """The request for one run; a refusal is said on stderr (the row then says None)."""

    def __enter__(self) -> HeldCpuLatency:
        super().__enter__()
        if self.why:
            print(f"hapticproxy bench floor: idle CPUs' wake-up latency not held: {self.why}", file=sys.stderr)
        return self


def _us(v) -> str:
    return "-" if v is None else f"{v:g}"


def print_report(res: dict) -> None:
    print(f"empty tick (the loop's wait, nothing done at the deadline), real-time scheduling "
          f"{'yes' if res['rt_scheduling'] else 'no: ' + str(res['rt_refused'])}, "
          f"{'not pinned' if res['cpu'] is None else 'on CPU ' + str(res['cpu'])}; {res['machine']}")
    print(f"{'rate':>8} {'idle CPUs':>14} {'spin':>6} {'s':>5} {'wakes':>9} {'skipped':>8} "
          f"{'lateness p50/p99/p99.9/max us':>31} {'missed':>9} {'>100us':>7} {'steal':>8}")
    for r in res["rows"]:
        lat = r["lateness_us"]
        idle = "OS" if r["cpu_latency_us"] is None else f"wake <= {r['cpu_latency_us']} us"
        print(f"{r['rate_hz']:>6g} Hz {idle:>14} {r['spin_us']:>6g} {r['seconds']:>5g} {r['wakes']:>9} "
              f"{r['skipped']:>8} {'/'.join(_us(lat[k]) for k in ('p50', 'p99', 'p999', 'max')):>31} "
              f"{100 * r['missed_fraction']:>8.3f}% {r['late_over_100us']:>7} "
              f"{'-' if r['steal_ms'] is None else format(r['steal_ms'], 'g') + ' ms':>8}")
    for g in res["gaps"]:
        idle = "OS" if g["cpu_latency_us"] is None else f"wake <= {g['cpu_latency_us']} us"
        floor = ", ".join(f"{float(r) / 1000:g} kHz {100 * v:.4f} %" for r, v in g["miss_floor"].items())
        print(f"CPU gaps ({idle}, {g['seconds']:g} s spinning, {g['reads']} reads): over 10 us {g['over_10us']}, "
              f"over 100 us {g['over_100us']}, over 250 us {g['over_250us']}, over 1 ms {g['over_1ms']}, max "
              f"{g['max_us']:g} us; steal {'-' if g['steal_ms'] is None else format(g['steal_ms'], 'g') + ' ms'}")
        print(f"  deadlines missed for these gaps alone: {floor}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="hapticproxy bench floor", description=doc_summary(__doc__))
    ap.add_argument("--json", action="store_true", help="print one JSON object (default: a table)")
    ap.add_argument("--rates", default="10000,4000,1000", help="comma-separated rates [Hz] (default %(default)s)")
    ap.add_argument("--seconds", type=float, default=10.0, help="seconds per run (default %(default)s)")
    ap.add_argument("--rounds", type=int, default=1, help="runs of every rate and setting (default %(default)s)")
    ap.add_argument("--cpu-latency", choices=("both", "0", "off"), default="both",
                    help="the idle CPUs' wake-up latency: held at 0 us, left to the OS (off), or both alternately "
                         "(default)")
    ap.add_argument("--spin-us", default="auto", metavar="US",
                    help="the spin before each deadline, us (auto: the daemon's calibration; capped at 60 %% of "
                         "the period)")
    ap.add_argument("--gap-seconds", type=float, default=5.0,
                    help="seconds of the CPU-gap detector per latency setting (0: skip it; default %(default)s)")
    args = ap.parse_args(argv)
    try:
        rates = [float(x) for x in args.rates.split(",") if x.strip()]
        spin = args.spin_us if args.spin_us == "auto" else float(args.spin_us)
    except ValueError:
        rates, spin = [], -1.0
    if (not rates or any(not 100 <= r <= 20000 for r in rates) or not args.seconds > 0 or args.rounds < 1
            or args.gap_seconds < 0 or (spin != "auto" and not 0 <= spin <= 5000)):
        print("hapticproxy bench floor: --rates in [100, 20000] Hz, --seconds > 0, --rounds >= 1, --gap-seconds >= 0, "
              "--spin-us auto or in [0, 5000]", file=sys.stderr)
        return 2
    latencies = {"both": [0, None], "0": [0], "off": [None]}[args.cpu_latency]
    res = run(rates, args.seconds, latencies, spin, args.gap_seconds, args.rounds)
    if args.json:
        print_json(res, indent=1)
    else:
        print_report(res)
    return 0


if __name__ == "__main__":
    sys.exit(main())
