"""What compiled code needs from the operating system and the CPU, as numba intrinsics.

The haptic tick runs as compiled code that never returns to Python per period: in a thread of its
own that owns the clock, or in a device SDK's servo thread. It therefore reads the clock, sleeps
until an absolute deadline, orders its memory accesses against other threads and calls a device
library's C functions itself. Each is one LLVM instruction or one libc call, emitted here:

- ``monotonic_ns()``: ``clock_gettime(CLOCK_MONOTONIC)`` in ns, the clock ``time.monotonic_ns``
  reads (so Python and compiled code compare times directly);
- ``sleep_until_ns(t)``: ``clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, t)``: an absolute
  deadline, so a late wake-up never shifts the next one;
- ``fence()``: a sequentially consistent fence (``mfence`` on x86-64): every load and store
  before it is visible before any after it, to this thread and to others, and the compiler moves
  none across it;
- ``fd_readable(fd)``: ``poll(fd, POLLIN, 0)``: a datagram waits on the socket (no wait);
- ``call_i32_ptr_ptr(fn, a, b)``: call the C function at address ``fn`` as
  ``int32_t fn(void *a, void *b)`` (a device's compiled read or write, a C callback);
- ``address_as_f64(addr, n)`` / ``address_as_i64(addr, n)``: a float64/int64 array over ``n``
  elements at a raw address (a descriptor of arrays handed to a C callback as ``void *``).

The libc functions are bound by name, not by address, so kernels that use them are cached like
any other (the symbol is resolved again when the cache is loaded).
"""
from __future__ import annotations

from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

CLOCK_MONOTONIC = 1   # <time.h> on Linux
TIMER_ABSTIME = 1

_I32 = ir.IntType(32)
_I64 = ir.IntType(64)
_TIMESPEC = ir.LiteralStructType([_I64, _I64])  # struct timespec on LP64: time_t, long


def _timespec_fields(builder, ts):
    zero = ir.Constant(_I32, 0)
    return builder.gep(ts, [zero, zero]), builder.gep(ts, [zero, ir.Constant(_I32, 1)])


@intrinsic
def monotonic_ns(typingctx):
    """``clock_gettime(CLOCK_MONOTONIC)`` in ns (int64)."""
    sig = types.int64()

    def codegen(context, builder, signature, args):
        ts = cgutils.alloca_once(builder, _TIMESPEC)
        fnty = ir.FunctionType(_I32, [_I32, _TIMESPEC.as_pointer()])
        fn = cgutils.get_or_insert_function(builder.module, fnty, "clock_gettime")
        builder.call(fn, [ir.Constant(_I32, CLOCK_MONOTONIC), ts])
        ps, pns = _timespec_fields(builder, ts)
        return builder.add(builder.mul(builder.load(ps), ir.Constant(_I64, 1_000_000_000)), builder.load(pns))

    return sig, codegen


@intrinsic
def sleep_until_ns(typingctx, t_ns):
    """``clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, t_ns)``; returns its result (0, or EINTR
    when a signal woke the thread early: the caller re-reads the clock either way)."""
    if not isinstance(t_ns, types.Integer):
        return None
    sig = types.int32(t_ns)

    def codegen(context, builder, signature, args):
        t = context.cast(builder, args[0], signature.args[0], types.int64)
        ts = cgutils.alloca_once(builder, _TIMESPEC)
        ps, pns = _timespec_fields(builder, ts)
        sec = builder.sdiv(t, ir.Constant(_I64, 1_000_000_000))
        builder.store(sec, ps)
        builder.store(builder.sub(t, builder.mul(sec, ir.Constant(_I64, 1_000_000_000))), pns)
        fnty = ir.FunctionType(_I32, [_I32, _I32, _TIMESPEC.as_pointer(), _TIMESPEC.as_pointer()])
        fn = cgutils.get_or_insert_function(builder.module, fnty, "clock_nanosleep")
        return builder.call(fn, [ir.Constant(_I32, CLOCK_MONOTONIC), ir.Constant(_I32, TIMER_ABSTIME), ts,
                                 ir.Constant(_TIMESPEC.as_pointer(), None)])

    return sig, codegen


@intrinsic
def fence(typingctx):
    """A sequentially consistent memory fence."""
    sig = types.void()

    def codegen(context, builder, signature, args):
        builder.fence("seq_cst")
        return context.get_dummy_value()

    return sig, codegen


POLLIN = 1
_I16 = ir.IntType(16)
_POLLFD = ir.LiteralStructType([_I32, _I16, _I16])  # struct pollfd: int fd; short events, revents


@intrinsic
def fd_readable(typingctx, fd):
    """1 when ``poll`` says the descriptor has data to read now, 0 when not (or on an error)."""
    if not isinstance(fd, types.Integer):
        return None
    sig = types.int32(fd)

    def codegen(context, builder, signature, args):
        p = cgutils.alloca_once(builder, _POLLFD)
        zero = ir.Constant(_I32, 0)
        builder.store(builder.trunc(context.cast(builder, args[0], signature.args[0], types.int64), _I32),
                      builder.gep(p, [zero, zero]))
        builder.store(ir.Constant(_I16, POLLIN), builder.gep(p, [zero, ir.Constant(_I32, 1)]))
        builder.store(ir.Constant(_I16, 0), builder.gep(p, [zero, ir.Constant(_I32, 2)]))
        fnty = ir.FunctionType(_I32, [_POLLFD.as_pointer(), _I64, _I32])
        fn = cgutils.get_or_insert_function(builder.module, fnty, "poll")
        n = builder.call(fn, [p, ir.Constant(_I64, 1), zero])
        rev = builder.load(builder.gep(p, [zero, ir.Constant(_I32, 2)]))
        hit = builder.and_(builder.icmp_signed(">", n, zero),
                           builder.icmp_unsigned("!=", builder.and_(rev, ir.Constant(_I16, POLLIN)),
                                                 ir.Constant(_I16, 0)))
        return builder.zext(hit, _I32)

    return sig, codegen


@intrinsic
def call_i32_ptr_ptr(typingctx, fn, a, b):
    """``((int32_t (*)(void *, void *)) fn)(a, b)``: ``fn``, ``a`` and ``b`` are addresses (int64)."""
    if not all(isinstance(x, types.Integer) for x in (fn, a, b)):
        return None
    sig = types.int32(fn, a, b)

    def codegen(context, builder, signature, args):
        ptr = ir.IntType(8).as_pointer()
        fnty = ir.FunctionType(_I32, [ptr, ptr])
        f = builder.inttoptr(context.cast(builder, args[0], signature.args[0], types.int64), fnty.as_pointer())
        pa = builder.inttoptr(context.cast(builder, args[1], signature.args[1], types.int64), ptr)
        pb = builder.inttoptr(context.cast(builder, args[2], signature.args[2], types.int64), ptr)
        return builder.call(f, [pa, pb])

    return sig, codegen


def _address_as(dtype):
    @intrinsic
    def address_as(typingctx, addr, n):
        if not (isinstance(addr, types.Integer) and isinstance(n, types.Integer)):
            return None
        arrty = types.Array(dtype, 1, "C")
        sig = arrty(addr, n)

        def codegen(context, builder, signature, args):
            ary = context.make_array(arrty)(context, builder)
            itemsize = context.get_abi_sizeof(context.get_data_type(dtype))
            data = builder.inttoptr(context.cast(builder, args[0], signature.args[0], types.int64),
                                    context.get_data_type(dtype).as_pointer())
            count = context.cast(builder, args[1], signature.args[1], types.intp)
            context.populate_array(ary, data=data, shape=cgutils.pack_array(builder, [count]),
                                   strides=cgutils.pack_array(builder, [context.get_constant(types.intp, itemsize)]),
                                   itemsize=context.get_constant(types.intp, itemsize), meminfo=None)
            return ary._getvalue()

        return sig, codegen

    return address_as


address_as_f64 = _address_as(types.float64)
address_as_i64 = _address_as(types.int64)


def address_as(arrty):
    """An intrinsic ``f(addr, shape)``: an array of numba type ``arrty`` (C-contiguous; its dtype a
    number or a record type, aligned or not as the type says) over memory at a raw address."""
    ndim = arrty.ndim
    dtype = arrty.dtype

    @intrinsic
    def _as(typingctx, addr, shape):
        if not (isinstance(addr, types.Integer) and isinstance(shape, types.BaseTuple) and len(shape) == ndim):
            return None
        sig = arrty(addr, shape)

        def codegen(context, builder, signature, args):
            ary = context.make_array(arrty)(context, builder)
            lty = context.get_data_type(dtype)
            itemsize = context.get_abi_sizeof(lty)
            data = builder.inttoptr(context.cast(builder, args[0], signature.args[0], types.int64), lty.as_pointer())
            dims = cgutils.unpack_tuple(builder, args[1], ndim)
            dims = [context.cast(builder, d, t, types.intp) for d, t in zip(dims, signature.args[1])]
            strides = []
            acc = context.get_constant(types.intp, itemsize)
            for d in reversed(dims):
                strides.insert(0, acc)
                acc = builder.mul(acc, d)
            context.populate_array(ary, data=data, shape=cgutils.pack_array(builder, dims),
                                   strides=cgutils.pack_array(builder, strides),
                                   itemsize=context.get_constant(types.intp, itemsize), meminfo=None)
            return ary._getvalue()

        return sig, codegen

    return _as


@intrinsic
def atomic_cas(typingctx, arr, i, expected, new):
    """Compare-and-swap ``arr[i]`` (int64[:]): if it holds ``expected`` it becomes ``new``;
    returns the value it held (sequentially consistent)."""
    if not (isinstance(arr, types.Array) and arr.dtype == types.int64):
        return None
    sig = types.int64(arr, i, expected, new)

    def codegen(context, builder, signature, args):
        a = context.make_array(signature.args[0])(context, builder, args[0])
        idx = context.cast(builder, args[1], signature.args[1], types.intp)
        ptr = builder.gep(a.data, [idx])
        exp = context.cast(builder, args[2], signature.args[2], types.int64)
        val = context.cast(builder, args[3], signature.args[3], types.int64)
        res = builder.cmpxchg(ptr, exp, val, "seq_cst", "seq_cst")
        return builder.extract_value(res, 0)

    return sig, codegen


@intrinsic
def atomic_store(typingctx, arr, i, v):
    """``arr[i] = v`` (int64[:]) as one sequentially consistent atomic store."""
    if not (isinstance(arr, types.Array) and arr.dtype == types.int64):
        return None
    sig = types.void(arr, i, v)

    def codegen(context, builder, signature, args):
        a = context.make_array(signature.args[0])(context, builder, args[0])
        idx = context.cast(builder, args[1], signature.args[1], types.intp)
        ptr = builder.gep(a.data, [idx])
        st = builder.store_atomic(context.cast(builder, args[2], signature.args[2], types.int64), ptr, "seq_cst", 8)
        return context.get_dummy_value()

    return sig, codegen


def _fnptr(builder, context, value, valty, fnty):
    return builder.inttoptr(context.cast(builder, value, valty, types.int64), fnty.as_pointer())


@intrinsic
def call_v_u32(typingctx, fn, a):
    """``((void (*)(uint32_t)) fn)(a)``."""
    if not (isinstance(fn, types.Integer) and isinstance(a, types.Integer)):
        return None
    sig = types.void(fn, a)

    def codegen(context, builder, signature, args):
        fnty = ir.FunctionType(ir.VoidType(), [_I32])
        f = _fnptr(builder, context, args[0], signature.args[0], fnty)
        builder.call(f, [builder.trunc(context.cast(builder, args[1], signature.args[1], types.int64), _I32)])
        return context.get_dummy_value()

    return sig, codegen


@intrinsic
def call_v_u32_ptr(typingctx, fn, a, p):
    """``((void (*)(uint32_t, void *)) fn)(a, p)``: ``p`` an address."""
    if not all(isinstance(x, types.Integer) for x in (fn, a, p)):
        return None
    sig = types.void(fn, a, p)

    def codegen(context, builder, signature, args):
        ptr = ir.IntType(8).as_pointer()
        fnty = ir.FunctionType(ir.VoidType(), [_I32, ptr])
        f = _fnptr(builder, context, args[0], signature.args[0], fnty)
        pp = builder.inttoptr(context.cast(builder, args[2], signature.args[2], types.int64), ptr)
        builder.call(f, [builder.trunc(context.cast(builder, args[1], signature.args[1], types.int64), _I32), pp])
        return context.get_dummy_value()

    return sig, codegen


@intrinsic
def call_struct12_error(typingctx, fn):
    """The first 32-bit field of a 12-byte struct of three 32-bit integers returned by value by
    ``fn(void)`` (OpenHaptics' ``HDErrorInfo hdGetError(void)``): on x86-64 System V such a struct
    comes back in RAX (the first two fields) and EDX (the third)."""
    if not isinstance(fn, types.Integer):
        return None
    sig = types.int64(fn)

    def codegen(context, builder, signature, args):
        rty = ir.LiteralStructType([_I64, _I32])
        fnty = ir.FunctionType(rty, [])
        f = _fnptr(builder, context, args[0], signature.args[0], fnty)
        r = builder.call(f, [])
        lo = builder.extract_value(r, 0)
        return builder.and_(lo, ir.Constant(_I64, 0xFFFFFFFF))

    return sig, codegen


@intrinsic
def voidptr_to_int(typingctx, p):
    """The address a ``void *`` holds, as int64 (a C callback's user data)."""
    if not isinstance(p, (types.RawPointer, types.CPointer)) and p != types.voidptr:
        return None
    sig = types.int64(p)

    def codegen(context, builder, signature, args):
        return builder.ptrtoint(args[0], _I64)

    return sig, codegen
