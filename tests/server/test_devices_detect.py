"""``hapticproxy devices`` against the emulators (two Force Dimension devices, a Touch, a fake
Inverse Service), and a config picking one of several devices by serial."""
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

from hapticproxy.server.devices import models  # noqa: E402
from hapticproxy.testing.emulators import build, inverse_service  # noqa: E402
from hapticproxy.testing.emulators.block import Block  # noqa: E402
from hapticproxy.testing.emulators.harness import attach_fd_blocks, sdk_root  # noqa: E402
from hapticproxy.testing.emulators.physics import Physics  # noqa: E402

EXE = str(Path(sys.executable).parent / "hapticproxy")


def _fd_block(path, system_type, serial):
    b = Block(path, create=True)
    Physics(b, models.FORCEDIMENSION[system_type], model_id=system_type, serial=serial)
    return b


def test_the_command_lists_what_is_connected_and_what_finds_nothing(tmp_path):
    a = _fd_block(tmp_path / "a.blk", 33, 101)
    s = _fd_block(tmp_path / "s.blk", 104, 202)
    t = Block(tmp_path / "t.blk", create=True)
    Physics(t, models.TOUCH["Touch"], model_id=0, serial=303)
    i = Block(tmp_path / "i.blk", create=True)
    Physics(i, models.INVERSE3, model_id=0, serial=1, initial_pose=[0.0, -0.1, 0.1, 0, 0, 0])
    hd = build.build_libhd(tmp_path / "hd")
    proc, url = inverse_service.spawn(i.path, str(tmp_path))
    env = dict(os.environ, FDSDK=str(sdk_root()), HAPTICPROXY_EMU_BLOCKS=f"{a.path}:{s.path}",
               LD_LIBRARY_PATH=str(hd.parent), HAPTICPROXY_EMU_HD_DEVICES=f"Default Device={t.path}")
    try:
        out = subprocess.run([EXE, "devices", "--json", "--service", url], env=env, capture_output=True, text=True,
                             timeout=300)
        text = subprocess.run([EXE, "devices", "--service", url], env=env, capture_output=True, text=True,
                              timeout=300).stdout
    finally:
        i["stop"] = 1.0
        proc.wait(timeout=10)
    assert out.returncode == 0, out.stderr
    rows = json.loads(out.stdout)
    got = {(r["driver"], r.get("model"), r.get("serial")) for r in rows if r["status"] == "connected"}
    assert got == {("forcedimension", "omega.3", "101"), ("forcedimension", "sigma.7", "202"),
                   ("touch", "Touch", "303"), ("haply", "Inverse3", "049D")}
    assert 'serial = 202' in text and 'device_name = "Default Device"' in text
    # each device was closed again: nothing holds it
    assert a["owner_pid"] == 0.0 and s["owner_pid"] == 0.0 and t["owner_pid"] == 0.0


def test_nothing_connected_is_said_per_driver(tmp_path):
    env = dict(os.environ, FDSDK=str(sdk_root()), HAPTICPROXY_EMU_BLOCKS="", HAPTICPROXY_EMU_HD_DEVICES="",
               LD_LIBRARY_PATH=str(build.build_libhd(tmp_path / "hd").parent))
    out = subprocess.run([EXE, "devices", "--json", "--service", "ws://127.0.0.1:9"], env=env, capture_output=True,
                         text=True, timeout=300)
    rows = {r["driver"]: r["status"] for r in json.loads(out.stdout)}
    assert rows == {"forcedimension": "installed, nothing connected", "haply": "installed, nothing connected",
                    "touch": "installed, nothing connected"}


def test_a_config_picks_a_device_by_serial(tmp_path):
    from hapticproxy.server.devices.forcedimension import make_forcedimension_device

    a = _fd_block(tmp_path / "a.blk", 33, 101)
    b = _fd_block(tmp_path / "b.blk", 33, 202)
    attach_fd_blocks([a.path, b.path])
    d = make_forcedimension_device({"serial": 202}, period_s=1e-3)
    try:
        assert d.info.serial == "202" and b["owner_pid"] == os.getpid() and a["owner_pid"] == 0.0
        d2 = make_forcedimension_device({}, period_s=1e-3)   # the next free one
        try:
            assert d2.info.serial == "101"
        finally:
            d2.close()
    finally:
        d.close()
