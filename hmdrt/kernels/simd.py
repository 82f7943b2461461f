"""SIMD loads and blends written in LLVM IR, for the image kernels that numba would leave scalar.

numba compiles with LLVM's SLP vectoriser off (it can miscompile: numba pull request 8852), so a blend written
channel by channel stays one load and one multiply per float. These builders let an intrinsic load a texel's
channels as one vector and blend them lane by lane; `texel_blend` is such an intrinsic for the foveation pyramids
(`texel_blend_into` stores its blend as a texel), `rgb_accumulate` one for sums of weighted RGB texels in float64,
`rgb_bilinear` a bilinear tap of an RGB image in float64 (`rgb_bilinear_add` adds one to a weighted sum).
"""

from __future__ import annotations

from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

I32 = ir.IntType(32)
F32 = ir.FloatType()
F64 = ir.DoubleType()
TEXEL_FLOATS = 5  # the float32 of a texel the texel intrinsics read: a foveation pyramid's r, g, b, depth, weight


def splat(builder: ir.IRBuilder, x: ir.Value, lanes: int) -> ir.Value:
    """x in every one of `lanes` lanes."""
    vector = ir.VectorType(x.type, lanes)
    first = builder.insert_element(ir.Constant(vector, ir.Undefined), x, ir.Constant(I32, 0))
    return pick(builder, first, [0] * lanes)


def pick(builder: ir.IRBuilder, v: ir.Value, lanes: list[int]) -> ir.Value:
    """The vector of v's lanes `lanes`, in that order."""
    return builder.shuffle_vector(
        v, ir.Constant(v.type, ir.Undefined), ir.Constant(ir.VectorType(I32, len(lanes)), lanes)
    )


def lerp(builder: ir.IRBuilder, a: ir.Value, b: ir.Value, t: ir.Value) -> ir.Value:
    """a + t * (b - a) lane by lane, the multiply-add fused where the CPU has FMA (llvm.fmuladd)."""
    name = f"llvm.fmuladd.v{a.type.count}f32"
    fmuladd = cgutils.get_or_insert_function(builder.module, ir.FunctionType(a.type, [a.type] * 3), name)
    return builder.call(fmuladd, [t, builder.fsub(b, a), a])


def lanes_tuple(context, builder: ir.IRBuilder, tuple_type, v: ir.Value, n: int) -> ir.Value:
    """The first n lanes of vector v as a numba tuple of `tuple_type`: what an intrinsic returns."""
    return context.make_tuple(builder, tuple_type, [builder.extract_element(v, ir.Constant(I32, i)) for i in range(n)])


def lerp_wide(builder: ir.IRBuilder, u: ir.Value, v: ir.Value, t: ir.Value) -> ir.Value:
    """u + t (v - u) for float32 vectors u and v and a float64 t, in float64: v - u in float32, then t times it added
    to u, the multiply and the add apart, as the same lerp written channel by channel does."""
    wide = ir.VectorType(F64, u.type.count)
    return builder.fadd(
        builder.fpext(u, wide), builder.fmul(splat(builder, t, u.type.count), builder.fpext(builder.fsub(v, u), wide))
    )


def _flat(a, dtype) -> bool:
    """Whether numba type `a` is a C-contiguous 1-d array of `dtype`."""
    return isinstance(a, types.Array) and a.ndim == 1 and a.layout == "C" and a.dtype == dtype


def prefetch(builder: ir.IRBuilder, data: ir.Value, index: ir.Value) -> None:
    """A hint to bring the cache line of element `index` of data into every cache level (llvm.prefetch: a read,
    locality 3, data); it never faults, so an index past the image is harmless."""
    i8p = ir.IntType(8).as_pointer()
    fn = cgutils.get_or_insert_function(
        builder.module, ir.FunctionType(ir.VoidType(), [i8p, I32, I32, I32]), "llvm.prefetch.p0i8"
    )
    address = builder.bitcast(builder.gep(data, [index]), i8p)
    builder.call(fn, [address, ir.Constant(I32, 0), ir.Constant(I32, 3), ir.Constant(I32, 1)])


def vector_at(builder: ir.IRBuilder, data: ir.Value, index: ir.Value, lanes: int) -> ir.Value:
    """A pointer to `lanes` float32 from element `index` of data, for one unaligned load or store."""
    return builder.bitcast(builder.gep(data, [index]), ir.VectorType(F32, lanes).as_pointer())


def _first(builder: ir.IRBuilder, k: ir.Value) -> ir.Value:
    """The element of texel k's first float, k times TEXEL_FLOATS: a constant, which the compiler multiplies by with
    an add and a shift, where the array's row length would take a load and a multiply (TAA 5% longer)."""
    return builder.mul(k, ir.Constant(k.type, TEXEL_FLOATS))


def _texel(builder: ir.IRBuilder, data: ir.Value, k: ir.Value) -> ir.Value:
    """Texel k's first four channels: one 16-byte load."""
    return builder.load(vector_at(builder, data, _first(builder, k), 4), align=4)


@intrinsic
def texel_blend(typingctx, data, k00, k01, k10, k11, a, b):
    """The first four channels (a pyramid's r, g, b and depth) in float32 between texels k00 (top left), k01, k10 and
    k11 of `data`, a C-contiguous (texels, TEXEL_FLOATS) float32 array, with float32 weights a across and b down:
    q (p t00 + a t01) + b (p t10 + a t11) with p = 1 - a, q = 1 - b, the multiplies and adds apart (no fused
    multiply-add), so that each lane rounds as the same blend written channel by channel does. Each texel is one
    16-byte load; the blend four lanes at once. The indices are not checked."""
    if not _blend_types(data, k00, k01, k10, k11, a, b):
        return None

    def codegen(context, builder, sig, args):
        blend = _blend_texels(context, builder, sig, args)
        return lanes_tuple(context, builder, sig.return_type, blend, 4)

    return types.UniTuple(types.float32, 4)(data, k00, k01, k10, k11, a, b), codegen


def _texels_types(data, *indices) -> bool:
    """Whether `data` is a C-contiguous 2-d float32 array of texels (a pyramid's, or rows of RGB) and `indices`
    integers, as the texel and RGB-row intrinsics take them."""
    if not (isinstance(data, types.Array) and data.ndim == 2 and data.layout == "C" and data.dtype == types.float32):
        return False
    return all(isinstance(k, types.Integer) for k in indices)


def _blend_types(data, k00, k01, k10, k11, a, b) -> bool:
    """Whether texel_blend takes these argument types."""
    return _texels_types(data, k00, k01, k10, k11) and (a, b) == (types.float32,) * 2


def _blend_texels(context, builder, sig, args) -> ir.Value:
    """texel_blend's four lanes, for the arguments (data, k00, k01, k10, k11, a, b) at the front of sig and args."""
    array = context.make_array(sig.args[0])(context, builder, args[0])
    taps = [
        _texel(builder, array.data, context.cast(builder, k, t, types.int64))
        for k, t in zip(args[1:5], sig.args[1:5], strict=True)
    ]
    a4, b4 = splat(builder, args[5], 4), splat(builder, args[6], 4)
    one = splat(builder, ir.Constant(F32, 1.0), 4)
    p4, q4 = builder.fsub(one, a4), builder.fsub(one, b4)
    top = builder.fadd(builder.fmul(p4, taps[0]), builder.fmul(a4, taps[1]))
    bottom = builder.fadd(builder.fmul(p4, taps[2]), builder.fmul(a4, taps[3]))
    return builder.fadd(builder.fmul(q4, top), builder.fmul(b4, bottom))


@intrinsic
def texel_trilinear(typingctx, data, k00, k01, k10, k11, a, b, m00, m01, m10, m11, c, d, t):
    """u + t (v - u) lane by lane in float64, for u the texel_blend of texels k00..k11 with weights a, b and v that of
    m00..m11 with c, d (two pyramid levels, say): v - u in float32, then t times it added to u in float64, the
    multiply and the add apart, so that each lane rounds as the same lerp written channel by channel with a
    float64 t does. Each texel one 16-byte load; the blends and the lerp four lanes at once. The indices are not
    checked."""
    if not (_blend_types(data, k00, k01, k10, k11, a, b) and _blend_types(data, m00, m01, m10, m11, c, d)):
        return None
    if t != types.float64:
        return None

    def codegen(context, builder, sig, args):
        u = _blend_texels(context, builder, sig, args)
        v = _blend_texels(context, builder, sig.return_type(sig.args[0], *sig.args[7:13]), (args[0], *args[7:13]))
        return lanes_tuple(context, builder, sig.return_type, lerp_wide(builder, u, v, args[13]), 4)

    signature = types.UniTuple(types.float64, 4)(data, k00, k01, k10, k11, a, b, m00, m01, m10, m11, c, d, t)
    return signature, codegen


@intrinsic
def texel_blend_into(typingctx, data, k00, k01, k10, k11, a, b, i):
    """texel_blend's four lanes stored as texel i's first four channels of `data`, one 16-byte store (texel i must
    not be one of the four it reads from). The indices are not checked."""
    if not (_blend_types(data, k00, k01, k10, k11, a, b) and _texels_types(data, i)):
        return None

    def codegen(context, builder, sig, args):
        blend = _blend_texels(context, builder, sig, args)
        array = context.make_array(sig.args[0])(context, builder, args[0])
        k = context.cast(builder, args[7], sig.args[7], types.int64)
        builder.store(blend, vector_at(builder, array.data, _first(builder, k), 4), align=4)
        return context.get_dummy_value()

    return types.void(data, k00, k01, k10, k11, a, b, i), codegen


@intrinsic
def rgb_accumulate(typingctx, r, g, b, weight, data, i):
    """(r + weight t0, g + weight t1, b + weight t2) in float64, for the three float32 t0, t1, t2 from element i of
    `data`, a C-contiguous 1-d float32 array (an RGB image flattened: i a texel's red): each a multiply and then an
    add, so the same sums as channel by channel, three lanes at once. The texel is one 16-byte load, so the float
    after its blue must be readable memory: the next texel's red, or past the last texel a spare float the array's
    buffer keeps (temporal.History's colour ring does). i is not checked."""
    if (r, g, b, weight) != (types.float64,) * 4 or not isinstance(i, types.Integer):
        return None
    if not _flat(data, types.float32):
        return None

    def codegen(context, builder, sig, args):
        array = context.make_array(sig.args[4])(context, builder, args[4])
        texel = builder.load(vector_at(builder, array.data, args[5], 4), align=4)
        acc = ir.Constant(ir.VectorType(F64, 4), [0.0] * 4)
        for lane, x in enumerate(args[:3]):
            acc = builder.insert_element(acc, x, ir.Constant(I32, lane))
        total = builder.fadd(acc, builder.fmul(splat(builder, args[3], 4), builder.fpext(texel, acc.type)))
        return lanes_tuple(context, builder, sig.return_type, total, 3)

    return types.UniTuple(types.float64, 3)(r, g, b, weight, data, i), codegen


def _rgb_at(builder: ir.IRBuilder, data: ir.Value, index: ir.Value) -> ir.Value:
    """The three float32 from element `index` of data as the first lanes of four (the fourth 0): one masked load
    (llvm.masked.load), which reads nothing past the three, so the last texel of an image needs no spare float."""
    vector, mask = ir.VectorType(F32, 4), ir.VectorType(ir.IntType(1), 4)
    fn = cgutils.get_or_insert_function(
        builder.module,
        ir.FunctionType(vector, [vector.as_pointer(), I32, mask, vector]),
        "llvm.masked.load.v4f32.p0v4f32",
    )
    lanes, zero = ir.Constant(mask, [1, 1, 1, 0]), ir.Constant(vector, [0.0] * 4)
    return builder.call(fn, [vector_at(builder, data, index, 4), ir.Constant(I32, 4), lanes, zero])


def _bilinear_rgb(context, builder, data_type, data, indices, a, b) -> ir.Value:
    """rgb_bilinear's sums in four float64 lanes (the fourth 0), for its data, (i, step_x, step_y) as (value, type)
    pairs and float64 weights a and b."""
    array = context.make_array(data_type)(context, builder, data)
    first, right, down = (context.cast(builder, v, t, types.uint64) for v, t in indices)
    one = ir.Constant(F64, 1.0)
    p, q = builder.fsub(one, a), builder.fsub(one, b)
    weights = (builder.fmul(p, q), builder.fmul(a, q), builder.fmul(p, b), builder.fmul(a, b))
    below = builder.add(first, down)
    texels = (first, builder.add(first, right), below, builder.add(below, right))
    total = None
    for weight, k in zip(weights, texels, strict=True):
        texel = builder.fpext(_rgb_at(builder, array.data, k), ir.VectorType(F64, 4))
        term = builder.fmul(splat(builder, weight, 4), texel)
        total = term if total is None else builder.fadd(total, term)
    return total


def _rgb_image_types(data, i, step_x, step_y, a, b) -> bool:
    """Whether rgb_bilinear takes these argument types."""
    if (a, b) != (types.float64,) * 2 or not all(isinstance(k, types.Integer) for k in (i, step_x, step_y)):
        return False
    return isinstance(data, types.Array) and data.layout == "C" and data.dtype == types.float32


@intrinsic
def rgb_bilinear(typingctx, data, i, step_x, step_y, a, b):
    """The bilinear tap of an RGB image read flat (`data`, a C-contiguous float32 array of any shape, indexed by
    element as its flat view is) at element i (a texel's red) and its neighbours step_x to the right and step_y down,
    with float64 weights a across and b down, in float64: (1 - a)(1 - b) t00 + a (1 - b) t01 + (1 - a) b t10 + a b t11,
    the weights, products and sums in that order, each rounded on its own as the same sum written channel by
    channel (projection.blend_footprint's). Each texel one masked load, the sums three lanes at once. The indices
    are not checked."""
    if not _rgb_image_types(data, i, step_x, step_y, a, b):
        return None

    def codegen(context, builder, sig, args):
        indices = tuple(zip(args[1:4], sig.args[1:4], strict=True))
        total = _bilinear_rgb(context, builder, sig.args[0], args[0], indices, args[4], args[5])
        return lanes_tuple(context, builder, sig.return_type, total, 3)

    return types.UniTuple(types.float64, 3)(data, i, step_x, step_y, a, b), codegen


@intrinsic
def rgb_bilinear_add(typingctx, sums, j, weight, data, i, step_x, step_y, a, b):
    """sums[j:j + 3] += weight times rgb_bilinear(data, i, step_x, step_y, a, b), and sums[j + 3] += weight: a
    weighted sum of taps and of their weights, kept as four float64 in a row (`sums` a C-contiguous 1-d float64
    array); each a multiply and then an add, as channel by channel, the four lanes at once (one load and one
    store). The indices are not checked."""
    if not (_rgb_image_types(data, i, step_x, step_y, a, b) and weight == types.float64):
        return None
    if not (_flat(sums, types.float64) and isinstance(j, types.Integer)):
        return None

    def codegen(context, builder, sig, args):
        indices = tuple(zip(args[4:7], sig.args[4:7], strict=True))
        tap = _bilinear_rgb(context, builder, sig.args[3], args[3], indices, args[7], args[8])
        tap = builder.insert_element(tap, ir.Constant(F64, 1.0), ir.Constant(I32, 3))  # weight x 1 is the weight
        array = context.make_array(sig.args[0])(context, builder, args[0])
        k = context.cast(builder, args[1], sig.args[1], types.int64)
        at = builder.bitcast(builder.gep(array.data, [k]), ir.VectorType(F64, 4).as_pointer())
        total = builder.fadd(builder.load(at, align=8), builder.fmul(splat(builder, args[2], 4), tap))
        builder.store(total, at, align=8)
        return context.get_dummy_value()

    return types.void(sums, j, weight, data, i, step_x, step_y, a, b), codegen


def _rgb_blend(context, builder, sig, args) -> ir.Value:
    """(1 - a) rows[i0] + a rows[i1] in float32, four lanes (the fourth 0), for (rows, i0, i1, a) at the front of sig
    and args; each texel one masked load (_rgb_at)."""
    array = context.make_array(sig.args[0])(context, builder, args[0])
    three = ir.Constant(ir.IntType(64), 3)
    first, second = (
        _rgb_at(builder, array.data, builder.mul(context.cast(builder, k, t, types.int64), three))
        for k, t in zip(args[1:3], sig.args[1:3], strict=True)
    )
    a = splat(builder, args[3], 4)
    p = builder.fsub(splat(builder, ir.Constant(F32, 1.0), 4), a)
    return builder.fadd(builder.fmul(p, first), builder.fmul(a, second))


@intrinsic
def rgb_blend(typingctx, rows, i0, i1, a):
    """(1 - a) rows[i0] + a rows[i1] for the three channels of an (n, 3) float32 array of texels, in float32, the
    multiplies and the add apart as channel by channel; each texel one masked load, the blend three lanes at once.
    The indices are not checked."""
    if not (_texels_types(rows, i0, i1) and a == types.float32):
        return None

    def codegen(context, builder, sig, args):
        return lanes_tuple(context, builder, sig.return_type, _rgb_blend(context, builder, sig, args), 3)

    return types.UniTuple(types.float32, 3)(rows, i0, i1, a), codegen


@intrinsic
def rgb_lerp_to_blend(typingctx, r, g, b, rows, j0, j1, c, t):
    """x + t (v - x) for the float32 colour x = (r, g, b) and v = rgb_blend(rows, j0, j1, c): v - x in float32, then
    t times it added to x in float64, the multiply and the add apart, as channel by channel with a float64 t; three
    lanes at once. The indices are not checked."""
    if (r, g, b, c, t) != (types.float32,) * 4 + (types.float64,) or not _texels_types(rows, j0, j1):
        return None

    def codegen(context, builder, sig, args):
        x = ir.Constant(ir.VectorType(F32, 4), [0.0] * 4)
        for lane, value in enumerate(args[:3]):
            x = builder.insert_element(x, value, ir.Constant(I32, lane))
        v = _rgb_blend(context, builder, sig.return_type(*sig.args[3:7]), args[3:7])
        return lanes_tuple(context, builder, sig.return_type, lerp_wide(builder, x, v, args[7]), 3)

    return types.UniTuple(types.float64, 3)(r, g, b, rows, j0, j1, c, t), codegen


@intrinsic
def texel_mean(typingctx, data, k00, k01, k10, k11, right, down, j):
    """A pyramid's pull at texel j of `data` ((texels, TEXEL_FLOATS) float32: r, g, b, depth, weight): the weighted
    mean of the four children k00 (top left), k01, k10, k11, each counted where its weight is above 0 and it is
    present (the right ones where `right`, the lower ones where `down`; k00 always), whatever the others hold, NaN
    too. Colour and depth are written where the weights sum above 0, and min(1, that sum) as the weight: the sums in
    float64 in the children's order, each child's channels times its weight in float32, so each lane rounds as
    channel by channel. Each child's colour and depth one 16-byte load, masked by its bits; the mean one 16-byte
    store."""
    if not (_texels_types(data, k00, k01, k10, k11, j) and (right, down) == (types.boolean,) * 2):
        return None

    def codegen(context, builder, sig, args):
        array = context.make_array(sig.args[0])(context, builder, args[0])
        i32, f32x4 = ir.IntType(32), ir.VectorType(F32, 4)
        right, down = args[5], args[6]
        present = [ir.Constant(ir.IntType(1), 1), right, down, builder.and_(right, down)]
        wsum = ir.Constant(F64, 0.0)
        acc = ir.Constant(ir.VectorType(F64, 4), [0.0] * 4)
        for k, t, here in zip(args[1:5], sig.args[1:5], present, strict=True):
            first = _first(builder, context.cast(builder, k, t, types.int64))
            weight = builder.load(builder.gep(array.data, [builder.add(first, ir.Constant(first.type, 4))]), align=4)
            counts = builder.and_(here, builder.fcmp_ordered(">", weight, ir.Constant(F32, 0.0)))
            keep = builder.select(counts, ir.Constant(i32, -1), ir.Constant(i32, 0))
            w = builder.bitcast(builder.and_(builder.bitcast(weight, i32), keep), F32)
            texel = builder.load(vector_at(builder, array.data, first, 4), align=4)
            bits = builder.bitcast(texel, ir.VectorType(i32, 4))
            texel = builder.bitcast(builder.and_(bits, splat(builder, keep, 4)), f32x4)
            wsum = builder.fadd(wsum, builder.fpext(w, F64))
            acc = builder.fadd(acc, builder.fpext(builder.fmul(splat(builder, w, 4), texel), acc.type))
        out = _first(builder, context.cast(builder, args[7], sig.args[7], types.int64))
        with builder.if_then(builder.fcmp_ordered(">", wsum, ir.Constant(F64, 0.0))):
            mean = builder.fptrunc(builder.fdiv(acc, splat(builder, wsum, 4)), f32x4)
            builder.store(mean, vector_at(builder, array.data, out, 4), align=4)
        one = ir.Constant(F64, 1.0)
        capped = builder.select(builder.fcmp_ordered("<", one, wsum), one, wsum)
        weight_at = builder.gep(array.data, [builder.add(out, ir.Constant(out.type, 4))])
        builder.store(builder.fptrunc(capped, F32), weight_at)
        return context.get_dummy_value()

    return types.void(data, k00, k01, k10, k11, right, down, j), codegen
