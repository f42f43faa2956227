"""Stripe-noise removal (image-quality enhancement of seed 003, section 2 (1); docs/algorithms/destripe.md).

Stripes are a multiplicative gain that is constant along one image axis (the *stripe
axis*: azimuth for the simulator's beam-seam stripes, ``stripes_along="azimuth"``; range
for stripes repeating along azimuth, ``stripes_along="range"``) and varies across it. In
the logarithm of the power, ``y = ln P``, the gain is an additive profile ``s`` of the
across coordinate only, so its 2-D spectrum lies on the zero-frequency line of the stripe
axis. The method of seed 003 (1-D FFT across the stripes, stripe peaks found by Otsu
thresholding and a Hough line transform on the spectrum, band-stop, inverse FFT) becomes:

1. **Scene pass** (:func:`segment_sums`, tiled): the sums of ``y`` and the counts of
   present pixels over fixed global segments of ``segment`` lines along the stripe axis,
   per across position. Sums are accumulated in 2**-24 fixed point in int64, so the
   reduction is exact and independent of the tiling (tiles add integers).
2. **Spectrum** (:func:`stripe_spectrum`): the segments are pooled into ``groups``
   consecutive groups; each group's mean profile (segment means winsorised at 3 MADs per
   position, so ships do not leak in) is transformed by a 1-D real FFT across the stripes,
   ``P_g(k)``, and compared with the scatter of its segments' spectra: the coherence ratio
   ``Z[g, k] = |P_g(k)|^2 / (sum_j |P_j(k) - P_g(k)|^2 / (n_g (n_g - 1)))``. Stripes are
   the same in every segment (coherent): ``Z`` grows with the segment count; speckle,
   texture, land and ships are not: ``Z`` is F(2, 2(n_g - 1))-like (noise floor).
3. **Stripe bins** (:func:`otsu_threshold`, :func:`hough_lines`): ``log10 Z`` is binarised
   at its Otsu threshold (Otsu 1979, eq. 18-19: the level maximising the between-class
   variance), never below ``z_min`` (default 4: a noise bin passes with probability about
   ``(1 + 4/(n_g - 1))^-(n_g - 1)``, 0.04 for 8 segments a group); lines in the binary (group, frequency) image are found
   with the Hough transform (Duda & Hart 1972, eq. 1: ``rho = k cos(theta) + g sin(theta)``,
   ``|theta| <= theta_max``) and kept when at least ``min_votes`` of the groups vote (a stripe
   frequency must persist along the whole stripe axis; a slanted line is a slowly drifting
   frequency). The bins of the kept lines, widened by ``notch_halfwidth``, are the stop band.
4. **Band-stop** (:func:`stripe_profile`): the stripe profile is the inverse FFT of the
   pooled (all-segment) mean spectrum restricted to the stop band; the filtered image is
   ``y - s``: power times ``exp(-s)`` (complex amplitudes times ``exp(-s/2)``), applied per
   pixel (:func:`apply_gain`), so the tiled result is bit-identical to the whole scene.

Absent pixels (NaN, inf, power <= 0) are left out of the sums and stay as they are.

References (docs/references.md): seed 003 (GF-3 NSC ship detection, section 2 (1)),
otsu1979, dudahart1972.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from sarship.pipeline.errors import InputError
from sarship.pipeline.tiling.intensity_absent import xp_of as _xp  # NumPy or CuPy, by the array

#: Fixed-point scale of the exact scene-pass sums (``y`` in units of 2**-24).
FIXED_SCALE = float(2**24)
#: ``|ln P|`` beyond this is clipped before the fixed-point sums (P in [1e-130, 1e130]).
Y_CLIP = 300.0
STRIPE_AXES = ("azimuth", "range")


@dataclass(frozen=True)
class DestripeParams:
    """Parameters of the stripe estimate (docs/algorithms/destripe.md)."""

    stripes_along: str = "azimuth"  # the axis along which the stripe gain is constant
    segment: int = 32  # lines per segment along the stripe axis
    groups: int = 8  # segment groups (rows of the Hough image)
    z_min: float = 4.0  # noise floor of the coherence ratio Z
    min_votes: float = 0.75  # fraction of groups a stripe line must cross
    theta_max_deg: float = 20.0  # largest Hough line slope from the stripe axis
    notch_halfwidth: int = 1  # stop band: detected bins +- this many bins
    k_min: int = 1  # lowest frequency bin that may be stopped (0 = mean: never)
    bright_db: float = 5.0  # cells (segment x segment) this far over the median: land, left out

    def __post_init__(self) -> None:
        if self.stripes_along not in STRIPE_AXES:
            raise InputError(
                f"destripe stripes_along: must be one of {', '.join(STRIPE_AXES)} (got {self.stripes_along!r})"
            )
        checks = (
            ("segment", self.segment, 2, 4096),
            ("groups", self.groups, 1, 256),
            ("notch_halfwidth", self.notch_halfwidth, 0, 64),
            ("k_min", self.k_min, 1, 1 << 20),
        )
        for name, v, lo, hi in checks:
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or not lo <= v <= hi:
                raise InputError(f"destripe {name}: must be an integer in [{lo}, {hi}] (got {v!r})")
        fchecks = (
            ("z_min", self.z_min, 1.0, 1e12),
            ("min_votes", self.min_votes, 0.0, 1.0),
            ("theta_max_deg", self.theta_max_deg, 0.0, 60.0),
            ("bright_db", self.bright_db, 0.5, 100.0),
        )
        for name, v, lo, hi in fchecks:
            if (
                isinstance(v, bool)
                or not isinstance(v, (int, float, np.floating))
                or not math.isfinite(float(v))
                or not lo <= float(v) <= hi
            ):
                raise InputError(f"destripe {name}: must be a number in [{lo:g}, {hi:g}] (got {v!r})")
        if self.min_votes <= 0:
            raise InputError(f"destripe min_votes: must be in (0, 1] (got {self.min_votes!r})")

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


# --------------------------------------------------------------------------- scene pass


def log_power(block) -> Any:
    """``ln`` of the power of each pixel (float64), NaN where absent (non-finite or <= 0).

    ``block``: intensity (2-D real), a complex channel (2-D complex: ``|z|^2``), or stacked
    complex channels ``(rows, cols, p)`` (the span). NumPy or CuPy.
    """
    xp = _xp(block)
    a = block
    if a.ndim == 3:
        p = xp.sum(a.real.astype(xp.float64) ** 2 + a.imag.astype(xp.float64) ** 2, axis=2)
    elif xp.iscomplexobj(a):
        p = a.real.astype(xp.float64) ** 2 + a.imag.astype(xp.float64) ** 2
    else:
        p = a.astype(xp.float64)
    ok = xp.isfinite(p) & (p > 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        y = xp.log(xp.where(ok, p, 1.0))
    return xp.where(ok, xp.clip(y, -Y_CLIP, Y_CLIP), xp.nan)


def _quantised_log(block):
    """``(q, ok)``: ``ln P`` of every present pixel in units of 2**-24 (int64, 0 where absent)
    and the present pixels. Single-precision data stay in float32 (``ln`` of a float32 is at
    most 88.8, so no clipping is needed and ``y * 2**24`` is exact); each pixel's value is
    the same whatever tile it is read in, so the sums are exact for every tiling."""
    xp = _xp(block)
    a = block
    if a.ndim == 3:
        p = (a.real**2 + a.imag**2).sum(axis=2) if xp.iscomplexobj(a) else (a**2).sum(axis=2)
    elif xp.iscomplexobj(a):
        p = a.real**2 + a.imag**2
    else:
        p = a
    if p.dtype != xp.float32:
        y = log_power(p)
        ok = xp.isfinite(y)
        return xp.where(ok, xp.rint(xp.where(ok, y, 0.0) * FIXED_SCALE), 0.0).astype(xp.int64), ok
    ok = (p > 0) & (p < xp.inf)
    y = xp.log(xp.where(ok, p, xp.float32(1.0)))
    y *= xp.float32(FIXED_SCALE)
    q = xp.rint(y).astype(xp.int64)
    q[~ok] = 0
    return q, ok


def segment_sums(block, r0: int, c0: int, params: DestripeParams) -> dict[str, Any]:
    """One tile's contribution to the scene pass: exact segment sums of ``ln P``.

    ``block`` is the tile core (no halo) whose element ``[0, 0]`` is scene pixel
    ``(r0, c0)``. With stripes along azimuth, segments are ``segment`` rows (global index
    ``row // segment``) and the result holds, for segments ``j0 .. j0 + n - 1`` and columns
    ``c0 .. c0 + w - 1``, ``sums`` (int64, ``ln P`` in units of 2**-24, rounded per pixel) and
    ``counts`` (int64, present pixels). Along range the roles of rows and columns swap.
    Integer sums make the scene total the same for every tiling (:func:`assemble`).
    """
    xp = _xp(block)
    q, ok = _quantised_log(block)
    if params.stripes_along == "range":
        q, ok = q.T, ok.T
        a0, b0 = c0, r0
    else:
        a0, b0 = r0, c0
    L = params.segment
    n_along, n_across = q.shape
    j0 = a0 // L
    j1 = (a0 + n_along - 1) // L + 1
    sums = xp.zeros((j1 - j0, n_across), xp.int64)
    counts = xp.zeros((j1 - j0, n_across), xp.int64)
    # segment boundaries inside the block: reduce each run of lines at once
    edges = [0] + [int((j + 1) * L - a0) for j in range(j0, j1 - 1)] + [n_along]
    for i in range(j1 - j0):
        a, b = edges[i], edges[i + 1]
        sums[i] = q[a:b].sum(axis=0)
        counts[i] = ok[a:b].sum(axis=0)
    if xp is not np:
        sums, counts = sums.get(), counts.get()
    return {"j0": int(j0), "b0": int(b0), "sums": sums, "counts": counts}


def assemble(
    parts: list[dict[str, Any]], shape: tuple[int, int], params: DestripeParams
) -> tuple[np.ndarray, np.ndarray]:
    """The scene's ``(sums, counts)`` (segments x across positions) from the tiles' parts."""
    H, W = shape
    n_along, n_across = (W, H) if params.stripes_along == "range" else (H, W)
    nseg = -(-n_along // params.segment)
    sums = np.zeros((nseg, n_across), np.int64)
    counts = np.zeros((nseg, n_across), np.int64)
    for p in parts:
        j0, b0 = p["j0"], p["b0"]
        n, w = p["sums"].shape
        sums[j0 : j0 + n, b0 : b0 + w] += p["sums"]
        counts[j0 : j0 + n, b0 : b0 + w] += p["counts"]
    return sums, counts


# --------------------------------------------------------------------------- Otsu, Hough


def otsu_threshold(values: np.ndarray, bins: int = 256) -> float:
    """Otsu's threshold (Otsu 1979, eq. 18-19) of the finite ``values``.

    Histogram of ``bins`` equal bins over [min, max]; the returned level is the upper edge of
    the bin ``k*`` maximising the between-class variance
    ``sigma_B^2(k) = (mu_T omega(k) - mu(k))^2 / (omega(k) (1 - omega(k)))`` (eq. 18); values
    ``> level`` are the upper class. A constant input returns its value.
    """
    v = np.asarray(values, np.float64)
    v = v[np.isfinite(v)]
    if v.size == 0:
        raise ValueError("otsu_threshold: no finite values")
    lo, hi = float(v.min()), float(v.max())
    if hi <= lo:
        return lo
    hist, edges = np.histogram(v, bins=bins, range=(lo, hi))
    p = hist / hist.sum()
    centres = 0.5 * (edges[:-1] + edges[1:])
    omega = np.cumsum(p)
    mu = np.cumsum(p * centres)
    mu_t = mu[-1]
    with np.errstate(divide="ignore", invalid="ignore"):
        sb = (mu_t * omega - mu) ** 2 / (omega * (1.0 - omega))
    sb[~np.isfinite(sb)] = -1.0
    k = int(np.argmax(sb[:-1]))
    return float(edges[k + 1])


def hough_lines(
    binary: np.ndarray, theta_max_deg: float, min_votes: int, n_theta: int | None = None
) -> list[dict[str, float]]:
    """Straight lines in a binary image by the Hough transform (Duda & Hart 1972, eq. 1).

    The image axes are ``(g, k)`` (rows: groups along the stripe axis, columns: frequency
    bins). A line is ``rho = k cos(theta) + g sin(theta)`` with ``theta`` measured from the
    row axis (``theta = 0``: a constant bin ``k = rho``), ``|theta| <= theta_max_deg``, ``rho``
    in half-bin steps, each cell 1 bin wide (a digital line's rounding fits one cell). Every
    row votes once per ``theta`` for each cell holding the ``rho`` of one of its set pixels
    (a line's votes are the number of rows it crosses on set pixels); cells with at least
    ``min_votes`` votes are lines, reported strongest first after non-maximum suppression (a
    cell is kept if no cell within half a bin in ``rho`` and one ``theta`` step has more votes;
    ties to the smaller ``|theta|``, then the smaller ``rho``). Returns ``[{rho, theta_deg, votes}]``.
    """
    b = np.asarray(binary, bool)
    G, K = b.shape
    if n_theta is None:
        # one theta step moves the line end by at most half a bin across the image height
        n_theta = 1 + 2 * int(math.ceil(math.radians(theta_max_deg) * max(G - 1, 1) * 2))
    thetas = (
        np.linspace(-math.radians(theta_max_deg), math.radians(theta_max_deg), n_theta) if n_theta > 1 else np.zeros(1)
    )
    g, k = np.nonzero(b)
    if g.size == 0:
        return []
    # rho cells every half bin, each 1 bin wide ([c/2 - 1/2, c/2 + 1/2]): a digital line's
    # rounding jitter (+-1/2 bin) always fits one cell
    rmax = 2 * (int(math.ceil(math.hypot(G, K))) + 2)
    acc = np.zeros((n_theta, 2 * rmax + 1), np.int64)
    for t, th in enumerate(thetas):
        c = np.floor(2.0 * (k * math.cos(th) + g * math.sin(th))).astype(np.int64) + rmax
        # one vote per row and cell: several pixels of a wide band in one row count once
        ids = np.concatenate([g * acc.shape[1] + c, g * acc.shape[1] + c + 1])
        acc[t] = np.bincount(np.unique(ids) % acc.shape[1], minlength=acc.shape[1])
    cand = np.argwhere(acc >= max(int(min_votes), 1))
    out = []
    for t, r in cand:
        v = acc[t, r]
        nb = acc[max(t - 1, 0) : t + 2, max(r - 1, 0) : r + 2]
        if v < nb.max():
            continue
        # ties: keep the cell of smallest |theta| (then smallest rho) among equal neighbours
        ties = np.argwhere(nb == v)
        best = min(((abs(thetas[max(t - 1, 0) + a]), max(r - 1, 0) + c) for a, c in ties))
        if (abs(thetas[t]), r) != best:
            continue
        out.append({"rho": float(r - rmax) / 2.0, "theta_deg": float(math.degrees(thetas[t])), "votes": int(v)})
    out.sort(key=lambda d: (-d["votes"], abs(d["theta_deg"]), d["rho"]))
    return out


def line_bins(line: dict[str, float], G: int) -> np.ndarray:
    """The frequency bin of ``line`` in each of the ``G`` groups (rounded)."""
    th = math.radians(line["theta_deg"])
    g = np.arange(G)
    return np.rint((line["rho"] - g * math.sin(th)) / math.cos(th)).astype(np.int64)


# --------------------------------------------------------------------------- spectrum and filter


@dataclass
class StripeEstimate:
    """What the client found: the stop band, the lines, the stripe profile and diagnostics."""

    params: DestripeParams
    n_across: int
    stop: np.ndarray  # bool, rfft bins stopped
    profile: np.ndarray  # float64 stripe profile s (ln gain) per across position
    lines: list[dict[str, float]] = field(default_factory=list)
    threshold_log10z: float = float("nan")
    otsu_log10z: float = float("nan")
    groups: int = 0
    segments: int = 0

    def record(self) -> dict[str, Any]:
        """The ``enhance.destripe`` record written into the output scene's attributes."""
        bins = np.flatnonzero(self.stop)
        return {
            "method": "stripe profile band-stop (seed 003 section 2 (1); docs/algorithms/destripe.md)",
            "parameters": self.params.as_dict(),
            "segments": int(self.segments),
            "groups": int(self.groups),
            "otsu_log10_z": _finite(self.otsu_log10z),
            "threshold_log10_z": _finite(self.threshold_log10z),
            "lines": self.lines,
            "stop_bins": [int(b) for b in bins],
            "stop_periods_px": [round(self.n_across / int(b), 3) for b in bins if b > 0],
            "stripe_rms_db": float(10.0 / math.log(10.0) * np.sqrt(np.mean(self.profile**2)))
            if self.profile.size
            else 0.0,
            "stripe_max_db": float(10.0 / math.log(10.0) * np.max(np.abs(self.profile))) if self.profile.size else 0.0,
        }


def _finite(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


def _segment_means(sums: np.ndarray, counts: np.ndarray) -> np.ndarray:
    with np.errstate(invalid="ignore", divide="ignore"):
        m = sums.astype(np.float64) / FIXED_SCALE / counts
    m[counts == 0] = np.nan
    return m


def bright_cells(sums: np.ndarray, counts: np.ndarray, params: DestripeParams) -> np.ndarray:
    """Positions of land and other large bright areas, left out of the estimate (bool, like
    ``sums``): the mean ``ln P`` of each ``segment x segment`` cell (a segment and ``segment``
    across positions) is compared with the median over all cells; cells more than
    ``bright_db`` over it are bright. Land lies +8..12 dB over the sea (and spans whole
    columns when the coast runs along the stripe axis, where it would look like a stripe);
    the sea's own cell means scatter by about 1.5 dB (K texture, 32 x 32 px).
    """
    L = params.segment
    nseg, n = sums.shape
    nb = -(-n // L)
    pad = nb * L - n
    s = np.pad(sums.astype(np.float64), ((0, 0), (0, pad))).reshape(nseg, nb, L).sum(axis=2)
    c = np.pad(counts, ((0, 0), (0, pad))).reshape(nseg, nb, L).sum(axis=2)
    with np.errstate(invalid="ignore", divide="ignore"):
        cell = s / FIXED_SCALE / c
    ok = c > 0
    if not ok.any():
        return np.zeros(sums.shape, bool)
    level = float(np.median(cell[ok]))
    bright = ok & (cell > level + params.bright_db * math.log(10.0) / 10.0)
    return np.repeat(bright, L, axis=1)[:, :n]


def _winsorise(m: np.ndarray) -> np.ndarray:
    """Clip each position's segment means to its median +- 3 MAD (ships, bright land spots)."""
    med = np.nanmedian(m, axis=0) if np.isfinite(m).any() else np.zeros(m.shape[1])
    mad = 1.4826 * np.nanmedian(np.abs(m - med), axis=0)
    lo, hi = med - 3.0 * mad, med + 3.0 * mad
    return np.where(np.isfinite(m), np.clip(m, lo, hi), np.nan)


def _profiles(m: np.ndarray) -> np.ndarray:
    """Mean-removed profiles with absent positions at the profile's mean (0)."""
    mu = np.nanmean(np.where(np.isfinite(m), m, np.nan), axis=1, keepdims=True)
    mu = np.where(np.isfinite(mu), mu, 0.0)
    return np.where(np.isfinite(m), m - mu, 0.0)


def stripe_spectrum(sums: np.ndarray, counts: np.ndarray, params: DestripeParams) -> dict[str, np.ndarray]:
    """The coherence-ratio image ``Z[g, k]`` and the pooled mean spectrum (module doc, step 2)."""
    import warnings

    nseg, n = sums.shape
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN positions
        m = _segment_means(sums, counts)
        m[bright_cells(sums, counts, params)] = np.nan
        m = _winsorise(m)
        prof = _profiles(m)
    P = np.fft.rfft(prof, axis=1)  # segment spectra
    G = max(1, min(params.groups, nseg // 2)) if nseg >= 2 else 1
    bounds = np.linspace(0, nseg, G + 1).round().astype(int)
    Z = np.zeros((G, P.shape[1]))
    for g in range(G):
        Pg = P[bounds[g] : bounds[g + 1]]
        ng = Pg.shape[0]
        mean = Pg.mean(axis=0)
        if ng >= 2:
            var_of_mean = (np.abs(Pg - mean) ** 2).sum(axis=0) / (ng * (ng - 1))
            with np.errstate(divide="ignore", invalid="ignore"):
                Z[g] = np.where(var_of_mean > 0, np.abs(mean) ** 2 / var_of_mean, 0.0)
    return {"Z": Z, "pooled": P.mean(axis=0), "groups": G, "segments": nseg}


def estimate(sums: np.ndarray, counts: np.ndarray, params: DestripeParams) -> StripeEstimate:
    """Find the stripe bins (Otsu + Hough) and the stripe profile from the scene-pass sums."""
    spec = stripe_spectrum(sums, counts, params)
    Z, pooled, G = spec["Z"], spec["pooled"], spec["groups"]
    n = sums.shape[1]
    nb = pooled.shape[0]
    stop = np.zeros(nb, bool)
    k_lo = params.k_min
    res = StripeEstimate(params=params, n_across=n, stop=stop, profile=np.zeros(n), groups=G, segments=spec["segments"])
    if nb <= k_lo or sums.shape[0] < 2:
        return res
    with np.errstate(divide="ignore"):
        lz = np.log10(np.maximum(Z[:, k_lo:], 1e-300))
    otsu = otsu_threshold(lz)
    thr = max(otsu, math.log10(params.z_min))
    res.otsu_log10z, res.threshold_log10z = otsu, thr
    binary = lz > thr
    votes = max(1, int(math.ceil(params.min_votes * G - 1e-9)))
    lines = hough_lines(binary, params.theta_max_deg, votes)
    # bins whose column of the binary image has the votes of a line: a peak wider than one
    # bin (a drifting period, a band of steps) is stopped over its whole width
    wide = np.zeros(nb, bool)
    wide[k_lo:] = binary.sum(axis=0) >= votes
    for ln in lines:
        kb = line_bins(ln, G) + k_lo
        for k0 in np.unique(kb[(kb >= k_lo) & (kb < nb)]):
            a = b = int(k0)
            while a - 1 >= k_lo and wide[a - 1]:
                a -= 1
            while b + 1 < nb and wide[b + 1]:
                b += 1
            stop[max(a - params.notch_halfwidth, k_lo) : min(b + params.notch_halfwidth, nb - 1) + 1] = True
    res.lines = [{**ln, "rho": ln["rho"] + k_lo} for ln in lines]
    res.profile = stripe_profile(pooled, stop, n)
    return res


def stripe_profile(pooled: np.ndarray, stop: np.ndarray, n: int) -> np.ndarray:
    """Inverse FFT of the pooled spectrum on the stop band: the stripe part of the profile."""
    if not stop.any():
        return np.zeros(n)
    return np.fft.irfft(np.where(stop, pooled, 0.0), n=n)


def apply_gain(block, profile_part: np.ndarray, params: DestripeParams, complex_amplitude: bool | None = None):
    """The filtered tile: power times ``exp(-s)`` (complex amplitude times ``exp(-s/2)``).

    ``profile_part`` is the stripe profile over this tile's across positions (columns for
    stripes along azimuth, rows along range). Absent pixels stay as they are (NaN times a
    gain is NaN, 0 stays 0). NumPy or CuPy ``block``; the output has the block's dtype.
    """
    xp = _xp(block)
    cplx = xp.iscomplexobj(block) if complex_amplitude is None else complex_amplitude
    s = xp.asarray(profile_part, dtype=xp.float64)
    g = xp.exp(-0.5 * s) if cplx else xp.exp(-s)
    g = g[None, :] if params.stripes_along == "azimuth" else g[:, None]
    if block.ndim == 3:
        g = g[..., None]
    real_dtype = block.real.dtype if cplx else block.dtype
    return (block * g.astype(real_dtype)).astype(block.dtype)


# --------------------------------------------------------------------------- metric


def stripe_to_background_db(
    power: np.ndarray,
    stripes_along: str = "azimuth",
    reference: np.ndarray | None = None,
    valid: np.ndarray | None = None,
) -> float:
    """Stripe-to-background ratio (dB) of a scene: how much the across-stripe profile of
    ``ln P`` (mean along the stripe axis over present pixels, its mean removed) varies.

    With ``reference`` (the same scene without stripes) the ratio is
    ``var(profile) / var(reference profile)``: 0 dB means no stripe energy left above what
    the scene itself has. Without it, the profile variance is divided by the variance a
    profile of independent speckle would have (``var(ln P) / n_along``). ``valid``: the pixels
    to use (e.g. the sea), others are left out.
    """

    def prof(p):
        y = log_power(np.asarray(p))
        if valid is not None:
            y = np.where(valid, y, np.nan)
        if stripes_along == "range":
            y = y.T
        with np.errstate(invalid="ignore"):
            import warnings

            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                m = np.nanmean(y, axis=0)
        m = m[np.isfinite(m)]
        return m - m.mean(), y

    m, y = prof(power)
    if reference is not None:
        r, _ = prof(reference)
        return float(10 * math.log10(np.var(m) / np.var(r)))
    base = np.nanvar(y) / y.shape[0]
    return float(10 * math.log10(np.var(m) / base))
