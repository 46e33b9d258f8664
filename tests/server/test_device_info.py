"""DeviceInfo (what a device is) and the DeviceLimits the safety layer reads, derived from it."""
from __future__ import annotations

import math

import pytest

from hapticproxy.server.devices.base import DeviceInfo
from hapticproxy.server.devices.sim import make_sim_device


def _touch(**kw):
    base = dict(model="Touch", vendor="3D Systems", driver="touch", sensed=("position", "rotation"),
                actuated=("position",), max_force_n=3.3, max_torque_n_m=0.5, clock="device")
    base.update(kw)
    return DeviceInfo(**base)


def test_a_device_that_senses_six_and_renders_three():
    info = _touch()
    assert (info.dof_sensed, info.dof_actuated) == (6, 3)
    assert info.wrench_mask == (1, 1, 1, 0, 0, 0)
    lim = info.limits(watchdog_s=0.01)
    assert lim.max_torque_n_m == 0.0 and lim.max_torque_norm_n_m == 0.0   # a stated torque, but not actuated
    assert lim.max_force_n == 3.3 and lim.max_force_norm_n == 3.3 and lim.watchdog_s == 0.01


def test_the_config_may_lower_the_cap_never_raise_it():
    info = _touch()
    assert info.limits(max_force_n=1.0).max_force_norm_n == 1.0
    assert info.limits(max_force_n=30.0).max_force_n == 3.3


@pytest.mark.parametrize("bad", [dict(clock="servo"), dict(sensed=("position", "wrist"))])
def test_bad_info_is_refused(bad):
    with pytest.raises(ValueError):
        _touch(**bad)


def test_every_driver_declares_info():
    d = make_sim_device({"kind": "spatial"}, period_s=1e-3)
    info = d.info
    assert info.driver == "sim" and info.clock == "loop" and info.dof_actuated == 6
    assert "clock: loop" in info.summary()
    assert info.as_dict()["wrench_mask"] == [1] * 6
    assert math.isinf(d.limits.max_force_norm_n)  # the simulated device caps per axis only


@pytest.mark.parametrize("kind, dof", [("1dof", 1), ("planar", 3), ("spatial", 6)])
def test_a_simulated_device_counts_the_coordinates_of_its_kind(kind, dof):
    info = make_sim_device({"kind": kind}, period_s=1e-3).info
    assert (info.dof_sensed, info.dof_actuated) == (dof, dof)
    assert f"{dof} DOF sensed / {dof} rendered" in info.summary()


def test_status_shows_what_the_device_is():
    from hapticproxy.server.status import format_status

    info = _touch(serial="22011", native_rate_hz=1000.0, calibration="done")
    text = format_status({"device_info": info.as_dict(), "loop_state": "idle"})
    line = next(ln for ln in text.splitlines() if ln.startswith("device       "))
    assert line == ("device       3D Systems Touch #22011, 6 DOF sensed / 3 rendered, 3.3 N, 1000 Hz native, "
                    "calibration done, clock: device")
    assert not any(ln.startswith("device       ") for ln in format_status({"loop_state": "idle"}).splitlines())
