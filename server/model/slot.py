"""The update slot: how a model update reaches the tick, and its acknowledgement comes back.

The engine's contacts are decoded and checked by Python (the protocol side), beside the tick or
between ticks; the tick applies them. Python copies one update into the slot's staging arrays
(``keys``, ``pos``, ``nrm``, ``sep``, ``vc``, the engine's tool configuration ``q`` and the
work the engine declares ``ax[AX_WORK_J]``) and then publishes it by moving the tick's word
``TK_UPD_SEQ`` on; the tick that sees ``TK_UPD_SEQ != TK_UPD_DONE`` applies it with the model's
own update kernel (``kernels.update_rigid`` / ``linkage.update_linkage``, on the scratch arrays
below), steps the model with it, writes what acknowledges it (``ack_st``, ``ack_lw``, ``ax``'s
hand wrench and inputs) and then moves ``TK_UPD_DONE`` on. Python reads the result and the
acknowledgement only after that, and stages the next update only after reading them: each side
writes the slot's arrays only while the other does not read them, so no lock is taken for an
update, and the decoder's buffer and the slot are the two buffers (the next datagram is decoded
while the tick holds the staged one). The words are stored after the arrays they publish
(x86-64 keeps stores in order; the tick's word store is an atomic store).

``UpdateSlot`` is one layout, declared once here; the model (``LocalModel.slot``) owns its
arrays, allocated with the model (nothing is allocated per update), and the tick reads them
through a descriptor (``descriptor`` / ``slot_at``), as it reads ``tick.TickArrays``.
"""
from __future__ import annotations

from collections import namedtuple

import numpy as np
from numba import njit, types

from ..native import address_as
from .layout import NCOLS_F, NCOLS_I, NLW, NSTATE

_JIT = dict(cache=True, nogil=True, error_model="numpy")

UpdateSlot = namedtuple("UpdateSlot", (
    # staged by Python: the update's rows (the first TK_UPD_N), the engine's tool configuration
    "keys", "pos", "nrm", "sep", "vc", "q",
    # the update kernel's scratch (the model's)
    "sel", "newF", "newI", "st_e", "Re", "ce", "lw_e",
    # written by the tick: the model's state after the tick that applied the update (the
    # acknowledgement's proxy state), a linkage's link poses then
    "ack_st", "ack_lw",
    # floats both ways (AX_*)
    "ax",
))

# ---- ax: float64[NAX]
AX_WORK_J = 0        # staged: the work the engine declares it did on the tool (ContactUpdate.work_on_tool_j)
AX_GRANTED_J = 1     # the tick: what the passivity layer's tank took of it
AX_HAND = 2          # the tick: the hand wrench of the acknowledging tick (6)
AX_INPUTS = 8        # the tick: the device's inputs then (buttons, gripper: 3)
NAX = 11

_F1 = types.Array(types.float64, 1, "C")
_F2 = types.Array(types.float64, 2, "C")
_I1 = types.Array(types.int64, 1, "C")
_I2 = types.Array(types.int64, 2, "C")
FIELD_TYPES = (_I2, _F2, _F2, _F1, _F1, _F1,
               _I1, _F2, _I2, _F1, _F2, _F1, _F2,
               _F1, _F2,
               _F1)
assert len(FIELD_TYPES) == len(UpdateSlot._fields)
NFIELDS = len(FIELD_TYPES)
_f1, _f2, _i1, _i2 = (address_as(t) for t in (_F1, _F2, _I1, _I2))


def new_slot(max_rows: int, capacity: int, nq: int, n_links: int) -> UpdateSlot:
    """The arrays of one model's slot (``n_links``: 0 for a rigid tool)."""
    u = int(max_rows)
    nl = max(1, int(n_links))
    return UpdateSlot(
        np.zeros((u, 3), dtype=np.int64), np.zeros((u, 3)), np.zeros((u, 3)), np.zeros(u), np.zeros(u),
        np.zeros(int(nq)),
        np.zeros(u, dtype=np.int64), np.zeros((capacity, NCOLS_F)), np.zeros((capacity, NCOLS_I), dtype=np.int64),
        np.zeros(NSTATE), np.zeros((3, 3)), np.zeros(3), np.zeros((nl, NLW)),
        np.zeros(NSTATE), np.zeros((nl, NLW)),
        np.zeros(NAX))


def descriptor(U: UpdateSlot) -> np.ndarray:
    """int64[3 * NFIELDS]: (address, rows, cols) of each array of ``U`` (kept referenced by its
    owner as long as the descriptor is in use)."""
    d = np.zeros(3 * NFIELDS, dtype=np.int64)
    for k, a in enumerate(U):
        d[3 * k] = a.__array_interface__["data"][0]
        d[3 * k + 1] = a.shape[0]
        d[3 * k + 2] = a.shape[1] if a.ndim == 2 else 0
    return d


@njit(**_JIT)
def slot_at(addr):
    """The ``UpdateSlot`` a descriptor at ``addr`` describes, as views (nothing is copied)."""
    d = _i1(addr, (3 * NFIELDS,))
    return UpdateSlot(
        _i2(d[0], (d[1], d[2])), _f2(d[3], (d[4], d[5])), _f2(d[6], (d[7], d[8])), _f1(d[9], (d[10],)),
        _f1(d[12], (d[13],)), _f1(d[15], (d[16],)),
        _i1(d[18], (d[19],)), _f2(d[21], (d[22], d[23])), _i2(d[24], (d[25], d[26])), _f1(d[27], (d[28],)),
        _f2(d[30], (d[31], d[32])), _f1(d[33], (d[34],)), _f2(d[36], (d[37], d[38])),
        _f1(d[39], (d[40],)), _f2(d[42], (d[43], d[44])),
        _f1(d[45], (d[46],)))
