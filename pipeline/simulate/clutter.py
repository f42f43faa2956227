"""Sea clutter: speckle, complex Gaussian draws and the polarimetric sea covariance.

Clutter (sea)
    * ``rayleigh``: fully developed single-look speckle, intensity exponential with mean
      ``clutter_mean`` (Goodman 1976; Oliver & Quegan, *Understanding SAR Images*, 1998, ch. 4).
      The scene's ``looks`` is 1 whatever ``cfg.looks`` says.
    * ``gamma``: L-look intensity, Gamma(shape L, mean ``clutter_mean``) (Oliver & Quegan ch. 4);
      ``looks`` may be fractional.
    * ``k``: compound model I = clutter_mean * T * S, with texture T ~ Gamma(shape nu, mean 1)
      spatially correlated and S the L-look gamma speckle, i.e. K-distributed intensity
      (Jakeman & Pusey 1976; Ward 1981). T is a Gaussian copula: a unit-variance Gaussian
      random field, mapped pixel by pixel through the Gamma(nu) quantile function (a 4097-point
      table, linear interpolation), so its marginal is exactly Gamma(nu, 1/nu) and
      E[T] = 1, Var[T] = 1/nu. The Gaussian field is a separable cubic B-spline of i.i.d.
      N(0,1) nodes, renormalised per pixel by sqrt(sum w^2) so that its variance is exactly 1;
      the node spacing is ``texture_corr_px / 1.1847`` so that the field's autocorrelation
      B7(lag/s)/B7(0) (B7: the degree-7 B-spline, the autocorrelation of the cubic) is 1/e at
      lag ``texture_corr_px``. Intensity moments: E[I] = clutter_mean,
      Var[I]/E[I]^2 = (1 + 1/nu)(1 + 1/L) - 1.
    * ``g0``: compound model I = clutter_mean * T * S with an inverse-gamma texture,
      T = (a - 1) / G, G ~ Gamma(a, 1), a = ``texture_shape`` > 1 (E[T] = 1), and L-look gamma
      speckle S: the G0 intensity distribution of Frery et al. 1997 with alpha = -a and
      gamma = (a - 1) clutter_mean (docs/references.md#frery1997). T is the same Gaussian copula
      as for ``k`` (:func:`sea_texture`: T = (a - 1) / (a T_a), T_a the copula's
      Gamma(a, 1/a) texture), so its marginal is exactly inverse gamma and the texture is
      correlated over ``texture_corr_px``; the speckle is i.i.d.
    * ``ggd``: generalized gamma intensity (Stacy 1962; Li et al. 2011,
      docs/references.md#li2011), i.i.d. between pixels: I = sigma (G / kappa)^(1 / v),
      G ~ Gamma(kappa, 1), v = ``ggd_power``, kappa = ``ggd_shape``, sigma such that
      E[I] = clutter_mean (:func:`ggd_speckle`). Intensity scenes only; the scene's ``looks``
      is the GGD's equivalent number of looks mean^2 / variance (:func:`ggd_enl`).
    * ``slc``: circular complex Gaussian hh with E|hh|^2 = clutter_mean (times T for ``k``):
      the single-look complex form of the same models; ``looks`` is 1.
    * ``cggd`` (``slc`` only): circular complex generalized Gaussian hh of shape ``shape_beta``
      (Novey et al. 2010; seed 004 eq 25-31, :func:`sarship.pipeline.stats.cggd.sample`), i.i.d.,
      E|hh|^2 = clutter_mean; beta = 1 is the complex Gaussian.
    * ``quadpol``: X = [HH, HV, VV] zero-mean circular complex Gaussian (thesis
      Sun 2020, docs/references.md#sun2020, eq 2-1, 2-2) with the reflection-symmetric covariance of eq 2-3,
      Sigma = sigma_hh [[1, 0, rho sqrt(g)], [0, eps, 0], [conj(rho) sqrt(g), 0, g]], where
      ``rho = E[HH VV*] / sqrt(E|HH|^2 E|VV|^2)`` (eq 2-4 omits the conjugate; the usual
      definition is used). Sea values (typical C/L-band open sea, not fitted to data):
      :data:`SEA_EPS` = 0.03 (HV ~15 dB below HH), :data:`SEA_GAMMA` = 1.5 (VV 1.8 dB above
      HH, Bragg scattering), :data:`SEA_RHO` = 0.7 exp(i 10 deg). sigma_hh = clutter_mean;
      X = sqrt(T) L z with L the Cholesky factor of Sigma and z ~ CN(0, I) for ``k``.
    Speckle is i.i.d. between pixels (an ideal, unweighted single-look processor sampled at
    the resolution): the CFAR calibration tests rely on it.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from scipy import special

from sarship.pipeline.simulate.config import SimConfig

#: Quad-pol sea covariance parameters (eq 2-3 of thesis 000): HV/HH, VV/HH, HH-VV correlation.
SEA_EPS = 0.03
SEA_GAMMA = 1.5
SEA_RHO = complex(0.7 * math.cos(math.radians(10.0)), 0.7 * math.sin(math.radians(10.0)))


def sea_covariance(cfg: SimConfig | None = None) -> np.ndarray:
    """The quad-pol sea covariance Sigma (eq 2-3), times ``cfg.clutter_mean`` (3x3 complex128)."""
    s = 1.0 if cfg is None else float(cfg.clutter_mean)
    return s * _refl_cov(SEA_EPS, SEA_GAMMA, SEA_RHO)


def _refl_cov(eps: float, gamma: float, rho: complex) -> np.ndarray:
    sg = math.sqrt(gamma)
    return np.array([[1, 0, rho * sg], [0, eps, 0], [np.conj(rho) * sg, 0, gamma]], dtype=np.complex128)


def _span_factor(eps: float, gamma: float) -> float:
    return 1.0 + 2.0 * eps + gamma


def _sea_power(cfg: SimConfig) -> float:
    """Mean sea power in the units ships are scaled in (span for quad-pol)."""
    f = _span_factor(SEA_EPS, SEA_GAMMA) if cfg.kind == "quadpol" else 1.0
    return cfg.clutter_mean * f


def _cn(rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
    """n1 + i n2 with n1, n2 i.i.d. N(0,1) (E|z|^2 = 2), complex64."""
    return rng.standard_normal(shape + (2,), dtype=np.float32).view(np.complex64)[..., 0]


def _speckle(rng: np.random.Generator, looks: float, shape: tuple[int, ...]) -> np.ndarray:
    """Unit-mean L-look gamma intensity speckle (float32)."""
    if looks == 1.0:
        return rng.standard_exponential(shape, dtype=np.float32)
    g = rng.standard_gamma(looks, shape, dtype=np.float32)
    g *= np.float32(1.0 / looks)
    return g


def _chol(eps: float, gamma: float, rho: complex) -> np.ndarray:
    return np.linalg.cholesky(_refl_cov(eps, gamma, rho))


def _polmix(lc: np.ndarray, z: np.ndarray, amp: Any) -> list[np.ndarray]:
    """X = amp * L z for the lower-triangular L (skipping zeros); z (3, ...) complex64."""
    out = []
    for i in range(3):
        acc = None
        for j in range(i + 1):
            v = complex(lc[i, j])
            if v == 0:
                continue
            if v == 1:
                t = z[j]
            elif v.imag == 0:
                t = z[j] * np.float32(v.real)
            else:
                t = z[j] * np.complex64(v)
            acc = t if acc is None else acc + t
        out.append(acc * amp)
    return out


def sea_texture(cfg: SimConfig, g: np.ndarray) -> np.ndarray:
    """The unit-mean sea texture T of ``k`` (Gamma(nu, 1/nu)) or ``g0`` (inverse gamma,
    (a - 1) / Gamma(a, 1)) from a unit Gaussian field ``g`` (float32)."""
    from sarship.pipeline.simulate.fields import _gamma_texture

    a = float(cfg.texture_shape)
    t = _gamma_texture(g, a)
    if cfg.clutter == "k":
        return t
    # a T_a ~ Gamma(a, 1)  =>  (a - 1) / (a T_a) is inverse gamma with mean 1
    return (np.float32((a - 1.0) / a) / t).astype(np.float32)


def _ggd_moment(v: float, kappa: float, k: float) -> float:
    """E[(G / kappa)^(k / v)], G ~ Gamma(kappa, 1)."""
    return math.exp(special.gammaln(kappa + k / v) - special.gammaln(kappa) - (k / v) * math.log(kappa))


def ggd_enl(v: float, kappa: float) -> float:
    """Equivalent number of looks mean^2 / variance of the GGD (power v, shape kappa)."""
    m1 = _ggd_moment(v, kappa, 1.0)
    m2 = _ggd_moment(v, kappa, 2.0)
    return float(m1 * m1 / (m2 - m1 * m1))


def effective_looks(cfg: SimConfig) -> float:
    """The scene's number of looks: cfg.looks for gamma/K/G0 intensity (the speckle's L), the
    equivalent number of looks mean^2 / variance of the GGD for ``ggd``, else 1."""
    if cfg.kind != "intensity" or cfg.clutter == "rayleigh":
        return 1.0
    if cfg.clutter == "ggd":
        return ggd_enl(cfg.ggd_power, cfg.ggd_shape)
    return float(cfg.looks)


def ggd_speckle(rng: np.random.Generator, cfg: SimConfig, shape: tuple[int, ...]) -> np.ndarray:
    """Unit-mean GGD intensity (float32): (G / kappa)^(1 / v) / E[(G / kappa)^(1 / v)]."""
    v, kappa = float(cfg.ggd_power), float(cfg.ggd_shape)
    g = rng.standard_gamma(kappa, shape, dtype=np.float32).astype(np.float64)
    x = np.power(g * (1.0 / kappa), 1.0 / v) * (1.0 / _ggd_moment(v, kappa, 1.0))
    return x.astype(np.float32)
