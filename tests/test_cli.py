"""The command-line entry point and its first subcommands."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

EXE = str(Path(sys.executable).parent / "hapticproxy")


def run(*args, cwd=None, timeout=600):
    return subprocess.run([EXE, *args], capture_output=True, text=True, cwd=cwd, timeout=timeout)


def test_help_lists_subcommands():
    out = run("--help")
    assert out.returncode == 0
    for name in ("demo", "bench", "protocol"):
        assert name in out.stdout


def test_unknown_command_and_bench_target_fail_cleanly():
    out = run("frobnicate")
    assert out.returncode == 2 and "unknown command" in out.stderr and "Traceback" not in out.stderr
    out = run("bench", "nosuch")
    assert out.returncode == 2 and "Traceback" not in out.stderr


def test_demo_runs_server_and_pymunk_client_and_feels_the_wall(tmp_path):
    import re

    out = run("demo", "--out", str(tmp_path / "demo"), "--seconds", "4")
    assert out.returncode == 0, out.stderr
    lines = [ln for ln in out.stdout.splitlines() if ln.strip()]
    assert len(lines) == 1, out.stdout
    line = lines[0]
    felt, real = map(float, re.search(r"wall felt at y_COM ([-\d.]+) mm, it is at ([-\d.]+) mm", line).groups())
    assert real == 124.0
    assert abs(felt - real) < 3.0  # epsilon-active geometry: the wall is felt where it is
    force = float(re.search(r"final force ([-+\d.]+) N", line).group(1))
    assert abs(force + 0.5) < 0.05  # balances the 0.5 N push
    assert "settled" in line and "NOT settled" not in line and "faults 0" in line
    haptic = float(re.search(r"haptic ([\d.]+) Hz", line).group(1))
    assert haptic > 0.5 * 512  # loose: a shared CI machine may skip deadlines; the counts are the point
    assert int(re.search(r"\((\d+) updates\)", line).group(1)) > 30
    png = tmp_path / "demo" / "static_contact.png"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    from hapticproxy.server.telemetry import read

    meta, rows = read(tmp_path / "demo" / "static_contact.mcap")
    assert len(rows) > 512


def test_bench_model_prints_rows_with_the_documented_keys():
    out = run("bench", "model", "--json", "--steps", "300", "--numpy-steps", "5", "--tools", "planar,spatial",
              "--contacts", "0,8")
    assert out.returncode == 0, out.stderr
    rows = json.loads(out.stdout)
    assert [(r["tool"], r["contacts"]) for r in rows] == [("planar", 0), ("planar", 8), ("spatial", 0), ("spatial", 8)]
    for r in rows:
        for key in ("numba_median_us", "numba_p99_us", "numpy_median_us", "speedup"):
            assert isinstance(r[key], float) and r[key] > 0
        # (the medians are printed rounded to 3 decimals: at a 700x speed-up that rounding alone
        # moves the ratio by 0.15, so the check is relative)
        ratio = r["numpy_median_us"] / r["numba_median_us"]
        assert abs(r["speedup"] - ratio) <= max(0.1, 1e-3 * ratio)
        assert r["nonfinite"] == 0
    assert rows[1]["collision_steps"] > 0 and rows[1]["resting_steps"] > 0
    assert "warm start" in out.stderr


def test_bench_model_rejects_bad_arguments():
    out = run("bench", "model", "--tools", "hexapod")
    assert out.returncode == 2 and "Traceback" not in out.stderr
