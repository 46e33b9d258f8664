"""One haptic tick as one compiled call, and the compiled loop that owns the clock.

``tick(T, wake_ns, late_ns)`` is everything a haptic period needs, in this order, the device
sampled and commanded first after the deadline:

1. read the device (``IO_SIM``: the simulated device's kernel; ``IO_NATIVE``: a C function of
   the device's library, through ``native.call_i32_ptr_ptr``; ``IO_EXTERNAL``: the caller read it
   into ``T.dev`` and passes its status in ``T.tk[TK_EXT_RC]``); a position frozen under force
   (``devices.frozen``, judged on the raw row) is the read's fault ``DEV_FAULT_FROZEN``; with a
   workspace mapping (``TK_MAPPED``), ``devices.mapping.map_state`` then turns the row into the
   scene's (scale, offset, rotation, the clutch; its array is ``T.map``);
2. a model update Python staged in the engaged model's slot (``model/slot.py``), applied by the
   model's own update kernel (``apply_staged``), then the controller, the model step and the
   safety filter (``control.haptic_step`` or ``haptic_step_linkage``);
3. with a mapping, ``map_command`` turns the filter's wrench into the device's (``T.map``'s block
   ``M_CMD``); write the device (``IO_EXTERNAL``: the caller writes ``device_command(T)`` after
   the call);
4. after a staged update was applied, what acknowledges it into the slot, which is then
   Python's again (``acknowledge_staged``);
5. account: histograms, maxima and one telemetry row (``rings.account``).

It allocates nothing and touches no Python object; ``T`` (:class:`TickArrays`) holds every array it
reads or writes, each with its layout declared once where its owner lives (``control``,
``model.layout``, ``devices.layout``, ``shm``) and this module's own ``TK_*`` words.

Who calls it:

- ``run_ticks(T)``, a compiled loop that owns the clock (absolute deadlines; ``clock_nanosleep``
  until ``spin_ns`` before each, then a spin on the monotonic clock; ``spin_ns`` is at most
  ``SPIN_MAX_SHARE`` of the period, so the thread sleeps in every period and never meets the
  kernel's real-time throttling). It releases the GIL and returns to Python only on events: a step that
  needs Python (an update that engages a session, a stall, the environment's silence), a tick
  that applied a staged update (its acknowledgement is Python's), a tick
  that reported a fault, a fade that ended, housekeeping due, a datagram waiting (``poll`` on the
  transport's socket), a stop. The plain steps between (most of them) never touch Python.
- ``HapticLoop.step`` in Python (simulated time in tests, and the steps ``run_ticks`` hands back):
  the same ``tick``, then the protocol work after the device was written.
- a device SDK's servo thread through a C callback (``servo.py``), for a device that owns the
  clock.
"""
from __future__ import annotations

from collections import namedtuple

import numpy as np
from numba import from_dtype, njit, types

from . import control as ctl
from . import passivity as pv
from .devices.base import DEV_FAULT_FROZEN, DS_BUTTONS
from .devices.dynamics import sim_read, sim_write_hand
from .devices.frozen import watch as frozen_watch
from .devices.mapping import M_CMD, map_command, map_state
from .native import address_as, atomic_store, call_i32_ptr_ptr, fd_readable, monotonic_ns, sleep_until_ns
from .lifecycle import LS
from .model.kernels import update_rigid
from .model.linkage import update_linkage
from .model.slot import AX_GRANTED_J, AX_HAND, AX_INPUTS, AX_WORK_J, slot_at
from .rings import account
from .shm import STATUS_DTYPE, TEL_DTYPE

_JIT = dict(cache=True, nogil=True, error_model="numpy")

#: Every array the tick touches. The controller's (``control.Controller``), the device's (its
#: state row ``dev``, a simulated device's own arrays ``d*``: dummies for other devices, and the
#: workspace mapping's array ``map``, ``devices.mapping.M_*``: a dummy without a mapping), the
#: model's (``LocalModel.kernel_args`` and, for a linkage, ``linkage_args``: dummies for a rigid
#: tool), the shared rings' (``shm.SharedState``) and the tick's own words ``tk``.
TickArrays = namedtuple("TickArrays", (
    "cp", "cs", "cc", "cmd", "hand", "R", "c",
    "dev", "dpar", "dst", "dcnt", "dctl", "dhp", "dtab", "dhout", "dcmd", "map",
    "par", "st", "C", "CI", "cnt", "wk", "lmeta", "lk", "lki", "lw",
    "tel", "head", "hist_late", "hist_step", "stat",
    "tk",
))

# ---- the tick's words (int64[NTK])
TK_PERIOD_NS = 0
TK_DEADLINE_NS = 1      # the next deadline (absolute, monotonic clock)
TK_T0_NS = 2            # when the loop started
TK_LAST_WRITE_NS = 3    # the end of the last tick (its device write and accounting)
TK_STALL_GAP_NS = 4     # a gap between two ticks longer than this is a stall (Python handles it)
TK_IO = 5               # IO_*: how the tick reaches the device
TK_ACTIVE = 6           # 1: a session has engaged the model (else the filter runs on zero)
TK_LINKAGE = 7          # 1: the engaged tool is a linkage
TK_KIND = 8             # the rigid tool's kind (model.layout TOOL_*)
TK_STATE = 9            # the loop state (lifecycle LS code), for the telemetry row and the checks
TK_UPDATES = 10         # model updates applied, for the telemetry row
TK_SIMULATED = 11       # 1: simulated time (the step's end is wake + TK_SIM_COST_NS)
TK_SIM_COST_NS = 12
TK_EXT_RC = 13          # IO_EXTERNAL: the status of the caller's device read
TK_RC = 14              # the last tick's results: control rc | device read rc << 8 | write rc << 16
TK_WAKE_NS = 15         # the wake-up of the step run_ticks hands to Python (EV_STEP)
TK_LATE_NS = 16
TK_SPIN_NS = 17         # how long before a deadline run_ticks stops sleeping and spins
TK_HK_EVERY = 18        # ticks between housekeeping
TK_HK_COUNT = 19        # ticks since the last housekeeping
TK_FD = 20              # the transport's socket (-1: none; run_ticks then hands back each period)
TK_NEEDS_PYTHON = 21    # 1: the next step has Python work (an update waiting: to engage, or for the slot)
TK_WATCHDOG_NS = 22     # the environment's silence that starts a fade while engaged
TK_QUIET_SINCE_NS = 23  # when the environment was last heard (or the loop's last stall ended)
TK_STOP = 24            # 1: run_ticks returns at once (a request from Python or a signal)
TK_NATIVE_READ = 25     # IO_NATIVE: int32 read(void *ctx, double *state_row)
TK_NATIVE_WRITE = 26    # IO_NATIVE: int32 write(void *ctx, const double *wrench)
TK_NATIVE_CTX = 27      # IO_NATIVE: the device's context pointer
TK_TICKS = 28           # ticks run by run_ticks (the rest ran in Python)
TK_RETURNS = 29         # times run_ticks handed back to Python
TK_MISSED = 30          # deadlines missed (whole periods skipped)
TK_RX_PENDING = 31      # a transport without a socket received something (its thread sets it)
TK_PREV_WRITE_NS = 32   # the end of the tick before the last (a stall inside the last one shows
                        # as the time from there to its end)
TK_LOCK = 33            # device-clocked: 0 free, 1 a servo tick runs, 2 Python changes the arrays
TK_RC_STICKY = 34       # device-clocked: every tick's results since Python last took them (OR)
TK_POLL_EVERY = 35      # a transport without a socket is polled by Python every this many ticks
TK_POLL_COUNT = 36      # ticks since it was
TK_MAPPED = 37          # 1: the device is seen through the workspace mapping ``T.map`` (map_state
                        # after the read, map_command before the write); 0: as it is
TK_DEV_WD_NS = 38       # the device's watchdog: a gap between ticks this long is a stall trip
                        # (the clock thread cuts at once, Python classifies it: LoopLife.see_wake)
TK_STALL_SEEN = 39      # clock thread: stalls seen since Python last took them
TK_STALL_WAKE_NS = 40   # clock thread: the wake-up that ended the last stall seen
TK_STALL_FROM_NS = 41   # clock thread: the end of the tick before it
TK_UPD_DESC = 42        # the engaged model's update slot (``model.slot``): its descriptor's address (0: none)
TK_UPD_SEQ = 43         # Python: updates staged in the slot (moved on after the slot's arrays are written)
TK_UPD_DONE = 44        # the tick: the staged update it applied last (== TK_UPD_SEQ: the slot is Python's)
TK_UPD_CODE = 45        # the tick: the update kernel's code for it (``model.layout`` E_*; 0: applied)
TK_UPD_N = 46           # Python: the staged update's rows
TK_UPD_USE_Q = 47       # Python: 1: the slot's ``q`` is the engine's tool configuration (contact_frame engine)
TK_UPD_HEARD_NS = 48    # Python: when the staged update was received (applied: the environment heard then)
NTK = 49

#: the largest share of a period ``run_ticks`` may spin before a deadline. The thread then sleeps
#: at least the rest of every period (SCHED_FIFO stays far below the kernel's real-time
#: throttling, 95 % of each second, and the core's other threads run then). Not less: a
#: ``clock_nanosleep`` on this class of VM wakes 25-35 us late at p50 and 35-75 us at p99 (timer
#: slack 1 ns, SCHED_FIFO; /tmp/slp.py-style measurement, 2026-12-05), so at 10 kHz a quarter
#: period (25 us) woke late in most periods (``bench loop --rate 10000 --seconds 15``: lateness
#: p50 3 / p99 21 us, missed 0.065 %) and 60 % does not (p50 1 / p99 10 us, missed 0.038 %).
SPIN_MAX_SHARE = 0.6

IO_EXTERNAL = 0
IO_SIM = 1
IO_NATIVE = 2

# run_ticks' events: why it handed back
EV_STEP = 1        # the step at TK_WAKE_NS needs Python (it was not ticked)
EV_TICKED = 2      # a tick ran whose aftermath needs Python (a fault, a fade's end, housekeeping,
                   # a datagram waiting)
EV_STOP = 3

LS_ENGAGED = 1      # lifecycle LS codes the checks read (asserted against lifecycle below)
_LS_FADING = 2
_LS_STOPPING = 4


@njit(**_JIT)
def device_command(T):
    """The wrench the tick writes to the device (``IO_EXTERNAL``: the caller does): the safety
    filter's ``T.cmd``, or through a mapping its image in the device's frame (``T.map``'s block
    ``M_CMD``)."""
    if T.tk[TK_MAPPED] != 0:
        return T.map[M_CMD:M_CMD + 6]
    return T.cmd


@njit(**_JIT)
def tick(T, wake_ns, late_ns):
    """One haptic period (see the module docstring). Returns the packed results (also in
    ``TK_RC``): the controller's rc, the device read's << 8, the write's << 16; 0: all fine."""
    tk = T.tk
    tk[TK_PREV_WRITE_NS] = tk[TK_LAST_WRITE_NS]
    io = tk[TK_IO]
    if io == IO_SIM:
        rc_dev = sim_read(T.dst, T.dctl, T.dcnt, T.dev, wake_ns)
    elif io == IO_NATIVE:
        rc_dev = call_i32_ptr_ptr(tk[TK_NATIVE_READ], tk[TK_NATIVE_CTX], T.dev.ctypes.data)
    else:
        rc_dev = tk[TK_EXT_RC]
    mapped = tk[TK_MAPPED] != 0
    # judged before the controller uses it, on the raw row (device frame: a held clutch keeps the
    # mapped row still on purpose) against the force written to the device in the period it covers
    if rc_dev == 0 and frozen_watch(T.cp, ctl.CP_FROZEN, T.cs, ctl.CS_FROZEN, T.dev, device_command(T), wake_ns):
        rc_dev = DEV_FAULT_FROZEN
    if mapped:
        map_state(T.dev, T.map)  # device frame -> the scene's, the clutch (devices/mapping.py)
    # a staged model update: applied before the model steps (after the device read: the sample
    # keeps its time), acknowledged from this tick's state after the device write
    staged = tk[TK_UPD_SEQ] != tk[TK_UPD_DONE] and tk[TK_UPD_DESC] != 0
    if staged:
        apply_staged(T)
    if tk[TK_LINKAGE] != 0:
        rc = ctl.haptic_step_linkage(T.cp, T.cs, T.cc, T.dev, T.cmd, T.par, T.lmeta, T.lk, T.lki, T.st, T.C, T.CI,
                                     T.cnt, T.wk, T.lw, T.hand)
    else:
        rc = ctl.haptic_step(T.cp, T.cs, T.cc, T.dev, T.cmd, tk[TK_ACTIVE], tk[TK_KIND], T.par, T.st, T.C, T.CI,
                             T.cnt, T.wk, T.hand, T.R, T.c)
    wcmd = T.cmd
    if mapped:
        wcmd = device_command(T)
        map_command(T.cmd, T.map, wcmd)  # the scene's wrench -> the device's, the clutch's gain
    rc_w = 0
    simulated = tk[TK_SIMULATED] != 0
    if io == IO_SIM:
        rc_w = sim_write_hand(T.dpar, T.dst, T.dcnt, T.dctl, T.dhp, T.dtab, T.dhout, wcmd, T.dcmd,
                              wake_ns if simulated else monotonic_ns())
    elif io == IO_NATIVE:
        rc_w = call_i32_ptr_ptr(tk[TK_NATIVE_WRITE], tk[TK_NATIVE_CTX], wcmd.ctypes.data)
    if staged:
        acknowledge_staged(T)
    end = wake_ns + tk[TK_SIM_COST_NS] if simulated else monotonic_ns()
    tk[TK_LAST_WRITE_NS] = end
    account(T.tel, T.head, T.hist_late, T.hist_step, T.stat, tk[TK_PERIOD_NS], late_ns, end - wake_ns,
            wake_ns - tk[TK_T0_NS], float(tk[TK_STATE]), tk[TK_UPDATES], T.cs, T.cnt, T.dev, T.cmd)
    packed = (rc & 0xFF) | ((rc_dev & 0xFF) << 8) | ((rc_w & 0xFF) << 16)
    tk[TK_RC] = packed
    return packed


@njit(**_JIT)
def apply_staged(T):
    """The update staged in the engaged model's slot (``model/slot.py``), applied by the model's
    own kernel; its code in ``TK_UPD_CODE``. Applied: counted (``TK_UPDATES``), the environment
    heard when it was received (``TK_QUIET_SINCE_NS``), the work the engine declares into the
    passivity layer's tank (``ax[AX_GRANTED_J]``: what the tank took). Refused: nothing changes
    (the kernel's contract)."""
    tk = T.tk
    U = slot_at(tk[TK_UPD_DESC])
    n = tk[TK_UPD_N]
    use = tk[TK_UPD_USE_Q]
    if tk[TK_LINKAGE] != 0:
        code = update_linkage(T.par, T.lmeta, T.lk, T.lki, T.st, T.C, T.CI, T.cnt, T.wk, T.lw, U.keys, U.pos,
                              U.nrm, U.sep, U.vc, n, U.sel, U.newF, U.newI, U.q, use, U.lw_e)
    else:
        code = update_rigid(tk[TK_KIND], T.par, T.st, T.C, T.CI, T.cnt, T.wk, U.keys, U.pos, U.nrm, U.sep, U.vc, n,
                            U.sel, U.newF, U.newI, U.q, use, U.st_e, U.Re, U.ce)
    tk[TK_UPD_CODE] = code
    U.ax[AX_GRANTED_J] = 0.0
    if code == 0:
        tk[TK_UPDATES] += 1
        if tk[TK_UPD_HEARD_NS] > tk[TK_QUIET_SINCE_NS]:
            tk[TK_QUIET_SINCE_NS] = tk[TK_UPD_HEARD_NS]
        U.ax[AX_GRANTED_J] = pv.grant(T.cp[ctl.CP_TANK:ctl.CP_TANK + pv.NTP], T.cs[ctl.CS_TANK:ctl.CS_TANK + pv.NTS],
                                      U.ax[AX_WORK_J])


@njit(**_JIT)
def acknowledge_staged(T):
    """After the tick that applied the staged update: what acknowledges it (the model's state, a
    linkage's link poses, the hand wrench, the device's inputs) into the slot, then the slot is
    Python's again (``TK_UPD_DONE``, an atomic store after them)."""
    tk = T.tk
    U = slot_at(tk[TK_UPD_DESC])
    if tk[TK_UPD_CODE] == 0:
        U.ack_st[:] = T.st
        if tk[TK_LINKAGE] != 0:
            U.ack_lw[:, :] = T.lw
        for k in range(6):
            U.ax[AX_HAND + k] = T.cs[ctl.CS_HAND + k]
        for k in range(3):
            U.ax[AX_INPUTS + k] = T.dev[DS_BUTTONS + k]
    atomic_store(tk, TK_UPD_DONE, tk[TK_UPD_SEQ])


@njit(**_JIT)
def _needs_python(T, wake_ns):
    """The step at ``wake_ns`` has work only Python does: an update to apply or acknowledge, a
    stall to classify, the environment's silence to act on."""
    tk = T.tk
    if tk[TK_NEEDS_PYTHON] != 0:
        return True
    if wake_ns - tk[TK_LAST_WRITE_NS] > tk[TK_STALL_GAP_NS]:
        return True
    return silent(tk, wake_ns)


@njit(**_JIT)
def silent(tk, now_ns):
    """Engaged, and the environment not heard for its watchdog (an update staged for the tick is
    heard: it is applied in the next tick)."""
    return (tk[TK_STATE] == LS_ENGAGED and now_ns - tk[TK_QUIET_SINCE_NS] > tk[TK_WATCHDOG_NS]
            and tk[TK_UPD_SEQ] == tk[TK_UPD_DONE])


@njit(**_JIT)
def _after_needs_python(T):
    """The tick just run left work for Python: a fault, a fade that reached zero, housekeeping."""
    tk = T.tk
    if tk[TK_RC] != 0:
        return True
    st = tk[TK_STATE]
    if (st == _LS_FADING or st == _LS_STOPPING) and T.cs[ctl.CS_GAIN] <= 0.0:
        return True
    return tk[TK_HK_COUNT] >= tk[TK_HK_EVERY]


@njit(**_JIT)
def wait_until_deadline(tk):
    """Sleep, then spin, until the next deadline; move it on, skipping whole periods missed
    (counted in ``TK_MISSED``). Returns ``(wake_ns, late_ns, missed)``; the caller counts the
    missed periods where the tick's arrays keep them (:func:`count_missed`)."""
    deadline = tk[TK_DEADLINE_NS]
    period = tk[TK_PERIOD_NS]
    wake_at = deadline - tk[TK_SPIN_NS]
    now = monotonic_ns()
    if now < wake_at:
        sleep_until_ns(wake_at)
        now = monotonic_ns()
    while now < deadline:
        now = monotonic_ns()
    late = now - deadline
    missed = 0
    if late >= period:
        missed = late // period
        tk[TK_MISSED] += missed
        tk[TK_DEADLINE_NS] = deadline + (missed + 1) * period
    else:
        tk[TK_DEADLINE_NS] = deadline + period
    return now, late, missed


@njit(**_JIT)
def count_missed(T, missed):
    """Whole periods skipped: in the status, and in the safety filter's gain (which moves on as if
    they had run)."""
    if missed > 0:
        T.stat[0].missed_deadlines += float(missed)
        T.cs[ctl.CS_SKIPPED] += float(missed)


@njit(**_JIT)
def wait_deadline(T):
    """Sleep, then spin, until the next deadline; move it on (skipping whole periods missed, which
    the safety filter's gain still counts). Returns ``(wake_ns, late_ns)``."""
    now, late, missed = wait_until_deadline(T.tk)
    count_missed(T, missed)
    return now, late


@njit(**_JIT)
def run_ticks(T):
    """Tick on the clock until Python is needed (see the module docstring); returns ``EV_*``.
    A datagram waiting is seen on the socket ``TK_FD`` or, for a transport without one, through
    ``TK_RX_PENDING``, which its receiving thread sets."""
    tk = T.tk
    while True:
        if tk[TK_STOP] != 0:
            return EV_STOP
        wake, late = wait_deadline(T)
        if _needs_python(T, wake):
            tk[TK_WAKE_NS] = wake
            tk[TK_LATE_NS] = late
            tk[TK_RETURNS] += 1
            return EV_STEP
        done = tk[TK_UPD_DONE]
        tick(T, wake, late)
        tk[TK_TICKS] += 1
        if tk[TK_UPD_DONE] != done:  # a staged update applied: its acknowledgement is Python's
            tk[TK_RETURNS] += 1
            return EV_TICKED
        tk[TK_HK_COUNT] += 1
        polled = False
        if tk[TK_FD] < 0:  # no socket to watch (Zenoh, memory): Python polls every millisecond
            tk[TK_POLL_COUNT] += 1
            if tk[TK_POLL_COUNT] >= tk[TK_POLL_EVERY]:
                tk[TK_POLL_COUNT] = 0
                polled = True
        if (_after_needs_python(T) or polled or tk[TK_RX_PENDING] != 0
                or (tk[TK_FD] >= 0 and fd_readable(tk[TK_FD]) != 0)):
            tk[TK_RETURNS] += 1
            return EV_TICKED


_F1 = types.Array(types.float64, 1, "C")
_F2 = types.Array(types.float64, 2, "C")
_I1 = types.Array(types.int64, 1, "C")
_I2 = types.Array(types.int64, 2, "C")
_TEL = types.Array(from_dtype(TEL_DTYPE), 1, "C", aligned=False)
_STAT = types.Array(from_dtype(STATUS_DTYPE), 1, "C", aligned=False)
#: the numba type of each field of ``tick.TickArrays``, in order
FIELD_TYPES = (_F1, _F1, _I1, _F1, _F1, _F2, _F1,
               _F1, _F1, _F1, _I1, _I1, _F1, _F2, _F1, _F1, _F1,
               _F1, _F1, _F2, _I2, _I1, _F1, _I1, _F2, _I2, _F2,
               _TEL, _I1, _I1, _I1, _STAT,
               _I1)
assert len(FIELD_TYPES) == len(TickArrays._fields)
NFIELDS = len(FIELD_TYPES)
_f1, _f2, _i1, _i2, _tel, _stat = (address_as(t) for t in (_F1, _F2, _I1, _I2, _TEL, _STAT))
#: an int64 array at an address (the servo block, the tick ring)
as_i64 = _i1


def descriptor(T, check: bool = False) -> np.ndarray:
    """int64[3 * NFIELDS]: (address, rows, cols) of each array of ``T`` (a ``TickArrays``).
    ``check``: each array's numba type against :data:`FIELD_TYPES` (a view the reader builds must
    be the array Python holds); the loop checks at warm-up, not at every engagement (numba's
    types cost allocations)."""
    d = np.zeros(3 * NFIELDS, dtype=np.int64)
    if check:
        import numba

        for name, a, want in zip(T._fields, T, FIELD_TYPES):
            got = numba.typeof(a)
            if got != want:
                raise TypeError(f"tick: TickArrays.{name} is {got}, the descriptor's reader builds {want}")
    for k, a in enumerate(T):
        d[3 * k] = a.__array_interface__["data"][0]  # (``a.ctypes`` keeps a helper on each array)
        d[3 * k + 1] = a.shape[0]
        d[3 * k + 2] = a.shape[1] if a.ndim == 2 else 0
    return d


@njit(**_JIT)
def tick_arrays_at(addr):
    """The ``TickArrays`` a descriptor at ``addr`` describes, as views (nothing is copied)."""
    d = address_as_i64_view(addr)
    return TickArrays(
        _f1(d[0], (d[1],)), _f1(d[3], (d[4],)), _i1(d[6], (d[7],)), _f1(d[9], (d[10],)), _f1(d[12], (d[13],)),
        _f2(d[15], (d[16], d[17])), _f1(d[18], (d[19],)),
        _f1(d[21], (d[22],)), _f1(d[24], (d[25],)), _f1(d[27], (d[28],)), _i1(d[30], (d[31],)), _i1(d[33], (d[34],)),
        _f1(d[36], (d[37],)), _f2(d[39], (d[40], d[41])), _f1(d[42], (d[43],)), _f1(d[45], (d[46],)),
        _f1(d[48], (d[49],)),
        _f1(d[51], (d[52],)), _f1(d[54], (d[55],)), _f2(d[57], (d[58], d[59])), _i2(d[60], (d[61], d[62])),
        _i1(d[63], (d[64],)), _f1(d[66], (d[67],)), _i1(d[69], (d[70],)), _f2(d[72], (d[73], d[74])),
        _i2(d[75], (d[76], d[77])), _f2(d[78], (d[79], d[80])),
        _tel(d[81], (d[82],)), _i1(d[84], (d[85],)), _i1(d[87], (d[88],)), _i1(d[90], (d[91],)),
        _stat(d[93], (d[94],)),
        _i1(d[96], (d[97],)))


@njit(**_JIT)
def address_as_i64_view(addr):
    return _i1(addr, (3 * NFIELDS,))

@njit(**_JIT)
def tick_at(addr, wake_ns, late_ns):
    """``tick`` on the arrays a descriptor at ``addr`` describes: a call from Python that passes
    one integer, not 32 arrays (each array argument costs its unboxing: about 6 us for all)."""
    return tick(tick_arrays_at(addr), wake_ns, late_ns)


@njit(**_JIT)
def run_ticks_at(addr):
    """``run_ticks`` on the arrays a descriptor at ``addr`` describes (one argument to unbox)."""
    return run_ticks(tick_arrays_at(addr))


assert (LS_ENGAGED, _LS_FADING, _LS_STOPPING) == tuple(int(LS[n]) for n in ("engaged", "fading", "stopping"))


def new_words(period_ns: int) -> np.ndarray:
    tk = np.zeros(NTK, dtype=np.int64)
    tk[TK_PERIOD_NS] = int(period_ns)
    tk[TK_FD] = -1
    tk[TK_POLL_EVERY] = max(1, int(round(1_000_000 / int(period_ns))))  # a millisecond of ticks
    return tk
