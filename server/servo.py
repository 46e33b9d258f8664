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
SB_TK = 11           # clock thread: the address of the tick's words (int64[tick.NTK])
SB_RUN = 12          # clock thread: 1 while it should run (Python sets 0 to end it)
SB_MISSED = 13       # clock thread: periods skipped while held, counted at the next tick run
SB_CMD = 14          # clock thread: the address of the command the device is written (stable:
                     # the controller's, or the mapping's image of it), for a held tick
SB_NEXT_NS = 15      # when the next tick is due (written after each tick, run or held): Python
                     # takes the lock only with room before it (``lock_between_ticks``)
NSB = 16

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
        _locked_tick(blk, T, now, late)
        atomic_store(tk, tk_.TK_LOCK, 0)
    else:
        _held_tick(blk, T)
    blk[SB_LAST_NS] = now
    blk[SB_NEXT_NS] = now + blk[SB_PERIOD_NS]
    if blk[SB_END] != 0:
        call_i32_ptr_ptr(blk[SB_END], blk[SB_CTX], 0)
    return 1


@njit(**_JIT)
def _locked_tick(blk, T, now, late):
    """A tick run with the lock taken (a servo thread's or the clock thread's)."""
    tk = T.tk
    # the environment's silence starts the fade here, at once, and the rows say so from this tick
    # on; Python makes it the transition it is (``LoopLife.take_tick_fade``) at its next pass
    if tk_.silent(tk, now):
        T.cs[ctl.CS_TARGET] = 0.0
        tk[tk_.TK_STATE] = tk_._LS_FADING
    rcs = tk_.tick(T, now, late)
    if (rcs >> 8) != 0 or (rcs & 0xFF) == ctl.RC_NONFINITE:
        # a device fault or a non-finite value: zero from the next tick on, whenever Python acts
        sf.reset(T.cs[ctl.CS_SAFETY:ctl.CS_SAFETY + sf.NSS])
    tk[tk_.TK_RC_STICKY] |= rcs
    blk[SB_TICKS] += 1


@njit(**_JIT)
def _held_tick(blk, T):
    """Python is changing the tick's state: the device gets the previous command again (in its
    own frame: through a mapping, what map_command made of it)."""
    tk = T.tk
    if tk[tk_.TK_IO] == tk_.IO_NATIVE:
        call_i32_ptr_ptr(tk[tk_.TK_NATIVE_WRITE], tk[tk_.TK_NATIVE_CTX], tk_.device_command(T).ctypes.data)
    blk[SB_HELD] += 1


@njit(**_JIT)
def clock_tick(blk, tk, now, late, missed):
    """One period of the clock thread, woken at ``now`` (see :func:`run_clock`)."""
    blk[SB_ALL] += 1
    if blk[SB_RING] != 0:
        ring = tk_.as_i64(blk[SB_RING], (blk[SB_RING_N],))
        ring[(blk[SB_ALL] - 1) % blk[SB_RING_N]] = now
    if atomic_cas(tk, tk_.TK_LOCK, 0, 1) == 0:
        # the arrays are read from the descriptor with the lock held: an engagement binds new ones
        # (under the lock), and the old descriptor may be gone after it
        T = tk_.tick_arrays_at(blk[SB_DESC])
        tk_.count_missed(T, missed + blk[SB_MISSED])
        blk[SB_MISSED] = 0
        gap = now - tk[tk_.TK_LAST_WRITE_NS]
        if gap > tk[tk_.TK_STALL_GAP_NS]:
            # the process did not run (a stall): Python classifies it (LoopLife.see_wake); the
            # environment's silence counts from its end (its updates waited in the socket)
            tk[tk_.TK_STALL_SEEN] += 1
            tk[tk_.TK_STALL_WAKE_NS] = now
            tk[tk_.TK_STALL_FROM_NS] = tk[tk_.TK_LAST_WRITE_NS]
            if tk[tk_.TK_QUIET_SINCE_NS] < now:
                tk[tk_.TK_QUIET_SINCE_NS] = now
            if tk[tk_.TK_DEV_WD_NS] > 0 and gap >= tk[tk_.TK_DEV_WD_NS]:
                # as long as the device's watchdog: it cut the output; nothing comes back until
                # Python's stall recovery ramps it in (the same cut as LoopLife.on_stall_trip's:
                # gain and target zero, CS_TARGET being the filter's own target)
                sf.reset(T.cs[ctl.CS_SAFETY:ctl.CS_SAFETY + sf.NSS])
        _locked_tick(blk, T, now, late)
        end = tk[tk_.TK_LAST_WRITE_NS]
        if end - now > tk[tk_.TK_STALL_GAP_NS]:
            # the process stopped inside this tick (its device write came that much after its
            # read): a stall like one between ticks, reported and cut the same way (the
            # single-thread loop sees it in the same step: LoopLife.stalled_recently)
            tk[tk_.TK_STALL_SEEN] += 1
            tk[tk_.TK_STALL_WAKE_NS] = end
            tk[tk_.TK_STALL_FROM_NS] = now
            if tk[tk_.TK_QUIET_SINCE_NS] < end:
                tk[tk_.TK_QUIET_SINCE_NS] = end
            if tk[tk_.TK_DEV_WD_NS] > 0 and end - now >= tk[tk_.TK_DEV_WD_NS]:
                sf.reset(T.cs[ctl.CS_SAFETY:ctl.CS_SAFETY + sf.NSS])
        tk[tk_.TK_TICKS] += 1
        tk[tk_.TK_HK_COUNT] += 1
        atomic_store(tk, tk_.TK_LOCK, 0)
    else:
        # Python is changing the tick's state: the arrays may be rebound right now, so a held
        # tick reaches only the words and the command (both the loop's for its whole life)
        blk[SB_MISSED] += missed
        if tk[tk_.TK_IO] == tk_.IO_NATIVE:
            call_i32_ptr_ptr(tk[tk_.TK_NATIVE_WRITE], tk[tk_.TK_NATIVE_CTX], blk[SB_CMD])
        blk[SB_HELD] += 1
    blk[SB_LAST_NS] = now
    blk[SB_NEXT_NS] = tk[tk_.TK_DEADLINE_NS]  # (moved on as the thread woke)


@njit(**_JIT)
def run_clock(blk):
    """The clock thread of a loop that owns the clock (``[loop] protocol_thread``): wait for each
    deadline (``tick.wait_until_deadline``: absolute deadlines, sleep then a bounded spin) and tick
    with the lock taken, or hold (the previous command again) while Python has it, until
    ``SB_RUN`` is 0. Never returns to Python in between, never takes the GIL: everything Python
    does (the protocol, the lifecycle, housekeeping) runs on another thread, beside it."""
    tk = tk_.as_i64(blk[SB_TK], (tk_.NTK,))
    while blk[SB_RUN] != 0:
        now, late, missed = tk_.wait_until_deadline(tk)
        clock_tick(blk, tk, now, late, missed)
    return 0


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
def lock_between_ticks(tk, blk, room_ns, patience_ns):
    """Take the tick lock for Python in the gap after a tick (a clock thread's or a device's servo
    thread's, ``blk`` its block): once the next tick is due at least ``room_ns`` from now
    (``SB_NEXT_NS``, written after each tick: while a tick is under way it still names the one
    under way, which is due already), so that what Python does with the lock ends before the
    next tick wants it. After ``patience_ns`` of waiting (the ticking thread stalled, or gone) it
    takes the lock as :func:`lock` does. Returns the time it waited, ns."""
    t0 = monotonic_ns()
    while True:
        now = monotonic_ns()
        if blk[SB_NEXT_NS] - now >= room_ns or now - t0 > patience_ns:
            if atomic_cas(tk, tk_.TK_LOCK, 0, 2) == 0:
                return now - t0


@njit(**_JIT)
def unlock(tk):
    atomic_store(tk, tk_.TK_LOCK, 0)
