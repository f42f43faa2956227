r"""Sea-land segmentation by amplitude texture (``land_mask=texture``), for every detector.

Source: Liu Zeyu, Liu Bin et al., "Ship detection in GF-3 NSC-mode SAR images" (Journal of
Radars, 2017; docs/references.md#liu2017), section 2, step (2): "the local-neighbourhood
amplitude variance measures the strength of texture; a Gaussian mixture models the texture
and classifies it; the sea region of interest (ROI) is extracted". The paper gives no window,
no number of classes and no clean-up; what we chose, and why, is stated here and in
docs/algorithms/landmask.md.

Texture (the paper's "local amplitude variance")
    For amplitude ``a = sqrt(I)`` (``I``: the intensity a single-channel detector reads, the
    span of polarimetric channels, the trace of a covariance) over the ``m x m`` window
    ``W(x)`` centred on pixel ``x``, counting only present pixels (finite, ``I >= 0``)::

        n(x) = #present(W(x)),  m1(x) = sum_W a / n,  m2(x) = sum_W I / n
        V(x) = max(m2 - m1^2, 0)                       (sample variance of the amplitude)
        t(x) = log10 V(x)                              (the texture; -inf where V = 0)

    The three window sums are :func:`sarship.pipeline.tiling.boxsum.centered_box_sum` (bit-identical
    for any tiling). ``t`` is NaN where fewer than half the window is present. The mixture is
    fitted on ``t`` = log10 V rather than on V: V spans decades (bright land, calm sea) and a
    Gaussian mixture on V itself puts everything but the brightest pixels into one component.

Mixture (the paper's Gaussian mixture on the texture)
    ``p(t) = sum_k w_k N(t; mu_k, s_k^2)``, ``k = 1..K`` (default K = 2: sea and land),
    fitted by EM (Dempster, Laird and Rubin 1977) on a scene-wide sample of ``t``: the
    pixels with ``row % stride == 0`` and ``col % stride == 0``, pooled in (row, col) order,
    so the fit does not depend on the tiling (the EM itself runs on the sample's histogram,
    4096 bins: :func:`fit_mixture`). Sea is the component of smallest mean
    (lowest texture), as in the paper: the sea ROI is the low-variance class; land is the
    rest. A pixel is land candidate where ``t(x) > t*``, ``t*`` the first texture above the
    sea mean where the sea posterior falls below 1/2 (one threshold: a mixture with
    unequal variances can give the wider component both tails, and a dark pixel is never
    land).

No land (open sea)
    A 2-class mixture always finds two classes, also on open sea (calm and rough patches, or
    the ship pixels). Land is declared only where the sea component and the nearest other
    one are well separated: Ashman's D = sqrt(2) |mu_l - mu_s| / sqrt(s_l^2 + s_s^2) >= 2
    (Ashman, Bird and Zepf 1994: D > 2 is a clean separation of two Gaussians), else the
    mask is empty. The fit and the decision are recorded in ``run.json``.

Two kinds of land
    A scene that is mostly land of two kinds (town and fields) with little sea can have its two
    classes split the land, the sea hidden in the lower one (D < 2). When the ``K``-class fit is
    not separated, one more class is fitted and decided by the same rules, and accepted only if
    the classes above the sea weigh at least :data:`MIN_EXTRA_LAND_WEIGHT` (the sea hides only
    when it is a small part of the scene). On open sea the extra class splits the one speckle
    population and D stays < 2.

Clean-up (bounded morphology)
    On the candidate mask ``C``: a binary opening with an ``o x o`` square (``land_open_px``:
    removes every candidate region narrower than ``o``, e.g. the texture blob of a ship at
    sea, the ship's width plus the window), then a bounded reconstruction ``C AND dilate(open(C),
    (2o - 1) x (2o - 1))`` (candidates within ``o - 1`` pixels of the opened land are land again,
    so the coast keeps its narrow capes and piers, while blobs the opening removed whole stay
    removed unless they touch land), then a binary closing with a ``c x c`` square
    (``land_close_px``: fills sea gaps narrower than ``c`` inside land). All are min/max
    filters over bounded squares (scipy.ndimage), so the mask at a pixel depends only on the
    pixels within ``land_halo = m // 2 + 2 (o // 2) + (o - 1) + 2 (c // 2)`` of it: a tile read
    with that halo gives the whole-scene mask bit for bit. Steps that are not bounded (filling
    every hole, removing components by area, a full geodesic reconstruction) are not used.

Pure array code (NumPy, SciPy); no I/O. The FILE masks are :mod:`sarship.pipeline.land.landmask_files`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit
from scipy import ndimage

from sarship.pipeline.tiling.boxsum import centered_box_sum

#: Ashman's D at or above which the sea and land components count as separate (Ashman et al. 1994).
MIN_SEPARATION = 2.0
#: Smallest weight of the land components (together) for land to be declared: on open sea the
#: second component is the texture of the ships (about 1 % of the pixels of the real chips).
MIN_LAND_WEIGHT = 0.02
#: Most mixture classes (``land_classes`` and the extra class tried when the sea hides in one).
MAX_CLASSES = 6
#: Land weight the extra-class fit needs (module doc, "Two kinds of land"): the sea hides in a
#: land class only when it is a small part of the scene (a synthetic town-and-fields scene: with
#: 5-10 % sea, not with 20 %), while on the shared open-sea chips the extra class found up to
#: 46 % "land" (sea, sidelobes and ship; half A, OpenSARShip Cargo_x14914_y11708, D 2.02).
MIN_EXTRA_LAND_WEIGHT = 0.75
#: Largest scene-wide sample for the mixture fit (the stride grid is chosen to stay under it).
MAX_SAMPLE = 200_000
#: EM stopping rule: change of the mean log-likelihood per sample, or iterations.
EM_TOL = 1e-9
EM_MAX_ITER = 500


@dataclass(frozen=True)
class TextureConfig:
    """The texture land mask's settings (from the detector parameters ``land_*``)."""

    window: int = 15
    classes: int = 2
    open_px: int = 31
    close_px: int = 5

    def __post_init__(self):
        for name in ("window", "open_px", "close_px"):
            v = getattr(self, name)
            if v < 1 or v % 2 != 1:
                raise ValueError(f"land_{name}: must be odd and >= 1, got {v}")
        if not 2 <= self.classes <= MAX_CLASSES:
            raise ValueError(f"land_classes: must be in 2..6, got {self.classes}")

    @property
    def halo(self) -> int:
        """Pixels of context one pixel's land decision needs (texture window, then opening and closing)."""
        return self.window // 2 + 2 * (self.open_px // 2) + (self.open_px - 1) + 2 * (self.close_px // 2)


def land_halo(cfg: TextureConfig) -> int:
    return cfg.halo


def power(block: np.ndarray) -> np.ndarray:
    """Per-pixel power of what a detector reads: intensity (2-D), span of stacked complex
    channels (3-D), trace of covariance matrices (4-D); float64."""
    b = np.asarray(block)
    if b.ndim == 2:
        return b.astype(np.float64, copy=False)
    if b.ndim == 3:
        return (b.real.astype(np.float64) ** 2 + b.imag.astype(np.float64) ** 2).sum(axis=-1)
    if b.ndim == 4:
        return np.trace(b, axis1=2, axis2=3).real.astype(np.float64)
    raise ValueError(f"land mask: block must be 2-D, 3-D or 4-D, got shape {b.shape}")


def texture(block: np.ndarray, halo: int, origin: tuple[int, int], window: int) -> np.ndarray:
    """log10 of the local amplitude variance over ``window x window`` (module doc) for the
    core of a padded block (``window // 2 <= halo``); float64 ``(h, w)``, -inf where the
    variance is 0, NaN where under half the window is present."""
    return _texture_of_sums(*_window_sums(block, halo, origin, window), window)


def _window_sums(block: np.ndarray, halo: int, origin: tuple[int, int], window: int):
    """The window sums of :func:`texture`: present count, amplitude, intensity (core-sized)."""
    return _sums_of_inputs(*_window_inputs(block), halo, origin, window)


def _window_inputs(block: np.ndarray):
    """What the window sums add up: the present pixels (float64; None when every pixel is
    present), the amplitude and the intensity (absent pixels 0)."""
    I = power(block)
    ok = np.isfinite(I) & (I >= 0)
    if ok.all():
        return None, np.sqrt(I), I
    Iz = np.where(ok, I, 0.0)
    return ok.astype(np.float64), np.sqrt(Iz), Iz


def _sums_of_inputs(okf, a: np.ndarray, Iz: np.ndarray, halo: int, origin: tuple[int, int], window: int):
    if okf is None:  # every window full (the sums of ones are exact): no box sum for the count
        n = np.full((a.shape[0] - 2 * halo, a.shape[1] - 2 * halo), float(window * window))
    else:
        n = centered_box_sum(okf, window, halo, origin)
    s1 = centered_box_sum(a, window, halo, origin)
    s2 = centered_box_sum(Iz, window, halo, origin)
    return n, s1, s2


def _texture_of_sums(n: np.ndarray, s1: np.ndarray, s2: np.ndarray, window: int) -> np.ndarray:
    """:func:`texture` from its window sums, element by element (so any subset of pixels gets
    the values the whole array would)."""
    enough = n >= (window * window + 1) // 2
    with np.errstate(divide="ignore", invalid="ignore"):
        m1 = s1 / n
        v = np.maximum(s2 / n - m1 * m1, 0.0)
        t = np.log10(v)
    t[~enough] = np.nan
    return t


def sample_stride(shape: tuple[int, int], max_sample: int = MAX_SAMPLE) -> int:
    """The global grid step for the mixture's sample: at most ``max_sample`` grid pixels."""
    H, W = shape
    return max(1, math.ceil(math.sqrt(H * W / max_sample)))


@njit(nogil=True, cache=True)
def _line_sum(v, j, m, phase):
    """The window sum ``v[j] + ... + v[j + m - 1]`` formed exactly as the van Herk scan of
    :mod:`sarship.pipeline.tiling.boxsum` forms it along a row (``phase``: the global coordinate of
    ``v[j]`` modulo ``m``): the suffix of the global block holding ``j`` from its end down,
    plus the prefix of the next block up to ``j + m - 1``, each started as ``0.0 + v[.]``."""
    s = j - phase
    e = s + m - 1
    a = 0.0
    for c in range(e, j - 1, -1):
        a = a + v[c]
    if phase == 0:
        return a
    p = 0.0
    for c in range(s + m, j + m):
        p = p + v[c]
    return a + p


@njit(nogil=True, cache=True)
def _vertical_sum(h, m, phase):
    """The vertical pass of :mod:`sarship.pipeline.tiling.boxsum` on one column of horizontal sums
    ``h`` (``h[0]`` is the window's first row, ``phase`` its global row modulo ``m``): the
    block's suffix starts at ``h[e]`` itself and the next block's prefix at ``h[s + m]``."""
    s = -phase
    e = s + m - 1
    a = h[e]
    for r in range(e - 1, -1, -1):
        a = a + h[r]
    if phase == 0:
        return a
    p = h[s + m]
    for r in range(s + m + 1, m):
        p = p + h[r]
    return a + p


@njit(nogil=True, cache=True)
def _grid_sums(sub, m, g0r, g0c, ri, ci, n_out, s1_out, s2_out):
    """The window sums of :func:`texture` (present count, amplitude, intensity) at the grid
    pixels only: window rows ``ri[k] .. ri[k] + m - 1`` and columns ``ci[l] .. ci[l] + m - 1``
    of ``sub`` (``sub[0, 0]`` is global ``(g0r, g0c)``), each sum formed in the order of
    :func:`sarship.pipeline.tiling.boxsum.centered_box_sum`, so bit for bit its values. Only the
    pixels of the grid's windows are read (a fraction ``(m / stride)^2`` of the tile)."""
    ha = np.empty(m)
    hi = np.empty(m)
    rowa = np.empty(sub.shape[1])
    rowi = np.empty(sub.shape[1])
    for k in range(ri.size):
        i = ri[k]
        ph_r = (g0r + i) % m
        for l in range(ci.size):
            j = ci[l]
            ph_c = (g0c + j) % m
            cnt = 0
            for q in range(m):
                x = sub[i + q]
                for c in range(j, j + m):
                    v = np.float64(x[c])
                    if np.isfinite(v) and v >= 0.0:
                        rowi[c] = v
                        rowa[c] = np.sqrt(v)
                        cnt += 1
                    else:
                        rowi[c] = 0.0
                        rowa[c] = 0.0
                ha[q] = _line_sum(rowa, j, m, ph_c)
                hi[q] = _line_sum(rowi, j, m, ph_c)
            n_out[k, l] = cnt
            s1_out[k, l] = _vertical_sum(ha, m, ph_r)
            s2_out[k, l] = _vertical_sum(hi, m, ph_r)


def texture_sample(block: np.ndarray, halo: int, origin: tuple[int, int], cfg: TextureConfig, stride: int) -> dict:
    """A tile's part of the scene-wide sample: finite textures of the core pixels on the global
    ``stride`` grid, with their (row, col), in (row, col) order. ``block`` has ``halo >=
    window // 2``; ``origin`` is its ``[0, 0]``. The window sums are formed at the grid pixels
    alone (:func:`_grid_sums`), bit for bit the values of :func:`texture` there."""
    r = cfg.window // 2
    sub = block[halo - r : block.shape[0] - (halo - r), halo - r : block.shape[1] - (halo - r)]
    if sub.dtype not in (np.float32, np.float64) or sub.ndim != 2:
        sub = power(sub)
    r0, c0 = origin[0] + halo, origin[1] + halo
    rows = np.arange(r0, r0 + sub.shape[0] - 2 * r)
    cols = np.arange(c0, c0 + sub.shape[1] - 2 * r)
    ri = np.flatnonzero(rows % stride == 0)
    ci = np.flatnonzero(cols % stride == 0)
    n = np.empty((ri.size, ci.size))
    s1 = np.empty_like(n)
    s2 = np.empty_like(n)
    if ri.size and ci.size:
        _grid_sums(sub, cfg.window, r0 - r, c0 - r, ri.astype(np.int64), ci.astype(np.int64), n, s1, s2)
    g = _texture_of_sums(n, s1, s2, cfg.window)
    rr, cc = np.meshgrid(rows[ri], cols[ci], indexing="ij")
    keep = np.isfinite(g)
    with np.errstate(divide="ignore", invalid="ignore"):
        m = s2 / n  # the window's mean power (finite wherever the texture is)
    return {
        "t": g[keep].astype(np.float64),
        "m": m[keep].astype(np.float64),
        "rc": np.stack([rr[keep], cc[keep]], -1).astype(np.int64),
    }


def pool_samples(parts: list[dict], key: str = "t") -> np.ndarray:
    """The tiles' samples (``key``: ``t`` the texture, ``m`` the window's mean power) as one
    array in (row, col) order (independent of the tiling)."""
    return pool_sample_arrays(parts, (key,))[0]


def pool_sample_arrays(parts: list[dict], keys: tuple[str, ...]) -> list[np.ndarray]:
    """:func:`pool_samples` of several ``keys`` with one sort of the positions."""
    if not parts:
        return [np.zeros(0) for _ in keys]
    rc = np.concatenate([np.asarray(p["rc"], np.int64).reshape(-1, 2) for p in parts])
    order = np.lexsort((rc[:, 1], rc[:, 0]))
    return [np.concatenate([np.asarray(p[k], np.float64) for p in parts])[order] for k in keys]


def sea_mean(t: np.ndarray, m: np.ndarray, decision: dict) -> float | None:
    """The sea's mean power: the mean of the sample windows' mean power (``m``) over the
    windows whose texture ``t`` is sea (at or below ``t*``; every window when there is no
    land), in (row, col) order, so the same for any tiling. The clutter reference of each
    detection's ``tcr_db`` (docs/interfaces/files.md). None without a sea window."""
    t = np.asarray(t, np.float64)
    m = np.asarray(m, np.float64)
    ok = np.isfinite(t) & np.isfinite(m)
    thr = decision.get("threshold")
    if decision.get("land") and thr is not None:
        ok &= t <= thr
    return float(np.mean(m[ok])) if ok.any() else None


def _normal_logpdf(x: np.ndarray, mu: np.ndarray, var: np.ndarray) -> np.ndarray:
    return -0.5 * (np.log(2.0 * np.pi * var) + (x[:, None] - mu) ** 2 / var)


#: The EM runs on a histogram of the sample with this many equal bins over its range (weighted
#: EM on the bin centres): O(bins) per iteration whatever the sample size; the bins are
#: range / 4096 wide, under 1/20 of the component sds met on real and simulated scenes.
EM_BINS = 4096


def fit_mixture(
    t: np.ndarray, k: int = 2, tol: float = EM_TOL, max_iter: int = EM_MAX_ITER, bins: int = EM_BINS
) -> dict:
    """EM for a ``k``-component 1-D Gaussian mixture (Dempster et al. 1977; Bishop 2006 sec.
    9.2.2), run on the histogram of ``t`` (``bins`` equal bins over [min, max]; each bin's
    centre weighted by its count). Deterministic: means start at the quantiles ``(j + 1/2) / k``
    of ``t``, variances at var(t) / k^2, equal weights; variances are floored at 1e-6 var(t) and
    (bin width)^2 / 12. Stops when the mean log-likelihood per sample changes by less than
    ``tol`` or after ``max_iter`` iterations. Returns the components sorted by mean:
    ``weights``, ``means``, ``sds``, ``loglik`` (total, on the bin centres), ``iterations``,
    ``bic`` (-2 loglik + (3k - 1) ln n), ``n``."""
    x = np.asarray(t, np.float64)
    n = x.size
    if n < 10 * k:
        raise ValueError(f"land mask: {n} texture samples are too few for a {k}-class mixture")
    lo, hi = float(x.min()), float(x.max())
    if hi > lo:
        counts, edges = np.histogram(x, bins=bins, range=(lo, hi))
        keep = counts > 0
        c = (0.5 * (edges[:-1] + edges[1:]))[keep]
        cnt = counts[keep].astype(np.float64)
        width = (hi - lo) / bins
    else:
        c, cnt, width = np.array([lo]), np.array([float(n)]), 0.0
    v0 = float(x.var())
    floor = max(v0 * 1e-6, width * width / 12.0, 1e-12)
    mu = np.quantile(x, (np.arange(k) + 0.5) / k)
    var = np.full(k, max(v0 / k**2, floor))
    w = np.full(k, 1.0 / k)
    ll_old = -np.inf
    it = 0
    for it in range(1, max_iter + 1):  # noqa: B007 (the count is reported after the loop)
        lp = _normal_logpdf(c, mu, var) + np.log(w)
        lmax = lp.max(axis=1, keepdims=True)
        lse = lmax[:, 0] + np.log(np.exp(lp - lmax).sum(axis=1))
        ll = float((cnt * lse).sum())
        r = np.exp(lp - lse[:, None]) * cnt[:, None]
        nk = np.maximum(r.sum(axis=0), 1e-12)
        w = nk / n
        mu = (r * c[:, None]).sum(axis=0) / nk
        var = np.maximum((r * (c[:, None] - mu) ** 2).sum(axis=0) / nk, floor)
        if abs(ll - ll_old) <= tol * n:
            break
        ll_old = ll
    lp = _normal_logpdf(c, mu, var) + np.log(w)
    lmax = lp.max(axis=1, keepdims=True)
    ll = float((cnt * (lmax[:, 0] + np.log(np.exp(lp - lmax).sum(axis=1)))).sum())
    o = np.argsort(mu, kind="stable")
    return {
        "weights": w[o].tolist(),
        "means": mu[o].tolist(),
        "sds": np.sqrt(var[o]).tolist(),
        "loglik": ll,
        "iterations": it,
        "bic": -2.0 * ll + (3 * k - 1) * math.log(n),
        "n": int(n),
    }


def sea_posterior(t: np.ndarray, fit: dict) -> np.ndarray:
    """Posterior probability of the sea component (the first: smallest mean) at textures ``t``."""
    x = np.asarray(t, np.float64).reshape(-1)
    lp = _normal_logpdf(x, np.asarray(fit["means"]), np.asarray(fit["sds"]) ** 2) + np.log(fit["weights"])
    lmax = lp.max(axis=1, keepdims=True)
    r = np.exp(lp - lmax)
    return (r[:, 0] / r.sum(axis=1)).reshape(np.shape(t))


def ashman_d(fit: dict) -> float:
    """Ashman's D between the sea component and the next one (by mean)."""
    m, s = fit["means"], fit["sds"]
    return float(math.sqrt(2.0) * abs(m[1] - m[0]) / math.sqrt(s[0] ** 2 + s[1] ** 2))


def threshold(fit: dict) -> float | None:
    """``t*``: the smallest texture above the sea mean where the sea posterior falls below 1/2
    (bisection to 1e-12 on a bracket found on a grid up to the largest mean + 8 sds); None when
    it never does."""
    mu0 = fit["means"][0]
    hi = max(m + 8.0 * s for m, s in zip(fit["means"], fit["sds"]))
    grid = np.linspace(mu0, hi, 4097)
    post = sea_posterior(grid, fit)
    below = np.flatnonzero(post < 0.5)
    if below.size == 0:
        return None
    j = int(below[0])
    if j == 0:
        return float(mu0)
    a, b = float(grid[j - 1]), float(grid[j])
    for _ in range(200):
        mid = 0.5 * (a + b)
        if sea_posterior(np.array([mid]), fit)[0] < 0.5:
            b = mid
        else:
            a = mid
        if b - a <= 1e-12 * max(1.0, abs(b)):
            break
    return float(b)


def decide(t: np.ndarray, cfg: TextureConfig) -> dict:
    """The scene-wide land decision from the pooled texture sample ``t``: the mixture, Ashman's
    D, whether land is present and the threshold ``t*`` (JSON-serialisable, for ``run.json``).
    Too few samples (a scene almost all absent) means no land."""
    out: dict = {
        "source": "texture",
        "window": cfg.window,
        "classes": cfg.classes,
        "open_px": cfg.open_px,
        "close_px": cfg.close_px,
        "halo_px": cfg.halo,
        "sample": int(np.size(t)),
        "min_separation": MIN_SEPARATION,
        "min_land_weight": MIN_LAND_WEIGHT,
    }
    t = np.asarray(t, np.float64)
    t = t[np.isfinite(t)]
    out["sample_finite"] = int(t.size)
    if t.size < 10 * cfg.classes:
        return {**out, "land": False, "threshold": None, "reason": f"{t.size} texture samples: too few for a fit"}
    one = fit_mixture(t, 1)
    fit, d, thr, land, reason = _decide_k(t, cfg.classes)
    res = {
        **out,
        "mixture": fit,
        "bic_one_class": one["bic"],
        "ashman_d": d,
        "land": bool(land),
        "threshold": thr if land else None,
        "reason": reason,
    }
    if not land and d < MIN_SEPARATION and cfg.classes < MAX_CLASSES and t.size >= 10 * (cfg.classes + 1):
        # Two kinds of land (fields and town) with little sea: K classes split the land and the
        # sea hides in the lowest one (D < 2). One more class gives the sea its own (module doc,
        # "Two kinds of land"); on open sea the extra class splits the sea and D stays < 2.
        fit2, d2, thr2, land2, reason2 = _decide_k(t, cfg.classes + 1)
        land2 = land2 and 1.0 - fit2["weights"][0] >= MIN_EXTRA_LAND_WEIGHT
        res["extra_class"] = {
            "classes": cfg.classes + 1,
            "mixture": fit2,
            "ashman_d": d2,
            "land": bool(land2),
            "min_land_weight": MIN_EXTRA_LAND_WEIGHT,
        }
        if land2:
            res.update(
                land=True,
                threshold=thr2,
                mixture=fit2,
                ashman_d=d2,
                reason=f"{reason}; with {cfg.classes + 1} classes: {reason2}",
            )
    return res


def _decide_k(t: np.ndarray, k: int) -> tuple[dict, float, float | None, bool, str]:
    """One ``k``-class fit and its land decision: (fit, Ashman's D, ``t*``, land, reason)."""
    fit = fit_mixture(t, k)
    d = ashman_d(fit)
    thr = threshold(fit)
    wl = 1.0 - fit["weights"][0]
    land = d >= MIN_SEPARATION and wl >= MIN_LAND_WEIGHT and thr is not None
    if land:
        reason = f"sea and land components separate (Ashman's D {d:.2f} >= {MIN_SEPARATION:g}, land weight {wl:.3f})"
    elif d < MIN_SEPARATION:
        reason = f"no land: Ashman's D {d:.2f} < {MIN_SEPARATION:g} (one texture population)"
    elif wl < MIN_LAND_WEIGHT:
        reason = f"no land: land weight {wl:.4f} < {MIN_LAND_WEIGHT:g} (the bright class is ships, not land)"
    else:
        reason = "no land: the sea posterior never falls below 1/2"
    return fit, d, thr, bool(land), reason


def _square_open_close(m: np.ndarray, open_px: int, close_px: int) -> np.ndarray:
    u = m.astype(np.uint8)
    if open_px > 1:
        opened = ndimage.maximum_filter(
            ndimage.minimum_filter(u, size=open_px, mode="nearest"), size=open_px, mode="nearest"
        )
        # bounded reconstruction: candidates within open_px - 1 of the opened land are land again
        # (the coast keeps its detail; isolated blobs, removed whole by the opening, stay removed)
        near = ndimage.maximum_filter(opened, size=2 * open_px - 1, mode="nearest")
        u = u & near
    if close_px > 1:
        u = ndimage.minimum_filter(
            ndimage.maximum_filter(u, size=close_px, mode="nearest"), size=close_px, mode="nearest"
        )
    return u.astype(bool)


def classify(block: np.ndarray, halo: int, origin: tuple[int, int], cfg: TextureConfig, decision: dict) -> np.ndarray:
    """Boolean land mask of the core of a padded block (``halo >= cfg.halo``): texture above
    ``t*``, opened and closed (module doc). All False when the decision says no land."""
    h, w = block.shape[0] - 2 * halo, block.shape[1] - 2 * halo
    if not decision.get("land"):
        return np.zeros((h, w), bool)
    if halo < cfg.halo:
        raise ValueError(f"land mask needs a halo of {cfg.halo}, block has {halo}")
    e = cfg.halo - cfg.window // 2  # morphology margin around the core
    inner = halo - e  # halo of the texture's region (core + e each side)
    t = texture(block, inner, origin, cfg.window)
    with np.errstate(invalid="ignore"):
        cand = t > decision["threshold"]  # NaN (absent) and -inf are sea
    m = _square_open_close(cand, cfg.open_px, cfg.close_px)
    return m[e : e + h, e : e + w] if e else m


def apply_absent(block: np.ndarray, land_core: np.ndarray) -> np.ndarray:
    """``block`` (2-D intensity, 3-D channels or 4-D covariances) with land pixels set to NaN
    (every detector's absent-pixel marker; a copy when there is land, else ``block`` itself)."""
    if not land_core.any():
        return block
    out = np.array(block, copy=True)
    if not np.issubdtype(out.dtype, np.inexact):
        out = out.astype(np.float32)
    out[land_core] = np.nan
    return out
