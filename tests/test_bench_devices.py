"""``hapticproxy bench devices``: its rows (counts only: its timings are printed, never asserted),
every fault row with 0 violations, and a driver that breaks a promise shows up as violations."""
from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

for _m in ("forcedimension_core", "pyOpenHaptics", "HaplyHardwareAPI", "websockets"):
    if importlib.util.find_spec(_m) is None:
        pytest.skip(f"{_m} is not installed (the devices extra)", allow_module_level=True)

from hapticproxy.benchmarks import bench_devices as bd  # noqa: E402
from hapticproxy.server.devices.base import DEV_OK  # noqa: E402

EXE = str(Path(sys.executable).parent / "hapticproxy")


def test_every_fault_row_has_no_violation():
    out = subprocess.run([EXE, "bench", "devices", "--json", "--drivers", "forcedimension,touch,haply-service",
                          "--steps", "200", "--seconds", "0.3"], capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    rows = [json.loads(line) for line in out.stdout.splitlines()][1:]
    faults = [r for r in rows if r["kind"] == "fault"]
    assert {(r["driver"], r["fault"]) for r in faults} >= {
        ("forcedimension", "unplugged"), ("forcedimension", "device error"), ("forcedimension", "frozen position"),
        ("forcedimension", "different model"), ("touch", "late servo ticks"), ("haply-service", "unplugged")}
    assert all(r["violations"] == 0 for r in faults), [r for r in faults if r["violations"]]
    seen = {(r["driver"], r["fault"]): r for r in faults}
    assert seen[("touch", "unplugged")]["named"] == ["device link lost"]
    assert seen[("forcedimension", "device error")]["named"] == ["hardware fault"]
    for d in ("forcedimension", "touch", "haply-service"):  # seen by the frozen-position watch, named
        assert seen[(d, "frozen position")]["named"] == ["position frozen"], seen[(d, "frozen position")]
    rates = {(r["driver"], r["target_hz"]): r for r in rows if r["kind"] == "rate"}
    assert {("forcedimension", 1000.0), ("forcedimension", 4000.0), ("touch", 1000.0)} <= set(rates)
    assert rates[("touch", 1000.0)]["clock"] == "device" and rates[("touch", 1000.0)]["periods"] > 10
    # the servo rows, side by side, with the idle CPUs' wake-up latency held as the daemon holds it
    servo = [r for r in rows if r["kind"] == "servo"]
    assert {(r["callback"], r["target_hz"]) for r in servo} == {
        (c, hz) for c in ("python callback", "compiled tick") for hz in (1000.0, 4000.0)}
    held = 0 if os.access("/dev/cpu_dma_latency", os.W_OK) else None
    assert all(r["cpu_latency_us"] == held and r["periods"] > 10 for r in servo), servo


def test_a_driver_that_ignores_the_device_error_is_caught(monkeypatch):
    from hapticproxy.server.devices import touch

    real = touch.TouchDevice._io_read

    def ignores(self, row):
        real(self, row)
        return DEV_OK

    monkeypatch.setattr(touch.TouchDevice, "_io_read", ignores)
    row = bd.fault_row("touch", "unplugged")
    assert row["violations"] > 0 and "named" in row["broken"]
