"""What the vendor drivers (``forcedimension``, ``haply``, ``touch``) share: the safety contract
of :mod:`.base` kept once, above each vendor's own I/O.

:class:`VendorDevice` keeps the latched fault, the enable state, the refusal of non-finite
commands, the caps (per axis and on the norm; parts the model does not actuate are dropped) and
the driver's watchdog on the loop's clock, and the frozen-position watch (:mod:`.frozen`: the
position bit-identical under force, a sensor that stopped, latched as ``DEV_FAULT_FROZEN``); a
vendor driver implements four methods over its SDK:

``_io_read(row) -> int``
    Fill the state row (pose, twist, time; hand NaN: no force sensor); ``DEV_OK`` or a fault code.
``_io_write(wrench) -> int``
    Send ``wrench`` (already checked, capped and masked; zeros when the output is off).
``_io_enable(on) -> int``
    Switch the device's force output (``dhdEnableForce``; a no-op where the SDK has none).
``_io_close()``
    Release the device (output zeroed first by :meth:`close`).

A fault the device reports (unplugged, an SDK error, its firmware watchdog) is latched as
``DEV_FAULT_LINK``, ``DEV_FAULT_HARDWARE`` or ``DEV_FAULT_WATCHDOG`` and the output zeroed at
once; only ``enable()`` clears it, and only when the device answers again (``_io_enable``
succeeds). Per step: no allocation that outlives the call (ctypes and the SDKs make temporaries).

:func:`missing` builds the one line a server prints when a vendor package or SDK is absent.
"""
from __future__ import annotations

import math
import time

import numpy as np

from . import frozen as fz
from .base import (
    DEV_FAULT_DISABLED, DEV_FAULT_FROZEN, DEV_FAULT_NAMES, DEV_FAULT_NONFINITE_COMMAND, DEV_FAULT_WATCHDOG, DEV_NSTATE, DEV_OK,
    DeviceDriver, DeviceInfo, DeviceLimits,
)


class DeviceUnavailable(ValueError):
    """The driver cannot reach its device: the message is the one line the user reads (cause
    and fix). A ``ValueError`` starting with ``device.<key>:`` so the server reports it as a
    configuration problem (exit 2)."""


def check_force_cap(asked: float, info: DeviceInfo) -> float | None:
    """The config's ``max_force_n`` (0: none) against the device's continuous force: ``None`` to
    use the device's, the value when lower, ``DeviceUnavailable`` naming the nearest safe value
    when higher (a config never gets more than the device renders continuously)."""
    if not asked:
        return None
    if asked > info.max_force_n:
        raise DeviceUnavailable(f"device.max_force_n: {asked:g} N is above the {info.model}'s continuous force "
                                f"({info.max_force_n:g} N): at most {info.max_force_n:g} (0: the device's own)")
    return asked


def missing(driver: str, package: str, *, extra: str = "", variable: str = "") -> DeviceUnavailable:
    """``device.driver: <driver> needs <package> (pip install ...); set <variable>``."""
    how = f"pip install 'hapticproxy[devices]' (or: pip install {package})"
    tail = f"; then set {variable}" if variable else ""
    more = f" {extra}" if extra else ""
    return DeviceUnavailable(f"device.driver: {driver} needs the Python package {package}, which is not installed: "
                             f"{how}{tail}{more}")


class VendorDevice(DeviceDriver):
    """A real device behind a vendor SDK (see the module docstring). Starts disabled."""

    kind = "spatial"

    def __init__(self, info: DeviceInfo, limits: DeviceLimits, *, clock_ns=None) -> None:
        self._info = info
        self._limits = limits
        self._clock = clock_ns if clock_ns is not None else time.monotonic_ns
        self._enabled = False
        self._fault = DEV_OK
        self._wd_ns = int(round(limits.watchdog_s * 1e9))
        self._last_write_ns = 0
        self._mask = np.array(info.wrench_mask, dtype=np.float64)
        self._cmd = np.zeros(6)
        self._zero = np.zeros(6)
        self._sent = np.zeros(6)
        self.counters = {"reads": 0, "writes": 0, "saturated": 0, "nonfinite_refused": 0, "watchdog_trips": 0,
                         "device_faults": 0, "frozen_trips": 0}
        self._closed = False
        # the frozen-position watch on the driver's own readings (``frozen``): also standalone, a
        # driver never pushes on a sensor that stopped; the loop sets it from [safety]
        self._fp = np.zeros(fz.NFP)
        self._fs = np.zeros(fz.NFS)
        self.watch_frozen(fz.FROZEN_S, fz.min_force_n(0.0, limits.max_force_norm_n))

    def watch_frozen(self, frozen_s: float, min_force_n: float) -> None:
        """Trip ``DEV_FAULT_FROZEN`` when the position stays bit-identical for ``frozen_s`` while
        at least ``min_force_n`` was written (0 s: off). Compiles the watch now, never in a step."""
        fz.set_parameters(self._fp, 0, frozen_s=frozen_s, min_force_n=min_force_n)
        fz.reset(self._fs, 0)
        fz.watch(self._fp, 0, self._fs, 0, self._fs, self._sent, self._clock())
        fz.reset(self._fs, 0)

    # -- DeviceDriver -----------------------------------------------------------------------
    @property
    def limits(self) -> DeviceLimits:
        return self._limits

    @property
    def info(self) -> DeviceInfo:
        return self._info

    @property
    def enabled(self) -> bool:
        return self._enabled

    @property
    def fault(self) -> int:
        return self._fault

    def enable(self) -> None:
        """Arm the output; a latched fault clears only if the device takes ``enable`` again."""
        if self._io_enable(True) != DEV_OK:
            return
        self._fault = DEV_OK
        self._enabled = True
        self._last_write_ns = self._clock()

    def disable(self) -> None:
        self._enabled = False
        if not self._closed:
            self._io_write(self._zero)
            self._sent[:] = 0.0
            self._io_enable(False)

    def read(self, state_out: np.ndarray) -> int:
        now = self._clock()
        self._watchdog(now)
        self.counters["reads"] += 1
        rc = self._io_read(state_out)
        if rc != DEV_OK:
            self._trip(rc)
        elif self._enabled and self._fault == DEV_OK and fz.watch(self._fp, 0, self._fs, 0, state_out, self._sent, now):
            self.counters["frozen_trips"] += 1
            self._trip(DEV_FAULT_FROZEN)
        return self._status()

    def write(self, wrench: np.ndarray) -> int:
        now = self._clock()
        self._watchdog(now)
        self._last_write_ns = now
        self.counters["writes"] += 1
        w = wrench
        if not (math.isfinite(w[0]) and math.isfinite(w[1]) and math.isfinite(w[2])
                and math.isfinite(w[3]) and math.isfinite(w[4]) and math.isfinite(w[5])):
            self.counters["nonfinite_refused"] += 1
            if self._fault == DEV_OK:
                self._fault = DEV_FAULT_NONFINITE_COMMAND
        if self._enabled and self._fault == DEV_OK:
            out = self._capped(w)
        else:
            out = self._zero
        rc = self._io_write(out)
        self._sent[:] = out
        if rc != DEV_OK:
            self._trip(rc)
        return self._status()

    def close(self) -> None:
        if self._closed:
            return
        try:
            self.disable()
        finally:
            self._closed = True
            self._io_close()

    # -- shared logic ------------------------------------------------------------------------
    @property
    def last_command(self) -> np.ndarray:
        """The wrench sent to the device in the last ``write`` (after caps and mask)."""
        return self._sent.copy()

    def status_text(self) -> str:
        return DEV_FAULT_NAMES.get(self._status(), f"fault {self._status()}")

    def _status(self) -> int:
        if self._fault != DEV_OK:
            return self._fault
        return DEV_OK if self._enabled else DEV_FAULT_DISABLED

    def _watchdog(self, now: int) -> None:
        if self._enabled and self._fault == DEV_OK and self._wd_ns > 0 and now - self._last_write_ns > self._wd_ns:
            self.counters["watchdog_trips"] += 1
            self._trip(DEV_FAULT_WATCHDOG)

    def _trip(self, code: int) -> None:
        """Latch ``code`` and zero the output now (the device may not answer: best effort)."""
        if self._fault == DEV_OK:
            self._fault = code
            if code != DEV_FAULT_WATCHDOG:
                self.counters["device_faults"] += 1
            self._io_write(self._zero)
            self._sent[:] = 0.0

    def _capped(self, w: np.ndarray) -> np.ndarray:
        """``w`` masked to what the device renders, each axis and the norm within the limits."""
        c = self._cmd
        lim = self._limits
        sat = False
        for i in range(6):
            cap = lim.max_force_n if i < 3 else lim.max_torque_n_m
            v = w[i] * self._mask[i]
            if v > cap:
                v = cap
                sat = True
            elif v < -cap:
                v = -cap
                sat = True
            c[i] = v
        for base, cap in ((0, lim.max_force_norm_n), (3, lim.max_torque_norm_n_m)):
            n = math.sqrt(c[base] * c[base] + c[base + 1] * c[base + 1] + c[base + 2] * c[base + 2])
            if n > cap:
                s = cap / n
                c[base] *= s
                c[base + 1] *= s
                c[base + 2] *= s
                sat = True
        if sat:
            self.counters["saturated"] += 1
        return c

    # -- the vendor's part -------------------------------------------------------------------
    def _io_read(self, row: np.ndarray) -> int:  # pragma: no cover - interface
        raise NotImplementedError

    def _io_write(self, wrench: np.ndarray) -> int:  # pragma: no cover - interface
        raise NotImplementedError

    def _io_enable(self, on: bool) -> int:
        return DEV_OK

    def _io_close(self) -> None:
        pass


def quat_from_matrix(r, out: np.ndarray, at: int) -> None:
    """The unit quaternion (w x y z) of the rotation matrix ``r`` (3x3, row-major sequence of 9
    or a 3x3 array) into ``out[at:at + 4]`` (Shepperd's method: stable for every rotation)."""
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = (float(v) for v in np.ravel(r)[:9])
    tr = r00 + r11 + r22
    if tr > 0.0:
        s = 2.0 * math.sqrt(tr + 1.0)
        w, x, y, z = 0.25 * s, (r21 - r12) / s, (r02 - r20) / s, (r10 - r01) / s
    elif r00 > r11 and r00 > r22:
        s = 2.0 * math.sqrt(1.0 + r00 - r11 - r22)
        w, x, y, z = (r21 - r12) / s, 0.25 * s, (r01 + r10) / s, (r02 + r20) / s
    elif r11 > r22:
        s = 2.0 * math.sqrt(1.0 + r11 - r00 - r22)
        w, x, y, z = (r02 - r20) / s, (r01 + r10) / s, 0.25 * s, (r12 + r21) / s
    else:
        s = 2.0 * math.sqrt(1.0 + r22 - r00 - r11)
        w, x, y, z = (r10 - r01) / s, (r02 + r20) / s, (r12 + r21) / s, 0.25 * s
    n = math.sqrt(w * w + x * x + y * y + z * z)
    if w < 0.0:
        n = -n
    out[at] = w / n
    out[at + 1] = x / n
    out[at + 2] = y / n
    out[at + 3] = z / n


__all__ = ["DEV_NSTATE", "DeviceUnavailable", "VendorDevice", "missing", "quat_from_matrix"]
