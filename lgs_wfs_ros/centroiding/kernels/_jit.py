"""numba, when the ``fast`` extra is installed.

:data:`COMPILED` says whether numba is there (the modules compile their passes at import);
:func:`enabled` whether the compiled passes run now: the package's ``AVAILABLE``, read at
each call, so that turning it off (a test comparing the numpy paths) takes every wrapper
and every caller to numpy together. :func:`prefetch` (compiled code only) asks the CPU for
a cache line before a pass needs it.
"""

import sys

try:                                     # optional: the 'fast' extra
    import numba
    from llvmlite import ir
    from numba.core import cgutils
    from numba.extending import intrinsic
    COMPILED = True
except ImportError:                      # pragma: no cover - exercised where it is absent
    numba = None
    COMPILED = False


def enabled() -> bool:
    """True when the compiled passes are to be used (``kernels.AVAILABLE``)."""
    return bool(sys.modules[__package__].AVAILABLE)


if COMPILED:
    @intrinsic
    def prefetch(typingctx, arr, index):
        """``prefetch(arr, i)`` in compiled code: ask for the cache line of ``arr[i]`` (1-D
        array, any stride) to be loaded into every cache level for reading (LLVM's
        ``llvm.prefetch``: a hint; it changes no value and never faults). A pass whose next
        blocks sit at addresses the hardware cannot guess (a filter row picked per block, a
        block's 16 pixel rows 1,920 bytes apart) asks for them a few blocks ahead."""
        if not (isinstance(arr, numba.types.Array) and arr.ndim == 1
                and isinstance(index, numba.types.Integer)):
            return None
        sig = numba.types.void(arr, index)

        def codegen(context, builder, signature, args):
            aty = signature.args[0]
            ary = context.make_array(aty)(context, builder, args[0])
            ptr = cgutils.get_item_pointer(context, builder, aty, ary, [args[1]],
                                           wraparound=False)
            i8p, i32 = ir.IntType(8).as_pointer(), ir.IntType(32)
            fn = builder.module.declare_intrinsic(
                "llvm.prefetch", [i8p], ir.FunctionType(ir.VoidType(), [i8p, i32, i32, i32]))
            # read, locality 3 (keep in all levels), data cache
            builder.call(fn, [builder.bitcast(ptr, i8p), ir.Constant(i32, 0),
                              ir.Constant(i32, 3), ir.Constant(i32, 1)])
            return context.get_dummy_value()
        return sig, codegen
