"""GPU twins of the polarimetric detectors' per-pixel maths (``apwf``, ``pcdm``).

Blocks are CuPy arrays of complex channels ``(rows, cols, p)`` or covariance matrices
``(rows, cols, p, p)`` (complex64 as the scene stores them; other complex types are cast to
complex64). Products of X X^H and the window sums are formed with the CPU's arithmetic and
order (bit-identical sums); the adjugate and quadratic form repeat ``apwf._pwf``. For
covariance input the CPU solves ``S y = C`` with LAPACK while the GPU uses the adjugate:
those statistics agree to rounding (relative ~1e-12), not bit for bit.
"""

from __future__ import annotations

import math

import numpy as np

from sarship.pipeline.gpu import kernels
from sarship.pipeline.gpu.box import centered_box_sum


def _complex_block(cp, block):
    if block.dtype != cp.complex64:
        block = block.astype(cp.complex64)
    return cp.ascontiguousarray(block)


def _planes(cp, block, scale1: float):
    """(p^2, rows, cols) float64 planes of X X^H (or of C for covariance blocks)."""
    rows, cols, p = block.shape[:3]
    n = rows * cols
    planes = cp.empty((p * p, rows, cols), cp.float64)
    x = block.view(cp.float32)
    if block.ndim == 4:
        kernels.launch("cov_planes", n, (x, np.int64(cols), np.int64(rows), np.int64(cols), np.int32(p), planes))
    else:
        kernels.launch(
            "xxh_planes",
            n,
            (x, np.int64(cols), np.int64(rows), np.int64(cols), np.int32(p), np.float64(scale1), planes),
        )
    return planes


def apwf(
    block,
    halo: int,
    origin,
    b: int,
    g: int,
    ring: bool,
    n_samples: float,
    thr: float,
    pfa: float | None = None,
    kmin: int | None = None,
):
    """Adaptive PWF (see :mod:`sarship.pipeline.detectors.apwf`): y = K X^H S^-1 X > T(K).

    Absent pixels (:func:`sarship.pipeline.tiling.polsar_absent.present`) are zeroed before the
    products and counted out with the same box sums as the CPU (K, exact integers); the
    per-pixel thresholds come from :func:`sarship.pipeline.detectors.apwf.threshold_map`
    (host SciPy for the tile's distinct partial counts, as on the CPU). ``pfa`` and ``kmin``
    are needed only when the tile has absent pixels (``kmin`` default: ``min_valid``)."""
    import cupy as cp

    from sarship.pipeline.detectors.apwf import min_valid, threshold_map
    from sarship.pipeline.tiling.polsar_absent import present, zero_absent

    block = _complex_block(cp, block)
    cov = block.ndim == 4
    p = block.shape[2]
    h = block.shape[0] - 2 * halo
    w = block.shape[1] - 2 * halo
    r = b // 2
    off = halo - r
    sub = block[off : off + h + 2 * r, off : off + w + 2 * r]
    o = (int(origin[0]) + off, int(origin[1]) + off)
    ok = present(sub)
    complete = bool(ok.all())
    sub = zero_absent(sub, ok)
    prods = _planes(cp, cp.ascontiguousarray(sub), 1.0)
    S = cp.empty((p * p, h, w), cp.float64)
    for q in range(p * p):
        S[q] = centered_box_sum(prods[q], b, r, o)
        if ring:
            S[q] -= centered_box_sum(prods[q], g, r, o)
    if complete:
        K = cp.full((h, w), float(n_samples))
    else:
        v = ok.astype(cp.float64)
        K = centered_box_sum(v, b, r, o)
        if ring:
            K -= centered_box_sum(v, g, r, o)
    okc = ok[r : r + h, r : r + w]
    if kmin is None:
        kmin = min_valid(int(n_samples), p)
    if pfa is None and not complete:
        raise ValueError("apwf on a tile with absent pixels needs pfa (per-pixel thresholds)")
    T = threshold_map(
        K,
        okc & (K >= kmin),
        pfa if pfa is not None else 0.5,
        p,
        "ring" if ring else "window",
        float(n_samples),
        float(thr),
    )
    core = cp.ascontiguousarray(sub[r : r + h, r : r + w])
    Cp = cp.ascontiguousarray(prods[:, r : r + h, r : r + w]) if cov else S  # core covariance planes
    mask = cp.empty((h, w), cp.bool_)
    stat = cp.empty((h, w), cp.float32)
    thr32 = np.float32(thr)
    above = np.nextafter(thr32, np.float32(np.inf))
    n = h * w
    kernels.launch(
        "apwf_decide_valid",
        n,
        (
            S,
            np.int64(n),
            core.view(cp.float32),
            np.int64(w),
            np.int64(w),
            np.int32(p),
            np.int32(1 if cov else 0),
            Cp,
            cp.ascontiguousarray(K),
            cp.ascontiguousarray(T),
            np.float64(thr),
            np.float32(above),
            mask,
            stat,
        ),
    )
    return mask, stat


def pcdm_span_psh(block, halo_px: int, origin, looks_window: int):
    """SPAN_P and PSH (float64, CuPy) of the core (see :func:`sarship.pipeline.detectors.pcdm.span_psh`;
    NaN where not tested: absent data within the halo, found by the same box sums)."""
    import cupy as cp

    from sarship.pipeline.detectors.pcdm import tested_count
    from sarship.pipeline.tiling.polsar_absent import present, zero_absent

    block = _complex_block(cp, block)
    ok = present(block)
    complete = bool(ok.all())
    block = cp.ascontiguousarray(zero_absent(block, ok))
    p = block.shape[2]
    r = looks_window // 2
    planes = _planes(cp, block, 1.0 if block.ndim == 4 else math.sqrt(2.0) if p == 3 else 1.0)
    if r > 0:
        nw = float(looks_window * looks_window)
        planes = cp.stack([centered_box_sum(pl, looks_window, r, (origin[0], origin[1])) / nw for pl in planes])
    off = halo_px - r - 1
    h = block.shape[0] - 2 * halo_px
    w = block.shape[1] - 2 * halo_px
    C = cp.ascontiguousarray(planes[:, off : off + h + 2, off : off + w + 2])
    span = cp.empty((h, w), cp.float64)
    psh = cp.empty((h, w), cp.float64)
    kernels.launch(
        "pcdm_kernel",
        h * w,
        (C, np.int64(w + 2), np.int64((h + 2) * (w + 2)), np.int64(h), np.int64(w), np.int32(p), span, psh),
    )
    if not complete:
        untested = tested_count(ok, looks_window, halo_px, origin) < (looks_window + 2) ** 2
        span[untested] = cp.nan
        psh[untested] = cp.nan
    return span, psh


def vb_pixels(core, c, P, m, g1, t_init: float, a0: float, b0: float, max_iter: int, tol: float, joint: bool):
    """vb_polsar pass 2 on the device (see :func:`sarship.pipeline.detectors.vb_polsar._pixels`):
    ``core`` (h, w, p) complex channels; the mixture terms as NumPy arrays. CUDA's
    ``exp``/``log`` differ from the CPU's in the last bits: the log-odds agree to ~1e-12
    relative, the masks except at pixels within that of the threshold."""
    import cupy as cp

    core = _complex_block(cp, core)
    h, w, p = core.shape
    K, D = np.asarray(m).shape
    if K > 16:
        raise ValueError(f"vb_polsar on the GPU supports up to 16 components, got {K}")
    dev = [cp.asarray(np.ascontiguousarray(a, dtype=np.float64)) for a in (c, P, m, g1)]
    mask = cp.empty((h, w), cp.bool_)
    stat = cp.empty((h, w), cp.float32)
    n = h * w
    kernels.launch(
        "vb_pixels",
        n,
        (
            core.view(cp.float32),
            np.int64(n),
            np.int32(p),
            np.int32(K),
            np.int32(D),
            *dev,
            np.float64(t_init),
            np.float64(a0),
            np.float64(b0),
            np.int32(max_iter),
            np.float64(tol),
            np.int32(1 if joint else 0),
            mask,
            stat,
        ),
    )
    return mask, stat
