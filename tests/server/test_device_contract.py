"""Every registered device driver keeps the DeviceDriver contract (hapticproxy.testing.device_contract,
the suite a lab runs against its own driver), and the suite catches drivers that break it."""
from __future__ import annotations


import numpy as np
import pytest

from hapticproxy.server.devices.base import DEVICE_KINDS
from hapticproxy.server.devices.layout import DC_WD_NS
from hapticproxy.server.devices.sim import SimDevice
from hapticproxy.server.devices.base import DEVICE_REGISTRY
from hapticproxy.testing import device_contract as dcon

REGISTERED = sorted(DEVICE_REGISTRY.names())


def test_the_registry_holds_the_built_in_drivers():
    assert {"sim", "remote"} <= set(REGISTERED)


def _driver_kinds():
    """(driver, kind) for every kind a driver builds (a factory's ``kinds``; default: all)."""
    out = []
    for name in REGISTERED:
        try:
            kinds = getattr(DEVICE_REGISTRY.load(name), "kinds", DEVICE_KINDS)
        except ValueError:  # a vendor driver whose package is absent: its own tests say so
            kinds = DEVICE_KINDS
        out += [(name, k) for k in kinds]
    return out


@pytest.mark.parametrize("rule", list(dcon.RULES))
@pytest.mark.parametrize("name,kind", _driver_kinds())
def test_every_registered_driver_keeps_the_contract(name, rule, kind):
    dcon.check(rule, name, kind)


# ------------------------------------------------------------------ the suite can fail
class _Broken(dcon.SimHarness):
    cls: type = SimDevice

    def __init__(self, kind="planar", period_s=dcon.PERIOD_S):
        super().__init__(kind, period_s)
        self.driver.__class__ = self.cls   # the same device, one method broken


class DisableKeepsRendering(SimDevice):
    def disable(self):
        pass


class NonFiniteZeroedNotLatched(SimDevice):
    def write(self, wrench):
        w = np.nan_to_num(np.asarray(wrench, dtype=float), nan=0.0, posinf=0.0, neginf=0.0)
        return super().write(w)


class WatchdogClaimedNotKept(SimDevice):
    def read(self, state_out):
        self._ctl[DC_WD_NS] = 0  # limits say 0.05 s; the device has none
        return super().read(state_out)


class ReadAllocates(SimDevice):
    log: list = []

    def read(self, state_out):
        self.log.append(state_out.copy())
        return super().read(state_out)


class EngageArms(SimDevice):
    def on_engage(self):
        self.enable()


@pytest.mark.parametrize("cls,rule", [
    (DisableKeepsRendering, "disable"),
    (NonFiniteZeroedNotLatched, "non-finite"),
    (WatchdogClaimedNotKept, "watchdog"),
    (ReadAllocates, "no-allocation"),
    (EngageArms, "on-engage"),
])
def test_the_suite_fails_a_driver_that_breaks_a_promise(cls, rule):
    harness = type(f"{cls.__name__}Harness", (_Broken,), {"cls": cls})
    results = {r: ok for r, ok, _ in dcon.run(harness)}
    assert not results[rule], rule
    assert all(ok for r, ok in results.items() if r != rule), results


def test_an_unknown_driver_has_no_harness():
    with pytest.raises(ValueError, match="not registered"):
        dcon.harness_for("no-such-driver")
