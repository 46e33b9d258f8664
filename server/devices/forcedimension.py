"""Force Dimension devices (omega.3/6/7, delta.3, sigma.7, lambda.7) and the Novint Falcon
through the Force Dimension SDK (entry point ``forcedimension``), on PyPI ``forcedimension-core``.

**Who owns the clock: the loop.** The DHD SDK is polled: each ``read`` asks the device for its
newest sample over USB (``dhdGetPositionAndOrientationFrame``, ``dhdGetLinearVelocity``, ...),
each ``write`` sends one command (``dhdSetForceAndTorqueAndGripperForce``); the device renders
the last command until the next one. Its firmware watchdog (``dhdSetWatchdog``, expert mode,
125 us units, at most 31.9 ms) cuts the forces when no command arrives in time: the loop
stalling cannot leave a force on. :attr:`ForceDimensionDevice.native` keeps what compiled code
needs to call the SDK itself (the loaded ``libdrd`` as a ``ctypes.CDLL`` and the device ID).

The package finds ``libdrd`` at import through ``$FDSDK`` (``$FDSDK/lib/release/lin-<machine>-gcc/
libdrd.so.*``), the legacy ``$FORCEDIM_SDK``, ``~/.local/lib`` or ``/usr/local/lib``, and refuses an
SDK older than 3.16.

Config (``[device]``, ``driver = "forcedimension"``; every key optional):

``kind`` = ``"spatial"``
    The only kind (a Force Dimension device moves in 3-D).
``serial`` = 0
    Open the device with this serial number (several attached); 0: the first free one.
``model`` = ``""``
    The model the config is written for (``omega.3``, ``sigma.7``, ``Falcon``, ...): another
    model attached is refused (its caps and workspace differ); empty: any.
``calibrate`` = false
    ``drdAutoInit`` when the device is not calibrated. The handle then moves by itself for a
    few seconds (let go of it), so it never happens unless the config asks; a device that needs
    calibration otherwise is refused with the fix.
``max_force_n`` = 0
    A cap below the model's continuous force (0: the model's; a higher one is refused with it).
``watchdog_s`` = 0.02
    The firmware watchdog (rounded to 125 us; at most 0.031875 s; 0: none).
``max_speed_m_per_s`` = 2.0, ``max_angular_speed_rad_per_s`` = 20.0
    Speeds the safety layer trips at.
``button_emulation`` = false
    ``dhdEmulateButton``: the gripper of an omega.7 / sigma.7 acts as a button.
"""
from __future__ import annotations

import ctypes
import importlib.util
import os
from dataclasses import dataclass
from typing import Annotated

import msgspec
import numpy as np
from msgspec import Meta

from . import _check as ck
from . import models
from .base import (
    DEV_FAULT_HARDWARE, DEV_FAULT_LINK, DEV_FAULT_WATCHDOG, DEV_OK, DS_BUTTONS, DS_GRIPPER, DS_GRIPPER_RATE, DeviceInfo,
)
from .vendor import DeviceUnavailable, VendorDevice, check_force_cap, missing, quat_from_matrix

PACKAGE = "forcedimension_core"
DIST = "forcedimension-core"
WATCHDOG_UNIT_S = 125e-6
WATCHDOG_MAX_S = 255 * WATCHDOG_UNIT_S
# DHD error numbers (forcedimension_core.constants.ErrorNum)
E_COM, E_NO_DRIVER, E_NO_DEVICE, E_NOT_AVAILABLE, E_IN_USE = 2, 4, 5, 6, 20
#: read the device's status (force on? why off?) every this many reads (one more USB request)
STATUS_EVERY = 50
CAUSE_WATCHDOG = 3  # forcedimension_core.constants.ForceOffCause.WATCHDOG


class ForceDimensionConfig(msgspec.Struct, forbid_unknown_fields=True, kw_only=True):
    driver: str = "forcedimension"
    kind: str = "spatial"
    serial: Annotated[int, Meta(ge=0, le=65535)] = 0
    model: str = ""
    calibrate: bool = False
    #: a cap below the model's continuous force (0: the model's; above it is refused at open)
    max_force_n: Annotated[float, Meta(ge=0.0, le=100.0)] = 0.0
    watchdog_s: Annotated[float, Meta(ge=0.0, le=WATCHDOG_MAX_S)] = 0.02
    max_speed_m_per_s: Annotated[float, Meta(gt=0.0, le=100.0)] = 2.0
    max_angular_speed_rad_per_s: Annotated[float, Meta(gt=0.0, le=1000.0)] = 20.0
    button_emulation: bool = False


def parse_config(config: dict | None) -> ForceDimensionConfig:
    c = ck.convert(ForceDimensionConfig, dict(config or {}), "device")
    if c.kind != "spatial":
        raise ck.fail("device.kind", f"a Force Dimension device is spatial (it moves in 3-D), got {c.kind!r}")
    if c.model and c.model.lower() not in models.FORCEDIMENSION_NAMES:
        raise ck.fail("device.model", f"unknown model {c.model!r}; known: "
                      f"{', '.join(sorted({m.name for m in models.FORCEDIMENSION.values()}))}")
    return c


def effective_config(config: dict, *, period_s: float) -> dict:
    """Every key with its value (no device is opened: the config loader checks keys only)."""
    return ck.table(parse_config(config))


def sdk():
    """Import the vendor package (it loads ``libdrd`` at import). ``DeviceUnavailable`` naming the
    fix: the package missing, or the SDK's library not found or too old."""
    if importlib.util.find_spec(PACKAGE) is None:
        raise missing("forcedimension", DIST, variable="FDSDK to the Force Dimension SDK's folder")
    import contextlib
    import io

    said = io.StringIO()  # the package writes its own complaint to stderr: folded into the one line
    try:
        with contextlib.redirect_stderr(said):
            import forcedimension_core as fdc  # noqa: F401 - loads libdrd
            from forcedimension_core import dhd, drd  # noqa: F401
            import forcedimension_core.dhd.expert  # noqa: F401
            from forcedimension_core.dhd import direct  # noqa: F401
    except ImportError:
        where = os.environ.get("FDSDK") or os.environ.get("FORCEDIM_SDK")
        hint = (f"FDSDK={where} holds no usable lib/release/lin-*-gcc/libdrd.so.* (SDK 3.16 or newer)" if where
                else "FDSDK is not set: set it to the Force Dimension SDK's folder (the one holding lib/release/)")
        why = " ".join(said.getvalue().split()) or "no libdrd"
        raise DeviceUnavailable(f"device.driver: forcedimension: {DIST} could not load libdrd ({why}); {hint}") from None
    return fdc


@dataclass(frozen=True)
class Native:
    """What compiled code needs to drive the device through the SDK itself."""

    lib: ctypes.CDLL      # the libdrd the package loaded (dhd* and drd* symbols)
    device_id: int        # the DHD device ID (the trailing ``char ID`` of every call)
    system_type: int


def _error_line(fdc, what: str) -> DeviceUnavailable:
    dhd = fdc.dhd
    err = int(dhd.errorGetLast())
    text = dhd.errorGetLastStr()
    if err == E_NO_DEVICE:
        fix = "plug it in and power it on (`hapticproxy devices` lists what is connected)"
    elif err == E_IN_USE:
        fix = "another program holds it: close that program (or the other hapticproxy serve)"
    elif err == E_NO_DRIVER:
        fix = ("no access to the USB device: install deploy/udev/99-hapticproxy.rules "
               "(sudo cp ... /etc/udev/rules.d/ && sudo udevadm control --reload && replug)")
    elif err == E_COM:
        fix = "check the USB cable and the device's power"
    else:
        fix = "see the SDK's error above"
    return DeviceUnavailable(f"device.driver: forcedimension: {what}: {text} (DHD error {err}); {fix}")


class ForceDimensionDevice(VendorDevice):
    """One open Force Dimension device (see the module docstring)."""

    name = "forcedimension"

    def __init__(self, config: dict, *, period_s: float, clock_ns=None) -> None:
        c = parse_config(config)
        fdc = sdk()
        self._fdc = fdc
        dhd = fdc.dhd
        self._dhd = dhd
        self.config = c
        dev_id = dhd.openSerial(c.serial) if c.serial else dhd.open()
        if dev_id < 0:
            raise _error_line(fdc, f"cannot open {'the device with serial ' + str(c.serial) if c.serial else 'a device'}")
        self._id = int(dev_id)
        try:
            info = self._identify(c)
            limits = info.limits(max_speed_m_per_s=c.max_speed_m_per_s,
                                 max_angular_speed_rad_per_s=c.max_angular_speed_rad_per_s,
                                 watchdog_s=self._watchdog_s, max_force_n=check_force_cap(c.max_force_n, info))
        except BaseException:
            dhd.close(self._id)
            raise
        super().__init__(info, limits, clock_ns=clock_ns)
        from forcedimension_core.containers.numpy import Mat3x3, Vec3

        self._p = Vec3()
        self._v = Vec3()
        self._w = Vec3()
        self._R = Mat3x3()
        self._grip = ctypes.c_double()
        self._grip_w = ctypes.c_double()
        self._f = np.zeros(3)
        self._t = np.zeros(3)
        self._rot = "rotation" in info.sensed
        self._has_grip = info.gripper
        self.gripper_angle_rad = 0.0
        self.buttons = 0
        self._reads = 0
        self._status_v = fdc.containers.Status()
        self.native = Native(fdc.runtime._libdrd, self._id, self._system_type)
        self._direct = fdc.dhd.direct
        self._set = dhd.setForceAndTorqueAndGripperForce
        self._mask_bits = dhd.getButtonMask
        self._has_buttons = info.buttons > 0
        self._grip_angle = dhd.getGripperAngleRad
        self._grip_rate = dhd.getGripperAngularVelocityRad

    def _identify(self, c: ForceDimensionConfig) -> DeviceInfo:
        dhd, drd, fdc = self._dhd, self._fdc.drd, self._fdc
        i = self._id
        st = int(dhd.getSystemType(i))
        self._system_type = st
        spec = models.FORCEDIMENSION.get(st)
        sn = dhd.getSerialNumber(i)
        if spec is None:
            raise DeviceUnavailable(f"device.driver: forcedimension: device type {st} "
                                    f"({dhd.getSystemName(i)!r}, serial {sn}) is not one this driver knows")
        if c.model and st not in models.FORCEDIMENSION_NAMES[c.model.lower()]:
            raise DeviceUnavailable(f"device.model: the config is for a {c.model}, the device attached is a "
                                    f"{spec.name} (serial {sn}): write model = \"{spec.name}\" (and check the caps) "
                                    f"or attach the {c.model}")
        calibrated = bool(drd.isInitialized(i))
        if not calibrated:
            if not c.calibrate:
                raise DeviceUnavailable(f"device.calibrate: the {spec.name} (serial {sn}) needs calibration: set "
                                        f"calibrate = true in [device] (the handle moves by itself for a few "
                                        f"seconds: let go of it) or calibrate it with the SDK's tools")
            if drd.autoInit(i) < 0:
                raise _error_line(fdc, f"calibrating the {spec.name}")
            drd.stop(True, i)  # the regulation thread drdAutoInit started hands the forces back
            calibrated = bool(drd.isInitialized(i))
        # the firmware watchdog (expert mode, as the SDK wants it)
        self._watchdog_s = 0.0
        if c.watchdog_s > 0.0:
            units = max(1, min(255, int(round(c.watchdog_s / WATCHDOG_UNIT_S))))
            fdc.dhd.expert.enableExpertMode()
            ok = fdc.dhd.expert.setWatchdog(units, i) >= 0
            fdc.dhd.expert.disableExpertMode()
            if not ok:
                raise _error_line(fdc, f"setting the {spec.name}'s firmware watchdog (watchdog_s = 0 runs without)")
            self._watchdog_s = units * WATCHDOG_UNIT_S
        if c.button_emulation:
            dhd.emulateButton(True, i)
        lo, hi = spec.workspace_box()
        freq_khz = float(dhd.getComFreq(i))
        return DeviceInfo(
            model=spec.name, vendor=spec.vendor, driver="forcedimension", serial=str(sn),
            sensed=spec.sensed, actuated=spec.actuated, max_force_n=float(spec.max_force_n),
            max_torque_n_m=spec.max_torque_n_m, max_gripper_force_n=spec.max_gripper_force_n,
            max_stiffness_n_per_m=spec.max_stiffness_n_per_m, max_damping_n_s_per_m=spec.max_damping_n_s_per_m,
            max_rot_stiffness_n_m_per_rad=spec.max_rot_stiffness_n_m_per_rad,
            max_rot_damping_n_m_s_per_rad=spec.max_rot_damping_n_m_s_per_rad,
            workspace_radius_m=spec.workspace_radius_m, workspace_min_m=lo, workspace_max_m=hi,
            native_rate_hz=freq_khz * 1e3 if freq_khz > 0 else None, gripper=spec.gripper, buttons=spec.buttons,
            calibration="done" if calibrated else "needed", clock="loop", sdk_units="m, N, rad", hand=spec.hand,
            source=f"CHAI3D's figures for the model; serial, calibration and rate from the SDK "
                   f"({DIST}; dhdGetSystemType {st})")

    # -- the SDK ----------------------------------------------------------------------------
    def _fail_code(self) -> int:
        err = int(self._dhd.errorGetLast())
        return DEV_FAULT_LINK if err in (E_COM, E_NO_DEVICE) else DEV_FAULT_HARDWARE

    def _io_read(self, row: np.ndarray) -> int:
        i = self._id
        d = self._direct
        if d.getPositionAndOrientationFrame(self._p, self._R, i) < 0 or d.getLinearVelocity(self._v, i) < 0:
            return self._fail_code()
        if self._rot and d.getAngularVelocityRad(self._w, i) < 0:
            return self._fail_code()
        row[0:3] = self._p
        quat_from_matrix(self._R, row, 3)
        row[7:10] = self._v
        if self._rot:
            row[10:13] = self._w
        else:
            row[10:13] = 0.0
        row[13:19] = np.nan
        row[19] = self._clock() * 1e-9
        # the inputs (buttons, gripper) reach the engine through the state row (base.py)
        if self._has_buttons:
            self.buttons = int(self._mask_bits(i))
            row[DS_BUTTONS] = self.buttons
        else:
            row[DS_BUTTONS] = np.nan
        row[DS_GRIPPER] = row[DS_GRIPPER_RATE] = np.nan
        if self._has_grip:
            if self._grip_angle(self._grip, i) >= 0:
                self.gripper_angle_rad = row[DS_GRIPPER] = self._grip.value
            if self._grip_rate(self._grip_w, i) >= 0:
                row[DS_GRIPPER_RATE] = self._grip_w.value
        self._reads += 1
        if self._enabled and self._fault == DEV_OK and self._reads % STATUS_EVERY == 0:
            # the device may have cut its forces itself (its watchdog, its force button, ...)
            if self._dhd.getStatus(self._status_v, i) < 0:
                return self._fail_code()
            if self._status_v[5] == 0:
                return DEV_FAULT_WATCHDOG if self._status_v[14] == CAUSE_WATCHDOG else DEV_FAULT_HARDWARE
        return DEV_OK

    def _io_write(self, wrench: np.ndarray) -> int:
        self._f[:] = wrench[:3]
        self._t[:] = wrench[3:]
        return DEV_OK if self._set(self._f, self._t, 0.0, self._id) >= 0 else self._fail_code()

    def _io_enable(self, on: bool) -> int:
        return DEV_OK if self._dhd.enableForce(on, self._id) >= 0 else self._fail_code()

    def _io_close(self) -> None:
        self._dhd.close(self._id)


def make_forcedimension_device(config: dict, *, period_s: float, clock_ns=None) -> ForceDimensionDevice:
    """Entry point ``forcedimension``: open the configured device (see the module docstring)."""
    return ForceDimensionDevice(config, period_s=period_s, clock_ns=clock_ns)


make_forcedimension_device.effective_config = effective_config
#: the kinds this driver builds (the contract suite runs it on these only)
make_forcedimension_device.kinds = ("spatial",)

#: for `hapticproxy plugins` and `hapticproxy devices`
make_forcedimension_device.about = {"clock": "loop", "package": "forcedimension-core", "module": "forcedimension_core", "sdk": "the Force Dimension SDK ($FDSDK)", "models": sorted({m.name for m in models.FORCEDIMENSION.values()})}
