"""Absent (no-data) pixels of single-channel intensity blocks, shared by ``ca_cfar``, ``os_cfar``,
``two_parameter`` and ``lmm`` (CPU and GPU).

Rule. A pixel is *absent* when it is not finite (NaN: the scene store's no-data marker) or
equals the detector's ``nodata`` parameter when one is set (``nodata=0`` for a zero-filled
border). Exact zeros are *not* absent by default: 8-bit quantised chips (SSDD, HRSID JPEGs)
carry legitimate zeros in dark sea (up to 84 % of a chip in SAR-Ship-Dataset), and a rule
decided per tile from the data ("zero absent when the data takes no other zero") would
break tiling invariance. ``lmm`` fits ln x, so it leaves out non-positive samples anyway.

Absent pixels are never targets (mask 0, statistic 0) and enter no ring statistic. Per
pixel, ``K`` = the number of present cells of the ring (tiling-invariant box sums of the
presence indicator, exact integers). A pixel is tested when its whole target window is
present and ``K >= min_valid(N) = ceil(N / 2)``; the threshold is then the exact one for K
ring samples (each detector's module says how). Pixels whose background window holds no
absent cell keep the complete-data computation, bit for bit: the window sums only add
values inside their window (:mod:`sarship.pipeline.tiling.boxsum`), so they do not see how far away
data is absent. The pixels whose background window meets an absent cell are recomputed
here (ca_cfar, two_parameter; os_cfar in its own kernel) with the absent cells zeroed,
in NumPy or CuPy (the array's own module), the same IEEE operations on both.
"""

from __future__ import annotations

import functools

import numpy as np

from sarship.pipeline.gpu import is_device_array
from sarship.pipeline.stats.tails import f_isf, norm_isf, t_isf


def xp_of(a):
    if is_device_array(a):
        import cupy

        return cupy
    return np


def min_valid(n_ring: int) -> int:
    """The fewest present ring cells for a pixel to be tested: half the ring, rounded up."""
    return (int(n_ring) + 1) // 2


def present(block, nodata=None):
    """Boolean array: the pixels of ``block`` that are present (finite, and != ``nodata``)."""
    xp = xp_of(block)
    ok = xp.isfinite(block)
    if nodata is not None:
        ok &= block != block.dtype.type(nodata) if block.dtype.kind == "f" else block != nodata
    return ok


def fill(block, ok, value):
    """``block`` with its absent pixels set to ``value`` (a copy)."""
    xp = xp_of(block)
    return xp.where(ok, block, xp.asarray(value, dtype=block.dtype))


def counts(ok, halo: int, origin, b: int, g: int, t: int, box):
    """``(K, n_bg, n_t)``: present cells of the ring, of the background window and of the
    target window of each core pixel (float64 holding exact integers); ``box`` is
    ``centered_box_sum`` of :mod:`sarship.pipeline.tiling.boxsum` or :mod:`sarship.pipeline.gpu.box`."""
    xp = xp_of(ok)
    okf = ok.astype(xp.float64)
    nb = box(okf, b, halo, origin)
    K = nb - box(okf, g, halo, origin)
    h = ok.shape[0] - 2 * halo
    w = ok.shape[1] - 2 * halo
    nt = box(okf, t, halo, origin) if t > 1 else okf[halo : halo + h, halo : halo + w]
    return K, nb, nt


def per_k_table(K, fn):
    """A float64 table ``tab[k] = fn(k)`` for the distinct values ``k`` of ``K`` (others NaN),
    in ``K``'s array module."""
    xp = xp_of(K)
    ks = np.unique(np.asarray(K.get() if xp is not np else K)).astype(np.int64)
    tab = np.full(int(ks.max()) + 1 if ks.size else 1, np.nan)
    for k in ks:
        tab[k] = fn(int(k))
    return xp.asarray(tab)


@functools.lru_cache(maxsize=8192)
def ca_threshold(pfa: float, looks: float, k: int, n_target: int) -> float:
    return f_isf(pfa, 2.0 * n_target * looks, 2.0 * k * looks)


@functools.lru_cache(maxsize=8192)
def tp_threshold(pfa: float, k: int, n_target: int, kind: str) -> float:
    if kind == "student":
        return float(np.sqrt(1.0 / n_target + 1.0 / k) * t_isf(pfa, k - 1))
    return float(norm_isf(pfa) / np.sqrt(n_target))


def scaled_stat(xp, s, thr_k, thr_n, det):
    """The statistic reported where K < N: ``s * T(N) / T(K)`` (float32), so that, as for
    complete rings, ``stat > T(N)`` exactly where the pixel is detected (``det``: s > T(K))."""
    with np.errstate(over="ignore", invalid="ignore"):
        r = (s * (thr_n / thr_k)).astype(xp.float32)
    lo = np.float32(thr_n)
    if not float(lo) > thr_n:
        lo = np.nextafter(lo, np.float32(np.inf))
    hi = np.float32(thr_n)
    if float(hi) > thr_n:
        hi = np.nextafter(hi, np.float32(-np.inf))
    r = xp.where(det & ~(r > lo), lo, r)  # detected: above T(N)
    return xp.where(~det & (r > hi), hi, r)  # not detected: not above T(N)


def ca_redo(xz, ok, halo, origin, b, g, t, n_ring, pfa, looks, thr_n, mask, stat, box):
    """ca_cfar on the pixels whose background window meets an absent cell (``xz``: the block
    with absent cells zeroed); updates ``mask`` / ``stat`` in place."""
    xp = xp_of(xz)
    K, nb, nt = counts(ok, halo, origin, b, g, t, box)
    redo = nb < float(b * b)
    if not bool(redo.any()):
        return
    tested = redo & (nt == float(t * t)) & (K >= float(min_valid(n_ring)))
    mask[redo] = False
    stat[redo] = 0
    if not bool(tested.any()):
        return
    bg = box(xz, b, halo, origin)[tested]
    gd = box(xz, g, halo, origin)[tested]
    h = xz.shape[0] - 2 * halo
    w = xz.shape[1] - 2 * halo
    if t == 1:
        xt = xz[halo : halo + h, halo : halo + w].astype(xp.float64)[tested]
    else:
        xt = box(xz, t, halo, origin)[tested] / float(t * t)
    k = K[tested].astype(xp.int64)
    n_t = t * t
    tab = per_k_table(k, lambda kk: ca_threshold(float(pfa), float(looks), kk, n_t))
    m = (bg - gd) * (1.0 / k.astype(xp.float64))
    with np.errstate(divide="ignore", invalid="ignore"):
        q = xt / xp.where(m > 0.0, m, 1.0)
    s = xp.where(m > 0.0, q, xp.where(xt > 0.0, xp.inf, 0.0))
    tk = tab[k]
    det = s > tk
    stat[tested] = scaled_stat(xp, s, tk, float(thr_n), det)
    mask[tested] = det


def tp_redo(yz, ok, halo, origin, b, g, t, n_ring, pfa, kind, thr_n, mask, stat, box):
    """two_parameter on the pixels whose background window meets an absent cell (``yz``: the
    transformed block, float64, absent cells zeroed); updates ``mask`` / ``stat`` in place."""
    xp = xp_of(yz)
    K, nb, nt = counts(ok, halo, origin, b, g, t, box)
    redo = nb < float(b * b)
    if not bool(redo.any()):
        return
    tested = redo & (nt == float(t * t)) & (K >= float(max(2, min_valid(n_ring))))
    mask[redo] = False
    stat[redo] = 0
    if not bool(tested.any()):
        return
    y2 = yz * yz
    s1 = box(yz, b, halo, origin)[tested] - box(yz, g, halo, origin)[tested]
    s2 = box(y2, b, halo, origin)[tested] - box(y2, g, halo, origin)[tested]
    h = yz.shape[0] - 2 * halo
    w = yz.shape[1] - 2 * halo
    if t == 1:
        xt = yz[halo : halo + h, halo : halo + w][tested]
    else:
        xt = box(yz, t, halo, origin)[tested] / float(t * t)
    kf = K[tested]
    k = kf.astype(xp.int64)
    n_t = t * t
    tab = per_k_table(k, lambda kk: tp_threshold(float(pfa), kk, n_t, kind))
    mu = s1 / kf
    var = (s2 - s1 * mu) / (kf - 1.0)
    d = xt - mu
    with np.errstate(divide="ignore", invalid="ignore"):
        q = d / xp.sqrt(xp.where(var > 0.0, var, 1.0))
    s = xp.where(var > 0.0, q, xp.where(d > 0.0, xp.inf, 0.0))
    tk = tab[k]
    det = s > tk
    stat[tested] = scaled_stat(xp, s, tk, float(thr_n), det)
    mask[tested] = det
