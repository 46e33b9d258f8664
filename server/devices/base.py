"""The device-driver interface: what the haptic loop needs from a haptic device.

One state layout for every device kind, so the loop and the controllers never branch on the
driver: ``read`` fills a preallocated float64 row, ``write`` takes a 6-vector wrench.

State row (``float64[DEV_NSTATE]``), world frame, at the device handle (the point the user
holds, which the loop maps onto the proxy's hand point):

=========  =====  ======================================================================
columns    name   meaning
=========  =====  ======================================================================
0:7        pose   x y z [m], then unit quaternion qw qx qy qz (handle orientation)
7:13       twist  linear velocity [m/s] (3), angular velocity [rad/s] (3)
13:19      hand   wrench the user's hand applies to the handle [N, N m], as a force sensor
                  measures it; NaN in all six if the device has no sensor
19         time   device clock [s] of this sample
=========  =====  ======================================================================

A 1-DOF device moves along its ``axis`` (world, unit) only: pose is ``origin + x axis`` with
identity orientation; a planar device moves in world x-y and turns about +z (z = 0, quaternion
about z). Only the components a kind can move in matter; the others are zero.

Commands are wrenches in the same frame at the same point; components a kind cannot render
are ignored by the driver. ``write`` is the *last* thing the loop does in a step; a simulated
device advances its own dynamics by one haptic period inside ``write``.

Safety contract every driver keeps (the loop relies on it):
- ``write`` of a non-finite wrench is refused: zero is rendered and a fault is latched;
- ``disable()`` zeroes the output at once and keeps it zero until ``enable()``; while disabled,
  ``read`` and ``write`` return a non-OK status (the latched fault's code, else
  ``DEV_FAULT_DISABLED``), never ``DEV_OK``: the loop takes a non-OK status as "not rendering"
  (the contract's ``disable`` rule checks it);
- a driver whose hardware has its own watchdog (``limits.watchdog_s``) zeroes its output when
  no ``write`` arrives within that time and latches the fault: forces never come back by
  themselves, only through ``enable()``. The loop holds a stall of its own at least that long
  to be such a trip while it renders force (it disables the device), whether or not the
  driver saw it: a driver or device program that was late itself changes nothing.
"""
from __future__ import annotations

import abc
from dataclasses import dataclass

import numpy as np

from ...protocol.devlink import ROW_COLUMNS, ROW_FLOATS, DeviceFault
from ...protocol.registry import Registry
from ...protocol.vocab import DEVICE_KINDS  # noqa: F401 - re-exported

# The state row and the status codes are the remote-device link's (protocol/devlink.py): one set
# of numbers for every driver and for the wire.
DS_POSE, DS_TWIST, DS_HAND, DS_TIME = (c.start for c in ROW_COLUMNS)
DEV_NSTATE = ROW_FLOATS
#: Wrench components a kind renders (the rest are ignored): fx fy fz tx ty tz.
KIND_WRENCH_MASK = {
    "1dof": (1, 1, 1, 0, 0, 0),  # the projection on the axis
    "planar": (1, 1, 0, 0, 0, 1),
    "spatial": (1, 1, 1, 1, 1, 1),
}

#: Status codes returned by ``read``/``write`` (0 = fine). A non-zero code is a latched fault.
DEV_OK = int(DeviceFault.OK)
DEV_FAULT_NONFINITE_COMMAND = int(DeviceFault.NONFINITE_COMMAND)
DEV_FAULT_WATCHDOG = int(DeviceFault.WATCHDOG)
DEV_FAULT_DISABLED = int(DeviceFault.DISABLED)
DEV_FAULT_LINK = int(DeviceFault.LINK)  # remote device: no state within its timeout
DEV_FAULT_HARDWARE = int(DeviceFault.HARDWARE)
DEV_FAULT_NAMES = {
    DEV_OK: "ok",
    DEV_FAULT_NONFINITE_COMMAND: "non-finite command",
    DEV_FAULT_WATCHDOG: "device watchdog: no command within watchdog_s",
    DEV_FAULT_DISABLED: "disabled",
    DEV_FAULT_LINK: "device link lost",
    DEV_FAULT_HARDWARE: "hardware fault",
}


@dataclass(frozen=True)
class DeviceLimits:
    """What the hardware can do; the loop's safety layer never commands more."""

    max_force_n: float  # per translational axis
    max_torque_n_m: float  # per rotational axis
    max_speed_m_per_s: float
    max_angular_speed_rad_per_s: float
    workspace_min_m: tuple = (-0.2, -0.2, -0.2)
    workspace_max_m: tuple = (0.2, 0.2, 0.2)
    #: The driver's own watchdog (0 = none): no ``write`` for this long -> zero output, latched.
    watchdog_s: float = 0.05


class DeviceDriver(abc.ABC):
    """A haptic device. Thin: it owns its arrays; ``read``/``write`` allocate nothing."""

    #: "1dof", "planar" or "spatial"
    kind: str = "spatial"
    #: name the driver was registered under (entry point), for status and logs
    name: str = "device"

    @property
    @abc.abstractmethod
    def limits(self) -> DeviceLimits: ...

    @abc.abstractmethod
    def enable(self) -> None:
        """Arm the output (clears a latched fault if its cause is gone)."""

    @abc.abstractmethod
    def disable(self) -> None:
        """Zero the output now and keep it zero until ``enable``."""

    @property
    @abc.abstractmethod
    def enabled(self) -> bool: ...

    @property
    @abc.abstractmethod
    def fault(self) -> int:
        """Latched fault code (``DEV_OK`` if none); ``DEV_FAULT_NAMES`` says what it means."""

    @abc.abstractmethod
    def read(self, state_out: np.ndarray) -> int:
        """Fill ``state_out`` (float64[DEV_NSTATE]); return the status code."""

    @abc.abstractmethod
    def write(self, wrench: np.ndarray) -> int:
        """Command ``wrench`` (float64[6], N and N m, world frame at the handle); return the status:
        ``DEV_OK`` only while enabled and rendering, else the latched fault or ``DEV_FAULT_DISABLED``."""

    def on_engage(self) -> None:
        """A new session engaged the loop (called once per engagement, outside the hot path).
        Real hardware ignores it; a simulated hand starts its script here."""

    def close(self) -> None:
        """Release the hardware (output zeroed first)."""
        self.disable()


#: the entry-point group device drivers register in
DEVICE_GROUP = "hapticproxy.devices"
#: the built-in drivers (name -> module:factory); a lab's package adds its own through
#: ``[project.entry-points."hapticproxy.devices"] mydev = "mypkg:make_device"``
DEVICES = {
    "sim": "hapticproxy.server.devices.sim:make_sim_device",
    "remote": "hapticproxy.server.devices.remote:make_remote_device",
}


def _is_factory(name: str, obj) -> str:
    return "" if callable(obj) else "is not callable (a device factory)"


#: device drivers by name: :data:`DEVICES` merged with the ``hapticproxy.devices`` entry points
DEVICE_REGISTRY = Registry("device", DEVICE_GROUP, DEVICES, check=_is_factory, field="device.driver")


def device_factory(name: str):
    """The factory registered as ``name`` (imported now); ``ValueError`` starting with
    ``device.driver:`` naming the choices when it is unknown or does not load."""
    return DEVICE_REGISTRY.load(name)


def load_device(name: str, config: dict, *, period_s: float, clock_ns=None) -> DeviceDriver:
    """Build the driver registered as ``name`` (:data:`DEVICE_REGISTRY`).

    The factory is called as ``factory(config, period_s=..., clock_ns=...)`` where ``config`` is
    the ``[device]`` table of the server config (a dict) and ``clock_ns`` a callable returning
    the loop's clock in ns (the injected clock; ``None`` means ``time.monotonic_ns``).
    Raises ``ValueError`` naming the choices when ``name`` is unknown.
    """
    dev = device_factory(name)(config, period_s=period_s, clock_ns=clock_ns)
    if not isinstance(dev, DeviceDriver):
        raise ValueError(f"device.driver: {name!r} did not build a DeviceDriver (got {type(dev).__name__})")
    if dev.kind not in DEVICE_KINDS:
        raise ValueError(f"device.driver: {name!r} has unknown kind {dev.kind!r}")
    return dev


def empty_state() -> np.ndarray:
    """A state row with NaN hand wrench and identity orientation (for initialisation)."""
    s = np.zeros(DEV_NSTATE)
    s[DS_POSE + 3] = 1.0
    s[DS_HAND:DS_HAND + 6] = np.nan
    return s
