"""The haptic device models the vendor drivers know, with the figures their makers state.

One table per vendor, keyed the way the vendor's SDK names a model (Force Dimension: the DHD
system type ``dhdGetSystemType``; 3D Systems: the HD model string; Haply: the wake-up reply's
model number). Figures are CHAI3D 3.x's ``cHapticDeviceInfo`` declarations for that model
(``CDeltaDevices.cpp``, ``CPhantomDevices.cpp``: maximum continuous force, torque, gripper force,
stiffness and damping renderable at 1 kHz, workspace radius, sensed and actuated parts); a figure
CHAI3D does not state is ``None``, never a guess. A driver turns a row into its
:class:`~hapticproxy.server.devices.base.DeviceInfo`, adding what the device reports itself
(serial number, calibration state, the HD API's nominal figures for a Touch).

The emulators (``hapticproxy.testing.emulators``) build their physical device from the same
rows, so a driver and its emulator agree on what the model is.
"""
from __future__ import annotations

from dataclasses import dataclass, replace


@dataclass(frozen=True)
class ModelSpec:
    """One model's stated figures (SI units, at the handle)."""

    name: str
    vendor: str
    max_force_n: float
    max_torque_n_m: float = 0.0
    max_gripper_force_n: float = 0.0
    max_stiffness_n_per_m: float | None = None
    max_damping_n_s_per_m: float | None = None
    max_rot_stiffness_n_m_per_rad: float | None = None
    max_rot_damping_n_m_s_per_rad: float | None = None
    workspace_radius_m: float = 0.075
    sensed: tuple = ("position",)
    actuated: tuple = ("position",)
    buttons: int = 1
    hand: str = ""
    #: the emulator's physical device: moving mass at the handle [kg] and viscous damping
    #: [N s/m] (plausible values for the mechanism, not vendor figures: the emulator needs some)
    emu_mass_kg: float = 0.2
    emu_damping_n_s_per_m: float = 1.0

    @property
    def gripper(self) -> bool:
        return "gripper" in self.sensed

    def workspace_box(self) -> tuple[tuple, tuple]:
        """The box inscribing the workspace sphere, centred on the device's origin [m]."""
        r = self.workspace_radius_m
        return (-r, -r, -r), (r, r, r)


_FD = "Force Dimension"
_P = ("position",)
_PR = ("position", "rotation")
_PRG = ("position", "rotation", "gripper")
_PG = ("position", "gripper")

_OMEGA3 = ModelSpec("omega.3", _FD, 12.0, max_stiffness_n_per_m=5000.0, max_damping_n_s_per_m=30.0,
                    workspace_radius_m=0.075, emu_mass_kg=0.18)
_OMEGA6 = replace(_OMEGA3, name="omega.6", sensed=_PR)
_OMEGA7 = replace(_OMEGA3, name="omega.7", sensed=_PRG, actuated=_PG, max_gripper_force_n=8.0)
_SIGMA7 = ModelSpec("sigma.7", _FD, 12.0, 0.2, 8.0, 4000.0, 30.0, 1.0, 0.07, 0.075, _PRG, _PRG, emu_mass_kg=0.4)
_DELTA3 = ModelSpec("delta.3", _FD, 20.0, max_stiffness_n_per_m=5000.0, workspace_radius_m=0.15, emu_mass_kg=0.5)
# (its torque is not in the notes this table was built from: capped at 0 until it is stated)
_LAMBDA7 = ModelSpec("lambda.7", _FD, 12.0, 0.0, 8.0, 8000.0, None, None, None, 0.1125, _PRG, _PRG, emu_mass_kg=0.4)
_FALCON = ModelSpec("Falcon", "Novint Technologies", 8.0, max_stiffness_n_per_m=3000.0, max_damping_n_s_per_m=20.0,
                    workspace_radius_m=0.04, buttons=4, emu_mass_kg=0.15)

#: DHD system type (``dhdGetSystemType``, forcedimension_core.constants.DeviceType) -> model
FORCEDIMENSION: dict[int, ModelSpec] = {
    33: _OMEGA3,
    34: replace(_OMEGA6, hand="right"), 36: replace(_OMEGA6, hand="left"),
    35: replace(_OMEGA7, hand="right"), 37: replace(_OMEGA7, hand="left"),
    104: replace(_SIGMA7, hand="right"), 105: replace(_SIGMA7, hand="left"),
    63: _DELTA3,
    108: replace(_LAMBDA7, hand="right"), 109: replace(_LAMBDA7, hand="left"),
    60: _FALCON,
}
#: the config's ``model`` names -> system types (a config may ask for a model and is refused
#: when another is attached)
FORCEDIMENSION_NAMES: dict[str, tuple[int, ...]] = {}
for _t, _m in FORCEDIMENSION.items():
    FORCEDIMENSION_NAMES.setdefault(_m.name.lower(), ())
    FORCEDIMENSION_NAMES[_m.name.lower()] += (_t,)

#: 3D Systems / SensAble models by their HD model string (``hdGetString(HD_DEVICE_MODEL_TYPE)``):
#: the CHAI3D figures; the driver prefers the device's own nominal figures (HD_NOMINAL_*).
TOUCH: dict[str, ModelSpec] = {
    "Touch": ModelSpec("Touch", "3D Systems", 3.3, max_stiffness_n_per_m=400.0, max_damping_n_s_per_m=4.0,
                       workspace_radius_m=0.075,
                       sensed=_PR, actuated=_P, buttons=2, emu_mass_kg=0.045, emu_damping_n_s_per_m=0.5),
    "PHANTOM Omni": ModelSpec("PHANTOM Omni", "SensAble Technologies", 3.3, max_stiffness_n_per_m=700.0,
                              max_damping_n_s_per_m=8.0, workspace_radius_m=0.10, sensed=_PR, actuated=_P, buttons=2,
                              emu_mass_kg=0.045, emu_damping_n_s_per_m=0.5),
    "PHANTOM Desktop": ModelSpec("PHANTOM Desktop", "SensAble Technologies", 7.9, max_stiffness_n_per_m=1000.0,
                                 max_damping_n_s_per_m=8.0, workspace_radius_m=0.10, sensed=_PR, actuated=_P,
                                 buttons=2, emu_mass_kg=0.045),
}

#: Haply Inverse3: no figure here is a vendor's: Haply's datasheet was not available to this
#: project, so the force cap is the config's (``max_force_n``) and stiffness/damping are unknown.
INVERSE3 = ModelSpec("Inverse3", "Haply Robotics", 0.0, workspace_radius_m=0.2, sensed=_P, actuated=_P, buttons=0,
                     emu_mass_kg=0.3)
