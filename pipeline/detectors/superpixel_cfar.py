"""``superpixel_cfar``: superpixel CFAR for high-resolution SAR (seed 002).

Zhang, Lu, Xiang, Yuan 2023, "An improved superpixel-based CFAR method for high-resolution SAR
image ship target detection", Journal of Radars 12(1) (docs/references.md, ``zhang2023``).
Equation numbers are the paper's; docs/algorithms/superpixel_cfar.md states every choice.

1. Superpixels (section 3.1, eq 7-10): bounded DBSCAN-style growth from a global seed grid and
   the merge of small superpixels (:mod:`sarship.pipeline.image.superpixels`).
2. Shadow removal (section 3.2): superpixels whose mean intensity is below ``shadow_ratio``
   times the scene's median superpixel mean are shadow: neither tested nor clutter.
3. K-means (k = 2) on the superpixel means in dB (section 3.3, Table 1 step 1), scene-wide:
   the brighter class is the potential-target set, the other the background. A scene pass
   histograms the means of the superpixels anchored in each tile's core (fixed log bins:
   integer counts, tiling-invariant); ``reduce`` takes the exact optimal 2-means split of the
   binned means (no initialisation to depend on). The split must separate the class
   centroids by ``min_separation_db`` (an addition: K-means always splits, and on a scene of
   sea alone, or of sea with a few small ships, it puts half the sea in the target class);
   otherwise the potential targets are the superpixels ``min_separation_db`` above the
   centroid of all superpixels (in dB).
4. Clutter superpixels per target superpixel (Table 1): :func:`superpixels.select_clutter`.
5. Rayleigh mixture (M_a = ``components``, eq 3-6) fitted by EM on the clutter pixels' amplitudes
   and ``T_cfar`` from ``1 - F(T_cfar) = pfa`` (eq 14) on a proven bracket
   (:mod:`sarship.pipeline.stats.rayleigh_mixture`): one threshold per target superpixel.
6. Local contrast (eq 11-13): ``C_local(x) = exp(-CoV(x) / kappa) * sum_{SP_n in S_clutter}
   Omega(SP_m, SP_n)``, CoV of the amplitudes over ``cov_window`` x ``cov_window``; decision
   (eq 16) ``A(x) C_local(x) > T_cfar`` with ``A = sqrt(I)`` the amplitude, the variable the
   Rayleigh mixture models. ``contrast="off"`` is eq 15 (``A(x) > T_cfar``).
7. Superpixel decision (section 3.4): a target superpixel whose fraction of detected present
   pixels exceeds ``fraction`` is target whole (``decision="pixel"``: eq 16's pixels; ``decision="boundaries"``: the superpixel boundaries
   as the mask, a debugging view for the mask quicklook).
8. Additions (issue 31). **Small ships** (``point_pfa``): a ship of a few pixels raises its
   superpixel's mean by a dB or two, so step 3 never tests it and step 7's fraction would drop
   it; in a background superpixel the pixels above ``mean x point_level(point_pfa, L)`` (the
   gamma law of the superpixel's mean, L looks) are detected too (:func:`point_targets`).
   **Largest ship** (``max_ship_m2`` where the pixel spacing is known, ``max_ship_px`` where it
   is not; :func:`for_scene` sets the shared ``max_area_px``): where land escapes the land mask
   (harbours), step 7 marks its edge superpixels and every ship moored against it as one
   connected detection; the size rule drops such a detection after the tiles are merged.

Tiling. Every superpixel is a function of the pixels within a bounded distance of its anchor
(``superpixels.context_px``) and extends at most ``superpixels.extent_px`` from it; clutter
superpixels are taken only with anchors within ``clutter_radius`` of the target's anchor. So
``halo = extent + clutter_radius + context = 10 reach + 5 + clutter_radius`` pixels make every
tile see, bit for bit, each superpixel that touches its core, its clutter set and their
pixels; each tile decides those superpixels and writes its core (a superpixel across tiles is
decided identically in each, in the same order of the same float operations), and the scene
pass counts a superpixel in the one tile whose core holds its anchor.

Absent pixels (NaN, inf, negative) belong to no superpixel, enter no statistic and are never
detected. The superpixel label image (global ids) of a block's core: :func:`superpixel_labels`.

GPU: a CuPy block runs steps 1-5 (:func:`host_steps`) on a host copy and steps 6-7 on the
device (:mod:`sarship.pipeline.gpu.superpixel_cfar`); masks equal the CPU's bit for bit.
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np
from numba import njit
from pydantic import Field, model_validator

from sarship.pipeline.detectors.base import DetectorParams, DetectorSpec, area_px, float_block, with_defaults
from sarship.pipeline.gpu import is_device_array, to_host
from sarship.pipeline.image import superpixels as spx
from sarship.pipeline.stats.rayleigh_mixture import BIN_WIDTH, fit_binned, threshold_intensity

#: Fixed histogram of log10(superpixel mean) for the scene-wide K-means and shadow rule.
HIST_LO = -40.0
HIST_PER_DECADE = 128
HIST_BINS = 80 * HIST_PER_DECADE
#: ``max_ship_px``'s default: chosen on half A of the real chips (bench/REALDATA.md, "Issue 31").
MAX_SHIP_PX = 5000
#: ``max_ship_m2``'s default: chosen on half A of the real chips (bench/REALDATA.md, "Issue 31").
MAX_SHIP_M2 = 300000.0
#: ``point_pfa``'s default: chosen on half A of the real chips (bench/REALDATA.md, "Issue 31").
POINT_PFA = 1e-7


class SuperpixelCFARParams(
    with_defaults(
        DetectorParams, "SuperpixelCFARDefaults", pfa=1e-3, merge_px=4, land_mask="texture", min_contrast_db=7.0
    )
):
    """Parameters of ``superpixel_cfar`` (module docstring; docs/algorithms/superpixel_cfar.md).

    The paper's defaults: M_a = 3, CoV over 7x7, kappa 0.4, at most 10 clutter superpixels,
    detected fraction 0.7. ``target``/``guard``/``background`` are unused (no windows).
    ``land_mask`` texture: the contrast of eq 11 does not keep coastal land out (its sum of
    dissimilarities is large for land too); on the HRSID chips the land mask took the pixel FPR
    from 1.63 % to 0.15 % (bench/REALDATA.md).
    """

    spacing: int = Field(
        12, ge=4, le=64, description="seed grid spacing in pixels (superpixels of about spacing^2 pixels)"
    )
    reach: int = Field(
        8,
        ge=2,
        le=128,
        description="a superpixel grows at most this many pixels from its seed (Chebyshev); at least spacing / 2",
    )
    eps: float = Field(4.0, gt=0.0, le=1e6, description="growth threshold on the pixel dissimilarity (eq 7-8)")
    min_size: int = Field(
        32,
        ge=1,
        le=10000,
        description="superpixels smaller than this merge into their least dissimilar neighbour (eq 9-10)",
    )
    shadow_ratio: float = Field(
        0.05,
        ge=0.0,
        lt=1.0,
        description="shadow superpixels: mean below this times the scene's median superpixel mean (0: off)",
    )
    kmeans: bool = Field(
        True,
        description="K-means (k = 2) on superpixel means: test only the brighter class; "
        "false: test every superpixel (diagnostics, calibration)",
    )
    min_separation_db: float = Field(
        6.0,
        ge=0.0,
        le=100.0,
        description="the K-means split is kept when its class centroids are this many dB "
        "apart (0: always, as the paper); otherwise the potential targets are "
        "the superpixels this many dB above the centroid of all",
    )
    th_clu: float = Field(
        4.0,
        ge=0.0,
        le=1e9,
        description="Table 1: adjacent background superpixels with dissimilarity (eq 9) above this are clutter",
    )
    tl_clu: float = Field(
        2.0, ge=0.0, le=1e9, description="Table 1: clutter grows through neighbours with dissimilarity below this"
    )
    max_clutter: int = Field(10, ge=1, le=100, description="Table 1: most clutter superpixels per target")
    clutter_radius: int = Field(
        36,
        ge=1,
        le=512,
        description="clutter superpixels' anchors lie within this many pixels (Chebyshev) of the target's",
    )
    rings: int = Field(
        1,
        ge=0,
        le=32,
        description="Table 1 for a target superpixel without background "
        "neighbours: look for them through at most this many rings "
        "of target superpixels (0: adjacent only, as the paper)",
    )
    components: int = Field(3, ge=1, le=8, description="Rayleigh components M_a of the clutter mixture (eq 3)")
    em_iter: int = Field(50, ge=1, le=10000, description="EM iterations at most (eq 5-6 as M-step)")
    contrast: Literal["paper", "off"] = Field(
        "paper", description="local contrast of eq 11-13 in the decision (eq 16), or off (eq 15)"
    )
    kappa: float = Field(0.4, gt=0.0, le=100.0, description="spatial factor kappa of eq 12")
    cov_window: int = Field(7, ge=3, le=31, description="CoV window side of eq 13 (odd, pixels)")
    fraction: float = Field(
        0.7,
        ge=0.0,
        lt=1.0,
        description="a target superpixel whose detected fraction exceeds this is target whole (section 3.4)",
    )
    point_pfa: float | None = Field(
        POINT_PFA,
        ge=1e-15,
        lt=0.5,
        description="small ships (a few pixels: they raise their superpixel's mean too little to make it a "
        "potential target): in a background superpixel, a pixel whose intensity exceeds the (1 - "
        "point_pfa) quantile of the gamma law (L looks) of the superpixel's mean is detected (chosen on "
        "half A of the real chips; none: off, the paper)",
    )
    max_ship_m2: float | None = Field(
        MAX_SHIP_M2,
        gt=0.0,
        le=1e9,
        description="largest detection kept where the scene's pixel spacing is known, in m^2 (the superpixel "
        "decision marks whole superpixels, so a ship's detection is larger than its hull: chosen on "
        "half A of the real chips); a larger one is land, a quay or a structure with the ships it "
        "swallowed; sets max_area_px when that is not given (none: no limit)",
    )
    max_ship_px: int | None = Field(
        MAX_SHIP_PX,
        ge=1,
        le=10**9,
        description="largest ship kept where the pixel spacing is unknown, in pixels (chosen on half A of the "
        "real chips, bench/REALDATA.md); sets max_area_px when that is not given (none: no limit)",
    )
    decision: Literal["superpixel", "pixel", "boundaries"] = Field(
        "superpixel",
        description="superpixel: step 7's decision; pixel: eq 16's pixel mask; boundaries: the "
        "mask is the superpixel boundaries (to view the segmentation in the mask "
        "quicklook; its detections mean nothing)",
    )

    @model_validator(mode="after")
    def _own(self):
        if self.cov_window % 2 == 0:
            raise ValueError(f"cov_window must be odd, got {self.cov_window}")
        if 2 * self.reach < self.spacing:
            raise ValueError(f"reach ({self.reach}) must be at least spacing / 2 ({self.spacing / 2:g})")
        if self.reach > 2 * self.spacing:
            raise ValueError(f"reach ({self.reach}) must be at most 2 * spacing ({2 * self.spacing})")
        if self.tl_clu > self.th_clu:
            raise ValueError(f"tl_clu ({self.tl_clu}) must not exceed th_clu ({self.th_clu})")
        return self


def largest_ship_px(p: SuperpixelCFARParams, spacing) -> int | None:
    """The largest detection kept, in pixels: ``max_area_px`` when given; else ``max_ship_m2`` as
    pixels (:func:`~sarship.pipeline.detectors.base.area_px`) where the ground ``spacing``
    (azimuth, range metres) is known, ``max_ship_px`` where it is not (None: no limit)."""
    if "max_area_px" in p.model_fields_set or p.max_area_px is not None:
        return p.max_area_px
    if spacing is not None:
        return None if p.max_ship_m2 is None else area_px(p.max_ship_m2, spacing)
    return p.max_ship_px


def for_scene(p: SuperpixelCFARParams, shape, spacing=None) -> tuple[SuperpixelCFARParams, list[str]]:
    """``DetectorSpec.for_scene``: ``max_area_px`` from :func:`largest_ship_px` (the shared size
    rule then drops larger merged detections, whatever the tiling, on CPU and GPU alike)."""
    cap = largest_ship_px(p, spacing)
    if cap == p.max_area_px:
        return p, []
    if p.min_area_px is not None and cap < p.min_area_px:
        cap = p.min_area_px
    return p.model_copy(update={"max_area_px": int(cap)}), []


def halo(p: SuperpixelCFARParams) -> int:
    """extent + clutter_radius + context (module docstring) = 10 reach + 5 + clutter_radius."""
    return spx.extent_px(p.reach) + int(p.clutter_radius) + spx.context_px(p.reach)


def prepare(p: SuperpixelCFARParams) -> dict:
    return {"looks": float(p.looks if p.looks is not None else 1.0), "halo": halo(p)}


def hist_bin(mean: np.ndarray) -> np.ndarray:
    """Bin of log10(mean) in the fixed scene histogram (0 for a zero mean)."""
    with np.errstate(divide="ignore"):
        b = np.floor((np.log10(np.asarray(mean, np.float64)) - HIST_LO) * HIST_PER_DECADE)
    b = np.where(np.isfinite(b), b, 0)
    return np.clip(b, 0, HIST_BINS - 1).astype(np.int64)


def _present(x: np.ndarray) -> np.ndarray:
    return np.isfinite(x) & (x >= 0)


def _segment(x, ok, origin, p: SuperpixelCFARParams, looks: float) -> spx.Superpixels:
    return spx.segment(x, ok, origin, p.spacing, p.reach, p.eps, looks, p.min_size)


def _looks(p, prep) -> float:
    return float(prep.get("looks", p.looks if p.looks is not None else 1.0))


def _check(block, halo_px, p):
    x = float_block(to_host(block))  # a CuPy block: the host steps run on a host copy
    if int(halo_px) < halo(p):
        raise ValueError(
            f"superpixel_cfar needs a halo of {halo(p)} (10 reach + 5 + clutter_radius), block has {halo_px}"
        )
    return x


def scene_pass(block, halo_px, origin, p: SuperpixelCFARParams, prep: dict) -> dict:
    """Histogram (fixed log10 bins, integer counts) of the means of the superpixels anchored in the core."""
    x = _check(block, halo_px, p)
    sp = _segment(x, _present(x), origin, p, _looks(p, prep))
    return _histogram(sp, x.shape, int(halo_px), origin)


def _histogram(sp: spx.Superpixels, shape, hp: int, origin) -> dict:
    r0, c0 = origin[0] + hp, origin[1] + hp
    h, w = shape[0] - 2 * hp, shape[1] - 2 * hp
    a = sp.anchor
    own = (sp.size > 0) & (a[:, 0] >= r0) & (a[:, 0] < r0 + h) & (a[:, 1] >= c0) & (a[:, 1] < c0 + w)
    counts = np.bincount(hist_bin(sp.mean[own]), minlength=HIST_BINS).astype(np.int64)
    return {"counts": counts}


def split_bins(counts: np.ndarray, shadow_ratio: float) -> tuple[int, int, float]:
    """``(shadow_bin, target_bin, separation_db)``: superpixels in bins below ``shadow_bin`` are
    shadow; the exact optimal 2-means split (least within-class sum of squares of the bin
    centres in dB) of the others puts bins from ``target_bin`` on in the target class
    (``HIST_BINS``: none); ``separation_db`` is the distance of the two class centroids."""
    c = np.asarray(counts, np.float64)
    tot = c.sum()
    if tot == 0:
        return 0, HIST_BINS, 0.0
    centre = 10.0 ** (HIST_LO + (np.arange(HIST_BINS) + 0.5) / HIST_PER_DECADE)
    cum = np.cumsum(c)
    med = centre[int(np.searchsorted(cum, 0.5 * tot))]
    sh = int(hist_bin(np.array([shadow_ratio * med]))[0]) if shadow_ratio > 0 else 0
    c = c.copy()
    c[:sh] = 0
    nz = np.flatnonzero(c)
    if nz.size < 2:
        return sh, HIST_BINS, 0.0
    v = (HIST_LO + (nz + 0.5) / HIST_PER_DECADE) * 10.0  # bin centres in dB
    n = c[nz]
    cn = np.cumsum(n)
    cs = np.cumsum(n * v)
    nl, sl = cn[:-1], cs[:-1]
    nr, sr = cn[-1] - nl, cs[-1] - sl
    gain = sl * sl / nl + sr * sr / nr  # total SS - within SS; maximised by the best split
    k = int(np.argmax(gain))
    return sh, int(nz[k + 1]), float(sr[k] / nr[k] - sl[k] / nl[k])


def above_centroid(counts: np.ndarray, shadow_bin: int, db: float) -> int:
    """First bin whose centre is ``db`` dB above the count-weighted centroid (dB) of the bins from
    ``shadow_bin`` on (``HIST_BINS`` when none is)."""
    c = np.asarray(counts, np.float64).copy()
    c[:shadow_bin] = 0
    if c.sum() == 0:
        return HIST_BINS
    centre_db = (HIST_LO + (np.arange(HIST_BINS) + 0.5) / HIST_PER_DECADE) * 10.0
    mu = float(np.sum(c * centre_db) / c.sum())
    above = np.flatnonzero(centre_db >= mu + db)
    return int(above[0]) if above.size else HIST_BINS


def reduce(parts: list[dict], p: SuperpixelCFARParams, prep: dict) -> dict:
    counts = np.sum([q["counts"] for q in parts], axis=0).astype(np.int64)
    sh, tb, sep = split_bins(counts, p.shadow_ratio)
    rule = "kmeans"
    if p.kmeans and sep < p.min_separation_db:
        # the two classes are one population (a scene of sea, a few small ships): potential targets
        # are the superpixels min_separation_db above the centroid of all (non-shadow) superpixels
        tb, rule = above_centroid(counts, sh, p.min_separation_db), "centroid + min_separation_db"
    edge = lambda b: float(10.0 ** (HIST_LO + b / HIST_PER_DECADE)) if b < HIST_BINS else None  # noqa: E731
    return {
        "superpixels": int(counts.sum()),
        "shadow_bin": sh,
        "target_bin": tb,
        "shadow_below": edge(sh) if sh > 0 else 0.0,
        "target_from": edge(tb),
        "shadow_count": int(counts[:sh].sum()),
        "target_count": int(counts[tb:].sum()),
        "separation_db": sep,
        "target_rule": rule,
    }


def scene_prep(x: np.ndarray, p: SuperpixelCFARParams, prep: dict | None = None, tile: int | None = None) -> dict:
    """``prep`` with the scene pass run on a whole scene ``x`` (tiles of ``tile`` px, default one):
    the tests' and benches' stand-in for the job's scene pass."""
    from sarship.pipeline.tiling.windows import mirror_pad

    prep = dict(prepare(p) if prep is None else prep)
    h = halo(p)
    P = mirror_pad(x, h)
    H, W = x.shape
    t = tile or max(H, W)
    parts = []
    for r in range(0, H, t):
        for c in range(0, W, t):
            r1, c1 = min(r + t, H), min(c + t, W)
            parts.append(scene_pass(P[r : r1 + 2 * h, c : c1 + 2 * h], h, (r - h, c - h), p, prep))
    prep.update(reduce(parts, p, prep))
    return prep


@njit(cache=True, nogil=True)
def _thresholds(
    cands,
    is_bg,
    is_target,
    n,
    mean,
    cov,
    ptr,
    idx,
    anc_r,
    anc_c,
    pix_ptr,
    pix,
    xf,
    radius,
    th_clu,
    tl_clu,
    max_clutter,
    rings,
    looks,
    K,
    em_iter,
    bin_width,
    pfa,
    thr,
    somega_out,
    decided,
    n_clutter,
):
    """Steps 4-5 per candidate: Table 1's clutter set, the Rayleigh-mixture EM on its pixels'
    values ``xf`` and ``T_cfar`` (eq 14), and eq 11's ``sum Omega(SP_m, SP_n)`` over the set;
    ``decided[t]``: ``t`` has a threshold (clutter found, at least ``K`` clutter pixels)."""
    nl = n.size
    mark = np.full(nl, -1, np.int64)
    queue = np.empty(nl + 1, np.int64)
    out = np.empty(max_clutter, np.int64)
    w = np.zeros(K)
    s = np.zeros(K)
    for ci in range(cands.size):
        t = cands[ci]
        m = spx.select_clutter(
            t,
            is_bg,
            is_target,
            n,
            mean,
            cov,
            ptr,
            idx,
            anc_r,
            anc_c,
            radius,
            th_clu,
            tl_clu,
            max_clutter,
            looks,
            out,
            mark,
            queue,
            rings,
        )
        n_clutter[t] = m
        if m == 0:
            continue
        tot = 0
        for q in range(m):
            c = out[q]
            tot += pix_ptr[c + 1] - pix_ptr[c]
        vals = np.empty(tot)
        k = 0
        somega = 0.0
        for q in range(m):
            c = out[q]
            for e in range(pix_ptr[c], pix_ptr[c + 1]):
                vals[k] = xf[pix[e]]
                k += 1
            somega += spx.sp_dissimilarity(n[t], mean[t], cov[t], n[c], mean[c], cov[c], looks)
        if tot < K:
            continue
        fit_binned(vals, K, em_iter, bin_width, w, s)
        thr[t] = math.sqrt(threshold_intensity(w, s, pfa))
        somega_out[t] = somega
        decided[t] = True


@njit(cache=True, nogil=True)
def _pixels(cands, decided, thr, somega, pix_ptr, pix, amp, zeta, use_contrast, frac, det, ratio):
    """Steps 6-7 per decided candidate: eq 16 per pixel (``A C_local / T_cfar``) and the
    detected fraction (:mod:`sarship.pipeline.gpu.superpixel_cfar` is the device twin)."""
    for ci in range(cands.size):
        t = cands[ci]
        if not decided[t]:
            continue
        T = thr[t]
        so = somega[t]
        cnt = 0
        for e in range(pix_ptr[t], pix_ptr[t + 1]):
            i = pix[e]
            v = amp[i] * zeta[i] * so if use_contrast else amp[i]
            d = v > T
            det[i] = d
            ratio[i] = v / T if T > 0 else (np.inf if v > 0 else 0.0)
            if d:
                cnt += 1
        frac[t] = cnt / (pix_ptr[t + 1] - pix_ptr[t])


def point_level(point_pfa: float, looks: float) -> float:
    """The (1 - ``point_pfa``) quantile of a unit-mean gamma law of ``looks`` looks (speckle of
    mean 1): a background superpixel's point threshold is its mean intensity times this."""
    from scipy.special import gammainccinv

    return float(gammainccinv(float(looks), float(point_pfa))) / float(looks)


def point_targets(
    x: np.ndarray, ok: np.ndarray, sp: spx.Superpixels, bg: np.ndarray, p: SuperpixelCFARParams, looks: float
) -> tuple[np.ndarray, np.ndarray]:
    """Small ships (issue 31): ``(det, ratio)`` block arrays, ``det`` the present pixels of
    background superpixels whose intensity exceeds ``mean x point_level(point_pfa, looks)`` of
    their superpixel, ``ratio`` intensity / that threshold there (0 elsewhere). A ship of a few
    pixels raises its ~144-pixel superpixel's mean by a dB or two: it is never a potential target
    (step 3), and step 7's fraction would drop it anyway. Per-superpixel means are the same in
    every tile: tiling-invariant; host code, so the GPU path uses the same arrays."""
    det = np.zeros(x.shape, bool)
    ratio = np.zeros(x.shape)
    if p.point_pfa is None or sp.size.size == 0:
        return det, ratio
    lab = sp.labels
    safe = np.where(lab >= 0, lab, 0)
    thr = sp.mean.astype(np.float64) * point_level(p.point_pfa, looks)
    t = thr[safe]
    with np.errstate(invalid="ignore"):
        det = (lab >= 0) & ok & bg[safe] & (x > t) & (t > 0)
    ratio[det] = x[det] / t[det]
    return det, ratio


def host_steps(x: np.ndarray, halo_px: int, origin, p: SuperpixelCFARParams, prep: dict) -> dict:
    """Steps 1-5 on a host block ``x`` (float_block'ed, halo checked): superpixels, classes,
    candidates (target superpixels touching the core), their pixel lists and, per candidate,
    the clutter count, ``T_cfar``, eq 11's sum of dissimilarities and whether it is decided.
    Shared by the CPU path and the GPU twin (which runs steps 6-7 on the device)."""
    ok = _present(x)
    looks = _looks(p, prep)
    sp = _segment(x, ok, origin, p, looks)
    hp = int(halo_px)
    if "target_bin" not in prep:  # no scene pass ran: the block is the whole scene
        prep = {**prep, **reduce([_histogram(sp, x.shape, hp, origin)], p, prep)}
    b = hist_bin(sp.mean)
    shadow = b < int(prep["shadow_bin"])
    if p.kmeans:
        target = (~shadow) & (b >= int(prep["target_bin"])) & (sp.size > 0)
        bg = (~shadow) & (~target) & (sp.size > 0)
    else:
        target = (~shadow) & (sp.size > 0)
        bg = target.copy()
    lab = sp.labels
    core = lab[hp : lab.shape[0] - hp, hp : lab.shape[1] - hp]
    in_core = np.zeros(sp.size.size, bool)
    in_core[core[core >= 0]] = True
    cands = np.flatnonzero(in_core & target).astype(np.int64)
    pix_ptr, order = spx.pixel_lists(lab, sp.size.size)
    order = order.astype(np.int64)
    nl = sp.size.size
    thr = np.full(nl, np.nan)
    somega = np.zeros(nl)
    decided = np.zeros(nl, np.bool_)
    n_clutter = np.zeros(nl, np.int64)
    _thresholds(
        cands,
        bg,
        target,
        sp.size,
        sp.mean,
        sp.cov,
        sp.ptr,
        sp.idx,
        sp.anchor[:, 0].copy(),
        sp.anchor[:, 1].copy(),
        pix_ptr,
        order,
        np.where(ok, x, 0.0).ravel(),
        int(p.clutter_radius),
        float(p.th_clu),
        float(p.tl_clu),
        int(p.max_clutter),
        int(p.rings),
        looks,
        int(p.components),
        int(p.em_iter),
        float(BIN_WIDTH),
        float(p.pfa),
        thr,
        somega,
        decided,
        n_clutter,
    )
    point, point_ratio = point_targets(x, ok, sp, bg, p, looks)
    return {
        "sp": sp,
        "ok": ok,
        "shadow": shadow,
        "target": target,
        "background": bg,
        "candidates": cands,
        "pix_ptr": pix_ptr,
        "pix": order,
        "threshold": thr,
        "somega": somega,
        "decided": decided,
        "n_clutter": n_clutter,
        "point": point,
        "point_ratio": point_ratio,
    }


def analyse(block, halo_px: int, origin, p: SuperpixelCFARParams, prep: dict) -> dict:
    """Every step on a block: superpixels, classes, per target superpixel the clutter count,
    (``prep`` without the scene pass' values: the block's core is taken for the whole scene)
    ``T_cfar`` and detected fraction, per pixel eq 16's decision and ``A C_local / T_cfar``
    (block arrays; the core is ``[halo:-halo, halo:-halo]``)."""
    x = _check(block, halo_px, p)
    res = host_steps(x, halo_px, origin, p, prep)
    ok = res["ok"]
    amp = np.sqrt(np.where(ok, x, 0.0)).ravel()
    if p.contrast == "paper":
        _, cv = spx.local_stats(amp.reshape(x.shape), ok, origin, p.cov_window)
        zeta = np.exp(-cv / p.kappa).ravel()
    else:
        zeta = np.ones(x.size)
    nl = res["sp"].size.size
    frac = np.zeros(nl)
    det = np.zeros(x.size, np.bool_)
    ratio = np.zeros(x.size)
    _pixels(
        res["candidates"],
        res["decided"],
        res["threshold"],
        res["somega"],
        res["pix_ptr"],
        res["pix"],
        amp,
        zeta,
        p.contrast == "paper",
        frac,
        det,
        ratio,
    )
    return {**res, "frac": frac, "pixel_det": det.reshape(x.shape), "ratio": ratio.reshape(x.shape)}


def _core(a, h):
    return a[h : a.shape[0] - h, h : a.shape[1] - h]


def _above(stat, mask, level: float):
    """float32 ``stat`` with ``stat > level`` wherever ``mask`` (rounding fixed up), 0 elsewhere;
    NumPy or CuPy arrays alike (the GPU path calls it on its device arrays)."""
    s = stat.astype(np.float32)
    lo = np.float32(level)
    if not float(lo) > level:
        lo = np.nextafter(lo, np.float32(np.inf))
    s[mask & ~(s > lo)] = lo
    s[~mask] = 0
    return s


def detect(block, halo_px, origin, p: SuperpixelCFARParams, prep: dict):
    """(mask, stat) of the core. ``decision="superpixel"``: stat = the superpixel's detected
    fraction (> ``fraction`` where the mask is set); ``"pixel"``: stat = A C_local / T_cfar (> 1).
    A CuPy ``block`` runs steps 6-7 on its device (:mod:`sarship.pipeline.gpu.superpixel_cfar`)
    and returns CuPy arrays equal to these."""
    if is_device_array(block):
        return SPEC.twin()(block, halo_px, origin, p, prep)
    hp = int(halo_px)
    if p.decision == "boundaries":
        x = _check(block, halo_px, p)
        lab = _segment(x, _present(x), origin, p, _looks(p, prep)).labels
        mask = _core(boundaries(lab), hp)
        return mask, mask.astype(np.float32)
    res = analyse(block, halo_px, origin, p, prep)
    if p.decision == "pixel":
        mask = _core(res["pixel_det"], hp).copy()
        return mask, _above(_core(res["ratio"], hp), mask, 1.0)
    lab = _core(res["sp"].labels, hp)
    if res["frac"].size == 0:  # nothing present
        return np.zeros(lab.shape, bool), np.zeros(lab.shape, np.float32)
    return superpixel_mask(lab, res["frac"], res["target"], _core(res["point"], hp), _core(res["point_ratio"], hp), p)


def superpixel_mask(lab, frac, target, point, point_ratio, p: SuperpixelCFARParams):
    """Step 7's ``(mask, stat)`` of a core: the target superpixels whose detected ``frac`` exceeds
    ``fraction`` (stat: the fraction), with the point targets (:func:`point_targets`; stat:
    intensity / point threshold, > 1); NumPy or CuPy arrays alike (the GPU path calls it)."""
    hit = (frac > p.fraction) & target
    safe = (lab >= 0) * lab
    whole = (lab >= 0) & hit[safe]
    mask = whole | point
    stat = frac[safe] * whole + point_ratio * (point & ~whole)
    return mask, _above(stat, mask, float(p.fraction))


def boundaries(lab: np.ndarray) -> np.ndarray:
    """Labelled pixels whose right or lower neighbour has another label (a debugging view)."""
    out = np.zeros(lab.shape, bool)
    d = lab[:, :-1] != lab[:, 1:]
    out[:, :-1] |= d & (lab[:, :-1] >= 0)
    d = lab[:-1, :] != lab[1:, :]
    out[:-1, :] |= d & (lab[:-1, :] >= 0)
    return out


def superpixel_labels(block, halo_px: int, origin, p: SuperpixelCFARParams, prep: dict | None = None) -> np.ndarray:
    """The superpixel label image of the core: global ids (int64, -1 for absent pixels), the same
    for any tiling. A debugging aid: ``scene_prep`` is not needed (labels precede the classes)."""
    x = _check(block, halo_px, p)
    sp = _segment(x, _present(x), origin, p, _looks(p, prep or prepare(p)))
    lab = _core(sp.labels, int(halo_px))
    if sp.gid.size == 0:
        return np.full(lab.shape, -1, np.int64)
    return np.where(lab >= 0, sp.gid[np.where(lab >= 0, lab, 0)], -1)


SPEC = DetectorSpec(
    name="superpixel_cfar",
    summary="Superpixel CFAR: bounded DBSCAN superpixels, scene K-means, Table 1 clutter superpixels, "
    "Rayleigh-mixture (EM) threshold per superpixel, CoV local contrast, superpixel decision",
    reference="Zhang et al. 2023, Journal of Radars 12(1) (seed 002); docs/algorithms/superpixel_cfar.md",
    params=SuperpixelCFARParams,
    prepare=prepare,
    detect=detect,
    input="intensity",
    needs_looks=True,
    scene_pass=scene_pass,
    reduce=reduce,
    for_scene=for_scene,
    halo_fn=halo,
    halo_rule="10 reach + 5 + clutter_radius",
    gpu="sarship.pipeline.gpu.superpixel_cfar:detect",  # steps 6-7 on the device, 1-5 on a host copy of the block (pipeline/gpu/superpixel_cfar.py)
    scene_pass_gpu=False,  # the scene pass is the segmentation: host work, so GPU workers pass it the host block
)
