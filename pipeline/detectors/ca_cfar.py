"""Cell-averaging CFAR (``ca_cfar``) for L-look gamma intensity, with its exact threshold.

Model. Sea clutter intensity in a homogeneous neighbourhood is L-look gamma with unknown
mean mu: x ~ Gamma(L, mu/L) (ALGORITHMS.md, "CFAR families"; Goldstein 1973; Novak & Hesse
1991). The cell under test (CUT) is the mean of the ``target`` window, n = target^2 cells:
x_t ~ Gamma(nL, mu/(nL)). The clutter level is the mean of the N = background^2 - guard^2
cells of the ring between the guard and background windows: m ~ Gamma(NL, mu/(NL)).

Threshold. The ratio of two independent scaled chi-square means is Fisher-Snedecor:

    x_t / m  ~  F(2 n L, 2 N L)                                    (exact, any N)

so the detection rule x_t > T * m has PFA = P(F > T), and T = F.isf(PFA; 2nL, 2NL)
(``scipy.stats.f.isf``), exact for every N and every L, and independent of mu (CFAR).
For n = 1 this is the classical result that the CUT over the ring mean is F(2L, 2LN).
Its large-N limit is the gamma quantile T -> Q^{-1}(L, PFA)/L used by tools that ignore
the estimation noise of m (they overshoot the PFA by a factor of 2-10 for N ~ 100-500).

Window sums use :mod:`pipeline.boxsum` (O(1) per pixel, tiling-invariant).
"""

from __future__ import annotations

import numpy as np
from numba import njit
from scipy import stats

from pipeline.boxsum import centered_box_sum, core
from pipeline.detectors.base import DetectorParams, DetectorSpec


class CAParams(DetectorParams):
    """Parameters of ``ca_cfar`` (all shared names of CONTRACT.md)."""


def threshold(pfa: float, looks: float, n_ring: int, n_target: int = 1) -> float:
    """Exact CA-CFAR multiplier T with P(x_t / m > T) = pfa, x_t/m ~ F(2nL, 2NL)."""
    return float(stats.f.isf(pfa, 2.0 * n_target * looks, 2.0 * n_ring * looks))


def prepare(p: CAParams) -> dict:
    if p.looks is None:
        raise ValueError("looks must be resolved before prepare()")
    n_t = p.target**2
    return {
        "n_ring": p.n_ring,
        "n_target": n_t,
        "looks": p.looks,
        "threshold": threshold(p.pfa, p.looks, p.n_ring, n_t),
        "statistic": "target-window mean / ring mean",
        "distribution": f"F(2*{n_t}*L, 2*{p.n_ring}*L)",
    }


@njit(nogil=True, cache=True)
def _decide(xt, bg, gd, n_ring, thr, mask, stat):
    h, w = xt.shape
    inv = 1.0 / n_ring
    for i in range(h):
        for j in range(w):
            m = (bg[i, j] - gd[i, j]) * inv
            x = xt[i, j]
            if m > 0.0:
                s = x / m
            elif x > 0.0:
                s = np.inf
            else:
                s = 0.0
            stat[i, j] = s
            mask[i, j] = s > thr


def detect(block: np.ndarray, halo: int, origin: tuple[int, int], p: CAParams, prep: dict):
    """CA-CFAR on one padded tile; returns (mask, x_t / ring mean)."""
    bg = centered_box_sum(block, p.background, halo, origin)
    gd = centered_box_sum(block, p.guard, halo, origin)
    if p.target == 1:
        xt = core(block, halo)
    else:
        xt = centered_box_sum(block, p.target, halo, origin) / float(p.target**2)
    mask = np.empty(bg.shape, np.bool_)
    stat = np.empty(bg.shape, np.float32)
    _decide(xt, bg, gd, float(prep["n_ring"]), float(prep["threshold"]), mask, stat)
    return mask, stat


SPEC = DetectorSpec(
    name="ca_cfar",
    summary="Cell-averaging CFAR for L-look gamma intensity, exact F-distributed threshold",
    reference="Goldstein 1973; Novak & Hesse 1991; ALGORITHMS.md 'CFAR families'",
    params=CAParams,
    prepare=prepare,
    detect=detect,
    input="intensity",
    needs_looks=True,
)
