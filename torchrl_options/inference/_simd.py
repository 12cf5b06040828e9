"""Eight-lane float32 vectors for the Numba kernels (imported only when Numba is installed).

Numba vectorises loops whose trip count it can see, but the E-step's inner loops run over the K options of one
time step: a handful of iterations, too few for the compiler's vector loops (at K = 8 it ran them one element at a
time). This module gives the kernels an explicit vector type, ``f32x8`` (an LLVM ``<8 x float>``, a ``ymm``
register on x86, two ``q`` registers on ARM), and the few operations they need, each a Numba intrinsic that emits
plain LLVM IR (no target-specific intrinsics, so it compiles wherever Numba does):

* memory: :func:`vload`, :func:`vstore` (8 lanes of a 1-D float32 array at an element offset), :func:`vload_n`,
  :func:`vstore_n` (only the first ``n`` lanes touched: the tail of a row whose K is not a multiple of 8);
* arithmetic: :func:`vsplat`, :func:`vadd`, :func:`vsub`, :func:`vmul`, :func:`vdiv`, :func:`vfma`,
  :func:`vmax`, :func:`vmin` (IEEE, no fast-math flags: the kernels choose the order of every operation);
* reductions over the 8 lanes: :func:`vsum`, :func:`vhmax`, :func:`vhmin` (a fixed shuffle tree), :func:`vsumv`
  (the sum in every lane), :func:`vhmax8` (the maxima of eight vectors at once), :func:`vfirst` (lane 0);
* :func:`vexp`: ``exp(x)`` for ``x <= 0`` to about 1 ulp (Cody-Waite reduction, a degree-6 minimax polynomial,
  the power of two from the exponent bits), exactly 0 below -87 and for ``-inf``.

Offsets are element offsets into 1-D C-contiguous float32 arrays; there are no bounds checks (the callers'
loops stay inside their rows).
"""
from __future__ import annotations

import numpy as np
from llvmlite import ir
from numba.core import cgutils, types
from numba.extending import intrinsic, models, register_model

__all__ = [
    "EXP_CONSTANTS",
    "exp_constants",
    "f32x8",
    "nan_or_posinf",
    "vadd",
    "vdiv",
    "vexp",
    "vfirst",
    "vfma",
    "vhmax",
    "vhmax8",
    "vhmin",
    "vload",
    "vload_n",
    "vmax",
    "vmin",
    "vmul",
    "vsplat",
    "vstore",
    "vstore_n",
    "vsub",
    "vsum",
    "vsum2",
    "vsumv",
]

LANES = 8
_V = ir.VectorType(ir.FloatType(), LANES)
_I32 = ir.IntType(32)
_VI = ir.VectorType(_I32, LANES)


class F32x8Type(types.Type):
    """The Numba type of an 8-lane float32 vector."""

    def __init__(self):
        super().__init__(name="f32x8")


f32x8 = F32x8Type()


@register_model(F32x8Type)
class _F32x8Model(models.PrimitiveModel):
    def __init__(self, dmm, fe_type):
        super().__init__(dmm, fe_type, _V)


def _elem_ptr(context, builder, aryty, ary, idx):
    data = context.make_array(aryty)(context, builder, ary).data
    return builder.gep(data, [idx], inbounds=True)


def _call(builder, name, ret, args):
    fn = cgutils.get_or_insert_function(builder.module, ir.FunctionType(ret, [a.type for a in args]), name)
    return builder.call(fn, args)


def _splat(builder, x, vty=_V):
    v = builder.insert_element(ir.Constant(vty, ir.Undefined), x, ir.Constant(_I32, 0))
    return builder.shuffle_vector(v, ir.Constant(vty, ir.Undefined), ir.Constant(_VI, [0] * LANES))


def _const(v):
    return ir.Constant(_V, [float(np.float32(v))] * LANES)


def _is_f32_array(arr):
    return isinstance(arr, types.Array) and arr.dtype == types.float32 and arr.ndim == 1


@intrinsic
def vload(typingctx, arr, i):
    """``arr[i:i + 8]`` as a vector."""
    if not (_is_f32_array(arr) and isinstance(i, types.Integer)):
        return None

    def codegen(context, builder, sig, args):
        ptr = builder.bitcast(_elem_ptr(context, builder, sig.args[0], args[0], args[1]), _V.as_pointer())
        return builder.load(ptr, align=4)

    return f32x8(arr, i), codegen


@intrinsic
def vload_n(typingctx, arr, i, n, fill):
    """Lanes ``j < n`` from ``arr[i + j]``, the others ``fill``; no memory beyond ``arr[i + n - 1]`` is read."""
    if not (_is_f32_array(arr) and isinstance(i, types.Integer) and isinstance(n, types.Integer)):
        return None
    if fill != types.float32:
        return None

    def codegen(context, builder, sig, args):
        ary, idx, cnt, fillv = args
        out = cgutils.alloca_once_value(builder, _splat(builder, fillv))
        for j in range(LANES):
            with builder.if_then(builder.icmp_signed(">", cnt, ir.Constant(cnt.type, j))):
                p = _elem_ptr(context, builder, sig.args[0], ary, builder.add(idx, ir.Constant(idx.type, j)))
                v = builder.insert_element(builder.load(out), builder.load(p), ir.Constant(_I32, j))
                builder.store(v, out)
        return builder.load(out)

    return f32x8(arr, i, n, fill), codegen


@intrinsic
def vstore(typingctx, arr, i, v):
    """``arr[i:i + 8] = v``."""
    if not (_is_f32_array(arr) and isinstance(i, types.Integer) and v == f32x8):
        return None

    def codegen(context, builder, sig, args):
        ptr = builder.bitcast(_elem_ptr(context, builder, sig.args[0], args[0], args[1]), _V.as_pointer())
        builder.store(args[2], ptr, align=4)
        return context.get_dummy_value()

    return types.none(arr, i, v), codegen


@intrinsic
def vstore_n(typingctx, arr, i, v, n):
    """``arr[i + j] = v[j]`` for the lanes ``j < n`` only."""
    if not (_is_f32_array(arr) and isinstance(i, types.Integer) and v == f32x8 and isinstance(n, types.Integer)):
        return None

    def codegen(context, builder, sig, args):
        ary, idx, vec, cnt = args
        for j in range(LANES):
            with builder.if_then(builder.icmp_signed(">", cnt, ir.Constant(cnt.type, j))):
                p = _elem_ptr(context, builder, sig.args[0], ary, builder.add(idx, ir.Constant(idx.type, j)))
                builder.store(builder.extract_element(vec, ir.Constant(_I32, j)), p)
        return context.get_dummy_value()

    return types.none(arr, i, v, n), codegen


@intrinsic
def nan_or_posinf(typingctx, x):
    """Whether the float32 ``x`` is NaN or +inf, from its bits (so that no fast-math assumption can fold it)."""
    if x != types.float32:
        return None

    def codegen(context, builder, sig, args):
        bits = builder.bitcast(args[0], _I32)
        mag = builder.and_(bits, ir.Constant(_I32, 0x7FFFFFFF))
        nan = builder.icmp_signed(">", mag, ir.Constant(_I32, 0x7F800000))
        posinf = builder.icmp_signed("==", bits, ir.Constant(_I32, 0x7F800000))
        return builder.or_(nan, posinf)

    return types.boolean(x), codegen


@intrinsic
def vsplat(typingctx, x):
    """``x`` (a float32) in every lane."""
    if x != types.float32:
        return None

    def codegen(context, builder, sig, args):
        return _splat(builder, args[0])

    return f32x8(x), codegen


def _binary(op: str, doc: str):
    @intrinsic
    def fn(typingctx, a, b):
        if a != f32x8 or b != f32x8:
            return None

        def codegen(context, builder, sig, args):
            return getattr(builder, op)(args[0], args[1])

        return f32x8(a, b), codegen

    fn.__doc__ = doc
    return fn


vadd = _binary("fadd", "Lane-wise ``a + b``.")
vsub = _binary("fsub", "Lane-wise ``a - b``.")
vmul = _binary("fmul", "Lane-wise ``a * b``.")
vdiv = _binary("fdiv", "Lane-wise ``a / b`` (a true quotient).")


def _select(pred: str, doc: str):
    @intrinsic
    def fn(typingctx, a, b):
        if a != f32x8 or b != f32x8:
            return None

        def codegen(context, builder, sig, args):
            return builder.select(builder.fcmp_ordered(pred, args[0], args[1]), args[0], args[1])

        return f32x8(a, b), codegen

    fn.__doc__ = doc
    return fn


vmax = _select(">", "Lane-wise ``a if a > b else b``.")
vmin = _select("<", "Lane-wise ``a if a < b else b``.")


@intrinsic
def vfma(typingctx, a, b, c):
    """Lane-wise ``a * b + c``, rounded once."""
    if not (a == b == c == f32x8):
        return None

    def codegen(context, builder, sig, args):
        return _call(builder, "llvm.fma.v8f32", _V, list(args))

    return f32x8(a, b, c), codegen


def _reduce(kind: str, doc: str):
    @intrinsic
    def fn(typingctx, v):
        if v != f32x8:
            return None

        def codegen(context, builder, sig, args):
            x = args[0]
            undef = ir.Constant(_V, ir.Undefined)
            for half in (4, 2, 1):
                y = builder.shuffle_vector(x, undef, ir.Constant(_VI, [(j + half) % LANES for j in range(LANES)]))
                if kind == "sum":
                    x = builder.fadd(x, y)
                else:
                    x = builder.select(builder.fcmp_ordered(">" if kind == "max" else "<", x, y), x, y)
            return builder.extract_element(x, ir.Constant(_I32, 0))

        return types.float32(v), codegen

    fn.__doc__ = doc
    return fn


vsum = _reduce("sum", "The sum of the 8 lanes (a fixed pairwise order).")


@intrinsic
def vsum2(typingctx, a, b):
    """``(vsum(a), vsum(b))`` with shared shuffles (each the sum of its 8 lanes, a fixed pairwise order)."""
    if a != f32x8 or b != f32x8:
        return None

    def codegen(context, builder, sig, args):
        a, b = args
        lo = builder.shuffle_vector(a, b, ir.Constant(_VI, [0, 1, 2, 3, 8, 9, 10, 11]))
        hi = builder.shuffle_vector(a, b, ir.Constant(_VI, [4, 5, 6, 7, 12, 13, 14, 15]))
        x = builder.fadd(lo, hi)  # lanes 0-3: a's half sums, 4-7: b's
        undef = ir.Constant(_V, ir.Undefined)
        for half in (2, 1):
            y = builder.shuffle_vector(x, undef, ir.Constant(_VI, [(j // 4) * 4 + (j + half) % 4 for j in range(LANES)]))
            x = builder.fadd(x, y)
        ra = builder.extract_element(x, ir.Constant(_I32, 0))
        rb = builder.extract_element(x, ir.Constant(_I32, 4))
        return context.make_tuple(builder, sig.return_type, [ra, rb])

    return types.UniTuple(types.float32, 2)(a, b), codegen
vhmax = _reduce("max", "The largest of the 8 lanes.")
vhmin = _reduce("min", "The smallest of the 8 lanes.")


@intrinsic
def vsumv(typingctx, v):
    """The sum of the 8 lanes, in every lane: a butterfly (lane ``j`` adds lane ``j ^ 4``, then ``j ^ 2``, then
    ``j ^ 1``), the pairwise order of :func:`vsum`, so every lane holds exactly :func:`vsum`'s value, with no
    extraction and broadcast on the way."""
    if v != f32x8:
        return None

    def codegen(context, builder, sig, args):
        x = args[0]
        undef = ir.Constant(_V, ir.Undefined)
        for bit in (4, 2, 1):
            x = builder.fadd(x, builder.shuffle_vector(x, undef, ir.Constant(_VI, [j ^ bit for j in range(LANES)])))
        return x

    return f32x8(v), codegen


@intrinsic
def vfirst(typingctx, v):
    """Lane 0 of ``v``, a float32."""
    if v != f32x8:
        return None

    def codegen(context, builder, sig, args):
        return builder.extract_element(args[0], ir.Constant(_I32, 0))

    return types.float32(v), codegen


@intrinsic
def vhmax8(typingctx, v0, v1, v2, v3, v4, v5, v6, v7):
    """The vector whose lane ``i`` is ``vhmax(v_i)``, eight lane maxima at once: three levels of two-input shuffles
    (14 in all) and 7 maxima, against 8 x 3 shuffle-and-max steps one vector at a time. Each comparison is
    :func:`vhmax`'s, in its order (lane ``j`` against ``j + 4``, then ``+ 2``, then ``+ 1``), so the result is
    the same, NaN included."""
    vs = (v0, v1, v2, v3, v4, v5, v6, v7)
    if not all(v == f32x8 for v in vs):
        return None

    def codegen(context, builder, sig, args):
        # (vector, which input each lane's group belongs to); ``width``: lanes per group, each one input's
        cur = [(x, [i] * LANES) for i, x in enumerate(args)]
        width = LANES
        while len(cur) > 1:
            half = width // 2
            nxt = []
            for (a, ta), (b, tb) in zip(cur[0::2], cur[1::2]):
                lo, hi, tags = [], [], []
                for tag, off in ((ta, 0), (tb, LANES)):
                    for g in range(0, LANES, width):
                        lo += [off + g + j for j in range(half)]  # the low half of each group
                        hi += [off + g + half + j for j in range(half)]  # and its high half
                        tags += [tag[g]] * half
                x = builder.shuffle_vector(a, b, ir.Constant(_VI, lo))
                y = builder.shuffle_vector(a, b, ir.Constant(_VI, hi))
                nxt.append((builder.select(builder.fcmp_ordered(">", x, y), x, y), tags))
            cur, width = nxt, half
        out, tags = cur[0]
        order = [tags.index(i) for i in range(LANES)]
        return builder.shuffle_vector(out, ir.Constant(_V, ir.Undefined), ir.Constant(_VI, order))

    return f32x8(*vs), codegen

# exp on [-ln2/2, ln2/2]: minimax polynomial of degree 6 for the relative error (2e-9 before float32 rounding)
_EXP_POLY = (1.0, 1.000000032194708, 0.49999994217020166, 0.16666431177443375, 0.04166799994767056,
             0.008374160681625022, 0.0013843777357477529)  # fmt: skip
_LOG2E = 1.4426950408889634
_LN2_HI = 0.693359375  # exact in float32 (Cephes' split of ln 2)
_LN2_LO = -2.12194440e-4
_EXP_MIN = -87.0  # exp(-87) = 1.6e-38, just above float32's smallest normal number
#: The constants of :func:`vexp`, in the order it reads them (see :data:`EXP_CONSTANTS`).
EXP_CONSTANTS = np.array([_EXP_MIN, _LOG2E, 0.5, -_LN2_HI, -_LN2_LO, 127.0, *_EXP_POLY[::-1]], np.float32)
_N_EXP = len(EXP_CONSTANTS)


@intrinsic
def exp_constants(typingctx, arr):
    """The constants of :func:`vexp`, each in every lane, from ``arr`` (:data:`EXP_CONSTANTS`, a 1-D float32 array).

    Read from memory at run time, once, before the loops (not compile-time constants): the compiler then keeps
    them in registers (or folds a reload into the instruction that uses it) instead of reloading each from the
    constant pool, with its address, at every use inside the loops.
    """
    if not _is_f32_array(arr):
        return None
    tup = types.UniTuple(f32x8, _N_EXP)

    def codegen(context, builder, sig, args):
        vals = []
        for j in range(_N_EXP):
            x = builder.load(_elem_ptr(context, builder, sig.args[0], args[0], ir.Constant(ir.IntType(64), j)))
            vals.append(_splat(builder, x))
        return context.make_tuple(builder, tup, vals)

    return tup(arr), codegen


@intrinsic
def vexp(typingctx, x, c):
    """Lane-wise ``exp(x)`` for ``x <= 0`` (about 1 ulp); exactly 0 below -87, ``-inf`` included. ``c``: the
    constants of :func:`exp_constants`."""
    if x != f32x8 or c != types.UniTuple(f32x8, _N_EXP):
        return None

    def codegen(context, builder, sig, args):
        x, ctup = args
        lo, log2e, half, ln2_hi, ln2_lo, bias, *poly = cgutils.unpack_tuple(builder, ctup, _N_EXP)

        def fma(a, b, c):
            return _call(builder, "llvm.fma.v8f32", _V, [a, b, c])

        ok = builder.fcmp_ordered(">=", x, lo)
        xc = builder.select(ok, x, lo)
        k = _call(builder, "llvm.floor.v8f32", _V, [fma(xc, log2e, half)])
        r = fma(k, ln2_hi, xc)
        r = fma(k, ln2_lo, r)
        p = poly[0]
        for q in poly[1:]:
            p = fma(p, r, q)
        # 2^k from the exponent bits: k + 127 is exact in float32 (k is an integer in [-126, 0])
        bits = builder.shl(builder.fptosi(builder.fadd(k, bias), _VI), ir.Constant(_VI, [23] * LANES))
        y = builder.fmul(p, builder.bitcast(bits, _V))
        return builder.select(ok, y, ir.Constant(_V, [0.0] * LANES))

    return f32x8(x, c), codegen
