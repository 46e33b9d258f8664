"""OpenHaptics' HD calls as compiled C functions, for the haptic tick in the servo thread.

A Touch samples and commands its device inside the scheduler's callback, between
``hdBeginFrame`` and ``hdEndFrame``. When the loop runs its tick there (``server/servo.py``), these
four numba ``cfunc`` s are the device's part of it, called through their addresses with the
context ``ctx`` (int64[NX], :func:`context`) as their ``void *``:

- ``frame_begin(ctx, _)``: ``hdBeginFrame(handle)``;
- ``read(ctx, row)``: the state row of ``devices.base`` from ``hdGetDoublev`` (transform in mm,
  column-major; velocity in mm/s; angular velocity) and ``hdGetIntegerv`` (buttons); the status:
  the error ``frame_end`` found last (``HD_COMM_ERROR``: the link, any other: a hardware fault);
- ``write(ctx, wrench)``: ``hdSetDoublev(HD_CURRENT_FORCE)`` with the force, or zero while the
  driver is disabled (``X_ARMED``, which ``TouchDevice.enable`` / ``disable`` set);
- ``frame_end(ctx, _)``: ``hdEndFrame(handle)``, then ``hdGetError`` (kept for the next read).

The HD functions are called by the addresses the driver's ``CDLL`` (the one ``pyopenhaptics``
loaded) gives; nothing here allocates or touches Python.
"""
from __future__ import annotations

import ctypes
import math

import numpy as np
from numba import cfunc, njit, types

from ..native import address_as, call_i32_ptr_ptr, call_struct12_error, call_v_u32, call_v_u32_ptr, voidptr_to_int
from .base import DEV_FAULT_HARDWARE, DEV_FAULT_LINK, DEV_OK

_JIT = dict(cache=True, nogil=True, error_model="numpy")

HD_CURRENT_BUTTONS = 0x2000
HD_CURRENT_VELOCITY = 0x2051
HD_CURRENT_TRANSFORM = 0x2052
HD_CURRENT_ANGULAR_VELOCITY = 0x2053
HD_CURRENT_FORCE = 0x2700
HD_COMM_ERROR = 0x0302

# ---- the context (int64[NX])
X_GET_DOUBLEV = 0
X_GET_INTEGERV = 1
X_SET_DOUBLEV = 2
X_BEGIN_FRAME = 3
X_END_FRAME = 4
X_GET_ERROR = 5
X_HANDLE = 6
X_BUF = 7            # address of float64[NBUF]: matrix (16), velocity (3), angular velocity (3), force (3)
X_IBUF = 8           # address of int64[2]: hdGetIntegerv writes an int into the first
X_ARMED = 9          # 1: the driver is enabled (write renders the force), 0: zero
X_ERROR = 10         # the last hdGetError code after a frame (0: none)
X_BUTTONS = 11       # the buttons of the last read
X_CLOCK_NS = 12      # 0: the row's time is the monotonic clock
NX = 14
B_M, B_V, B_W, B_F = 0, 16, 19, 22
NBUF = 25

_I1 = address_as(types.Array(types.int64, 1, "C"))
_F1 = address_as(types.Array(types.float64, 1, "C"))


@njit(**_JIT)
def _quat_from_colmajor(m, row, at):
    """The unit quaternion (w x y z) of the rotation part of the column-major 4x4 ``m``."""
    r00 = m[0]; r01 = m[4]; r02 = m[8]
    r10 = m[1]; r11 = m[5]; r12 = m[9]
    r20 = m[2]; r21 = m[6]; r22 = m[10]
    tr = r00 + r11 + r22
    if tr > 0.0:
        s = 2.0 * math.sqrt(tr + 1.0)
        w = 0.25 * s; x = (r21 - r12) / s; y = (r02 - r20) / s; z = (r10 - r01) / s
    elif r00 > r11 and r00 > r22:
        s = 2.0 * math.sqrt(1.0 + r00 - r11 - r22)
        w = (r21 - r12) / s; x = 0.25 * s; y = (r01 + r10) / s; z = (r02 + r20) / s
    elif r11 > r22:
        s = 2.0 * math.sqrt(1.0 + r11 - r00 - r22)
        w = (r02 - r20) / s; x = (r01 + r10) / s; y = 0.25 * s; z = (r12 + r21) / s
    else:
        s = 2.0 * math.sqrt(1.0 + r22 - r00 - r11)
        w = (r10 - r01) / s; x = (r02 + r20) / s; y = (r12 + r21) / s; z = 0.25 * s
    n = math.sqrt(w * w + x * x + y * y + z * z)
    if w < 0.0:
        n = -n
    row[at] = w / n
    row[at + 1] = x / n
    row[at + 2] = y / n
    row[at + 3] = z / n


@njit(**_JIT)
def hd_read(x, row):
    buf = _F1(x[X_BUF], (NBUF,))
    ib = _I1(x[X_IBUF], (2,))
    call_v_u32_ptr(x[X_GET_DOUBLEV], HD_CURRENT_TRANSFORM, x[X_BUF] + 8 * B_M)
    call_v_u32_ptr(x[X_GET_DOUBLEV], HD_CURRENT_VELOCITY, x[X_BUF] + 8 * B_V)
    call_v_u32_ptr(x[X_GET_DOUBLEV], HD_CURRENT_ANGULAR_VELOCITY, x[X_BUF] + 8 * B_W)
    ib[0] = 0
    call_v_u32_ptr(x[X_GET_INTEGERV], HD_CURRENT_BUTTONS, x[X_IBUF])
    x[X_BUTTONS] = ib[0] & 0xFFFFFFFF
    row[0] = buf[B_M + 12] * 1e-3
    row[1] = buf[B_M + 13] * 1e-3
    row[2] = buf[B_M + 14] * 1e-3
    _quat_from_colmajor(buf, row, 3)
    for j in range(3):
        row[7 + j] = buf[B_V + j] * 1e-3
        row[10 + j] = buf[B_W + j]
    for j in range(13, 19):
        row[j] = math.nan  # no force sensor
    err = x[X_ERROR]
    if err == HD_COMM_ERROR:
        return DEV_FAULT_LINK
    if err != 0:
        return DEV_FAULT_HARDWARE
    return DEV_OK


@njit(**_JIT)
def hd_write(x, wrench):
    buf = _F1(x[X_BUF], (NBUF,))
    for j in range(3):
        buf[B_F + j] = wrench[j] if x[X_ARMED] != 0 else 0.0
    call_v_u32_ptr(x[X_SET_DOUBLEV], HD_CURRENT_FORCE, x[X_BUF] + 8 * B_F)
    return DEV_OK


@cfunc(types.int32(types.voidptr, types.voidptr), **_JIT)
def _read(ctx, row):
    x = _I1(voidptr_to_int(ctx), (NX,))
    return hd_read(x, _F1(voidptr_to_int(row), (20,)))


@cfunc(types.int32(types.voidptr, types.voidptr), **_JIT)
def _write(ctx, wrench):
    x = _I1(voidptr_to_int(ctx), (NX,))
    return hd_write(x, _F1(voidptr_to_int(wrench), (6,)))


@cfunc(types.int32(types.voidptr, types.voidptr), **_JIT)
def _begin(ctx, _unused):
    x = _I1(voidptr_to_int(ctx), (NX,))
    call_v_u32(x[X_BEGIN_FRAME], x[X_HANDLE])
    return 0


@cfunc(types.int32(types.voidptr, types.voidptr), **_JIT)
def _end(ctx, _unused):
    x = _I1(voidptr_to_int(ctx), (NX,))
    call_v_u32(x[X_END_FRAME], x[X_HANDLE])
    x[X_ERROR] = call_struct12_error(x[X_GET_ERROR])
    return 0


#: (frame_begin, read, write, frame_end): the cfuncs' addresses
ADDRESSES = (_begin.address, _read.address, _write.address, _end.address)


def context(lib, handle: int):
    """``(ctx, keep)``: the int64 context for ``lib`` (the HD ``CDLL``) and the device ``handle``, and
    the arrays it points into (keep them referenced while the servo runs)."""
    buf = np.zeros(NBUF)
    ibuf = np.zeros(2, dtype=np.int64)
    x = np.zeros(NX, dtype=np.int64)

    def addr(fn):
        return ctypes.cast(fn, ctypes.c_void_p).value

    x[X_GET_DOUBLEV] = addr(lib.hdGetDoublev)
    x[X_GET_INTEGERV] = addr(lib.hdGetIntegerv)
    x[X_SET_DOUBLEV] = addr(lib.hdSetDoublev)
    x[X_BEGIN_FRAME] = addr(lib.hdBeginFrame)
    x[X_END_FRAME] = addr(lib.hdEndFrame)
    x[X_GET_ERROR] = addr(lib.hdGetError)
    x[X_HANDLE] = int(handle)
    x[X_BUF] = buf.ctypes.data
    x[X_IBUF] = ibuf.ctypes.data
    return x, (buf, ibuf)
