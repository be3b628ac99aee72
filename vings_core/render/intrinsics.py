"""Small LLVM intrinsics for the numba kernels: software prefetch and count-trailing-zeros.

The tile kernels visit the Gaussians of a tile in depth order, so their per-Gaussian records
(``params``, ``aux``, ``bbox`` rows) and per-pair gradient rows are scattered in memory: without
help every (tile, Gaussian) pair starts with cache misses that the out-of-order core cannot hide
behind the long per-pixel loop. :func:`prefetch_row` / :func:`prefetch_at` (read) and
:func:`prefetch_w` (write) ask for those lines a few pairs ahead. :func:`ctz64` iterates the set
bits of a 64-bit pixel mask. All are pure hints or exact integer ops: results do not depend on them.
"""
from __future__ import annotations

from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic


def _row_pointer(context, builder, aryty, ary_val, i_val, i_ty, c_val=None, c_ty=None):
    ary = context.make_array(aryty)(context, builder, ary_val)
    idx = context.cast(builder, i_val, i_ty, types.intp)
    col = (ir.Constant(idx.type, 0) if c_val is None
           else context.cast(builder, c_val, c_ty, types.intp))
    return cgutils.get_item_pointer2(context, builder, data=ary.data,
                                     shape=cgutils.unpack_tuple(builder, ary.shape),
                                     strides=cgutils.unpack_tuple(builder, ary.strides),
                                     layout=aryty.layout, inds=[idx, col], wraparound=False,
                                     boundscheck=False)


def _emit_prefetch(builder, ptr, write: int) -> None:
    i8p = ir.IntType(8).as_pointer()
    i32 = ir.IntType(32)
    fnty = ir.FunctionType(ir.VoidType(), [i8p, i32, i32, i32])
    fn = cgutils.get_or_insert_function(builder.module, fnty, "llvm.prefetch.p0")
    # (address, rw, locality 3 = keep in all levels, cache type 1 = data)
    builder.call(fn, [builder.bitcast(ptr, i8p), ir.Constant(i32, write), ir.Constant(i32, 3),
                      ir.Constant(i32, 1)])


def _is_2d_index(arr, i) -> bool:
    return isinstance(arr, types.Array) and arr.ndim == 2 and isinstance(i, types.Integer)


@intrinsic
def prefetch_row(typingctx, arr, i):
    """Prefetch for reading the cache line holding ``arr[i, 0]`` (2-D array; no bounds check,
    a prefetch never faults)."""
    if not _is_2d_index(arr, i):
        return None

    def codegen(context, builder, sig, args):
        _emit_prefetch(builder, _row_pointer(context, builder, sig.args[0], args[0], args[1],
                                             sig.args[1]), 0)
        return context.get_dummy_value()
    return types.void(arr, i), codegen


@intrinsic
def prefetch_at(typingctx, arr, i, c):
    """Prefetch for reading the cache line holding ``arr[i, c]``."""
    if not (_is_2d_index(arr, i) and isinstance(c, types.Integer)):
        return None

    def codegen(context, builder, sig, args):
        _emit_prefetch(builder, _row_pointer(context, builder, sig.args[0], args[0], args[1],
                                             sig.args[1], args[2], sig.args[2]), 0)
        return context.get_dummy_value()
    return types.void(arr, i, c), codegen


@intrinsic
def prefetch_w(typingctx, arr, i):
    """Prefetch for writing the cache line holding ``arr[i, 0]``."""
    if not _is_2d_index(arr, i):
        return None

    def codegen(context, builder, sig, args):
        _emit_prefetch(builder, _row_pointer(context, builder, sig.args[0], args[0], args[1],
                                             sig.args[1]), 1)
        return context.get_dummy_value()
    return types.void(arr, i), codegen


@intrinsic
def ctz64(typingctx, x):
    """Number of trailing zero bits of a ``uint64`` (64 for 0)."""
    if not isinstance(x, types.Integer):
        return None

    def codegen(context, builder, sig, args):
        v = context.cast(builder, args[0], sig.args[0], types.uint64)
        return builder.cttz(v, ir.Constant(ir.IntType(1), 0))
    return types.uint64(x), codegen
