"""`hapticproxy bench transport --json`: the rows carry the documented keys (no timing asserts)."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

EXE = str(Path(sys.executable).parent / "hapticproxy")


def test_bench_transport_json_rows():
    out = subprocess.run(
        [EXE, "bench", "transport", "--json", "--exchanges", "40", "--warmup", "10", "--transports", "udp,zenoh"],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert out.returncode == 0, out.stderr
    rows = json.loads(out.stdout)
    assert [(r["transport"], r["paced"]) for r in rows] == [
        ("udp", True),
        ("udp", False),
        ("zenoh", True),
        ("zenoh", False),
    ]
    for r in rows:
        assert r["exchanges"] == 40 and r["warmup"] == 10
        assert r["update_bytes"] == 1300 and r["ack_bytes"] == 200
        assert r["lost"] == 0
        rtt = r["rtt_us"]
        assert 0 < rtt["p50"] <= rtt["p99"] <= rtt["max"]
        assert (r["rate_hz"] == 1000.0) == r["paced"]
        assert r["poll"]["io_threads"] in ("other", "same", "float")
    assert all(r["zenoh_runtime"] for r in rows if r["transport"] == "zenoh")


def test_bench_transport_rejects_unknown_transport():
    out = subprocess.run([EXE, "bench", "transport", "--transports", "carrier-pigeon"], capture_output=True, text=True, timeout=60)
    assert out.returncode == 2 and "carrier-pigeon" in out.stderr


def test_zenoh_floor_json_rows():
    out = subprocess.run(
        [sys.executable, "-m", "hapticproxy.benchmarks.zenoh_floor", "--json", "--exchanges", "30", "--warmup", "5",
         "--variants", "raw-udp,raw-tcp,zenoh-poll,zenoh-poll-lowlatency", "--io-threads", "other"],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert out.returncode == 0, out.stderr
    rows = json.loads(out.stdout)
    assert [r["variant"] for r in rows] == ["raw-udp", "raw-tcp", "zenoh-poll", "zenoh-poll-lowlatency"]
    for r in rows:
        assert r["exchanges"] == 30
        assert 0 < r["rtt_us"]["p50"] <= r["rtt_us"]["p99"] <= r["rtt_us"]["max"]
        assert (r["zenoh_runtime"] is None) == r["variant"].startswith("raw")
