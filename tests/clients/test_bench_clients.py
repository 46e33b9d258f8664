"""`python -m hapticproxy.benchmarks.bench_clients --json` (the `hapticproxy bench clients` target):
rows carry the documented keys (no timing asserts)."""
from __future__ import annotations

import json
import subprocess
import sys


def test_bench_clients_json_rows():
    out = subprocess.run(
        [sys.executable, "-m", "hapticproxy.benchmarks.bench_clients", "--json", "--engines", "stub,pymunk",
         "--scenes", "testbed,wall", "--ticks", "40", "--warmup", "5", "--repeat", "2", "--seconds", "0.3"],
        capture_output=True, text=True, timeout=300,
    )
    assert out.returncode == 0, out.stderr
    rows = json.loads(out.stdout)
    assert [(r["engine"], r["scene"]) for r in rows] == [
        ("stub", "testbed"), ("stub", "wall"), ("pymunk", "testbed"), ("pymunk", "wall")]
    for r in rows:
        assert r["ticks"] == 80 and len(r["tick_p99_blocks_us"]) == 2
        for key in ("tick_median_us", "tick_p99_us", "tick_cpu_p99_us", "sustained_hz", "sent_hz"):
            assert isinstance(r[key], float) and r[key] > 0, key
        assert r["tick_p99_us"] >= r["tick_median_us"] * 0.5
        assert r["sustained_hz"] <= r["sent_hz"]  # acknowledged never exceeds sent
        assert 0 <= r["contacts_mean"] <= r["contacts_max"] <= 16


def test_bench_clients_refuses_an_unknown_engine():
    out = subprocess.run([sys.executable, "-m", "hapticproxy.benchmarks.bench_clients", "--engines", "ode"],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 2 and "not available" in out.stderr and "Traceback" not in out.stderr
