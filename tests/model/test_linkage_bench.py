"""``hapticproxy bench model`` has rows for 3- and 6-joint linkages at 8 and 32 contacts."""
import json
import subprocess
import sys


def test_bench_model_prints_linkage_rows():
    out = subprocess.run([sys.executable, "-m", "hapticproxy.cli.main", "bench", "model", "--json", "--steps", "300",
                          "--numpy-steps", "3", "--tools", "linkage3,linkage6"],
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    rows = json.loads(out.stdout)
    assert [(r["tool"], r["contacts"]) for r in rows] == [("linkage3", 8), ("linkage3", 32), ("linkage6", 8),
                                                          ("linkage6", 32)]
    for r in rows:
        for key in ("numba_median_us", "numba_p99_us", "numpy_median_us", "speedup"):
            assert isinstance(r[key], float) and r[key] > 0
        assert r["nonfinite"] == 0
        assert r["collision_steps"] > 0 and r["resting_steps"] > 0
