"""Iterative kurtosis segmentation of a complex ship chip (seed 004 section 5.2, fig 16-17) and Otsu.

Source: Leng et al. 2020 (docs/references.md#leng2020), section 5.2, after Leng, Ji & Zhou 2018
(its ref. 75). A chip holds a ship and sea whose real (and imaginary) parts are zero-mean
Gaussian. Take the pixels whose amplitude is below a threshold t: for small t (the paper starts
at 0.5 x the mean amplitude) their real parts are spread like the flat top of a Gaussian
(excess kurtosis near -1.2, a uniform law's); as t grows, more of the Gaussian's tails enter
and the excess kurtosis climbs to 0, reached when every sea pixel is in; ship pixels, far
brighter and heavier-tailed, would push it above 0. The t* where the excess kurtosis first
reaches 0 separates sea (below) from ship (above).

Implementation: the pixels sorted by amplitude, the excess kurtosis of the zero-mean real parts
(``part="real"``; "imag", or "both" pooled) of every prefix from running sums,
K_k = k sum x^4 / (sum x^2)^2 - 3 (zero mean: the paper's assumption for SLC data), so every
candidate threshold (each pixel's amplitude from 0.5 x mean up) is tried exactly, in
O(N log N). t* is the amplitude of the first prefix with K_k >= 0; a chip whose prefixes never
reach 0 has no outlier population: t* = inf (no ship pixel).

Otsu (the paper's comparison, fig 17): on the 8-bit image mapped linearly from the amplitude
(0 to its 99.5th percentile, clipped), the threshold maximising the between-class variance of
the 256-bin histogram (Otsu 1979, docs/references.md#otsu1979).

:func:`ship_geometry` keeps the 8-connected component of the ship pixels nearest the chip centre
and measures it in metres (pixel spacing per axis): length and width are the extents along the
principal axes of the pixel coordinates plus one pixel's footprint along each axis.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage


def _values(z: np.ndarray, part: str) -> tuple[np.ndarray, np.ndarray]:
    z = np.asarray(z)
    if not np.iscomplexobj(z):
        raise ValueError("kurtosis segmentation needs complex (SLC) data: the real parts of amplitude are not Gaussian")
    ok = np.isfinite(z.real) & np.isfinite(z.imag)
    zz = z[ok].astype(np.complex128)
    a = np.abs(zz)
    if part == "real":
        return a, zz.real[:, None]
    if part == "imag":
        return a, zz.imag[:, None]
    if part == "both":
        return a, np.stack([zz.real, zz.imag], axis=1)
    raise ValueError(f"part must be 'real', 'imag' or 'both', got {part!r}")


def kurtosis_curve(z, part: str = "real") -> tuple[np.ndarray, np.ndarray]:
    """``(t, K)``: every pixel amplitude in increasing order and the excess kurtosis of the
    zero-mean ``part`` of the pixels at or below it (fig 16's curve)."""
    a, x = _values(z, part)
    order = np.argsort(a, kind="stable")
    t = a[order]
    x = x[order]
    s2 = np.cumsum((x * x).sum(axis=1))
    s4 = np.cumsum((x**4).sum(axis=1))
    n = np.arange(1, t.size + 1) * x.shape[1]
    with np.errstate(divide="ignore", invalid="ignore"):
        k = n * s4 / (s2 * s2) - 3.0
    return t, k


def kurtosis_threshold(z, part: str = "real", start: float = 0.5, min_pixels: int = 30) -> float:
    """t*: the smallest amplitude >= ``start`` x mean amplitude at which the excess kurtosis of
    the pixels at or below it reaches 0 (section 5.2); inf when it never does."""
    if not start > 0:
        raise ValueError(f"start must be positive, got {start}")
    t, k = kurtosis_curve(z, part)
    if t.size == 0:
        raise ValueError("chip has no finite pixel")
    idx = np.arange(t.size)
    cand = (t >= start * float(t.mean())) & (idx + 1 >= min_pixels) & (k >= 0.0)
    hit = np.flatnonzero(cand)
    return float(t[hit[0]]) if hit.size else math.inf


def otsu_threshold(z, clip_percentile: float = 99.5) -> float:
    """Otsu's threshold on the 8-bit stretch of the amplitude, returned as an amplitude."""
    a = np.abs(np.asarray(z))
    a = a[np.isfinite(a)]
    hi = float(np.percentile(a, clip_percentile))
    if not hi > 0:
        return math.inf
    g = np.clip(np.floor(a / hi * 255.0), 0, 255).astype(np.int64)
    hist = np.bincount(g, minlength=256).astype(np.float64)
    p = hist / hist.sum()
    w0 = np.cumsum(p)
    mu = np.cumsum(p * np.arange(256))
    with np.errstate(divide="ignore", invalid="ignore"):
        between = (mu[-1] * w0 - mu) ** 2 / (w0 * (1.0 - w0))
    between[~np.isfinite(between)] = -1.0
    level = int(np.argmax(between))          # class 0: grey levels <= level
    return (level + 1) / 255.0 * hi


@dataclass(frozen=True)
class ShipGeometry:
    pixels: int
    length_m: float
    width_m: float
    heading_deg: float  # principal axis, degrees from the row (azimuth) axis, in [0, 180)


def ship_geometry(mask: np.ndarray, spacing: tuple[float, float], centre: tuple[float, float] | None = None
                  ) -> ShipGeometry | None:
    """The 8-connected component of ``mask`` nearest ``centre`` (default: the chip centre),
    measured in metres with ``spacing`` = (row, column) pixel sizes; None without pixels."""
    m = np.asarray(mask, bool)
    lab, n = ndimage.label(m, structure=np.ones((3, 3)))
    if n == 0:
        return None
    cy, cx = ((m.shape[0] - 1) / 2, (m.shape[1] - 1) / 2) if centre is None else centre
    yy, xx = np.nonzero(lab)
    d = np.hypot(yy - cy, xx - cx)
    comp = lab == lab[yy[np.argmin(d)], xx[np.argmin(d)]]
    yy, xx = np.nonzero(comp)
    sy, sx = float(spacing[0]), float(spacing[1])
    P = np.stack([yy * sy, xx * sx], axis=1)
    if len(P) == 1:
        return ShipGeometry(1, max(sy, sx), min(sy, sx), 0.0)
    w, V = np.linalg.eigh(np.cov(P.T))
    u = V[:, 1]                      # main axis
    v = V[:, 0]
    pu, pv = P @ u, P @ v
    foot_u = abs(u[0]) * sy + abs(u[1]) * sx
    foot_v = abs(v[0]) * sy + abs(v[1]) * sx
    heading = math.degrees(math.atan2(u[1], u[0])) % 180.0
    return ShipGeometry(int(comp.sum()), float(pu.max() - pu.min() + foot_u), float(pv.max() - pv.min() + foot_v),
                        heading)
