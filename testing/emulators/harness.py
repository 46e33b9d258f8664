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
