"""Circular statistics (eq 1-11) and the von Mises fit (eq 12-17) of seed 004 against scipy.stats
and against the distributions' known values (pipeline/stats/circular.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import integrate, special, stats

from sarship.pipeline.stats import circular


def test_trig_moments_match_scipy_circmean_circvar_circstd():
    rng = np.random.default_rng(0)
    for kappa, n in [(0.5, 50), (2.0, 200), (8.0, 1000)]:
        x = stats.vonmises.rvs(kappa, loc=1.3, size=n, random_state=rng)
        s = circular.summary(x)
        assert s.mean_direction == pytest.approx(stats.circmean(x), abs=1e-12)
        assert s.variance == pytest.approx(stats.circvar(x), abs=1e-12)
        assert s.std == pytest.approx(stats.circstd(x), abs=1e-12)
        assert s.mean_resultant_length == pytest.approx(1.0 - stats.circvar(x), abs=1e-12)
        assert s.resultant_length == pytest.approx(n * s.mean_resultant_length)


def test_mean_direction_wraps():
    # 1 deg and 359 deg average to 0 (the paper's example), not 180
    x = np.radians([1.0, 359.0])
    mu = circular.mean_direction(x)
    assert min(mu, 2 * math.pi - mu) < 1e-12
    # eq 3's quadrants: (C<0) -> atan + pi, (S<0, C>0) -> atan + 2 pi
    for ang in (0.3, 2.0, 3.5, 5.9):
        assert circular.mean_direction([ang - 0.1, ang + 0.1]) == pytest.approx(ang, abs=1e-12)


def test_paper_table_std_uses_minus_two_log():
    # Table 1/2: Rbar 0.05 -> std 2.46, 0.73 -> 0.79 (eq 6 with Fisher's factor 2)
    for rbar, std in [(0.05, 2.45), (0.73, 0.79), (0.79, 0.69)]:
        x = np.array([0.0, 2 * np.arccos(rbar)]) - np.arccos(rbar)  # two phases with Rbar = rbar
        assert circular.summary(x).std == pytest.approx(std, abs=0.01)


def test_skewness_kurtosis_dispersion_of_von_mises_population():
    """Population values (Fisher 1995 section 3.3.6): for vM(mu, kappa), rho_1 = A1(k),
    rho_2 = I2(k)/I0(k), both at mean direction mu: skewness 0, kurtosis
    (rho_2 - rho_1^4)/(1 - rho_1)^2, dispersion (1 - rho_2)/(2 rho_1^2)."""
    rng = np.random.default_rng(3)
    k = 2.0
    x = stats.vonmises.rvs(k, loc=0.7, size=400_000, random_state=rng)
    s = circular.summary(x)
    r1 = special.iv(1, k) / special.iv(0, k)
    r2 = special.iv(2, k) / special.iv(0, k)
    assert s.skewness == pytest.approx(0.0, abs=0.02)
    assert s.kurtosis == pytest.approx((r2 - r1**4) / (1 - r1) ** 2, rel=0.02)
    assert s.dispersion == pytest.approx((1 - r2) / (2 * r1**2), rel=0.02)
    # a skewed distribution: wrapped exponential of scale 0.8, trigonometric moments
    # phi_p = 1 / (1 - i p 0.8) (its characteristic function), skewness and kurtosis from them
    y = rng.exponential(0.8, 400_000) % (2 * math.pi)
    p1, p2 = 1 / (1 - 0.8j), 1 / (1 - 1.6j)
    r1, m1, r2, m2 = abs(p1), np.angle(p1), abs(p2), np.angle(p2)
    sy = circular.summary(y)
    assert sy.skewness == pytest.approx(r2 * math.sin(m2 - 2 * m1) / (1 - r1) ** 1.5, rel=0.03)
    assert sy.kurtosis == pytest.approx((r2 * math.cos(m2 - 2 * m1) - r1**4) / (1 - r1) ** 2, rel=0.03)


def test_kappa_solves_eq17_and_matches_scipy_vonmises_fit():
    rng = np.random.default_rng(1)
    for kappa in (0.3, 1.0, 4.0, 30.0, 500.0):
        x = stats.vonmises.rvs(kappa, loc=-2.0, size=2000, random_state=rng)
        f = circular.fit_von_mises(x, corrected=False)
        assert float(circular.bessel_ratio(f.kappa)) == pytest.approx(f.rbar, rel=1e-12)
        k_sp, loc_sp, _ = stats.vonmises.fit(x, fscale=1)
        assert f.kappa == pytest.approx(k_sp, rel=1e-4)
        d = (f.mu - loc_sp) % (2 * math.pi)
        assert min(d, 2 * math.pi - d) < 1e-6
    assert circular.kappa_from_rbar(0.0) == 0.0
    assert circular.kappa_from_rbar(1.0) == math.inf
    assert circular.kappa_from_rbar(0.999999) == pytest.approx(5e5, rel=1e-3)  # A ~ 1 - 1/(2k)


def test_small_sample_correction_eq16_removes_the_bias():
    """Rbar_e^2 (eq 16) is unbiased for A(kappa)^2 (eq 15); plain Rbar^2 is not. Over many small
    samples (N = 10) the corrected kappa is far less biased than the ML one."""
    rng = np.random.default_rng(2)
    kappa, n, reps = 1.0, 10, 20000
    x = stats.vonmises.rvs(kappa, size=(reps, n), random_state=rng)
    c, s = np.cos(x).mean(1), np.sin(x).mean(1)
    r2 = c * c + s * s
    re2 = n / (n - 1) * (r2 - 1 / n)
    a2 = float(circular.bessel_ratio(kappa)) ** 2
    se = re2.std() / math.sqrt(reps)
    assert abs(re2.mean() - a2) < 4 * se  # eq 16 unbiased
    assert r2.mean() - a2 > 20 * se  # eq 14 biased up by ~ (1 - A^2)/N
    assert r2.mean() == pytest.approx(1 / n + (n - 1) / n * a2, abs=4 * r2.std() / math.sqrt(reps))  # eq 15
    k_ml = np.array([circular.fit_von_mises(xi, corrected=False).kappa for xi in x[:3000]])
    k_c = np.array([circular.fit_von_mises(xi, corrected=True).kappa for xi in x[:3000]])
    assert k_ml.mean() > 1.2 * kappa  # ML over-estimates kappa at N = 10 (measured: 1.30)
    assert abs(k_c.mean() - kappa) < abs(k_ml.mean() - kappa) / 3  # corrected: 0.99
    # uniform phases: corrected kappa is 0 about half the time, ML never
    u = rng.uniform(0, 2 * math.pi, (2000, n))
    zeros = np.mean([circular.fit_von_mises(ui).kappa == 0.0 for ui in u])
    assert 0.4 < zeros < 0.8


def test_von_mises_pdf_eq12():
    for mu, k in [(0.0, 0.0), (1.0, 2.0), (-2.0, 700.0)]:
        tot, _ = integrate.quad(
            lambda t: float(circular.von_mises_pdf(t, mu, k)),
            -math.pi,
            math.pi,
            points=[((mu + math.pi) % (2 * math.pi)) - math.pi],
            limit=400,
        )
        assert tot == pytest.approx(1.0, rel=1e-7)
    t = np.linspace(-3, 3, 13)
    np.testing.assert_allclose(circular.von_mises_pdf(t, 0.5, 3.0), stats.vonmises.pdf(t, 3.0, loc=0.5), rtol=1e-12)
    with pytest.raises(ValueError, match="kappa"):
        circular.von_mises_pdf(t, 0.0, -1.0)


def test_bad_input_raises():
    with pytest.raises(ValueError, match="at least one"):
        circular.summary([])
    with pytest.raises(ValueError, match="finite"):
        circular.summary([0.1, np.nan])
    with pytest.raises(ValueError, match="at least 2"):
        circular.fit_von_mises([0.3])


def test_npdd_eq19_21():
    # a smooth phase ramp (a homogeneous surface): the 3x3 ring's mean direction is the centre's,
    # NPDD_31 = 0 inside (the paper's "theoretically 0" for smooth surfaces)
    yy, xx = np.mgrid[0:40, 0:50]
    z = np.exp(1j * (0.2 * xx + 0.1 * yy)).astype(np.complex64) * 3.0
    d = circular.npdd(z)
    np.testing.assert_allclose(d[1:-1, 1:-1], 0.0, atol=1e-6)
    # a phase jump (a dihedral's edge): non-zero along it
    z2 = z.copy()
    z2[:, 25:] *= np.exp(1j * 2.0)
    d2 = circular.npdd(z2)
    assert np.abs(d2[5:-5, 24:26]).min() > 0.3 and np.abs(d2[5:-5, 5:20]).max() < 1e-5
    # i.i.d. uniform phases: NPDD uniform, circular variance near 1
    rng = np.random.default_rng(0)
    u = np.exp(1j * rng.uniform(0, 2 * np.pi, (200, 200)))
    v, r = circular.npdd_spread(circular.npdd(u))
    assert v > 0.97 and r < 0.03
    # against a direct evaluation of eq 20-21 at one pixel, s = 5, t = 3
    i, j = 17, 23
    th = np.angle(u)
    ring5 = [(a, b) for a in range(i - 2, i + 3) for b in range(j - 2, j + 3) if (a, b) != (i, j)]
    ring3 = [(a, b) for a in range(i - 1, i + 2) for b in range(j - 1, j + 2) if (a, b) != (i, j)]
    m5 = np.angle(np.mean([np.exp(1j * th[p]) for p in ring5]))
    m3 = np.angle(np.mean([np.exp(1j * th[p]) for p in ring3]))
    ref = np.angle(np.exp(1j * m5) / np.exp(1j * m3))
    assert circular.npdd(u, s=5, t=3)[i, j] == pytest.approx(ref, abs=1e-9)
    # absent pixels
    un = u.copy()
    un[50, 50] = np.nan
    assert np.isnan(circular.npdd(un)[50, 50]) and np.isfinite(circular.npdd(un)[50, 51])
    for bad in ({"s": 2}, {"s": 3, "t": 3}, {"t": 0}):
        with pytest.raises(ValueError):
            circular.npdd(u, **bad)
    with pytest.raises(ValueError, match="complex"):
        circular.npdd(np.abs(u))
    assert all(np.isnan(circular.npdd_spread([np.nan])))
