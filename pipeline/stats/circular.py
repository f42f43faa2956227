"""Circular statistics of phases and the von Mises fit (seed 004, section 3.1-3.2).

Source: Leng, Ji, Xiong, Kuang, "Statistical modeling methods of single-channel complex-valued
SAR images for ship detection", Journal of Radars 9(3), 2020 (docs/references.md#leng2020),
after Fisher 1995 and Mardia & Jupp 2000 (docs/references.md#fisher1995, #mardia2000).

For phases x_1..x_N (radians), the trigonometric moments of order p (eq 1-3)::

    C_p = sum cos(p x_n),  S_p = sum sin(p x_n),  Cbar_p = C_p / N,  Sbar_p = S_p / N   (1)
    R_p = sqrt(C_p^2 + S_p^2),  Rbar_p = R_p / N                                          (2)
    T_p = the direction of (Cbar_p, Sbar_p) in [0, 2 pi)                                  (3)

and the statistics (eq 4-11): mean direction mu = T_1 (4), circular variance V = 1 - Rbar_1
(5), circular standard deviation (6), resultant length R = R_1 (7), mean resultant length
Rbar = Rbar_1 (8), circular dispersion (9), skewness (10) and kurtosis (11).

Two printing slips of the paper are corrected here, both to Fisher 1995 (section 2.3.1) and
both checked against the paper's own tables:

- eq 6 prints v = sqrt(-ln Rbar_1); Fisher's circular standard deviation is sqrt(-2 ln Rbar_1),
  and the paper's tables 1 and 2 use it (Rbar = 0.05 -> 2.46, Rbar = 0.73 -> 0.79; the printed
  formula would give 1.73 and 0.56). ``scipy.stats.circstd`` is the same quantity.
- eq 9 prints delta = (1 - T_2) / (2 Rbar_1^2); Fisher's dispersion is (1 - Rbar_2) / (2 Rbar_1^2)
  (a length, not a direction, enters it).

T_p of eq 3 is undefined for Cbar_p = 0 or Sbar_p = 0 on a branch of the printed cases; here it
is ``arctan2(Sbar_p, Cbar_p) mod 2 pi``, which agrees with eq 3 wherever eq 3 is defined (the
convention of ``scipy.stats.circmean``).

von Mises fit (eq 12-17). Density (eq 12) p(x | mu, kappa) = exp(kappa cos(x - mu)) /
(2 pi I0(kappa)); ML mean direction mu = Arg(mean exp(j x)) (eq 13); kappa solves
Rbar = I1(kappa) / I0(kappa) (eq 17, the ML equation). For small N, Rbar^2 (eq 14) is biased:
E[Rbar^2] = 1/N + (N - 1)/N A(kappa)^2 (eq 15) with A = I1 / I0, so eq 16,
Rbar_e^2 = N / (N - 1) (Rbar^2 - 1/N), is unbiased for A(kappa)^2 and the corrected kappa
solves A(kappa) = sqrt(max(Rbar_e^2, 0)) (kappa = 0 when Rbar_e^2 <= 0: no evidence of
concentration). A(kappa) is increasing from 0 to 1, so each equation has one root, found by
``scipy.optimize.brentq`` on A computed with the exponentially scaled Bessel functions
``scipy.special.i1e / i0e`` (no overflow at any kappa).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import special


def _phases(x) -> np.ndarray:
    a = np.asarray(x, dtype=np.float64).ravel()
    if a.size == 0:
        raise ValueError("circular statistics need at least one phase")
    if not np.all(np.isfinite(a)):
        raise ValueError("phases must be finite (drop absent pixels first)")
    return a


def trig_moment(x, p: int = 1) -> tuple[float, float, float, float]:
    """``(Cbar_p, Sbar_p, Rbar_p, T_p)`` of the phases ``x`` (eq 1-3); T_p in [0, 2 pi)."""
    a = _phases(x)
    c = float(np.mean(np.cos(p * a)))
    s = float(np.mean(np.sin(p * a)))
    r = math.hypot(c, s)
    t = math.atan2(s, c) % (2.0 * math.pi)
    return c, s, r, t


@dataclass(frozen=True)
class CircularSummary:
    """The statistics of eq 4-11 of one sample of phases."""

    n: int
    mean_direction: float  # mu = T_1, eq 4, in [0, 2 pi)
    variance: float  # V = 1 - Rbar_1, eq 5
    std: float  # sqrt(-2 ln Rbar_1), eq 6 (Fisher; see the module docstring)
    resultant_length: float  # R = R_1, eq 7
    mean_resultant_length: float  # Rbar = Rbar_1, eq 8
    dispersion: float  # (1 - Rbar_2) / (2 Rbar_1^2), eq 9 (Fisher)
    skewness: float  # Rbar_2 sin(T_2 - 2 T_1) / (1 - Rbar_1)^(3/2), eq 10
    kurtosis: float  # (Rbar_2 cos(T_2 - 2 T_1) - Rbar_1^4) / (1 - Rbar_1)^2, eq 11


def summary(x) -> CircularSummary:
    """Every circular statistic of eq 4-11 of the phases ``x`` (radians, any shape).

    Where a statistic is undefined (Rbar_1 = 0 for std/dispersion, Rbar_1 = 1 for skewness and
    kurtosis) it is ``inf`` or ``nan`` as IEEE arithmetic gives it.
    """
    a = _phases(x)
    _, _, r1, t1 = trig_moment(a, 1)
    _, _, r2, t2 = trig_moment(a, 2)
    with np.errstate(divide="ignore", invalid="ignore"):
        std = float(np.sqrt(-2.0 * np.log(np.float64(r1)))) if r1 > 0 else math.inf
        disp = float(np.float64(1.0 - r2) / np.float64(2.0 * r1 * r1))
        d = np.float64(1.0 - r1)
        skew = float(np.float64(r2 * math.sin(t2 - 2.0 * t1)) / d**1.5)
        kurt = float(np.float64(r2 * math.cos(t2 - 2.0 * t1) - r1**4) / (d * d))
    return CircularSummary(
        n=a.size,
        mean_direction=t1,
        variance=1.0 - r1,
        std=std,
        resultant_length=r1 * a.size,
        mean_resultant_length=r1,
        dispersion=disp,
        skewness=skew,
        kurtosis=kurt,
    )


def mean_direction(x) -> float:
    """mu = T_1 (eq 4, = eq 13, the von Mises ML location), in [0, 2 pi)."""
    return trig_moment(x, 1)[3]


def circular_variance(x) -> float:
    """V = 1 - Rbar_1 (eq 5)."""
    return 1.0 - trig_moment(x, 1)[2]


def circular_std(x) -> float:
    """sqrt(-2 ln Rbar_1) (eq 6 as Fisher and the paper's tables have it)."""
    return summary(x).std


def bessel_ratio(kappa) -> np.ndarray:
    """A(kappa) = I1(kappa) / I0(kappa) (the right side of eq 17), overflow-free."""
    k = np.asarray(kappa, dtype=np.float64)
    return special.i1e(k) / special.i0e(k)


def kappa_from_rbar(r: float) -> float:
    """The kappa >= 0 with A(kappa) = r (eq 17), r in [0, 1); 0 for r <= 0, inf for r >= 1.

    A is increasing (A' = 1 - A/kappa - A^2 > 0), A(0) = 0, A -> 1; the root is bracketed by
    [0, hi], hi doubled from 1 until A(hi) > r (A(kappa) ~ 1 - 1/(2 kappa), so hi stays
    below ~2/(1 - r)), then found by Brent's method to full double precision.
    """
    from scipy import optimize  # lazy: importing scipy.optimize costs every command start-up time

    r = float(r)
    if not math.isfinite(r):
        raise ValueError(f"mean resultant length must be finite, got {r}")
    if r <= 0.0:
        return 0.0
    if r >= 1.0:
        return math.inf
    hi = 1.0
    while float(bessel_ratio(hi)) <= r:
        hi *= 2.0
    return float(optimize.brentq(lambda k: float(bessel_ratio(k)) - r, 0.0, hi, xtol=1e-14, rtol=1e-15, maxiter=200))


@dataclass(frozen=True)
class VonMisesFit:
    """The von Mises fit of eq 13-17."""

    mu: float  # eq 13, in [0, 2 pi)
    kappa: float  # solves eq 17 with Rbar (corrected=False) or sqrt(Rbar_e^2) of eq 16
    rbar: float  # Rbar (eq 8; sqrt of eq 14)
    rbar_e2: float  # eq 16 (nan for N = 1)
    corrected: bool


def fit_von_mises(x, corrected: bool = True) -> VonMisesFit:
    """von Mises ML fit of the phases ``x`` (eq 13-17).

    ``corrected``: kappa from the small-sample statistic of eq 16 (unbiased for A(kappa)^2),
    else from Rbar itself (eq 17, the ML estimate, biased up for small N; what
    ``scipy.stats.vonmises.fit(x, fscale=1)`` returns).
    """
    a = _phases(x)
    n = a.size
    c, s, r, t = trig_moment(a, 1)
    r2 = c * c + s * s  # eq 14
    re2 = n / (n - 1.0) * (r2 - 1.0 / n) if n > 1 else math.nan  # eq 16
    if corrected:
        if n < 2:
            raise ValueError("the small-sample correction (eq 16) needs at least 2 phases")
        kappa = kappa_from_rbar(math.sqrt(re2)) if re2 > 0 else 0.0
    else:
        kappa = kappa_from_rbar(r)
    return VonMisesFit(mu=t, kappa=kappa, rbar=r, rbar_e2=re2, corrected=corrected)


def von_mises_pdf(x, mu: float, kappa: float) -> np.ndarray:
    """The von Mises density of eq 12, exp(kappa cos(x - mu)) / (2 pi I0(kappa)), computed as
    exp(kappa (cos(x - mu) - 1)) / (2 pi i0e(kappa)) (no overflow)."""
    if not kappa >= 0.0:
        raise ValueError(f"kappa must be >= 0, got {kappa}")
    xa = np.asarray(x, dtype=np.float64)
    return np.exp(kappa * (np.cos(xa - mu) - 1.0)) / (2.0 * math.pi * special.i0e(kappa))


# ------------------------------------------------------------------------------------------
# Neighbourhood phase direction difference (NPDD, eq 19-21)
# ------------------------------------------------------------------------------------------


def _window_phasor_mean(u: np.ndarray, r: int) -> np.ndarray:
    """Sum of the unit phasors ``u`` over W_r (eq 20, up to the 1/N that Arg ignores): r = 1 the
    pixel itself; r > 1 the r x r window without its centre; mirror-extended at the border
    (numpy ``reflect``, the project's border rule)."""
    if r == 1:
        return u
    from scipy import ndimage

    k = np.ones((r, r))
    k[r // 2, r // 2] = 0.0
    re = ndimage.correlate(u.real, k, mode="mirror")
    im = ndimage.correlate(u.imag, k, mode="mirror")
    return re + 1j * im


def npdd(z, s: int = 3, t: int = 1) -> np.ndarray:
    """NPDD_st of a complex image ``z`` (eq 19-21), radians in (-pi, pi], float64, NaN where
    ``z`` is absent (not finite) or a window's phasors cancel exactly.

    theta = Arg(z) (eq 19); theta_r = Arg(sum of exp(j theta) over W_r) (eq 20), W_1 the pixel,
    W_r (r > 1) the r x r window without its centre (the paper's "radius" r is read as the
    window side: r = 1 must be the pixel itself, and s = 3, t = 1 its example); NPDD_st =
    Arg(exp(j theta_s) / exp(j theta_t)) (eq 21). Absent pixels contribute no phasor.
    """
    s, t = int(s), int(t)
    for name, v in (("s", s), ("t", t)):
        if v < 1 or (v > 1 and v % 2 == 0):
            raise ValueError(f"{name} must be 1 or an odd window side >= 3, got {v}")
    if s == t:
        raise ValueError(f"s and t must differ, got s = t = {s}")
    za = np.asarray(z)
    if za.ndim != 2 or not np.iscomplexobj(za):
        raise ValueError("NPDD needs a 2-D complex (SLC) image: amplitude has no phase")
    ok = np.isfinite(za.real) & np.isfinite(za.imag) & (za != 0)
    u = np.where(ok, za / np.where(ok, np.abs(za), 1.0), 0.0).astype(np.complex128)  # exp(j theta), eq 19
    a = _window_phasor_mean(u, s)
    b = _window_phasor_mean(u, t)
    d = a * np.conj(b)  # eq 21
    out = np.angle(d)
    out[~ok | (np.abs(a) == 0) | (np.abs(b) == 0)] = np.nan
    return out


def npdd_spread(values) -> tuple[float, float]:
    """``(circular variance, mean resultant length)`` of NPDD values (eq 5 and 8), NaN left out;
    (nan, nan) when none is present. Ships: larger variance / smaller length than sea (section 3.3)."""
    a = np.asarray(values, dtype=np.float64).ravel()
    a = a[np.isfinite(a)]
    if a.size == 0:
        return math.nan, math.nan
    _, _, r, _ = trig_moment(a, 1)
    return 1.0 - r, r
