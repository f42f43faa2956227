"""``csk``: complex signal kurtosis of local windows of a single-channel SLC, a global threshold.

Source: Leng, Ji, Xiong, Kuang 2020 (docs/references.md#leng2020), section 5.1, after Leng et
al. 2019 (docs/references.md#leng2019csk): the CSK of sea clutter stays near 0 across sensors,
bands, polarisations and incidence angles, ships are strongly super-Gaussian (CSK >> 0), so one
global CSK threshold finds ships over a whole swath. docs/algorithms/complex_stats.md.

Statistic. For each pixel, over the ``window`` x ``window`` cells (n = window^2) centred on it,
the sample CSK of eq 37 with zero mean (SLC data, the paper's assumption), from four window sums
(:mod:`sarship.pipeline.boxsum`, tiling-invariant):

    CSK = n S22 / S11^2 - 2 - (SR^2 + SI^2) / S11^2,
    S11 = sum |z|^2, S22 = sum |z|^4, SR + j SI = sum z^2.

Threshold (what ``pfa`` means). Under circular complex Gaussian sea (i.i.d. CN(0, s2): fully
developed speckle, eq 39 with beta = 1) CSK's law depends on n only; the threshold T with
P(false alarm) = ``pfa`` per pixel comes from that law, simulated by importance sampling with a
fixed seed (:mod:`sarship.pipeline.csk_null`: exact mean -4/(n+1), asymptotic N(-4/(n+1), 4/n),
why the asymptotic law is not used). A pixel is detected when

* ``cells="bright"`` (default): CSK > T and its own power exceeds the window's mean power
  (|z|^2 > S11 / n): the detection covers the bright cells of a super-Gaussian window, so a
  ship's shape is not dilated by the window; ``pfa`` = P(CSK > T and |z_0|^2 > S11 / n);
* ``cells="window"``: CSK > T alone (every pixel whose window is super-Gaussian);
  ``pfa`` = P(CSK > T).

Absent pixels (NaN, or ``nodata``) are never tested and a pixel is tested only when its whole
window is present (the null law is that of n cells; no per-count tables). Texture: on
K-compound sea the texture is nearly constant within a small window, so CSK stays near its
Gaussian law there; tests/test_csk.py measures how far the false-alarm rate moves.
"""

from __future__ import annotations

from typing import Literal, Optional

import numpy as np
from pydantic import Field, model_validator

from sarship.pipeline import boxsum, csk_null
from sarship.pipeline.detectors.base import DetectorParams, DetectorSpec, check_windows, with_defaults
from sarship.pipeline.gpu import is_device_array


class CSKParams(with_defaults(DetectorParams, "CSKDefaults", pfa=1e-6, merge_px=10,
                              auto_min_area_px=4, auto_min_length_m=20.0, auto_min_area_m2=100.0)):
    """Parameters of ``csk``. ``target``, ``guard``, ``background`` and ``looks`` are not used
    (one window, single-look complex data)."""

    window: int = Field(7, ge=3, le=63, description="CSK window side (odd, pixels): n = window^2 cells")
    cells: Literal["bright", "window"] = Field(
        "bright", description="bright: a pixel is detected when its window's CSK exceeds the threshold and its "
                              "power exceeds the window's mean power (the ship's bright cells); window: every "
                              "pixel whose window's CSK exceeds it; pfa is calibrated for the rule chosen")
    nodata: Optional[float] = Field(
        None, description="value of the complex data (real part, imaginary part 0) marking absent pixels besides "
                          "NaN, e.g. 0 for a zero-filled border; None: NaN only")

    @model_validator(mode="after")
    def _csk_checks(self):
        if self.window % 2 == 0:
            raise ValueError(f"window must be odd, got {self.window}")
        if self.land_mask == "texture":
            raise ValueError("land_mask: texture is not available for csk (its texture model reads intensity); "
                             "give a land mask FILE")
        return self


def prepare(p: CSKParams) -> dict:
    n = int(p.window) ** 2
    thr, rse = csk_null.threshold(n, float(p.pfa), p.cells)
    return {
        "n_window": n,
        "threshold": thr,
        "threshold_rel_se": rse,
        "cells": p.cells,
        "null_mean": -4.0 / (n + 1),
        "statistic": "zero-mean sample CSK of the window, eq 37: n S22/S11^2 - 2 - |S20|^2/S11^2",
        "distribution": (f"circular complex Gaussian sea, n = {n}: importance-sampled "
                         f"({csk_null.SAMPLES} windows, seed {csk_null.SEED}; pipeline/csk_null.py)"),
    }


def csk_window(block, halo: int, origin: tuple[int, int], window: int, nodata: float | None, box, xp):
    """``(csk, tested, power, s11)`` of the core: the window CSK (float64), whether the pixel is
    tested (whole window present, non-zero power), the pixel's power and the window's power sum.
    ``box`` is :func:`sarship.pipeline.boxsum.centered_box_sum` or its GPU twin, ``xp`` numpy or
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
    return xp.where(tested, k, 0.0), tested, pw[halo: halo + h, halo: halo + w], s11


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
        raise ValueError("csk needs complex single-look (SLC) data: amplitude or intensity has no phase "
                         f"(got a {b.dtype} block)")
    return b


def detect(block, halo: int, origin: tuple[int, int], p: CSKParams, prep: dict):
    """``csk`` on one padded complex tile; returns (mask, CSK) of the core."""
    check_windows(halo, int(p.window))
    if is_device_array(block):
        from sarship.pipeline.gpu.csk import csk_detect

        return csk_detect(block, halo, origin, p, prep)
    b = _complex_block(block)
    k, tested, pw, s11 = csk_window(b, halo, origin, int(p.window), p.nodata, boxsum.centered_box_sum, np)
    return decide(k, tested, pw, s11, int(prep["n_window"]), float(prep["threshold"]), p.cells, np)


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
    gpu=True,
)
