"""The ProxyState that acknowledges an update, packed by one numba kernel the server plugs into
the protocol's codec (``Codec(proxy_state_packer=ProxyStatePacker())``).

The codec's own trusted path (``Codec.encode_proxy_state(trusted=True)``) builds six ``bytes``,
joins them for one finiteness test and hands a list to msgspec: a dozen Python calls in the
haptic step that acknowledges an update. The kernel writes the same bytes (msgspec's msgpack:
the smallest integer form, float64 for floats, bin8/bin16 for the arrays, fixarray or array16)
into a preallocated buffer in one call, and says "not sure" (``None``) for anything its rule
does not cover (a value that is not finite or beyond the float bound, a buffer too small): then
the codec's path runs and names the field. ``tests/server/test_egress.py`` holds the two to the
same bytes.
"""
from __future__ import annotations

import numpy as np
from numba import njit

from ..protocol.messages import (
    INPUT_BUTTONS, INPUT_GRIPPER, INPUT_GRIPPER_RATE, MAX_ABS_FLOAT, PROTOCOL_MAJOR, MessageType,
)

_TYPE_ID = int(MessageType.PROXY_STATE)
_MAJOR = int(PROTOCOL_MAJOR)
_IN_BUTTONS, _IN_GRIPPER, _IN_GRIPPER_RATE = int(INPUT_BUTTONS), int(INPUT_GRIPPER), int(INPUT_GRIPPER_RATE)
#: scalars of a 1.3 ProxyState (5 header integers, seq, ack_seq, server_state, buttons,
#: device_inputs; server_time_s, epsilon_m, lead_s and the gripper's two floats), 9 bytes each at most
_SCALARS_MAX = 17


@njit(cache=True)
def _put_uint(out, i, v):
    if v < 0x80:
        out[i] = v
        return i + 1
    if v <= 0xFF:
        out[i] = 0xCC
        out[i + 1] = v
        return i + 2
    if v <= 0xFFFF:
        out[i] = 0xCD
        w = 2
    elif v <= 0xFFFFFFFF:
        out[i] = 0xCE
        w = 4
    else:
        out[i] = 0xCF
        w = 8
    for k in range(w):
        out[i + w - k] = (v >> (8 * k)) & 0xFF
    return i + 1 + w


@njit(cache=True)
def _put_u64(out, i, hi, lo):
    """An unsigned integer given as two 32-bit halves (it may use all 64 bits)."""
    if hi == 0:
        return _put_uint(out, i, lo)
    out[i] = 0xCF
    for k in range(4):
        out[i + 4 - k] = (hi >> (8 * k)) & 0xFF
        out[i + 8 - k] = (lo >> (8 * k)) & 0xFF
    return i + 9


@njit(cache=True)
def _put_f64(out, i, x, scratch):
    scratch[0] = x
    b = scratch.view(np.uint8)
    out[i] = 0xCB
    for k in range(8):
        out[i + 1 + k] = b[7 - k]  # msgpack floats are big-endian
    return i + 9


@njit(cache=True)
def _put_bin(out, i, a, scratch):
    """``a`` (float64) as a bin of its little-endian bytes (the host's: the server packs only on
    a little-endian host)."""
    nb = 8 * a.shape[0]
    if nb <= 0xFF:
        out[i] = 0xC4
        out[i + 1] = nb
        i += 2
    else:
        out[i] = 0xC5
        out[i + 1] = nb >> 8
        out[i + 2] = nb & 0xFF
        i += 3
    b = scratch.view(np.uint8)
    for j in range(a.shape[0]):
        x = a[j]
        if not (-MAX_ABS_FLOAT <= x <= MAX_ABS_FLOAT):  # NaN fails too
            return -1
        scratch[0] = x
        for k in range(8):
            out[i + k] = b[k]
        i += 8
    return i


@njit(cache=True)
def pack_proxy_state(out, scratch, minor, session_id, token_hi, token_lo, seq, ack_seq, server_time_s, pose, twist,
                     wrench, joint_position, joint_velocity, joint_effort, server_state, epsilon_m, lead_s,
                     has_state, inputs, has_inputs):
    """The ProxyState's bytes into ``out``; returns their count, or -1 (not sure: a value out of
    the rules, or ``out`` too small). The token as two 32-bit halves (it may use all 64 bits);
    ``scratch``: one float64. ``inputs``: the device row's input columns (buttons, gripper angle,
    gripper rate; NaN: not reported), turned into the 1.3 fields by the rule of
    ``protocol.messages.device_inputs_fields`` (``has_inputs``: the codec writes 1.3)."""
    # at most: the array header, 12 integers and 5 floats of 9 bytes, 6 bin headers, the values
    need = 3 + _SCALARS_MAX * 9 + 6 * 3 + 8 * (7 + 6 + 6 + joint_position.shape[0] + joint_velocity.shape[0]
                                               + joint_effort.shape[0])
    if out.shape[0] < need or pose.shape[0] != 7 or twist.shape[0] != 6 or wrench.shape[0] != 6:
        return -1
    if has_inputs and inputs.shape[0] != 3:
        return -1
    for x in (server_time_s, epsilon_m, lead_s):
        if not (-MAX_ABS_FLOAT <= x <= MAX_ABS_FLOAT):
            return -1
    count = 21 if has_inputs else (17 if has_state else 14)
    if count <= 15:
        out[0] = 0x90 + count
        i = 1
    else:
        out[0] = 0xDC
        out[1] = 0
        out[2] = count
        i = 3
    i = _put_uint(out, i, _MAJOR)
    i = _put_uint(out, i, minor)
    i = _put_uint(out, i, _TYPE_ID)
    i = _put_uint(out, i, session_id)
    i = _put_u64(out, i, token_hi, token_lo)
    i = _put_uint(out, i, seq)
    i = _put_uint(out, i, ack_seq)
    i = _put_f64(out, i, server_time_s, scratch)
    # one by one: the arrays may differ in type (a read-only empty joint array), so no loop
    i = _put_bin(out, i, pose, scratch)
    if i >= 0:
        i = _put_bin(out, i, twist, scratch)
    if i >= 0:
        i = _put_bin(out, i, wrench, scratch)
    if i >= 0:
        i = _put_bin(out, i, joint_position, scratch)
    if i >= 0:
        i = _put_bin(out, i, joint_velocity, scratch)
    if i >= 0:
        i = _put_bin(out, i, joint_effort, scratch)
    if i < 0:
        return -1
    if has_state or has_inputs:
        i = _put_uint(out, i, server_state)
        i = _put_f64(out, i, epsilon_m, scratch)
        i = _put_f64(out, i, lead_s, scratch)
    if has_inputs:
        # a value not reported (NaN, beyond the bound, a mask outside u32) is 0 with its bit clear
        b = inputs[0]
        flags = 0
        bi = 0
        if 0.0 <= b <= 4294967295.0:
            bi = int(b)
            flags |= _IN_BUTTONS
        g = inputs[1]
        ga = 0.0
        if -MAX_ABS_FLOAT <= g <= MAX_ABS_FLOAT:
            ga = g
            flags |= _IN_GRIPPER
        gr = inputs[2]
        gv = 0.0
        if -MAX_ABS_FLOAT <= gr <= MAX_ABS_FLOAT:
            gv = gr
            flags |= _IN_GRIPPER_RATE
        i = _put_uint(out, i, bi)
        i = _put_f64(out, i, ga, scratch)
        i = _put_f64(out, i, gv, scratch)
        i = _put_uint(out, i, flags)
    return i


class ProxyStatePacker:
    """``Codec(proxy_state_packer=ProxyStatePacker())``: ``packer(minor, session_id, token, seq,
    ack_seq, server_time_s, pose, twist, wrench, joint_position, joint_velocity, joint_effort,
    server_state, epsilon_m, lead_s, has_state, inputs, has_inputs) -> bytes | None`` (the arrays
    float64, 1-D; ``inputs`` 3 floats)."""

    def __init__(self, max_links: int = 64) -> None:
        self._out = np.zeros(3 + _SCALARS_MAX * 9 + 6 * 3 + 8 * (19 + 3 * max_links), dtype=np.uint8)  # the kernel's bound
        self._scratch = np.zeros(1)
        self._mv = memoryview(self._out)
        self.packed = 0  # ProxyStates this packer packed (the rest the codec did)

    def __call__(self, minor, session_id, token, seq, ack_seq, server_time_s, pose, twist, wrench, joint_position,
                 joint_velocity, joint_effort, server_state, epsilon_m, lead_s, has_state, inputs=None,
                 has_inputs=False):
        if seq > _I64_MAX or ack_seq > _I64_MAX:
            return None
        if inputs is None:
            inputs = _NO_INPUTS
        elif type(inputs) is not np.ndarray or inputs.dtype != np.float64 or inputs.ndim != 1:
            return None  # the codec's path converts (and names a bad value)
        # every scalar converted, so the kernel sees the one signature warm_up compiled
        n = pack_proxy_state(self._out, self._scratch, int(minor), int(session_id), token >> 32, token & 0xFFFF_FFFF,
                             int(seq), int(ack_seq), float(server_time_s), pose, twist, wrench, joint_position,
                             joint_velocity, joint_effort, int(server_state), float(epsilon_m), float(lead_s),
                             bool(has_state), inputs, bool(has_inputs))
        if n < 0:
            return None
        self.packed += 1
        return bytes(self._mv[:n])


_I64_MAX = (1 << 63) - 1
_NO_INPUTS = np.full(3, np.nan)


def warm_up() -> None:
    """Compile / load the kernel with the array types the loop passes (its own float64 arrays,
    writable, and a read-only empty joint array)."""
    p = ProxyStatePacker(2)
    z = np.zeros(0)
    ro = np.zeros(0)
    ro.flags.writeable = False
    for joints in (z, ro):
        # the loop's inputs are a view of its device row (contiguous float64, writable)
        p(3, 1, 1, 1, 1, 0.0, np.zeros(7), np.zeros(6), np.zeros(6), joints, joints, joints, 0, 0.0, 0.0, 1,
          np.zeros(23)[20:23], 1)
