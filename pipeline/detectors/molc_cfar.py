"""Per-pixel part of ``g0_cfar``, ``k_cfar`` and ``ggd_cfar``: ring log-cumulants from
tiling-invariant window sums, the MoLC threshold read from a table, the decision.

One implementation for NumPy and CuPy: every function takes the array module ``xp`` and the
window-sum function ``box`` (:func:`sarship.pipeline.tiling.boxsum.centered_box_sum` or its bit-identical
GPU twin :func:`sarship.pipeline.gpu.box.centered_box_sum`), so the GPU twin
(:mod:`sarship.pipeline.gpu.molc`) runs the same operations in the same order; only ``log``,
``log1p``, ``sqrt`` and ``exp`` of CUDA may differ from the CPU's in the last bit.

Absent pixels (:mod:`sarship.pipeline.tiling.intensity_absent`): a pixel is *usable* when it is finite
and > 0 (the log needs x > 0; NaN is no-data and land once a land mask has run). Unusable
pixels are never targets (mask 0, statistic 0) and enter no ring sum; a pixel is tested
when it is usable and its ring holds at least ``max(3, ceil(N / 2))`` usable samples
(k3 needs three), N = background^2 - guard^2.

Bright-pixel censoring (``censor`` = c, optional): a ring sample x_j is left out of the
sums when x_j > c m_j, m_j the mean of the usable samples of the background-size window
centred on the sample itself (a per-sample flag from window sums: tiling-invariant; the
halo grows to 2 (background // 2)). Docs: docs/algorithms/g0_k_ggd.md.
"""

from __future__ import annotations

import numpy as np

from sarship.pipeline.stats import molc
from sarship.pipeline.tiling.intensity_absent import min_valid

#: Rows of the core processed at once on the CPU (bounds the float64 intermediates; results
#: do not depend on it: the strips are tiles, and the window sums are tiling-invariant).
STRIP_ROWS = 256
#: The same on the GPU (fewer, larger launches).
GPU_STRIP_ROWS = 2048


#: The GPU twin of :func:`detect_block` (the ``gpu`` of ``g0_cfar``, ``k_cfar`` and ``ggd_cfar``'s specs),
#: resolved on first use by :func:`sarship.pipeline.gpu.twin`.
GPU_TWIN = "sarship.pipeline.gpu.molc:molc_cfar"


def min_ring(n_ring: int) -> int:
    """The fewest usable ring samples for a pixel to be tested."""
    return max(3, min_valid(n_ring))


def censor_halo(background: int) -> int:
    return 2 * (background // 2)


def ring_cumulants(xp, box, block, halo: int, origin, b: int, g: int, censor):
    """``(n, k1, k2, k3, y_t, usable_t)`` over the core: the ring's usable-sample count (a scalar
    when every ring is complete), its
    k-statistics of ln x (eq (1) of :mod:`sarship.pipeline.stats.molc`), and ln x / usability of the
    pixel under test. ``censor``: None, or the factor c of the module docstring."""
    h = block.shape[0] - 2 * halo
    w = block.shape[1] - 2 * halo
    x = block.astype(xp.float64)
    ok = xp.isfinite(x) & (x > 0.0)
    r = b // 2
    if censor is not None:  # flag bright samples on the core grown by r (their windows lie in the block)
        hc = halo - r
        xz = xp.where(ok, x, 0.0)
        okf = ok.astype(xp.float64)
        cnt = box(okf, b, hc, origin)
        sm = box(xz, b, hc, origin)
        xe = xz[hc : hc + h + 2 * r, hc : hc + w + 2 * r]
        oke = ok[hc : hc + h + 2 * r, hc : hc + w + 2 * r] & ~(xe * cnt > float(censor) * sm)
        x = x[hc : hc + h + 2 * r, hc : hc + w + 2 * r]
        ok_t = ok[halo : halo + h, halo : halo + w]
        halo, origin = r, (origin[0] + hc, origin[1] + hc)
        ok = oke
    else:
        ok_t = ok[halo : halo + h, halo : halo + w]
    y = xp.where(ok, xp.log(xp.where(ok, x, 1.0)), 0.0)
    y2 = y * y
    y3 = y2 * y
    if bool(ok.all()):  # complete ring everywhere: n is the scalar N (the same IEEE operations)
        n = nn = float(b * b - g * g)
    else:
        okf = ok.astype(xp.float64)
        n = box(okf, b, halo, origin) - box(okf, g, halo, origin)
        nn = xp.where(n >= 3.0, n, 3.0)  # k3 needs n >= 3; fewer samples: not tested anyway
    s1 = box(y, b, halo, origin) - box(y, g, halo, origin)
    s2 = box(y2, b, halo, origin) - box(y2, g, halo, origin)
    s3 = box(y3, b, halo, origin) - box(y3, g, halo, origin)
    k1, k2, k3 = molc.k_statistics(nn, s1, s2, s3)
    y_t = y[halo : halo + h, halo : halo + w]
    if censor is not None:  # the pixel under test is tested whatever its own flag
        xt = x[halo : halo + h, halo : halo + w]
        y_t = xp.where(ok_t, xp.log(xp.where(ok_t, xt, 1.0)), 0.0)
    return n, k1, k2, k3, y_t, ok_t


def log_excess(xp, kind: str, tab, looks: float, k1, k2, k3, y_t):
    """``(d, in_domain)``: d = ln x_t - ln t with t the pixel's MoLC threshold, and whether the
    ring's log-cumulants lie in the model's domain.

    * ``g0`` / ``k``: u = k2 - psi_1(L); u <= 0 (ring lighter-tailed than L-look gamma) is
      the gamma limit; w = ln(1 + u / psi_1(L)) beyond the table (shape < SHAPE_MIN) is out of
      domain;
      ln t = k1 + H(w).
    * ``ggd``: k2 must be > 0 and |g1| = |k3| / k2^{3/2} <= G1_MAX; ln t = k1 + sqrt(k2) D(g1).
    """
    f = tab.f if xp is np else xp.asarray(tab.f)
    if kind in ("g0", "k"):
        u = k2 - float(molc.trigamma(looks))
        wv = molc.w_of_u(xp, u, molc.u_scale(looks))
        dom = wv <= tab.x1
        wv = xp.where(dom, wv, 0.0)
        hv = molc.interp(xp, f, tab.x0, tab.inv_h, tab.n, wv)
        return (y_t - k1) - hv, dom
    pos = k2 > 0.0
    sk = xp.sqrt(xp.where(pos, k2, 1.0))
    g1 = k3 / (xp.where(pos, k2, 1.0) * sk)
    dom = pos & (xp.abs(g1) <= tab.x1)
    g1 = xp.where(dom, g1, 0.0)
    dv = molc.interp(xp, f, tab.x0, tab.inv_h, tab.n, g1)
    return (y_t - k1) - sk * dv, dom


def decide(
    xp,
    box,
    block,
    halo: int,
    origin,
    b: int,
    g: int,
    censor,
    kind: str,
    tab,
    looks: float,
    strip_rows: int = STRIP_ROWS,
):
    """``(mask, stat)`` of the core: mask = tested and ln x_t > ln t; stat = x_t / t (float32,
    > 1 exactly where mask; 0 where not tested). Processes ``strip_rows`` rows at a time."""
    h = block.shape[0] - 2 * halo
    w = block.shape[1] - 2 * halo
    mask = xp.zeros((h, w), dtype=bool)
    stat = xp.zeros((h, w), dtype=xp.float32)
    need = min_ring(b * b - g * g)
    one = np.float32(1.0)
    above = np.nextafter(one, np.float32(2.0))
    for r0 in range(0, h, strip_rows):
        r1 = min(r0 + strip_rows, h)
        sub = block[r0 : r1 + 2 * halo]
        n, k1, k2, k3, y_t, ok_t = ring_cumulants(xp, box, sub, halo, (origin[0] + r0, origin[1]), b, g, censor)
        d, dom = log_excess(xp, kind, tab, looks, k1, k2, k3, y_t)
        tested = ok_t & (n >= float(need)) & dom & xp.isfinite(d)
        m = tested & (d > 0.0)
        s = xp.exp(xp.where(tested, xp.minimum(d, 80.0), -xp.inf)).astype(xp.float32)
        s = xp.where(m & ~(s > one), above, s)  # detected: stat > 1
        s = xp.where(~m & (s > one), one, s)  # not detected: stat <= 1
        mask[r0:r1] = m
        stat[r0:r1] = s
    return mask, stat


def detect_block(block, halo: int, origin, b: int, g: int, censor, kind: str, tab, looks: float):
    """The detectors' ``detect`` body: CPU (NumPy + :mod:`sarship.pipeline.tiling.boxsum`) or, for a
    CuPy block, the GPU twin :func:`sarship.pipeline.gpu.molc.molc_cfar` (same operations)."""
    from sarship.pipeline.gpu import is_device_array, twin

    if censor is not None and halo < censor_halo(b):
        raise ValueError(f"censoring with background {b} needs a halo of {censor_halo(b)}, block has {halo}")
    if is_device_array(block):
        return twin(GPU_TWIN)(block, halo, origin, b, g, censor, kind, tab, looks)
    from sarship.pipeline.tiling.boxsum import centered_box_sum

    x = np.asarray(block)
    if x.ndim != 2:
        raise ValueError(f"block must be 2-D, got shape {x.shape}")
    return decide(np, centered_box_sum, x, halo, origin, b, g, censor, kind, tab, looks)
