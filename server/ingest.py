"""The value rules of an arriving ContactUpdate, as two numba kernels the server plugs into the
protocol's codec and session (``Codec(contact_check=...)``, ``ServerEndpoint(update_check=...)``).

Both layers state their rules once, in numpy (``protocol/codec.py``, ``protocol/session.py``):
a dozen ufunc calls of about 1 us each, whatever the contact count, which made receiving an
update the costliest haptic step (about 60 us here). Each kernel here is one call that answers
"surely valid" (``True``) or "not sure" (``False``); on ``False`` the protocol's own numpy rules
run as before and decide, with their error codes and messages. So the kernels can only make a
valid update cheaper, never change what is accepted: where floating-point rounding could tell
the two implementations apart (the unit-normal test near its tolerance), the kernel says "not
sure". The protocol package stays free of numba (clients import it).
"""
from __future__ import annotations

import numpy as np
from numba import njit

from ..protocol.messages import CONTACT_FLOATS, MAX_ABS_FLOAT, UNIT_TOLERANCE

# the codec's window for |n|^2 (``| |n| - 1 | <= UNIT_TOLERANCE``)
_LO = (1.0 - UNIT_TOLERANCE) ** 2
_HI = (1.0 + UNIT_TOLERANCE) ** 2
#: how far inside the unit window |n|^2 must be for the kernel to decide alone: well above the
#: rounding difference of summing three squares in another order (a few ulp of 1)
_SURE = 1e-13
_SURE_LO = _LO + _SURE
_SURE_HI = _HI - _SURE
#: keys are compared pairwise up to this many contacts (n^2 / 2 comparisons); above it the
#: codec's set of keys decides
_PAIRWISE_MAX = 64
_BLOCKS = CONTACT_FLOATS  # the v1 column blocks: position (3), normal (3), separation, v_constr


@njit(cache=True)
def contacts_surely_valid(cols, normal, keys):
    """The codec's rules for ``contact_data`` and ``contact_keys`` (``Codec._check_contacts``):
    every float of the v1 blocks finite with ``|x| <= MAX_ABS_FLOAT``, unit normals, unique
    keys. ``cols``: the (blocks, n) view of contact_data; ``normal``: its (n, 3) normals;
    ``keys``: (n, 3) int64."""
    n = keys.shape[0]
    for b in range(_BLOCKS):
        for i in range(n):
            x = cols[b, i]
            if not (-MAX_ABS_FLOAT <= x <= MAX_ABS_FLOAT):  # NaN fails too
                return False
    for i in range(n):
        s = normal[i, 0] * normal[i, 0] + normal[i, 1] * normal[i, 1] + normal[i, 2] * normal[i, 2]
        if not (_SURE_LO <= s <= _SURE_HI):
            return False
    if n > _PAIRWISE_MAX:
        return False
    for i in range(n):
        a0 = keys[i, 0]
        a1 = keys[i, 1]
        a2 = keys[i, 2]
        for j in range(i + 1, n):
            if keys[j, 0] == a0 and keys[j, 1] == a1 and keys[j, 2] == a2:
                return False
    return True


@njit(cache=True)
def update_surely_in_bounds(cols, normal, keys, extent_m, speed_m_per_s, separation_m, n_links, planar):
    """The session's rules (``ServerSession.check_update``) for the contacts: positions within
    the workspace extent, |v_constr| and |separation| within the Welcome's bounds, tool links
    in ``0..n_links-1``, a planar tool's normals in the x-y plane. Comparisons only (no
    arithmetic), so the answer is exactly the session's."""
    n = keys.shape[0]
    for b in range(3):
        for i in range(n):
            if abs(cols[b, i]) > extent_m:
                return False
    for i in range(n):
        if abs(cols[6, i]) > separation_m or abs(cols[7, i]) > speed_m_per_s:
            return False
        link = keys[i, 0]
        if link < 0 or link >= n_links:
            return False
        if planar and abs(normal[i, 2]) > UNIT_TOLERANCE:
            return False
    return True


def warm_up(n: int = 2) -> None:
    """Compile / load both kernels with the types the decoder hands them (read-only views of a
    packet's bytes)."""
    buf = np.zeros(_BLOCKS * n).tobytes()
    cols = np.frombuffer(buf, np.dtype((np.float64, (n,))))
    normal = np.frombuffer(buf, np.dtype((np.float64, (n, 3))), 2)[1]
    keys = np.frombuffer(np.arange(3 * n, dtype=np.int64).tobytes(), np.dtype((np.int64, (3,))))
    contacts_surely_valid(cols, normal, keys)
    update_surely_in_bounds(cols, normal, keys, 1.0, 1.0, 1.0, 1, True)
