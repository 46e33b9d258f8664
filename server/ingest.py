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

import sys

import numpy as np
from numba import njit

from ..protocol.messages import CONTACT_FLOATS, MAX_ABS_FLOAT, UNIT_TOLERANCE, ContactUpdate

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
    lim = np.zeros(12, dtype=np.int64)
    out_i = np.zeros(I_KEYS + 3 * n, dtype=np.int64)
    out_f = np.zeros(F_DATA + 8 * n + 1)
    for pkt in (b"\x9b", bytearray(b"\x9b")):  # a datagram as bytes and as the loop's bytearray
        parse_contact_update(np.frombuffer(pkt, np.uint8), lim, np.zeros(3), out_i, out_f)


# ------------------------------------------------------------------ the whole ContactUpdate
# What parse_contact_update expects: ``lim_i`` (int64) the codec's limits, then the session the
# update must belong to and its grant; ``lim_f`` the Welcome's bounds.
(L_MAX_CONTACTS, L_MAX_LINKS, L_MAX_BIN, L_SESSION, L_TOKEN_HI, L_TOKEN_LO, L_NEWEST, L_GRANTED, L_MAX_JUMP,
 L_N_LINKS, L_N_JOINTS, L_PLANAR) = range(12)
LF_EXTENT, LF_SPEED, LF_SEPARATION = range(3)
# Where it leaves what it read: ``out_i`` (int64) and ``out_f`` (float64), one row per slot of a
# ContactParser.
I_MINOR, I_SESSION, I_TOKEN_HI, I_TOKEN_LO, I_SEQ, I_COUNT, I_JOINTS, I_KEYS = range(8)
F_ENV_TIME, F_POSE = 0, 1
F_DATA = 8  # then 8 n float64 (contact_data as sent); the joint positions after 8 max_contacts
_NOT_SURE = -1


@njit(cache=True)
def _uint(p, i, end):
    """msgpack unsigned integer at ``p[i]``: (value, next index); next -1 if it is none (or
    wider than 63 bits: the slow path decides those)."""
    if i >= end:
        return 0, -1
    b = p[i]
    if b < 0x80:
        return np.int64(b), i + 1
    w = 0
    if b == 0xCC:
        w = 1
    elif b == 0xCD:
        w = 2
    elif b == 0xCE:
        w = 4
    elif b == 0xCF:
        w = 8
        if i + 1 < end and p[i + 1] >= 0x80:
            return 0, -1
    else:
        return 0, -1
    if i + 1 + w > end:
        return 0, -1
    v = np.int64(0)
    for k in range(w):
        v = (v << 8) | np.int64(p[i + 1 + k])
    return v, i + 1 + w


@njit(cache=True)
def _bin(p, i, end):
    """msgpack bin header at ``p[i]``: (length, index of the first byte); -1 if none."""
    if i >= end:
        return 0, -1
    b = p[i]
    if b == 0xC4 and i + 2 <= end:
        return np.int64(p[i + 1]), i + 2
    if b == 0xC5 and i + 3 <= end:
        return (np.int64(p[i + 1]) << 8) | np.int64(p[i + 2]), i + 3
    if b == 0xC6 and i + 5 <= end:
        v = np.int64(0)
        for k in range(4):
            v = (v << 8) | np.int64(p[i + 1 + k])
        return v, i + 5
    return 0, -1


@njit(cache=True)
def parse_contact_update(p, lim, lim_f, out_i, out_f):
    """A whole ContactUpdate datagram ``p`` (uint8) in one call, for the packets every engine
    sends: the header and fields in their usual msgpack forms (unsigned integers, a float64
    ``env_time_s``, bins), no unknown fields, every value rule of the codec kept with a margin
    (``contacts_surely_valid``), and every rule of the session it names (``lim``'s session:
    its token, a seq newer than the newest accepted and not too far ahead, the granted
    contacts, the bounds and links of ``ServerSession.check_update``). Returns n >= 0 with the
    fields in ``out_i`` / ``out_f`` (the layout above; the bins copied as sent, little-endian),
    or -1: not sure, and the codec and the session decide (with their error codes)."""
    end = p.shape[0]
    if end < 4:
        return _NOT_SURE
    b = p[0]
    i = 1
    if b == 0x9B or b == 0x9C:
        count = b - 0x90
    elif b == 0xDC and end > 3:
        count = (np.int64(p[1]) << 8) | np.int64(p[2])
        i = 3
    else:
        return _NOT_SURE
    if count != 11 and count != 12:
        return _NOT_SURE
    major, i = _uint(p, i, end)
    if i < 0 or major != 1:
        return _NOT_SURE
    minor, i = _uint(p, i, end)
    if i < 0 or minor > 0xFFFF:
        return _NOT_SURE
    tid, i = _uint(p, i, end)
    if i < 0 or tid != 4:
        return _NOT_SURE
    sid, i = _uint(p, i, end)
    if i < 0 or sid != lim[L_SESSION]:
        return _NOT_SURE
    # the token may use all 64 bits: read as two halves
    if i + 9 <= end and p[i] == 0xCF:
        hi = np.int64(0)
        lo = np.int64(0)
        for k in range(4):
            hi = (hi << 8) | np.int64(p[i + 1 + k])
            lo = (lo << 8) | np.int64(p[i + 5 + k])
        i += 9
    else:
        lo, i = _uint(p, i, end)
        if i < 0:
            return _NOT_SURE
        hi = lo >> 32
        lo = lo & 0xFFFFFFFF
    if hi != lim[L_TOKEN_HI] or lo != lim[L_TOKEN_LO]:
        return _NOT_SURE
    seq, i = _uint(p, i, end)
    if i < 0 or seq <= lim[L_NEWEST] or seq - lim[L_NEWEST] > lim[L_MAX_JUMP]:
        return _NOT_SURE
    # env_time_s: a float64 (big-endian), finite, within the bound
    if i + 9 > end or p[i] != 0xCB:
        return _NOT_SURE
    fb = out_f.view(np.uint8)
    for k in range(8):
        fb[7 - k] = p[i + 1 + k]
    i += 9
    t = out_f[F_ENV_TIME]
    if not (-MAX_ABS_FLOAT <= t <= MAX_ABS_FLOAT):
        return _NOT_SURE
    nb, i = _bin(p, i, end)
    if i < 0 or nb != 56 or i + 56 > end:
        return _NOT_SURE
    for k in range(56):
        fb[8 * F_POSE + k] = p[i + k]
    i += 56
    extent = lim_f[LF_EXTENT]
    for k in range(3):
        x = out_f[F_POSE + k]
        if not (-MAX_ABS_FLOAT <= x <= MAX_ABS_FLOAT and -extent <= x <= extent):
            return _NOT_SURE
    qw = out_f[F_POSE + 3]
    qx = out_f[F_POSE + 4]
    qy = out_f[F_POSE + 5]
    qz = out_f[F_POSE + 6]
    qn = qw * qw + qx * qx + qy * qy + qz * qz
    if not (_SURE_LO <= qn <= _SURE_HI):
        return _NOT_SURE
    n, i = _uint(p, i, end)
    if i < 0 or n > lim[L_MAX_CONTACTS] or n > lim[L_GRANTED]:
        return _NOT_SURE
    nb, i = _bin(p, i, end)
    if i < 0 or nb != 24 * n or i + nb > end:
        return _NOT_SURE
    ib = out_i.view(np.uint8)
    base = 8 * I_KEYS
    for k in range(nb):
        ib[base + k] = p[i + k]
    i += nb
    nb, i = _bin(p, i, end)
    if i < 0 or nb != 64 * n or nb > lim[L_MAX_BIN] or i + nb > end:
        return _NOT_SURE
    base = 8 * F_DATA
    for k in range(nb):
        fb[base + k] = p[i + k]
    i += nb
    joints = 0
    if count == 12:
        nb, i = _bin(p, i, end)
        if i < 0 or nb % 8 != 0 or nb > 8 * lim[L_MAX_LINKS] or i + nb > end:
            return _NOT_SURE
        jat = F_DATA + 8 * lim[L_MAX_CONTACTS]  # after room for the most contacts: one view per count
        base = 8 * jat
        for k in range(nb):
            fb[base + k] = p[i + k]
        i += nb
        joints = nb // 8
        if joints != 0 and joints != lim[L_N_JOINTS]:
            return _NOT_SURE
        for k in range(joints):
            x = out_f[jat + k]
            if not (-MAX_ABS_FLOAT <= x <= MAX_ABS_FLOAT):
                return _NOT_SURE
    if i != end:  # trailing bytes: not one msgpack object
        return _NOT_SURE
    # the contacts: the codec's rules and the session's, by the two kernels above
    cols = out_f[F_DATA:F_DATA + 8 * n].reshape(8, n)
    normal = out_f[F_DATA + 3 * n:F_DATA + 6 * n].reshape(n, 3)
    keys = out_i[I_KEYS:I_KEYS + 3 * n].reshape(n, 3)
    if not contacts_surely_valid(cols, normal, keys):
        return _NOT_SURE
    if not update_surely_in_bounds(cols, normal, keys, extent, lim_f[LF_SPEED], lim_f[LF_SEPARATION], lim[L_N_LINKS],
                                   lim[L_PLANAR] != 0):
        return _NOT_SURE
    out_i[I_MINOR] = minor
    out_i[I_SESSION] = sid
    out_i[I_TOKEN_HI] = hi
    out_i[I_TOKEN_LO] = lo
    out_i[I_SEQ] = seq
    out_i[I_COUNT] = n
    out_i[I_JOINTS] = joints
    return n


def _frozen(a: np.ndarray) -> np.ndarray:
    a.flags.writeable = False  # the kernels' types: the codec hands out read-only views too
    return a


class ContactParser:
    """``ServerEndpoint(update_parser=ContactParser(limits))``: a ContactUpdate datagram of the
    session the endpoint expects (:meth:`expect`) decoded and checked by
    :func:`parse_contact_update` into one of a few preallocated slots, its arrays read-only
    views of that slot (the shapes, dtypes and layouts the codec's own views have, so every
    kernel downstream sees the types it was compiled for). ``None`` when the kernel is not
    sure: the codec and the session then decide as before.

    A slot is reused only once nothing but this parser holds the message it was handed out
    in (its reference count), so an update the loop keeps (pending, or applied and not yet
    acknowledged) is never overwritten by a newer one; the views of a slot are built once per
    contact count. Keep the message, not only its arrays (the loop does). With every slot held
    it returns ``None`` and the codec allocates as it always did. Its messages carry the
    columns (``keys``, ``position_m``, ...), not the raw bins: ``contact_keys`` and
    ``contact_data`` are empty (the codec re-encodes from the columns)."""

    SLOTS = 4

    def __init__(self, limits) -> None:
        k, j = int(limits.max_contacts), int(limits.max_links)
        self._lim = np.zeros(12, dtype=np.int64)
        self._lim[[L_MAX_CONTACTS, L_MAX_LINKS, L_MAX_BIN]] = k, j, limits.max_bin_bytes
        self._lim[L_SESSION] = -1  # no session expected: nothing is sure
        self._lim_f = np.zeros(3)
        self._i = np.zeros((self.SLOTS, I_KEYS + 3 * k), dtype=np.int64)
        self._f = np.zeros((self.SLOTS, F_DATA + 8 * k + j))
        self._rows = [(self._i[s], self._f[s]) for s in range(self.SLOTS)]
        self._held: list = [None] * self.SLOTS
        self._views: list[dict] = [{} for _ in range(self.SLOTS)]
        self._joints: list[dict] = [{} for _ in range(self.SLOTS)]
        self._k = k
        self._pose = [_frozen(self._f[s, F_POSE:F_POSE + 7]) for s in range(self.SLOTS)]
        self.parsed = 0  # updates this parser handed out (the rest went to the codec)
        self.reused = 0  # slots taken again (their previous message dropped)
        self.all_held = 0  # datagrams left to the codec because every slot was held

    def expect(self, session, max_seq_jump: int) -> None:
        """Vouch only for updates of ``session`` (a ``ServerSession``): its id and token, seq
        after its newest accepted and at most ``max_seq_jump`` ahead, its grant and bounds."""
        lim = self._lim
        lim[L_SESSION] = session.session_id
        lim[L_TOKEN_HI] = session.token >> 32
        lim[L_TOKEN_LO] = session.token & 0xFFFF_FFFF
        lim[L_NEWEST] = min(session.contact_seq.newest, _I64_MAX)
        lim[L_GRANTED] = session.max_contacts
        lim[L_MAX_JUMP] = min(max_seq_jump, _I64_MAX)
        lim[L_N_LINKS] = session.n_links
        lim[L_N_JOINTS] = session.n_joints
        lim[L_PLANAR] = int(session.planar)
        self._lim_f[:] = session.bounds

    def accepted(self, seq: int) -> None:
        """The expected session accepted ``seq`` (its newest now)."""
        self._lim[L_NEWEST] = seq

    def _contact_views(self, slot: int, n: int) -> tuple:
        row = self._f[slot]
        d = row[F_DATA:F_DATA + 8 * n]
        cols = _frozen(d.reshape(8, n))
        v = (_frozen(self._i[slot, I_KEYS:I_KEYS + 3 * n].reshape(n, 3)), _frozen(d[:3 * n].reshape(n, 3)),
             _frozen(d[3 * n:6 * n].reshape(n, 3)), cols[6], cols[7], cols)
        self._views[slot][n] = v
        return v

    def _joint_view(self, slot: int, j: int):
        a = self._f[slot, F_DATA + 8 * self._k:F_DATA + 8 * self._k + j]
        v = self._joints[slot][j] = _frozen(a)
        return v

    def __call__(self, data):
        held = self._held
        getrc = _getrefcount
        for slot in range(self.SLOTS):
            m = held[slot]
            if m is None or getrc(m) <= 3:  # held[slot], m, getrefcount's argument
                break
        else:
            self.all_held += 1
            return None
        m = None
        out_i, out_f = self._rows[slot]
        n = parse_contact_update(_frombuffer(data, _U8), self._lim, self._lim_f, out_i, out_f)
        if n < 0:
            return None
        minor, sid, hi, lo, seq, _n, joints = out_i[:I_KEYS].tolist()
        views = self._views[slot].get(n) or self._contact_views(slot, n)
        jv = _NO_JOINTS
        if joints:
            jv = self._joints[slot].get(joints)
            if jv is None:
                jv = self._joint_view(slot, joints)
        msg = ContactUpdate(minor=minor, session_id=sid, token=(hi << 32) | lo, seq=seq,
                            env_time_s=float(out_f[F_ENV_TIME]), tool_pose=self._pose[slot], contact_count=n,
                            contact_keys=b"", contact_data=b"", tool_joint_position=jv)
        msg.keys, msg.position_m, msg.normal, msg.separation_m, msg.v_constr_m_per_s, msg.contact_columns = views
        if held[slot] is not None:
            self.reused += 1
        held[slot] = msg
        self.parsed += 1
        return msg


_getrefcount = sys.getrefcount
_frombuffer = np.frombuffer
_U8 = np.uint8
_NO_JOINTS = _frozen(np.zeros(0))
_I64_MAX = (1 << 63) - 1
