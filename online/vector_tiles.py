"""Register tiles: TILE_ROWS rows of one 64-byte vector each (16 float32 or 8 float64
lanes), summed in vector registers, for the products of the tangent's q-q projection
(hyperreduced's ``_add_projected_stiffness``). The arrays are C-contiguous 2-d float32 or
float64 ones (a tile's row is ``lanes`` consecutive values); the others are refused at
compile time, and so is an output that is read only.

Why: numba's loops over the contiguous modes vectorise, but keep each sum in memory (a
load and a store of the output a multiply-add triple), and LLVM vectorised literal-size
tiles written as loops along the wrong axis (gathers across the rows; measured on the
demo's held region, 12 elements' projection: 85 us as loops, 118-600 us as loop tiles).
Written here as vector operations on a stack buffer that only vector loads and stores
touch, the tile lives in registers for the whole inner loop: 85 -> 23 us (stop 52, an AMD
EPYC with AVX-512). On a machine with narrower vectors LLVM splits each 64-byte vector.

A tile is a pointer to TILE_ROWS x lanes values of an array's type on the calling
function's stack (:func:`tile`, made once, at the function's entry); the other intrinsics
read and write it whole. Indices are not checked: the callers check the shapes.
"""

from __future__ import annotations

from llvmlite import ir
from numba import njit, types
from numba.core import cgutils
from numba.extending import intrinsic

TILE_ROWS = 4  # a tile's rows: a step loads one vector of A for 4 multiply-adds
TILE_BYTES = 64  # a row: one AVX-512 register (two AVX2 ones)
_I64 = ir.IntType(64)


def _lanes(dtype) -> int:
    return TILE_BYTES // (dtype.bitwidth // 8)


@njit(inline="always")
def tile_lanes(a) -> int:
    """The values in a tile's row of ``a``'s type (16 float32, 8 float64)."""
    return TILE_BYTES // a.itemsize


def _vector(context, dtype) -> ir.VectorType:
    return ir.VectorType(context.get_value_type(dtype), _lanes(dtype))


def tile_row(context, builder, dtype, acc, row):
    """The tile's row ``row`` as a pointer to one vector (codegen: for intrinsics that
    work on tiles, here and in node_blocks)."""
    lanes = _lanes(dtype)
    start = builder.gep(acc, [ir.Constant(_I64, row * lanes)])
    return builder.bitcast(start, _vector(context, dtype).as_pointer())


def _array_pointer(context, builder, aryty, ary, i, j):
    """&ary[i, j] as a pointer to one vector of ary's type (no wraparound, no check)."""
    array = context.make_array(aryty)(context, builder, ary)
    item = cgutils.get_item_pointer(context, builder, aryty, array, [i, j], wraparound=False)
    return builder.bitcast(item, _vector(context, aryty.dtype).as_pointer())


def _align(dtype) -> int:
    return dtype.bitwidth // 8


_FLOATS = (types.float32, types.float64)


def _is_matrix(a) -> bool:
    """A 2-d C-contiguous float array: its rows' values are consecutive."""
    return isinstance(a, types.Array) and a.ndim == 2 and a.layout == "C" and a.dtype in _FLOATS


def _is_tile(acc) -> bool:
    return isinstance(acc, types.CPointer) and acc.dtype in _FLOATS


@intrinsic
def tile(typingctx, like):
    """A tile of ``like``'s type (a 2-d float32 or float64 array) on the stack."""
    if not _is_matrix(like):
        return None
    dtype = like.dtype

    def codegen(context, builder, sig, args):
        value = context.get_value_type(dtype)
        return cgutils.alloca_once(builder, value, size=TILE_ROWS * _lanes(dtype))

    return types.CPointer(dtype)(like), codegen


@intrinsic
def tile_zero(typingctx, acc):
    """Every value of the tile 0."""
    if not _is_tile(acc):
        return None
    dtype = acc.dtype

    def codegen(context, builder, sig, args):
        zero = ir.Constant(_vector(context, dtype), None)
        for row in range(TILE_ROWS):
            builder.store(zero, tile_row(context, builder, dtype, args[0], row),
                          align=_align(dtype))  # fmt: skip
        return context.get_dummy_value()

    return types.void(acc), codegen


@intrinsic
def tile_fma(typingctx, acc, A, i, j, b0, b1, b2, b3):
    """Row r of the tile += b_r A[i, j : j + lanes], for r < TILE_ROWS: one load of A and
    TILE_ROWS fused multiply-adds (one rounding each)."""
    floats = all(isinstance(b, types.Float) for b in (b0, b1, b2, b3))
    if not (_is_operand(acc, A, i, j) and floats):
        return None
    dtype = acc.dtype

    def codegen(context, builder, sig, args):
        vector = _vector(context, dtype)
        fma = cgutils.get_or_insert_function(
            builder.module, ir.FunctionType(vector, [vector] * 3),
            f"llvm.fma.v{_lanes(dtype)}f{dtype.bitwidth}",
        )  # fmt: skip
        i = context.cast(builder, args[2], sig.args[2], types.intp)
        j = context.cast(builder, args[3], sig.args[3], types.intp)
        a = builder.load(_array_pointer(context, builder, sig.args[1], args[1], i, j),
                         align=_align(dtype))  # fmt: skip
        broadcast = ir.Constant(ir.VectorType(ir.IntType(32), _lanes(dtype)), [0] * _lanes(dtype))
        for row in range(TILE_ROWS):
            b = context.cast(builder, args[4 + row], sig.args[4 + row], dtype)
            b = builder.insert_element(ir.Constant(vector, ir.Undefined), b,
                                       ir.Constant(ir.IntType(32), 0))  # fmt: skip
            b = builder.shuffle_vector(b, ir.Constant(vector, ir.Undefined), broadcast)
            pointer = tile_row(context, builder, dtype, args[0], row)
            total = builder.load(pointer, align=_align(dtype))
            builder.store(builder.call(fma, [b, a, total]), pointer, align=_align(dtype))
        return context.get_dummy_value()

    return types.void(acc, A, i, j, b0, b1, b2, b3), codegen


def _write_tile(context, builder, sig, args, add: bool):
    """K[i + r, j : j + lanes] = (or +=) row r of the tile, for r < TILE_ROWS."""
    dtype = sig.args[0].dtype
    i = context.cast(builder, args[2], sig.args[2], types.intp)
    j = context.cast(builder, args[3], sig.args[3], types.intp)
    for row in range(TILE_ROWS):
        at = builder.add(i, ir.Constant(i.type, row))
        pointer = _array_pointer(context, builder, sig.args[1], args[1], at, j)
        value = builder.load(tile_row(context, builder, dtype, args[0], row),
                             align=_align(dtype))  # fmt: skip
        if add:
            value = builder.fadd(builder.load(pointer, align=_align(dtype)), value)
        builder.store(value, pointer, align=_align(dtype))
    return context.get_dummy_value()


def _is_operand(acc, K, i, j) -> bool:
    """A tile and an array of its type, indexed by integers."""
    integers = isinstance(i, types.Integer) and isinstance(j, types.Integer)
    return _is_tile(acc) and _is_matrix(K) and K.dtype == acc.dtype and integers


def _is_output(acc, K, i, j) -> bool:
    return _is_operand(acc, K, i, j) and K.mutable


@intrinsic
def tile_store(typingctx, acc, K, i, j):
    """K[i + r, j : j + lanes] = row r of the tile, for r < TILE_ROWS."""
    if not _is_output(acc, K, i, j):
        return None
    return types.void(acc, K, i, j), lambda c, b, sig, args: _write_tile(c, b, sig, args, False)


@intrinsic
def tile_add(typingctx, acc, K, i, j):
    """K[i + r, j : j + lanes] += row r of the tile, for r < TILE_ROWS."""
    if not _is_output(acc, K, i, j):
        return None
    return types.void(acc, K, i, j), lambda c, b, sig, args: _write_tile(c, b, sig, args, True)
