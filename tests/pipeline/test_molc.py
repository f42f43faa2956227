"""The maths of g0_cfar / k_cfar / ggd_cfar (:mod:`sarship.pipeline.stats.molc`): log-cumulant
estimators, exact thresholds against independent inversions, closed forms and Monte Carlo,
the K bracket, and the interpolation error of the per-pixel tables (docs/algorithms/g0_k_ggd.md)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import optimize, special, stats

from sarship.pipeline.stats import molc


def test_inverse_polygamma_round_trips():
    a = np.array([0.051, 0.3, 1.0, 7.5, 300.0, 1e6])
    np.testing.assert_allclose(molc.inv_trigamma(molc.trigamma(a)), a, rtol=1e-12)
    k = np.array([0.06, 0.5, 2.0, 40.0, 1e5])
    np.testing.assert_allclose(molc.inv_ggd_skew(molc.ggd_skew(k)), k, rtol=1e-10)
    assert molc.ggd_skew(1e-3) < -1.999 and -1e-3 < molc.ggd_skew(1e7) < 0  # the (-2, 0) range


def test_k_statistics_are_the_unbiased_cumulants():
    rng = np.random.default_rng(0)
    x = rng.gamma(2.0, 1.0, 50)
    k1, k2, k3 = molc.sample_log_cumulants(x)
    y = np.log(x)
    assert k1 == pytest.approx(y.mean(), rel=1e-13)
    assert k2 == pytest.approx(y.var(ddof=1), rel=1e-12)
    assert k3 == pytest.approx(stats.kstat(y, 3), rel=1e-10)


def test_k_tail_equals_the_bessel_closed_form():
    """Single-look K intensity: P(x > mu t) = 2 / Gamma(nu) (nu t)^{nu/2} K_nu(2 sqrt(nu t))
    (Jakeman & Pusey 1976), an expression independent of the trapezoid integral (5)."""
    for nu in (0.05, 0.3, 1.0, 4.0, 30.0):
        for t in (0.5, 5.0, 50.0):
            ex = 2.0 / special.gamma(nu) * (nu * t) ** (nu / 2) * special.kv(nu, 2.0 * math.sqrt(nu * t))
            assert molc.k_sf(t, nu, 1.0) == pytest.approx(ex, rel=1e-11), (nu, t)


def test_k_tail_and_quantile_against_monte_carlo_fractional_looks():
    rng = np.random.default_rng(1)
    nu, L, pfa, n = 1.5, 2.5, 1e-2, 2_000_000
    x = rng.gamma(nu, 1 / nu, n) * rng.gamma(L, 1 / L, n)
    tau = float(molc.k_tau(nu, L, pfa)[0])
    k = int((x > tau).sum())
    assert abs(k - n * pfa) <= 5 * math.sqrt(n * pfa), k
    # and the 1.25x-pfa quantile is told apart by the same bound
    k2 = int((x > float(molc.k_tau(nu, L, 1.25 * pfa)[0])).sum())
    assert abs(k2 - n * pfa) > 5 * math.sqrt(n * pfa), k2


@pytest.mark.parametrize("L,pfa", [(1.0, 1e-3), (3.7, 1e-9), (0.6, 1e-15), (50.0, 0.3)])
def test_k_bracket_is_a_bracket_and_inversion_converges(L, pfa):
    nu = np.array([0.05, 0.2, 1.0, 5.0, 50.0, 1e4])
    lo, hi = molc.k_bracket(nu, L, pfa)
    assert np.all(molc.k_sf(lo, nu, L) >= pfa) and np.all(molc.k_sf(hi, nu, L) <= pfa)
    t = molc.k_tau(nu, L, pfa)
    assert np.all((lo <= t) & (t <= hi))
    np.testing.assert_allclose(molc.k_sf(t, nu, L), pfa, rtol=1e-10)
    np.testing.assert_allclose(t, molc.k_tau_bisect(nu, L, pfa), rtol=1e-11)


@pytest.mark.parametrize(
    "a,L,pfa", [(0.08, 1.0, 1e-3), (1.5, 1.0, 1e-3), (3.0, 2.0, 1e-6), (80.0, 4.5, 1e-3), (2e4, 1.0, 1e-12)]
)
def test_g0_closed_form_equals_numerical_inversion(a, L, pfa):
    """Eq (3) against brentq on ln t of the G0 CDF (betainc)."""
    gam = max(2.0, a)  # x of order 1
    t = float(molc.g0_threshold(a, gam, L, pfa))
    f = lambda z: math.log(float(molc.g0_sf(math.exp(z), a, gam, L))) - math.log(pfa)  # noqa: E731
    z = optimize.brentq(f, math.log(t) - 1.0, math.log(t) + 1.0, xtol=1e-14, rtol=1e-14)
    assert math.log(t) == pytest.approx(z, abs=1e-9)


def test_g0_threshold_against_monte_carlo():
    rng = np.random.default_rng(2)
    a, L, gam, pfa, n = 2.5, 2.0, 1.5, 1e-2, 2_000_000
    x = gam / L * rng.gamma(L, 1.0, n) / rng.gamma(a, 1.0, n)
    k = int((x > float(molc.g0_threshold(a, gam, L, pfa))).sum())
    assert abs(k - n * pfa) <= 5 * math.sqrt(n * pfa), k


@pytest.mark.parametrize("v,kappa,pfa", [(0.7, 3.0, 1e-3), (2.0, 0.4, 1e-6), (-1.2, 2.0, 1e-3), (-0.5, 8.0, 1e-9)])
def test_ggd_closed_form_equals_numerical_inversion_and_table_form(v, kappa, pfa):
    sigma = 1.7
    t = float(molc.ggd_threshold(sigma, v, kappa, pfa))
    f = lambda z: math.log(float(molc.ggd_sf(math.exp(z), sigma, v, kappa))) - math.log(pfa)  # noqa: E731
    z = optimize.brentq(f, math.log(t) - 1.0, math.log(t) + 1.0, xtol=1e-14, rtol=1e-14)
    assert math.log(t) == pytest.approx(z, abs=1e-9)
    # eq (8): ln t = k1 + sqrt(k2) D(g1) with the model's own log-cumulants (eq 7)
    k1 = math.log(sigma) + (special.digamma(kappa) - math.log(kappa)) / v
    k2 = special.polygamma(1, kappa) / v**2
    k3 = special.polygamma(2, kappa) / v**3
    d = float(molc.ggd_D(k3 / k2**1.5, pfa)[0])
    assert k1 + math.sqrt(k2) * d == pytest.approx(math.log(t), abs=1e-9)


def test_ggd_D_is_continuous_through_the_lognormal_limit():
    z = stats.norm.isf(1e-3)
    d = molc.ggd_D(np.array([-1e-4, 0.0, 1e-4]), 1e-3)
    assert d[1] == pytest.approx(z, rel=1e-15)
    assert np.all(np.abs(d - z) < 1e-3)


def test_gamma_limit_is_the_l_look_gamma_quantile():
    """u -> 0: ln t - k1 = H(0), and k1 + H(0) is the log of the L-look gamma pfa-quantile."""
    L, pfa, mu = 3.0, 1e-4, 2.0
    k1 = math.log(mu) + special.digamma(L) - math.log(L)
    t = mu * special.gammainccinv(L, pfa) / L
    assert k1 + molc.gamma_H(L, pfa) == pytest.approx(math.log(t), abs=1e-12)
    for H in (molc.g0_H, molc.k_H):
        assert float(H(1e-7, L, pfa)[0]) == pytest.approx(molc.gamma_H(L, pfa), abs=1e-4)


@pytest.mark.parametrize("pfa,L", [(1e-3, 1.0), (1e-3, 4.0), (1e-8, 2.0), (1e-15, 0.3), (1e-6, 1e4)])
def test_tables_interpolation_error_is_bounded(pfa, L):
    """The per-pixel tables read at random points against the exact functions: the error in
    ln t is below 2e-5 (measured: <= 5e-6 for L in [0.05, 30], <= 1.5e-5 up to L = 1e4, pfa
    in [1e-15, 1e-3]; GGD <= 7e-6), i.e. a relative threshold error below 2e-5."""
    rng = np.random.default_rng(3)
    for tab, fn in ((molc.g0_table(pfa, L), molc.g0_H), (molc.k_table(pfa, L), molc.k_H)):
        w = rng.uniform(0.0, tab.x1, 60)
        got = molc.interp(np, tab.f, tab.x0, tab.inv_h, tab.n, w)
        err = np.abs(got - fn(molc.u_of_w(w, L), L, pfa))
        assert err.max() < 2e-5, (tab.key, err.max())
    g = rng.uniform(-molc.G1_MAX, molc.G1_MAX, 60)
    tab = molc.ggd_table(pfa)
    err = np.abs(molc.interp(np, tab.f, tab.x0, tab.inv_h, tab.n, g) - molc.ggd_D(g, pfa))
    assert err.max() < 2e-5, err.max()


def test_estimators_recover_known_parameters():
    rng = np.random.default_rng(4)
    n = 1_000_000
    # G0: a = 3, gamma = 2, L = 2
    a, gam, L = 3.0, 2.0, 2.0
    x = gam / L * rng.gamma(L, 1.0, n) / rng.gamma(a, 1.0, n)
    k1, k2, _ = molc.sample_log_cumulants(x)
    ah, gh = molc.g0_fit(k1, k2, L)
    assert float(ah) == pytest.approx(a, rel=0.03) and float(gh) == pytest.approx(gam, rel=0.03)
    # K: nu = 1.5, mu = 3, L = 1
    nu, mu, L = 1.5, 3.0, 1.0
    x = mu * rng.gamma(nu, 1 / nu, n) * rng.gamma(L, 1 / L, n)
    k1, k2, _ = molc.sample_log_cumulants(x)
    nh, mh = molc.k_fit(k1, k2, L)
    assert float(nh) == pytest.approx(nu, rel=0.05) and float(mh) == pytest.approx(mu, rel=0.02)
    # GGD, both signs of v
    for sigma, v, kappa in ((1.5, 0.7, 3.0), (0.5, -1.2, 2.0)):
        x = sigma * (rng.gamma(kappa, 1.0, n) / kappa) ** (1 / v)
        sh, vh, kh = molc.ggd_fit(*molc.sample_log_cumulants(x))
        assert float(vh) == pytest.approx(v, rel=0.05) and float(kh) == pytest.approx(kappa, rel=0.1)
        assert float(sh) == pytest.approx(sigma, rel=0.03)
    # a ring lighter-tailed than L-look gamma: the gamma limit
    assert np.isinf(molc.g0_fit(0.0, molc.trigamma(2.0) - 0.01, 2.0)[0])
