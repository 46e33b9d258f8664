"""The numba kernels that write the shared rings of ``shm``: one telemetry row per haptic step
(with the timing histograms and maxima), one contact row per applied model update. Both write
named fields of the structured dtypes declared in ``shm``, allocate nothing and are called with
one signature each (``HapticLoop.warm_up`` compiles it)."""
from __future__ import annotations

from numba import njit

from .control import CS_DPOSE, CS_EHAND, CS_ENV, CS_FC, CS_GAIN, CS_PPOSE, CS_TANK
from .passivity import TS_TANK
from .devices.base import DS_HAND
from .model.layout import K_M
from .native import fence
from .shm import HBINS


@njit(cache=True, nogil=True)
def account(tel, head, hist_late, hist_step, stat, period_ns, late_ns, comp_ns, since_start_ns, state, updates,
            cs, cnt, dev, cmd):
    """Histograms, maxima, counters and one telemetry row (``shm.TEL_DTYPE``) for a step. The
    scalars as the loop has them (integers; ``state`` a float), the gain read from the
    controller's ``cs`` and the live contacts from the model's counters ``cnt``: the step's
    Python converts nothing (a haptic step pays for every Python operation)."""
    lu = late_ns / 1000.0
    cu = comp_ns / 1000.0
    bl = int(lu) if lu > 0.0 else 0
    bc = int(cu) if cu > 0.0 else 0
    hist_late[bl if bl < HBINS - 1 else HBINS - 1] += 1
    hist_step[bc if bc < HBINS - 1 else HBINS - 1] += 1
    st = stat[0]
    st.steps += 1.0
    if lu > st.lateness_max_us:
        st.lateness_max_us = lu
    if cu > st.compute_max_us:
        st.compute_max_us = cu
    if late_ns + comp_ns > period_ns:
        st.overruns += 1.0  # the step finished after the next deadline
    seq = head[0]
    r = tel[seq % tel.shape[0]]
    # a seqlock (``SharedState.rows`` is the reader): -1 while the fields change, then the row's
    # number; the fences keep the three groups of stores in this order, for the compiler and CPU
    r.seq = -1.0
    fence()
    r.t_s = since_start_ns * 1e-9
    r.lateness_us = lu
    r.compute_us = cu
    r.loop_state = state
    r.gain = cs[CS_GAIN]
    r.contacts = float(cnt[K_M])
    r.updates = float(updates)
    r.energy_hand_j = cs[CS_EHAND]
    r.tank_j = cs[CS_TANK + TS_TANK]
    for j in range(13):  # pose (7) and twist (6)
        r.dev[j] = cs[CS_DPOSE + j]
        r.proxy[j] = cs[CS_PPOSE + j]
    for j in range(6):
        r.cmd[j] = cmd[j]
        r.env[j] = cs[CS_ENV + j]
        r.hand[j] = dev[DS_HAND + j]
        r.couple[j] = cs[CS_FC + j]
    fence()
    r.seq = float(seq)
    head[0] = seq + 1


@njit(cache=True, nogil=True)
def record_contacts(ring, t_s, env_time_s, update, n, kbuf, pbuf, nbuf, sbuf):
    """One contact-ring row (``shm.SharedState.contacts``) for an applied model update: its time,
    count and first ``MAX_CONTACTS`` contacts (key, position, normal, separation)."""
    hdr, key, pos, nrm, sep, chead = ring
    seq = chead[0]
    i = seq % hdr.shape[0]
    h = hdr[i]
    h.seq = -1  # being written: a reader copying it now drops it
    m = n
    if m > key.shape[1]:
        m = key.shape[1]
    if m > kbuf.shape[0]:
        m = kbuf.shape[0]
    for j in range(m):
        for a in range(3):
            key[i, j, a] = kbuf[j, a]
            pos[i, j, a] = pbuf[j, a]
            nrm[i, j, a] = nbuf[j, a]
        sep[i, j] = sbuf[j]
    h.t_s = t_s
    h.env_time_s = env_time_s
    h.update = update
    h.count = n
    h.seq = seq
    chead[0] = seq + 1
