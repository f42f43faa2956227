"""Four-lane float64 SIMD for numba kernels: LLVM vector intrinsics with IEEE arithmetic.

What: a numba type for ``<4 x double>`` and ``@intrinsic`` operations on it: loads, stores
and 4 x 4 transposing gathers / scatters at flat indices of C-contiguous arrays (``vload``,
``vstore``, ``vcols``, ``vscatter4``, ...), ``vadd`` / ``vsub`` / ``vmul`` / ``vdiv`` /
``vsqrt``, an exact division by an integer without the divider (``vdivn``), a select, the
steady vertical step of the window-sum streams (``vstep``), a statistic / mask store and a
prefetch. Used by the fused kernel of :mod:`sarship.pipeline.detectors.two_parameter`.

Why: LLVM does not vectorise the van Herk scans (chains of dependent additions it may not
reassociate); running four rows, or four columns, in the lanes of one vector does. Each
lane does exactly the scalar operations (no fast-math flags, no contraction; ``vdivn``'s
FMAs give the correctly rounded quotient), so results are bit-identical to scalar code on
any CPU.

CPUs: numba compiles for the host; a vector is one AVX register, or two SSE2 / NEON
registers where there is no AVX; ``llvm.fma`` is the FMA instruction where the CPU has one,
else a call to libm's ``fma`` (same bits, slower). Where the intrinsics fail to compile
(another numba / llvmlite release), ``two_parameter.detect`` falls back to its plain
``detect_reference``.

Tests: tests/pipeline/test_two_parameter_kernel.py (the kernel bit for bit against numpy, ``vdivn``
against IEEE division). A ``cache=True`` kernel that uses these intrinsics must key its
cache on :func:`source_stamp` of this module (numba watches only the kernel's own file).
"""

from __future__ import annotations

import hashlib
from pathlib import Path

from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic, models, register_model


def source_stamp(*modules) -> str:
    """A hash of the source files of ``modules``: a closure variable of a cached numba kernel
    that compiles their code in (closure variables are part of numba's cache key)."""
    h = hashlib.sha256()
    for mod in modules:
        h.update(Path(mod.__file__).read_bytes())
    return h.hexdigest()


class _Vec4Type(types.Type):
    """Four float64 in an LLVM vector (one SIMD register with AVX)."""

    def __init__(self):
        super().__init__(name="Vec4f64")


_vec4 = _Vec4Type()
_V4 = ir.VectorType(ir.DoubleType(), 4)
_I32 = ir.IntType(32)


@register_model(_Vec4Type)
class _Vec4Model(models.PrimitiveModel):
    def __init__(self, dmm, fe_type):
        super().__init__(dmm, fe_type, _V4)


# The intrinsics below address C-contiguous arrays (any number of dimensions) by flat
# element index, unchecked. Array views are avoided in the hot code on purpose: each view
# costs two atomic reference-count operations.


def _is_c(a, dtype=types.float64):
    return isinstance(a, types.Array) and a.layout == "C" and a.dtype == dtype


def _ptr(context, builder, aty, arr, idx, vty=None):
    """Address of element ``idx`` of ``arr``, as a pointer to ``vty`` (default: element)."""
    p = builder.gep(context.make_array(aty)(context, builder, arr).data, [idx])
    return p if vty is None else builder.bitcast(p, vty.as_pointer())


def _mask(*xs):
    return ir.Constant(ir.VectorType(_I32, len(xs)), list(xs))


def _transpose(builder, va, vb, vc, vd):
    """4 x 4 transpose: lane k of the outputs comes from input k."""
    t0 = builder.shuffle_vector(va, vb, _mask(0, 4, 2, 6))  # a0 b0 a2 b2
    t1 = builder.shuffle_vector(va, vb, _mask(1, 5, 3, 7))  # a1 b1 a3 b3
    t2 = builder.shuffle_vector(vc, vd, _mask(0, 4, 2, 6))  # c0 d0 c2 d2
    t3 = builder.shuffle_vector(vc, vd, _mask(1, 5, 3, 7))  # c1 d1 c3 d3
    return (
        builder.shuffle_vector(t0, t2, _mask(0, 1, 4, 5)),  # a0 b0 c0 d0
        builder.shuffle_vector(t1, t3, _mask(0, 1, 4, 5)),  # a1 b1 c1 d1
        builder.shuffle_vector(t0, t2, _mask(2, 3, 6, 7)),  # a2 b2 c2 d2
        builder.shuffle_vector(t1, t3, _mask(2, 3, 6, 7)),
    )  # a3 b3 c3 d3


@intrinsic
def vload(typingctx, a, k):
    """a.flat[k: k + 4]."""
    if not _is_c(a):
        return None

    def codegen(context, builder, sig, args):
        return builder.load(_ptr(context, builder, sig.args[0], args[0], args[1], _V4), align=8)

    return _vec4(a, k), codegen


@intrinsic
def vstore(typingctx, a, k, v):
    """a.flat[k: k + 4] = v."""
    if not _is_c(a):
        return None

    def codegen(context, builder, sig, args):
        builder.store(args[2], _ptr(context, builder, sig.args[0], args[0], args[1], _V4), align=8)
        return context.get_dummy_value()

    return types.none(a, k, v), codegen


@intrinsic
def vstep(typingctx, h, ka, kb, pre, kp):
    """Steady vertical step: pre.flat[kp: kp+4] += h.flat[kb: kb+4]; returns
    h.flat[ka: ka+4] + pre.flat[kp: kp+4]."""
    if not (_is_c(h) and _is_c(pre)):
        return None

    def codegen(context, builder, sig, args):
        h, ka, kb, pre, kp = args
        pp = _ptr(context, builder, sig.args[3], pre, kp, _V4)
        p = builder.fadd(
            builder.load(pp, align=8), builder.load(_ptr(context, builder, sig.args[0], h, kb, _V4), align=8)
        )
        builder.store(p, pp, align=8)
        ha = builder.load(_ptr(context, builder, sig.args[0], h, ka, _V4), align=8)
        return builder.fadd(ha, p)

    return _vec4(h, ka, kb, pre, kp), codegen


@intrinsic
def prefetch(typingctx, a, r, c):
    """Prefetch the cache line holding a[r, c] (any 2-D array) for reading."""
    if not (isinstance(a, types.Array) and a.ndim == 2):
        return None

    def codegen(context, builder, sig, args):
        ary = context.make_array(sig.args[0])(context, builder, args[0])
        p = cgutils.get_item_pointer(context, builder, sig.args[0], ary, [args[1], args[2]])
        i8p = ir.IntType(8).as_pointer()
        fty = ir.FunctionType(ir.VoidType(), [i8p, _I32, _I32, _I32])
        fn = cgutils.get_or_insert_function(builder.module, fty, "llvm.prefetch.p0i8")
        builder.call(fn, [builder.bitcast(p, i8p), ir.Constant(_I32, 0), ir.Constant(_I32, 3), ir.Constant(_I32, 1)])
        return context.get_dummy_value()

    return types.none(a, types.intp, types.intp), codegen


def _vbinop(op):
    @intrinsic
    def f(typingctx, a, b):
        def codegen(context, builder, sig, args):
            return getattr(builder, op)(args[0], args[1])

        return _vec4(a, b), codegen

    return f


vadd = _vbinop("fadd")
vsub = _vbinop("fsub")
vmul = _vbinop("fmul")
vdiv = _vbinop("fdiv")


@intrinsic
def vsqrt(typingctx, a):
    def codegen(context, builder, sig, args):
        fn = cgutils.get_or_insert_function(builder.module, ir.FunctionType(_V4, [_V4]), "llvm.sqrt.v4f64")
        return builder.call(fn, [args[0]])

    return _vec4(a), codegen


@intrinsic
def vdivn(typingctx, a, n, y):
    """a / n, correctly rounded, for n a positive integer below 2**21 and y = 1.0 / n.

    Markstein's correction, two FMAs instead of the divider (the divider, also needed by
    the square root and the last division, bounds the decision loop). q0 = RN(a y) is
    within about 2 ulp of a / n; r = a - n q0 is then exact (a multiple of ulp(a / n) / 4,
    fewer than 2**25 times it); q0 + r y = a / n - (1 - n y)(a / n - q0) differs from
    a / n by less than 2**-104 |a / n|, and the FMA rounds it once. A rounding boundary (a
    midpoint between doubles) is never within 2**-76 |a / n| of a / n: n * midpoint - a
    is a multiple of ulp(a / n) / 4, and not zero, since a midpoint has a 54-bit odd
    significand and n * midpoint would not fit in 53 bits. So RN(q0 + r y) = RN(a / n).
    This needs normal numbers throughout: a vector with any |a| outside [2**-900, 2**1000]
    (zeros, subnormals, huge values, inf, NaN) goes through the divider instead.
    """

    def codegen(context, builder, sig, args):
        a, n, y = args
        v3 = ir.FunctionType(_V4, [_V4] * 3)
        fma = cgutils.get_or_insert_function(builder.module, v3, "llvm.fma.v4f64")
        fabs = cgutils.get_or_insert_function(builder.module, ir.FunctionType(_V4, [_V4]), "llvm.fabs.v4f64")
        q0 = builder.fmul(a, y)
        r = builder.call(fma, [builder.fneg(q0), n, a])
        q1 = builder.call(fma, [r, y, q0])
        fa = builder.call(fabs, [a])
        ok = builder.and_(
            builder.fcmp_ordered(">=", fa, ir.Constant(_V4, [2.0**-900] * 4)),
            builder.fcmp_ordered("<=", fa, ir.Constant(_V4, [2.0**1000] * 4)),
        )
        i4 = ir.IntType(4)
        all_ok = builder.icmp_unsigned("==", builder.bitcast(ok, i4), ir.Constant(i4, 15))
        with builder.if_else(all_ok, likely=True) as (fast, slow):
            with fast:
                b_fast = builder.basic_block
            with slow:
                qd = builder.fdiv(a, n)
                b_slow = builder.basic_block
        q = builder.phi(_V4)
        q.add_incoming(q1, b_fast)
        q.add_incoming(qd, b_slow)
        return q

    return _vec4(a, n, y), codegen


@intrinsic
def vsplat(typingctx, x):
    """(x, x, x, x)."""

    def codegen(context, builder, sig, args):
        v = builder.insert_element(ir.Constant(_V4, ir.Undefined), args[0], ir.Constant(_I32, 0))
        return builder.shuffle_vector(v, v, _mask(0, 0, 0, 0))

    return _vec4(types.float64), codegen


@intrinsic
def vsel_gt(typingctx, a, b, x, y):
    """x where a > b (ordered: false for NaN) else y, lane by lane."""

    def codegen(context, builder, sig, args):
        return builder.select(builder.fcmp_ordered(">", args[0], args[1]), args[2], args[3])

    return _vec4(a, b, x, y), codegen


@intrinsic
def vstore_stat(typingctx, stat, mask, k, s, thr):
    """stat.flat[k: k+4] = float32(s); mask.flat[k: k+4] = s > thr."""
    if not (_is_c(stat, types.float32) and _is_c(mask, types.boolean)):
        return None

    def codegen(context, builder, sig, args):
        st, mk, k, s, thr = args
        f4 = ir.VectorType(ir.FloatType(), 4)
        builder.store(builder.fptrunc(s, f4), _ptr(context, builder, sig.args[0], st, k, f4), align=4)
        b4 = ir.VectorType(ir.IntType(8), 4)
        gt = builder.zext(builder.fcmp_ordered(">", s, thr), b4)
        builder.store(gt, _ptr(context, builder, sig.args[1], mk, k, b4), align=1)
        return context.get_dummy_value()

    return types.none(stat, mask, k, s, thr), codegen


@intrinsic
def vcol(typingctx, y, o0, o1, o2, o3, c):
    """(y.flat[o0 + c], y.flat[o1 + c], y.flat[o2 + c], y.flat[o3 + c])."""
    if not _is_c(y):
        return None

    def codegen(context, builder, sig, args):
        v = ir.Constant(_V4, ir.Undefined)
        for k in range(4):
            x = builder.load(_ptr(context, builder, sig.args[0], args[0], builder.add(args[1 + k], args[5])))
            v = builder.insert_element(v, x, ir.Constant(_I32, k))
        return v

    return _vec4(y, o0, o1, o2, o3, c), codegen


@intrinsic
def vcols(typingctx, y, o0, o1, o2, o3, c):
    """Columns c .. c+3 of the rows starting at y.flat[o0], .., y.flat[o3], as four vectors
    (lanes: rows)."""
    if not _is_c(y):
        return None

    def codegen(context, builder, sig, args):
        rows = [
            builder.load(_ptr(context, builder, sig.args[0], args[0], builder.add(args[1 + k], args[5]), _V4), align=8)
            for k in range(4)
        ]
        return context.make_tuple(builder, sig.return_type, _transpose(builder, *rows))

    return types.UniTuple(_vec4, 4)(y, o0, o1, o2, o3, c), codegen


@intrinsic
def vscatter(typingctx, h, o0, o1, o2, o3, c, v):
    """h.flat[o_k + c] = v[k]."""
    if not _is_c(h):
        return None

    def codegen(context, builder, sig, args):
        for k in range(4):
            builder.store(
                builder.extract_element(args[6], ir.Constant(_I32, k)),
                _ptr(context, builder, sig.args[0], args[0], builder.add(args[1 + k], args[5])),
            )
        return context.get_dummy_value()

    return types.none(h, o0, o1, o2, o3, c, v), codegen


@intrinsic
def vscatter4(typingctx, h, o0, o1, o2, o3, c, a, b, cc, d):
    """Four columns c .. c+3 (vectors a, b, cc, d; lanes: rows) stored in the rows starting
    at h.flat[o0], .., h.flat[o3]."""
    if not _is_c(h):
        return None

    def codegen(context, builder, sig, args):
        for k, r in enumerate(_transpose(builder, *args[6:10])):
            builder.store(
                r, _ptr(context, builder, sig.args[0], args[0], builder.add(args[1 + k], args[5]), _V4), align=8
            )
        return context.get_dummy_value()

    return types.none(h, o0, o1, o2, o3, c, a, b, cc, d), codegen
