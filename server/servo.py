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
not tick, it writes the previous command again (what the safety filter last let through: the
device never waits, never gets anything new) and counts the tick as held (``SB_HELD``). What a
tick reports for Python (faults, a fade that ended) accumulates in ``TK_RC_STICKY`` until Python
takes it. A device fault or a non-finite value cuts the output in the servo thread at once (the
safety filter's reset: zero from the next tick), and the environment's silence starts the fade
there too, whenever Python gets to act on them.

The servo thread's own timing (its period jitter, ticks late, held) is measured here: each tick's
start goes into a ring (``SB_RING``), which ``bench devices`` and ``bench loop`` read.
"""
from __future__ import annotations

import numpy as np
from numba import cfunc, from_dtype, njit, types

from . import control as ctl
from . import safety as sf
from . import tick as tk_
from .native import address_as, atomic_cas, atomic_store, call_i32_ptr_ptr, monotonic_ns, voidptr_to_int
from .shm import STATUS_DTYPE, TEL_DTYPE

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

_F1 = types.Array(types.float64, 1, "C")
_F2 = types.Array(types.float64, 2, "C")
_I1 = types.Array(types.int64, 1, "C")
_I2 = types.Array(types.int64, 2, "C")
_TEL = types.Array(from_dtype(TEL_DTYPE), 1, "C", aligned=False)
_STAT = types.Array(from_dtype(STATUS_DTYPE), 1, "C", aligned=False)
#: the numba type of each field of ``tick.TickArrays``, in order
FIELD_TYPES = (_F1, _F1, _I1, _F1, _F1, _F2, _F1,
               _F1, _F1, _F1, _I1, _I1, _F1, _F2, _F1, _F1,
               _F1, _F1, _F2, _I2, _I1, _F1, _I1, _F2, _I2, _F2,
               _TEL, _I1, _I1, _I1, _STAT,
               _I1)
assert len(FIELD_TYPES) == len(tk_.TickArrays._fields)
NFIELDS = len(FIELD_TYPES)
_f1, _f2, _i1, _i2, _tel, _stat = (address_as(t) for t in (_F1, _F2, _I1, _I2, _TEL, _STAT))


def descriptor(T) -> np.ndarray:
    """int64[3 * NFIELDS]: (address, rows, cols) of each array of ``T`` (a ``TickArrays``), checked
    against :data:`FIELD_TYPES` (a view the callback builds must be the array Python holds)."""
    import numba

    d = np.zeros(3 * NFIELDS, dtype=np.int64)
    for k, (name, a, want) in enumerate(zip(T._fields, T, FIELD_TYPES)):
        got = numba.typeof(a)
        if got != want:
            raise TypeError(f"servo: TickArrays.{name} is {got}, the servo callback builds {want}")
        d[3 * k] = a.ctypes.data
        d[3 * k + 1] = a.shape[0]
        d[3 * k + 2] = a.shape[1] if a.ndim == 2 else 0
    return d


@njit(**_JIT)
def tick_arrays_at(addr):
    """The ``TickArrays`` a descriptor at ``addr`` describes, as views (nothing is copied)."""
    d = address_as_i64_view(addr)
    return tk_.TickArrays(
        _f1(d[0], (d[1],)), _f1(d[3], (d[4],)), _i1(d[6], (d[7],)), _f1(d[9], (d[10],)), _f1(d[12], (d[13],)),
        _f2(d[15], (d[16], d[17])), _f1(d[18], (d[19],)),
        _f1(d[21], (d[22],)), _f1(d[24], (d[25],)), _f1(d[27], (d[28],)), _i1(d[30], (d[31],)),
        _i1(d[33], (d[34],)), _f1(d[36], (d[37],)), _f2(d[39], (d[40], d[41])), _f1(d[42], (d[43],)),
        _f1(d[45], (d[46],)),
        _f1(d[48], (d[49],)), _f1(d[51], (d[52],)), _f2(d[54], (d[55], d[56])), _i2(d[57], (d[58], d[59])),
        _i1(d[60], (d[61],)), _f1(d[63], (d[64],)), _i1(d[66], (d[67],)), _f2(d[69], (d[70], d[71])),
        _i2(d[72], (d[73], d[74])), _f2(d[75], (d[76], d[77])),
        _tel(d[78], (d[79],)), _i1(d[81], (d[82],)), _i1(d[84], (d[85],)), _i1(d[87], (d[88],)),
        _stat(d[90], (d[91],)),
        _i1(d[93], (d[94],)))


@njit(**_JIT)
def address_as_i64_view(addr):
    return _i1(addr, (3 * NFIELDS,))


@njit(**_JIT)
def servo_tick(blk):
    """One servo tick (the callback's body; ``blk`` the servo block). Returns 1 (continue)."""
    now = monotonic_ns()
    blk[SB_ALL] += 1
    if blk[SB_RING] != 0:
        ring = _i1(blk[SB_RING], (blk[SB_RING_N],))
        ring[(blk[SB_ALL] - 1) % blk[SB_RING_N]] = now
    T = tick_arrays_at(blk[SB_DESC])
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
        if tk[tk_.TK_STATE] == tk_.S_ENGAGED and now - tk[tk_.TK_QUIET_SINCE_NS] > tk[tk_.TK_WATCHDOG_NS]:
            T.cs[ctl.CS_TARGET] = 0.0
        rcs = tk_.tick(T, now, late)
        if (rcs >> 8) != 0 or (rcs & 0xFF) == ctl.RC_NONFINITE:
            # a device fault or a non-finite value: zero from the next tick on, whenever Python acts
            sf.reset(T.cs[ctl.CS_SAFETY:ctl.CS_SAFETY + sf.NSS])
        tk[tk_.TK_RC_STICKY] |= rcs
        blk[SB_TICKS] += 1
        atomic_store(tk, tk_.TK_LOCK, 0)
    else:
        # Python is changing the tick's state: the device gets the previous command again
        if tk[tk_.TK_IO] == tk_.IO_NATIVE:
            call_i32_ptr_ptr(tk[tk_.TK_NATIVE_WRITE], tk[tk_.TK_NATIVE_CTX], T.cmd.ctypes.data)
        blk[SB_HELD] += 1
    blk[SB_LAST_NS] = now
    if blk[SB_END] != 0:
        call_i32_ptr_ptr(blk[SB_END], blk[SB_CTX], 0)
    return 1


@cfunc(types.uint32(types.voidptr), cache=True, nogil=True, error_model="numpy")
def _servo_callback(data):
    return servo_tick(_i1(voidptr_to_int(data), (NSB,)))

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
        self.desc = np.zeros(3 * NFIELDS, dtype=np.int64)

    def bind(self, T) -> None:
        """Point the callback at ``T`` (call with the tick lock held, or before the servo runs)."""
        d = descriptor(T)
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
