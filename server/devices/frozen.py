"""A frozen position: a device whose position stopped changing while it was pushing.

A stuck encoder, a hung firmware or an SDK that hands back its last sample keeps reporting the
same position; every read still succeeds, so no error code says so. The loop would go on
computing forces from a handle that, as far as it knows, never moves: the coupling holds a
constant force on a hand that may have let go. Physics gives the test: a device commanded a
force moves unless something rigid holds it. A hand is not rigid (its tremor alone moves a
handle by tenths of a millimetre, many encoder counts, within a few hundred milliseconds), so a
reading whose position and velocity stay *identical* (equal floats, all six) while at least
``min_force_n`` was commanded, for ``window_ns``, is a sensor that stopped. The velocity is
part of the test because a simulated hand is rigid: a scripted push balanced by the rendered force
settles to a position that no longer changes in float64 (the increments fall below its
resolution) while the velocity, driven by the forces' rounding, still does.

``watch(fp, po, fs, so, row, cmd, now_ns) -> bool``, pure, one call per tick after the device
was read and before the new command is computed (``cmd`` still holds the wrench written in the
period the reading covers). Layouts (declared once here; ``control`` embeds them at ``po``/``so``
of its parameter and state arrays, :class:`~.vendor.VendorDevice` keeps its own):

- parameters ``fp`` float64[NFP]: ``FP_WINDOW_NS`` (0: off), ``FP_MIN_FORCE_N``;
- state ``fs`` float64[NFS]: the last position ``FS_POS..+3``, velocity ``FS_VEL..+3`` (the
  state row's columns 0-2 and 7-9) and ``FS_SINCE_NS``, when the
  current run of identical readings under force began (-1: no run).

Contract (``tests/server/test_frozen_watch.py`` checks each over random sequences):

1. **Off.** ``window <= 0``: never trips.
2. **Only a run under force counts.** A reading that differs from the last (``!=``) in any of
   the three position or three velocity components (or a first reading: the state starts NaN)
   ends the run; so does
   a command whose force norm is below ``min_force_n``. NaN never equals itself, so a non-finite
   reading never extends a run (the controller's non-finite check owns it).
3. **Trips after the window.** It returns True exactly when the run began at ``t0`` and
   ``now_ns - t0 >= window``: the run's readings were all identical and every command in it
   was at least ``min_force_n``. Once true it stays true while the run lasts.
4. **Nothing else.** It never changes the command: the caller treats True as a device fault
   (``DEV_FAULT_FROZEN``: the output is cut, the device disabled, the fault named, a re-arm
   brings force back through the ramp).

What it cannot tell apart: a handle held still against its own mechanical stop while force is
commanded into the stop. That trips too, on the safe side (the force is cut); ``safety.frozen_s``
= 0 turns the check off for a rig that does this on purpose.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

_JIT = dict(cache=True, nogil=True, error_model="numpy")

FP_WINDOW_NS = 0     # a run of identical readings under force this long trips (0: off)
FP_MIN_FORCE_N = 1   # the force norm a command needs to count as pushing
NFP = 2

FS_POS = 0           # 0..2 the last reading's position
FS_VEL = 3           # 3..5 and velocity
FS_SINCE_NS = 6      # when the current run began (-1: no run)
NFS = 7

#: defaults of ``[safety] frozen_s`` and of the force a command needs (``frozen_force_n`` = 0:
#: this or a quarter of the device's force cap, whichever is lower)
FROZEN_S = 0.5
FROZEN_FORCE_N = 0.25


@njit(**_JIT)
def reset(fs, so):
    """No reading yet: the next one starts fresh (no run)."""
    for j in range(3):
        fs[so + FS_POS + j] = math.nan
        fs[so + FS_VEL + j] = math.nan
    fs[so + FS_SINCE_NS] = -1.0


@njit(**_JIT)
def watch(fp, po, fs, so, row, cmd, now_ns):
    """True when the position has been frozen under force for the window (see the contract)."""
    window = fp[po + FP_WINDOW_NS]
    if not window > 0.0:
        return False
    p = so + FS_POS
    v = so + FS_VEL
    if (row[0] != fs[p] or row[1] != fs[p + 1] or row[2] != fs[p + 2]
            or row[7] != fs[v] or row[8] != fs[v + 1] or row[9] != fs[v + 2]):
        for j in range(3):
            fs[p + j] = row[j]
            fs[v + j] = row[7 + j]
        fs[so + FS_SINCE_NS] = -1.0
        return False
    fmin = fp[po + FP_MIN_FORCE_N]
    if not cmd[0] * cmd[0] + cmd[1] * cmd[1] + cmd[2] * cmd[2] >= fmin * fmin:
        fs[so + FS_SINCE_NS] = -1.0
        return False
    since = fs[so + FS_SINCE_NS]
    if since < 0.0:
        fs[so + FS_SINCE_NS] = float(now_ns)
        return False
    return float(now_ns) - since >= window


def set_parameters(fp: np.ndarray, po: int, *, frozen_s: float, min_force_n: float) -> None:
    if not (math.isfinite(frozen_s) and frozen_s >= 0.0 and math.isfinite(min_force_n) and min_force_n > 0.0):
        raise ValueError(f"frozen position watch: frozen_s >= 0 and min_force_n > 0, got {frozen_s!r}, {min_force_n!r}")
    fp[po + FP_WINDOW_NS] = frozen_s * 1e9
    fp[po + FP_MIN_FORCE_N] = min_force_n


def min_force_n(asked_n: float, force_cap_n: float) -> float:
    """The force a command needs to count (``asked_n`` 0: the default, at most a quarter of the
    device's cap, so a weak device's pushes count too)."""
    return asked_n if asked_n > 0.0 else min(FROZEN_FORCE_N, 0.25 * force_cap_n)


__all__ = ["FP_MIN_FORCE_N", "FP_WINDOW_NS", "FROZEN_FORCE_N", "FROZEN_S", "FS_POS", "FS_SINCE_NS", "FS_VEL", "NFP", "NFS",
           "min_force_n", "reset", "set_parameters", "watch"]
