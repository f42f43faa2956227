"""Two-parameter (Gaussian) CFAR (``two_parameter``), with the exact small-sample threshold.

The classical detector (Novak & Hesse 1991; ESA SNAP's "Adaptive Thresholding"): estimate
the clutter mean mu and standard deviation sigma from the N cells of the background ring
and declare a target where the tested value exceeds ``mu + t sigma``, with t from the PFA
under a Gaussian model, t = Phi^{-1}(1 - PFA).

Target-window version. When the tested value is the mean of the n = target^2 cells of the
target window, its standard deviation is sigma / sqrt(n): the rule must be
``x_t > mu + t sigma / sqrt(n)`` (the t/sqrt(n) correction SNAP never applied, so its
target-window PFA is far below the one asked for).

Exact threshold (``threshold="student"``, default). mu and sigma are estimates from N
samples: for Gaussian clutter, (x_t - mu_hat) / (sigma_hat * sqrt(1/n + 1/N)) follows
Student's t with N - 1 degrees of freedom, exactly (independent CUT and ring). So the
detection rule (x_t - mu_hat)/sigma_hat > t_N with t_N = sqrt(1/n + 1/N) * t_{N-1}^{-1}(1 -
PFA) has exactly the PFA asked for. ``threshold="gaussian"`` gives the classical
t = Phi^{-1}(1 - PFA) / sqrt(n), exact only as N -> infinity.

``domain`` picks the quantity the Gaussian model is applied to: ``intensity`` (as SNAP),
``amplitude`` (sqrt) or ``db`` (10 log10, where speckle is closest to Gaussian). In ``db``
non-positive values are floored at 1e-30 (-300 dB), a fixed floor so that tiles agree;
data with exact zeros (8-bit quantised JPEG chips, no-data borders) then carry -300 dB
outliers into the ring statistics: use ``intensity`` or ``amplitude`` for such data.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from numba import njit
from pydantic import Field
from scipy import stats

from pipeline.boxsum import centered_box_sum, core
from pipeline.detectors.base import DetectorParams, DetectorSpec, with_defaults


class TwoParameterParams(with_defaults(DetectorParams, "TwoParameterDefaults", pfa=1e-3, guard=21,
                                       background=41, min_area_px=15, merge_px=0)):
    """Parameters of ``two_parameter``.

    Defaults chosen on real data (SAR-Ship-Dataset, HRSID, OpenSARShip; bench/REALDATA.md).
    """

    threshold: Literal["student", "gaussian"] = Field(
        "student", description="exact Student-t threshold for N ring samples, or the classical Gaussian one"
    )
    domain: Literal["intensity", "amplitude", "db"] = Field(
        "intensity", description="quantity modelled as Gaussian"
    )


def threshold(pfa: float, n_ring: int, n_target: int, kind: str = "student") -> float:
    """Threshold on (x_t - mu_hat) / sigma_hat for the given PFA."""
    if kind == "student":
        return float(np.sqrt(1.0 / n_target + 1.0 / n_ring) * stats.t.isf(pfa, n_ring - 1))
    return float(stats.norm.isf(pfa) / np.sqrt(n_target))


def prepare(p: TwoParameterParams) -> dict:
    n_t = p.target**2
    return {
        "n_ring": p.n_ring,
        "n_target": n_t,
        "threshold": threshold(p.pfa, p.n_ring, n_t, p.threshold),
        "statistic": "(target mean - ring mean) / ring std",
        "domain": p.domain,
    }


def _transform(block: np.ndarray, domain: str) -> np.ndarray:
    x = block.astype(np.float64)
    if domain == "amplitude":
        return np.sqrt(np.maximum(x, 0.0))
    if domain == "db":
        return 10.0 * np.log10(np.maximum(x, 1e-30))
    return x


@njit(nogil=True, cache=True)
def _decide(xt, s1b, s1g, s2b, s2g, n_ring, thr, mask, stat):
    h, w = xt.shape
    for i in range(h):
        for j in range(w):
            s1 = s1b[i, j] - s1g[i, j]
            s2 = s2b[i, j] - s2g[i, j]
            mu = s1 / n_ring
            var = (s2 - s1 * mu) / (n_ring - 1.0)
            d = xt[i, j] - mu
            if var > 0.0:
                s = d / np.sqrt(var)
            elif d > 0.0:
                s = np.inf
            else:
                s = 0.0
            stat[i, j] = s
            mask[i, j] = s > thr


def detect(block: np.ndarray, halo: int, origin: tuple[int, int], p: TwoParameterParams, prep: dict):
    """Two-parameter CFAR on one padded tile; returns (mask, standardised statistic)."""
    x = _transform(block, p.domain)
    x2 = x * x
    s1b = centered_box_sum(x, p.background, halo, origin)
    s1g = centered_box_sum(x, p.guard, halo, origin)
    s2b = centered_box_sum(x2, p.background, halo, origin)
    s2g = centered_box_sum(x2, p.guard, halo, origin)
    if p.target == 1:
        xt = np.ascontiguousarray(core(x, halo))
    else:
        xt = centered_box_sum(x, p.target, halo, origin) / float(p.target**2)
    mask = np.empty(xt.shape, np.bool_)
    stat = np.empty(xt.shape, np.float32)
    _decide(xt, s1b, s1g, s2b, s2g, float(prep["n_ring"]), float(prep["threshold"]), mask, stat)
    return mask, stat


SPEC = DetectorSpec(
    name="two_parameter",
    summary="Two-parameter (Gaussian) CFAR with the exact Student-t threshold and target-window correction",
    reference="Novak & Hesse 1991; ESA SNAP Adaptive Thresholding; ALGORITHMS.md 'CFAR families'",
    params=TwoParameterParams,
    prepare=prepare,
    detect=detect,
    input="intensity",
    needs_looks=False,
)
