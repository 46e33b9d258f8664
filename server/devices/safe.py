"""Safe settings derived from the device's info: the gains the device renders stably at the
loop's rate, checked once the device is open (the config loader cannot: it knows no device).

Contract
--------
:func:`gain_limits` ``(info, rate_hz, controller) -> [GainLimit]``: for each gain the device
renders, the largest value it takes, with the reason. What the device renders: the coupling
(``controller.stiffness_n_per_m``, ``controller.damping_n_s_per_m``, and where the device
renders rotation ``controller.rot_stiffness_n_m_per_rad``, ``controller.rot_damping_n_m_s_per_rad``)
for the four-channel and coupler controllers; with direct coupling the device is the tool and
renders the contact (``model.stiffness_n_per_m``, ``model.damping_n_s_per_m``). Each limit is
the smallest of what the device's figures give (none stated: no limit from them):

- its stiffness figures (``DeviceInfo.max_stiffness_n_per_m``, ``max_rot_stiffness_n_m_per_rad``:
  CHAI3D's, or the device's own ``HD_NOMINAL_*``) are what it renders stably at 1 kHz; by
  Colgate and Schenkel's passivity bound ``K < 2 (b - |B|) / T`` (b the device's physical damping)
  they grow with the rate: ``K_max = K_1kHz rate / 1 kHz`` (``stability.device_stiffness_at_rate``);
- its damping figures (``max_damping_n_s_per_m``, ``max_rot_damping_n_m_s_per_rad``) hold at every
  rate (B enters the bound without T). Stiffness and damping are bounded apart, as the figures are
  stated: the joint bound, with b taken from the stiffness figure (b = K_1kHz T / 2, 2.5 N s/m on an
  omega), would refuse the damping the same tables state the device takes (30 N s/m);
- its moving mass m (``moving_mass_kg``) bounds both at the rate: ``K <= 2 m rate^2`` and
  ``B <= m rate`` (``stability.device_spring_limit_n_per_m``, ``device_damper_limit_n_s_per_m``).

A workspace mapping does not change them: by its force rule (``mapping.py``) a gain of the scene
is felt at the device as it is.

:func:`derive` ``(settings, info) -> Settings``: every gain within its limit is kept; one above
it that the config did not set (a default, :attr:`Settings.given`) is lowered to the limit and
listed in :attr:`Settings.lowered` (so a first run with a Touch works unedited); one the config
set is refused, ``ConfigError`` naming the key, the device, the limit and the nearest safe value,
unless ``safety.allow_outside_stable_region`` is set: then it is kept and listed in
:attr:`Settings.outside_stable_region` (a warning at start, a line in ``status``). Idempotent:
deriving again from its result changes nothing.
"""
from __future__ import annotations

import copy
import dataclasses
import logging
from dataclasses import dataclass

from .. import stability
from ..config import ConfigError, Settings
from .base import DeviceInfo

log = logging.getLogger("hapticproxy.devices")


@dataclass(frozen=True)
class GainLimit:
    """The largest value of one setting the device takes, and why."""

    key: str            # dotted config key
    limit: float        # in the key's unit
    why: str            # what bounds it (the figure, the rate, the mass)


def _least(key: str, bounds: list[tuple[float | None, str]]) -> list[GainLimit]:
    """The tightest of ``bounds`` (value, reason; a None value: not stated) as a one-item list."""
    stated = [(v, why) for v, why in bounds if v is not None]
    if not stated:
        return []
    v, why = min(stated, key=lambda b: b[0])
    return [GainLimit(key, float(v), why)]


def gain_limits(info: DeviceInfo, rate_hz: float, controller: str) -> list[GainLimit]:
    """The limits of the gains the device renders (module docstring)."""
    name = f"{info.vendor} {info.model}".strip()
    at = f"at {rate_hz:g} Hz"
    m = info.moving_mass_kg
    section = "model" if controller == "direct" else "controller"
    k1, b1 = info.max_stiffness_n_per_m, info.max_damping_n_s_per_m
    k = None if k1 is None else stability.device_stiffness_at_rate(k1, rate_hz)
    k_m = None if not m else stability.device_spring_limit_n_per_m(m, rate_hz)
    b_m = None if not m else stability.device_damper_limit_n_s_per_m(m, rate_hz)
    out = _least(f"{section}.stiffness_n_per_m", [
        (k, f"the {name} renders {k1:g} N/m stably at 1 kHz, {k:.6g} N/m {at} (the figure scaled with the rate)"
         if k is not None else ""),
        (k_m, f"its {m:g} kg moving mass takes at most {k_m:.6g} N/m {at} "
              f"(k dt^2 / m <= {stability.DEVICE_SPRING_STABILITY:g})" if k_m is not None else "")])
    out += _least(f"{section}.damping_n_s_per_m", [
        (b1, f"the {name} renders at most {b1:g} N s/m stably" if b1 is not None else ""),
        (b_m, f"its {m:g} kg moving mass takes at most {b_m:.6g} N s/m {at} "
              f"(b dt / m <= {stability.DEVICE_DAMPER_STABILITY:g})" if b_m is not None else "")])
    if section == "controller" and "rotation" in info.actuated:
        kr1, br1 = info.max_rot_stiffness_n_m_per_rad, info.max_rot_damping_n_m_s_per_rad
        kr = None if kr1 is None else stability.device_stiffness_at_rate(kr1, rate_hz)
        out += _least("controller.rot_stiffness_n_m_per_rad", [
            (kr, f"the {name} renders {kr1:g} N m/rad stably at 1 kHz, {kr:.6g} N m/rad {at} (the figure scaled "
                 f"with the rate)" if kr is not None else "")])
        out += _least("controller.rot_damping_n_m_s_per_rad", [
            (br1, f"the {name} renders at most {br1:g} N m s/rad stably" if br1 is not None else "")])
    return out


def _get(data: dict, key: str) -> float:
    section, name = key.split(".")
    return float(data[section][name])


def derive(settings: Settings, info: DeviceInfo) -> Settings:
    """``settings`` with the gains the device cannot take lowered (defaults), refused (set by the
    config) or listed (the research override): the module docstring's contract."""
    rate = settings.rate_hz
    controller = settings["controller"]["type"]
    allow = bool(settings["safety"]["allow_outside_stable_region"])
    data = None
    lowered = list(settings.lowered)
    outside = list(settings.outside_stable_region)
    known = {k for k, _ in outside}
    for lim in gain_limits(info, rate, controller):
        v = _get(settings.data, lim.key)
        if v <= lim.limit:
            continue
        if lim.key not in settings.given:
            if data is None:
                data = copy.deepcopy(settings.data)
            section, name = lim.key.split(".")
            data[section][name] = lim.limit
            lowered.append((lim.key, v, lim.limit, lim.why))
            continue
        why = f"{v:g} is more than the device renders stably: {lim.why}; nearest safe value {lim.limit:.6g}"
        if not allow:
            raise ConfigError(lim.key, f"{why}; or set safety.allow_outside_stable_region = true (research only)")
        if lim.key not in known:
            outside.append((lim.key, why))
            known.add(lim.key)
    if data is None and len(outside) == len(settings.outside_stable_region):
        return settings
    return dataclasses.replace(settings, data=data if data is not None else settings.data,
                               outside_stable_region=tuple(outside), lowered=tuple(lowered))


def log_derived(before: Settings, after: Settings, logger: logging.Logger = log) -> None:
    """One line per gain :func:`derive` lowered, one warning per gain it let through outside the
    device's stable region (what ``before`` did not list already)."""
    for key, was, now, why in after.lowered[len(before.lowered):]:
        logger.info("%s lowered from %g to %.6g, what the device renders stably (%s); set it in the config "
                    "to choose another value within that", key, was, now, why)
    for key, why in after.outside_stable_region[len(before.outside_stable_region):]:
        logger.warning("OUTSIDE THE DEVICE'S STABLE REGION (safety.allow_outside_stable_region = true): %s: %s",
                       key, why)
