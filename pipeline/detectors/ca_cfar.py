"""Cell-averaging CFAR (``ca_cfar``) for L-look gamma intensity, with its exact threshold.

Model. Sea clutter intensity in a homogeneous neighbourhood is L-look gamma with unknown
mean mu: x ~ Gamma(L, mu/L) (docs/algorithms/cfar.md; Finn & Johnson 1968; Goldstein 1973;
Novak & Hesse 1991). The cell under test (CUT) is the mean of the ``target`` window,
n = target^2 cells: x_t ~ Gamma(nL, mu/(nL)). The clutter level is the mean of the N = background^2 - guard^2
cells of the ring between the guard and background windows: m ~ Gamma(NL, mu/(NL)).

Threshold. The ratio of two independent scaled chi-square means is Fisher-Snedecor:

    x_t / m  ~  F(2 n L, 2 N L)                                    (exact, any N)

so the detection rule x_t > T * m has PFA = P(F > T), and T = F.isf(PFA; 2nL, 2NL)
(:func:`sarship.pipeline.stats.tails.f_isf`), exact for every N and every L, and independent of mu (CFAR).
For n = 1 this is the classical result that the CUT over the ring mean is F(2L, 2LN).
Its large-N limit is the gamma quantile T -> Q^{-1}(L, PFA)/L used by tools that ignore
the estimation noise of m (they overshoot the PFA by a factor of 2-10 for N ~ 100-500).

Window sums use :mod:`sarship.pipeline.tiling.boxsum` (O(1) per pixel, tiling-invariant), streamed row by
row for the guard and background windows together and fused with the decision.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
from numba import njit
from pydantic import Field

from sarship.pipeline.detectors.base import DetectorParams, DetectorSpec, check_windows, with_defaults
from sarship.pipeline.gpu import is_device_array
from sarship.pipeline.stats.tails import f_isf
from sarship.pipeline.tiling import boxsum, intensity_absent
from sarship.pipeline.tiling.boxsum import box_stream, box_stream_row


class CAParams(
    with_defaults(
        DetectorParams,
        "CADefaults",
        pfa=1e-5,
        guard=41,
        background=81,
        merge_px=4,
        land_mask="texture",
        auto_min_area_px=10,
        auto_min_length_m=25.0,
        auto_min_area_m2=200.0,
    )
):
    """Parameters of ``ca_cfar`` (the shared parameters of docs/algorithms/README.md).

    Defaults chosen on real data by cross-validation (tuned on half A of SAR-Ship-Dataset,
    HRSID and OpenSARShip, reported on half B; bench/REALDATA.md). Size rule (unset
    ``min_area_px`` / ``min_length_m``, :func:`~sarship.pipeline.detectors.base.resolve_size`):
    ships of at least 25 m and 200 m^2 when the scene's pixel spacing is known, of at least
    10 px otherwise.
    """

    nodata: float | None = Field(
        None,
        description="value marking absent pixels besides NaN (e.g. 0 for a zero-filled border); "
        "None: NaN only (exact zeros are data: 8-bit chips have them in dark sea)",
    )


def threshold(pfa: float, looks: float, n_ring: int, n_target: int = 1) -> float:
    """Exact CA-CFAR multiplier T with P(x_t / m > T) = pfa, x_t/m ~ F(2nL, 2NL)."""
    return f_isf(pfa, 2.0 * n_target * looks, 2.0 * n_ring * looks)


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
def _decide_row(xt, bg, gd, inv, thr, mask, stat):
    """One row: ring mean (bg - gd) * (1/N), statistic x_t / mean, decision."""
    for j in range(xt.size):
        m = (bg[j] - gd[j]) * inv
        x = xt[j]
        if m > 0.0:
            s = x / m
        elif x > 0.0:
            s = np.inf
        else:
            s = 0.0
        stat[j] = s
        mask[j] = s > thr


def _make_detect_strip(boxsum_stamp: str):
    """The fused kernel. Its machine code includes that of the :mod:`sarship.pipeline.tiling.boxsum`
    streams, but numba's on-disk cache only watches this file: ``boxsum_stamp`` (a hash of
    ``boxsum.py``) is a closure variable, and closure variables are part of numba's cache
    key, so an edited ``boxsum.py`` gets a fresh compilation instead of stale cached code.
    """

    @njit(nogil=True, cache=True)
    def detect_strip(block, xs, halo, g0r, g0c, target, guard, background, inv, thr, c0, c1, mask, stat):
        """Columns [c0, c1) of the core: window sums streamed row by row, then the decision.

        One :mod:`sarship.pipeline.tiling.boxsum` stream per window (the additions of ``centered_box_sum``),
        all in lockstep, so no full-size float64 intermediate is ever written.
        """
        boxsum_stamp  # noqa: B018 (keeps the stamp in the closure, hence in the cache key)
        h = mask.shape[0]
        w = c1 - c0
        ob = halo - background // 2
        og = halo - guard // 2
        xb = xs[ob : ob + h + background - 1, ob + c0 : ob + c1 + background - 1]
        xg = xs[og : og + h + guard - 1, og + c0 : og + c1 + guard - 1]
        sb = box_stream(background, w, g0r + ob)
        sg = box_stream(guard, w, g0r + og)
        bgrow = np.empty(w, np.float64)
        gdrow = np.empty(w, np.float64)
        if target == 1:
            for i in range(h):
                box_stream_row(xb, background, g0c + ob + c0, sb, i, bgrow)
                box_stream_row(xg, guard, g0c + og + c0, sg, i, gdrow)
                _decide_row(
                    block[halo + i, halo + c0 : halo + c1], bgrow, gdrow, inv, thr, mask[i, c0:c1], stat[i, c0:c1]
                )
        else:
            ot = halo - target // 2
            xt = xs[ot : ot + h + target - 1, ot + c0 : ot + c1 + target - 1]
            stt = box_stream(target, w, g0r + ot)
            trow = np.empty(w, np.float64)
            tt = float(target * target)
            for i in range(h):
                box_stream_row(xb, background, g0c + ob + c0, sb, i, bgrow)
                box_stream_row(xg, guard, g0c + og + c0, sg, i, gdrow)
                box_stream_row(xt, target, g0c + ot + c0, stt, i, trow)
                for j in range(w):
                    trow[j] = trow[j] / tt
                _decide_row(trow, bgrow, gdrow, inv, thr, mask[i, c0:c1], stat[i, c0:c1])

    return detect_strip


_detect_strip = _make_detect_strip(hashlib.sha256(Path(boxsum.__file__).read_bytes()).hexdigest())


def detect(block: np.ndarray, halo: int, origin: tuple[int, int], p: CAParams, prep: dict):
    """CA-CFAR on one padded tile; returns (mask, x_t / ring mean).

    A CuPy ``block`` runs on its GPU (:func:`sarship.pipeline.gpu.cfar.ca_cfar`) and returns CuPy
    arrays, bit-identical to the CPU's.

    The core is processed in column strips of ``boxsum.STRIP`` pixels (the window streams
    of a strip stay in L2); strips change nothing in the sums, whose column blocks are
    aligned on global columns.
    """
    b, g, t = int(p.background), int(p.guard), int(p.target)
    check_windows(halo, b, g, t)
    if is_device_array(block):  # CuPy block: the GPU twin (pipeline.gpu.cfar), same sums and rule
        return SPEC.twin()(
            block,
            halo,
            origin,
            b,
            g,
            t,
            int(prep["n_ring"]),
            float(prep["threshold"]),
            pfa=float(p.pfa),
            looks=float(prep["looks"]),
            nodata=p.nodata,
        )
    ok = intensity_absent.present(block, p.nodata)
    if not ok.all():  # absent pixels (module docstring of pipeline.intensity_absent)
        xz = intensity_absent.fill(
            block if block.dtype in (np.float32, np.float64) else block.astype(np.float64), ok, 0.0
        )
        mask, stat = _detect_complete(xz, halo, origin, t, g, b, prep)
        intensity_absent.ca_redo(
            xz,
            ok,
            halo,
            origin,
            b,
            g,
            t,
            int(prep["n_ring"]),
            float(p.pfa),
            float(prep["looks"]),
            float(prep["threshold"]),
            mask,
            stat,
            boxsum.centered_box_sum,
        )
        return mask, stat
    return _detect_complete(block, halo, origin, t, g, b, prep)


def _detect_complete(block, halo, origin, t, g, b, prep):
    h = block.shape[0] - 2 * halo
    w = block.shape[1] - 2 * halo
    xs = block if block.dtype in (np.float32, np.float64) else block.astype(np.float64)
    mask = np.empty((h, w), np.bool_)
    stat = np.empty((h, w), np.float32)
    inv = 1.0 / float(prep["n_ring"])
    thr = float(prep["threshold"])
    strip = boxsum.STRIP
    for c0 in range(0, w, strip):
        _detect_strip(
            block, xs, halo, int(origin[0]), int(origin[1]), t, g, b, inv, thr, c0, min(c0 + strip, w), mask, stat
        )
    return mask, stat


SPEC = DetectorSpec(
    name="ca_cfar",
    summary="Cell-averaging CFAR for L-look gamma intensity, exact F-distributed threshold",
    reference="Finn & Johnson 1968; Goldstein 1973; Novak & Hesse 1991; docs/algorithms/cfar.md",
    params=CAParams,
    prepare=prepare,
    detect=detect,
    input="intensity",
    needs_looks=True,
    gpu="sarship.pipeline.gpu.cfar:ca_cfar",
)
