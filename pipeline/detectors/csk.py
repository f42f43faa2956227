"""``csk``: complex signal kurtosis of local windows of a single-channel SLC, a global threshold.

Source: Leng, Ji, Xiong, Kuang 2020 (docs/references.md#leng2020), section 5.1, after Leng et
al. 2019 (docs/references.md#leng2019csk): the CSK of sea clutter stays near 0 across sensors,
bands, polarisations and incidence angles, ships are strongly super-Gaussian (CSK >> 0), so one
global CSK threshold finds ships over a whole swath. docs/algorithms/complex_stats.md.

Statistic. For each pixel, over the ``window`` x ``window`` cells (n = window^2) centred on it,
the sample CSK of eq 37 with zero mean (SLC data, the paper's assumption), from four window sums
(:mod:`sarship.pipeline.tiling.boxsum`, tiling-invariant):

    CSK = n S22 / S11^2 - 2 - (SR^2 + SI^2) / S11^2,
    S11 = sum |z|^2, S22 = sum |z|^4, SR + j SI = sum z^2.

Threshold (what ``pfa`` means). Under circular complex Gaussian sea (i.i.d. CN(0, s2): fully
developed speckle, eq 39 with beta = 1) CSK's law depends on n only; the threshold T with
P(false alarm) = ``pfa`` per pixel comes from that law, simulated by importance sampling with a
fixed seed (:mod:`sarship.pipeline.stats.csk_null`: exact mean -4/(n+1), asymptotic N(-4/(n+1), 4/n),
why the asymptotic law is not used). A pixel is detected when

* ``cells="bright"`` (default): CSK > T and its own power exceeds the window's mean power
  (|z|^2 > S11 / n): the detection covers the bright cells of a super-Gaussian window, so a
  ship's shape is not dilated by the window; ``pfa`` = P(CSK > T and |z_0|^2 > S11 / n);
* ``cells="window"``: CSK > T alone (every pixel whose window is super-Gaussian);
  ``pfa`` = P(CSK > T).

Absent pixels (NaN, or ``nodata``) are never tested and a pixel is tested only when its whole
window is present (the null law is that of n cells; no per-count tables). Texture: on
K-compound sea the texture is nearly constant within a small window, so CSK stays near its
Gaussian law there; tests/pipeline/test_csk.py measures how far the false-alarm rate moves.

Ship geometry (``ship_segmentation``, default ``kurtosis``): each detection's chip of the SLC is
segmented by the iterative kurtosis segmentation of section 5.2 (or Otsu) and the segmented
ship's geometry replaces the mask's (:func:`segment_geometry`, pipeline/targets/kurtosis_seg.py).
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import Field, field_validator, model_validator

from sarship.pipeline.detectors.base import DetectorParams, DetectorSpec, check_windows, land_mask_parts, with_defaults
from sarship.pipeline.gpu import is_device_array
from sarship.pipeline.stats import csk_null
from sarship.pipeline.tiling import boxsum


class CSKParams(
    with_defaults(
        DetectorParams,
        "CSKDefaults",
        pfa=1e-6,
        merge_px=10,
        auto_min_area_px=4,
        auto_min_length_m=20.0,
        auto_min_area_m2=100.0,
    )
):
    """Parameters of ``csk``. ``target``, ``guard``, ``background`` and ``looks`` are not used
    (one window, single-look complex data)."""

    window: int = Field(7, ge=3, le=15, description="CSK window side (odd, 3..15 pixels): n = window^2 cells")
    cells: Literal["bright", "window"] = Field(
        "bright",
        description="bright: a pixel is detected when its window's CSK exceeds the threshold and its "
        "power exceeds the window's mean power (the ship's bright cells); window: every "
        "pixel whose window's CSK exceeds it; pfa is calibrated for the rule chosen",
    )
    npdd_s: int = Field(
        3,
        ge=1,
        le=31,
        description="NPDD (eq 19-21) of each detection's pixels: outer neighbourhood s (window side, centre excluded)",
    )
    npdd_t: int = Field(1, ge=1, le=31, description="NPDD inner neighbourhood t (1: the pixel itself)")
    ship_segmentation: Literal["kurtosis", "otsu", "none"] = Field(
        "kurtosis",
        description="each detection's geometry (length, width, heading, centroid, outline) from a "
        "segmentation of its chip of the SLC (bounding box + segmentation_margin_px): "
        "kurtosis: the iterative kurtosis segmentation (seed 004 section 5.2), otsu: Otsu "
        "on the 8-bit amplitude stretch, none: the detection mask's own geometry",
    )
    segmentation_margin_px: int = Field(
        3,
        ge=1,
        le=64,
        description="margin (pixels) around a detection's bounding box of the chip ship_segmentation reads",
    )
    nodata: float | None = Field(
        None,
        description="value of the complex data (real part, imaginary part 0) marking absent pixels besides "
        "NaN, e.g. 0 for a zero-filled border; None: NaN only",
    )

    @field_validator("ship_segmentation", mode="before")
    @classmethod
    def _none_is_none(cls, v):
        # the command line's --set ship_segmentation=none arrives as None (parse_params): no segmentation
        return "none" if v is None else v

    @model_validator(mode="after")
    def _csk_checks(self):
        if self.window % 2 == 0:
            raise ValueError(f"window must be odd, got {self.window}")
        for name in ("npdd_s", "npdd_t"):
            v = getattr(self, name)
            if v > 1 and v % 2 == 0:
                raise ValueError(f"{name} must be 1 or odd, got {v}")
        if self.npdd_s == self.npdd_t:
            raise ValueError(f"npdd_s and npdd_t must differ, got {self.npdd_s}")
        if "texture" in land_mask_parts(self.land_mask)[0]:
            raise ValueError(
                "land_mask: texture is not available for csk (its texture model reads intensity); give a land mask FILE"
            )
        return self


def prepare(p: CSKParams) -> dict:
    n = int(p.window) ** 2
    samples = csk_null.samples_for(n)
    thr, rse = csk_null.threshold(n, float(p.pfa), p.cells, samples=samples)
    return {
        "n_window": n,
        "threshold": thr,
        "threshold_rel_se": rse,
        "cells": p.cells,
        "null_mean": -4.0 / (n + 1),
        "statistic": "zero-mean sample CSK of the window, eq 37: n S22/S11^2 - 2 - |S20|^2/S11^2",
        "distribution": (
            f"circular complex Gaussian sea, n = {n}: importance-sampled "
            f"({samples} windows, seed {csk_null.SEED}; pipeline/stats/csk_null.py)"
        ),
    }


def csk_window(block, halo: int, origin: tuple[int, int], window: int, nodata: float | None, box, xp):
    """``(csk, tested, power, s11)`` of the core: the window CSK (float64), whether the pixel is
    tested (whole window present, non-zero power), the pixel's power and the window's power sum.
    ``box`` is :func:`sarship.pipeline.tiling.boxsum.centered_box_sum` or its GPU twin, ``xp`` numpy or
    cupy; the same IEEE operations in the same order on both."""
    zr = block.real.astype(xp.float64)
    zi = block.imag.astype(xp.float64)
    ok = xp.isfinite(zr) & xp.isfinite(zi)
    if nodata is not None:
        ok &= ~((zr == float(nodata)) & (zi == 0.0))
    zr = xp.where(ok, zr, 0.0)
    zi = xp.where(ok, zi, 0.0)
    pw = zr * zr + zi * zi
    s11 = box(pw, window, halo, origin)
    s22 = box(pw * pw, window, halo, origin)
    sr = box(zr * zr - zi * zi, window, halo, origin)
    si = box(2.0 * zr * zi, window, halo, origin)
    cnt = box(ok.astype(xp.float64), window, halo, origin)
    n = float(window * window)
    tested = (cnt == n) & (s11 > 0.0)
    den = xp.where(tested, s11 * s11, 1.0)
    k = n * s22 / den - 2.0 - (sr * sr + si * si) / den
    h = block.shape[0] - 2 * halo
    w = block.shape[1] - 2 * halo
    return xp.where(tested, k, 0.0), tested, pw[halo : halo + h, halo : halo + w], s11


def decide(k, tested, pw, s11, n: int, thr: float, cells: str, xp):
    """Mask and float32 statistic (stat > thr wherever mask) from :func:`csk_window`."""
    mask = tested & (k > thr)
    if cells == "bright":
        mask &= pw * float(n) > s11
    stat = k.astype(xp.float32)
    t32 = np.float32(thr)
    up = np.nextafter(t32, np.float32(np.inf)) if not float(t32) > thr else t32
    stat = xp.where(mask & ~(stat > t32), up, stat)
    return mask, stat


def _complex_block(block) -> np.ndarray:
    b = np.asarray(block)
    if b.ndim != 2:
        raise ValueError(f"csk reads one complex channel: a 2-D block, got shape {b.shape}")
    if not np.iscomplexobj(b):
        raise ValueError(
            f"csk needs complex single-look (SLC) data: amplitude or intensity has no phase (got a {b.dtype} block)"
        )
    return b


def detect(block, halo: int, origin: tuple[int, int], p: CSKParams, prep: dict):
    """``csk`` on one padded complex tile; returns (mask, CSK) of the core."""
    check_windows(halo, int(p.window))
    if is_device_array(block):
        return SPEC.twin()(block, halo, origin, p, prep)
    b = _complex_block(block)
    k, tested, pw, s11 = csk_window(b, halo, origin, int(p.window), p.nodata, boxsum.centered_box_sum, np)
    return decide(k, tested, pw, s11, int(prep["n_window"]), float(prep["threshold"]), p.cells, np)


#: Level of the two tests of the RFI flag (:func:`rfi_flag`).
RFI_ALPHA = 1e-3


def complex_stats(v) -> tuple[float, float]:
    """``(CSK, non-circularity)`` of a detection's complex pixel values: the zero-mean CSK of
    eq 37 and |sum z^2| / sum |z|^2 (0: circular, 1: one phase direction)."""
    v = np.asarray(v, dtype=np.complex128).ravel()
    pw = v.real**2 + v.imag**2
    s11 = float(pw.sum())
    if v.size == 0 or not s11 > 0:
        return float("nan"), float("nan")
    s20 = complex(np.sum(v * v))
    nc = abs(s20) / s11
    return float(v.size * float(np.sum(pw * pw)) / s11**2 - 2.0 - nc * nc), float(nc)


def rfi_flag(n: int, k: float, nc: float, alpha: float = RFI_ALPHA) -> bool:
    """Radio interference rather than a ship (Leng et al. 2019b, docs/references.md#leng2019rfi;
    seed 004 section 5.1): RFI is weakly non-circular and sub-Gaussian, ships strongly
    non-circular and super-Gaussian. A candidate of n >= 8 pixels is RFI when its CSK (eq 37) is
    at most 0 (not super-Gaussian: narrow-band interference has a near-constant envelope, CSK
    -1 for one tone) and its non-circularity |sum z^2| / sum |z|^2 is consistent with circular
    data at level ``alpha``: n nc^2 / 2 <= ln(1/alpha) (under circularity m20 is asymptotically
    CN(0, 2 s2^2 / n), so n |m20|^2 / m11^2 / 2 is Exp(1))."""
    if n < 8 or not (np.isfinite(k) and np.isfinite(nc)):
        return False
    return bool(k <= 0.0 and n * nc * nc / 2.0 <= np.log(1.0 / alpha))


def detection_properties(
    feats: list,
    records,
    read,
    read_mask,
    shape,
    merge_r: int,
    p: CSKParams,
    prep: dict,
    spacing: tuple[float, float] | None = None,
    geo: dict | None = None,
) -> list:
    """Each detection's complex statistics from its own pixels (the component of the mask):
    ``csk`` (eq 37), ``noncircularity``, ``npdd_variance`` and ``npdd_rbar`` (circular variance
    and mean resultant length of NPDD_st, eq 19-21 and 5, 8) and ``rfi`` (:func:`rfi_flag`); then,
    unless ``ship_segmentation`` is ``none``, the segmented geometry (:func:`segment_geometry`).
    ``spacing`` and ``geo`` (the scene's pixel spacing and georeference attributes) measure it."""
    from sarship.pipeline.stats import circular
    from sarship.pipeline.targets.sidelobes import component_in_window

    H, W = shape
    m = max(int(p.npdd_s), int(p.npdd_t)) // 2 + 1
    for f, rec in zip(feats, records):
        ra, rb = max(int(rec["r0"]) - m, 0), min(int(rec["r1"]) + m, H)
        ca, cb = max(int(rec["c0"]) - m, 0), min(int(rec["c1"]) + m, W)
        z = np.asarray(read(ra, rb, ca, cb))
        mask = np.asarray(read_mask(ra, rb, ca, cb)) > 0
        comp = component_in_window(mask, (int(rec["peak_r"]) - ra, int(rec["peak_c"]) - ca), merge_r)
        bb = np.zeros_like(comp)
        bb[int(rec["r0"]) - ra : int(rec["r1"]) - ra, int(rec["c0"]) - ca : int(rec["c1"]) - ca] = True
        comp &= bb & np.isfinite(z.real) & np.isfinite(z.imag)
        k, nc = complex_stats(z[comp])
        var, rbar = circular.npdd_spread(circular.npdd(z, int(p.npdd_s), int(p.npdd_t))[comp])
        n = int(comp.sum())
        f["properties"].update(
            {
                "csk": None if not np.isfinite(k) else round(k, 6),
                "noncircularity": None if not np.isfinite(nc) else round(nc, 6),
                "npdd_variance": None if not np.isfinite(var) else round(var, 6),
                "npdd_rbar": None if not np.isfinite(rbar) else round(rbar, 6),
                "rfi": rfi_flag(n, k, nc),
            }
        )
    if p.ship_segmentation != "none":
        feats = segment_geometry(feats, records, read, read_mask, shape, merge_r, p, spacing, geo)
    return feats


#: Times :func:`segment_geometry` may widen a detection's chip to the segmented ship, and the
#: largest chip side (pixels) it widens to.
SEGMENTATION_GROW_MAX = 4
SEGMENTATION_MAX_SIDE = 256


def segment_geometry(
    feats: list,
    records,
    read,
    read_mask,
    shape,
    merge_r: int,
    p: CSKParams,
    spacing: tuple[float, float] | None,
    geo: dict | None,
) -> list:
    """Each detection's ship geometry from a segmentation of its chip (seed 004 section 5.2,
    fig 17; :mod:`sarship.pipeline.targets.kurtosis_seg`).

    The chip is the detection's bounding box plus ``segmentation_margin_px``, read from the
    scene (never the tile: the result does not depend on tiling), absent pixels (NaN, or
    ``nodata``) left out. It is segmented by ``ship_segmentation`` (the amplitude threshold of
    the iterative kurtosis segmentation, or Otsu's); the ship is the 8-connected segmented
    component holding the brightest segmented pixel of the detection (its mask component,
    :func:`sarship.pipeline.targets.sidelobes.component_in_window`, inside its bounding box). Where the
    ship reaches a side of the chip (inside the scene), the detection covered only part of it
    (``csk`` finds the ends of a ship whose middle is homogeneous speckle, whose windows are
    Gaussian): the chip is widened to the ship's box plus the margin and segmented again, at
    most ``SEGMENTATION_GROW_MAX`` times and up to ``SEGMENTATION_MAX_SIDE`` pixels a side
    (``segmentation_window_px``: the last chip, [r0, c0, r1, c1]). Fragments of one ship then
    carry the same ship's geometry (the detections are not merged). Its moment
    geometry (``centroid_px``, ``length_px``, ``width_px``, ``heading_deg``, ``length_m``,
    ``width_m`` and the outline) replaces the detection's, whose values are kept as
    ``<name>_raw`` (unless the sidelobe step already kept them). Properties added:
    ``segmentation`` (the method), ``segmentation_threshold`` (the amplitude threshold, null
    when none was found), ``segmented_area_px`` (0: nothing segmented at the detection, the
    geometry left as it was)."""
    from sarship.pipeline.targets import kurtosis_seg
    from sarship.pipeline.targets.ship_features import features
    from sarship.pipeline.targets.sidelobes import GEOMETRY_KEYS, component_in_window

    H, W = shape
    m = int(p.segmentation_margin_px)
    out = []
    for f, rec in zip(feats, records):
        props = f["properties"]
        ra, rb = max(int(rec["r0"]) - m, 0), min(int(rec["r1"]) + m, H)
        ca, cb = max(int(rec["c0"]) - m, 0), min(int(rec["c1"]) + m, W)
        for grow in range(SEGMENTATION_GROW_MAX + 1):
            z = np.asarray(read(ra, rb, ca, cb)).astype(np.complex128)
            if p.nodata is not None:
                z = np.where((z.real == float(p.nodata)) & (z.imag == 0.0), np.nan + 0j, z)
            det = component_in_window(
                np.asarray(read_mask(ra, rb, ca, cb)) > 0, (int(rec["peak_r"]) - ra, int(rec["peak_c"]) - ca), merge_r
            )
            bb = np.zeros_like(det)
            bb[int(rec["r0"]) - ra : int(rec["r1"]) - ra, int(rec["c0"]) - ca : int(rec["c1"]) - ca] = True
            seg, t = kurtosis_seg.segment(z, p.ship_segmentation)
            amp = np.abs(np.where(np.isfinite(z), z, 0))
            ship = kurtosis_seg.component_of(seg, amp, det & bb)
            if not ship.any():
                break
            # the ship reaches a side of the chip inside the scene: widen the chip to its box + margin
            rr, cc = np.nonzero(ship)
            na, nb = min(ra, max(ra + int(rr.min()) - m, 0)), max(rb, min(ra + int(rr.max()) + 1 + m, H))
            nc, nd = min(ca, max(ca + int(cc.min()) - m, 0)), max(cb, min(ca + int(cc.max()) + 1 + m, W))
            if (
                (na, nb, nc, nd) == (ra, rb, ca, cb)
                or grow == SEGMENTATION_GROW_MAX
                or max(nb - na, nd - nc) > SEGMENTATION_MAX_SIDE
            ):
                break
            ra, rb, ca, cb = na, nb, nc, nd
        props["segmentation_window_px"] = [ra, ca, rb, cb]
        props["segmentation"] = p.ship_segmentation
        props["segmentation_threshold"] = round(t, 6) if np.isfinite(t) else None
        props["segmented_area_px"] = int(ship.sum())
        if not ship.any():
            out.append(f)
            continue
        rec1 = kurtosis_seg.moment_record(ship, (ra, ca))
        for k in ("peak", "sumv", "score", "peak_r", "peak_c"):
            rec1[k] = rec[k]
        nf = features(rec1, spacing, geo)[0]
        for k in GEOMETRY_KEYS:
            props.setdefault(f"{k}_raw", props[k])
            props[k] = nf["properties"][k]
        out.append({**f, "geometry": nf["geometry"], "properties": props})
    return out


SPEC = DetectorSpec(
    name="csk",
    summary="complex signal kurtosis of local SLC windows (eq 37), one global threshold calibrated on "
    "circular complex Gaussian sea",
    reference="Leng et al. 2020, Journal of Radars 9(3), section 5.1 (seed 004); docs/algorithms/complex_stats.md",
    params=CSKParams,
    prepare=prepare,
    detect=detect,
    input="slc",
    needs_looks=False,
    halo_fn=lambda p: int(p.window) // 2,
    halo_rule="window // 2",
    gpu="sarship.pipeline.gpu.csk:csk_detect",
    detection_properties=detection_properties,
)
