"""CGGD sampler (eq 27-31), density (eq 25-26) and shape estimators: Novey's ML (eq 32-34) and
the CSK route (eq 37, eq 39 inverted) of seed 004 (pipeline/stats/cggd.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import integrate, special, stats

from sarship.pipeline.stats import cggd


def _noncircular():
    return cggd.augmented_covariance(2.0, 1.2 * np.exp(0.7j))


@pytest.mark.parametrize("beta", [0.3, 1.0, 2.5])
def test_sampler_follows_the_density(beta):
    """Under eq 25, (c zz^H C^-1 zz / 2)^beta ~ Gamma(1/beta, 1) for any C (the radial law of the
    density); the samples of eq 27-31 must pass a KS test of it, and have covariance C."""
    rng = np.random.default_rng(7)
    C = _noncircular()
    z = cggd.sample(beta, C, 200_000, rng)
    c = math.exp(special.gammaln(2 / beta) - special.gammaln(1 / beta))
    g = (c * cggd._quad(z, C) / 2) ** beta
    assert stats.kstest(g, stats.gamma(1 / beta).cdf).pvalue > 1e-3
    assert np.mean(np.abs(z) ** 2) == pytest.approx(2.0, rel=0.03)
    assert abs(np.mean(z**2) - C[0, 1]) < 0.05 * 2.0
    # a wrong normalisation (eq 28 read literally, w = z / c) fails the same KS test unless c = 1
    if beta != 1.0:
        g_bad = (c * cggd._quad(z * math.sqrt(c) / c, C) / 2) ** beta
        assert stats.kstest(g_bad, stats.gamma(1 / beta).cdf).pvalue < 1e-6


@pytest.mark.parametrize("beta", [0.5, 1.0, 3.0])
def test_density_integrates_to_one_and_reduces_to_gaussian(beta):
    C = _noncircular()

    def f(y, x):
        return math.exp(float(cggd.log_pdf(complex(x, y), beta, C)))

    tot, _ = integrate.dblquad(f, -40, 40, -40, 40, epsabs=1e-9, epsrel=1e-7)
    assert tot == pytest.approx(1.0, abs=2e-4)
    if beta == 1.0:  # complex Gaussian with augmented covariance C: the real bivariate normal
        z = np.array([0.3 + 0.2j, -1.0 + 2.0j])
        s2, tau = C[0, 0].real, C[0, 1]
        cov = 0.5 * np.array([[s2 + tau.real, tau.imag], [tau.imag, s2 - tau.real]])
        ref = stats.multivariate_normal(np.zeros(2), cov).logpdf(np.c_[z.real, z.imag])
        np.testing.assert_allclose(cggd.log_pdf(z, 1.0, C), ref, rtol=1e-12)


def test_csk_of_beta_eq39():
    assert float(cggd.csk_of_beta(1.0)) == pytest.approx(0.0, abs=1e-14)
    assert float(cggd.csk_of_beta(2.0)) == pytest.approx(math.pi / 2 - 2, abs=1e-14)  # G(.5)G(1.5)/G(1)^2 - 2
    assert float(cggd.csk_of_beta(0.5)) == pytest.approx(120 / 36 - 2, abs=1e-12)  # G(2)G(6)/G(4)^2 - 2
    beta, c = cggd.csk_table()
    assert beta.size == 10_000 and beta[0] == pytest.approx(1e-3) and beta[-1] == pytest.approx(10.0)
    assert np.all(np.diff(c) < 0)  # monotone: the inversion is unique
    assert c[-1] > -2 / 3 and float(cggd.csk_of_beta(1e4)) == pytest.approx(-2 / 3, abs=1e-3)


def test_exact_inversion_vs_the_papers_table():
    rng = np.random.default_rng(0)
    b = np.concatenate([rng.uniform(0.05, 5.0, 300), [1e-3, 1.0, 9.999]])
    k = cggd.csk_of_beta(b)
    ex = cggd.beta_from_csk(k)
    np.testing.assert_allclose(ex, b, rtol=1e-9)  # exact round trip
    tb = cggd.beta_from_csk(k, method="table")
    assert np.max(np.abs(tb - b)) <= 1e-3  # nearest CSK entry of a 1e-3 grid: within one step (measured 5.1e-4)
    assert cggd.beta_from_csk(-0.7) == 10.0 and cggd.beta_from_csk(-0.7, method="table") == 10.0
    assert cggd.beta_from_csk(1e300) == pytest.approx(1e-3) and cggd.beta_from_csk(1e300, "table") == pytest.approx(
        1e-3
    )
    with pytest.raises(ValueError, match="method"):
        cggd.beta_from_csk(0.0, method="lut")


def test_sample_csk_converges_to_eq39_and_whitening_makes_it_hold_for_noncircular_data():
    rng = np.random.default_rng(3)
    for beta in (0.5, 1.0, 2.0):
        zc = cggd.sample(beta, None, 400_000, rng)
        assert cggd.csk(zc) == pytest.approx(
            float(cggd.csk_of_beta(beta)), abs=0.05 + 0.02 * abs(float(cggd.csk_of_beta(beta)))
        )
        zn = cggd.sample(beta, cggd.augmented_covariance(1.0, 0.9), 400_000, rng)
        if beta != 1.0:  # eq 39 needs circularity
            assert abs(cggd.csk(zn) - float(cggd.csk_of_beta(beta))) > 0.1
        assert cggd.csk(zn, whiten_first=True) == pytest.approx(float(cggd.csk_of_beta(beta)), abs=0.06)
        assert cggd.beta_csk(zn, whiten_first=True) == pytest.approx(beta, rel=0.05)


@pytest.mark.parametrize("beta", [0.4, 1.0, 2.0])
def test_novey_ml_recovers_shape_and_covariance(beta):
    rng = np.random.default_rng(11)
    C = _noncircular()
    z = cggd.sample(beta, C, 20_000, rng)
    fit = cggd.beta_novey(z)
    assert fit.beta == pytest.approx(beta, rel=0.06)
    np.testing.assert_allclose(fit.C, C, atol=0.08 * 2.0)
    # it is a stationary point of the likelihood in beta at the fitted C
    q = cggd._quad(z, fit.C)
    L, dL, d2L = cggd._loglik_derivs(fit.beta, q, math.log(float(np.linalg.det(fit.C).real)))
    assert abs(dL) < 1e-3 * z.size and d2L < 0
    # the analytic derivatives against finite differences
    h = 1e-5
    Lp = cggd._loglik_derivs(fit.beta + h, q, 0.0)[0]
    Lm = cggd._loglik_derivs(fit.beta - h, q, 0.0)[0]
    L0, d1, d2 = cggd._loglik_derivs(fit.beta, q, 0.0)
    assert d1 == pytest.approx((Lp - Lm) / (2 * h), rel=1e-4, abs=1e-3)
    assert d2 == pytest.approx((Lp - 2 * L0 + Lm) / h**2, rel=1e-3)
    # the likelihood of eq 26 is the sum of log_pdf
    assert L0 - 0.5 * 0.0 == pytest.approx(
        float(np.sum(cggd.log_pdf(z, fit.beta, fit.C))) + 0.5 * z.size * math.log(float(np.linalg.det(fit.C).real)),
        rel=1e-9,
    )


def test_bad_parameters_raise():
    with pytest.raises(ValueError, match="beta"):
        cggd.sample(0.0)
    with pytest.raises(ValueError, match="tau"):
        cggd.augmented_covariance(1.0, 1.0)
    with pytest.raises(ValueError, match="s2"):
        cggd.augmented_covariance(-1.0)
    with pytest.raises(ValueError, match="augmented covariance"):
        cggd.sample(1.0, np.eye(2) * [1.0, 2.0])
    with pytest.raises(ValueError, match="at least 2"):
        cggd.csk([1.0 + 0j])
    with pytest.raises(ValueError, match="NaN"):
        cggd.beta_from_csk(float("nan"))


def test_simulate_slc_cggd_clutter(tmp_path):
    """``sarship simulate --kind slc --clutter cggd --shape-beta B``: the sea is circular CGGD of
    shape B and mean power clutter_mean (its CSK is eq 39's, the CSK route recovers B)."""
    from sarship.pipeline.errors import InputError
    from sarship.pipeline.simulate import SimConfig, simulate_array, validate

    for beta in (0.5, 2.0):
        arr, _ = simulate_array(
            SimConfig(kind="slc", shape=(512, 512), ships=0, seed=4, clutter="cggd", shape_beta=beta, clutter_mean=3.0)
        )
        z = arr["hh"]
        assert z.dtype == np.complex64 and np.mean(np.abs(z) ** 2) == pytest.approx(3.0, rel=0.03)
        assert cggd.csk(z) == pytest.approx(float(cggd.csk_of_beta(beta)), abs=0.08)
        assert cggd.beta_csk(z) == pytest.approx(beta, rel=0.08)
    for bad in (dict(kind="intensity", clutter="cggd"), dict(kind="slc", clutter="cggd", shape_beta=0.0)):
        with pytest.raises(InputError, match="clutter|shape_beta"):
            validate(SimConfig(ships=0, **bad))
    import subprocess
    import sys

    res = subprocess.run(
        [
            sys.executable,
            "-m",
            "sarship",
            "simulate",
            str(tmp_path / "s.zarr"),
            "--kind",
            "slc",
            "--shape",
            "64x64",
            "--ships",
            "0",
            "--clutter",
            "cggd",
            "--shape-beta",
            "0.7",
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert res.returncode == 0, res.stderr
    res = subprocess.run(
        [
            sys.executable,
            "-m",
            "sarship",
            "simulate",
            str(tmp_path / "t.zarr"),
            "--shape",
            "64x64",
            "--clutter",
            "cggd",
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert res.returncode == 2 and "cggd" in res.stderr and len(res.stderr.strip().splitlines()) == 1
