"""GPU twins of the single-channel CFAR detectors (``ca_cfar``, ``two_parameter``, ``os_cfar``).

Absent pixels (NaN, or the ``nodata`` value): as on the CPU (:mod:`sarship.pipeline.tiling.intensity_absent`):
the complete-data kernel runs on the block with absent cells zeroed (NaN for ``os_cfar``), then
the pixels whose background window meets an absent cell are recomputed with K present ring
cells by the same CuPy/NumPy code as the CPU (``ca_redo``, ``tp_redo``); for ``os_cfar`` those
pixels (a band along the absent region) are decided by the CPU kernel (``os_cfar.absent_redo``)
and copied back.

Each takes the same arguments as the CPU ``detect`` with a CuPy ``block`` and returns CuPy
``(mask, stat)``; the window sums are those of :mod:`sarship.pipeline.gpu.box` (bit-identical to
the CPU's) and the decision repeats the CPU kernel's arithmetic (see
:mod:`sarship.pipeline.gpu.kernels`).
"""

from __future__ import annotations

import numpy as np

from sarship.pipeline.gpu import kernels
from sarship.pipeline.gpu.box import centered_box_sum
from sarship.pipeline.tiling import intensity_absent


def _float_block(cp, block):
    if block.ndim != 2:
        raise ValueError(f"block must be 2-D, got shape {block.shape}")
    if block.dtype != cp.float32 and block.dtype != cp.float64:
        block = block.astype(cp.float64)
    return cp.ascontiguousarray(block)


def ca_cfar(
    block, halo: int, origin, b: int, g: int, t: int, n_ring: int, thr: float, *, pfa=None, looks=None, nodata=None
):
    """CA-CFAR (see :mod:`sarship.pipeline.detectors.ca_cfar`): x_t / ring mean > T."""
    import cupy as cp

    x = _float_block(cp, block)
    if pfa is not None:
        ok = intensity_absent.present(x, nodata)
        if not bool(ok.all()):
            xz = cp.ascontiguousarray(intensity_absent.fill(x, ok, 0.0))
            mask, stat = ca_cfar(xz, halo, origin, b, g, t, n_ring, thr)
            intensity_absent.ca_redo(
                xz, ok, halo, origin, b, g, t, int(n_ring), float(pfa), float(looks), thr, mask, stat, centered_box_sum
            )
            return mask, stat
    h = x.shape[0] - 2 * halo
    w = x.shape[1] - 2 * halo
    bg = centered_box_sum(x, b, halo, origin)
    gd = centered_box_sum(x, g, halo, origin)
    if t == 1:
        xt = cp.ascontiguousarray(x[halo : halo + h, halo : halo + w], dtype=cp.float64)
    else:
        xt = centered_box_sum(x, t, halo, origin) / float(t * t)
    mask = cp.empty((h, w), cp.bool_)
    stat = cp.empty((h, w), cp.float32)
    n = h * w
    kernels.launch(
        "ca_decide", n, (xt, bg, gd, np.float64(1.0 / float(n_ring)), np.float64(thr), np.int64(n), mask, stat)
    )
    return mask, stat


_MODES = {"intensity": 0, "amplitude": 1, "db": 2}


def two_parameter(
    block,
    halo: int,
    origin,
    b: int,
    g: int,
    t: int,
    n_ring: float,
    thr: float,
    domain: str,
    *,
    pfa=None,
    kind="student",
    nodata=None,
):
    """Two-parameter CFAR (see :mod:`sarship.pipeline.detectors.two_parameter`)."""
    import cupy as cp

    x = _float_block(cp, block)
    if pfa is not None:
        ok = intensity_absent.present(x, nodata)
        if not bool(ok.all()):
            xz = cp.ascontiguousarray(intensity_absent.fill(x, ok, 0.0))
            mask, stat = two_parameter(xz, halo, origin, b, g, t, n_ring, thr, domain)
            y = cp.empty(xz.shape, cp.float64)
            y2 = cp.empty(xz.shape, cp.float64)
            name = "tp_transform_f32" if xz.dtype == cp.float32 else "tp_transform_f64"
            kernels.launch(name, xz.size, (xz, np.int64(xz.size), np.int32(_MODES[domain]), y, y2))
            yz = cp.ascontiguousarray(intensity_absent.fill(y, ok, 0.0))
            intensity_absent.tp_redo(
                yz, ok, halo, origin, b, g, t, int(n_ring), float(pfa), kind, thr, mask, stat, centered_box_sum
            )
            return mask, stat
    h = x.shape[0] - 2 * halo
    w = x.shape[1] - 2 * halo
    y = cp.empty(x.shape, cp.float64)
    y2 = cp.empty(x.shape, cp.float64)
    name = "tp_transform_f32" if x.dtype == cp.float32 else "tp_transform_f64"
    kernels.launch(name, x.size, (x, np.int64(x.size), np.int32(_MODES[domain]), y, y2))
    s1b = centered_box_sum(y, b, halo, origin)
    s1g = centered_box_sum(y, g, halo, origin)
    s2b = centered_box_sum(y2, b, halo, origin)
    s2g = centered_box_sum(y2, g, halo, origin)
    if t == 1:
        xt = cp.ascontiguousarray(y[halo : halo + h, halo : halo + w])
    else:
        xt = centered_box_sum(y, t, halo, origin) / float(t * t)
    mask = cp.empty((h, w), cp.bool_)
    stat = cp.empty((h, w), cp.float32)
    n = h * w
    kernels.launch(
        "tp_decide", n, (xt, s1b, s1g, s2b, s2g, np.float64(n_ring), np.float64(thr), np.int64(n), mask, stat)
    )
    return mask, stat


def os_cfar(
    block,
    halo: int,
    rb: int,
    rg: int,
    rt: int,
    k: int,
    alpha: float,
    stat_floor: float,
    *,
    origin=None,
    params=None,
    prep=None,
):
    """OS-CFAR (see :mod:`sarship.pipeline.detectors.os_cfar`): x_t > alpha X_(k).

    The decision counts, per pixel, the ring samples below the smallest value ``c`` of the
    block's type with ``not (alpha * c < x_t)`` (exact comparisons: the CPU's mask); the
    statistic ``x_t / X_(k)`` is computed for the detected pixels only, with X_(k) found
    exactly by bisection on order-preserving integer keys of the ring values.
    """
    import cupy as cp

    x = _float_block(cp, block)
    if params is not None:
        ok = intensity_absent.present(x, params.nodata)
        if not bool(ok.all()):
            xn = cp.ascontiguousarray(intensity_absent.fill(x, ok, np.nan))
            mask, stat = os_cfar(xn, halo, rb, rg, rt, k, alpha, stat_floor)
            from sarship.pipeline.detectors.os_cfar import absent_redo

            m_h, s_h = mask.get(), stat.get()
            absent_redo(xn.get(), ok.get(), halo, origin, params, prep, m_h, s_h)
            return cp.asarray(m_h), cp.asarray(s_h)
    h = x.shape[0] - 2 * halo
    w = x.shape[1] - 2 * halo
    f32 = x.dtype == cp.float32
    mask = cp.empty((h, w), cp.bool_)
    xt = cp.empty((h, w), cp.float64)
    stat = cp.zeros((h, w), cp.float32)
    ld = np.int64(x.shape[1])
    kernels.launch(
        "os_decide_f32" if f32 else "os_decide_f64",
        h * w,
        (
            x,
            ld,
            np.int64(h),
            np.int64(w),
            np.int32(halo),
            np.int32(rb),
            np.int32(rg),
            np.int32(rt),
            np.int64(k),
            np.float64(alpha),
            mask,
            xt,
        ),
    )
    idx = cp.flatnonzero(mask).astype(cp.int64)
    if idx.size:
        kernels.launch(
            "os_stat_f32" if f32 else "os_stat_f64",
            int(idx.size),
            (
                x,
                ld,
                np.int64(w),
                np.int32(halo),
                np.int32(rb),
                np.int32(rg),
                np.int64(k),
                idx,
                np.int64(idx.size),
                xt,
                np.float64(alpha),
                np.float32(stat_floor),
                stat,
            ),
        )
    return mask, stat
