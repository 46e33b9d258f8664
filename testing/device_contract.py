"""The device-driver contract as a suite every registered driver passes (python-can's
back-to-back interface tests are the model), shipped so a lab can run it against its own driver.

The contract is :class:`~hapticproxy.server.devices.base.DeviceDriver`'s (``server/devices/base.py``);
each rule of :data:`RULES` checks one promise on a fresh driver in simulated time:

- ``identity``: a ``DeviceDriver`` with a known ``kind`` and a ``name``;
- ``limits``: ``limits`` is a ``DeviceLimits`` with positive, finite caps, a workspace box with
  min < max, a finite ``watchdog_s`` >= 0;
- ``state-row``: ``read`` fills the float64[23] row: finite pose, twist and time, a unit
  quaternion, the hand wrench finite or all NaN, the inputs (buttons a bit mask or NaN, the
  gripper's angle and rate finite or NaN), time never going back, and nothing a kind cannot
  move (planar: z, tilt and their rates zero; 1dof: identity orientation, no spin);
- ``disable``: ``disable()`` zeroes the output at once (within one hardware tick) and keeps it
  zero, whatever is written, until ``enable()``; every ``write`` meanwhile returns a non-OK
  status (``DEV_FAULT_DISABLED``, or a latched fault's code), never ``DEV_OK``;
- ``non-finite``: a non-finite ``write`` is refused (status ``DEV_FAULT_NONFINITE_COMMAND``),
  zero is rendered, the fault stays latched through finite writes until ``enable()``;
- ``watchdog``: with ``limits.watchdog_s`` > 0, no ``write`` (nor ``read``) for longer than that
  zeroes the output and latches ``DEV_FAULT_WATCHDOG``; forces come back only through ``enable()``;
- ``no-allocation``: 1000 ``read``/``write`` steps leave no memory behind (tracemalloc);
- ``on-engage``: ``on_engage()`` exists, can be called outside the hot path, and neither arms
  nor disarms the output.

What the suite needs around a driver is a :class:`Harness`: it builds the driver on a simulated
clock, advances the hardware side by one period (:meth:`Harness.tick`) and says what the
hardware renders now (:meth:`Harness.rendered`). The built-in drivers have theirs
(:class:`SimHarness`; :class:`RemoteHarness` puts ``hapticproxy device``'s program, itself driving
a simulated device, on the other end of the link over UDP loopback, stepped in lock-step). A lab
attaches one to its driver's factory, next to its entry point::

    # mypkg/__init__.py          [project.entry-points."hapticproxy.devices"] mydev = "mypkg:make_mydev"
    class MyHarness(hapticproxy.testing.device_contract.Harness):
        def __init__(self, kind, period_s):
            super().__init__(period_s)
            self.driver = make_mydev({"kind": kind, ...}, period_s=period_s, clock_ns=self.clock)
        def tick(self): ...                  # advance the clock (and a bench rig) one period
        def rendered(self): ...              # the wrench the hardware renders now
    make_mydev.contract_harness = MyHarness

and runs the suite from its own tests::

    from .device_contract import RULES, check
    @pytest.mark.parametrize("rule", RULES)
    def test_mydev_keeps_the_device_contract(rule):
        check(rule, "mydev")          # or check(rule, lambda: MyHarness("planar", 1e-3))

:func:`check` raises ``AssertionError`` saying what broke; :func:`run` returns one
``(rule, ok, message)`` per rule.
"""
from __future__ import annotations

import math
import tracemalloc
from collections.abc import Callable

import numpy as np

from ..server.devices.base import (
    DEV_FAULT_NONFINITE_COMMAND, DEV_FAULT_WATCHDOG, DEV_NSTATE, DEV_OK, DEVICE_KINDS, DS_BUTTONS, DS_GRIPPER,
    DeviceDriver, DeviceLimits,
)

__all__ = ["RULES", "FakeClock", "Harness", "RemoteHarness", "SimHarness", "check", "harness_for", "run"]

PERIOD_S = 1e-3


class FakeClock:
    """A simulated clock in ns (what a driver's ``clock_ns`` is given)."""

    def __init__(self, start_ns: int = 5_000_000_000) -> None:
        self.ns = int(start_ns)

    def __call__(self) -> int:
        return self.ns

    def advance(self, s: float) -> None:
        self.ns += int(round(s * 1e9))


class Harness:
    """One driver on a simulated clock, and the hardware on its other side.

    Subclasses set :attr:`driver` (built with ``clock_ns=self.clock``) and implement
    :meth:`rendered`; :meth:`tick` advances the clock by one period (override it to advance the
    hardware too). ``continuous``: the hardware renders between writes (a device with its own
    loop, whose watchdog must cut *during* a stall); ``False`` for a simulation that advances only
    inside ``write``.
    """

    continuous = False

    def __init__(self, period_s: float = PERIOD_S) -> None:
        self.period_s = float(period_s)
        self.clock = FakeClock()
        self.driver: DeviceDriver
        self.row = np.zeros(DEV_NSTATE)

    def tick(self) -> None:
        self.clock.advance(self.period_s)

    def rendered(self) -> np.ndarray:  # pragma: no cover - interface
        """The wrench (6) the hardware renders now."""
        raise NotImplementedError

    def settle(self) -> None:
        """Make the driver ready to be enabled (e.g. wait for its link)."""

    def step(self, wrench) -> tuple[int, int]:
        """One haptic period as the loop runs it: the hardware's tick, ``read``, ``write``;
        returns both statuses."""
        self.tick()
        rs = self.driver.read(self.row)
        ws = self.driver.write(wrench)
        return rs, ws

    def close(self) -> None:
        self.driver.close()


class SimHarness(Harness):
    """The ``sim`` driver: a simulated device rendering inside ``write``."""

    def __init__(self, kind: str = "planar", period_s: float = PERIOD_S, config: dict | None = None) -> None:
        super().__init__(period_s)
        from ..server.devices.sim import make_sim_device

        self.driver = make_sim_device({"kind": kind, **(config or {})}, period_s=period_s, clock_ns=self.clock)

    def rendered(self) -> np.ndarray:
        return self.driver.last_command


class RemoteHarness(Harness):
    """The ``remote`` driver (built by its registered factory, listening on UDP loopback) with a
    device program on the other end (the one ``hapticproxy device`` runs, driving a simulated
    device of the same kind, with the driver's watchdog), stepped in lock-step on one clock."""

    continuous = True

    def __init__(self, kind: str = "planar", period_s: float = PERIOD_S, config: dict | None = None) -> None:
        super().__init__(period_s)
        from ..server.devices.base import load_device
        from ..server.devices.remote import DeviceProgram
        from ..server.devices.sim import make_sim_device

        self.driver = load_device("remote", {"kind": kind, "listen": "127.0.0.1:0", **(config or {})},
                                  period_s=period_s, clock_ns=self.clock)
        try:
            self.sim = make_sim_device({"kind": kind, "watchdog_s": 0.0}, period_s=period_s, clock_ns=self.clock)
            self.program = DeviceProgram(self.sim, self.driver.local_address, watchdog_s=self.driver.limits.watchdog_s,
                                         clock_ns=self.clock, period_s=period_s)
        except BaseException:
            self.driver.close()
            raise

    def tick(self) -> None:
        super().tick()
        self.program.tick()

    def settle(self) -> None:
        for _ in range(100):
            self.tick()
            self.driver.read(self.row)
            if self.driver.link_up:
                return
        raise AssertionError("the remote driver's link did not come up in 100 periods")

    def rendered(self) -> np.ndarray:
        return self.program.command

    def close(self) -> None:
        try:
            self.program.close()
        finally:
            self.driver.close()


def _emulated(cls_name: str) -> Callable[..., Harness]:
    """A vendor driver's harness on its emulator (``testing/emulators/harness.py``, which builds on
    this module: named, not imported, here)."""
    def make(kind: str = "spatial", period_s: float = PERIOD_S) -> Harness:
        import importlib

        return getattr(importlib.import_module("hapticproxy.testing.emulators.harness"), cls_name)(kind, period_s)
    return make


_BUILTIN = {"sim": SimHarness, "remote": RemoteHarness, "forcedimension": _emulated("ForceDimensionHarness"),
            "haply": _emulated("HaplyHarness"), "touch": _emulated("TouchHarness")}


def harness_for(name: str, kind: str = "planar", period_s: float = PERIOD_S) -> Callable[[], Harness]:
    """A factory of fresh harnesses for the driver registered as ``name`` (the device registry:
    built-ins merged with the ``hapticproxy.devices`` entry points): its factory's
    ``contract_harness(kind, period_s)``, or a built-in one. ``ValueError`` if the driver has
    neither."""
    from ..server.devices.base import DEVICE_REGISTRY

    if not DEVICE_REGISTRY.known(name):
        raise ValueError(f"device driver {name!r} is not registered; installed: {DEVICE_REGISTRY.names()}")
    made = getattr(DEVICE_REGISTRY.load(name), "contract_harness", None) or _BUILTIN.get(name)
    if made is None:
        raise ValueError(f"device driver {name!r} has no contract harness: attach one to its factory "
                         f"(make_x.contract_harness = MyHarness, see hapticproxy.testing.device_contract)")
    return lambda: made(kind, period_s)


# ------------------------------------------------------------------------------- the rules
def _push(h: Harness) -> np.ndarray:
    """A wrench every kind renders part of: a tenth of the caps on x, y and about z."""
    lim = h.driver.limits
    return np.array([0.1 * lim.max_force_n, 0.1 * lim.max_force_n, 0.0, 0.0, 0.0, 0.1 * lim.max_torque_n_m])


def _renders(h: Harness) -> bool:
    return bool(np.any(h.rendered() != 0.0))


def _enabled_and_pushing(h: Harness, steps: int = 5) -> np.ndarray:
    h.settle()
    h.driver.enable()
    w = _push(h)
    for _ in range(steps):
        h.step(w)
    assert _renders(h), f"enabled and writing {w.tolist()}, the hardware renders nothing"
    return w


def rule_identity(h: Harness) -> None:
    d = h.driver
    assert isinstance(d, DeviceDriver), f"{type(d).__name__} is not a DeviceDriver"
    assert d.kind in DEVICE_KINDS, f"kind {d.kind!r} is not one of {DEVICE_KINDS}"
    assert isinstance(d.name, str) and d.name, "the driver has no name"


def rule_limits(h: Harness) -> None:
    lim = h.driver.limits
    assert isinstance(lim, DeviceLimits), f"limits is a {type(lim).__name__}, not DeviceLimits"
    assert math.isfinite(lim.max_force_n) and lim.max_force_n > 0, f"max_force_n {lim.max_force_n}"
    assert math.isfinite(lim.max_torque_n_m) and lim.max_torque_n_m >= 0, f"max_torque_n_m {lim.max_torque_n_m}"
    assert math.isfinite(lim.max_speed_m_per_s) and lim.max_speed_m_per_s > 0, f"max_speed {lim.max_speed_m_per_s}"
    assert lim.max_angular_speed_rad_per_s > 0, f"max_angular_speed {lim.max_angular_speed_rad_per_s}"
    lo, hi = np.asarray(lim.workspace_min_m, float), np.asarray(lim.workspace_max_m, float)
    assert lo.shape == hi.shape and lo.size in (2, 3), f"workspace {lo.tolist()} .. {hi.tolist()}"
    dims = 2 if h.driver.kind == "planar" else 3   # a planar device's box has no height
    assert np.all(np.isfinite(lo)) and np.all(np.isfinite(hi)) and np.all(lo[:dims] < hi[:dims]), \
        f"workspace {lo.tolist()} .. {hi.tolist()} is not a box"
    assert math.isfinite(lim.watchdog_s) and lim.watchdog_s >= 0, f"watchdog_s {lim.watchdog_s}"


def _check_row(kind: str, r: np.ndarray) -> None:
    assert np.all(np.isfinite(r[0:13])) and math.isfinite(r[19]), f"non-finite pose, twist or time: {r.tolist()}"
    q = r[3:7]
    assert abs(float(q @ q) - 1.0) <= 1e-6, f"quaternion {q.tolist()} is not unit"
    hand = r[13:19]
    assert np.all(np.isfinite(hand)) or np.all(np.isnan(hand)), f"hand wrench {hand.tolist()}: finite or all NaN"
    b, g, gr = r[DS_BUTTONS], r[DS_GRIPPER], r[DS_GRIPPER + 1]
    assert math.isnan(b) or (0.0 <= b <= 0xFFFF_FFFF and b == int(b)), \
        f"buttons {b!r}: a bit mask (an integer in [0, 2^32)) or NaN (no buttons)"
    assert math.isnan(g) or math.isfinite(g), f"gripper angle {g!r}: finite or NaN (no gripper)"
    assert math.isnan(gr) or (math.isfinite(gr) and math.isfinite(g)), \
        f"gripper rate {gr!r}: finite (with an angle) or NaN (not measured)"
    if kind == "planar":
        assert r[2] == 0.0 and r[9] == 0.0, "a planar device moved in z"
        assert r[4] == 0.0 and r[5] == 0.0 and r[10] == 0.0 and r[11] == 0.0, "a planar device tilted"
    elif kind == "1dof":
        assert list(q) == [1.0, 0.0, 0.0, 0.0], "a 1dof device turned"
        assert np.all(r[10:13] == 0.0), "a 1dof device spins"


def rule_state_row(h: Harness) -> None:
    d = h.driver
    row = np.full(DEV_NSTATE, -7.0)
    status = d.read(row)
    assert isinstance(status, (int, np.integer)), f"read returned {status!r}, not a status code"
    _check_row(d.kind, row)
    w = _enabled_and_pushing(h)
    t_prev = h.row[19]
    for _ in range(50):
        h.step(w)
        _check_row(d.kind, h.row)
        assert h.row[19] >= t_prev, f"time went back from {t_prev} to {h.row[19]}"
        t_prev = h.row[19]


def rule_disable(h: Harness) -> None:
    d = h.driver
    w = _enabled_and_pushing(h)
    d.disable()
    if _renders(h):
        h.tick()  # a device on a link gets the zero command at its next tick
    assert not _renders(h), f"disable(): still rendering {h.rendered().tolist()}"
    assert not d.enabled, "disable(): enabled is still true"
    for i in range(20):
        _, st = h.step(w)
        assert st != DEV_OK, (f"disabled, write returned DEV_OK (step {i}): while disabled it must return "
                              f"DEV_FAULT_DISABLED or its latched fault (DeviceDriver's safety contract)")
        assert not _renders(h), f"disabled, rendering {h.rendered().tolist()} after {i + 1} writes"
    d.enable()
    for _ in range(3):
        h.step(w)
    assert _renders(h), "enable() after disable(): the output did not come back"


def rule_non_finite(h: Harness) -> None:
    d = h.driver
    for bad in (math.nan, math.inf):
        w = _enabled_and_pushing(h)
        nan = w.copy()
        nan[0] = bad
        h.tick()
        d.read(h.row)
        st = d.write(nan)
        assert st == DEV_FAULT_NONFINITE_COMMAND and d.fault == DEV_FAULT_NONFINITE_COMMAND, \
            f"write({bad}) returned {st}, fault {d.fault}; expected {DEV_FAULT_NONFINITE_COMMAND} latched"
        h.tick()
        assert not _renders(h), f"after write({bad}): rendering {h.rendered().tolist()}"
        for i in range(20):
            _, st = h.step(w)
            assert st == DEV_FAULT_NONFINITE_COMMAND, f"the non-finite fault did not stay latched (status {st})"
            assert not _renders(h), f"after write({bad}): rendering again after {i + 1} finite writes"
        d.enable()
        for _ in range(3):
            h.step(w)
        assert d.fault == DEV_OK and _renders(h), "enable() did not clear the non-finite fault"


def rule_watchdog(h: Harness) -> None:
    d = h.driver
    wd = d.limits.watchdog_s
    if wd <= 0:
        return  # no watchdog declared: nothing to keep
    w = _enabled_and_pushing(h)
    stall = int(math.ceil(1.5 * wd / h.period_s))
    for _ in range(stall):  # the loop stalls: no read, no write
        h.tick()
    if h.continuous:
        assert not _renders(h), f"no write for {1.5 * wd:g} s (watchdog_s {wd:g}): still rendering"
    faulted = False
    for i in range(20):
        _, st = h.step(w)
        assert not _renders(h), f"after the stall, rendering again after {i + 1} writes"
        faulted = faulted or st == DEV_FAULT_WATCHDOG
        if faulted:
            assert st != DEV_OK, "the watchdog fault did not stay latched"
    assert faulted and d.fault == DEV_FAULT_WATCHDOG, f"no DEV_FAULT_WATCHDOG after the stall (fault {d.fault})"
    d.enable()
    for _ in range(3):
        h.step(w)
    assert d.fault == DEV_OK and _renders(h), "enable() did not bring the output back after the watchdog"


def rule_no_allocation(h: Harness) -> None:
    w = _enabled_and_pushing(h)
    for _ in range(200):
        h.step(w)
    tracemalloc.start()
    try:
        before = tracemalloc.get_traced_memory()[0]
        for _ in range(1000):
            h.step(w)
        grown = tracemalloc.get_traced_memory()[0] - before
    finally:
        tracemalloc.stop()
    assert grown < 1024, f"1000 read/write steps left {grown} bytes behind"


def rule_on_engage(h: Harness) -> None:
    d = h.driver
    assert callable(getattr(d, "on_engage", None)), "no on_engage()"
    d.on_engage()  # disabled: must not arm
    assert not d.enabled, "on_engage() enabled the driver"
    w = _enabled_and_pushing(h)
    d.on_engage()
    for _ in range(3):
        _, st = h.step(w)
    assert d.enabled and st == DEV_OK and _renders(h), f"on_engage() disturbed the output (status {st})"


RULES: dict[str, Callable[[Harness], None]] = {
    "identity": rule_identity,
    "limits": rule_limits,
    "state-row": rule_state_row,
    "disable": rule_disable,
    "non-finite": rule_non_finite,
    "watchdog": rule_watchdog,
    "no-allocation": rule_no_allocation,
    "on-engage": rule_on_engage,
}


def check(rule: str, harness: str | Callable[[], Harness], kind: str = "planar") -> None:
    """Run one rule on a fresh harness (a registered driver's name, or a harness factory);
    ``AssertionError`` saying what broke."""
    make = harness_for(harness, kind) if isinstance(harness, str) else harness
    h = make()
    try:
        RULES[rule](h)
    finally:
        h.close()


def run(harness: str | Callable[[], Harness], kind: str = "planar") -> list[tuple[str, bool, str]]:
    """Every rule, each on a fresh harness: ``(rule, ok, message)``."""
    out = []
    for rule in RULES:
        try:
            check(rule, harness, kind)
            out.append((rule, True, ""))
        except AssertionError as exc:
            out.append((rule, False, str(exc)))
    return out
