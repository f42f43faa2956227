r"""Lognormal-mixture CFAR (``lmm``): per-cell fit of a mixture of ln x, calibrated tail.

Source: chapter 3 of SUN Tianyu, *基于 GPU 的极化 SAR 图像舰船检测算法设计* ("Design of
GPU-based ship detection algorithms for polarimetric SAR images"), thesis, Department of
Electronic Engineering, Tsinghua University, 2020 ([sun2020] in ``docs/references.md``).
The model, the fit, the threshold, their calibration (measured) and the parameters are
described in ``docs/algorithms/lmm.md``; timings are in ``bench/RESULTS.md``.

Per cell under test (CUT), from the positive finite samples of the ring between the guard
and background squares (thesis fig 3.1):

- model: x is a K-component lognormal mixture (eq 3-1), i.e. y = ln x is a Gaussian mixture
  (eq 3-3); K = ``components`` (default 3);
- fit: EM (eq 3-4) for K' = 1..K with K' chosen by BIC (``select="bic"``), the chosen fit
  polished to the maximum likelihood by damped Newton;
- threshold: t = ln T with 1 - F(T) = PFA (eq 3-5, 3-7), safeguarded Newton (eq 3-6) in the
  log domain, raised by the first-order predictive correction for the fit's finite-sample
  error (``tail="predictive"``); ``select="fixed", tail="plugin"`` is the thesis' plug-in
  EM threshold (eq 3-4..3-7 as written);
- contamination (``refuse_weight``, default 0.15): a fit whose tail at the threshold is
  carried by a light component (weight <= refuse_weight) foreign to the others (its mean
  beyond their own 1e-5 threshold, or twice their spread) is refused as a ship's own pixels
  in the ring, and the ring is refitted with the samples above the others' 1 - 1/n level
  right-censored: the censored likelihood ``sum ln f(y_kept) + n_c ln S(c)`` in every step
  (censored CFAR, [rickard1977]; censored EM, [dempster1977] sec 4.2, [lee2012]; [cohen1959]);
  opt-in: two-pass censoring of every ring (``censor``) and left-censoring of the darkest
  samples (``censor_low``) (docs/algorithms/lmm.md, "Contamination and quantisation"; a
  CuPy block with any of these is decided by the CPU kernels, :func:`cpu_only_fit`);
- decision: ``ln x_t > t`` with x_t the mean of the target window; ``stat = x_t / T``
  (float32, > 1 where detected, 0 elsewhere).

Forms (``method``): ``exact`` fits the raw ring samples; ``fast`` fits the ring's histogram
of ln x on a global grid of ``bin_width`` nepers (slid along each row, Sheppard-corrected);
``grid`` (default) does the fast fit only at global nodes every ``grid_step`` pixels,
interpolates ln T bilinearly in between and gives the pixels within ``grid_refine`` nepers
of it their own fast fit. Everything is per pixel (and per global node), independent of the
tile origin: bit-identical for any tiling.

The per-ring maths is :mod:`sarship.pipeline.stats.lmm_fit` (re-exported here); this module holds
the parameters, the per-tile kernels (Numba, single-threaded, no fastmath) and the
dispatch: a CuPy block runs :mod:`sarship.pipeline.gpu.lmm`, looked up when needed, which
depends on :mod:`sarship.pipeline.stats.lmm_fit` and never on this module.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from pydantic import Field
from scipy import special

from sarship.pipeline.detectors.base import DetectorParams, DetectorSpec, float_block, with_defaults
from sarship.pipeline.gpu import is_device_array
from sarship.pipeline.stats.lmm_fit import (
    em_fit_points,
    fit_threshold,
    init_z_table,
    mixture_grad_hess,
    mixture_loglik,
    mixture_sf_log,
    mixture_threshold_log,
    ml_newton,
    predictive_shift,
)

__all__ = [
    "LMMParams",
    "SPEC",
    "prepare",
    "detect",
    "em_fit_points",
    "mixture_threshold_log",
    "mixture_sf_log",
    "mixture_loglik",
    "mixture_grad_hess",
    "ml_newton",
    "predictive_shift",
    "fit_threshold",
    "init_z_table",
    "LMM_NOTES",
]

#: Measured agreement / speed of the forms: where they are written down.
LMM_NOTES = "see docs/algorithms/lmm.md (agreement, calibration) and bench/RESULTS.md (timings)"

DEFAULT_METHOD = "grid"
#: Default censored fraction of the ring (docs/algorithms/lmm.md, "Contamination and quantisation").
DEFAULT_CENSOR = 0.0
#: Default left-censored fraction and refusal weight (docs/algorithms/lmm.md, "Contamination and quantisation").
DEFAULT_CENSOR_LOW = 0.0
DEFAULT_REFUSE_WEIGHT = 0.15


class LMMParams(
    with_defaults(
        DetectorParams,
        "LMMDefaults",
        pfa=1e-3,
        guard=41,
        background=81,
        merge_px=4,
        auto_min_area_px=10,
        auto_min_length_m=25.0,
        auto_min_area_m2=200.0,
    )
):
    """LMM-CFAR parameters: the common ones plus the mixture / EM settings."""

    components: int = Field(
        3,
        ge=1,
        le=6,
        description="K, number of lognormal components (eq 3-1); with select='bic' the most, K' <= K chosen per cell",
    )
    method: str = Field(
        DEFAULT_METHOD,
        pattern="^(exact|fast|grid)$",
        description="'exact': EM on the ring samples; 'fast': EM on the ring histogram of ln x; "
        "'grid': the fast fit at global grid nodes, ln T bilinearly interpolated",
    )
    max_iter: int = Field(200, ge=1, le=100000, description="EM iteration cap")
    tol: float = Field(
        1e-5, gt=0.0, lt=1.0, description="EM stops when the mean log-likelihood per sample changes by less than this"
    )
    bin_width: float = Field(
        0.125, gt=0.0, le=1.0, description="fast / grid forms: histogram bin width in ln x (nepers)"
    )
    grid_step: int | None = Field(
        None,
        ge=1,
        le=256,
        description="grid form: node spacing in pixels (nodes at global multiples); "
        "default max(1, guard // 4), so nodes stay inside a ship's guard",
    )
    grid_refine: float = Field(
        1.0,
        ge=0.0,
        le=100.0,
        description="grid form: pixels with ln x_t > interpolated ln T - grid_refine "
        "(nepers) get their own fast fit, which decides",
    )
    select: str = Field(
        "bic",
        pattern="^(bic|fixed)$",
        description="'bic': per cell, K' <= components chosen by the BIC of the EM fits; "
        "'fixed': K' = components (the thesis)",
    )
    tail: str = Field(
        "predictive",
        pattern="^(predictive|plugin)$",
        description="'predictive': ML fit (Newton-polished EM) and its threshold raised by the "
        "delta-method predictive correction (calibrated PFA); 'plugin': 1 - F(T) = PFA "
        "for the EM fit (thesis eq 3-5)",
    )
    censor: float = Field(
        DEFAULT_CENSOR,
        ge=0.0,
        le=0.5,
        description="fraction of each ring's brightest usable samples right-censored in the "
        "fit (censored likelihood; the threshold is the fitted clutter tail), "
        "so that a ship's own pixels in the ring do not enter the clutter model; "
        "0: the uncensored fit",
    )
    censor_level: float = Field(
        0.0,
        ge=0.0,
        le=0.2,
        description="with censor > 0, pass 2 censors only the ring samples above the "
        "pass-1 clutter fit's exceedance level censor_level (0: 1/n, n "
        "the ring's usable samples)",
    )
    censor_low: float = Field(
        DEFAULT_CENSOR_LOW,
        ge=0.0,
        le=0.5,
        description="fraction of each ring's darkest usable samples left-censored in the fit "
        "(known only to lie below the lowest kept value): the coarse quantised "
        "low values of 8-bit products and the lower tail no longer shape the "
        "clutter's upper tail; 0: none",
    )
    refuse_weight: float = Field(
        DEFAULT_REFUSE_WEIGHT,
        ge=0.0,
        le=0.5,
        description="a ring fit whose tail at the threshold is carried by a component "
        "of weight <= refuse_weight is refused as contamination (a ship's "
        "own pixels in the ring): the ring samples above the other "
        "components' 1 - 1/n level are right-censored and the ring fitted "
        "again (at most 3 times); 0: off",
    )
    nodata: float | None = Field(
        None,
        description="value marking absent pixels besides NaN (e.g. a positive fill value); "
        "non-positive values are never usable samples (ln x)",
    )


def cpu_only_fit(prep: dict, params: LMMParams) -> bool:
    """True when the fit uses censoring or the refusal rule (``censor``, ``censor_low`` or
    ``refuse_weight`` > 0, the default included), which the GPU twin does not transcribe:
    a CuPy block is then decided by the CPU kernels (docs/algorithms/lmm.md, "GPU")."""
    return any(float(prep.get(k, getattr(params, k))) > 0.0 for k in ("censor", "censor_low", "refuse_weight"))


def min_usable(n_ring: int, K: int) -> int:
    """The fewest usable (positive, finite, present) ring samples for a pixel to be tested:
    half the ring (rounded up), and at least max(8, 3K) for the fit."""
    return max(8, 3 * int(K), (int(n_ring) + 1) // 2)


def grid_step(p: LMMParams) -> int:
    """The node spacing: ``grid_step``, else ``max(1, guard // 4)`` (1 = the fast form)."""
    return int(p.grid_step) if p.grid_step is not None else max(1, int(p.guard) // 4)


def prepare(p: LMMParams) -> dict:
    K = int(p.components)
    return {
        "n_ring": p.n_ring,
        "components": K,
        "method": p.method,
        "z": float(-special.ndtri(p.pfa)),  # Phi^{-1}(1 - PFA)
        "log_pfa": float(math.log(p.pfa)),
        "init_z": [float(special.ndtri((k + 0.5) / K)) for k in range(K)],
        "select": p.select,
        "tail": p.tail,
        "censor": float(p.censor),
        "censor_level": float(p.censor_level),
        "censor_low": float(p.censor_low),
        "refuse_weight": float(p.refuse_weight),
        "max_iter": int(p.max_iter),
        "tol": float(p.tol),
        "bin_width": float(p.bin_width),
        "grid_step": grid_step(p),
        "grid_refine": float(p.grid_refine),
        "statistic": "x_t / T (T: 1 - F(T) = PFA for the fitted ring mixture); detected when > 1",
    }


# ---------------------------------------------------------------------------------------
# kernels: per tile, one fit per pixel (exact, fast) or per global node and candidate (grid).
# ``fit`` = (K, init_zs, max_iter, tol, select, predictive, z, log_pfa, censor, censor_level, censor_low,
# refuse_weight): the settings of
# :func:`sarship.pipeline.stats.lmm_fit.fit_threshold`, the same for every ring of a tile.


@njit(nogil=True, cache=True)
def _fit(y, wt, n_pts, shep, fit, a, mu, s):
    """``fit_threshold`` of the weighted points with the tile's settings: (t, work)."""
    K, init_zs, max_iter, tol, select, predictive, z, log_pfa, cens, cens_q, lcens, refuse = fit
    t, work, _ = fit_threshold(
        y,
        wt,
        n_pts,
        K,
        init_zs,
        max_iter,
        tol,
        shep,
        select,
        predictive,
        z,
        log_pfa,
        a,
        mu,
        s,
        cens,
        cens_q,
        lcens,
        refuse,
    )
    return t, work


@njit(nogil=True, cache=True)
def _target_log(block, ci, cj, rt):
    """ln of the target-window mean (row-major fixed order); NaN if not positive finite."""
    if rt == 0:
        x = np.float64(block[ci, cj])
    else:
        acc = 0.0
        for a in range(ci - rt, ci + rt + 1):
            for b in range(cj - rt, cj + rt + 1):
                acc += np.float64(block[a, b])
        x = acc / ((2 * rt + 1) * (2 * rt + 1))
    if x > 0.0 and x < np.inf:
        return math.log(x)
    return np.nan


@njit(nogil=True, cache=True)
def _decide(lx, t, i, j, mask, stat):
    if lx > t:
        mask[i, j] = True
        r = np.float32(math.exp(lx - t))
        if not (r > np.float32(1.0)):
            r = np.nextafter(np.float32(1.0), np.float32(np.inf))
        stat[i, j] = r


@njit(nogil=True, cache=True)
def _exact_kernel(block, halo, h, w, rb, rg, rt, fit, nmin, mask, stat, iters):
    H, Wd = block.shape
    Y = np.empty((H, Wd))
    for r in range(H):
        for c in range(Wd):
            x = np.float64(block[r, c])
            Y[r, c] = math.log(x) if (x > 0.0 and x < np.inf) else np.nan
    n_ring = (2 * rb + 1) ** 2 - (2 * rg + 1) ** 2
    buf = np.empty(n_ring)
    ones = np.ones(n_ring)
    K = fit[0]
    a = np.empty(K)
    mu = np.empty(K)
    s = np.empty(K)
    for i in range(h):
        ci = i + halo
        for j in range(w):
            cj = j + halo
            lx = _target_log(block, ci, cj, rt)
            if lx != lx:
                continue
            n = 0
            for r in range(ci - rb, ci + rb + 1):
                inner = (r >= ci - rg) and (r <= ci + rg)
                for c in range(cj - rb, cj + rb + 1):
                    if inner and c >= cj - rg and c <= cj + rg:
                        continue
                    v = Y[r, c]
                    if v == v:
                        buf[n] = v
                        n += 1
            if n < nmin:
                continue
            if fit[8] > 0.0 or fit[10] > 0.0 or fit[11] > 0.0:  # censoring takes the points in ascending order
                buf[:n].sort()
            t, iters[i, j] = _fit(buf, ones, n, 0.0, fit, a, mu, s)
            _decide(lx, t, i, j, mask, stat)


# histogram forms (fast, grid): the ring's counts of the global ln-x bins


@njit(nogil=True, cache=True)
def _bin_index(block, inv_h):
    """Global ln-x bin of every value (floor(ln x / h)), offset to >= 0; -1 if unusable;
    with the offset and the smallest and largest bin used (bmax = -1: none)."""
    H, Wd = block.shape
    off = 1 + int(math.ceil(800.0 * inv_h))  # ln of positive float64 > -745
    B = np.empty((H, Wd), np.int32)
    bmin = 1 << 30
    bmax = -1
    for r in range(H):
        for c in range(Wd):
            x = np.float64(block[r, c])
            if x > 0.0 and x < np.inf:
                b = int(math.floor(math.log(x) * inv_h)) + off
                B[r, c] = b
                if b < bmin:
                    bmin = b
                if b > bmax:
                    bmax = b
            else:
                B[r, c] = -1
    return B, off, bmin, bmax


@njit(nogil=True, cache=True)
def _hist_work(bmin, bmax, K):
    """Work arrays of a histogram kernel: the counts (zero), the points and the fit."""
    nb = bmax - bmin + 1
    return np.zeros(bmax + 1, np.int64), np.empty(nb), np.empty(nb), np.empty(K), np.empty(K), np.empty(K)


@njit(nogil=True, cache=True)
def _col(hist, B, r0, r1, c, d):
    for r in range(r0, r1):
        b = B[r, c]
        if b >= 0:
            hist[b] += d


@njit(nogil=True, cache=True)
def _add_ring(hist, B, ci, cj, rb, rg):
    """Count the ring around block cell (ci, cj) into ``hist``, column by column."""
    for c in range(cj - rb, cj + rb + 1):
        if c < cj - rg or c > cj + rg:
            _col(hist, B, ci - rb, ci + rb + 1, c, 1)
        else:
            _col(hist, B, ci - rb, ci - rg, c, 1)
            _col(hist, B, ci + rg + 1, ci + rb + 1, c, 1)


@njit(nogil=True, cache=True)
def _hist_fit(hist, bmin, bmax, off, bw, yv, wv, fit, nmin, clear, a, mu, s):
    """The fast form's fit of the counts in ``hist``: the non-empty bins in ascending order,
    each its centre ``((b - off) + 1/2) bw`` weighted by its count, Sheppard correction
    ``bw^2 / 12``. ``clear``: zero ``hist`` on the way. Returns (t, work); (NaN, 0) if the
    ring holds fewer than nmin usable samples."""
    n = 0
    ntot = 0
    for b in range(bmin, bmax + 1):
        cnt = hist[b]
        if cnt > 0:
            yv[n] = ((b - off) + 0.5) * bw
            wv[n] = np.float64(cnt)
            n += 1
            ntot += cnt
            if clear:
                hist[b] = 0
    if ntot < nmin:
        return np.nan, 0
    return _fit(yv, wv, n, bw * bw / 12.0, fit, a, mu, s)


@njit(nogil=True, cache=True)
def _fast_kernel(block, halo, h, w, rb, rg, rt, fit, nmin, bw, mask, stat, iters):
    B, off, bmin, bmax = _bin_index(block, 1.0 / bw)
    if bmax < 0:
        return
    hist, yv, wv, a, mu, s = _hist_work(bmin, bmax, fit[0])
    for i in range(h):
        ci = i + halo
        hist[:] = 0
        _add_ring(hist, B, ci, halo, rb, rg)
        for j in range(w):
            cj = j + halo
            if j > 0:
                # leaving column cj-1-rb (full), entering cj+rb (full);
                # column cj-1-rg becomes ring in the middle rows, cj+rg leaves it
                _col(hist, B, ci - rb, ci + rb + 1, cj - 1 - rb, -1)
                _col(hist, B, ci - rb, ci + rb + 1, cj + rb, 1)
                _col(hist, B, ci - rg, ci + rg + 1, cj - 1 - rg, 1)
                _col(hist, B, ci - rg, ci + rg + 1, cj + rg, -1)
            lx = _target_log(block, ci, cj, rt)
            if lx != lx:
                continue
            t, iters[i, j] = _hist_fit(hist, bmin, bmax, off, bw, yv, wv, fit, nmin, False, a, mu, s)
            _decide(lx, t, i, j, mask, stat)


@njit(nogil=True, cache=True)
def _ring_hist_fit(B, hist, ci, cj, rb, rg, bmin, bmax, off, bw, yv, wv, fit, nmin, a, mu, s):
    """The fast form's fit for the ring around block cell (ci, cj), histogram built directly
    (same integer counts as the sliding one, hence the same threshold bit for bit).
    ``hist`` must be zero on entry and is zero on return. Returns (t, work); t = NaN
    if the ring holds fewer than nmin usable samples."""
    _add_ring(hist, B, ci, cj, rb, rg)
    return _hist_fit(hist, bmin, bmax, off, bw, yv, wv, fit, nmin, True, a, mu, s)


@njit(nogil=True, cache=True)
def _grid_kernel(block, halo, h, w, rb, rg, rt, fit, nmin, bw, step, refine, g0r, g0c, mask, stat, iters):
    """Grid form: fast (histogram) fit at global nodes (multiples of ``step``), ln T
    bilinearly interpolated. ``(g0r, g0c)``: global coordinates of the core's [0, 0];
    ``halo >= rb + step - 1`` so the ring of every needed node lies in the block."""
    B, off, bmin, bmax = _bin_index(block, 1.0 / bw)
    if bmax < 0:
        return
    hist, yv, wv, a, mu, s = _hist_work(bmin, bmax, fit[0])
    # nodes kr0..kr1 (rows), kc0..kc1 (cols), global index k -> global coordinate k * step
    kr0 = g0r // step
    kr1 = (g0r + h - 1) // step + 1
    kc0 = g0c // step
    kc1 = (g0c + w - 1) // step + 1
    nr = kr1 - kr0 + 1
    nc = kc1 - kc0 + 1
    T = np.full((nr, nc), np.nan)
    itn = np.zeros((nr, nc), np.int32)
    # block index of global coordinate g: g - g0 + halo
    for u in range(nr):
        ci = (kr0 + u) * step - g0r + halo
        for v in range(nc):
            cj = (kc0 + v) * step - g0c + halo
            T[u, v], itn[u, v] = _ring_hist_fit(
                B, hist, ci, cj, rb, rg, bmin, bmax, off, bw, yv, wv, fit, nmin, a, mu, s
            )
    inv_step = 1.0 / step
    for i in range(h):
        gr = g0r + i
        kr = gr // step
        u = kr - kr0
        fr = (gr - kr * step) * inv_step
        ci = i + halo
        for j in range(w):
            gc = g0c + j
            kc = gc // step
            v = kc - kc0
            fc = (gc - kc * step) * inv_step
            if fr == 0.0 and fc == 0.0:
                iters[i, j] = itn[u, v]
            lx = _target_log(block, ci, j + halo, rt)
            if lx != lx:
                continue
            # fixed-order weighted mean over the valid surrounding nodes (weights > 0)
            corners = (
                (T[u, v], (1.0 - fr) * (1.0 - fc)),
                (T[u, v + 1], (1.0 - fr) * fc),
                (T[u + 1, v], fr * (1.0 - fc)),
                (T[u + 1, v + 1], fr * fc),
            )
            num = 0.0
            den = 0.0
            for tq, wq in corners:
                if wq > 0.0 and tq == tq:
                    num += wq * tq
                    den += wq
            if den > 0.0:
                t = num if den == 1.0 else num / den
                tmin = t
                for tq, _ in corners:
                    if tq < tmin:  # NaN compares False
                        tmin = tq
                if refine > 0.0 and lx > tmin - refine:  # candidate: its own fit decides
                    t, iters[i, j] = _ring_hist_fit(
                        B, hist, ci, j + halo, rb, rg, bmin, bmax, off, bw, yv, wv, fit, nmin, a, mu, s
                    )
                    if t != t:
                        continue
                _decide(lx, t, i, j, mask, stat)


def detect(block, halo: int, origin, params: LMMParams, prep: dict, *, _iters: bool = False):
    """LMM-CFAR on one padded tile: ``(mask, stat)`` of the ``(h, w)`` core.

    ``stat = x_t / T`` (float32, > 1 where ``mask``; 0 elsewhere). ``origin`` (scene
    coordinates of ``block[0, 0]``) is used by the grid form only (global node positions).
    ``_iters=True`` also returns the per-pixel work (EM iterations + Newton steps; for tests
    and benchmarks). A CuPy ``block`` runs on its GPU (:func:`sarship.pipeline.gpu.lmm.detect`:
    the same fits, one CUDA thread per ring) and returns CuPy arrays (``_iters`` is not
    available there).
    """
    gpu = is_device_array(block)
    if not gpu:
        block = float_block(block)
    elif block.ndim != 2:
        raise ValueError(f"block must be 2-D, got shape {block.shape}")
    halo = int(halo)
    rb, rg, rt = int(params.background) // 2, int(params.guard) // 2, int(params.target) // 2
    grid = prep["method"] == "grid"
    step = int(prep.get("grid_step", grid_step(params))) if grid else 0
    need = rb + step if grid else rb
    if halo < need:
        raise ValueError(f"halo ({halo}) must be at least {_halo_rule(prep['method'])} = {need}")
    h, w = block.shape[0] - 2 * halo, block.shape[1] - 2 * halo
    if h < 0 or w < 0:
        raise ValueError(f"block {block.shape} is smaller than twice the halo ({halo})")
    n_ring = (2 * rb + 1) ** 2 - (2 * rg + 1) ** 2
    K = int(prep["components"])
    if int(prep.get("n_ring", n_ring)) != n_ring or K != int(params.components):
        raise ValueError("prep does not match the parameters")
    refine = float(prep.get("grid_refine", params.grid_refine))
    if halo > need:  # trim the extra halo (the kernels take halo == need)
        d = halo - need
        block = block[d : block.shape[0] - d, d : block.shape[1] - d]
        origin = (int(origin[0]) + d, int(origin[1]) + d)
        halo = need
    if gpu and cpu_only_fit(prep, params):
        # the GPU twin has no censored fit and no refusal rule yet (pipeline/gpu/lmm.py
        # transcribes the plain fit only): the CPU kernels decide, CuPy arrays returned
        import cupy as cp

        mask, stat = detect(cp.asnumpy(block), halo, origin, params, prep)
        return cp.asarray(mask), cp.asarray(stat)
    if gpu and params.nodata is not None:  # a declared no-data value: absent, as NaN (as on the CPU)
        from sarship.pipeline.tiling.intensity_absent import fill, present

        block = fill(block, present(block, params.nodata), np.nan)
    if gpu:  # CuPy block: the GPU twin (pipeline.gpu.lmm), one thread per ring fit
        return SPEC.twin()(block, halo, origin, rb, rg, rt, K, prep, prep["method"], step, refine)
    mask = np.zeros((h, w), dtype=np.bool_)
    stat = np.zeros((h, w), dtype=np.float32)
    iters = np.zeros((h, w), dtype=np.int32)
    if h and w:
        block = np.ascontiguousarray(block)
        fit = (
            K,
            init_z_table(K),
            int(prep["max_iter"]),
            float(prep["tol"]),
            prep.get("select", params.select) == "bic",
            prep.get("tail", params.tail) == "predictive",
            float(prep["z"]),
            float(prep["log_pfa"]),
            float(prep.get("censor", params.censor)),
            float(prep.get("censor_level", params.censor_level)),
            float(prep.get("censor_low", params.censor_low)),
            float(prep.get("refuse_weight", params.refuse_weight)),
        )
        if params.nodata is not None:  # a declared no-data value: absent, as NaN
            from sarship.pipeline.tiling.intensity_absent import fill, present

            ok = present(block, params.nodata)
            if not ok.all():
                block = np.ascontiguousarray(fill(block, ok, np.nan))
        args = (block, halo, h, w, rb, rg, rt, fit, min_usable(n_ring, K))
        if prep["method"] == "exact":
            _exact_kernel(*args, mask, stat, iters)
        elif grid:
            _grid_kernel(
                *args,
                float(prep["bin_width"]),
                step,
                refine,
                int(origin[0]) + halo,
                int(origin[1]) + halo,
                mask,
                stat,
                iters,
            )
        else:
            _fast_kernel(*args, float(prep["bin_width"]), mask, stat, iters)
    if _iters:
        return mask, stat, iters
    return mask, stat


def _halo_rule(method) -> str:
    return "background // 2 + grid_step" if method == "grid" else "background // 2"


def _halo(p: LMMParams) -> int:
    """background // 2, plus grid_step for the grid form (the rings of the nodes around the core)."""
    return int(p.background) // 2 + (grid_step(p) if p.method == "grid" else 0)


SPEC = DetectorSpec(
    name="lmm",
    summary=(
        "Lognormal-mixture CFAR: per-cell fit of a Gaussian mixture of ln x over the background "
        "ring (EM, K' <= K components by BIC, ML by Newton); threshold 1 - F(T) = PFA plus the "
        "predictive correction for the fit's finite-sample error"
    ),
    reference="Tsinghua thesis 2020 (docs/algorithms/lmm.md), chapter 3, eq 3-1, 3-4..3-7",
    params=LMMParams,
    prepare=prepare,
    detect=detect,
    input="intensity",
    needs_looks=False,
    halo_fn=_halo,
    halo_rule="background // 2 (+ grid_step for method='grid')",
    gpu="sarship.pipeline.gpu.lmm:detect",
    gpu_params=lambda p: not cpu_only_fit({}, p),  # censored/refused fits: CPU workers
)
