"""The transported surface's grid in blocks of LANES consecutive nodes (one 64-byte vector of
float32), summed in vector registers, and its bilinear reads as 16-byte vector loads.

A block's field is the sum over the contact's neighbours j of R_j sum_m c_jm phi_jm, the
neighbour's modes (int16) at the block's nodes moved by its shift, rotated and weighed
(:func:`transported_surface <hapticrom.online.surface_kernels.transported_surface>`). The
modes' sums (:func:`block_modes`) and the rotated sum (:func:`block_rotate`) live in two
tiles (``vector_tiles.tile``: a stack buffer that only vector loads and stores touch, so
LLVM keeps it in registers), and the block is written once, interleaved (x, y, z, 0) a node
(:func:`block_store`), so that a vertex's bilinear read is four 16-byte loads
(:func:`node_read`) instead of twelve scalar ones.

Why: written as numba loops over a row's nodes, a short run's loop vectorised only past 64
nodes (LLVM's vector body is four 16-lane vectors, behind alias checks), so runs of needed
nodes ran scalar (80 against 9 us on the cornea demo), and the grid's interleaved stores
ran scalar too (80 us). Measured on the cornea demo (an AMD EPYC with AVX-512, stop 53,
min over 20,000 calls): the three neighbours' sums over every layer's rectangle (8,816
nodes) 9.1 us, over these blocks of the needed nodes (388 blocks, 6,208 nodes) 7.0 us
with the grid written once; the read loop 10.7 -> 5.6 us (four 16-byte loads a vertex, the
address the node times 16 bytes: with the grid's row stride loaded and multiplied, 8.0;
returning three floats for numba to store, 5.9).

The arrays are C-contiguous (checked at compile time); indices are not checked: the callers
check them (the chart's blocks, ``surface_kernels``).
"""

from __future__ import annotations

from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

from hapticrom.online.vector_tiles import TILE_BYTES, tile_row

LANES = TILE_BYTES // 4  # nodes a block: one vector of float32
MODES_A_BLOCK = 4  # modes one block_modes call sums (the terms past the last are zero)
ROTATION = 9  # a neighbour's terms: its weighed rotation (row-major), then its coefficients
# Each plane's modes are prefetched this many nodes ahead of the block (four cache lines of
# int16): a surface at a new contact reads three samples' modes that are no longer in the
# core's caches, and the hardware's prefetchers follow 36 streams of short runs poorly.
# Measured on the cornea demo (stop 53): the sums alone over new samples after the caches
# were flushed, p99 40-60 -> 20-25 us (two runs); the whole surface at a new contact every
# call, in turn over six pairs, p99 49-80 -> 38-67 us (at most 50 in 10 of 12 runs, against
# 4 of 12), p50 unchanged (22-24 us).
PREFETCH_NODES = 128
_I32 = ir.IntType(32)
_I64 = ir.IntType(64)


def _is_c(a, ndim: int, dtype) -> bool:
    return isinstance(a, types.Array) and a.ndim == ndim and a.layout == "C" and a.dtype == dtype


def _is_tile(t) -> bool:
    return isinstance(t, types.CPointer) and t.dtype == types.float32


def _float_vector(lanes: int = LANES) -> ir.VectorType:
    return ir.VectorType(ir.FloatType(), lanes)


def _mask(values) -> ir.Constant:
    return ir.Constant(ir.VectorType(_I32, len(values)), list(values))


def _splat(builder, value, lanes: int = LANES):
    vector = _float_vector(lanes)
    v = builder.insert_element(ir.Constant(vector, ir.Undefined), value, ir.Constant(_I32, 0))
    return builder.shuffle_vector(v, ir.Constant(vector, ir.Undefined), _mask([0] * lanes))


def _fma(builder, lanes: int = LANES):
    vector = _float_vector(lanes)
    return cgutils.get_or_insert_function(
        builder.module, ir.FunctionType(vector, [vector] * 3), f"llvm.fma.v{lanes}f32"
    )


def _item(context, builder, aryty, ary, indices, pointee):
    """&ary[indices] as a pointer to ``pointee`` (no wraparound, no check)."""
    array = context.make_array(aryty)(context, builder, ary)
    item = cgutils.get_item_pointer(context, builder, aryty, array, indices, wraparound=False)
    return builder.bitcast(item, pointee.as_pointer())


def _index(context, builder, value, ty):
    return context.cast(builder, value, ty, types.intp)


def _first(context, builder, sig, args, position):
    return context.cast(builder, args[position], sig.args[position], types.boolean)


def _keep_or_zero(builder, first, pointer):
    """0 on a first call, else the tile row's value."""
    return builder.select(first, ir.Constant(_float_vector(), None), builder.load(pointer, align=4))


@intrinsic
def block_modes(typingctx, P, node_basis, i, terms, j, k, src, first):
    """Row c of tile P (=, if ``first``; else +=) sum_q terms[j, ROTATION + k + q]
    node_basis[i, min(k + q, n - 1), c, src : src + LANES], q < MODES_A_BLOCK, c < 3: four
    modes of sample i at LANES nodes, times their scaled coefficients (zero past the last
    mode, whose plane is read again)."""
    integers = all(isinstance(x, types.Integer) for x in (i, j, k, src))
    if not (_is_tile(P) and _is_c(node_basis, 4, types.int16) and _is_c(terms, 2, types.float32)
            and integers and isinstance(first, types.Boolean)):  # fmt: skip
        return None
    sig = types.void(P, node_basis, i, terms, j, k, src, first)

    def codegen(context, builder, sig, args):
        fma, vector = _fma(builder), _float_vector()
        shorts = ir.VectorType(ir.IntType(16), LANES)
        prefetch = _prefetch(builder)
        i, j, k, src = (_index(context, builder, args[q], sig.args[q]) for q in (2, 4, 5, 6))
        first = _first(context, builder, sig, args, 7)
        array = context.make_array(sig.args[1])(context, builder, args[1])
        last = builder.sub(cgutils.unpack_tuple(builder, array.shape, 4)[1], ir.Constant(_I64, 1))
        modes, weights = [], []
        for q in range(MODES_A_BLOCK):
            m = builder.add(k, ir.Constant(_I64, q))
            modes.append(builder.select(builder.icmp_signed("<", m, last), m, last))
            column = builder.add(m, ir.Constant(_I64, ROTATION))
            weights.append(_term_at(context, builder, sig, args, j, column))
        for c in range(3):
            total = None
            for q in range(MODES_A_BLOCK):
                pointer = _item(context, builder, sig.args[1], args[1],
                                [i, modes[q], ir.Constant(_I64, c), src], shorts)  # fmt: skip
                prefetch(pointer, 2 * PREFETCH_NODES)  # a hint: never faults, even past the end
                x = builder.sitofp(builder.load(pointer, align=2), vector)
                total = (builder.fmul(weights[q], x) if total is None
                         else builder.call(fma, [weights[q], x, total]))  # fmt: skip
            row = tile_row(context, builder, types.float32, args[0], c)
            total = builder.fadd(_keep_or_zero(builder, first, row), total)
            builder.store(total, row, align=4)
        return context.get_dummy_value()

    return sig, codegen


def _prefetch(builder):
    """A function (pointer, bytes ahead) -> a read prefetch of the line there, into every
    cache level (llvm.prefetch: a hint, which no address makes fault)."""
    byte = ir.IntType(8).as_pointer()
    hint = cgutils.get_or_insert_function(
        builder.module, ir.FunctionType(ir.VoidType(), [byte, _I32, _I32, _I32]), "llvm.prefetch.p0"
    )
    read, locality, data = (ir.Constant(_I32, v) for v in (0, 3, 1))

    def prefetch(pointer, ahead: int):
        at = builder.gep(builder.bitcast(pointer, byte), [ir.Constant(_I64, ahead)])
        builder.call(hint, [at, read, locality, data])

    return prefetch


def _term_at(context, builder, sig, args, j, column):
    """terms[j, column] with a run-time column, as a vector of LANES equal values."""
    pointer = _item(context, builder, sig.args[3], args[3], [j, column], ir.FloatType())
    return _splat(builder, builder.load(pointer))


@intrinsic
def block_rotate(typingctx, acc, P, terms, j, first):
    """Row r of tile acc (=, if ``first``; else +=) sum_c terms[j, 3 r + c] P[c], r < 3:
    a neighbour's sums rotated and weighed."""
    if not (_is_tile(acc) and _is_tile(P) and _is_c(terms, 2, types.float32)
            and isinstance(j, types.Integer) and isinstance(first, types.Boolean)):  # fmt: skip
        return None
    sig = types.void(acc, P, terms, j, first)

    def codegen(context, builder, sig, args):
        fma = _fma(builder)
        j = _index(context, builder, args[3], sig.args[3])
        first = _first(context, builder, sig, args, 4)
        p = [
            builder.load(tile_row(context, builder, types.float32, args[1], c), align=4)
            for c in range(3)
        ]
        for r in range(3):
            row = tile_row(context, builder, types.float32, args[0], r)
            total = _keep_or_zero(builder, first, row)
            for c in range(3):
                pointer = _item(context, builder, sig.args[2], args[2],
                                [j, ir.Constant(_I64, 3 * r + c)], ir.FloatType())  # fmt: skip
                total = builder.call(fma, [_splat(builder, builder.load(pointer)), p[c], total])
            builder.store(total, row, align=4)
        return context.get_dummy_value()

    return sig, codegen


def _quarter(quarter: int) -> ir.Constant:
    """The shuffle of (x0 y0 x1 y1 ..., z0 0 z1 0 ...) that puts four nodes' (x, y, z, 0)
    in a row: nodes 4 (quarter % 2) to 4 (quarter % 2) + 3 of that half."""
    nodes = range(4 * (quarter % 2), 4 * (quarter % 2) + 4)
    return _mask([v for n in nodes for v in (2 * n, 2 * n + 1, LANES + 2 * n, LANES + 2 * n + 1)])


@intrinsic
def block_store(typingctx, grid, g, acc):
    """grid[g + b] = (acc[0][b], acc[1][b], acc[2][b], 0) for b < LANES: the block's rows
    of the tile, interleaved a node (grid (N, 4) float32: the callers check that a row is
    four values)."""
    if not (_is_c(grid, 2, types.float32) and isinstance(g, types.Integer) and _is_tile(acc)
            and grid.mutable):  # fmt: skip
        return None
    sig = types.void(grid, g, acc)

    def codegen(context, builder, sig, args):
        x, y, z = (
            builder.load(tile_row(context, builder, types.float32, args[2], r), align=4)
            for r in range(3)
        )
        zero = ir.Constant(_float_vector(), None)
        half = LANES // 2
        pairs = [[v for b in range(s, s + half) for v in (b, LANES + b)] for s in (0, half)]
        xy = [builder.shuffle_vector(x, y, _mask(m)) for m in pairs]  # x0 y0 x1 y1 ...
        zw = [builder.shuffle_vector(z, zero, _mask(m)) for m in pairs]  # z0 0 z1 0 ...
        g = _index(context, builder, args[1], sig.args[1])
        nodes = builder.bitcast(context.make_array(sig.args[0])(context, builder, args[0]).data,
                                ir.VectorType(ir.FloatType(), 4).as_pointer())  # fmt: skip
        for quarter in range(4):  # four nodes' (x, y, z, 0) a 64-byte store
            a, b = xy[quarter // 2], zw[quarter // 2]
            node = builder.gep(nodes, [builder.add(g, ir.Constant(_I64, 4 * quarter))])
            pointer = builder.bitcast(node, _float_vector().as_pointer())
            builder.store(builder.shuffle_vector(a, b, _quarter(quarter)), pointer, align=4)
        return context.get_dummy_value()

    return sig, codegen


@intrinsic
def node_read(typingctx, out, v, grid, s, columns, w00, w10, w01, w11):
    """out[v, 0:3] = (x, y, z) at a point of the cell whose lower-left node is s, bilinear:
    w00 grid[s] + w10 grid[s + columns] + w01 grid[s + 1] + w11 grid[s + columns + 1] in
    single precision, each node's (x, y, z, 0) one 16-byte load, the sum widened to double
    at once and stored as two values and one (grid (N, 4) float32, out (V, 3) float64: the
    callers check that their rows are four and three values; the addresses are the node
    times 16 bytes and the vertex times 24, with no stride to load)."""
    weights = (w00, w10, w01, w11)
    if not (_is_c(out, 2, types.float64) and out.mutable and isinstance(v, types.Integer)
            and _is_c(grid, 2, types.float32) and isinstance(s, types.Integer)
            and isinstance(columns, types.Integer)
            and all(isinstance(w, types.Float) for w in weights)):  # fmt: skip
        return None
    sig = types.void(out, v, grid, s, columns, *weights)

    def codegen(context, builder, sig, args):
        vector = _float_vector(4)
        fma = _fma(builder, 4)
        nodes = builder.bitcast(context.make_array(sig.args[2])(context, builder, args[2]).data,
                                vector.as_pointer())  # fmt: skip
        s = _index(context, builder, args[3], sig.args[3])
        t = builder.add(s, _index(context, builder, args[4], sig.args[4]))
        one = ir.Constant(_I64, 1)
        total = None
        for node, w in ((s, 5), (t, 6), (builder.add(s, one), 7), (builder.add(t, one), 8)):
            value = builder.load(builder.gep(nodes, [node]), align=4)
            weight = _splat(builder, context.cast(builder, args[w], sig.args[w], types.float32), 4)
            total = (builder.fmul(weight, value) if total is None
                     else builder.call(fma, [weight, value, total]))  # fmt: skip
        wide = builder.fpext(total, ir.VectorType(ir.DoubleType(), 4))
        doubles = builder.bitcast(context.make_array(sig.args[0])(context, builder, args[0]).data,
                                  ir.DoubleType().as_pointer())  # fmt: skip
        row = builder.gep(doubles, [builder.mul(_index(context, builder, args[1], sig.args[1]),
                                                ir.Constant(_I64, 3))])  # fmt: skip
        pair = builder.shuffle_vector(wide, wide, _mask([0, 1]))
        builder.store(pair, builder.bitcast(row, ir.VectorType(ir.DoubleType(), 2).as_pointer()),
                      align=8)  # fmt: skip
        third = builder.extract_element(wide, ir.Constant(_I32, 2))
        builder.store(third, builder.gep(row, [ir.Constant(_I64, 2)]), align=8)
        return context.get_dummy_value()

    return sig, codegen
