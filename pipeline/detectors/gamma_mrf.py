"""``gamma_mrf``: gamma-mixture pixel classification with a Potts MRF prior solved by ICM (seed 003).

Liu et al. 2017 (docs/references.md), section 3 "pixel classification for target screening";
the page docs/algorithms/gamma_mrf.md states every choice. Equation numbers are the paper's.

1. **Mixture** (eq (1)-(2)): a K = 4 class gamma mixture of the intensities with L looks (calm
   sea, rough sea, flat land, man-made), fitted by EM (:mod:`sarship.pipeline.stats.gamma_mixture`) on a
   scene-wide sample (the pixels of the global grid ``row % sample_stride == 0 and col %
   sample_stride == 0``, sorted by position: independent of the tiling). Classes are ordered by
   mean; the brightest (K-1) is the ship class.
2. **MAP with an MRF prior** (eq (3)-(7)): the label x_s of pixel s maximises
   ``p(y_s | x_s) P(x_s | x_eta_s)`` (eq (5)) with a Gibbs prior (eq (6)) of Potts pair cliques
   over the 4- or 8-neighbourhood eta; the local energy to minimise (eq (7)) is
   ``E_s(k) = L ln mu_k + L y_s / mu_k + beta * #{t in eta_s present: x_t != k}``
   (the class-independent part of -ln f dropped; eq (5) puts the MRF conditional in place of
   the label prior, so ``-ln pi_k``, the mixture weight as a single-site term, only with
   ``use_weights``, default off).
3. **ICM** (the paper's solver, its ref. [24]): labels start at the mixture's MAP labels (the
   paper: "the mixture estimate is the initial labelling"); each sweep first re-estimates the
   class means mu_k from the current labels (the paper: "the K gamma pdfs are re-estimated,
   updating mu_i") and then moves every pixel to its lowest-energy class given its
   neighbours. The paper stops when fewer than a given fraction of labels change between
   sweeps or after a fixed number of sweeps: here ``change_tol`` and ``sweeps``.
4. **Ships** = pixels of the brightest class (with the classes EM left identical to it or too
   light to be clutter: :func:`ship_from`) inside the sea ROI (absent pixels: the land mask
   sets land to NaN before the detector runs), then discrimination (section 3.3: geometry and
   scattering, no values given): a ship pixel's intensity must exceed the (1 - ``pfa``)
   quantile of the fitted clutter mixture (``scatter``), a candidate's peak the (1 -
   ``peak_pfa``) quantile (:func:`discriminate`, on whole components after the merge), and
   the geometry rule (length, width) is the shared size rule (``min_area_px``,
   ``min_length_m``, ``max_length_m``; base.resolve_size).

Tiling. ICM updates pixels in a fixed colouring by *global* coordinates (2 colours, the
checkerboard, for the 4-neighbourhood; 4 colours, ``(row % 2, col % 2)``, for the 8-neighbourhood:
no two neighbours share a colour, so each colour's update is a true Gauss-Seidel ICM step
whatever the order inside it). A pixel's label after p colour phases depends only on pixels
within p steps, so with ``halo = sweeps x colours`` the core's labels are those of the whole
scene. The per-sweep re-estimation is a global reduction: run_request's scene passes
(``DetectorSpec.scene_passes_max``): pass 0 pools the EM sample; pass m >= 1 runs the m - 1
sweeps known so far on every tile and returns the per-class exact sums of the core's
intensities (float32 values summed as integers per binary exponent: the same bits for any
tiling) and label counts, from which ``reduce`` takes mu for the next sweep.

Small scenes (:func:`sample_plan`, before any work; :func:`reduce`, after the land mask). EM
needs ``SAMPLES_PER_CLASS`` (10) sampled pixels with data a class. A scene of fewer pixels than
``10 x classes`` (40 by default: a 6 x 6 chip) is refused (:class:`InputError`, exit 2, naming
the minimum). Otherwise, where the grid at ``sample_stride`` holds fewer than ``sample_min``
pixels (default 1600, chosen on half A of the real chips; with ``sample_stride`` given, fewer
than ``10 x classes``), the stride is
lowered to the largest that holds that many (1 at the least; all of a scene smaller than
``sample_min``), recorded in ``run.json`` ``parameters.sample_stride`` and ``warnings``. When
absent pixels (land, no-data) leave the sample short of ``10 x classes``, pass 0 runs again at
half the stride (``prepared.sample_stride``, a warning) down to 1; too few pixels with data at
stride 1 is an :class:`InputError`. The rule is the detector's (:func:`for_scene`,
:func:`reduce`): the GPU path reads the same parameters and prepared values.

Absent pixels (NaN, +-inf, negative, or ``nodata``) are never ships, are left out of the
mixture sample and of the class sums, carry no label and cast no vote: a present pixel's
Potts term counts only its present neighbours (an absent neighbour adds 0 to every class's
energy, the same as a neighbour outside an image border).
"""

from __future__ import annotations

import math
from fractions import Fraction
from typing import Literal

import numpy as np
from numba import njit
from pydantic import Field, model_validator

from sarship.pipeline.detectors.base import DetectorParams, DetectorSpec, with_defaults
from sarship.pipeline.errors import InputError
from sarship.pipeline.gpu import is_device_array
from sarship.pipeline.stats.gamma_mixture import MEAN_FLOOR, class_energy_terms, fit_gamma_mixture, mixture_isf

#: Bins of the exact class sums: float32 binary exponents, offset so that every finite value fits.
EXP_BINS = 300
EXP_OFFSET = 180
#: EM sample pixels (with data) a class at least; a scene of fewer than this x ``classes`` pixels is refused.
SAMPLES_PER_CLASS = 10
#: Scene passes at most: the EM pass, its repeats at half the stride (``sample_stride`` <= 256:
#: 8), and one a sweep (``sweeps`` <= 20), with a margin.
MAX_PASSES = 31
ANOTHER_PASS = "another_pass"


class GammaMRFParams(with_defaults(DetectorParams, "GammaMRFDefaults", pfa=1e-3, merge_px=4, land_mask="texture")):
    """Parameters of ``gamma_mrf`` (module docstring; docs/algorithms/gamma_mrf.md).

    ``pfa`` is the scattering rule's false-alarm probability under the fitted clutter mixture
    (``scatter="quantile"``); ``target``/``guard``/``background`` are unused (no windows).
    ``beta`` 0.5 and ``merge_px`` 4 were chosen on half A of the real chips (SAR-Ship-Dataset
    and HRSID; reported on half B in bench/REALDATA.md).
    """

    classes: int = Field(
        4,
        ge=2,
        le=8,
        description="K, classes of the gamma mixture (the paper: 4, calm sea, "
        "rough sea, flat land, man-made); the brightest is the ship class",
    )
    beta: float = Field(0.5, ge=0.0, le=20.0, description="Potts interaction (nats per disagreeing neighbour, eq (6))")
    neighbourhood: int = Field(
        8, ge=4, le=8, json_schema_extra={"enum": [4, 8]}, description="MRF neighbourhood eta: 4 or 8 neighbours"
    )
    sweeps: int = Field(
        5,
        ge=1,
        le=20,
        description="ICM sweeps at most (the halo is sweeps x colours: 2 for the "
        "4-neighbourhood, 4 for the 8-neighbourhood)",
    )
    change_tol: float = Field(
        0.0,
        ge=0.0,
        lt=1.0,
        description="stop the sweeps early when fewer than this fraction of the present "
        "pixels changed label in the last sweep (0: always run every sweep)",
    )
    reestimate: bool = Field(
        True,
        description="re-estimate the class means from the labels before each sweep "
        "(the paper; one extra scene pass a sweep); false: EM means throughout",
    )
    use_weights: bool = Field(
        False, description="include -ln pi_k (mixture weights) in the energy; false: Potts prior only"
    )
    scatter: Literal["quantile", "none"] = Field(
        "quantile",
        description="scattering rule: 'quantile': ship pixels exceed the (1 - pfa) quantile of the "
        "fitted clutter mixture (the clutter classes, see clutter_weight); 'none': the ship "
        "class(es) alone",
    )
    peak_pfa: float | None = Field(
        1e-9,
        ge=1e-15,
        lt=0.5,
        description="scattering rule on whole candidates: a ship's peak intensity exceeds the (1 - peak_pfa) "
        "quantile of the fitted clutter mixture; none: off",
    )
    clutter_weight: float = Field(
        0.05,
        gt=0.0,
        lt=1.0,
        description="classes up to the brightest holding at least this fraction of the scene are clutter; the "
        "classes above are ship classes (at least the brightest, the paper's man-made class)",
    )
    sample_stride: int = Field(
        8,
        ge=1,
        le=256,
        description="EM sample: pixels with row, col % stride == 0 (lowered on a small scene: see sample_min)",
    )
    sample_min: int = Field(
        1600,
        ge=1,
        le=1_000_000,
        description="EM sample size wanted: where the grid at the default sample_stride holds "
        "fewer pixels (a small chip), the stride is lowered to the largest that "
        "holds this many (1 at the least); a given sample_stride is lowered only "
        "below 10 x classes (1600: chosen on half A of the real chips)",
    )
    em_max_iter: int = Field(300, ge=1, le=10000, description="EM iterations at most")
    nodata: float | None = Field(None, description="value marking absent pixels besides NaN")

    @model_validator(mode="after")
    def _own(self):
        if self.neighbourhood not in (4, 8):
            raise ValueError(f"neighbourhood must be 4 or 8, got {self.neighbourhood}")
        if self.looks is not None and not math.isfinite(self.looks):
            raise ValueError(f"looks must be finite, got {self.looks}")
        return self


def colours(p: GammaMRFParams) -> int:
    """Colour phases a sweep: 2 (checkerboard) for the 4-neighbourhood, 4 for the 8-neighbourhood."""
    return 2 if int(p.neighbourhood) == 4 else 4


def halo(p: GammaMRFParams) -> int:
    """Every colour phase widens a label's dependence by one pixel: sweeps x colours."""
    return int(p.sweeps) * colours(p)


def grid_count(shape, stride: int) -> int:
    """Pixels of a ``shape`` scene on the global sample grid ``row % stride == 0 and col % stride == 0``."""
    H, W = (int(v) for v in shape)
    return -(-H // int(stride)) * -(-W // int(stride))


def sample_plan(shape, p: GammaMRFParams) -> tuple[int, str | None]:
    """The EM sample's stride for a scene of ``shape`` (rows, cols), before any work.

    Parameters
    ----------
    shape : tuple of int
        The scene's rows and columns.
    p : GammaMRFParams
        The run's parameters (``classes``, ``sample_stride``, ``sample_min``).

    Returns
    -------
    stride : int
        ``sample_stride`` where its grid holds at least the wanted sample (``sample_min``, or
        ``SAMPLES_PER_CLASS x classes`` when ``sample_stride`` was given), else the largest
        stride below it whose grid does (1 at the least).
    note : str or None
        A one-line warning naming the change, None when the stride is kept.

    Raises
    ------
    InputError
        The scene holds fewer than ``SAMPLES_PER_CLASS x classes`` pixels (the minimum size).
    """
    H, W = (int(v) for v in shape)
    need = SAMPLES_PER_CLASS * int(p.classes)
    if H * W < need:
        raise InputError(
            f"gamma_mrf: the scene is {H} x {W} = {H * W} pixels, too small for {p.classes} classes: "
            f"at least {need} pixels needed ({SAMPLES_PER_CLASS} a class, e.g. "
            f"{math.isqrt(need - 1) + 1} x {math.isqrt(need - 1) + 1})"
        )
    s = int(p.sample_stride)
    want = need if "sample_stride" in p.model_fields_set else min(int(p.sample_min), H * W)
    want = max(want, need)
    while s > 1 and grid_count((H, W), s) < want:
        s -= 1
    if s == int(p.sample_stride):
        return s, None
    return s, (
        f"gamma_mrf: sample_stride {p.sample_stride} lowered to {s} on this {H} x {W} scene "
        f"(EM sample {grid_count((H, W), s)} pixels, {grid_count((H, W), p.sample_stride)} at stride "
        f"{p.sample_stride}; wanted {want})"
    )


def for_scene(p: GammaMRFParams, shape, spacing=None) -> tuple[GammaMRFParams, list[str]]:
    """``DetectorSpec.for_scene``: the parameters with :func:`sample_plan`'s stride, and its warning."""
    s, note = sample_plan(shape, p)
    if note is None:
        return p, []
    return p.model_copy(update={"sample_stride": s}), [note]


def prepare(p: GammaMRFParams) -> dict:
    if p.looks is None:
        raise ValueError("looks must be resolved before prepare()")
    return {
        "looks": float(p.looks),
        "classes": int(p.classes),
        "threshold": 0.0,
        "statistic": "ICM energy gap (nats): best other class minus the ship class, at the pixel's last update",
        "sweep_means": [],
        "passes": 0,
    }


# ---------------------------------------------------------------------------------- kernels


@njit(nogil=True, cache=True)
def _best(y, i, j, lab, ok, a, b, beta, nbh, K, ks, cnt):
    """Lowest-energy class of pixel (i, j) given its neighbours' labels (eq (7)); ties go to the
    lower class. Returns (label, gap): with a ship label (>= ``ks``), the best clutter class's
    energy minus the best ship class's (> 0), else 0."""
    H, W = lab.shape
    for k in range(K):
        cnt[k] = 0
    npres = 0
    for di in range(-1, 2):
        ii = i + di
        if ii < 0 or ii >= H:
            continue
        for dj in range(-1, 2):
            if di == 0 and dj == 0:
                continue
            if nbh == 4 and di != 0 and dj != 0:
                continue
            jj = j + dj
            if jj < 0 or jj >= W or not ok[ii, jj]:
                continue
            npres += 1
            cnt[lab[ii, jj]] += 1
    v = np.float64(y[i, j])
    best = 0
    ebest = np.inf
    eother = np.inf
    for k in range(K):
        e = a[k] + b[k] * v + beta * np.float64(npres - cnt[k])
        if e < ebest:
            ebest = e
            best = k
        if k < ks and e < eother:
            eother = e
    gap = eother - ebest if best >= ks else 0.0
    return best, gap


@njit(nogil=True, cache=True)
def icm(y, ok, r0, c0, a0, b0, A, B, beta, nbh, ks, lab, prev, gap):
    """Initial mixture-MAP labels (energies ``a0 + b0 y``), then ``A.shape[0]`` ICM sweeps, sweep
    s with the energies ``A[s] + B[s] y`` plus the Potts term; in place into ``lab`` (int8, -1
    where absent). ``prev``: the labels before the last sweep; ``gap``: a ship pixel's (label
    >= ``ks``) energy gap at its last update (0 elsewhere). ``(r0, c0)``: global position of ``y[0, 0]`` (the
    colouring is by global coordinates)."""
    H, W = y.shape
    K = a0.shape[0]
    cnt = np.zeros(K, np.int64)
    for i in range(H):
        for j in range(W):
            gap[i, j] = 0.0
            if not ok[i, j]:
                lab[i, j] = -1
                continue
            v = np.float64(y[i, j])
            best = 0
            ebest = np.inf
            for k in range(K):
                e = a0[k] + b0[k] * v
                if e < ebest:
                    ebest = e
                    best = k
            lab[i, j] = best
            if best >= ks:
                eo = np.inf
                for k in range(ks):
                    e = a0[k] + b0[k] * v
                    if e < eo:
                        eo = e
                gap[i, j] = eo - ebest
    S = A.shape[0]
    ncol = 2 if nbh == 4 else 4
    for s in range(S):
        if s == S - 1:
            prev[:, :] = lab
        a = A[s]
        b = B[s]
        for col in range(ncol):
            for i in range(H):
                gr = (r0 + i) & 1
                if nbh == 4:
                    js = (col ^ gr ^ (c0 & 1)) & 1
                else:
                    if gr != (col >> 1):
                        continue
                    js = ((col & 1) ^ (c0 & 1)) & 1
                for j in range(js, W, 2):
                    if not ok[i, j]:
                        continue
                    best, g = _best(y, i, j, lab, ok, a, b, beta, nbh, K, ks, cnt)
                    lab[i, j] = best
                    gap[i, j] = g
    if S == 0:
        prev[:, :] = lab


@njit(nogil=True, cache=True)
def class_sums(y, lab, K, acc, counts):
    """Exact per-class sums of ``y`` (float32 values) as integers per binary exponent:
    ``acc[k, e + EXP_OFFSET] += m`` with ``y = m 2^e``, ``m`` a 24-bit integer; ``counts[k]``:
    labels k. Integer sums: the same whatever the order, so whatever the tiling."""
    H, W = y.shape
    for i in range(H):
        for j in range(W):
            k = lab[i, j]
            if k < 0:
                continue
            counts[k] += 1
            v = np.float32(y[i, j])
            if v == 0:
                continue
            m, e = math.frexp(np.float64(v))
            acc[k, e - 24 + 180] += np.int64(m * 16777216.0)


# ----------------------------------------------------------------------------- host helpers


def present(block, nodata=None) -> np.ndarray:
    """Present pixels: finite, non-negative (an intensity) and != ``nodata``."""
    ok = np.isfinite(block)
    with np.errstate(invalid="ignore"):
        ok &= block >= 0
    if nodata is not None:
        ok &= block != block.dtype.type(nodata)
    return ok


def energies(prep: dict, p: GammaMRFParams) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(a0, b0, A, B)``: the initial (EM) energy terms and one row per sweep (module docstring)."""
    mix = prep["mixture"]
    w = np.asarray(mix["weights"], np.float64) if p.use_weights else np.ones(len(mix["means"]))
    L = float(prep["looks"])
    a0, b0 = class_energy_terms(w, mix["means"], L)
    rows = [class_energy_terms(w, mu, L) for mu in prep["sweep_means"]]
    K = len(a0)
    A = np.array([r[0] for r in rows], np.float64).reshape(-1, K)
    B = np.array([r[1] for r in rows], np.float64).reshape(-1, K)
    return a0, b0, A, B


def labels(block, halo_px: int, origin, p: GammaMRFParams, prep: dict):
    """ICM on the whole block with the sweeps known in ``prep``: (labels, prev, gap, ok) of the block."""
    x = np.ascontiguousarray(block)
    if x.dtype != np.float32 and x.dtype != np.float64:
        x = x.astype(np.float64)
    ok = present(x, p.nodata)
    a0, b0, A, B = energies(prep, p)
    lab = np.empty(x.shape, np.int8)
    prev = np.empty(x.shape, np.int8)
    gap = np.empty(x.shape, np.float64)
    icm(
        x,
        ok,
        int(origin[0]),
        int(origin[1]),
        a0,
        b0,
        A,
        B,
        float(p.beta),
        int(p.neighbourhood),
        int(prep["ship_from"]),
        lab,
        prev,
        gap,
    )
    return lab, prev, gap, ok


def _core(a, h: int):
    return a[h : a.shape[0] - h, h : a.shape[1] - h]


def _grid(n0: int, n: int, s: int) -> np.ndarray:
    return np.arange((-n0) % s, n, s)


def scene_pass(block, halo_px, origin, p: GammaMRFParams, prep: dict) -> dict:
    """Pass 0: the core's present pixels on the ``sample_stride`` grid with their global (row, col).
    Pass m >= 1: the m - 1 known sweeps on the block; exact class sums and counts of the
    core's labels, and the labels changed by the last sweep."""
    if is_device_array(block):
        gpu_labels = SPEC.twin().labels

        if not prep.get("mixture"):
            block = block.get()
        else:
            lab, prev = gpu_labels(block, halo_px, origin, p, prep)
            y = _core(block, halo_px).astype(block.dtype).get()
            return _stats(y, _core(lab, halo_px).get(), _core(prev, halo_px).get(), prep)
    x = np.asarray(block)
    if x.ndim != 2:
        raise ValueError(f"gamma_mrf needs a 2-D intensity block, got shape {x.shape}")
    hp = int(halo_px)
    if not prep.get("mixture"):
        core = _core(x, hp)
        r0, c0 = origin[0] + hp, origin[1] + hp
        s = int(prep.get("sample_stride", p.sample_stride))
        ri, ci = _grid(r0, core.shape[0], s), _grid(c0, core.shape[1], s)
        sub = core[np.ix_(ri, ci)]
        keep = present(sub, p.nodata)
        rr, cc = np.meshgrid(ri + r0, ci + c0, indexing="ij")
        return {"rc": np.stack([rr[keep], cc[keep]], 1).astype(np.int64), "y": sub[keep].astype(np.float64)}
    lab, prev, _, _ = labels(x, hp, origin, p, prep)
    return _stats(_core(x, hp), _core(lab, hp), _core(prev, hp), prep)


def _stats(y, lab, prev, prep: dict) -> dict:
    K = int(prep["classes"])
    acc = np.zeros((K, EXP_BINS), np.int64)
    counts = np.zeros(K, np.int64)
    class_sums(np.ascontiguousarray(y), np.ascontiguousarray(lab), K, acc, counts)
    changed = int(np.count_nonzero(lab != prev)) if prep["sweep_means"] else 0
    return {"acc": acc, "counts": counts, "changed": changed}


def exact_means(parts: list[dict], previous, floor: float) -> list[float]:
    """Class means from the tiles' exact sums: sum of m 2^e over tiles and exponents as a
    rational, divided by the count, rounded once to float64; an empty class keeps ``previous``."""
    K = len(previous)
    acc = sum((q["acc"].astype(object) for q in parts), np.zeros((K, EXP_BINS), object))
    counts = [int(sum(int(q["counts"][k]) for q in parts)) for k in range(K)]
    out = []
    for k in range(K):
        if counts[k] == 0:
            out.append(float(previous[k]))
            continue
        tot = Fraction(0)
        for e in range(EXP_BINS):
            if acc[k, e]:
                tot += Fraction(int(acc[k, e])) * Fraction(2) ** (e - EXP_OFFSET)
        out.append(max(float(tot / counts[k]), floor))
    return out


def ship_from(weights, means, clutter_weight: float) -> int:
    """First ship class. The brightest class is the ship class (the paper's man-made class),
    together with any class EM left identical to it (relative difference of the means < 1e-9:
    saturated 8-bit chips start two classes on the same values and EM never parts them). Below
    it, the classes up to the brightest one holding at least ``clutter_weight`` of the sample are
    clutter (class 0 always), those above it ship classes too. ``K`` (no ship class) when every
    class is the same."""
    K = len(means)
    top = K - 1
    while top > 0 and means[top - 1] >= means[K - 1] * (1.0 - 1e-9):
        top -= 1
    if top == 0:
        return K
    heavy = [k for k in range(top) if weights[k] >= clutter_weight]
    return min(top, (max(heavy) if heavy else 0) + 1)


def reduce(parts: list[dict], p: GammaMRFParams, prep: dict) -> dict:
    """Pass 0: EM on the pooled sample (sorted by global position) and the scattering threshold.
    Pass m >= 1: the class means for sweep m (exact); asks for another pass until ``sweeps``
    are known or fewer than ``change_tol`` of the labels changed."""
    npass = int(prep.get("passes", 0)) + 1
    if not prep.get("mixture"):
        rc = np.concatenate([q["rc"] for q in parts])
        y = np.concatenate([q["y"] for q in parts])
        y = y[np.lexsort((rc[:, 1], rc[:, 0]))]
        need = SAMPLES_PER_CLASS * int(p.classes)
        stride = int(prep.get("sample_stride", p.sample_stride))
        if y.size < need:
            if stride > 1:  # absent pixels (land, no-data) left the sample short: pass 0 again, denser
                half = stride // 2
                note = (
                    f"gamma_mrf: {y.size} sampled pixels with data at sample_stride {stride} (fewer than "
                    f"{need}): sampled again at stride {half}"
                )
                return {"passes": npass, "sample_stride": half, ANOTHER_PASS: True, "warnings": [note]}
            raise InputError(
                f"gamma_mrf: {y.size} pixels with data (after the land mask and nodata) are too few "
                f"for {p.classes} classes: at least {need} needed ({SAMPLES_PER_CLASS} a class)"
            )
        mix = fit_gamma_mixture(y, prep["looks"], p.classes, max_iter=p.em_max_iter)
        floor = MEAN_FLOOR * max(float(y.mean()), 1e-300)
        ks = ship_from(mix.weights, mix.means, p.clutter_weight)
        wc, mc = mix.weights[:ks], mix.means[:ks]
        q = mixture_isf(p.pfa, wc, mc, prep["looks"]) if p.scatter == "quantile" else 0.0
        qp = mixture_isf(p.peak_pfa, wc, mc, prep["looks"]) if p.peak_pfa is not None else None
        out = {
            "mixture": mix.to_dict(),
            "sample_size": int(y.size),
            "sample_stride": stride,
            "mean_floor": floor,
            "ship_from": ks,
            "scatter_threshold": float(q),
            "peak_threshold": qp,
            "passes": npass,
        }
        if p.reestimate:
            out.update({"sweep_means": [], ANOTHER_PASS: True})
        else:
            out["sweep_means"] = [list(mix.to_dict()["means"])] * int(p.sweeps)
        return out
    known = prep["sweep_means"]
    previous = known[-1] if known else prep["mixture"]["means"]
    n = int(sum(int(q["counts"].sum()) for q in parts))
    changed = int(sum(q["changed"] for q in parts))
    history = list(prep.get("changed_fraction", []))
    if known:
        history.append(changed / max(n, 1))
        if history[-1] < p.change_tol:
            return {"passes": npass, "changed_fraction": history, "stopped": "change_tol"}
    mu = exact_means(parts, previous, float(prep["mean_floor"]))
    sweep_means = [*known, mu]
    out = {"passes": npass, "sweep_means": sweep_means, "changed_fraction": history, "present_px": n}
    if len(sweep_means) < int(p.sweeps):
        out[ANOTHER_PASS] = True
    else:
        out["stopped"] = "sweeps"
    return out


def detect(block, halo_px, origin, p: GammaMRFParams, prep: dict):
    """Labels after the sweeps; mask = brightest class & present & (intensity > scattering
    threshold); stat = the ship class's ICM energy gap (> 0 where the mask is set)."""
    if is_device_array(block):
        return SPEC.twin().detect(block, halo_px, origin, p, prep)
    x = np.asarray(block)
    if x.ndim != 2:
        raise ValueError(f"gamma_mrf needs a 2-D intensity block, got shape {x.shape}")
    hp = int(halo_px)
    if hp < halo(p):
        raise ValueError(f"gamma_mrf needs a halo of {halo(p)} (sweeps x colours), block has {hp}")
    lab, _, gap, ok = labels(x, hp, origin, p, prep)
    lab, gap, ok, y = _core(lab, hp), _core(gap, hp), _core(ok, hp), _core(x, hp)
    mask = ok & (lab >= int(prep["ship_from"]))
    if p.scatter == "quantile":
        mask &= y.astype(np.float64) > np.float64(prep["scatter_threshold"])
    stat = np.where(mask, gap, 0.0).astype(np.float32)
    tiny = np.nextafter(np.float32(0), np.float32(1))
    stat[mask & (stat <= 0)] = tiny
    return mask, stat


def discriminate(records: np.ndarray, p: GammaMRFParams, prep: dict) -> np.ndarray:
    """The scattering rule on whole candidates (the paper's discrimination, section 3.3): keep
    a component whose peak intensity exceeds ``peak_threshold`` (the clutter mixture's
    (1 - ``peak_pfa``) quantile); the geometry rule is the shared size rule."""
    qp = prep.get("peak_threshold")
    if qp is None:
        return np.ones(len(records), bool)
    return records["peak"] > qp


SPEC = DetectorSpec(
    name="gamma_mrf",
    summary="K-class gamma mixture (EM) + Potts MRF MAP by ICM with per-sweep class re-estimation; "
    "ships = brightest class above the clutter mixture's (1 - pfa) quantile",
    reference="Liu et al. 2017, GF-3 NSC ship detection (seed 003, section 3); docs/algorithms/gamma_mrf.md",
    params=GammaMRFParams,
    prepare=prepare,
    detect=detect,
    input="intensity",
    needs_looks=True,
    scene_pass=scene_pass,
    reduce=reduce,
    for_scene=for_scene,
    halo_fn=halo,
    halo_rule="sweeps x colours (2 for the 4-neighbourhood, 4 for the 8-neighbourhood)",
    gpu="sarship.pipeline.gpu.gamma_mrf",
    scene_passes_max=MAX_PASSES,
    discriminate=discriminate,
)
