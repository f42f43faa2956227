"""Two-parameter (Gaussian) CFAR (``two_parameter``), with the exact small-sample threshold.

The classical detector (Novak & Hesse 1991; ESA SNAP's "Adaptive Thresholding"): estimate
the clutter mean mu and standard deviation sigma from the N cells of the background ring
and declare a target where the tested value exceeds ``mu + t sigma``, with t from the PFA
under a Gaussian model, t = Phi^{-1}(1 - PFA).

Target-window version. When the tested value is the mean of the n = target^2 cells of the
target window, its standard deviation is sigma / sqrt(n): the rule must be
``x_t > mu + t sigma / sqrt(n)`` (the t/sqrt(n) correction SNAP never applied, so its
target-window PFA is far below the one asked for).

Exact threshold (``threshold="student"``, default). mu and sigma are estimates from N
samples: for Gaussian clutter, (x_t - mu_hat) / (sigma_hat * sqrt(1/n + 1/N)) follows
Student's t with N - 1 degrees of freedom, exactly (independent CUT and ring). So the
detection rule (x_t - mu_hat)/sigma_hat > t_N with t_N = sqrt(1/n + 1/N) * t_{N-1}^{-1}(1 -
PFA) has exactly the PFA asked for. ``threshold="gaussian"`` gives the classical
t = Phi^{-1}(1 - PFA) / sqrt(n), exact only as N -> infinity.

``domain`` picks the quantity the Gaussian model is applied to: ``intensity`` (as SNAP),
``amplitude`` (sqrt) or ``db`` (10 log10, where speckle is closest to Gaussian). In ``db``
non-positive values are floored at 1e-30 (-300 dB), a fixed floor so that tiles agree;
data with exact zeros (8-bit quantised JPEG chips, no-data borders) then carry -300 dB
outliers into the ring statistics: use ``intensity`` or ``amplitude`` for such data.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from llvmlite import ir
from numba import njit, objmode, types, uint64
from numba.core import cgutils
from numba.extending import intrinsic, models, register_model
from pydantic import Field
from scipy import stats

from sarship.pipeline.detectors.base import DetectorParams, DetectorSpec, check_windows, with_defaults
from sarship.pipeline.gpu import is_device_array


class TwoParameterParams(with_defaults(DetectorParams, "TwoParameterDefaults", pfa=1e-3, guard=21,
                                       background=41, min_area_px=15, merge_px=0)):
    """Parameters of ``two_parameter``.

    Defaults chosen on real data (SAR-Ship-Dataset, HRSID, OpenSARShip; bench/REALDATA.md).
    """

    threshold: Literal["student", "gaussian"] = Field(
        "student", description="exact Student-t threshold for N ring samples, or the classical Gaussian one"
    )
    domain: Literal["intensity", "amplitude", "db"] = Field(
        "intensity", description="quantity modelled as Gaussian"
    )


def threshold(pfa: float, n_ring: int, n_target: int, kind: str = "student") -> float:
    """Threshold on (x_t - mu_hat) / sigma_hat for the given PFA."""
    if kind == "student":
        return float(np.sqrt(1.0 / n_target + 1.0 / n_ring) * stats.t.isf(pfa, n_ring - 1))
    return float(stats.norm.isf(pfa) / np.sqrt(n_target))


def prepare(p: TwoParameterParams) -> dict:
    n_t = p.target**2
    return {
        "n_ring": p.n_ring,
        "n_target": n_t,
        "threshold": threshold(p.pfa, p.n_ring, n_t, p.threshold),
        "statistic": "(target mean - ring mean) / ring std",
        "domain": p.domain,
    }


# ---------------------------------------------------------------------------------------
# Fused streaming kernel.
# ---------------------------------------------------------------------------------------
#
# Bit for bit the former implementation (transform to float64 y, y * y, four or five calls
# of ``boxsum.centered_box_sum``, then the decision; ``tests/test_two_parameter_kernel.py``
# states it in numpy): the same float64 values enter the same additions in the same order
# (``boxsum`` docstring), streamed like ``ca_cfar``: output rows are produced one at a time
# and the horizontal sums of the input rows just ahead, into small rings that stay in L2,
# so no full-size float64 intermediate is written. Per column strip:
#
# * Each input row is transformed once (``_transform_row``), into a ring of rows ``Y``.
#   The logarithm of ``db`` is numpy's (numba's differs in the last bit): it is taken by
#   ``np.log10`` on bands of DB_BAND rows (``_db_band``), in cache.
# * Horizontal pass (``_hpair4``): four rows at a time, one row per SIMD lane (the scans
#   along a row are chains of dependent additions; rows are the parallel dimension), y and
#   y * y together; 4 x 4 transposes move data between rows and lanes. Each lane performs
#   exactly the additions of ``boxsum._hsum1``.
# * Vertical pass and decision fused (``_decide_row``), four columns per vector: in a steady
#   row the running prefix of the next row block is updated and added to the suffix row,
#   for the four sums, and the statistic is formed at once; rows that open a row block or
#   start a prefix (a few per block) are formed first by ``_vprep``. The divisions by the
#   integers N, N - 1 and target**2 use ``_vdivn`` (exact, without the divider).
#
# The vector operations are LLVM IR vectors (the ``_v*`` intrinsics below): IEEE fadd, fmul,
# fdiv and sqrt, no fast-math flags, no contraction, so each lane rounds as scalar code
# would. The hot functions take whole arrays and flat indices and are compiled without the
# NRT (``_nrt=False``): array views and reference counting (atomic operations) in the
# inner loops cost more than the arithmetic.

#: Most output columns per strip: the rings (background and guard, y and y*y) stay in L2.
STRIP = 768

_MODE = {"intensity": 0, "amplitude": 1, "db": 2}

# stream state: current row-block start, whether the running prefix is started, first block start
_ST_BLOCK = 0
_ST_PRE = 1
_ST_BASE = 2


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
    return (builder.shuffle_vector(t0, t2, _mask(0, 1, 4, 5)),  # a0 b0 c0 d0
            builder.shuffle_vector(t1, t3, _mask(0, 1, 4, 5)),  # a1 b1 c1 d1
            builder.shuffle_vector(t0, t2, _mask(2, 3, 6, 7)),  # a2 b2 c2 d2
            builder.shuffle_vector(t1, t3, _mask(2, 3, 6, 7)))  # a3 b3 c3 d3


@intrinsic
def _vload(typingctx, a, k):
    """a.flat[k: k + 4]."""
    if not _is_c(a):
        return None

    def codegen(context, builder, sig, args):
        return builder.load(_ptr(context, builder, sig.args[0], args[0], args[1], _V4), align=8)

    return _vec4(a, k), codegen


@intrinsic
def _vstore(typingctx, a, k, v):
    """a.flat[k: k + 4] = v."""
    if not _is_c(a):
        return None

    def codegen(context, builder, sig, args):
        builder.store(args[2], _ptr(context, builder, sig.args[0], args[0], args[1], _V4), align=8)
        return context.get_dummy_value()

    return types.none(a, k, v), codegen


@intrinsic
def _vstep(typingctx, h, ka, kb, pre, kp):
    """Steady vertical step: pre.flat[kp: kp+4] += h.flat[kb: kb+4]; returns
    h.flat[ka: ka+4] + pre.flat[kp: kp+4]."""
    if not (_is_c(h) and _is_c(pre)):
        return None

    def codegen(context, builder, sig, args):
        h, ka, kb, pre, kp = args
        pp = _ptr(context, builder, sig.args[3], pre, kp, _V4)
        p = builder.fadd(builder.load(pp, align=8),
                         builder.load(_ptr(context, builder, sig.args[0], h, kb, _V4), align=8))
        builder.store(p, pp, align=8)
        ha = builder.load(_ptr(context, builder, sig.args[0], h, ka, _V4), align=8)
        return builder.fadd(ha, p)

    return _vec4(h, ka, kb, pre, kp), codegen


@intrinsic
def _prefetch(typingctx, a, r, c):
    """Prefetch the cache line holding a[r, c] (any 2-D array) for reading."""
    if not (isinstance(a, types.Array) and a.ndim == 2):
        return None

    def codegen(context, builder, sig, args):
        ary = context.make_array(sig.args[0])(context, builder, args[0])
        p = cgutils.get_item_pointer(context, builder, sig.args[0], ary, [args[1], args[2]])
        i8p = ir.IntType(8).as_pointer()
        fty = ir.FunctionType(ir.VoidType(), [i8p, _I32, _I32, _I32])
        fn = cgutils.get_or_insert_function(builder.module, fty, "llvm.prefetch.p0i8")
        builder.call(fn, [builder.bitcast(p, i8p), ir.Constant(_I32, 0), ir.Constant(_I32, 3),
                          ir.Constant(_I32, 1)])
        return context.get_dummy_value()

    return types.none(a, types.intp, types.intp), codegen


def _vbinop(op):
    @intrinsic
    def f(typingctx, a, b):
        def codegen(context, builder, sig, args):
            return getattr(builder, op)(args[0], args[1])

        return _vec4(a, b), codegen

    return f


_vadd = _vbinop("fadd")
_vsub = _vbinop("fsub")
_vmul = _vbinop("fmul")
_vdiv = _vbinop("fdiv")


@intrinsic
def _vsqrt(typingctx, a):
    def codegen(context, builder, sig, args):
        fn = cgutils.get_or_insert_function(builder.module, ir.FunctionType(_V4, [_V4]),
                                            "llvm.sqrt.v4f64")
        return builder.call(fn, [args[0]])

    return _vec4(a), codegen


@intrinsic
def _vdivn(typingctx, a, n, y):
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
        fabs = cgutils.get_or_insert_function(builder.module, ir.FunctionType(_V4, [_V4]),
                                              "llvm.fabs.v4f64")
        q0 = builder.fmul(a, y)
        r = builder.call(fma, [builder.fneg(q0), n, a])
        q1 = builder.call(fma, [r, y, q0])
        fa = builder.call(fabs, [a])
        ok = builder.and_(builder.fcmp_ordered(">=", fa, ir.Constant(_V4, [2.0 ** -900] * 4)),
                          builder.fcmp_ordered("<=", fa, ir.Constant(_V4, [2.0 ** 1000] * 4)))
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
def _vsplat(typingctx, x):
    """(x, x, x, x)."""
    def codegen(context, builder, sig, args):
        v = builder.insert_element(ir.Constant(_V4, ir.Undefined), args[0], ir.Constant(_I32, 0))
        return builder.shuffle_vector(v, v, _mask(0, 0, 0, 0))

    return _vec4(types.float64), codegen


@intrinsic
def _vsel_gt(typingctx, a, b, x, y):
    """x where a > b (ordered: false for NaN) else y, lane by lane."""
    def codegen(context, builder, sig, args):
        return builder.select(builder.fcmp_ordered(">", args[0], args[1]), args[2], args[3])

    return _vec4(a, b, x, y), codegen


@intrinsic
def _vstore_stat(typingctx, stat, mask, k, s, thr):
    """stat.flat[k: k+4] = float32(s); mask.flat[k: k+4] = s > thr."""
    if not (_is_c(stat, types.float32) and _is_c(mask, types.boolean)):
        return None

    def codegen(context, builder, sig, args):
        st, mk, k, s, thr = args
        f4 = ir.VectorType(ir.FloatType(), 4)
        builder.store(builder.fptrunc(s, f4), _ptr(context, builder, sig.args[0], st, k, f4),
                      align=4)
        b4 = ir.VectorType(ir.IntType(8), 4)
        gt = builder.zext(builder.fcmp_ordered(">", s, thr), b4)
        builder.store(gt, _ptr(context, builder, sig.args[1], mk, k, b4), align=1)
        return context.get_dummy_value()

    return types.none(stat, mask, k, s, thr), codegen


@intrinsic
def _vcol(typingctx, y, o0, o1, o2, o3, c):
    """(y.flat[o0 + c], y.flat[o1 + c], y.flat[o2 + c], y.flat[o3 + c])."""
    if not _is_c(y):
        return None

    def codegen(context, builder, sig, args):
        v = ir.Constant(_V4, ir.Undefined)
        for k in range(4):
            x = builder.load(_ptr(context, builder, sig.args[0], args[0],
                                  builder.add(args[1 + k], args[5])))
            v = builder.insert_element(v, x, ir.Constant(_I32, k))
        return v

    return _vec4(y, o0, o1, o2, o3, c), codegen


@intrinsic
def _vcols(typingctx, y, o0, o1, o2, o3, c):
    """Columns c .. c+3 of the rows starting at y.flat[o0], .., y.flat[o3], as four vectors
    (lanes: rows)."""
    if not _is_c(y):
        return None

    def codegen(context, builder, sig, args):
        rows = [builder.load(_ptr(context, builder, sig.args[0], args[0],
                                  builder.add(args[1 + k], args[5]), _V4), align=8)
                for k in range(4)]
        return context.make_tuple(builder, sig.return_type, _transpose(builder, *rows))

    return types.UniTuple(_vec4, 4)(y, o0, o1, o2, o3, c), codegen


@intrinsic
def _vscatter(typingctx, h, o0, o1, o2, o3, c, v):
    """h.flat[o_k + c] = v[k]."""
    if not _is_c(h):
        return None

    def codegen(context, builder, sig, args):
        for k in range(4):
            builder.store(builder.extract_element(args[6], ir.Constant(_I32, k)),
                          _ptr(context, builder, sig.args[0], args[0],
                               builder.add(args[1 + k], args[5])))
        return context.get_dummy_value()

    return types.none(h, o0, o1, o2, o3, c, v), codegen


@intrinsic
def _vscatter4(typingctx, h, o0, o1, o2, o3, c, a, b, cc, d):
    """Four columns c .. c+3 (vectors a, b, cc, d; lanes: rows) stored in the rows starting
    at h.flat[o0], .., h.flat[o3]."""
    if not _is_c(h):
        return None

    def codegen(context, builder, sig, args):
        for k, r in enumerate(_transpose(builder, *args[6:10])):
            builder.store(r, _ptr(context, builder, sig.args[0], args[0],
                                  builder.add(args[1 + k], args[5]), _V4), align=8)
        return context.get_dummy_value()

    return types.none(h, o0, o1, o2, o3, c, a, b, cc, d), codegen


#: Rows of the ``db`` domain's logarithm computed at a time (in cache, by numpy).
DB_BAND = 64


@njit(cache=True)
def _log10_inplace(L, n):
    """L[:n] = np.log10(L[:n]), by numpy itself.

    numba's ``log10`` (libm) and numpy's (SIMD) differ in the last bit for ~10 % of values:
    the ``db`` transform must be numpy's. An object-mode block (the GIL is taken for it)
    in a function of its own, without ``nogil``, which numba would warn about."""
    with objmode():
        np.log10(L[:n], out=L[:n])


@njit(nogil=True, cache=True)
def _db_band(src, r0, n, c0, L):
    """L[:n] = log10(max(src[r0: r0+n, c0: c0 + L.shape[1]] as float64, 1e-30)), as the
    former ``np.log10(np.maximum(x.astype(np.float64), 1e-30))`` (NaN propagated)."""
    w = L.shape[1]
    for r in range(n):
        for c in range(w):
            v = np.float64(src[uint64(r0 + r), uint64(c0 + c)])
            L[uint64(r), uint64(c)] = v if not (v <= 1e-30) else 1e-30
    _log10_inplace(L, n)


@njit(nogil=True, cache=True, _nrt=False)
def _transform_row(src, r, c0, n, mode, Y, slot):
    """Y[slot, :n] = y of src[r, c0: c0 + n]: as float64 (mode 0), sqrt(max(x, 0)) (1), or
    10 * src, src being the logarithm from ``_db_band`` (2) -- bit for bit the numpy
    transform."""
    if mode == 0:
        for c in range(n):
            Y[uint64(slot), uint64(c)] = np.float64(src[uint64(r), uint64(c0 + c)])
    elif mode == 1:
        for c in range(n):
            v = np.float64(src[uint64(r), uint64(c0 + c)])
            # np.maximum(x, 0.0): NaN kept, -0.0 -> +0.0
            Y[uint64(slot), uint64(c)] = np.sqrt(v if not (v <= 0.0) else 0.0)
    else:
        for c in range(n):
            Y[uint64(slot), uint64(c)] = 10.0 * src[uint64(r), uint64(c0 + c)]


@njit(nogil=True, cache=True, _nrt=False)
def _hpair4(Y, y0, y1, y2, y3, m, g0, n_out, H1, H2, o0, o1, o2, o3, su, sw):
    """Horizontal window sums of four rows of y (Y.flat[y_r + i], i = 0, 1, ..; the first
    is global column g0) and of y * y: H1.flat[o_r + i] = sum(y_r[i: i+m]) and H2.flat[o_r
    + i] = sum(y_r[i: i+m] ** 2), i < n_out. The additions of ``boxsum._hsum1`` in each SIMD
    lane (one lane per row). ``su``, ``sw``: scratch of 4 * m float64 (suffix sums)."""
    s = -(g0 % m)  # column of the first block start (<= 0)
    while s < n_out:
        i_lo = max(s, 0)
        i_hi = min(s + m, n_out)
        if i_lo < i_hi:
            e = s + m - 1  # block end: suffix sums from e down to i_lo
            a = _vsplat(0.0)
            b = _vsplat(0.0)
            c = e
            while c - 3 >= i_lo:
                v0, v1, v2, v3 = _vcols(Y, y0, y1, y2, y3, uint64(c - 3))
                ju = uint64(4 * (c - s))
                a = _vadd(a, v3)
                b = _vadd(b, _vmul(v3, v3))
                _vstore(su, ju, a)
                _vstore(sw, ju, b)
                a = _vadd(a, v2)
                b = _vadd(b, _vmul(v2, v2))
                _vstore(su, ju - 4, a)
                _vstore(sw, ju - 4, b)
                a = _vadd(a, v1)
                b = _vadd(b, _vmul(v1, v1))
                _vstore(su, ju - 8, a)
                _vstore(sw, ju - 8, b)
                a = _vadd(a, v0)
                b = _vadd(b, _vmul(v0, v0))
                _vstore(su, ju - 12, a)
                _vstore(sw, ju - 12, b)
                c -= 4
            while c >= i_lo:
                v = _vcol(Y, y0, y1, y2, y3, uint64(c))
                a = _vadd(a, v)
                b = _vadd(b, _vmul(v, v))
                ju = uint64(4 * (c - s))
                _vstore(su, ju, a)
                _vstore(sw, ju, b)
                c -= 1
            i0 = i_lo
            if i0 == s:  # the window starting the block is the whole block: suffix alone
                _vscatter(H1, o0, o1, o2, o3, uint64(i0), a)
                _vscatter(H2, o0, o1, o2, o3, uint64(i0), b)
                i0 += 1
            # prefix of the next block, up to column i0 + m - 2
            p = _vsplat(0.0)
            q = _vsplat(0.0)
            for c in range(s + m, i0 + m - 1):
                v = _vcol(Y, y0, y1, y2, y3, uint64(c))
                p = _vadd(p, v)
                q = _vadd(q, _vmul(v, v))
            i = i0
            while i + 4 <= i_hi:
                v0, v1, v2, v3 = _vcols(Y, y0, y1, y2, y3, uint64(i + m - 1))
                ju = uint64(4 * (i - s))
                p = _vadd(p, v0)
                q = _vadd(q, _vmul(v0, v0))
                ha = _vadd(_vload(su, ju), p)
                ka = _vadd(_vload(sw, ju), q)
                p = _vadd(p, v1)
                q = _vadd(q, _vmul(v1, v1))
                hb = _vadd(_vload(su, ju + 4), p)
                kb = _vadd(_vload(sw, ju + 4), q)
                p = _vadd(p, v2)
                q = _vadd(q, _vmul(v2, v2))
                hc = _vadd(_vload(su, ju + 8), p)
                kc = _vadd(_vload(sw, ju + 8), q)
                p = _vadd(p, v3)
                q = _vadd(q, _vmul(v3, v3))
                hd = _vadd(_vload(su, ju + 12), p)
                kd = _vadd(_vload(sw, ju + 12), q)
                _vscatter4(H1, o0, o1, o2, o3, uint64(i), ha, hb, hc, hd)
                _vscatter4(H2, o0, o1, o2, o3, uint64(i), ka, kb, kc, kd)
                i += 4
            while i < i_hi:
                v = _vcol(Y, y0, y1, y2, y3, uint64(i + m - 1))
                p = _vadd(p, v)
                q = _vadd(q, _vmul(v, v))
                ju = uint64(4 * (i - s))
                _vscatter(H1, o0, o1, o2, o3, uint64(i), _vadd(_vload(su, ju), p))
                _vscatter(H2, o0, o1, o2, o3, uint64(i), _vadd(_vload(sw, ju), q))
                i += 1
        s += m


@njit(nogil=True, cache=True, _nrt=False)
def _hsum4(Y, y0, y1, y2, y3, m, g0, n_out, H, o0, o1, o2, o3, su):
    """:func:`_hpair4` for y alone (the target window)."""
    s = -(g0 % m)
    while s < n_out:
        i_lo = max(s, 0)
        i_hi = min(s + m, n_out)
        if i_lo < i_hi:
            e = s + m - 1
            a = _vsplat(0.0)
            c = e
            while c - 3 >= i_lo:
                v0, v1, v2, v3 = _vcols(Y, y0, y1, y2, y3, uint64(c - 3))
                ju = uint64(4 * (c - s))
                a = _vadd(a, v3)
                _vstore(su, ju, a)
                a = _vadd(a, v2)
                _vstore(su, ju - 4, a)
                a = _vadd(a, v1)
                _vstore(su, ju - 8, a)
                a = _vadd(a, v0)
                _vstore(su, ju - 12, a)
                c -= 4
            while c >= i_lo:
                a = _vadd(a, _vcol(Y, y0, y1, y2, y3, uint64(c)))
                _vstore(su, uint64(4 * (c - s)), a)
                c -= 1
            i0 = i_lo
            if i0 == s:
                _vscatter(H, o0, o1, o2, o3, uint64(i0), a)
                i0 += 1
            p = _vsplat(0.0)
            for c in range(s + m, i0 + m - 1):
                p = _vadd(p, _vcol(Y, y0, y1, y2, y3, uint64(c)))
            i = i0
            while i + 4 <= i_hi:
                v0, v1, v2, v3 = _vcols(Y, y0, y1, y2, y3, uint64(i + m - 1))
                ju = uint64(4 * (i - s))
                p = _vadd(p, v0)
                ha = _vadd(_vload(su, ju), p)
                p = _vadd(p, v1)
                hb = _vadd(_vload(su, ju + 4), p)
                p = _vadd(p, v2)
                hc = _vadd(_vload(su, ju + 8), p)
                p = _vadd(p, v3)
                hd = _vadd(_vload(su, ju + 12), p)
                _vscatter4(H, o0, o1, o2, o3, uint64(i), ha, hb, hc, hd)
                i += 4
            while i < i_hi:
                p = _vadd(p, _vcol(Y, y0, y1, y2, y3, uint64(i + m - 1)))
                _vscatter(H, o0, o1, o2, o3, uint64(i), _vadd(_vload(su, uint64(4 * (i - s))), p))
                i += 1
        s += m


@njit(nogil=True, cache=True, _nrt=False)
def _hpair1(Y, yr, yc, m, g0, n_out, H1, H2, d, pair, su, sw):
    """One row of :func:`_hpair4` (``pair``) or :func:`_hsum4`, in scalar code (tile edges):
    y = Y[yr, yc:], into H1[d] and H2[d]."""
    s = -(g0 % m)
    while s < n_out:
        i_lo = max(s, 0)
        i_hi = min(s + m, n_out)
        if i_lo < i_hi:
            e = s + m - 1
            a0 = 0.0
            b0 = 0.0
            for c in range(e, i_lo - 1, -1):
                v0 = Y[yr, yc + c]
                a0 = a0 + v0
                b0 = b0 + v0 * v0
                su[c - s] = a0
                sw[c - s] = b0
            i0 = i_lo
            if i0 == s:
                H1[d, i0] = a0
                if pair:
                    H2[d, i0] = b0
                i0 += 1
            p0 = 0.0
            q0 = 0.0
            for c in range(s + m, i0 + m - 1):
                v0 = Y[yr, yc + c]
                p0 = p0 + v0
                q0 = q0 + v0 * v0
            for i in range(i0, i_hi):
                v0 = Y[yr, yc + i + m - 1]
                p0 = p0 + v0
                q0 = q0 + v0 * v0
                H1[d, i] = su[i - s] + p0
                if pair:
                    H2[d, i] = sw[i - s] + q0
        s += m


@njit(nogil=True, cache=True, _nrt=False)
def _fill(Y, ys, k, r0, col, m, g0, nrows, H1, H2, base, pair, su, sw):
    """Horizontal sums of the stream rows r0 .. r0 + k - 1 that lie in [0, nrows), whose
    values y are Y[ys[q], col:], q < k; into the rings H1 (y) and, if ``pair``, H2 (y * y):
    stream row r in slot (r - base) % len(H1)."""
    Rz, n_out = H1.shape
    ny = Y.shape[1]
    if k == 4 and r0 >= 0 and r0 + 4 <= nrows:
        o0 = (r0 - base) % Rz * n_out
        o1 = (r0 + 1 - base) % Rz * n_out
        o2 = (r0 + 2 - base) % Rz * n_out
        o3 = (r0 + 3 - base) % Rz * n_out
        y0 = ys[0] * ny + col
        y1 = ys[1] * ny + col
        y2 = ys[2] * ny + col
        y3 = ys[3] * ny + col
        if pair:
            _hpair4(Y, y0, y1, y2, y3, m, g0, n_out, H1, H2, o0, o1, o2, o3, su, sw)
        else:
            _hsum4(Y, y0, y1, y2, y3, m, g0, n_out, H1, o0, o1, o2, o3, su)
    else:
        for q in range(k):
            r = r0 + q
            if 0 <= r < nrows:
                _hpair1(Y, ys[q], col, m, g0, n_out, H1, H2, (r - base) % Rz, pair, su, sw)


@njit(nogil=True, cache=True, _nrt=False)
def _vprep(H, P, kp, st, m, i, D, kd):
    """Vertical pass of ``boxsum.box_stream_row`` for output row i, whose horizontal sums
    are in the ring H (stream row r in slot (r - base) % len(H)), except the steady case;
    P[kp] holds the running prefix of the next row block.

    Opens a row block when row i starts one (vertical suffix sums in place). Returns True
    when row i is steady (``pre += H[i + m - 1]``, ``sum = H[i] + pre``: left to the caller);
    otherwise writes the window sums of row i into D[kd] and returns False.
    """
    Rz, n = H.shape
    base = st[_ST_BASE]
    s = st[_ST_BLOCK]
    if i == 0 or i == s + m:  # output row i opens a block
        if i > 0:
            s += m
        st[_ST_BLOCK] = s
        st[_ST_PRE] = 0
        e = s + m - 1
        b = (e - base) % Rz
        for r in range(e - 1, i - 1, -1):
            a = (r - base) % Rz
            for c in range(n):
                H[a, c] = H[b, c] + H[a, c]
            b = a
        # prefix of the next block up to row i + m - 2 (only when a tile starts mid-block)
        for r in range(s + m, i + m - 1):
            a = (r - base) % Rz
            if st[_ST_PRE] == 0:
                st[_ST_PRE] = 1
                for c in range(n):
                    P[kp, c] = H[a, c]
            else:
                for c in range(n):
                    P[kp, c] = P[kp, c] + H[a, c]
    a = (i - base) % Rz
    if i == s:  # the window starting the block is the whole block: suffix alone
        for c in range(n):
            D[kd, c] = H[a, c]
        return False
    if st[_ST_PRE] == 1:
        return True
    st[_ST_PRE] = 1
    b = (i + m - 1 - base) % Rz
    for c in range(n):
        p = H[b, c]
        P[kp, c] = p
        D[kd, c] = H[a, c] + p
    return False


@njit(nogil=True, cache=True)
def _stream_state(m, g0r):
    st = np.empty(3, np.int64)
    s0 = -(g0r % m)
    st[_ST_BLOCK] = s0
    st[_ST_PRE] = 0
    st[_ST_BASE] = s0
    return st


@njit(nogil=True, cache=True, error_model="numpy", _nrt=False)
def _decide_row(w, steady_b, steady_g, Hb1, Hb2, ab, bb, Hg1, Hg2, ag, bg, P, D, X, xo, tt,
                n_ring, thr, mask, stat, i, c0, tmp_s, tmp_m, src, pf, pfc, pfn):
    """Window sums of output row i, columns c0 .. c0 + w - 1 (steady streams: from their
    rings, suffix row a and next-block row b, and running prefix P[0..3]; the others from
    D[0..3]), x_t = X.flat[xo + j] (divided by tt unless 1), and the decision, four columns
    at a time; columns past w (padding of the last vector) are not stored.

    Also prefetches src[pf, pfc: pfc + pfn] (an input row needed soon; pf < 0: none), a
    cache line every other vector: spread over this loop, the misses cost little."""
    n = Hb1.shape[1]
    nr = _vsplat(n_ring)
    nm1 = _vsplat(n_ring - 1.0)
    inr = _vsplat(1.0 / n_ring)
    inm1 = _vsplat(1.0 / (n_ring - 1.0))
    ttv = _vsplat(tt)
    itt = _vsplat(1.0 / tt)
    th = _vsplat(thr)
    zero = _vsplat(0.0)
    inf = _vsplat(np.inf)
    mo = i * mask.shape[1] + c0
    for j in range(0, w, 4):
        ju = uint64(j)
        if steady_b:
            s1b = _vstep(Hb1, ab * n + ju, bb * n + ju, P, ju)
            s2b = _vstep(Hb2, ab * n + ju, bb * n + ju, P, n + ju)
        else:
            s1b = _vload(D, ju)
            s2b = _vload(D, n + ju)
        if steady_g:
            s1g = _vstep(Hg1, ag * n + ju, bg * n + ju, P, 2 * n + ju)
            s2g = _vstep(Hg2, ag * n + ju, bg * n + ju, P, 3 * n + ju)
        else:
            s1g = _vload(D, 2 * n + ju)
            s2g = _vload(D, 3 * n + ju)
        if pf >= 0 and 2 * j < pfn:
            _prefetch(src, pf, pfc + 2 * j)
        x = _vload(X, xo + ju)
        if tt != 1.0:
            x = _vdivn(x, ttv, itt)
        s1 = _vsub(s1b, s1g)
        s2 = _vsub(s2b, s2g)
        mu = _vdivn(s1, nr, inr)
        var = _vdivn(_vsub(s2, _vmul(s1, mu)), nm1, inm1)
        d = _vsub(x, mu)
        q = _vdiv(d, _vsqrt(var))
        s = _vsel_gt(var, zero, q, _vsel_gt(d, zero, inf, zero))
        if j + 4 <= w:
            _vstore_stat(stat, mask, mo + ju, s, th)
        else:
            _vstore_stat(tmp_s, tmp_m, 0, s, th)
            for c in range(w - j):
                stat[i, c0 + j + c] = tmp_s[c]
                mask[i, c0 + j + c] = tmp_m[c]


@njit(nogil=True, cache=True)
def _detect_strip(src, mode, halo, g0r, g0c, target, guard, background, n_ring, thr, c0, c1,
                  mask, stat):
    """Columns [c0, c1) of the core: all window sums streamed row by row, and the decision."""
    h = mask.shape[0]
    w = c1 - c0
    wp = (w + 3) // 4 * 4  # streams run on whole vectors; the padding columns are dropped
    t, g, b = target, guard, background
    ob = halo - b // 2
    og = halo - g // 2
    ot = halo - t // 2
    win = w + b - 1  # columns of the transformed rows: those the background window needs
    xc = ob + c0
    # transformed rows, tile row r in slot (r - ob) % RY; held from their transform (up to
    # 3 rows past the background's need) until the target row halo + i is used
    RY = b // 2 + 8
    Y = np.zeros((RY + 1, wp + b - 1), np.float64)  # and a spare row: target window sums
    ny = Y.shape[1]
    ys = np.empty(4, np.int64)
    su = np.empty(4 * b, np.float64)
    sw = np.empty(4 * b, np.float64)
    # rings: filled up to 3 rows past the background's need, each window needs its rows
    # from the output row on: (m // 2 + b // 2 + 4) rows in flight
    Rb = 2 * (b // 2) + 5
    Rg = g // 2 + b // 2 + 5
    Rt = t // 2 + b // 2 + 5 if t > 1 else 1
    Hb1 = np.empty((Rb, wp), np.float64)
    Hb2 = np.empty((Rb, wp), np.float64)
    Hg1 = np.empty((Rg, wp), np.float64)
    Hg2 = np.empty((Rg, wp), np.float64)
    Ht = np.empty((Rt, wp), np.float64)
    P = np.empty((5, wp), np.float64)  # running prefixes: b y, b y*y, g y, g y*y, t y
    D = np.empty((4, wp), np.float64)  # window sums of rows that are not steady
    sb1 = _stream_state(b, g0r + ob)
    sb2 = _stream_state(b, g0r + ob)
    sg1 = _stream_state(g, g0r + og)
    sg2 = _stream_state(g, g0r + og)
    stt = _stream_state(t, g0r + ot)
    tmp_s = np.empty(4, np.float32)
    tmp_m = np.empty(4, np.bool_)
    tt = float(t * t)
    F = ob  # next tile row to transform
    f_end = ob + h + b - 1
    # db: log10 of the tile rows band0 .. band0 + DB_BAND - 1 (strip columns)
    L = np.empty((DB_BAND if mode == 2 else 0, win), np.float64)
    band0 = ob - DB_BAND
    for i in range(h):
        need = ob + i + b - 1
        while F <= need:
            k = min(4, f_end - F)
            for q in range(k):
                ys[q] = (F + q - ob) % RY
                if mode == 2:
                    if F + q >= band0 + DB_BAND:
                        band0 = F + q
                        _db_band(src, band0, min(DB_BAND, f_end - band0), xc, L)
                    _transform_row(L, F + q - band0, 0, win, mode, Y, ys[q])
                else:
                    _transform_row(src, F + q, xc, win, mode, Y, ys[q])
            _fill(Y, ys, k, F - ob, 0, b, g0c + ob + c0, h + b - 1, Hb1, Hb2, sb1[_ST_BASE],
                  True, su, sw)
            _fill(Y, ys, k, F - og, og - ob, g, g0c + og + c0, h + g - 1, Hg1, Hg2,
                  sg1[_ST_BASE], True, su, sw)
            if t > 1:
                _fill(Y, ys, k, F - ot, ot - ob, t, g0c + ot + c0, h + t - 1, Ht, Ht,
                      stt[_ST_BASE], False, su, sw)
            F += k
        steady_b = _vprep(Hb1, P, 0, sb1, b, i, D, 0)
        _vprep(Hb2, P, 1, sb2, b, i, D, 1)
        steady_g = _vprep(Hg1, P, 2, sg1, g, i, D, 2)
        _vprep(Hg2, P, 3, sg2, g, i, D, 3)
        if t == 1:  # x_t: the transformed row halo + i
            xo = (halo + i - ob) % RY * ny + b // 2
        else:  # x_t: the target window sums, in the spare row RY of Y
            if _vprep(Ht, P, 4, stt, t, i, Y, RY):
                a = (i - stt[_ST_BASE]) % Rt
                bt = (i + t - 1 - stt[_ST_BASE]) % Rt
                for c in range(wp):
                    p = P[4, c] + Ht[bt, c]
                    P[4, c] = p
                    Y[RY, c] = Ht[a, c] + p
            xo = RY * ny
        # prefetch: the next group of rows to transform, or the next band of the db logarithm
        pf = F + 4 + (i & 3) if mode != 2 else band0 + DB_BAND + i % DB_BAND
        if pf >= src.shape[0]:
            pf = -1
        _decide_row(w, steady_b, steady_g, Hb1, Hb2, (i - sb1[_ST_BASE]) % Rb,
                    (i + b - 1 - sb1[_ST_BASE]) % Rb, Hg1, Hg2, (i - sg1[_ST_BASE]) % Rg,
                    (i + g - 1 - sg1[_ST_BASE]) % Rg, P, D, Y, xo, tt, n_ring, thr, mask, stat,
                    i, c0, tmp_s, tmp_m, src, pf, xc, win)


def _transform_reference(block: np.ndarray, domain: str) -> np.ndarray:
    x = block.astype(np.float64)
    if domain == "amplitude":
        return np.sqrt(np.maximum(x, 0.0))
    if domain == "db":
        return 10.0 * np.log10(np.maximum(x, 1e-30))
    return x


@njit(nogil=True, cache=True)
def _decide_reference(xt, s1b, s1g, s2b, s2g, n_ring, thr, mask, stat):
    h, w = xt.shape
    for i in range(h):
        for j in range(w):
            s1 = s1b[i, j] - s1g[i, j]
            s2 = s2b[i, j] - s2g[i, j]
            mu = s1 / n_ring
            var = (s2 - s1 * mu) / (n_ring - 1.0)
            d = xt[i, j] - mu
            if var > 0.0:
                s = d / np.sqrt(var)
            elif d > 0.0:
                s = np.inf
            else:
                s = 0.0
            stat[i, j] = s
            mask[i, j] = s > thr


def detect_reference(block: np.ndarray, halo: int, origin: tuple[int, int], p: TwoParameterParams, prep: dict):
    """The same detector written plainly with :func:`sarship.pipeline.boxsum.centered_box_sum`
    (bit-identical to :func:`detect`, ~6x slower). :func:`detect` falls back to it when the
    fused kernel cannot be used: window sizes beyond its exact-division range, or a Numba /
    LLVM release on which the kernel's vector intrinsics fail to compile."""
    from sarship.pipeline.boxsum import centered_box_sum

    x = _transform_reference(block, p.domain)
    x2 = x * x
    s1b = centered_box_sum(x, p.background, halo, origin)
    s1g = centered_box_sum(x, p.guard, halo, origin)
    s2b = centered_box_sum(x2, p.background, halo, origin)
    s2g = centered_box_sum(x2, p.guard, halo, origin)
    if p.target == 1:
        xt = np.ascontiguousarray(x[halo:x.shape[0] - halo, halo:x.shape[1] - halo])
    else:
        xt = centered_box_sum(x, p.target, halo, origin) / float(p.target**2)
    mask = np.empty(xt.shape, np.bool_)
    stat = np.empty(xt.shape, np.float32)
    _decide_reference(xt, s1b, s1g, s2b, s2g, float(prep["n_ring"]), float(prep["threshold"]), mask, stat)
    return mask, stat


_FUSED_BROKEN: list[str] = []


def detect(block: np.ndarray, halo: int, origin: tuple[int, int], p: TwoParameterParams, prep: dict):
    """Two-parameter CFAR on one padded tile; returns (mask, standardised statistic).

    Bit-identical to: y = the tile as float64, transformed (``domain``); the window sums of
    y and y * y over the background and guard windows and of y over the target window by
    ``boxsum.centered_box_sum``; then, per pixel, s1 = s1b - s1g, s2 = s2b - s2g,
    mu = s1 / N, var = (s2 - s1 * mu) / (N - 1), d = x_t - mu, statistic d / sqrt(var)
    (inf if var <= 0 < d, 0 if var <= 0 and d <= 0), mask = statistic > threshold. Fused
    and streamed in column strips of at most ``STRIP`` pixels (which change nothing in the
    sums: their blocks are aligned on global coordinates). A CuPy ``block`` runs on its GPU
    (:func:`sarship.pipeline.gpu.cfar.two_parameter`, same sums and arithmetic; the ``db`` domain's
    logarithm may differ in the last bit) and returns CuPy arrays.
    """
    b, g, t = int(p.background), int(p.guard), int(p.target)
    check_windows(halo, b, g, t)
    if is_device_array(block):  # CuPy block: the GPU twin (pipeline.gpu.cfar), same sums and rule
        from sarship.pipeline.gpu.cfar import two_parameter

        return two_parameter(block, halo, origin, b, g, t, float(prep["n_ring"]), float(prep["threshold"]),
                             p.domain)
    h = block.shape[0] - 2 * halo
    w = block.shape[1] - 2 * halo
    mode = _MODE[p.domain]
    src = block if block.dtype in (np.float32, np.float64) else block.astype(np.float64)
    mask = np.empty((h, w), np.bool_)
    stat = np.empty((h, w), np.float32)
    n_ring = float(prep["n_ring"])
    thr = float(prep["threshold"])
    if _FUSED_BROKEN or not (n_ring == int(n_ring) and 8 <= n_ring < 2**21 and t * t < 2**21):
        return detect_reference(block, halo, origin, p, prep)  # outside _vdivn's exact range
    n_strips = -(-w // STRIP)
    sw = -(-w // max(n_strips, 1))  # equal strips (a narrow last strip would cost its overlap)
    try:
        for c0 in range(0, w, max(sw, 1)):
            _detect_strip(src, mode, halo, int(origin[0]), int(origin[1]), t, g, b, n_ring, thr,
                          c0, min(c0 + sw, w), mask, stat)
    except Exception as exc:  # compile failure of the intrinsics on another Numba/LLVM
        from numba.core.errors import NumbaError

        if not isinstance(exc, (NumbaError, RuntimeError, TypeError, NotImplementedError)):
            raise
        import warnings

        _FUSED_BROKEN.append(f"{type(exc).__name__}: {exc}")
        warnings.warn(f"two_parameter: fused kernel unavailable ({type(exc).__name__}); using the "
                      "reference implementation", RuntimeWarning, stacklevel=2)
        return detect_reference(block, halo, origin, p, prep)
    return mask, stat


SPEC = DetectorSpec(
    name="two_parameter",
    summary="Two-parameter (Gaussian) CFAR with the exact Student-t threshold and target-window correction",
    reference="Novak & Hesse 1991; ESA SNAP Adaptive Thresholding; ALGORITHMS.md 'CFAR families'",
    params=TwoParameterParams,
    prepare=prepare,
    detect=detect,
    input="intensity",
    needs_looks=False,
    gpu=True,
)
