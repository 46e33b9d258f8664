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
20         buttons the device's buttons as a bit mask (bit i set while button i is held), an
                  integer in a float64; NaN if the device has no buttons
21:23      gripper the gripper's opening angle [rad], then its rate [rad/s]; NaN where the device
                  has no gripper or does not measure the rate
=========  =====  ======================================================================

The device's inputs (buttons, gripper) were appended after the time column (the state row's
earlier columns keep their numbers); the loop reads them and passes them on to the engine in
every ``ProxyState`` (``buttons``, ``gripper_angle_rad``, ``gripper_velocity_rad_per_s``,
``device_inputs``).

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
import importlib
import math
from dataclasses import dataclass, fields

import numpy as np

from ...protocol.devlink import ROW_COLUMNS, ROW_FLOATS, DeviceFault
from ...protocol.registry import Registry
from ...protocol.vocab import DEVICE_KINDS  # noqa: F401 - re-exported

# The state row and the status codes are the remote-device link's (protocol/devlink.py): one set
# of numbers for every driver and for the wire.
DS_POSE, DS_TWIST, DS_HAND, DS_TIME, DS_BUTTONS, DS_GRIPPER = (c.start for c in ROW_COLUMNS)
#: the gripper's rate (the second gripper column)
DS_GRIPPER_RATE = DS_GRIPPER + 1
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
DEV_FAULT_FROZEN = int(DeviceFault.FROZEN)  # no motion under force (``devices.frozen``)
DEV_FAULT_NAMES = {
    DEV_OK: "ok",
    DEV_FAULT_NONFINITE_COMMAND: "non-finite command",
    DEV_FAULT_WATCHDOG: "device watchdog: no command within watchdog_s",
    DEV_FAULT_DISABLED: "disabled",
    DEV_FAULT_LINK: "device link lost",
    DEV_FAULT_HARDWARE: "hardware fault",
    DEV_FAULT_FROZEN: "position frozen",
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
    #: cap on the norm of the commanded force [N] (a device's motors saturate together: a
    #: per-axis cap alone lets a diagonal command reach sqrt(3) times it); inf: per axis only
    max_force_norm_n: float = math.inf
    #: cap on the norm of the commanded torque [N m]
    max_torque_norm_n_m: float = math.inf


#: who runs the haptic clock: the loop (a polled device: read/write when the loop wakes) or the
#: device (its SDK runs the servo thread and hands the loop its samples)
CLOCK_OWNERS = ("loop", "device")
#: what a device can sense or render, in the order of a wrench: position (force), rotation
#: (torque), gripper (gripper force)
DOF_PARTS = ("position", "rotation", "gripper")


@dataclass(frozen=True)
class DeviceInfo:
    """What a device is (CHAI3D's ``cHapticDeviceInfo``, plus what the loop needs to know).

    Figures a vendor does not state are ``None`` (never a guess); ``source`` says where the
    figures come from (the device's own queries, a vendor table, the config). ``sensed`` and
    ``actuated`` name the parts of :data:`DOF_PARTS` the device measures and renders: a Touch
    senses position and rotation (6 DOF) and renders position only (3), so its
    :attr:`wrench_mask` has no torque and :func:`DeviceLimits` derived from it cap torque at 0.
    """

    model: str
    vendor: str
    driver: str
    serial: str = ""
    sensed: tuple = ("position",)
    actuated: tuple = ("position",)
    #: continuous (rated) force at the handle [N]; what the caps never exceed
    max_force_n: float = 0.0
    #: peak force [N] (None: not stated)
    peak_force_n: float | None = None
    max_torque_n_m: float = 0.0
    max_gripper_force_n: float = 0.0
    #: the stiffest spring the device renders stably at its native rate [N/m] (None: not stated)
    max_stiffness_n_per_m: float | None = None
    max_damping_n_s_per_m: float | None = None
    max_rot_stiffness_n_m_per_rad: float | None = None
    max_rot_damping_n_m_s_per_rad: float | None = None
    #: the mass moving with the handle [kg], without the hand (None: not stated); bounds the
    #: coupling's stiffness and damping at the loop's rate (``server/devices/safe.py``)
    moving_mass_kg: float | None = None
    #: the smallest principal moment of inertia moving with the handle [kg m^2] (None: not
    #: stated; the passivity layer's work prediction, ``server/passivity.py``)
    moving_inertia_kg_m2: float | None = None
    #: the largest principal moment of inertia moving with the handle [kg m^2] (None: not stated;
    #: the heavy-tool rule's rotational handle, ``stability.rot_coupling_damping_for_tool``, which
    #: then takes the smallest)
    moving_inertia_max_kg_m2: float | None = None
    #: the handle's physical viscous damping [N s/m] and rotational [N m s/rad], the least the
    #: device itself dissipates (None: not stated); what it dissipates feeds the passivity
    #: layer's tank (``server/passivity.py``: ``damping_figures``)
    damping_n_s_per_m: float | None = None
    rot_damping_n_m_s_per_rad: float | None = None
    #: radius of the sphere the handle reaches [m]
    workspace_radius_m: float | None = None
    workspace_min_m: tuple = (-0.1, -0.1, -0.1)
    workspace_max_m: tuple = (0.1, 0.1, 0.1)
    #: the rate the device's own loop runs at [Hz] (None: polled, as fast as it is asked)
    native_rate_hz: float | None = None
    gripper: bool = False
    buttons: int = 0
    #: "not needed", "needed" (the device must be calibrated before use), "done"
    calibration: str = "not needed"
    #: "loop" or "device" (:data:`CLOCK_OWNERS`)
    clock: str = "loop"
    #: the units the SDK speaks (the driver converts to m, N, rad)
    sdk_units: str = "m, N"
    #: handedness ("right", "left", "" when both or not stated)
    hand: str = ""
    source: str = ""
    #: how many coordinates "position" and "rotation" each are on this device: 3 and 3 for a
    #: spatial one, 2 and 1 for a planar one (x, y and the turn about z), 1 and 0 for one axis
    position_dof: int = 3
    rotation_dof: int = 3

    def __post_init__(self) -> None:
        if self.clock not in CLOCK_OWNERS:
            raise ValueError(f"clock: expected one of {CLOCK_OWNERS}, got {self.clock!r}")
        for name in ("sensed", "actuated"):
            bad = [p for p in getattr(self, name) if p not in DOF_PARTS]
            if bad:
                raise ValueError(f"{name}: unknown parts {bad} (known: {DOF_PARTS})")

    def _dof(self, parts) -> int:
        return (self.position_dof * ("position" in parts) + self.rotation_dof * ("rotation" in parts)
                + ("gripper" in parts))

    @property
    def dof_sensed(self) -> int:
        return self._dof(self.sensed)

    @property
    def dof_actuated(self) -> int:
        return self._dof(self.actuated)

    @property
    def wrench_mask(self) -> tuple:
        """Which of fx fy fz tx ty tz the device renders (1) or ignores (0)."""
        f = int("position" in self.actuated)
        t = int("rotation" in self.actuated)
        return (f, f, f, t, t, t)

    def limits(self, *, max_speed_m_per_s: float = 2.0, max_angular_speed_rad_per_s: float = 20.0,
               watchdog_s: float = 0.0, max_force_n: float | None = None) -> DeviceLimits:
        """The safety layer's view: caps at the continuous force (per axis and on the norm; a
        lower ``max_force_n`` from the config wins), torque 0 where rotation is not actuated."""
        f = self.max_force_n if max_force_n is None else min(max_force_n, self.max_force_n)
        t = self.max_torque_n_m if "rotation" in self.actuated else 0.0
        return DeviceLimits(max_force_n=f, max_torque_n_m=t, max_speed_m_per_s=max_speed_m_per_s,
                            max_angular_speed_rad_per_s=max_angular_speed_rad_per_s,
                            workspace_min_m=tuple(self.workspace_min_m), workspace_max_m=tuple(self.workspace_max_m),
                            watchdog_s=watchdog_s, max_force_norm_n=f, max_torque_norm_n_m=t)

    def as_dict(self) -> dict:
        d = {f.name: getattr(self, f.name) for f in fields(self)}
        d.update(dof_sensed=self.dof_sensed, dof_actuated=self.dof_actuated, wrench_mask=list(self.wrench_mask))
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in d.items()}

    def summary(self) -> str:
        """One line: model, serial, DOF, force, clock (``status`` and ``plugins`` show it)."""
        serial = f" #{self.serial}" if self.serial else ""
        parts = [f"{self.vendor} {self.model}{serial}".strip(),
                 f"{self.dof_sensed} DOF sensed / {self.dof_actuated} rendered",
                 f"{self.max_force_n:g} N" + (f" (peak {self.peak_force_n:g})" if self.peak_force_n else "")]
        if self.max_torque_n_m and "rotation" in self.actuated:
            parts.append(f"{self.max_torque_n_m:g} N m")
        if self.max_stiffness_n_per_m:
            parts.append(f"<= {self.max_stiffness_n_per_m:g} N/m")
        if self.native_rate_hz:
            parts.append(f"{self.native_rate_hz:g} Hz native")
        if self.gripper:
            parts.append("gripper")
        if self.buttons:
            parts.append(f"{self.buttons} buttons")
        if self.calibration != "not needed":
            parts.append(f"calibration {self.calibration}")
        parts.append(f"clock: {self.clock}")
        return ", ".join(parts)


def info_from_limits(kind: str, limits: DeviceLimits, *, model: str, vendor: str, driver: str,
                     source: str = "config", clock: str = "loop") -> DeviceInfo:
    """The info of a device known only by its kind and limits (a simulated or remote one)."""
    sensed = {"1dof": ("position",), "planar": ("position", "rotation"), "spatial": ("position", "rotation")}[kind]
    pos, rot = {"1dof": (1, 0), "planar": (2, 1), "spatial": (3, 3)}[kind]
    return DeviceInfo(model=model, vendor=vendor, driver=driver, sensed=sensed, actuated=sensed,
                      position_dof=pos, rotation_dof=rot,
                      max_force_n=limits.max_force_n, max_torque_n_m=limits.max_torque_n_m,
                      workspace_min_m=tuple(limits.workspace_min_m), workspace_max_m=tuple(limits.workspace_max_m),
                      clock=clock, source=source)


class DeviceDriver(abc.ABC):
    """A haptic device. Thin: it owns its arrays; ``read``/``write`` allocate nothing."""

    #: "1dof", "planar" or "spatial"
    kind: str = "spatial"
    #: name the driver was registered under (entry point), for status and logs
    name: str = "device"

    @property
    @abc.abstractmethod
    def limits(self) -> DeviceLimits: ...

    @property
    def info(self) -> DeviceInfo:
        """What the device is (:class:`DeviceInfo`). A driver that does not declare it is
        described by its kind and limits."""
        return info_from_limits(self.kind, self.limits, model=self.kind, vendor="", driver=self.name,
                                source="kind and limits")

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
    "forcedimension": "hapticproxy.server.devices.forcedimension:make_forcedimension_device",
    "haply": "hapticproxy.server.devices.haply:make_haply_device",
    "touch": "hapticproxy.server.devices.touch:make_touch_device",
}


def _is_factory(name: str, obj) -> str:
    return "" if callable(obj) else "is not callable (a device factory)"


#: device drivers by name: :data:`DEVICES` merged with the ``hapticproxy.devices`` entry points
DEVICE_REGISTRY = Registry("device", DEVICE_GROUP, DEVICES, check=_is_factory, field="device.driver")


def device_factory(name: str):
    """The factory registered as ``name`` (imported now); ``ValueError`` starting with
    ``device.driver:`` naming the choices when it is unknown or does not load."""
    return DEVICE_REGISTRY.load(name)


#: what wraps a driver in a workspace mapping (``mapped.py``; loaded by name as the drivers are)
MAPPED = "hapticproxy.server.devices.mapped:wrap_mapped"
#: the ``[device]`` keys of the workspace mapping (``mapping.MAPPING_KEYS``): not the driver's
MAPPING_KEYS = ("workspace_scale", "workspace_offset_m", "workspace_rotation", "clutch_button", "clutch_ramp_s")


def load_device(name: str, config: dict, *, period_s: float, clock_ns=None) -> DeviceDriver:
    """Build the driver registered as ``name`` (:data:`DEVICE_REGISTRY`).

    The factory is called as ``factory(config, period_s=..., clock_ns=...)`` where ``config`` is
    the ``[device]`` table of the server config (a dict) without the mapping's keys
    (:data:`MAPPING_KEYS`) and ``clock_ns`` a callable returning the loop's clock in ns (the
    injected clock; ``None`` means ``time.monotonic_ns``). When the table asks for a workspace
    mapping (a scale, offset, rotation or clutch: ``mapping.py``), the driver is returned
    wrapped in it (``mapped.MappedDevice``). Raises ``ValueError`` naming the choices when
    ``name`` is unknown.
    """
    table = dict(config)
    mapping = {k: table.pop(k) for k in MAPPING_KEYS if k in table}
    dev = device_factory(name)(table, period_s=period_s, clock_ns=clock_ns)
    if not isinstance(dev, DeviceDriver):
        raise ValueError(f"device.driver: {name!r} did not build a DeviceDriver (got {type(dev).__name__})")
    if dev.kind not in DEVICE_KINDS:
        raise ValueError(f"device.driver: {name!r} has unknown kind {dev.kind!r}")
    if mapping:
        try:
            module, _, attr = MAPPED.partition(":")
            dev = getattr(importlib.import_module(module), attr)(dev, mapping, period_s=period_s)
        except BaseException:
            dev.close()
            raise
    return dev


def empty_state() -> np.ndarray:
    """A state row with NaN hand wrench and inputs and identity orientation (for initialisation)."""
    s = np.zeros(DEV_NSTATE)
    s[DS_POSE + 3] = 1.0
    s[DS_HAND:DS_HAND + 6] = np.nan
    s[DS_BUTTONS:DEV_NSTATE] = np.nan
    return s
