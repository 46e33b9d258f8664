"""The ``touch`` driver on the unmodified pyopenhaptics package over the fake libHD.so: the
scheduler's servo callback and the loop meet in the driver's mailbox. Lock-step (the test runs
each servo tick) except where the fake's own 1 kHz servo thread is the point."""
from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
import time

import numpy as np
import pytest

if importlib.util.find_spec("pyOpenHaptics") is None:
    pytest.skip("pyopenhaptics is not installed (the devices extra)", allow_module_level=True)

from hapticproxy.server.devices.base import (  # noqa: E402
    DEV_NSTATE,
    DEV_FAULT_HARDWARE, DEV_FAULT_LINK, DEV_FAULT_WATCHDOG, DEV_OK,
)
from hapticproxy.server.devices.touch import C_ARMED, S_TICK, make_touch_device  # noqa: E402
from hapticproxy.server.devices.vendor import DeviceUnavailable  # noqa: E402
from hapticproxy.testing.emulators.harness import TouchHarness, attach_hd_devices  # noqa: E402

PUSH = np.array([0.0, 0.0, -1.0, 0.0, 0.0, 0.0])


@pytest.fixture
def touch():
    h = TouchHarness()
    yield h
    h.close()


def _go(h, w=PUSH, steps=5):
    h.driver.enable()
    st = None
    for _ in range(steps):
        st = h.step(w)
    return st


def test_it_senses_six_renders_three_and_the_device_owns_the_clock(touch):
    info = touch.driver.info
    assert (info.model, info.vendor, info.serial) == ("Touch", "3D Systems", "22011")
    assert (info.dof_sensed, info.dof_actuated, info.clock, info.native_rate_hz) == (6, 3, "device", 1000.0)
    assert info.max_stiffness_n_per_m == pytest.approx(400.0) and info.sdk_units == "mm, N"
    assert touch.driver.limits.max_torque_n_m == 0.0
    assert touch.driver.native.handle == 0 and hasattr(touch.driver.native.lib, "hdScheduleAsynchronous")


def test_millimetres_become_metres_and_forces_reach_the_device(touch):
    assert _go(touch, steps=40) == (DEV_OK, DEV_OK)
    r = touch.row
    assert r[2] < 0.05 and r[9] < 0.0          # starts at z = 50 mm, pushed down
    assert 0.03 < r[2]                         # metres, not millimetres
    assert touch.rendered()[2] == pytest.approx(-1.0)
    assert abs(float(r[3:7] @ r[3:7]) - 1.0) < 1e-9


def test_torque_is_never_sent(touch):
    _go(touch, np.array([0.0, 0.0, 0.0, 0.1, 0.1, 0.1]))
    assert not np.any(touch.rendered())


def test_the_servo_side_watchdog_cuts_during_a_stall_and_enable_rearms(touch):
    _go(touch)
    for _ in range(12):                        # 12 ms without a command (watchdog 10 ms)
        touch.tick()
    assert not np.any(touch.rendered())
    rs, _ = touch.step(PUSH)
    assert rs == DEV_FAULT_WATCHDOG
    touch.driver.enable()
    for _ in range(3):
        assert touch.step(PUSH) == (DEV_OK, DEV_OK)
    assert touch.rendered()[2] == pytest.approx(-1.0)


def test_unplugged_and_device_fault_latch(touch):
    _go(touch)
    touch.block["fault_unplugged"] = 1.0
    rs, _ = touch.step(PUSH)
    assert rs == DEV_FAULT_LINK
    touch.block["fault_unplugged"] = 0.0
    for _ in range(5):
        touch.step(PUSH)
        assert touch.driver.command[C_ARMED] == 0.0 and not np.any(touch.rendered())
    touch.driver.enable()
    for _ in range(3):
        touch.step(PUSH)
    assert touch.driver.fault == DEV_OK and touch.rendered()[2] == pytest.approx(-1.0)
    touch.block["fault_error"] = 1.0
    rs, _ = touch.step(PUSH)
    assert rs == DEV_FAULT_HARDWARE
    assert not np.any(touch.rendered())


def test_a_servo_thread_that_stops_ticking_is_a_lost_device(touch):
    _go(touch)
    for _ in range(25):                        # the loop runs on, the servo thread does not
        touch.clock.advance(1e-3)
        rs = touch.driver.read(touch.row)
        touch.driver.write(PUSH)
    assert rs == DEV_FAULT_LINK


@pytest.mark.parametrize("kw,match", [
    (dict(config={"model": "PHANTOM Omni"}), "the config is for a PHANTOM Omni, the device 'Default Device' is a Touch"),
    (dict(config={"device_name": "Left"}), "no device configured as 'Left'"),
    (dict(calibrated=False), "needs calibration: set calibrate = true"),
    (dict(config={"serial": "1"}), "has serial 22011, the config asks for 1"),
])
def test_refusals_name_the_fix(kw, match):
    with pytest.raises(DeviceUnavailable, match=match) as ei:
        TouchHarness(**kw)
    assert "\n" not in str(ei.value)


def test_calibration_when_asked():
    h = TouchHarness(calibrated=False, config={"calibrate": True})
    try:
        assert h.driver.info.calibration == "done"
    finally:
        h.close()


def test_the_real_servo_thread_drives_the_python_callback(tmp_path):
    """Not lock-step: the fake's pthread ticks at 1 kHz on absolute deadlines and calls the
    driver's callback; the loop reads what it wrote. Counts only (the machine is shared)."""
    from hapticproxy.server.devices import models
    from hapticproxy.testing.emulators.block import Block
    from hapticproxy.testing.emulators.physics import Physics

    blk = Block(tmp_path / "d.blk", create=True)
    Physics(blk, models.TOUCH["Touch"], model_id=0, serial=5, initial_pose=[0.0, 0.0, 0.05, 0, 0, 0])
    attach_hd_devices({"Default Device": blk.path}, lockstep=False)
    d = make_touch_device({}, period_s=1e-3)
    try:
        row = np.zeros(DEV_NSTATE)
        t0 = d.state[S_TICK]
        time.sleep(0.3)
        assert d.state[S_TICK] - t0 > 10     # the servo thread ran the callback many times
        assert d.read(row) != DEV_FAULT_LINK and row[2] == pytest.approx(0.05)
        assert blk["servo_ticks"] >= d.state[S_TICK] - t0
    finally:
        d.close()
        blk.close()


def test_without_libhd_the_driver_says_what_to_install(tmp_path):
    code = ("from hapticproxy.server.devices.touch import make_touch_device as m\n"
            "try:\n    m({}, period_s=1e-3)\nexcept ValueError as e:\n    print(e)\n")
    env = {k: v for k, v in os.environ.items() if k != "LD_LIBRARY_PATH"}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    line = out.stdout.strip().splitlines()[-1]
    assert line.startswith("device.driver: touch: pyopenhaptics could not load libHD.so") and "LD_LIBRARY_PATH" in line


def test_late_servo_ticks_from_the_fake_thread_are_a_lost_device(tmp_path):
    """The fake's servo thread oversleeps 40 ms a tick (fault_late_ms): the loop's reads find no
    new sample for stale_s and latch a lost link; on time again, enable() re-arms."""
    from hapticproxy.server.devices import models
    from hapticproxy.testing.emulators.block import Block
    from hapticproxy.testing.emulators.physics import Physics

    blk = Block(tmp_path / "d.blk", create=True)
    Physics(blk, models.TOUCH["Touch"], model_id=0, serial=5, initial_pose=[0.0, 0.0, 0.05, 0, 0, 0])
    attach_hd_devices({"Default Device": blk.path}, lockstep=False)
    d = make_touch_device({"stale_s": 0.02}, period_s=1e-3)
    try:
        row = np.zeros(DEV_NSTATE)
        d.enable()
        blk["fault_late_ms"] = 40.0
        codes = set()
        end = time.monotonic() + 30.0
        while (DEV_FAULT_LINK not in codes or blk["servo_late"] == 0) and time.monotonic() < end:
            codes.add(d.read(row))
            d.write(PUSH)
            time.sleep(0.001)
        assert DEV_FAULT_LINK in codes and blk["servo_late"] > 0
        blk["fault_late_ms"] = 0.0
        while time.monotonic() < end:
            d.enable()
            if d.fault == DEV_OK:
                break
            time.sleep(0.01)
        assert d.fault == DEV_OK
    finally:
        d.close()
        blk.close()
