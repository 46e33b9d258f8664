"""The ``haply`` driver on the unmodified haplyhardwareapi package over a fake Inverse3 on a
pseudo-terminal (its own process), and on a fake Haply Inverse Service (websocket JSON, its own
process); the physics stepped in lock-step by the test."""
from __future__ import annotations

import importlib.util
import os
import tempfile

import numpy as np
import pytest

if importlib.util.find_spec("HaplyHardwareAPI") is None or importlib.util.find_spec("websockets") is None:
    pytest.skip("haplyhardwareapi / websockets are not installed (the devices extra)", allow_module_level=True)

from hapticproxy.server.devices.base import DEV_FAULT_HARDWARE, DEV_FAULT_LINK, DEV_OK  # noqa: E402
from hapticproxy.server.devices.haply import make_haply_device  # noqa: E402
from hapticproxy.server.devices.vendor import DeviceUnavailable  # noqa: E402
from hapticproxy.testing import device_contract as dcon  # noqa: E402
from hapticproxy.testing.emulators.harness import HaplyHarness, HaplyServiceHarness  # noqa: E402

PUSH = np.array([1.0, 0.0, 0.0, 0.0, 0.0, 0.0])


@pytest.mark.parametrize("rule", list(dcon.RULES))
def test_the_inverse_service_transport_keeps_the_contract(rule):
    dcon.check(rule, HaplyServiceHarness, "spatial")


@pytest.fixture(params=["serial", "service"])
def inv3(request):
    h = HaplyHarness(transport=request.param)
    yield h
    h.close()


def _enabled(h, steps=5):
    h.driver.enable()
    for _ in range(steps):
        st = h.step(PUSH)
    return st


def test_the_device_says_what_it_is_and_moves(inv3):
    info = inv3.driver.info
    assert (info.model, info.vendor, info.serial, info.clock) == ("Inverse3", "Haply Robotics", "1181", "loop")
    assert (info.dof_sensed, info.dof_actuated) == (3, 3)
    assert inv3.driver.limits.max_force_norm_n == 3.0  # the config's cap (no vendor figure here)
    assert _enabled(inv3, 50) == (DEV_OK, DEV_OK)
    r = inv3.row
    assert r[0] > 0.0 and r[7] > 0.0                   # pushed along +x, it moves along +x
    assert r[1] == pytest.approx(-0.12, abs=1e-6)      # float32 on the wire
    assert np.all(np.isnan(r[13:19]))
    assert inv3.rendered()[0] == pytest.approx(1.0)


def test_unplugged_is_a_lost_link_and_nothing_comes_back_by_itself(inv3):
    _enabled(inv3)
    inv3.block["fault_unplugged"] = 1.0
    _, ws = inv3.step(PUSH)
    assert ws == DEV_FAULT_LINK and inv3.driver.fault == DEV_FAULT_LINK
    assert not np.any(inv3.rendered())
    inv3.block["fault_unplugged"] = 0.0
    for _ in range(10):
        inv3.step(PUSH)
        assert not np.any(inv3.rendered()), "force came back without enable()"
    inv3.driver.enable()
    for _ in range(3):
        assert inv3.step(PUSH) == (DEV_OK, DEV_OK)
    assert inv3.rendered()[0] == pytest.approx(1.0)


def test_a_device_error_cuts_the_force(inv3):
    _enabled(inv3)
    inv3.block["fault_error"] = 1.0
    _, ws = inv3.step(PUSH)
    # serial: an unknown reply header (the package times out and returns zeros);
    # service: the device listed without a state
    assert ws == (DEV_FAULT_LINK if inv3.driver.config.transport == "serial" else DEV_FAULT_HARDWARE)
    assert not np.any(inv3.driver.last_command)


def test_a_missing_port_and_a_silent_one_are_named():
    with pytest.raises(DeviceUnavailable, match="/dev/ttyACM77 does not exist"):
        make_haply_device({"port": "/dev/ttyACM77"}, period_s=1e-3)
    master, slave = os.openpty()   # a serial port with nothing behind it
    try:
        with pytest.raises(DeviceUnavailable, match="nothing answered"):
            make_haply_device({"port": os.ttyname(slave), "timeout_s": 0.05}, period_s=1e-3)
    finally:
        os.close(master)
        os.close(slave)


def test_permission_denied_names_the_udev_rule(monkeypatch):
    master, slave = os.openpty()
    path = os.ttyname(slave)
    real = os.access
    monkeypatch.setattr(os, "access", lambda p, mode: False if p == path else real(p, mode))
    try:
        with pytest.raises(DeviceUnavailable, match=r"permission denied on .*99-hapticproxy.rules"):
            make_haply_device({"port": path}, period_s=1e-3)
    finally:
        os.close(master)
        os.close(slave)


@pytest.mark.parametrize("config,match", [
    ({}, "device.port: the serial transport needs the port"),
    ({"port": "/dev/x", "kind": "planar"}, "device.kind: an Inverse3 is spatial"),
    ({"transport": "usb"}, "device.transport"),
    ({"transport": "service", "url": "ws://127.0.0.1:9"}, "Inverse Service does not answer at ws://127.0.0.1:9"),
])
def test_config_refusals_are_one_line(config, match):
    with pytest.raises(ValueError, match=match) as ei:
        make_haply_device(config, period_s=1e-3)
    assert "\n" not in str(ei.value)


@pytest.mark.parametrize("transport", ["serial", "service"])
def test_another_device_than_configured_is_refused(transport):
    with pytest.raises(DeviceUnavailable, match="device.device_id"):
        HaplyHarness(transport=transport, config={"device_id": 7})


def test_the_native_handles_are_kept(inv3):
    n = inv3.driver.native
    if inv3.driver.config.transport == "serial":
        assert n["stream"] is not None and n["inverse3"] is not None
    else:
        assert n["device_id"] == "049D" and n["session_id"] == 1


def test_a_versegrip_on_the_service_gives_orientation_and_buttons():
    h = HaplyHarness(transport="service", versegrip=True,
                     hand={"type": "constant", "wrench": [0, 0, 0, 0.0, 0.0, 0.02], "start": "server"})
    try:
        info = h.driver.info
        assert info.model == "Inverse3 + VerseGrip" and (info.dof_sensed, info.dof_actuated) == (6, 3)
        assert info.buttons == 3 and h.driver.limits.max_torque_n_m == 0.0
        h.block["buttons"] = 5.0
        h.driver.enable()
        for _ in range(60):
            h.step(np.zeros(6))
        q = h.row[3:7]
        assert abs(float(q @ q) - 1.0) < 1e-9 and q[3] > 1e-3   # turned about z by the hand's torque
        assert h.driver.buttons == 5
    finally:
        h.close()
