"""The ``forcedimension`` driver on the unmodified forcedimension-core package, over the fake
libdrd (testing/emulators/libdrd_emu.c) with a simulated omega / sigma / Falcon behind it, in
lock-step on simulated time."""
from __future__ import annotations

import importlib.util
import math
import os
import subprocess
import sys

import numpy as np
import pytest

if importlib.util.find_spec("forcedimension_core") is None:  # (importing it loads libdrd: not here)
    pytest.skip("forcedimension-core is not installed (the devices extra)", allow_module_level=True)

from hapticproxy.server.devices.base import (  # noqa: E402
    DEV_FAULT_HARDWARE, DEV_FAULT_LINK, DEV_FAULT_WATCHDOG, DEV_OK, DeviceInfo,
)
from hapticproxy.server.devices.vendor import DeviceUnavailable  # noqa: E402
from hapticproxy.testing.emulators.harness import ForceDimensionHarness, sdk_root  # noqa: E402


@pytest.fixture
def omega():
    h = ForceDimensionHarness()
    yield h
    h.close()


def _run(h, wrench, steps=5):
    w = np.asarray(wrench, dtype=float)
    st = None
    for _ in range(steps):
        st = h.step(w)
    return st


def test_the_device_says_what_it_is(omega):
    info = omega.driver.info
    assert isinstance(info, DeviceInfo)
    assert (info.model, info.vendor, info.serial) == ("omega.3", "Force Dimension", "4242")
    assert (info.dof_sensed, info.dof_actuated, info.clock, info.calibration) == (3, 3, "loop", "done")
    assert info.max_force_n == 12.0 and info.native_rate_hz == 1000.0
    lim = omega.driver.limits
    assert lim.max_force_n == 12.0 and lim.max_force_norm_n == 12.0 and lim.max_torque_n_m == 0.0
    # the firmware watchdog the driver set through the SDK (expert mode), 160 x 125 us
    assert omega.block["watchdog_s"] == pytest.approx(0.02) and lim.watchdog_s == pytest.approx(0.02)
    assert omega.driver.native.device_id == 0 and omega.driver.native.system_type == 33
    assert hasattr(omega.driver.native.lib, "dhdSetForceAndTorqueAndGripperForce")


def test_the_force_is_capped_on_its_norm_and_torque_is_not_sent(omega):
    omega.settle()
    omega.driver.enable()
    _run(omega, [10.0, 10.0, 10.0, 0.3, 0.0, 0.0])
    sent = omega.driver.last_command
    assert np.linalg.norm(sent[:3]) == pytest.approx(12.0)
    assert np.allclose(sent[:3] / np.linalg.norm(sent[:3]), np.ones(3) / math.sqrt(3))
    assert np.all(sent[3:] == 0.0)  # an omega.3 has no actuated wrist
    assert np.linalg.norm(omega.rendered()[:3]) == pytest.approx(12.0)


def test_the_state_follows_the_device(omega):
    """A scripted hand pushes the handle down (-z): the driver sees it move, in metres."""
    omega.physics.sim.spec.hand  # noqa: B018 - the default hand is free; push through a command instead
    omega.settle()
    omega.driver.enable()
    _run(omega, [0.0, 0.0, -1.0, 0, 0, 0], steps=50)
    r = omega.row
    assert r[2] < -1e-4 and r[9] < 0.0            # moved down, moving down
    assert np.all(np.isnan(r[13:19]))             # no force sensor
    assert r[3:7].tolist() == [1.0, 0.0, 0.0, 0.0]  # no wrist: identity


def test_unplugged_mid_contact_cuts_and_nothing_comes_back_by_itself(omega):
    omega.settle()
    omega.driver.enable()
    assert _run(omega, [3.0, 0, 0, 0, 0, 0]) == (DEV_OK, DEV_OK)
    omega.block["fault_unplugged"] = 1.0
    rs, ws = omega.step(np.array([3.0, 0, 0, 0, 0, 0]))
    assert rs == DEV_FAULT_LINK and omega.driver.fault == DEV_FAULT_LINK
    omega.tick()
    assert not np.any(omega.rendered())
    omega.driver.enable()                      # still unplugged: refused
    assert omega.driver.fault == DEV_FAULT_LINK
    omega.block["fault_unplugged"] = 0.0       # plugged back in
    for _ in range(20):
        rs, ws = omega.step(np.array([3.0, 0, 0, 0, 0, 0]))
        assert not np.any(omega.rendered()), "the force came back without enable()"
    assert ws == DEV_FAULT_LINK
    omega.driver.enable()
    _run(omega, [3.0, 0, 0, 0, 0, 0])
    assert omega.driver.fault == DEV_OK and omega.rendered()[0] == 3.0


def test_a_device_error_latches_a_hardware_fault(omega):
    omega.settle()
    omega.driver.enable()
    _run(omega, [2.0, 0, 0, 0, 0, 0])
    omega.block["fault_error"] = 12.0          # DHD_ERROR_DEVICE_NOT_READY on every call
    rs, ws = omega.step(np.array([2.0, 0, 0, 0, 0, 0]))
    assert rs == DEV_FAULT_HARDWARE and omega.driver.fault == DEV_FAULT_HARDWARE
    assert not np.any(omega.driver.last_command)


def test_the_firmware_watchdog_cuts_during_a_stall(omega):
    omega.settle()
    omega.driver.enable()
    _run(omega, [2.0, 0, 0, 0, 0, 0])
    for _ in range(19):                        # 19 ms without a command: still on
        omega.tick()
    assert omega.rendered()[0] == 2.0
    for _ in range(3):
        omega.tick()
    assert not np.any(omega.rendered()) and omega.block["force_off_cause"] == 3
    rs, _ = omega.step(np.array([2.0, 0, 0, 0, 0, 0]))
    assert rs == DEV_FAULT_WATCHDOG


def test_a_stronger_model_is_capped_at_its_own_figures():
    h = ForceDimensionHarness(system_type=104)  # sigma.7: 7 sensed, 7 actuated, 0.2 N m
    try:
        info = h.driver.info
        assert (info.model, info.dof_sensed, info.dof_actuated, info.gripper) == ("sigma.7", 7, 7, True)
        h.settle()
        h.driver.enable()
        _run(h, [0.0, 0.0, 0.0, 0.0, 0.0, 1.0])
        assert h.driver.last_command[5] == pytest.approx(0.2)
        assert abs(float(np.sum(h.row[3:7] ** 2)) - 1.0) < 1e-9
    finally:
        h.close()


def test_a_config_lower_cap_wins_a_higher_one_is_refused():
    h = ForceDimensionHarness(config={"max_force_n": 5.0})
    try:
        assert h.driver.limits.max_force_n == 5.0 and h.driver.limits.max_force_norm_n == 5.0
    finally:
        h.close()
    with pytest.raises(ValueError, match="device.max_force_n"):
        ForceDimensionHarness(config={"max_force_n": 500.0})
    with pytest.raises(DeviceUnavailable, match=r"device.max_force_n: 30 N is above the omega.3's continuous force "
                                                r"\(12 N\): at most 12"):
        ForceDimensionHarness(config={"max_force_n": 30.0})


@pytest.mark.parametrize("setup,config,match", [
    ({"system_type": 33}, {"model": "sigma.7"}, "the config is for a sigma.7, the device attached is a omega.3"),
    ({"calibrated": False}, {}, "needs calibration: set calibrate = true"),
    ({}, {"serial": 999}, "no haptic device found.*plug it in"),
    ({}, {"kind": "planar"}, "device.kind: a Force Dimension device is spatial"),
    ({}, {"watchdog_s": 0.1}, "device.watchdog_s"),
])
def test_each_refusal_is_one_line_with_the_fix(setup, config, match):
    with pytest.raises(ValueError, match=match) as ei:
        ForceDimensionHarness(config=config, **setup)
    assert "\n" not in str(ei.value)


def test_calibration_runs_only_when_the_config_asks():
    h = ForceDimensionHarness(calibrated=False, config={"calibrate": True})
    try:
        assert h.driver.info.calibration == "done" and h.block["calibrated"] == 1.0
    finally:
        h.close()


def test_a_device_another_process_holds_is_busy():
    parent = os.getppid()

    class Held(ForceDimensionHarness):
        def __init__(self):
            from hapticproxy.testing.emulators import harness as hh
            orig = hh.attach_fd_blocks

            def held(paths):
                from hapticproxy.testing.emulators.block import Block
                b = Block(paths[0])
                b["owner_pid"] = parent
                b.close()
                orig(paths)
            hh.attach_fd_blocks = held
            try:
                super().__init__()
            finally:
                hh.attach_fd_blocks = orig

    with pytest.raises(DeviceUnavailable, match="device already in use.*another program holds it"):
        Held()


def test_without_fdsdk_the_driver_names_the_variable(tmp_path):
    code = ("from hapticproxy.server.devices.forcedimension import make_forcedimension_device as m\n"
            "try:\n    m({}, period_s=1e-3)\nexcept ValueError as e:\n    print(e)\n")
    env = {k: v for k, v in os.environ.items() if k not in ("FDSDK", "FORCEDIM_SDK")}
    env["HOME"] = str(tmp_path)
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    line = out.stdout.strip().splitlines()[-1]
    assert line.startswith("device.driver: forcedimension:") and "FDSDK is not set" in line, out


def test_the_fake_sdk_is_what_fdsdk_names():
    assert os.environ["FDSDK"] == str(sdk_root())


def test_the_drivers_own_watchdog_zeroes_the_device_at_once(omega):
    """A device without a firmware watchdog (none set): the driver's own, on the loop's clock,
    zeroes the device's command at the first read after the stall, before any write."""
    omega.settle()
    omega.driver.enable()
    _run(omega, [2.0, 0, 0, 0, 0, 0])
    omega.block["watchdog_s"] = 0.0
    for _ in range(40):
        omega.tick()
    assert omega.rendered()[0] == 2.0          # the device kept rendering through the stall
    omega.tick()
    assert omega.driver.read(omega.row) == DEV_FAULT_WATCHDOG
    omega.physics.step()
    assert not np.any(omega.rendered()), "the watchdog trip did not zero the device"


def test_enabling_after_a_long_idle_does_not_trip_the_firmware_watchdog(omega):
    """The firmware's watchdog counts from the enable as well as from each command (the server
    enables the device seconds after opening it: no command in between)."""
    for _ in range(200):
        omega.tick()
    omega.driver.enable()
    _run(omega, [2.0, 0, 0, 0, 0, 0], steps=3)
    assert omega.rendered()[0] == 2.0 and omega.block["watchdog_trips"] == 0


def test_a_cut_the_device_made_itself_is_seen_in_its_status(omega):
    omega.settle()
    omega.driver.enable()
    _run(omega, [2.0, 0, 0, 0, 0, 0])
    omega.block["force_on"] = 0.0         # e.g. its force button, or a watchdog the driver did not see
    omega.block["force_off_cause"] = 1.0
    codes = {omega.step(np.array([2.0, 0, 0, 0, 0, 0]))[0] for _ in range(60)}
    assert DEV_FAULT_HARDWARE in codes and omega.driver.fault == DEV_FAULT_HARDWARE


@pytest.mark.parametrize("system_type", sorted(__import__("hapticproxy.server.devices.models", fromlist=["x"])
                                               .FORCEDIMENSION))
def test_every_known_model_opens_with_its_own_figures(system_type):
    from hapticproxy.server.devices import models

    spec = models.FORCEDIMENSION[system_type]
    h = ForceDimensionHarness(system_type=system_type)
    try:
        info, lim = h.driver.info, h.driver.limits
        assert (info.model, info.vendor, info.hand) == (spec.name, spec.vendor, spec.hand)
        assert lim.max_force_norm_n == spec.max_force_n
        assert lim.max_torque_n_m == (spec.max_torque_n_m if "rotation" in spec.actuated else 0.0)
        assert info.dof_sensed == {"omega.3": 3, "delta.3": 3, "Falcon": 3, "omega.6": 6}.get(spec.name, 7)
        h.settle()
        h.driver.enable()
        _run(h, [0.0, 0.0, 1.0, 0.0, 0.0, 0.0])
        assert h.rendered()[2] == 1.0
    finally:
        h.close()
