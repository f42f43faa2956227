"""Equivalent number of looks (ENL) of intensity data by the method of log-cumulants.

Method (MoLC; Nicolas 2002, Tison et al. 2004)
----------------------------------------------
For fully developed speckle an L-look intensity ``I`` is gamma distributed with shape ``L``;
then ``ln I`` has second cumulant (variance)

    k2 = Var[ln I] = psi1(L)            (psi1 = trigamma),

which does not depend on the mean reflectivity. So ``L = psi1^{-1}(k2)``.

:func:`estimate_looks` computes the sample variance of ``ln I`` (ddof = 1, an unbiased
estimate of ``k2``) in each non-overlapping ``block x block`` window of every array it is
given, takes the **median** over the windows, corrects the median for its small-sample
bias (below) and inverts trigamma with a bracketed root finder (:func:`scipy.optimize.brentq`).

Robustness. Bright targets, land/sea edges, texture and a few outliers *raise* the log
variance of the windows they touch and leave the other windows alone; the median over
windows ignores them as long as they touch fewer than half of the windows. (With 2 % of
the pixels in compact bright blobs about a third of 32 x 32 windows are touched, which moves
the estimate by a few per cent; see ``tests/pipeline/test_looks.py``.) Pixels that are zero,
negative or not finite (no-data borders, masked land) are ignored; windows with fewer than
a quarter of their pixels valid are dropped. Windows at the right/bottom border that are
only partly inside an array count the same way.

Small-sample bias. The median of the window variances is not their mean (the sampling
distribution of a variance is right-skewed), so the raw median under-estimates ``k2`` by
about 1 % for 32 x 32 windows and single-look data (over-estimating ``L``). The sample
variance of ``n`` values is modelled as gamma distributed with the exact mean ``psi1(L)``
and the exact variance ``psi1(L)^2 (2/(n-1) + kappa/n)``, where
``kappa = psi3(L) / psi1(L)^2`` is the excess kurtosis of ``ln I``; its median is then
``psi1(L) * m(L, n)`` with ``m = gammaincinv(a, 1/2) / a``, ``a = 1 / (2/(n-1) + kappa/n)``.
The estimate is the root in ``L`` of ``psi1(L) m(L, n) = median``, with ``n`` the median
count of valid pixels per window. Checked by simulation (``tests/pipeline/test_looks.py``): on
clean gamma clutter L in {1, 2, 4, 8} the residual bias is below 1 %.

Limits. Textured clutter (K or G0 distributed sea) has ``k2 = psi1(L) + psi1(nu)``: a low
texture parameter ``nu`` makes the estimate *lower* than the true number of looks (which is
the conservative side for a CFAR threshold). Quantised 8-bit data (JPEG chips) and
contrast-stretched products do not follow the gamma law and give only an indicative value.
The result is clipped to [MIN_LOOKS, MAX_LOOKS].
"""

from __future__ import annotations

from collections.abc import Callable, Iterable

import numpy as np

from sarship.pipeline.errors import InputError

#: Bounds of the returned estimate (the root finder's bracket).
MIN_LOOKS = 0.05
MAX_LOOKS = 1.0e4


def _trigamma(x):
    from scipy.special import polygamma

    return polygamma(1, x)


def _median_factor(L: float, n: float) -> float:
    """Median / mean of the sample variance (ddof=1) of ``n`` values of ln(Gamma(L))."""
    from scipy.special import gammaincinv, polygamma

    p1 = float(polygamma(1, L))
    kappa = float(polygamma(3, L)) / (p1 * p1)  # excess kurtosis of ln I
    relvar = 2.0 / max(n - 1.0, 1.0) + kappa / n
    a = 1.0 / relvar
    return float(gammaincinv(a, 0.5)) / a


def block_log_variances(x: np.ndarray, block: int = 32) -> tuple[np.ndarray, np.ndarray]:
    """Sample variance of ``ln x`` (ddof=1) and valid-pixel count in each window.

    Windows tile ``x`` from its top-left corner; windows with fewer than
    ``max(8, block*block // 4)`` valid (positive, finite) pixels are dropped.
    """
    x = np.asarray(x)
    if x.ndim != 2:
        raise InputError(f"looks estimation needs 2-D intensity blocks, got shape {x.shape}")
    if np.iscomplexobj(x):
        raise InputError("looks estimation needs real intensity, got complex values")
    H, W = x.shape
    if H == 0 or W == 0:
        return np.empty(0), np.empty(0)
    nby, nbx = -(-H // block), -(-W // block)
    xf = np.asarray(x, dtype=np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        valid = np.isfinite(xf) & (xf > 0)
        lx = np.where(valid, np.log(np.where(valid, xf, 1.0)), 0.0)
    pad = ((0, nby * block - H), (0, nbx * block - W))
    if pad[0][1] or pad[1][1]:
        lx = np.pad(lx, pad)
        valid = np.pad(valid, pad)
    lx = lx.reshape(nby, block, nbx, block)
    vm = valid.reshape(nby, block, nbx, block)
    n = vm.sum(axis=(1, 3)).astype(np.float64)
    s1 = lx.sum(axis=(1, 3))
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = s1 / n
        d = np.where(vm, lx - mean[:, None, :, None], 0.0)
        var = (d * d).sum(axis=(1, 3)) / (n - 1.0)
    keep = n >= max(8, (block * block) // 4)
    return var[keep], n[keep]


def estimate_looks(intensity_blocks: Iterable[np.ndarray], block: int = 32) -> float:
    """Equivalent number of looks of intensity data (MoLC, median over windows; see module doc).

    ``intensity_blocks`` is any iterable of 2-D intensity arrays (e.g. a bounded sample of
    scene tiles); each is cut into non-overlapping ``block x block`` windows. Raises
    :class:`InputError` when no window has enough positive pixels (e.g. all-zero data) or
    when the data are constant (no speckle).
    """
    from scipy.optimize import brentq

    if isinstance(intensity_blocks, np.ndarray):
        intensity_blocks = [intensity_blocks]
    block = int(block)
    if block < 4:
        raise InputError(f"looks estimation: block must be >= 4 pixels, got {block}")
    vs, ns = [], []
    for b in intensity_blocks:
        v, n = block_log_variances(b, block)
        vs.append(v)
        ns.append(n)
    v = np.concatenate(vs) if vs else np.empty(0)
    n = np.concatenate(ns) if ns else np.empty(0)
    ok = np.isfinite(v)
    v, n = v[ok], n[ok]
    if v.size == 0:
        raise InputError(
            "cannot estimate the number of looks: no window has enough positive pixels (all zero or no data?)"
        )
    med = float(np.median(v))
    n_eff = float(np.median(n))
    if not med > 1e-12:  # float rounding leaves ~1e-30 on constant data
        raise InputError("cannot estimate the number of looks: the data are constant (no speckle)")

    def f(L: float) -> float:
        return float(_trigamma(L)) * _median_factor(L, n_eff) - med

    lo, hi = MIN_LOOKS, MAX_LOOKS
    if f(lo) <= 0:  # more variable than MIN_LOOKS-look speckle
        return lo
    if f(hi) >= 0:  # smoother than MAX_LOOKS looks
        return hi
    return float(brentq(f, lo, hi, xtol=1e-6, rtol=1e-8))


def estimate_scene_looks(
    read: Callable[[int, int, int, int], np.ndarray], shape: tuple[int, int], side: int = 512, grid: int = 4
) -> float:
    """:func:`estimate_looks` on a ``grid`` x ``grid`` sample of ``side`` x ``side`` blocks
    spread evenly over a scene of ``shape``, read with ``read(r0, r1, c0, c1)`` (intensity):
    16 blocks of 512^2 by default, whatever the scene's size, so the estimate costs the same
    on a chip and on a full product."""
    H, W = shape
    blocks = []
    for r in np.linspace(0, max(H - side, 0), grid).astype(int):
        for c in np.linspace(0, max(W - side, 0), grid).astype(int):
            blocks.append(read(int(r), min(int(r) + side, H), int(c), min(int(c) + side, W)))
    return float(estimate_looks(blocks))
