"""Without a vendor's package or SDK the server still starts its other drivers, and asking for a
vendor driver says in one line what is missing, how to install it and what to set."""
from __future__ import annotations

import importlib.util
import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from hapticproxy.server.devices.base import load_device
from hapticproxy.server.devices.vendor import DeviceUnavailable

ROOT = Path(__file__).resolve().parents[2]
EXE = str(Path(sys.executable).parent / "hapticproxy")


@pytest.mark.parametrize("driver,module,config,match", [
    ("forcedimension", "forcedimension_core", {}, r"needs the Python package forcedimension-core.*"
                                                  r"pip install 'hapticproxy\[devices\]'.*set FDSDK"),
    ("haply", "HaplyHardwareAPI", {"port": "/dev/ttyACM0"}, r"needs the Python package haplyhardwareapi"),
    ("haply", "websockets", {"transport": "service"}, r"needs the Python package websockets"),
    ("touch", "pyOpenHaptics", {}, r"needs the Python package pyopenhaptics.*OpenHaptics"),
])
def test_a_missing_package_is_one_line_with_the_fix(monkeypatch, driver, module, config, match):
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == module else real(name, *a))
    with pytest.raises(DeviceUnavailable, match=match) as ei:
        load_device(driver, {"kind": "spatial", **config}, period_s=1e-3)
    assert str(ei.value).startswith("device.") and "\n" not in str(ei.value)


def _port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_serve_names_the_missing_sdk_and_exits_2(tmp_path):
    cfg = tmp_path / "fd.toml"
    cfg.write_text((ROOT / "deploy" / "configs" / "forcedimension.toml").read_text()
                   .replace("udp://127.0.0.1:9870", f"udp://127.0.0.1:{_port()}")
                   .replace('address = "127.0.0.1:9871"', f'address = "127.0.0.1:{_port()}"'))
    env = {k: v for k, v in os.environ.items() if k not in ("FDSDK", "FORCEDIM_SDK")}
    env["HOME"] = str(tmp_path)
    out = subprocess.run([EXE, "serve", "--config", str(cfg)], env=env, capture_output=True, text=True, timeout=600)
    assert out.returncode == 2, out.stderr
    last = out.stderr.strip().splitlines()[-1]
    assert "device.driver: forcedimension:" in last and "FDSDK is not set" in last, out.stderr
