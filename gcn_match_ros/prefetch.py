"""A cache prefetch hint for compiled loops that read rows of a large array out of order.

The similarity block of a view pair (1 MB at 500 x 500) is larger than a core's L2 cache, and by
the time the candidate edges read it at scattered places it has mostly left the caches (the
other thread may have computed it): :func:`gcn_match_ros.edges.candidates._best_near_lines`
spent two thirds of a call waiting for such reads inside the solve (0.27 ms a first call, 0.08
on a copy just made). :func:`prefetch_row` asks the CPU to start fetching a row a few rows ahead,
while the current one is worked on. A hint: it changes no result, and where the CPU ignores it
only the time is lost.
"""
from __future__ import annotations

from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

__all__ = ["prefetch_row"]

_LINE = 64  # bytes of a cache line on x86-64 (where lines are longer, some hints repeat)


@intrinsic
def prefetch_row(typingctx, array, row):
    """``prefetch_row(array, row)`` in compiled code: a read prefetch (LLVM's ``llvm.prefetch``,
    kept in all cache levels) of the ``strides[0]`` bytes from the start of ``array[row]``: every
    cache line of the row of a C-contiguous array. Of another layout a different span, which costs
    time but nothing else (a prefetch never faults, and changes no value).

    Shapes: array (n, m), any dtype; row in [0, n) (the callers keep it there).
    """
    if not (isinstance(array, types.Array) and array.ndim == 2 and isinstance(row, types.Integer)):
        return None
    signature = types.void(array, row)

    def codegen(context, builder, sig, args):
        array_value, index = args
        data = context.make_array(sig.args[0])(context, builder, array_value)
        int64 = ir.IntType(64)
        index = context.cast(builder, index, sig.args[1], types.int64)
        row_bytes = builder.extract_value(data.strides, 0)
        start = builder.add(builder.ptrtoint(data.data, int64), builder.mul(index, row_bytes))
        n_lines = builder.udiv(builder.add(row_bytes, ir.Constant(int64, _LINE - 1)), ir.Constant(int64, _LINE))
        byte_ptr = ir.PointerType(ir.IntType(8))
        i32 = ir.IntType(32)
        prefetch = cgutils.get_or_insert_function(
            builder.module, ir.FunctionType(ir.VoidType(), [byte_ptr, i32, i32, i32]), "llvm.prefetch.p0i8")
        with cgutils.for_range(builder, n_lines) as loop:
            address = builder.add(start, builder.mul(loop.index, ir.Constant(int64, _LINE)))
            # read (0), keep in all levels (3), data cache (1)
            builder.call(prefetch, [builder.inttoptr(address, byte_ptr), ir.Constant(i32, 0), ir.Constant(i32, 3),
                                    ir.Constant(i32, 1)])
        return context.get_dummy_value()

    return signature, codegen
