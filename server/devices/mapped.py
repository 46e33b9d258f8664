"""Any driver seen through a workspace mapping (:mod:`.mapping`): what ``load_device`` builds when
``[device]`` asks for one (``workspace_scale``, ``workspace_offset_m``, ``workspace_rotation``,
``clutch_button``).

:class:`MappedDevice` is a :class:`~.base.DeviceDriver` around another: ``read`` is the inner
driver's read then ``mapping.map_state`` (device frame -> scene), ``write`` is
``mapping.map_command`` (scene -> device, the clutch's gain) then the inner driver's write.
Everything else (enable, disable, faults, the watchdog, the device's own caps in its units) is
the inner driver's: the mapping only changes coordinates, never the safety contract (a
non-finite wrench reaches the inner driver non-finite, which refuses it and latches).

Its ``limits`` are the inner device's in the scene's units (forces and speeds times the scale,
the workspace box mapped), so the controller's caps, taken as the lower of ``[safety]`` and
these, keep the device within its own caps; its ``info`` is the inner device's (figures in the
device's units: by the mapping's force rule the configured gains are felt as they are, so
``safe.py`` compares them with the device's figures directly).

The haptic loop does not call this wrapper's ``read`` / ``write``: it holds the array the loop's
tick maps with. The loop drives ``inner`` as it would drive it unmapped (a simulated device's
``tick_arrays``, a device-clocked one's ``servo_io``, a Python driver's ``read`` / ``write``) and
the compiled tick runs ``map_state`` after the read and ``map_command`` before the write on
``mapping`` (``server/tick.py``, ``TK_MAPPED``), so the clutch's state in it is the tick's. Its
own ``read`` / ``write`` are the same kernels on the same array, for a caller outside the loop's
tick (the driver contract, the loop's re-index at an engagement).
"""
from __future__ import annotations

import itertools

import numpy as np

from . import mapping as mp
from .base import DeviceDriver, DeviceInfo, DeviceLimits


class MappedDevice(DeviceDriver):
    """``inner`` through the mapping array ``m`` (:func:`.mapping.parse_mapping`)."""

    def __init__(self, inner: DeviceDriver, m: np.ndarray) -> None:
        self.inner = inner
        self.kind = inner.kind
        self.name = inner.name
        #: the mapping array the kernels work on (``mapping.M_*``)
        self.mapping = m
        self._out = np.zeros(6)
        mp.warm_up()
        s = float(m[mp.M_SCALE])
        lim = inner.limits
        R = m[mp.M_R:mp.M_R + 9].reshape(3, 3)
        lo = np.zeros(3)
        hi = np.zeros(3)
        wlo, whi = list(lim.workspace_min_m), list(lim.workspace_max_m)
        n = len(wlo)
        wlo += [0.0] * (3 - n)
        whi += [0.0] * (3 - n)
        corners = np.array([[(wlo, whi)[c][i] for i, c in enumerate(bits)]
                            for bits in itertools.product((0, 1), repeat=3)])
        mapped = m[mp.M_OFF:mp.M_OFF + 3] + s * corners @ R.T
        lo, hi = mapped.min(axis=0), mapped.max(axis=0)
        self._limits = DeviceLimits(
            max_force_n=lim.max_force_n * s, max_torque_n_m=lim.max_torque_n_m,
            max_speed_m_per_s=lim.max_speed_m_per_s * s, max_angular_speed_rad_per_s=lim.max_angular_speed_rad_per_s,
            workspace_min_m=tuple(lo[:n].tolist()), workspace_max_m=tuple(hi[:n].tolist()), watchdog_s=lim.watchdog_s,
            max_force_norm_n=lim.max_force_norm_n * s, max_torque_norm_n_m=lim.max_torque_norm_n_m)

    # -- DeviceDriver ------------------------------------------------------------------------
    @property
    def limits(self) -> DeviceLimits:
        """The inner device's limits in the scene's units (module docstring)."""
        return self._limits

    @property
    def info(self) -> DeviceInfo:
        return self.inner.info

    @property
    def enabled(self) -> bool:
        return self.inner.enabled

    @property
    def fault(self) -> int:
        return self.inner.fault

    def enable(self) -> None:
        self.inner.enable()

    def disable(self) -> None:
        self.inner.disable()

    def read(self, state_out: np.ndarray) -> int:
        rc = self.inner.read(state_out)
        mp.map_state(state_out, self.mapping)
        return rc

    def write(self, wrench: np.ndarray) -> int:
        w = wrench
        if not (type(w) is np.ndarray and w.dtype == np.float64 and w.shape == (6,)):
            w = np.asarray(wrench, dtype=np.float64)
            if w.shape != (6,):
                raise ValueError(f"wrench: expected 6 numbers (fx fy fz tx ty tz), got shape {w.shape}")
        mp.map_command(w, self.mapping, self._out)
        return self.inner.write(self._out)

    def on_engage(self) -> None:
        self.inner.on_engage()

    def close(self) -> None:
        self.inner.close()

    # -- extras --------------------------------------------------------------------------------
    @property
    def clutched(self) -> bool:
        """The clutch is held (the device moves freely, the scene holds its pose)."""
        return self.mapping[mp.M_CLUTCHED] != 0.0

    @property
    def clutch_gain(self) -> float:
        """The command's gain (0 while clutched once faded, 1 outside a clutch)."""
        return float(self.mapping[mp.M_GAIN])

    def warm_up(self) -> None:
        mp.warm_up()
        warm = getattr(self.inner, "warm_up", None)
        if callable(warm):
            warm()

    #: the inner driver's extras that mean the same through the mapping (never ``tick_arrays``,
    #: ``servo_io`` or ``native``: whoever drives the device by them must map around it, as the
    #: loop's tick does with ``inner``'s)
    _PASSED = frozenset({"counters", "status_text", "last_command", "config", "identity", "spec", "hand",
                         "watch_frozen"})

    def __getattr__(self, name: str):
        if name in MappedDevice._PASSED:
            return getattr(self.__dict__["inner"], name)
        raise AttributeError(f"{type(self).__name__} has no attribute {name!r}")


def wrap_mapped(inner: DeviceDriver, mapping_table: dict, *, period_s: float) -> DeviceDriver:
    """``inner`` as it is when ``mapping_table`` asks for no mapping, else a :class:`MappedDevice`;
    ``ValueError("device.<key>: ...")`` for a mapping the device cannot take (a clutch button
    it does not have)."""
    _c, m = mp.parse_mapping(mapping_table, kind=inner.kind, period_s=period_s)
    if m is None:
        return inner
    bit = int(m[mp.M_CLUTCH_BIT])
    if bit >= 0:
        n = int(inner.info.buttons)
        if bit >= n:
            has = f"has {n} button{'s' * (n != 1)} (0..{n - 1})" if n else "has no buttons"
            raise ValueError(f"device.clutch_button: {bit} is not a button of this device: the {inner.info.model} "
                             f"{has}; -1: no clutch")
    return MappedDevice(inner, m)
