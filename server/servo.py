"""A device that owns the clock: the haptic tick called from the device SDK's servo thread.

Some SDKs run the servo loop themselves (OpenHaptics' scheduler calls its callbacks at 1 kHz from
a thread of its own) and sample and command the device only inside that callback. For them the
tick (``tick.tick``) runs *in* that thread, as the C callback :data:`SERVO_CALLBACK` (a numba
``cfunc``: no Python, no GIL). The callback gets one ``void *``: the address of a servo block
(int64[NSB], :class:`ServoBinding` owns it) holding the address of a descriptor of every array of
``tick.TickArrays`` (address and shape each), from which it rebuilds the arrays as views each tick,
and the device's own C functions: ``frame_begin(ctx)`` / ``frame_end(ctx)`` around the tick
(OpenHaptics' ``hdBeginFrame`` / ``hdEndFrame``) and ``read`` / ``write`` inside it (``IO_NATIVE``).

Python (the loop's lifecycle and protocol: ``HapticLoop`` in its service loop) and the servo
thread share the tick's arrays. They take turns through one lock word (``TK_LOCK``, a
compare-and-swap): Python holds it while it changes anything the tick reads (an engagement, a
model update, a fault's cut, a transition) and for no longer; a servo tick that finds it held does
not tick, it writes the previous command again (what the safety filter last let through, in the
device's frame through a workspace mapping: the device never waits, never gets anything new) and
counts the tick as held (``SB_HELD``). What a tick reports for Python (faults, a fade that ended)
accumulates in ``TK_RC_STICKY`` until Python takes it. A device fault or a non-finite value cuts
the output in the servo thread at once (the safety filter's reset: zero from the next tick), and
the environment's silence starts the fade there too, whenever Python gets to act on them.

The servo thread's own timing (its period jitter, ticks late, held) is measured here: each tick's
start goes into a ring (``SB_RING``), which ``bench devices`` and ``bench loop`` read.
"""
from __future__ import annotations

import numpy as np
from numba import cfunc, njit, types

from . import control as ctl
from . import safety as sf
from . import tick as tk_
from .native import atomic_cas, atomic_store, call_i32_ptr_ptr, monotonic_ns, voidptr_to_int

_JIT = dict(cache=True, nogil=True, error_model="numpy")

# ---- the servo block (int64[NSB])
SB_DESC = 0          # address of the descriptor (int64[3 * len(TickArrays._fields)])
SB_BEGIN = 1         # int32 frame_begin(void *ctx, void *unused) (0: none)
SB_END = 2           # int32 frame_end(void *ctx, void *unused) (0: none)
SB_CTX = 3           # the device's context pointer
SB_PERIOD_NS = 4     # the servo's nominal period
SB_LAST_NS = 5       # the start of the last tick
SB_TICKS = 6         # ticks run
SB_HELD = 7          # ticks held because Python had the lock
SB_RING = 8          # address of int64[SB_RING_N]: each tick's start, index SB_TICKS_ALL % SB_RING_N
SB_RING_N = 9
SB_ALL = 10          # callbacks (ticks run + held)
NSB = 12

@njit(**_JIT)
def servo_tick(blk):
    """One servo tick (the callback's body; ``blk`` the servo block). Returns 1 (continue)."""
    now = monotonic_ns()
    blk[SB_ALL] += 1
    if blk[SB_RING] != 0:
        ring = tk_.as_i64(blk[SB_RING], (blk[SB_RING_N],))
        ring[(blk[SB_ALL] - 1) % blk[SB_RING_N]] = now
    T = tk_.tick_arrays_at(blk[SB_DESC])
    tk = T.tk
    if blk[SB_BEGIN] != 0:
        call_i32_ptr_ptr(blk[SB_BEGIN], blk[SB_CTX], 0)
    if atomic_cas(tk, tk_.TK_LOCK, 0, 1) == 0:
        last = blk[SB_LAST_NS]
        late = 0
        if last != 0:
            late = now - (last + blk[SB_PERIOD_NS])
            if late < 0:
                late = 0
        # the environment's silence starts the fade here, at once (Python makes it a transition)
        if tk[tk_.TK_STATE] == tk_.LS_ENGAGED and now - tk[tk_.TK_QUIET_SINCE_NS] > tk[tk_.TK_WATCHDOG_NS]:
            T.cs[ctl.CS_TARGET] = 0.0
        rcs = tk_.tick(T, now, late)
        if (rcs >> 8) != 0 or (rcs & 0xFF) == ctl.RC_NONFINITE:
            # a device fault or a non-finite value: zero from the next tick on, whenever Python acts
            sf.reset(T.cs[ctl.CS_SAFETY:ctl.CS_SAFETY + sf.NSS])
        tk[tk_.TK_RC_STICKY] |= rcs
        blk[SB_TICKS] += 1
        atomic_store(tk, tk_.TK_LOCK, 0)
    else:
        # Python is changing the tick's state: the device gets the previous command again (in its
        # own frame: through a mapping, what map_command made of it)
        if tk[tk_.TK_IO] == tk_.IO_NATIVE:
            call_i32_ptr_ptr(tk[tk_.TK_NATIVE_WRITE], tk[tk_.TK_NATIVE_CTX], tk_.device_command(T).ctypes.data)
        blk[SB_HELD] += 1
    blk[SB_LAST_NS] = now
    if blk[SB_END] != 0:
        call_i32_ptr_ptr(blk[SB_END], blk[SB_CTX], 0)
    return 1


@cfunc(types.uint32(types.voidptr), cache=True, nogil=True, error_model="numpy")
def _servo_callback(data):
    return servo_tick(tk_.as_i64(voidptr_to_int(data), (NSB,)))

#: ``HDCallbackCode callback(void *servo_block)``: the address a device-clocked driver schedules
SERVO_CALLBACK = _servo_callback.address


class ServoBinding:
    """The servo block, the descriptor and the tick ring for one ``TickArrays``; rebuilt (``bind``)
    under the lock when the tick's arrays change (an engagement binds the new model's). Keeps
    every array the callback reaches alive."""

    def __init__(self, period_ns: int, begin: int = 0, end: int = 0, ctx: int = 0, ring_n: int = 8192) -> None:
        self.block = np.zeros(NSB, dtype=np.int64)
        self.ring = np.zeros(ring_n, dtype=np.int64)
        b = self.block
        b[SB_BEGIN], b[SB_END], b[SB_CTX] = begin, end, ctx
        b[SB_PERIOD_NS] = int(period_ns)
        b[SB_RING] = self.ring.ctypes.data
        b[SB_RING_N] = ring_n
        self._keep = []
        self.desc = np.zeros(3 * tk_.NFIELDS, dtype=np.int64)

    def bind(self, T) -> None:
        """Point the callback at ``T`` (call with the tick lock held, or before the servo runs)."""
        d = tk_.descriptor(T)
        self._keep = [T, d]  # the arrays and their descriptor live as long as the callback reads them
        self.block[SB_DESC] = d.ctypes.data
        self.desc = d

    @property
    def address(self) -> int:
        """The ``void *`` the callback is scheduled with."""
        return int(self.block.ctypes.data)

    def periods_us(self) -> np.ndarray:
        """The periods between the ticks recorded in the ring (oldest first), us."""
        n = int(self.block[SB_ALL])
        k = min(n, len(self.ring))
        if k < 2:
            return np.zeros(0)
        idx = (np.arange(n - k, n)) % len(self.ring)
        return np.diff(self.ring[idx]) * 1e-3


@njit(**_JIT)
def lock(tk):
    """Take the tick lock for Python (spins; a servo tick holds it for one tick at most)."""
    while atomic_cas(tk, tk_.TK_LOCK, 0, 2) != 0:
        pass


@njit(**_JIT)
def unlock(tk):
    atomic_store(tk, tk_.TK_LOCK, 0)
