"""3D Systems Touch / Phantom devices through OpenHaptics' HD API (entry point ``touch``), on
PyPI ``pyopenhaptics`` (which loads ``libHD.so`` by its bare name: the OpenHaptics install's, found
through the loader's path, ``LD_LIBRARY_PATH`` included).

**Who owns the clock: the device.** OpenHaptics' scheduler runs the servo thread at 1 kHz and
calls the callback scheduled on it (:meth:`TouchDevice.schedule`); the device's state is
sampled and its force committed inside that callback (``hdBeginFrame`` / ``hdEndFrame``). Today's
loop still wakes on its own clock and calls ``read`` / ``write``; the two meet in a mailbox of
preallocated arrays, each written by one side only:

- ``state`` (float64[``NS``]): written by the servo callback only. ``state[0]`` is a sequence
  counter: odd while the callback writes, even when the sample is whole; ``read`` copies the
  sample and retries when the counter was odd or changed under it.
- ``command`` (float64[``NC``]): written by the loop only (``write``, ``enable``, ``disable``),
  under the same odd/even counter; the callback takes it when whole and keeps the last whole
  one otherwise (a command is never half old, half new).

Today the callback is Python: it and the loop take turns on the GIL, so neither side ever sees
the other mid-write and the counters are belt and braces. They are what a compiled callback
(a numba ``cfunc`` scheduled through :meth:`TouchDevice.schedule` with the mailbox's address as
its ``void*``) needs: it runs without the GIL, concurrently with the loop. On x86-64 aligned
8-byte stores are atomic and stores are not reordered with other stores, which the odd/even
protocol relies on; a compiled side on another architecture needs release/acquire fences.

The callback keeps the device-side watchdog: when the command's counter has not moved for
``watchdog_s`` of servo ticks, it renders zero and latches the cut until the loop's next
``enable()``. It renders zero as well when the loop disabled the output. A sample that stopped
arriving (the servo thread not run: late ticks, a hung driver) is a lost device for ``read`` once
none came for ``stale_s`` of the loop's clock.

Quirks of ``pyopenhaptics`` 1.0.1 (read in its source, run on the fake): ``init_device`` swallows
the failure and prints (it compares the handle with ``HD_BAD_HANDLE``, while ``hdInitDevice``
returns ``HD_INVALID_HANDLE``), so the driver checks the handle itself; ``get_error`` raises a
``KeyError`` for error codes outside its five (``HD_COMM_ERROR``, ``HD_DEVICE_FAULT``, ...), so the
driver reads ``hdGetError`` itself; ``enable_force`` and ``HapticDevice`` print to stdout, so the
driver calls ``hdEnable`` itself; ``hdAsyncSheduler`` passes a pointer to a local that dies with
the call as the callback's data. :attr:`TouchDevice.native` keeps the ``CDLL`` the package loaded
and the HD device handle.

Config (``[device]``, ``driver = "touch"``): ``kind`` = ``"spatial"``; ``device_name`` =
``"Default Device"`` (the name in the Touch Setup / ``Touch_Setup`` configuration: several
devices by name); ``serial`` = ``""`` (refuse another device); ``model`` = ``""`` (refuse another
model); ``calibrate`` = false (``hdUpdateCalibration`` when the device needs it: a Touch
calibrates from its inkwell without moving); ``max_force_n`` = 0 (a cap below the continuous force; 0: the device's; higher: refused); ``watchdog_s`` = 0.01;
``stale_s`` = 0.02; ``max_speed_m_per_s`` = 2.0.
"""
from __future__ import annotations

import ctypes
import importlib.util
from time import monotonic_ns as _monotonic_ns
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

HD_INVALID_HANDLE = 0xFFFFFFFF
HD_FORCE_OUTPUT = 0x4000
HD_CURRENT_BUTTONS = 0x2000
HD_CURRENT_VELOCITY = 0x2051
HD_CURRENT_TRANSFORM = 0x2052
HD_CURRENT_ANGULAR_VELOCITY = 0x2053
HD_DEVICE_MODEL_TYPE, HD_DEVICE_VENDOR, HD_DEVICE_SERIAL_NUMBER = 0x2501, 0x2503, 0x2504
HD_USABLE_WORKSPACE_DIMENSIONS = 0x2551
HD_UPDATE_RATE = 0x2600
HD_NOMINAL_MAX_STIFFNESS, HD_NOMINAL_MAX_FORCE, HD_NOMINAL_MAX_CONTINUOUS_FORCE = 0x2602, 0x2603, 0x2604
HD_NOMINAL_MAX_DAMPING = 0x2609
HD_CURRENT_FORCE = 0x2700
HD_CALIBRATION_OK, HD_CALIBRATION_NEEDS_UPDATE, HD_CALIBRATION_NEEDS_MANUAL_INPUT = 0x5000, 0x5001, 0x5002
HD_CALIBRATION_AUTO, HD_CALIBRATION_INKWELL = 2, 4
HD_COMM_ERROR, HD_COMM_CONFIG_ERROR, HD_DEVICE_ALREADY_INITIATED = 0x0302, 0x0303, 0x0301
HD_MAX_SCHEDULER_PRIORITY = (1 << 16) - 1
HD_CALLBACK_CONTINUE = 1

# the mailbox (see the module docstring)
S_SEQ, S_TICK, S_POS, S_QUAT, S_VEL, S_W, S_BUTTONS, S_ERROR, S_CUT, S_EPOCH = 0, 1, 2, 5, 9, 12, 15, 16, 17, 18
NS = 19
C_SEQ, C_FORCE, C_ARMED, C_EPOCH = 0, 1, 4, 5
NC = 6

CALLBACK = ctypes.CFUNCTYPE(ctypes.c_uint, ctypes.c_void_p)
TICK_RING = 4096


class TouchConfig(msgspec.Struct, forbid_unknown_fields=True, kw_only=True):
    driver: str = "touch"
    kind: str = "spatial"
    device_name: str = "Default Device"
    serial: str = ""
    model: str = ""
    calibrate: bool = False
    #: a cap below the model's continuous force (0: the model's; above it is refused at open)
    max_force_n: Annotated[float, Meta(ge=0.0, le=100.0)] = 0.0
    watchdog_s: Annotated[float, Meta(ge=0.0, le=1.0)] = 0.01
    stale_s: Annotated[float, Meta(gt=0.0, le=1.0)] = 0.02
    max_speed_m_per_s: Annotated[float, Meta(gt=0.0, le=100.0)] = 2.0


def parse_config(config: dict | None) -> TouchConfig:
    c = ck.convert(TouchConfig, dict(config or {}), "device")
    if c.kind != "spatial":
        raise ck.fail("device.kind", f"a Touch is spatial (it moves in 3-D and senses its stylus' rotation), "
                      f"got {c.kind!r}")
    return c


def effective_config(config: dict, *, period_s: float) -> dict:
    return ck.table(parse_config(config))


def hd():
    """The loaded HD library, through the package (``DeviceUnavailable`` with the fix)."""
    if importlib.util.find_spec("pyOpenHaptics") is None:
        raise missing("touch", "pyopenhaptics", extra="(OpenHaptics and the Touch device driver from 3D Systems "
                      "are needed too)")
    try:
        import pyOpenHaptics.hd as phd
    except OSError as exc:
        raise DeviceUnavailable(f"device.driver: touch: pyopenhaptics could not load libHD.so ({exc}): install "
                                f"OpenHaptics for Linux and the Touch device driver, or set LD_LIBRARY_PATH to the "
                                f"folder holding libHD.so") from None
    return phd


@dataclass(frozen=True)
class Native:
    """What compiled code needs: the HD library and the device handle (``hdBeginFrame(handle)``)."""

    lib: ctypes.CDLL
    handle: int


def _proto(lib) -> None:
    """argtypes for the HD calls the driver makes itself (the package sets its own on use)."""
    from pyOpenHaptics.hd_define import HDErrorInfo

    d = ctypes.POINTER(ctypes.c_double)
    lib.hdInitDevice.argtypes, lib.hdInitDevice.restype = [ctypes.c_char_p], ctypes.c_uint
    lib.hdGetError.argtypes, lib.hdGetError.restype = [], HDErrorInfo
    lib.hdEnable.argtypes, lib.hdEnable.restype = [ctypes.c_uint], None
    lib.hdDisable.argtypes, lib.hdDisable.restype = [ctypes.c_uint], None
    lib.hdBeginFrame.argtypes, lib.hdBeginFrame.restype = [ctypes.c_uint], None
    lib.hdEndFrame.argtypes, lib.hdEndFrame.restype = [ctypes.c_uint], None
    lib.hdMakeCurrentDevice.argtypes, lib.hdMakeCurrentDevice.restype = [ctypes.c_uint], None
    lib.hdGetDoublev.argtypes, lib.hdGetDoublev.restype = [ctypes.c_uint, d], None
    lib.hdSetDoublev.argtypes, lib.hdSetDoublev.restype = [ctypes.c_uint, d], None
    lib.hdGetIntegerv.argtypes, lib.hdGetIntegerv.restype = [ctypes.c_uint, ctypes.POINTER(ctypes.c_int)], None
    lib.hdGetString.argtypes, lib.hdGetString.restype = [ctypes.c_uint], ctypes.c_char_p
    lib.hdCheckCalibration.argtypes, lib.hdCheckCalibration.restype = [], ctypes.c_int
    lib.hdUpdateCalibration.argtypes, lib.hdUpdateCalibration.restype = [ctypes.c_int], None
    lib.hdScheduleAsynchronous.argtypes = [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_ushort]
    lib.hdScheduleAsynchronous.restype = ctypes.c_ulong
    lib.hdUnschedule.argtypes, lib.hdUnschedule.restype = [ctypes.c_ulong], None
    lib.hdStartScheduler.argtypes, lib.hdStartScheduler.restype = [], None
    lib.hdStopScheduler.argtypes, lib.hdStopScheduler.restype = [], None
    lib.hdDisableDevice.argtypes, lib.hdDisableDevice.restype = [ctypes.c_uint], None


class TouchDevice(VendorDevice):
    """A Touch / Phantom on the OpenHaptics scheduler (see the module docstring)."""

    name = "touch"

    def __init__(self, config: dict, *, period_s: float, clock_ns=None) -> None:
        c = parse_config(config)
        self.config = c
        phd = hd()
        lib = phd._lib_hd
        _proto(lib)
        self._lib = lib
        h = int(lib.hdInitDevice(c.device_name.encode()))
        if h == HD_INVALID_HANDLE:
            err = lib.hdGetError().errorCode
            fix = {HD_COMM_CONFIG_ERROR: f"no device configured as {c.device_name!r}: run Touch_Setup (or set "
                                         f"device_name to the configured name); is it plugged in?",
                   HD_DEVICE_ALREADY_INITIATED: "another program holds it: close that program",
                   HD_COMM_ERROR: "check the cable; permission: install deploy/udev/99-hapticproxy.rules"}.get(
                err, "see OpenHaptics' error code")
            raise DeviceUnavailable(f"device.device_name: touch: hdInitDevice({c.device_name!r}) failed "
                                    f"(HD error 0x{err:04x}): {fix}")
        self._h = h
        try:
            info = self._identify(c)
        except BaseException:
            lib.hdDisableDevice(h)
            raise
        wd = c.watchdog_s
        limits = info.limits(max_speed_m_per_s=c.max_speed_m_per_s, watchdog_s=wd,
                             max_force_n=check_force_cap(c.max_force_n, info))
        super().__init__(info, limits, clock_ns=clock_ns)
        self.native = Native(lib, h)
        # the mailbox and the callback's own buffers (preallocated: nothing is made per tick)
        self.state = np.zeros(NS)
        self.state[S_QUAT] = 1.0
        self.command = np.zeros(NC)
        self._m = (ctypes.c_double * 16)()
        self._v = (ctypes.c_double * 3)()
        self._w = (ctypes.c_double * 3)()
        self._f = (ctypes.c_double * 3)()
        self._b = ctypes.c_int()
        self._cmd_taken = np.zeros(NC)
        #: the servo ticks' start times [ns, CLOCK_MONOTONIC], a ring (the measured native rate
        #: and period jitter: ``bench devices``); index ``tick % TICK_RING``
        self.tick_ns = np.zeros(TICK_RING, dtype=np.int64)
        self._wd_ticks = int(round(wd * info.native_rate_hz)) if wd > 0 and info.native_rate_hz else 0
        self._since = 0        # servo ticks since the command's counter last moved
        self._last_seq = -1.0
        self._epoch_seen = 0.0
        self._stale_ns = int(round(c.stale_s * 1e9))
        self._last_tick = -1.0
        self._last_tick_ns = self._clock()
        self._sched = None
        self._cb = CALLBACK(self._servo)  # kept referenced: the scheduler holds its address
        self.schedule(ctypes.cast(self._cb, ctypes.c_void_p).value, None)
        lib.hdEnable(HD_FORCE_OUTPUT)
        lib.hdStartScheduler()

    def _identify(self, c: TouchConfig) -> DeviceInfo:
        lib = self._lib
        lib.hdMakeCurrentDevice(self._h)
        model = (lib.hdGetString(HD_DEVICE_MODEL_TYPE) or b"").decode()
        vendor = (lib.hdGetString(HD_DEVICE_VENDOR) or b"").decode()
        serial = (lib.hdGetString(HD_DEVICE_SERIAL_NUMBER) or b"").decode()
        if c.model and c.model != model:
            raise DeviceUnavailable(f"device.model: the config is for a {c.model}, the device {c.device_name!r} is a "
                                    f"{model} (serial {serial})")
        if c.serial and c.serial != serial:
            raise DeviceUnavailable(f"device.serial: {c.device_name!r} has serial {serial}, the config asks for "
                                    f"{c.serial} (set device_name to the device with that serial)")
        cal = lib.hdCheckCalibration()
        if cal == HD_CALIBRATION_NEEDS_MANUAL_INPUT:
            raise DeviceUnavailable(f"device.calibrate: the {model} needs manual calibration: put the stylus in its "
                                    f"inkwell (or run Touch_Diagnostic's calibration), then start again")
        if cal == HD_CALIBRATION_NEEDS_UPDATE:
            if not c.calibrate:
                raise DeviceUnavailable(f"device.calibrate: the {model} (serial {serial}) needs calibration: set "
                                        f"calibrate = true in [device] (hdUpdateCalibration; the stylus does not move)")
            lib.hdUpdateCalibration(HD_CALIBRATION_AUTO)
            cal = lib.hdCheckCalibration()

        def dv(code, n=1):
            a = (ctypes.c_double * n)()
            lib.hdGetDoublev(code, a)
            return list(a)

        rate = ctypes.c_int()
        lib.hdGetIntegerv(HD_UPDATE_RATE, rate)
        peak = dv(HD_NOMINAL_MAX_FORCE)[0]
        cont = dv(HD_NOMINAL_MAX_CONTINUOUS_FORCE)[0] or peak
        ws = dv(HD_USABLE_WORKSPACE_DIMENSIONS, 6)
        spec = models.TOUCH.get(model)
        return DeviceInfo(
            model=model, vendor=vendor, driver="touch", serial=serial, sensed=("position", "rotation"),
            actuated=("position",), max_force_n=cont, peak_force_n=peak,
            # the device's own nominal figures; where it states none, CHAI3D's for the model
            max_stiffness_n_per_m=dv(HD_NOMINAL_MAX_STIFFNESS)[0] * 1e3 or (spec.max_stiffness_n_per_m if spec else None),
            max_damping_n_s_per_m=dv(HD_NOMINAL_MAX_DAMPING)[0] * 1e3 or (spec.max_damping_n_s_per_m if spec else None),
            workspace_radius_m=spec.workspace_radius_m if spec else None,
            workspace_min_m=tuple(v * 1e-3 for v in ws[:3]), workspace_max_m=tuple(v * 1e-3 for v in ws[3:]),
            native_rate_hz=float(rate.value) or None, buttons=spec.buttons if spec else 2,
            calibration="done" if cal == HD_CALIBRATION_OK else "needed", clock="device", sdk_units="mm, N",
            source="the device's own HD_NOMINAL_* figures (pyopenhaptics / libHD); CHAI3D's for the model where "
                   "it states none")

    # -- the servo side (runs in OpenHaptics' thread) ----------------------------------------
    def schedule(self, callback_address: int, user_data: int | None) -> int:
        """Schedule ``callback_address`` (an ``HDCallbackCode (*)(void*)``) on the servo thread
        at the highest priority, with ``user_data`` as its ``void*``; the Python callback is
        unscheduled first (one callback drives the device). The compiled tick schedules itself
        here. Returns the scheduler's handle."""
        if self._sched is not None:
            self._lib.hdUnschedule(self._sched)
        self._sched = int(self._lib.hdScheduleAsynchronous(callback_address, user_data, HD_MAX_SCHEDULER_PRIORITY))
        return self._sched

    def schedule_python(self) -> int:
        """Schedule this driver's own Python callback again (the mailbox of ``read`` / ``write``)."""
        return self.schedule(ctypes.cast(self._cb, ctypes.c_void_p).value, None)

    def _servo(self, _data) -> int:
        lib, h, st, cm = self._lib, self._h, self.state, self.command
        self.tick_ns[int(st[S_TICK]) % TICK_RING] = _monotonic_ns()
        lib.hdBeginFrame(h)
        lib.hdGetDoublev(HD_CURRENT_TRANSFORM, self._m)
        lib.hdGetDoublev(HD_CURRENT_VELOCITY, self._v)
        lib.hdGetDoublev(HD_CURRENT_ANGULAR_VELOCITY, self._w)
        lib.hdGetIntegerv(HD_CURRENT_BUTTONS, self._b)
        # the command: the last whole one
        seq = cm[C_SEQ]
        if int(seq) & 1 == 0:
            self._cmd_taken[:] = cm
            if cm[C_SEQ] != seq:
                self._cmd_taken[C_SEQ] = self._last_seq  # torn: keep the last whole one
        tk = self._cmd_taken
        if tk[C_EPOCH] != self._epoch_seen:  # the loop re-armed: a new watchdog period
            self._epoch_seen = tk[C_EPOCH]
            self._since = 0
            st[S_CUT] = 0.0
        if tk[C_SEQ] != self._last_seq:
            self._last_seq = tk[C_SEQ]
            self._since = 0
        else:
            self._since += 1
        f = self._f
        if tk[C_ARMED] != 0.0 and st[S_CUT] == 0.0 and not (self._wd_ticks and self._since > self._wd_ticks):
            f[0], f[1], f[2] = tk[C_FORCE], tk[C_FORCE + 1], tk[C_FORCE + 2]
        else:
            if tk[C_ARMED] != 0.0 and st[S_CUT] == 0.0:
                st[S_CUT] = 1.0  # the device-side watchdog: latched until the loop re-arms
            f[0] = f[1] = f[2] = 0.0
        lib.hdSetDoublev(HD_CURRENT_FORCE, f)
        lib.hdEndFrame(h)
        err = lib.hdGetError().errorCode
        # the sample, under the counter
        st[S_SEQ] += 1.0
        m = self._m
        st[S_POS] = m[12] * 1e-3
        st[S_POS + 1] = m[13] * 1e-3
        st[S_POS + 2] = m[14] * 1e-3
        quat_from_matrix((m[0], m[4], m[8], m[1], m[5], m[9], m[2], m[6], m[10]), st, S_QUAT)
        st[S_VEL] = self._v[0] * 1e-3
        st[S_VEL + 1] = self._v[1] * 1e-3
        st[S_VEL + 2] = self._v[2] * 1e-3
        st[S_W] = self._w[0]
        st[S_W + 1] = self._w[1]
        st[S_W + 2] = self._w[2]
        st[S_BUTTONS] = self._b.value
        st[S_ERROR] = err
        st[S_EPOCH] = self._epoch_seen
        st[S_TICK] += 1.0
        st[S_SEQ] += 1.0
        return HD_CALLBACK_CONTINUE

    # -- the loop side ------------------------------------------------------------------------
    def _post(self, fx: float, fy: float, fz: float, armed: float, new_epoch: bool = False) -> None:
        cm = self.command
        cm[C_SEQ] += 1.0
        cm[C_FORCE] = fx
        cm[C_FORCE + 1] = fy
        cm[C_FORCE + 2] = fz
        cm[C_ARMED] = armed
        if new_epoch:
            cm[C_EPOCH] += 1.0
        cm[C_SEQ] += 1.0

    def _io_read(self, row: np.ndarray) -> int:
        st = self.state
        while True:
            s1 = st[S_SEQ]
            if int(s1) & 1:
                continue
            row[0:3] = st[S_POS:S_POS + 3]
            row[3:7] = st[S_QUAT:S_QUAT + 4]
            row[7:10] = st[S_VEL:S_VEL + 3]
            row[10:13] = st[S_W:S_W + 3]
            tick, err, cut, epoch = st[S_TICK], st[S_ERROR], st[S_CUT], st[S_EPOCH]
            self.buttons = int(st[S_BUTTONS])
            if st[S_SEQ] == s1:
                break
        row[13:19] = np.nan
        # the stylus' buttons (HD_CURRENT_BUTTONS, sampled in the servo tick); a Touch has no gripper
        row[DS_BUTTONS] = self.buttons
        row[DS_GRIPPER] = row[DS_GRIPPER_RATE] = np.nan
        now = self._clock()
        row[19] = now * 1e-9
        if tick != self._last_tick:
            self._last_tick = tick
            self._last_tick_ns = now
        elif now - self._last_tick_ns > self._stale_ns:
            return DEV_FAULT_LINK  # no servo tick for stale_s: the servo thread is not run
        if err:
            return DEV_FAULT_LINK if err == HD_COMM_ERROR else DEV_FAULT_HARDWARE
        if cut and self._enabled and epoch == self.command[C_EPOCH]:  # (a cut before the last enable: old news)
            return DEV_FAULT_WATCHDOG
        return DEV_OK

    def _io_write(self, wrench: np.ndarray) -> int:
        live = self._enabled and self._fault == DEV_OK
        self._post(float(wrench[0]), float(wrench[1]), float(wrench[2]), 1.0 if live else 0.0)
        return DEV_OK

    # -- the compiled servo (``server/servo.py``): the tick itself runs in the servo thread ----
    _x = None

    def servo_io(self) -> dict:
        """The device's C functions for the haptic tick run in the servo thread (``hd_native``):
        ``begin``, ``read``, ``write``, ``end`` and their context ``ctx`` (addresses). From the
        first call on, enabling and disabling arm the compiled write (``X_ARMED``) and its faults
        are the frames' own (``X_ERROR``); schedule ``server.servo.SERVO_CALLBACK`` with
        :meth:`schedule` to replace the Python callback."""
        from . import hd_native

        if self._x is None:
            self._x, self._x_keep = hd_native.context(self._lib, self._h)
            self._x[hd_native.X_ARMED] = 1 if self._enabled else 0
        begin, read, write, end = hd_native.ADDRESSES
        return {"begin": begin, "read": read, "write": write, "end": end, "ctx": int(self._x.ctypes.data)}

    def _io_enable(self, on: bool) -> int:
        if self._x is not None:  # the compiled servo's context is the device's state now
            from . import hd_native

            x = self._x
            if on:
                err = int(x[hd_native.X_ERROR])
                if err:
                    x[hd_native.X_ERROR] = 0  # seen: the next frame says whether it persists
                    return DEV_FAULT_LINK if err == HD_COMM_ERROR else DEV_FAULT_HARDWARE
                self._lib.hdMakeCurrentDevice(self._h)
                self._lib.hdEnable(HD_FORCE_OUTPUT)
            x[hd_native.X_ARMED] = 1 if on else 0
            return DEV_OK
        if on:
            st = self.state
            stale = st[S_TICK] == self._last_tick and self._clock() - self._last_tick_ns > self._stale_ns
            if st[S_ERROR] or stale:
                return DEV_FAULT_LINK if st[S_ERROR] in (0.0, HD_COMM_ERROR) else DEV_FAULT_HARDWARE
            self._lib.hdMakeCurrentDevice(self._h)
            self._lib.hdEnable(HD_FORCE_OUTPUT)
            self._post(0.0, 0.0, 0.0, 0.0, new_epoch=True)
        else:
            self._post(0.0, 0.0, 0.0, 0.0)
        return DEV_OK

    buttons = 0

    def _io_close(self) -> None:
        lib = self._lib
        lib.hdStopScheduler()
        if self._sched is not None:
            lib.hdUnschedule(self._sched)
        lib.hdDisableDevice(self._h)


def make_touch_device(config: dict, *, period_s: float, clock_ns=None) -> TouchDevice:
    """Entry point ``touch`` (see the module docstring)."""
    return TouchDevice(config, period_s=period_s, clock_ns=clock_ns)


make_touch_device.effective_config = effective_config
make_touch_device.kinds = ("spatial",)

#: for `hapticproxy plugins` and `hapticproxy devices`
make_touch_device.about = {"clock": "device", "package": "pyopenhaptics", "module": "pyOpenHaptics", "sdk": "OpenHaptics (libHD.so)", "models": sorted(models.TOUCH)}
