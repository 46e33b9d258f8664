"""Contract harnesses for the vendor drivers (``testing/device_contract.py``), each on its
emulator, in lock-step on simulated time: every :meth:`tick` advances the loop's clock and the
emulated device by one period, so the rules run deterministically.

The fake libraries are built once per process (:func:`sdk_root`, :func:`hd_folder`): a vendor
package loads its library once, at import, and keeps it.
"""
from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np

from ..device_contract import PERIOD_S, Harness
from . import build
from .block import Block
from .physics import Physics, model_for

_TMP: dict[str, str] = {}


def scratch() -> Path:
    """A folder for this process's emulator files (removed at exit by the OS's tmp cleaning;
    the tests' fixtures use their own tmp_path for blocks)."""
    if "root" not in _TMP:
        _TMP["root"] = tempfile.mkdtemp(prefix="hapticproxy-emu-")
    return Path(_TMP["root"])


def sdk_root() -> Path:
    """The fake Force Dimension SDK of this process (built on first use); ``FDSDK`` points at it
    unless it was set already (then that SDK must be this process's fake)."""
    root = scratch() / "fdsdk"
    build.build_libdrd(root)
    os.environ.setdefault("FDSDK", str(root))
    return root


def attach_fd_blocks(paths) -> None:
    """Point the fake libdrd at these device blocks (``$HAPTICPROXY_EMU_BLOCKS``) and make it
    read the list again."""
    os.environ["HAPTICPROXY_EMU_BLOCKS"] = ":".join(str(p) for p in paths)
    sdk_root()
    from ...server.devices.forcedimension import sdk

    sdk().runtime._libdrd.emu_drd_reattach()


class ForceDimensionHarness(Harness):
    """The ``forcedimension`` driver on the fake libdrd, the physics stepped in this process."""

    continuous = True  # the device renders between commands; its firmware watchdog cuts

    def __init__(self, kind: str = "spatial", period_s: float = PERIOD_S, config: dict | None = None,
                 system_type: int = 33, hand: dict | None = None, calibrated: bool = True) -> None:
        super().__init__(period_s)
        from ...server.devices.forcedimension import make_forcedimension_device

        self.folder = Path(tempfile.mkdtemp(dir=scratch()))
        self.block = Block(self.folder / "dev.blk", create=True)
        model, mid = model_for("forcedimension", system_type)
        self.physics = Physics(self.block, model, model_id=mid, serial=4242, period_s=period_s, hand=hand,
                               calibrated=calibrated)
        attach_fd_blocks([self.block.path])
        self.driver = make_forcedimension_device({"kind": kind, **(config or {})}, period_s=period_s,
                                                 clock_ns=self.clock)

    def tick(self) -> None:
        super().tick()
        self.physics.step()

    def rendered(self) -> np.ndarray:
        return self.block.view("rendered").copy()

    def close(self) -> None:
        try:
            super().close()
        finally:
            self.block.close()


class HaplyHarness(Harness):
    """The ``haply`` driver on a fake Inverse3 (a pseudo-terminal served by its own process) or
    on a fake Inverse Service (``transport="service"``); the physics stepped in this process.

    Not ``continuous``: the Inverse3 renders the last force through a stall of the host (no
    firmware watchdog is documented for it); the driver cuts at its next call."""

    def __init__(self, kind: str = "spatial", period_s: float = PERIOD_S, config: dict | None = None,
                 transport: str = "serial", hand: dict | None = None, model_id: int = 0,
                 versegrip: bool = False) -> None:
        super().__init__(period_s)
        from ...server.devices.haply import make_haply_device
        from . import inverse3, inverse_service

        self.folder = Path(tempfile.mkdtemp(dir=scratch()))
        self.block = Block(self.folder / "dev.blk", create=True)
        model, _ = model_for("inverse3", 0)
        # the handle rests in front of the base, never at its origin (see haply.py's quirks)
        self.physics = Physics(self.block, model, model_id=model_id, serial=1181, period_s=period_s, hand=hand,
                               max_force_n=10.0, initial_pose=[0.0, -0.12, 0.08, 0.0, 0.0, 0.0])
        if transport == "serial":
            self.proc, where = inverse3.spawn(self.block.path, str(self.folder))
            cfg = {"transport": "serial", "port": where}
        else:
            self.proc, where = inverse_service.spawn(self.block.path, str(self.folder), versegrip=versegrip)
            cfg = {"transport": "service", "url": where}
        # generous: the fake shares 2 cores with everything else (a timeout is a lost device)
        cfg["timeout_s"] = 0.25
        try:
            self.driver = make_haply_device({"kind": kind, **cfg, **(config or {})}, period_s=period_s,
                                            clock_ns=self.clock)
        except BaseException:
            self._stop()
            raise

    def tick(self) -> None:
        super().tick()
        self.physics.step()

    def rendered(self) -> np.ndarray:
        return self.physics.command_now()  # the Inverse3 applies a force as it arrives

    def _stop(self) -> None:
        self.block["stop"] = 1.0
        try:
            self.proc.wait(timeout=10)
        except Exception:  # noqa: BLE001
            self.proc.kill()
            self.proc.wait()

    def close(self) -> None:
        try:
            super().close()
        finally:
            self._stop()
            self.block.close()


class HaplyServiceHarness(HaplyHarness):
    def __init__(self, kind: str = "spatial", period_s: float = PERIOD_S, **kw) -> None:
        super().__init__(kind, period_s, transport="service", **kw)


def hd_folder() -> Path:
    """The fake libHD of this process, built and loaded (by absolute path, globally, so the
    package's ``CDLL("libHD.so")`` binds it: the loader matches the SONAME of a loaded library)."""
    import ctypes

    folder = scratch() / "hd"
    lib = build.build_libhd(folder)
    if "hd" not in _TMP:
        _TMP["hd"] = str(lib)
        ctypes.CDLL(str(lib), mode=ctypes.RTLD_GLOBAL)
    return folder


def attach_hd_devices(devices: dict[str, str], lockstep: bool) -> None:
    """Point the fake libHD at these devices (``name -> block``) and make it read them again."""
    hd_folder()
    os.environ["HAPTICPROXY_EMU_HD_DEVICES"] = ",".join(f"{n}={p}" for n, p in devices.items())
    from ...server.devices.touch import hd

    lib = hd()._lib_hd
    lib.emu_hd_reattach()
    lib.emu_hd_set_lockstep(1 if lockstep else 0)


class TouchHarness(Harness):
    """The ``touch`` driver on the fake libHD; lock-step: the scheduler's thread is not started,
    each :meth:`tick` steps the physics and runs one servo tick (the driver's callback)."""

    continuous = True  # the servo callback renders between writes; its watchdog cuts

    def __init__(self, kind: str = "spatial", period_s: float = PERIOD_S, config: dict | None = None,
                 model: str = "Touch", hand: dict | None = None, calibrated: bool = True,
                 name: str = "Default Device") -> None:
        super().__init__(period_s)
        from ...server.devices.touch import make_touch_device

        self.folder = Path(tempfile.mkdtemp(dir=scratch()))
        self.block = Block(self.folder / "dev.blk", create=True)
        m, mid = model_for("touch", model)
        self.physics = Physics(self.block, m, model_id=mid, serial=22011, period_s=period_s, hand=hand,
                               calibrated=calibrated, initial_pose=[0.0, 0.0, 0.05, 0.0, 0.0, 0.0])
        attach_hd_devices({name: self.block.path}, lockstep=True)
        self.lib = __import__("pyOpenHaptics.hd", fromlist=["_lib_hd"])._lib_hd
        self.driver = make_touch_device({"kind": kind, **(config or {})}, period_s=period_s, clock_ns=self.clock)

    def tick(self) -> None:
        super().tick()
        self.physics.step()
        self.lib.emu_hd_tick()

    def rendered(self) -> np.ndarray:
        return self.physics.command_now()

    def close(self) -> None:
        try:
            super().close()
        finally:
            self.block.close()
