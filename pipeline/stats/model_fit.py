"""Does the detector's clutter model fit this scene? The false-alarm rate measured on clutter.

A CFAR's threshold gives the false-alarm probability ``pfa`` only where the clutter follows its
model (docs/algorithms/cfar.md, "Where the clutter model does not fit"). This module measures,
per scene, what the detector's own decision does on clutter, and says whether that is the PFA.

Sample. The cells of a scene-wide grid, ``row % stride == 0`` and ``col % stride == 0`` in
scene pixels (:func:`sample_stride`: at most :data:`MAX_SAMPLE` cells, every
:data:`MIN_STRIDE`-th pixel at least), so the sample does not depend on the tiling (as
:func:`sarship.pipeline.land.landmask.sample_stride`'s). A cell counts when its pixel is present
(not absent, not land: land pixels are absent for the detector) and lies farther than
:data:`TARGET_MARGIN_PX` from every detection's bounding box (the targets are not clutter).

Exceedances. For each counted cell, whether the detector's decision at the PFA ``p`` marks it:
the cell's test statistic over the threshold computed from its own background ring, by the
detector's own code (the tile's detection at the asked PFA; at a probe PFA, the detection run
again with ``pfa`` = the probe, or, for ``ca_cfar`` whose statistic x_t / m does not depend on
the PFA, the statistic compared with the probe's threshold; for ``os_cfar``, whose model is
``ca_cfar``'s, the cell-averaging decision of that model with its windows and looks:
:data:`MODEL_PROBE`). Under the model each cell
exceeds with probability ``p``; k exceedances among n cells give the rate k / n.

Interval. The exact (Clopper-Pearson) binomial interval of k / n at :data:`CONFIDENCE`
(Clopper & Pearson 1934):

    lo = B^{-1}(a/2; k, n - k + 1),  hi = B^{-1}(1 - a/2; k + 1, n - k)        (1)

(B^{-1} the beta quantile, ``scipy.stats.binomtest(...).proportion_ci(method="exact")``). The
cells of the grid are not independent (neighbours share their rings, clutter texture is
correlated), so the interval is narrower than the truth; the verdict allows a factor
:data:`TOLERANCE` either side of the PFA:

    fits                   if  lo <= TOLERANCE * p  and  hi >= p / TOLERANCE            (2)
    too many false alarms  if  lo >  TOLERANCE * p
    too few                if  hi <  p / TOLERANCE
    undetermined           if  n * p < MIN_EXPECTED (the sample cannot resolve p)

and the ratio (k / n) / p says how far off. Asked PFAs too small for the sample (a 1e-5
needs 10^6 cells to expect 10) are measured too, but the verdict is that of the probe PFA
:data:`PROBE_PFA` (eq 2 at p = 1e-3), where the clutter tails that decide it (K against
Rayleigh speckle) already part: a heavier tail than the model's shows as a rate many times
the PFA there.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence

import numpy as np

from sarship.pipeline.land import landmask

#: The PFA at which a model is judged when the asked one is smaller (and the probe of ``auto``).
PROBE_PFA = 1e-3
#: Largest sample (grid cells) of a scene.
MAX_SAMPLE = 250_000
#: Smallest grid step: neighbouring pixels of oversampled SAR images are correlated.
MIN_STRIDE = 2
#: Confidence of the Clopper-Pearson interval (eq 1).
CONFIDENCE = 0.95
#: The verdict's allowance (eq 2): a rate within this factor of the PFA (interval included) fits.
TOLERANCE = 2.0
#: ``--detector auto`` moves from a candidate to the next only when the candidate's rate is off by
#: more than this factor (eq 2 with this tolerance): chosen on half A of the shared real chips
#: (bench/REALDATA.md, "Issue 31: clutter-model fit and --detector auto"; 2 to 6 there moved SSDD
#: and HRSID chips to ``k_cfar``/``g0_cfar`` at their defaults and lowered the half's FoM, 8 and
#: more kept ``ca_cfar`` on every real chip); the README's K sea is off by 30 times.
AUTO_TOLERANCE = 8.0
#: Fewer expected exceedances (n x pfa) than this: the sample cannot resolve the PFA.
MIN_EXPECTED = 5.0
#: Cells nearer than this to a detection's bounding box are the target's, not clutter.
TARGET_MARGIN_PX = 4
#: Detectors whose fit is measured (intensity CFARs without a scene-wide pass).
FIT_DETECTORS = ("ca_cfar", "os_cfar", "two_parameter", "k_cfar", "g0_cfar", "ggd_cfar")
#: Detectors whose statistic does not depend on the PFA: the probe compares it with the
#: probe's threshold (``prepare(...)["threshold"]``) instead of detecting again.
STATISTIC_PROBE = ("ca_cfar",)
#: Detectors whose probe is another detector of the same clutter model, with the same windows
#: and looks: ``os_cfar`` (L-look gamma of one mean, like ``ca_cfar``) detecting again at 1e-3
#: costs 2-7 times its detection (its screen passes far more pixels there: measured on a K sea,
#: 1024 x 1024), ``ca_cfar``'s cell-averaging decision at 1e-3 a few per cent.
MODEL_PROBE = {"os_cfar": "ca_cfar"}
#: ``--detector auto``: the candidate models, simplest first (gamma speckle, K, G0).
AUTO_CANDIDATES = ("ca_cfar", "k_cfar", "g0_cfar")
#: Models to suggest when a detector's model does not fit: heavier tails / lighter tails.
HEAVIER = {
    "ca_cfar": ("k_cfar", "g0_cfar"),
    "os_cfar": ("k_cfar", "g0_cfar"),
    "two_parameter": ("k_cfar", "g0_cfar"),
    "ggd_cfar": ("k_cfar", "g0_cfar"),
    "k_cfar": ("g0_cfar",),
    "g0_cfar": (),
}
LIGHTER = {
    "g0_cfar": ("k_cfar", "ca_cfar"),
    "k_cfar": ("ca_cfar",),
    "ggd_cfar": ("k_cfar", "ca_cfar"),
    "ca_cfar": (),
    "os_cfar": ("ca_cfar",),
    "two_parameter": ("ca_cfar",),
}

VALID = np.uint8(1)  # flag bit 0: a counted cell; bit i + 1: exceeds at the i-th PFA


def sample_stride(shape: tuple[int, int], max_sample: int = MAX_SAMPLE) -> int:
    """The grid step of the scene's sample: at most ``max_sample`` cells, at least
    :data:`MIN_STRIDE`."""
    return max(MIN_STRIDE, landmask.sample_stride(shape, max_sample))  # the land mask's rule, floored


def pfas_of(pfa: float) -> tuple[float, ...]:
    """The PFAs measured for a detection at ``pfa``: it, and :data:`PROBE_PFA` when smaller."""
    return (float(pfa),) if pfa >= PROBE_PFA else (float(pfa), PROBE_PFA)


def grid_slices(r0: int, c0: int, h: int, w: int, stride: int) -> tuple[slice, slice, int, int]:
    """The grid cells of the ``(h, w)`` core at scene ``(r0, c0)``: its row and column slices
    and the grid index (row // stride, col // stride) of the first cell."""
    i0, j0 = (-r0) % stride, (-c0) % stride
    return slice(i0, h, stride), slice(j0, w, stride), (r0 + i0) // stride, (c0 + j0) // stride


def pack(valid: np.ndarray, exceed: Sequence[np.ndarray], at: tuple[int, int]) -> dict:
    """A tile's flags: bit 0 where ``valid``, bit ``i + 1`` where ``exceed[i]`` (counted cells
    only); ``at``: the grid index of ``[0, 0]``."""
    flags = np.asarray(valid, bool).astype(np.uint8)
    for i, e in enumerate(exceed):
        flags |= (np.asarray(e, bool) & (flags > 0)).astype(np.uint8) << np.uint8(i + 1)
    return {"at": (int(at[0]), int(at[1])), "flags": flags}


def assemble(pieces: Iterable[dict], shape: tuple[int, int], stride: int) -> np.ndarray:
    """The scene's flag grid from the tiles' :func:`pack` results."""
    grid = np.zeros((-(-shape[0] // stride), -(-shape[1] // stride)), np.uint8)
    for p in pieces:
        f = p["flags"]
        a, b = p["at"]
        grid[a : a + f.shape[0], b : b + f.shape[1]] = f
    return grid


def exclude_targets(grid: np.ndarray, stride: int, boxes: np.ndarray, margin: int = TARGET_MARGIN_PX) -> int:
    """Clear (in place) the cells within ``margin`` pixels of each box ``(r0, c0, r1, c1)``
    (scene pixels, ``r1``/``c1`` exclusive); returns how many counted cells were cleared."""
    before = int(np.count_nonzero(grid & VALID))
    for r0, c0, r1, c1 in np.asarray(boxes, np.int64).reshape(-1, 4):
        a = max(-(-(r0 - margin) // stride), 0)
        b = (r1 - 1 + margin) // stride + 1
        c = max(-(-(c0 - margin) // stride), 0)
        d = (c1 - 1 + margin) // stride + 1
        grid[a:b, c:d] = 0
    return before - int(np.count_nonzero(grid & VALID))


def interval(k: int, n: int, confidence: float = CONFIDENCE) -> tuple[float, float]:
    """The Clopper-Pearson interval of a rate of ``k`` in ``n`` (eq 1)."""
    from scipy.stats import binomtest

    ci = binomtest(int(k), int(n)).proportion_ci(confidence_level=confidence, method="exact")
    return float(ci.low), float(ci.high)


def verdict(pfa: float, k: int, n: int, tolerance: float = TOLERANCE) -> tuple[str, tuple[float, float] | None]:
    """(verdict of eq 2, the interval or None when the sample is empty)."""
    if n == 0:
        return "undetermined", None
    lo, hi = interval(k, n)
    if n * pfa < MIN_EXPECTED:
        return "undetermined", (lo, hi)
    if lo > tolerance * pfa:
        return "too many false alarms", (lo, hi)
    if hi < pfa / tolerance:
        return "too few", (lo, hi)
    return "fits", (lo, hi)


def measure(grid: np.ndarray, pfas: Sequence[float]) -> list[dict]:
    """The rate, interval, ratio and verdict at each PFA of a flag grid (counted cells)."""
    valid = (grid & VALID) > 0
    n = int(np.count_nonzero(valid))
    out = []
    for i, p in enumerate(pfas):
        k = int(np.count_nonzero(grid & np.uint8(1 << (i + 1))))
        v, ci = verdict(p, k, n)
        rate = k / n if n else None
        out.append(
            {
                "pfa": p,
                "exceedances": k,
                "rate": rate,
                "interval": None if ci is None else [ci[0], ci[1]],
                "ratio": None if rate is None else rate / p,
                "verdict": v,
            }
        )
    return out


def record(detector: str, grid: np.ndarray, pfas: Sequence[float], stride: int, excluded: int) -> dict:
    """``run.json``'s ``model_fit``: the measurements at each PFA and the verdict, that of the
    largest PFA measured (the probe when the asked PFA is smaller)."""
    ms = measure(grid, pfas)
    judged = ms[-1]
    return {
        "detector": detector,
        "pfa": pfas[0],
        "probe_pfa": judged["pfa"],
        "sample": int(np.count_nonzero(grid & VALID)),
        "stride_px": stride,
        "excluded_near_detections": excluded,
        "target_margin_px": TARGET_MARGIN_PX,
        "confidence": CONFIDENCE,
        "tolerance": TOLERANCE,
        "measurements": ms,
        "exceedances": judged["exceedances"],
        "rate": judged["rate"],
        "interval": judged["interval"],
        "ratio": judged["ratio"],
        "verdict": judged["verdict"],
    }


def advice(rec: dict) -> str | None:
    """One line for stderr when the model does not fit (None when it fits or is undetermined),
    naming the detectors whose model has the other tail."""
    v, det = rec["verdict"], rec["detector"]
    if v not in ("too many false alarms", "too few"):
        return None
    heavy = v == "too many false alarms"
    how = "heavier" if heavy else "lighter"
    line = (
        f"model fit: the clutter is {how}-tailed than {det}'s model (exceedance {rec['ratio']:.3g}x the PFA "
        f"at {rec['probe_pfa']:g}, {rec['exceedances']} of {rec['sample']} clutter cells): "
        f"{'more' if heavy else 'fewer'} false alarms than pfa x pixels"
    )
    alt = (HEAVIER if heavy else LIGHTER).get(det, ())
    if alt:
        line += f"; try --detector {' or '.join(alt)}"
    return line


def choose(
    records: dict[str, dict], order: Sequence[str] = AUTO_CANDIDATES, tolerance: float = AUTO_TOLERANCE
) -> tuple[str, str]:
    """``auto``'s choice among the candidates' fit ``records`` (by name): the first in ``order``
    that fits at the probe PFA within ``tolerance`` (eq 2 with it); else the one whose rate is
    nearest its PFA (|log ratio|, a rate of zero counted as half an exceedance) among those the
    sample resolves; else (nothing resolved) the first. Returns (name, why)."""
    verdicts = {
        n: verdict(records[n]["probe_pfa"], records[n]["exceedances"], records[n]["sample"], tolerance)[0]
        for n in order
    }
    for name in order:
        if verdicts[name] == "fits":
            return name, (
                f"the first candidate, simplest model first, whose false-alarm rate at "
                f"{records[name]['probe_pfa']:g} is within {tolerance:g}x of it"
            )

    def off(name: str) -> float:
        r = records[name]
        rate = max(r["exceedances"], 0.5) / r["sample"]
        return abs(math.log(rate / r["probe_pfa"]))

    measured = [n for n in order if verdicts[n] != "undetermined"]
    if measured:
        best = min(measured, key=off)
        return best, (
            f"no candidate's model fits within {tolerance:g}x; {best}'s false-alarm rate is nearest its "
            f"PFA ({records[best]['ratio']:.3g}x)"
        )
    return order[0], "the sample cannot resolve the probe PFA (too few sea pixels): the simplest model"
