"""The physical device behind every emulator: the project's simulated device and scripted hand,
stepped under the command the fake SDK wrote into the shared block (:mod:`.block`).

:class:`Physics` is one device: a spatial :class:`~hapticproxy.server.devices.sim.SimDevice` with
the model's mass, damping, workspace and a hand from ``server/devices/hands.py``; each
:meth:`Physics.step` is one tick of the device's electronics:

1. the firmware watchdog: no new command (``cmd_seq`` unchanged) for ``watchdog_s`` of device
   time while forces are on -> forces off (cause 3), counted; only the host turns them on again;
2. unplugged -> forces off (cause 5): a device without its USB link renders nothing;
3. the rendered wrench: the command when forces are on, else zero; the parts the model does not
   actuate dropped; the force's norm scaled down to the model's maximum, direction kept (what
   the DHD SDK does: ``dhdSetForce`` returns ``DHD_MOTOR_SATURATED``);
4. one dynamics step of the simulated device with the hand;
5. the state published under the sequence lock, unless the position is frozen.

Run it in-process and step it from a test (lock-step, on simulated time: the contract
harnesses) or as its own real-time process (:func:`spawn`, ``python -m
hapticproxy.testing.emulators.physics``), ticking on absolute deadlines at ``rate_hz`` until the
block's ``stop`` slot is set or its parent dies.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import time

import numpy as np

from ...server.devices.base import DEV_NSTATE, DS_BUTTONS, DS_GRIPPER
from ...server.devices.models import ModelSpec
from ...server.devices.sim import make_sim_device
from .block import OFFSETS, Block

_O = OFFSETS
CAUSE_WATCHDOG = 3
CAUSE_SOFTWARE = 4
CAUSE_USB = 5


def sim_config(model: ModelSpec, *, hand: dict | None = None, initial_pose=None) -> dict:
    """The ``[device]`` table of the simulated device that stands for ``model``."""
    lo, hi = model.workspace_box()
    cfg = {"kind": "spatial", "mass_kg": model.emu_mass_kg, "damping_n_s_per_m": model.emu_damping_n_s_per_m,
           "max_force_n": max(model.max_force_n, 1.0), "max_torque_n_m": max(model.max_torque_n_m, 0.5),
           "max_speed_m_per_s": 10.0, "max_angular_speed_rad_per_s": 100.0,
           "workspace_min_m": list(lo), "workspace_max_m": list(hi), "rotation_limit_rad": 1.2,
           "watchdog_s": 0.0, "hand": hand or {"type": "none"}}
    if initial_pose is not None:
        cfg["initial_pose"] = list(initial_pose)
    return cfg


class Physics:
    """One emulated device on ``block`` (which it initialises: model id, serial, first state)."""

    def __init__(self, block: Block, model: ModelSpec, *, model_id: int, serial: int = 1234,
                 period_s: float = 1e-3, hand: dict | None = None, initial_pose=None,
                 max_force_n: float | None = None, calibrated: bool = True) -> None:
        self.block = block
        self.model = model
        self.period_s = float(period_s)
        self.max_force_n = float(max_force_n if max_force_n is not None else model.max_force_n)
        self.sim = make_sim_device(sim_config(model, hand=hand, initial_pose=initial_pose), period_s=period_s)
        self.sim.enable()
        self._row = np.zeros(DEV_NSTATE)
        self._cmd = np.zeros(7)
        self._w = np.zeros(6)
        self._mask = np.array([1.0 if "position" in model.actuated else 0.0] * 3
                              + [1.0 if "rotation" in model.actuated else 0.0] * 3)
        self._last_seq = -1.0
        self._last_cmd_t = 0.0
        self._was_on = False
        self._hand_go = 0.0
        b = block
        b["model_id"] = model_id
        b["serial"] = serial
        b["period_s"] = period_s
        b["calibrated"] = 1.0 if calibrated else 0.0
        self._publish()

    # ------------------------------------------------------------------------------ one tick
    def step(self) -> None:
        b = self.block.b
        t = self.sim.time_s
        seq = b[_O["cmd_seq"]]
        cmd = self._cmd
        if seq != self._last_seq:
            cmd[:] = b[_O["cmd"]:_O["cmd"] + 7]
            if b[_O["cmd_seq"]] == seq:  # not torn: take it (else keep the last one until next tick)
                self._last_seq = seq
                self._last_cmd_t = t
                self._w[:] = cmd[:6]
        on = b[_O["force_on"]] != 0.0
        if on and not self._was_on:
            self._last_cmd_t = t  # the firmware's watchdog counts from the enable, too
        self._was_on = on
        wd = b[_O["watchdog_s"]]
        if on and wd > 0.0 and t - self._last_cmd_t > wd:
            on = False
            b[_O["force_on"]] = 0.0
            b[_O["force_off_cause"]] = CAUSE_WATCHDOG
            b[_O["watchdog_trips"]] += 1
            self._was_on = False
        if on and b[_O["fault_unplugged"]] != 0.0:
            on = False
            b[_O["force_on"]] = 0.0
            b[_O["force_off_cause"]] = CAUSE_USB
        w = self._w * self._mask if on else self._w * 0.0
        f = math.sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2])
        if f > self.max_force_n:
            w[:3] *= self.max_force_n / f
            b[_O["saturated"]] += 1
        tq = math.sqrt(w[3] * w[3] + w[4] * w[4] + w[5] * w[5])
        if tq > self.model.max_torque_n_m > 0.0:
            w[3:] *= self.model.max_torque_n_m / tq
        if not np.all(np.isfinite(w)):
            w[:] = 0.0
        b[_O["rendered"]:_O["rendered"] + 6] = w
        go = b[_O["hand_go"]]
        if go != self._hand_go:
            self._hand_go = go
            self.sim.on_engage()
        self.sim.write(w)
        b[_O["steps"]] += 1
        if b[_O["fault_frozen"]] == 0.0:
            self._publish()

    def _publish(self) -> None:
        self.sim.read(self._row)
        r = self._row
        b = self.block.b
        seq = _O["state_seq"]
        b[seq] += 1  # odd: writing
        b[_O["time_s"]] = r[19]
        b[_O["pos_m"]:_O["pos_m"] + 3] = r[0:3]
        b[_O["quat"]:_O["quat"] + 4] = r[3:7]
        b[_O["vel_m_s"]:_O["vel_m_s"] + 3] = r[7:10]
        b[_O["angvel_rad_s"]:_O["angvel_rad_s"] + 3] = r[10:13]
        # the hand's button and gripper scripts (a test may also write these slots itself: a
        # device without the script leaves them alone)
        if not math.isnan(r[DS_BUTTONS]):
            b[_O["buttons"]] = r[DS_BUTTONS]
        if not math.isnan(r[DS_GRIPPER]):
            b[_O["gripper_rad"]] = r[DS_GRIPPER]
            b[_O["gripper_rad_s"]] = r[DS_GRIPPER + 1]
        b[seq] += 1  # even: done

    def command_now(self) -> np.ndarray:
        """What the motors render once the command in the block is taken (a device that applies
        each command as it arrives, between the physics' ticks): masked, norm-capped, zero when
        forces are off."""
        b = self.block.b
        w = b[_O["cmd"]:_O["cmd"] + 6] * self._mask
        if b[_O["force_on"]] == 0.0 or b[_O["fault_unplugged"]] != 0.0 or not np.all(np.isfinite(w)):
            return w * 0.0
        f = math.sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2])
        if f > self.max_force_n:
            w[:3] *= self.max_force_n / f
        return w

    @property
    def rendered(self) -> np.ndarray:
        return self.block.view("rendered").copy()


# ----------------------------------------------------------------------------- its own process
def run(physics: Physics, rate_hz: float, parent_pid: int) -> None:
    """Tick on absolute deadlines until ``stop`` or the parent is gone; late ticks are not
    caught up (a real device's electronics tick on, whatever the host does)."""
    b = physics.block
    b["alive"] = 1.0
    period_ns = int(round(1e9 / rate_hz))
    nxt = time.monotonic_ns()
    n = 0
    try:
        while b["stop"] == 0.0:
            physics.step()
            n += 1
            if n % 256 == 0 and os.getppid() != parent_pid:
                break
            nxt += period_ns
            now = time.monotonic_ns()
            if nxt > now:
                time.sleep((nxt - now) * 1e-9)
            elif now - nxt > 10 * period_ns:
                nxt = now
    finally:
        b["alive"] = 0.0


def spawn(block_path: str, model_key: str, *, vendor: str, period_s: float = 1e-3, hand: dict | None = None,
          initial_pose=None, serial: int = 1234, model_id: int | None = None, max_force_n: float | None = None,
          calibrated: bool = True) -> subprocess.Popen:
    """Start the physics of one device as its own process on ``block_path`` (created by the
    caller) and wait until it ticks. ``vendor``: ``forcedimension`` (``model_key`` a system type),
    ``touch`` (an HD model string) or ``inverse3``."""
    spec = {"vendor": vendor, "model": model_key, "period_s": period_s, "hand": hand, "initial_pose": initial_pose,
            "serial": serial, "model_id": model_id, "max_force_n": max_force_n, "calibrated": calibrated,
            "parent": os.getpid()}
    proc = subprocess.Popen([sys.executable, "-m", "hapticproxy.testing.emulators.physics", block_path, json.dumps(spec)])
    blk = Block(block_path)
    try:
        end = time.monotonic() + 120.0
        while blk["alive"] == 0.0 or blk["steps"] < 2:
            if proc.poll() is not None:
                raise RuntimeError(f"the physics process exited with {proc.returncode}")
            if time.monotonic() > end:
                proc.kill()
                raise RuntimeError("the physics process did not start ticking within 120 s")
            time.sleep(0.01)
    finally:
        blk.close()
    return proc


def model_for(vendor: str, key) -> tuple[ModelSpec, int]:
    """The model row and the id the block carries for it."""
    from ...server.devices import models

    if vendor == "forcedimension":
        return models.FORCEDIMENSION[int(key)], int(key)
    if vendor == "touch":
        return models.TOUCH[str(key)], list(models.TOUCH).index(str(key))
    if vendor == "inverse3":
        return models.INVERSE3, 0
    raise ValueError(f"vendor: expected forcedimension, touch or inverse3, got {vendor!r}")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m hapticproxy.testing.emulators.physics")
    p.add_argument("block")
    p.add_argument("spec", help="JSON: vendor, model, period_s, hand, initial_pose, serial, model_id, parent")
    a = p.parse_args(argv)
    spec = json.loads(a.spec)
    model, mid = model_for(spec["vendor"], spec["model"])
    if spec.get("model_id") is not None:
        mid = int(spec["model_id"])
    blk = Block(a.block)
    phys = Physics(blk, model, model_id=mid, serial=int(spec.get("serial") or 1234), period_s=float(spec["period_s"]),
                   hand=spec.get("hand"), initial_pose=spec.get("initial_pose"), max_force_n=spec.get("max_force_n"),
                   calibrated=bool(spec.get("calibrated", True)))
    run(phys, 1.0 / phys.period_s, int(spec.get("parent") or os.getppid()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
