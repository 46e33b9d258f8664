"""`hapticproxy bench floor`: the loop's wait with nothing to do, counted (no timing asserted)."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import time

import numpy as np
import pytest

from hapticproxy.benchmarks import bench_floor as bfl
from hapticproxy.server import tick
from hapticproxy.server.shm import percentiles


def test_every_period_is_a_wake_or_a_skip():
    """A deadline 10 periods in the past: the first wake skips them, and every period until the
    end is either woken for or counted as skipped."""
    period = 1_000_000
    bfl._wait_deadlines(tick.new_words(period), 0, np.zeros(8, dtype=np.int64))  # compiled before the clock starts
    tk = tick.new_words(period)
    tk[tick.TK_SPIN_NS] = 100_000
    start = time.monotonic_ns() - 10 * period
    tk[tick.TK_DEADLINE_NS] = start
    hist = np.zeros(bfl.HIST_BINS, dtype=np.int64)
    wakes, overruns, max_late = bfl._wait_deadlines(tk, 30, hist)
    periods = (tk[tick.TK_DEADLINE_NS] - start) // period
    assert periods >= 30 and wakes + tk[tick.TK_MISSED] == periods
    assert tk[tick.TK_MISSED] >= 10 and 1 <= overruns <= wakes and hist.sum() == wakes
    assert max_late >= 10 * period and hist[10_000:].sum() >= 1  # the first wake, 10 ms late or more
    assert percentiles(hist, (1.0,))["p100"] >= 10_000


def test_the_last_bin_holds_everything_beyond_and_reads_as_its_upper_edge():
    """The floor's histogram is longer than the status's: its percentiles reach its own last bin."""
    h = np.zeros(bfl.HIST_BINS, dtype=np.int64)
    h[-1] = 5
    assert percentiles(h)["p50"] == float(bfl.HIST_BINS)
    assert percentiles(np.array([0, 3, 0, 1]))["p50"] == 2.0 and percentiles(np.array([0, 3, 0, 1]))["p999"] == 4.0


def test_the_gap_detector_counts_nested_thresholds():
    """A longer threshold counts no more gaps than a shorter one; one beyond the longest gap, none."""
    thr = np.array([0, 1, 100_000, 10**12], dtype=np.int64)
    counts = np.zeros(4, dtype=np.int64)
    reads, max_gap = bfl._spin_gaps(20_000_000, thr, counts)
    assert reads > 1000 and max_gap > 0
    assert reads >= counts[0] >= counts[1] >= counts[2] and counts[0] > 0  # the clock moves between reads
    assert counts[3] == 0 and (counts[2] > 0) == (max_gap > 100_000)


def _floor_json(*extra: str) -> dict:
    out = subprocess.run([sys.executable, "-m", "hapticproxy.cli.main", "bench", "floor", "--json", *extra],
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout)


def test_bench_floor_prints_the_documented_keys():
    d = _floor_json("--rates", "2000,1000", "--seconds", "0.1", "--gap-seconds", "0.1", "--spin-us", "200")
    held = 0 if os.access("/dev/cpu_dma_latency", os.W_OK) else None  # without the QoS device nothing is held
    assert [(r["rate_hz"], r["cpu_latency_us"]) for r in d["rows"]] == [
        (2000.0, held), (2000.0, None), (1000.0, held), (1000.0, None)]
    for r in d["rows"]:
        assert r["spin_us"] == 200.0  # the spin it was given, under the 60 % cap at both rates
        assert r["wakes"] + r["skipped"] == r["periods"] >= round(0.1 * r["rate_hz"])
        lat = r["lateness_us"]
        assert lat["p50"] <= lat["p99"] <= lat["p999"] <= lat["max"] + 1
        assert 0.0 <= r["missed_fraction"] <= 1.0 and isinstance(r["rt_scheduling"], bool)
    assert len(d["gaps"]) == 2
    for g in d["gaps"]:
        assert g["reads"] > 0 and g["over_10us"] >= g["over_100us"] >= g["over_250us"] >= g["over_1ms"]
        assert g["miss_floor"] == {"10000": round(g["over_100us"] / 0.1 / 10000, 6),
                                   "4000": round(g["over_250us"] / 0.1 / 4000, 6),
                                   "1000": round(g["over_1ms"] / 0.1 / 1000, 6)}
    assert "machine" in d
    if len(os.sched_getaffinity(0)) >= 2:
        assert d["cpu"] == max(os.sched_getaffinity(0))  # where the server's clock thread ticks


def test_bench_floor_prints_a_table_for_a_person():
    out = subprocess.run([sys.executable, "-m", "hapticproxy.cli.main", "bench", "floor", "--rates", "1000",
                          "--seconds", "0.05", "--gap-seconds", "0", "--cpu-latency", "off"],
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    lines = out.stdout.splitlines()
    assert lines[0].startswith("empty tick") and "missed" in lines[1]
    assert len(lines) == 3 and lines[2].split()[:3] == ["1000", "Hz", "OS"]


@pytest.mark.parametrize("bad", [["--rates", "50"], ["--rates", "x"], ["--seconds", "0"], ["--rounds", "0"],
                                 ["--gap-seconds", "-1"], ["--spin-us", "9000"], ["--cpu-latency", "5"]])
def test_bench_floor_rejects_bad_arguments(bad):
    out = subprocess.run([sys.executable, "-m", "hapticproxy.cli.main", "bench", "floor", *bad],
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 2 and "Traceback" not in out.stderr
    assert out.stderr.startswith("hapticproxy bench floor:") or "invalid choice" in out.stderr  # argparse's own
