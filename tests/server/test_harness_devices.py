"""The harness's device doubles (``server_harness.PointDevice``, ``WatchdogDevice``) behave like a
real driver where the loop can tell: the statuses ``read`` and ``write`` return through the same
sequence of calls are the ``sim`` driver's (disabled before ``enable`` and after ``disable``, a
latched fault until ``enable``), and the device-driver contract's rules hold for them. A double
that never says "disabled" let loop tests pass that a real device would fail."""
from __future__ import annotations

import numpy as np
import pytest
from server_harness import PointDevice, WatchdogDevice

from hapticproxy.server.devices.base import DEV_FAULT_DISABLED, DEV_NSTATE, DEV_OK
from hapticproxy.testing import device_contract as dcon

PUSH = np.array([0.5, 0.5, 0.0, 0.0, 0.0, 0.01])
NAN = np.array([np.nan, 0.0, 0.0, 0.0, 0.0, 0.0])


class _Now:
    """The contract's clock as the loop's (``now_ns``), for ``WatchdogDevice``."""

    def __init__(self, fake: dcon.FakeClock) -> None:
        self.fake = fake

    def now_ns(self) -> int:
        return self.fake.ns


class _PointHarness(dcon.Harness):
    """A double renders inside ``write`` (as the ``sim`` driver does): what it renders now is the
    last write's force while it stays enabled without a fault, zero from ``disable`` or a fault on."""

    def __init__(self, kind="planar", period_s=dcon.PERIOD_S, watchdog=False):
        super().__init__(period_s)
        if watchdog:
            self.driver = WatchdogDevice(_Now(self.clock), watchdog_s=0.05, kind=kind, period_s=period_s)
        else:
            self.driver = PointDevice(kind=kind, period_s=period_s)

    def rendered(self):
        d = self.driver
        if not d.commands or not d.enabled or d.fault != DEV_OK:
            return np.zeros(6)
        f = d.commands[-1]
        return np.array([f[0], f[1], 0.0, 0.0, 0.0, f[2]])


def _statuses(h: dcon.Harness) -> list[tuple[int, int]]:
    """(read, write) statuses through: disabled, enabled, disabled again, a non-finite command
    while enabled (latched through finite ones), and re-enabled."""
    d = h.driver
    out = [h.step(PUSH)]
    d.enable()
    out += [h.step(PUSH), h.step(PUSH)]
    d.disable()
    out += [h.step(PUSH)]
    d.enable()
    out += [h.step(NAN), h.step(PUSH)]
    d.disable()
    out += [h.step(PUSH)]
    d.enable()
    out += [h.step(PUSH)]
    return [(int(a), int(b)) for a, b in out]


@pytest.mark.parametrize("watchdog", [False, True], ids=["point", "watchdog"])
def test_the_doubles_report_what_the_sim_driver_reports(watchdog):
    want = _statuses(dcon.SimHarness("planar"))
    got = _statuses(_PointHarness("planar", watchdog=watchdog))
    assert got == want
    assert want[0] == (DEV_FAULT_DISABLED, DEV_FAULT_DISABLED) and want[1] == (DEV_OK, DEV_OK)


@pytest.mark.parametrize("rule", ["identity", "disable", "non-finite", "on-engage"])
@pytest.mark.parametrize("watchdog", [False, True], ids=["point", "watchdog"])
def test_the_doubles_keep_the_device_contract(rule, watchdog):
    dcon.check(rule, lambda: _PointHarness("planar", watchdog=watchdog))


def test_the_watchdog_double_keeps_the_watchdog_rule():
    dcon.check("watchdog", lambda: _PointHarness("planar", watchdog=True))


def test_a_row_is_filled():
    h = _PointHarness("planar")
    row = np.zeros(DEV_NSTATE)
    assert h.driver.read(row) == DEV_FAULT_DISABLED and np.all(np.isfinite(row))
