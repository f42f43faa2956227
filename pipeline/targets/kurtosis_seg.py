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
and measures it with the product's moment geometry
(:func:`sarship.pipeline.targets.components.shape_from_moments`: length and width sqrt(12 lambda) of the
principal second moments of the pixel footprints in metres, heading of the main axis), the
geometry every detection carries. (Until issue 15's part 6 it measured the extent along the
principal axes: one sidelobe streak joined to the hull then counts whole; the moment length
weighs it by its pixels, as the product does.)

Product use (:func:`segment` and :func:`component_of`, run by the ``csk`` detector's
``ship_segmentation``, :func:`sarship.pipeline.detectors.csk.segment_geometry`): the
detection's chip (bounding box plus a margin) of the complex SLC is segmented and the ship is
the segmented component holding the detection's brightest segmented pixel.

What it does not do on Sentinel-1 IW SLC (bench/REALDATA.md, docs/algorithms/complex_stats.md):
t* sits at the upper edge of the sea, so a bright ship's SLC impulse response (the mainlobe's
skirt and the azimuth and range sidelobe cross, non-Gaussian outliers to the sea) is counted
as ship; on the OpenSARShip IW chips the length is over-estimated by about 5 azimuth pixels
(+72 to +80 m), where a simulated ship of independent pixels is segmented exactly. Textured
sea (K-compound with shape nu: excess kurtosis 3 / nu of the real parts) moves t* into the
sea's upper tail a little more.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from sarship.pipeline.targets.components import MOMENT_DTYPE, shape_from_moments

#: The segmentations :func:`segment` knows.
METHODS = ("kurtosis", "otsu")


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
    level = int(np.argmax(between))  # class 0: grey levels <= level
    return (level + 1) / 255.0 * hi


def segment(z, method: str = "kurtosis", part: str = "real", start: float = 0.5) -> tuple[np.ndarray, float]:
    """``(mask, t)``: the pixels of the complex chip ``z`` whose amplitude exceeds the threshold
    ``t`` of ``method`` (``"kurtosis"``: :func:`kurtosis_threshold`, ``"otsu"``:
    :func:`otsu_threshold`); absent (non-finite) pixels are never in the mask. A chip with fewer
    than 2 present pixels, or whose kurtosis never reaches 0, has an empty mask (t = inf)."""
    if method not in METHODS:
        raise ValueError(f"method must be one of {', '.join(METHODS)}, got {method!r}")
    z = np.asarray(z)
    if not np.iscomplexobj(z):
        raise ValueError("segmentation needs complex (SLC) data")
    ok = np.isfinite(z.real) & np.isfinite(z.imag)
    if int(ok.sum()) < 2:
        return np.zeros(z.shape, bool), math.inf
    t = kurtosis_threshold(z, part, start) if method == "kurtosis" else otsu_threshold(z)
    with np.errstate(invalid="ignore"):
        mask = ok & (np.abs(np.where(ok, z, 0)) > t)
    return mask, float(t)


def component_of(mask: np.ndarray, amplitude: np.ndarray, seed: np.ndarray) -> np.ndarray:
    """The 8-connected component of ``mask`` holding the brightest (``amplitude``) pixel of
    ``mask & seed`` (the detection's pixels); empty when they do not meet."""
    m = np.asarray(mask, bool)
    cand = m & np.asarray(seed, bool)
    if not cand.any():
        return np.zeros_like(m)
    a = np.where(cand, np.asarray(amplitude, np.float64), -np.inf)
    r, c = np.unravel_index(int(np.argmax(a)), a.shape)
    lab, _ = ndimage.label(m, structure=np.ones((3, 3)))
    return lab == lab[r, c]


def moment_record(mask: np.ndarray, origin: tuple[int, int] = (0, 0)) -> np.ndarray:
    """The moment record (:data:`sarship.pipeline.targets.components.MOMENT_DTYPE`, length 1) of the
    pixels of ``mask`` placed at ``origin``; only the moments and bounding box are filled."""
    rr, cc = np.nonzero(np.asarray(mask, bool))
    gr = (rr + origin[0]).astype(np.float64)
    gc = (cc + origin[1]).astype(np.float64)
    out = np.zeros(1, MOMENT_DTYPE)
    out["n"] = rr.size
    out["sr"], out["sc"] = gr.sum(), gc.sum()
    out["srr"], out["scc"], out["src"] = (gr * gr).sum(), (gc * gc).sum(), (gr * gc).sum()
    if rr.size:
        out["r0"], out["c0"] = int(gr.min()), int(gc.min())
        out["r1"], out["c1"] = int(gr.max()) + 1, int(gc.max()) + 1
    return out


@dataclass(frozen=True)
class ShipGeometry:
    pixels: int
    length_m: float
    width_m: float
    heading_deg: float  # main axis as the product's heading_deg (shape_from_moments), in [0, 180)


def ship_geometry(
    mask: np.ndarray, spacing: tuple[float, float], centre: tuple[float, float] | None = None
) -> ShipGeometry | None:
    """The 8-connected component of ``mask`` nearest ``centre`` (default: the chip centre),
    measured in metres with ``spacing`` = (row, column) pixel sizes by the product's moment
    geometry (:func:`sarship.pipeline.targets.components.shape_from_moments`); None without pixels."""
    m = np.asarray(mask, bool)
    lab, n = ndimage.label(m, structure=np.ones((3, 3)))
    if n == 0:
        return None
    cy, cx = ((m.shape[0] - 1) / 2, (m.shape[1] - 1) / 2) if centre is None else centre
    yy, xx = np.nonzero(lab)
    k = int(np.argmin(np.hypot(yy - cy, xx - cx)))
    comp = lab == lab[yy[k], xx[k]]
    g = shape_from_moments(moment_record(comp)[0], (float(spacing[0]), float(spacing[1])))
    return ShipGeometry(int(comp.sum()), float(g["length_m"]), float(g["width_m"]), float(g["heading_deg"]))
