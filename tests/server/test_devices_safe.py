"""Safe settings derived from the device's info (issue 30, section 3, ``server/devices/safe.py``):
the gains each device renders stably at the loop's rate (its figures scaled with the rate by
Colgate and Schenkel's bound, its moving mass), defaults lowered to them, a config asking more
refused with the nearest safe value (exit 2 from ``serve``), the research override listed
loudly; and the caps of force, torque and gripper never above the device's own."""
from __future__ import annotations

import importlib.util
import logging
import subprocess
import sys

import numpy as np
import pytest

from hapticproxy.server import config as cfgmod
from hapticproxy.server import stability
from hapticproxy.server.devices import models, safe
from hapticproxy.server.devices.base import DeviceInfo
from hapticproxy.server.devices.sim import make_sim_device


def _info(spec: models.ModelSpec, **kw) -> DeviceInfo:
    """What a vendor driver declares for a model of the table (as ``forcedimension.py`` does)."""
    d = dict(model=spec.name, vendor=spec.vendor, driver="x", sensed=spec.sensed, actuated=spec.actuated,
             max_force_n=spec.max_force_n, max_torque_n_m=spec.max_torque_n_m,
             max_gripper_force_n=spec.max_gripper_force_n, max_stiffness_n_per_m=spec.max_stiffness_n_per_m,
             max_damping_n_s_per_m=spec.max_damping_n_s_per_m,
             max_rot_stiffness_n_m_per_rad=spec.max_rot_stiffness_n_m_per_rad,
             max_rot_damping_n_m_s_per_rad=spec.max_rot_damping_n_m_s_per_rad, gripper=spec.gripper)
    d.update(kw)
    return DeviceInfo(**d)


def _limits(info, rate=1000.0, controller="four_channel"):
    return {g.key: g.limit for g in safe.gain_limits(info, rate, controller)}


def _settings(**sections) -> cfgmod.Settings:
    return cfgmod.load(sections)


# ----------------------------------------------------------------------------------- the limits
def test_the_figures_scale_with_the_rate_by_colgates_bound():
    omega = _info(models.FORCEDIMENSION[33])
    for rate in (256.0, 512.0, 1000.0, 4000.0):
        lim = _limits(omega, rate)
        assert lim["controller.stiffness_n_per_m"] == pytest.approx(5000.0 * rate / 1000.0)   # K ~ 1/T
        assert lim["controller.damping_n_s_per_m"] == 30.0                                   # B: no T in the bound
    assert stability.device_stiffness_at_rate(400.0, 1000.0) == 400.0


def test_each_model_of_the_tables_gets_its_own_limits():
    touch = _limits(_info(models.TOUCH["Touch"]))
    assert touch == {"controller.stiffness_n_per_m": 400.0, "controller.damping_n_s_per_m": 4.0}  # no rotation rendered
    sigma = _limits(_info(models.FORCEDIMENSION[104]), 2000.0)
    assert sigma == {"controller.stiffness_n_per_m": 8000.0, "controller.damping_n_s_per_m": 30.0,
                     "controller.rot_stiffness_n_m_per_rad": 2.0, "controller.rot_damping_n_m_s_per_rad": 0.07}
    assert _limits(_info(models.FORCEDIMENSION[60])) == {"controller.stiffness_n_per_m": 3000.0,
                                                         "controller.damping_n_s_per_m": 20.0}   # the Falcon
    assert _limits(_info(models.FORCEDIMENSION[108])) == {"controller.stiffness_n_per_m": 8000.0}  # lambda.7: K only
    assert _limits(_info(models.INVERSE3)) == {}                                                # nothing stated


def test_the_moving_mass_bounds_both_and_the_tighter_wins():
    light = _info(models.TOUCH["Touch"], moving_mass_kg=0.001)
    lim = _limits(light)
    assert lim["controller.stiffness_n_per_m"] == 400.0              # the figure (the mass takes 2 m rate^2 = 2000)
    assert lim["controller.damping_n_s_per_m"] == pytest.approx(1.0)   # the mass: m rate = 1, below the figure's 4
    sim = make_sim_device({"kind": "planar", "mass_kg": 0.4}, period_s=1e-3).info
    assert _limits(sim) == {"controller.stiffness_n_per_m": pytest.approx(800000.0),
                            "controller.damping_n_s_per_m": pytest.approx(400.0)}


def test_rotational_gains_are_bounded_only_where_rotation_is_rendered():
    spec = models.FORCEDIMENSION[104]                              # a sigma.7's figures ...
    sensing_only = _info(spec, actuated=("position", "gripper"))   # ... on a device that renders no torque
    assert set(_limits(sensing_only)) == {"controller.stiffness_n_per_m", "controller.damping_n_s_per_m"}
    assert "controller.rot_stiffness_n_m_per_rad" in _limits(_info(spec))


def test_with_direct_coupling_the_device_renders_the_contact():
    lim = _limits(_info(models.FORCEDIMENSION[104]), controller="direct")
    assert lim == {"model.stiffness_n_per_m": 4000.0, "model.damping_n_s_per_m": 30.0}  # the sigma.7's


# ---------------------------------------------------------------------------------- derive
def test_defaults_a_touch_cannot_take_are_lowered_and_logged(caplog):
    s = _settings()
    info = _info(models.TOUCH["Touch"])
    with caplog.at_level(logging.INFO, logger="hapticproxy.devices"):
        d = safe.derive(s, info)
        safe.log_derived(s, d)
    assert (d["controller"]["stiffness_n_per_m"], d["controller"]["damping_n_s_per_m"]) == (400.0, 4.0)
    assert [k for k, *_ in d.lowered] == ["controller.stiffness_n_per_m", "controller.damping_n_s_per_m"]
    assert s["controller"]["stiffness_n_per_m"] == 1500.0                    # the input is left alone
    assert "controller.stiffness_n_per_m lowered from 1500 to 400" in caplog.text
    assert safe.derive(d, info) is d                                         # idempotent


def test_a_config_asking_more_is_refused_with_the_nearest_safe_value():
    s = _settings(controller={"stiffness_n_per_m": 1000.0})
    with pytest.raises(cfgmod.ConfigError) as e:
        safe.derive(s, _info(models.TOUCH["Touch"]))
    msg = str(e.value)
    assert e.value.key == "controller.stiffness_n_per_m" and "nearest safe value 400" in msg
    assert "allow_outside_stable_region" in msg and "\n" not in msg
    # at the limit: kept; the damping default still lowered
    d = safe.derive(_settings(controller={"stiffness_n_per_m": 400.0}), _info(models.TOUCH["Touch"]))
    assert d["controller"]["stiffness_n_per_m"] == 400.0 and d["controller"]["damping_n_s_per_m"] == 4.0


def test_the_research_override_keeps_the_value_and_lists_it(caplog):
    s = _settings(controller={"damping_n_s_per_m": 10.0}, safety={"allow_outside_stable_region": True})
    with caplog.at_level(logging.WARNING, logger="hapticproxy.devices"):
        d = safe.derive(s, _info(models.TOUCH["Touch"]))
        safe.log_derived(s, d)
    assert d["controller"]["damping_n_s_per_m"] == 10.0
    assert [k for k, _ in d.outside_stable_region] == ["controller.damping_n_s_per_m"]
    assert "OUTSIDE THE DEVICE'S STABLE REGION" in caplog.text
    assert safe.derive(d, _info(models.TOUCH["Touch"])).outside_stable_region == d.outside_stable_region  # once


def test_the_loop_runs_the_gains_derived_for_its_device():
    from hapticproxy.server import control as ctl
    from hapticproxy.server.loop import HapticLoop

    s = _settings(transport={"url": "mem://safe-loop"}, device=LIGHT, telemetry={"ring_s": 0.2})
    loop = HapticLoop.build(s)
    try:
        assert loop.settings["controller"]["damping_n_s_per_m"] == 10.0 and loop.ctrl.cp[ctl.CP_BT] == 10.0
        assert loop.ctrl.cp[ctl.CP_KT] == 1500.0                   # (a 10 g mass takes 2 m rate^2 = 20 kN/m)
    finally:
        loop.close()


def test_what_the_config_sets_is_recorded_not_what_the_preset_or_defaults_do():
    s = cfgmod.load({"preset": "fast", "controller": {"type": "coupler"}, "device": {"kind": "planar"}},
                    {"loop": {"rate_hz": 700.0}})
    assert {"controller.type", "device.kind", "loop.rate_hz"} <= s.given
    assert "controller.stiffness_n_per_m" not in s.given and "preset" not in s.given


@pytest.mark.parametrize("which", ["forcedimension-33", "forcedimension-104", "forcedimension-60", "touch",
                                   "haply-service"])
def test_each_vendor_drivers_own_info_derives_its_limits(which):
    """The drivers on their emulators: the info each declares gives the defaults it can take."""
    from hapticproxy.testing.emulators import harness as H

    needs = {"forcedimension": "forcedimension_core", "touch": "pyOpenHaptics", "haply": "websockets"}
    if importlib.util.find_spec(needs[which.split("-")[0]]) is None:
        pytest.skip(f"{needs[which.split('-')[0]]} is not installed")
    if which.startswith("forcedimension"):
        h = H.ForceDimensionHarness(system_type=int(which.split("-")[1]))
    elif which == "touch":
        h = H.TouchHarness()
    else:
        h = H.HaplyServiceHarness()
    try:
        info = h.driver.info
        d = safe.derive(_settings(), info)
        k, b = d["controller"]["stiffness_n_per_m"], d["controller"]["damping_n_s_per_m"]
        if which == "touch":
            assert (k, b) == (400.0, 4.0)            # HD_NOMINAL_MAX_STIFFNESS; CHAI3D's damping
        elif which == "haply-service":
            assert (k, b) == (1500.0, 15.0) and not d.lowered   # Haply states nothing: the config's
        else:
            assert k <= info.max_stiffness_n_per_m and (info.max_damping_n_s_per_m is None
                                                        or b <= info.max_damping_n_s_per_m)
        # the caps: never above the device's continuous force; torque only where rotation is rendered
        lim = h.driver.limits
        assert lim.max_force_norm_n <= info.max_force_n and lim.max_force_n <= info.max_force_n
        if "rotation" in info.actuated:
            assert 0.0 < lim.max_torque_norm_n_m <= info.max_torque_n_m
        else:
            assert lim.max_torque_n_m == 0.0 and lim.max_torque_norm_n_m == 0.0
    finally:
        h.close()


@pytest.mark.skipif(importlib.util.find_spec("forcedimension_core") is None, reason="forcedimension-core missing")
def test_no_gripper_force_is_ever_commanded():
    """The wrench has no gripper part: an omega.7's gripper (8 N) gets 0 N whatever is written."""
    from hapticproxy.testing.emulators.harness import ForceDimensionHarness

    h = ForceDimensionHarness(system_type=35)
    try:
        h.driver.enable()
        for _ in range(20):
            h.step(np.array([50.0, -50.0, 50.0, 5.0, 5.0, 5.0]))
        assert h.block["cmd_gripper_n"] == 0.0
        assert np.linalg.norm(h.driver.last_command[:3]) <= h.driver.info.max_force_n + 1e-12
    finally:
        h.close()


# ------------------------------------------------------------------- the server: start, status
#: a light 1-DOF simulated device: 10 g moving mass takes at most 10 N s/m at 1 kHz (the default is 15)
LIGHT = {"driver": "sim", "kind": "1dof", "mass_kg": 0.01, "watchdog_s": 0.0}


def test_serve_refuses_a_set_gain_the_device_cannot_take_exit_2(tmp_path):
    cfg = tmp_path / "c.toml"
    cfg.write_text('[transport]\nurl = "udp://127.0.0.1:0"\n[status]\naddress = "127.0.0.1:0"\n'
                   '[controller]\ndamping_n_s_per_m = 20.0\n'
                   '[device]\ndriver = "sim"\nkind = "1dof"\nmass_kg = 0.01\n')
    r = subprocess.run([sys.executable, "-m", "hapticproxy.cli.main", "serve", "--config", str(cfg), "--duration", "1"],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 2, r.stderr
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "controller.damping_n_s_per_m" in lines[0] and "nearest safe value 10" in lines[0]


def test_the_loop_process_refuses_it_too_and_the_supervisor_exits_2():
    from hapticproxy.server.daemon import StartupError, Supervisor

    s = cfgmod.load({"transport": {"url": "udp://127.0.0.1:0"}, "status": {"address": "127.0.0.1:0"},
                     "controller": {"damping_n_s_per_m": 20.0}, "device": LIGHT, "telemetry": {"ring_s": 0.5}})
    sup = Supervisor(s)
    try:
        with pytest.raises(StartupError) as e:
            sup.start()
        assert e.value.code == 2 and "nearest safe value 10" in str(e.value)
    finally:
        sup.close()


def test_status_lists_the_lowered_defaults_and_the_override():
    from hapticproxy.server.daemon import Supervisor
    from hapticproxy.server.status import format_status

    s = cfgmod.load({"transport": {"url": "udp://127.0.0.1:0"}, "status": {"address": "127.0.0.1:0"},
                     "controller": {"rot_damping_n_m_s_per_rad": 0.015}, "device": LIGHT,
                     "telemetry": {"ring_s": 0.5}})
    sup = Supervisor(s)
    try:
        sup.start()
        snap = sup.status()
        assert sup.settings["controller"]["damping_n_s_per_m"] == 10.0      # adopted from the loop
        assert any(w.startswith("controller.damping_n_s_per_m 15 -> 10") for w in snap["lowered"])
        assert "lowered      controller.damping_n_s_per_m 15 -> 10" in format_status(snap)
    finally:
        sup.close()
    s2 = cfgmod.load({"transport": {"url": "udp://127.0.0.1:0"}, "status": {"address": "127.0.0.1:0"},
                      "controller": {"damping_n_s_per_m": 20.0}, "safety": {"allow_outside_stable_region": True},
                      "device": LIGHT, "telemetry": {"ring_s": 0.5}})
    sup = Supervisor(s2)
    try:
        sup.start()
        snap = sup.status()
        assert any(w.startswith("controller.damping_n_s_per_m: 20 is more than") for w in snap["outside_stable_region"])
        assert "WARNING      outside the stable region" in format_status(snap)
    finally:
        sup.close()


_TOUCH_STATES_NO_DAMPING = """
import dataclasses
from hapticproxy.server.devices import models
real = models.TOUCH["Touch"]
models.TOUCH["Touch"] = dataclasses.replace(real, max_damping_n_s_per_m=None)
from hapticproxy.testing.emulators.harness import TouchHarness, hd_folder
hd_folder()                      # the fake libHD built from that table: HD_NOMINAL_MAX_DAMPING is 0
models.TOUCH["Touch"] = real     # the driver's table: CHAI3D's 4 N s/m
h = TouchHarness()
print(h.driver.info.max_damping_n_s_per_m, h.driver.info.max_stiffness_n_per_m)
h.close()
"""


@pytest.mark.skipif(importlib.util.find_spec("pyOpenHaptics") is None, reason="pyopenhaptics is not installed")
def test_a_touch_that_states_no_damping_gets_chai3ds_figure():
    r = subprocess.run([sys.executable, "-c", _TOUCH_STATES_NO_DAMPING], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert r.stdout.split()[-2:] == ["4.0", "400.0"]
