"""Complex generalized Gaussian distribution (CGGD): sampler and shape estimators (seed 004, section 4).

Source: Leng, Ji, Xiong, Kuang 2020 (docs/references.md#leng2020), section 4.2-4.3, after
Novey, Adali & Roy 2010 (docs/references.md#novey2010) and Leng et al. 2020, IEEE GRSL
(docs/references.md#leng2020grsl) for the complex-signal-kurtosis (CSK) route.

Model (eq 25-26). A zero-mean complex z with augmented vector zz = [z, z*]^T and augmented
covariance C = E[zz zz^H] = [[s2, tau], [tau*, s2]] (eq 24: s2 = E|z|^2, tau = E z^2, the
pseudo-covariance; circular when tau = 0) has the density, c(beta) = Gamma(2/beta) / Gamma(1/beta),

    p(z | beta, C) = beta c(beta) / (pi sqrt|C| Gamma(1/beta)) exp(-[c(beta) zz^H C^-1 zz / 2]^beta)   (26)

beta = 1: complex Gaussian; beta < 1 super-Gaussian; beta > 1 sub-Gaussian.

Sampler (eq 27-31). z = G^(1/(2 beta)) exp(j 2 pi U), G ~ Gamma(1/beta, 1), U ~ U(0, 1) (eq 27);
w = z / sqrt(c(beta)) (eq 28: E|z|^2 = c(beta), so this w has unit variance; the paper prints
z / c(beta), a slip: only the square root makes E[ww ww^H] = I and eq 31's output have the
covariance C, as in Novey's eq 18); ww = [w, w*] (29); T = C^(1/2) (30, the Hermitian square
root); v = T ww (31), whose first entry is the sample. ``sample`` implements it and
``log_pdf`` the density of eq 25/26 (the tests check the two against each other).

Shape estimators (eq 32-39).

* Novey's maximum likelihood (eq 32-34), :func:`beta_novey`: the initial beta matches the
  sum of the real and imaginary parts' kurtoses to its CGGD value 3 Gamma(1/b)Gamma(3/b) /
  Gamma(2/b)^2 (eq 32; |f| minimised by Brent's method on ln beta), C starts as the sample
  augmented covariance; then Newton-Raphson on the log-likelihood in beta (eq 33, analytic
  first and second derivatives with digamma / trigamma, the step halved until the likelihood
  does not decrease), and, while beta < 1, the fixed-point update of C (eq 34),
  C = 2 beta (c/2)^beta / N sum_n (zz_n^H C^-1 zz_n)^(beta - 1) zz_n zz_n^H, until the step in
  beta is below 1e-6 (or 100 iterations).
* The CSK route (eq 35-39), :func:`beta_from_csk`: with standardised moments
  mu_{l,m} (Eriksson, Ollila & Koivunen 2010, docs/references.md#eriksson2010), zero mean,

      CSK = mu_22 - 2 - |mu_20|^2 = E|z|^4 / (E|z|^2)^2 - 2 - |E z^2|^2 / (E|z|^2)^2      (37)

  and for circular CGGD data (eq 39) CSK(beta) = Gamma(1/b) Gamma(3/b) / Gamma(2/b)^2 - 2,
  decreasing from +inf (beta -> 0) through 0 (beta = 1) to -2/3 (beta -> inf). The paper
  inverts it by the nearest entry of a table over beta in (0, 10], step 1e-3
  (``method="table"``, :func:`csk_table`). The default ``method="exact"`` solves
  ln(CSK + 2) = gammaln(1/b) + gammaln(3/b) - 2 gammaln(2/b) for ln beta by Brent's method
  (``scipy.optimize.brentq``, the left side is monotone in beta, so the root in the bracket
  [1e-3, 10] is unique): no quantisation (the table's nearest CSK entry is up to about half
  a step, 5e-4, off in beta: measured 5.1e-4), the answer to ~1e-12, and one scalar solve costs about
  as much as one table search (tens of microseconds, both negligible next to the moments
  for N >= 500). Both clip to [BETA_MIN, BETA_MAX] = [1e-3, 10], the paper's range: a sample
  CSK at or below CSK(10) gives 10.
* Eq 39 holds for circular data only: for non-circular CGGD (tau != 0) the sample CSK of eq 37
  moves away from it (beta = 0.5, |tau|/s2 = 0.9: 1.88 instead of 1.33). ``whiten=True``
  (:func:`whiten`) first maps the sample by the inverse square root of its sample augmented
  covariance (strong-uncorrelating / circularising transform), which makes CGGD data circular
  with the same beta, so eq 39 applies for any C. The paper's route is ``whiten=False``.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
from scipy import special

BETA_MIN = 1e-3
BETA_MAX = 10.0


def _check_beta(beta: float) -> float:
    b = float(beta)
    if not (math.isfinite(b) and b > 0.0):
        raise ValueError(f"shape parameter beta must be a positive finite number, got {beta!r}")
    return b


def augmented_covariance(s2: float, tau: complex = 0.0) -> np.ndarray:
    """C = [[s2, tau], [tau*, s2]] (eq 24); valid (positive definite) when |tau| < s2."""
    s2 = float(s2)
    tau = complex(tau)
    if not (math.isfinite(s2) and s2 > 0.0):
        raise ValueError(f"variance s2 must be positive and finite, got {s2!r}")
    if not abs(tau) < s2:
        raise ValueError(f"pseudo-covariance tau must have |tau| < s2 = {s2}, got {tau!r}")
    return np.array([[s2, tau], [tau.conjugate(), s2]], dtype=np.complex128)


def _sqrtm_aug(C: np.ndarray) -> np.ndarray:
    """Hermitian square root of a 2x2 Hermitian positive definite matrix (eq 30)."""
    w, V = np.linalg.eigh(C)
    if not np.all(w > 0):
        raise ValueError("augmented covariance C must be positive definite")
    return (V * np.sqrt(w)) @ V.conj().T


def sample(
    beta: float, C: np.ndarray | None = None, size=1, rng: np.random.Generator | None = None, dtype=np.complex128
) -> np.ndarray:
    """``size`` independent CGGD samples of shape ``beta`` and augmented covariance ``C``
    (default: circular, unit variance), by eq 27-31."""
    b = _check_beta(beta)
    rng = np.random.default_rng() if rng is None else rng
    C = augmented_covariance(1.0) if C is None else np.asarray(C, dtype=np.complex128)
    if C.shape != (2, 2) or not np.allclose(C, C.conj().T) or abs(C[0, 0] - C[1, 1]) > 1e-12 * abs(C[0, 0]):
        raise ValueError("C must be a 2x2 augmented covariance [[s2, tau], [conj(tau), s2]]")
    g = rng.standard_gamma(1.0 / b, size)
    u = rng.random(size)
    logc = special.gammaln(2.0 / b) - special.gammaln(1.0 / b)
    r = np.exp(np.log(g) / (2.0 * b) - 0.5 * logc) if np.any(g > 0) else np.zeros_like(g)  # eq 27, 28
    w = r * np.exp(2j * np.pi * u)
    T = _sqrtm_aug(C)  # eq 30
    v = T[0, 0] * w + T[0, 1] * np.conj(w)  # eq 29, 31
    return v.astype(dtype, copy=False)


def log_pdf(z, beta: float, C: np.ndarray) -> np.ndarray:
    """ln p(z | beta, C) of eq 25/26 at complex ``z`` (any shape)."""
    b = _check_beta(beta)
    C = np.asarray(C, dtype=np.complex128)
    z = np.asarray(z, dtype=np.complex128)
    q = _quad(z, C)
    logc = special.gammaln(2.0 / b) - special.gammaln(1.0 / b)
    det = float(np.linalg.det(C).real)
    with np.errstate(divide="ignore"):  # q = 0 (z = 0): the exponential term is exp(-inf) = 0
        return (
            math.log(b)
            + logc
            - math.log(math.pi)
            - 0.5 * math.log(det)
            - special.gammaln(1.0 / b)
            - np.exp(b * (logc + np.log(0.5 * q)))
        )


def _quad(z: np.ndarray, C: np.ndarray) -> np.ndarray:
    """zz^H C^-1 zz for zz = [z, z*] (real, >= 0)."""
    Ci = np.linalg.inv(C)
    a, bb = Ci[0, 0].real, Ci[0, 1]
    # [z*, z] Ci [z, z*]^T = a|z|^2 + Ci01 z* z* + Ci10 z z + a|z|^2
    return 2.0 * a * (z.real**2 + z.imag**2) + 2.0 * np.real(bb * np.conj(z) ** 2)


# ------------------------------------------------------------------------------------------
# CSK route (eq 35-39)
# ------------------------------------------------------------------------------------------


def csk_of_beta(beta) -> np.ndarray:
    """CSK of circular CGGD data of shape ``beta`` (eq 39), any shape of array."""
    b = np.asarray(beta, dtype=np.float64)
    return np.exp(special.gammaln(1.0 / b) + special.gammaln(3.0 / b) - 2.0 * special.gammaln(2.0 / b)) - 2.0


def moments(z) -> tuple[float, complex, float]:
    """``(m11, m20, m22)`` = (mean |z|^2, mean z^2, mean |z|^4) of a zero-mean sample."""
    z = np.asarray(z).ravel()
    if z.size < 2:
        raise ValueError("a CSK needs at least 2 samples")
    p = z.real.astype(np.float64) ** 2 + z.imag.astype(np.float64) ** 2
    m11 = float(p.mean())
    m20 = complex(np.mean(z.astype(np.complex128) ** 2))
    m22 = float(np.mean(p * p))
    return m11, m20, m22


def csk(z, whiten_first: bool = False) -> float:
    """Sample complex signal kurtosis (eq 37) of a zero-mean sample (the paper's assumption for
    SLC data): m22 / m11^2 - 2 - |m20|^2 / m11^2. ``whiten_first``: of :func:`whiten` (z)."""
    if whiten_first:
        z = whiten(z)
    m11, m20, m22 = moments(z)
    if not m11 > 0.0:
        raise ValueError("CSK of an all-zero sample is undefined")
    return m22 / (m11 * m11) - 2.0 - (m20.real**2 + m20.imag**2) / (m11 * m11)


def whiten(z) -> np.ndarray:
    """The sample mapped by the inverse square root of its sample augmented covariance
    [[m11, m20], [m20*, m11]]: unit variance and zero sample pseudo-covariance (circular)."""
    z = np.asarray(z, dtype=np.complex128).ravel()
    m11, m20, _ = moments(z)
    if not abs(m20) < m11:
        raise ValueError("sample is degenerate (improper to the limit |E z^2| = E|z|^2): cannot whiten")
    Ti = np.linalg.inv(_sqrtm_aug(np.array([[m11, m20], [np.conj(m20), m11]])))
    return Ti[0, 0] * z + Ti[0, 1] * np.conj(z)


@functools.lru_cache(maxsize=4)
def csk_table(step: float = 1e-3) -> tuple[np.ndarray, np.ndarray]:
    """The paper's look-up table (section 4.3.2): beta = step, 2 step, ..., 10 and CSK(beta)
    of eq 39 (decreasing), both float64, read-only."""
    n = int(round(BETA_MAX / step))
    beta = np.arange(1, n + 1, dtype=np.float64) * step
    c = csk_of_beta(beta)
    beta.setflags(write=False)
    c.setflags(write=False)
    return beta, c


def _beta_table(k: np.ndarray) -> np.ndarray:
    beta, c = csk_table()
    rc = c[::-1]  # increasing
    i = np.searchsorted(rc, k)  # rc[i-1] < k <= rc[i]
    i = np.clip(i, 1, rc.size - 1)
    nearer_low = np.abs(k - rc[i - 1]) <= np.abs(rc[i] - k)
    j = np.where(nearer_low, i - 1, i)
    out = beta[::-1][j]
    out = np.where(k >= rc[-1], beta[0], out)
    out = np.where(k <= rc[0], beta[-1], out)
    return out


def _beta_exact(k: float) -> float:
    from scipy import optimize  # lazy: importing scipy.optimize costs every command start-up time

    hi_c = float(csk_of_beta(BETA_MIN))
    lo_c = float(csk_of_beta(BETA_MAX))
    if not k > lo_c:
        return BETA_MAX
    if not k < hi_c:
        return BETA_MIN
    target = math.log(k + 2.0)

    def f(lb: float) -> float:
        b = math.exp(lb)
        return special.gammaln(1.0 / b) + special.gammaln(3.0 / b) - 2.0 * special.gammaln(2.0 / b) - target

    return math.exp(optimize.brentq(f, math.log(BETA_MIN), math.log(BETA_MAX), xtol=1e-13, rtol=1e-15))


def beta_from_csk(k, method: str = "exact"):
    """Shape beta of circular CGGD data whose CSK is ``k`` (eq 39 inverted), clipped to
    [BETA_MIN, BETA_MAX]; ``method`` "exact" (Brent on ln beta) or "table" (the paper's
    nearest entry of the 1e-3 table). Scalar in, float out; array in, array out."""
    if method not in ("exact", "table"):
        raise ValueError(f"method must be 'exact' or 'table', got {method!r}")
    ka = np.asarray(k, dtype=np.float64)
    if np.any(np.isnan(ka)):
        raise ValueError("CSK must not be NaN")
    if method == "table":
        out = _beta_table(ka)
    else:
        out = np.vectorize(_beta_exact, otypes=[np.float64])(ka) if ka.ndim else np.float64(_beta_exact(float(ka)))
    return float(out) if np.ndim(out) == 0 else out


def beta_csk(z, method: str = "exact", whiten_first: bool = False) -> float:
    """CGGD shape of a zero-mean sample by the CSK route (eq 37 then eq 39 inverted)."""
    return float(beta_from_csk(csk(z, whiten_first=whiten_first), method))


# ------------------------------------------------------------------------------------------
# Novey's maximum likelihood (eq 32-34)
# ------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class NoveyFit:
    beta: float
    C: np.ndarray
    beta0: float  # the moment start of eq 32
    iterations: int
    loglik: float


def _moment_start(z: np.ndarray) -> float:
    """beta minimising |f(beta)| of eq 32 (real and imaginary kurtoses summed)."""
    from scipy import optimize  # lazy: importing scipy.optimize costs every command start-up time

    x, y = z.real, z.imag
    kx = np.mean(x**4) / np.mean(x**2) ** 2
    ky = np.mean(y**4) / np.mean(y**2) ** 2
    s = float(kx + ky)

    def f(lb: float) -> float:
        return abs(s - 3.0 * (float(csk_of_beta(math.exp(lb))) + 2.0))

    r = optimize.minimize_scalar(
        f, bounds=(math.log(0.05), math.log(BETA_MAX)), method="bounded", options={"xatol": 1e-8}
    )
    return float(math.exp(r.x))


def _loglik_derivs(beta: float, q: np.ndarray, logdet: float) -> tuple[float, float, float]:
    """Log-likelihood of eq 26 in beta (C fixed; q = zz^H C^-1 zz) and its first and second
    derivatives in beta (digamma psi, trigamma psi1)."""
    n = q.size
    a = 1.0 / beta
    logc = special.gammaln(2 * a) - special.gammaln(a)
    g1 = 2 * special.digamma(2 * a) - special.digamma(a)  # d logc / da
    g2 = 4 * special.polygamma(1, 2 * a) - special.polygamma(1, a)  # d2 logc / da2
    dl = -g1 / beta**2  # d logc / d beta
    d2l = g2 / beta**4 + 2 * g1 / beta**3
    u = logc + np.log(0.5 * q)
    t = np.exp(beta * u)  # (c q / 2)^beta
    du = dl
    s1 = u + beta * du
    L = n * (math.log(beta) + logc - math.log(math.pi) - 0.5 * logdet - special.gammaln(a)) - float(t.sum())
    # normalisation n[ln b + lnG(2a) - 2 lnG(a)] (ln c - lnG(a) = lnG(2a) - 2 lnG(a))
    h1 = 2 * special.digamma(2 * a) - 2 * special.digamma(a)
    h2 = 4 * special.polygamma(1, 2 * a) - 2 * special.polygamma(1, a)
    dnorm = n * (1.0 / beta - h1 / beta**2)
    d2norm = n * (-1.0 / beta**2 + h2 / beta**4 + 2 * h1 / beta**3)
    dL = dnorm - float(np.sum(t * s1))
    d2L = d2norm - float(np.sum(t * (s1 * s1 + 2 * du + beta * d2l)))
    return L, dL, d2L


def beta_novey(z, max_iter: int = 100, tol: float = 1e-6) -> NoveyFit:
    """Novey's ML estimate of the CGGD shape and augmented covariance (eq 32-34)."""
    z = np.asarray(z, dtype=np.complex128).ravel()
    if z.size < 2:
        raise ValueError("Novey's estimator needs at least 2 samples")
    m11, m20, _ = moments(z)
    C = np.array([[m11, m20], [np.conj(m20), m11]])
    beta = _moment_start(z)
    beta0 = beta
    it = 0
    L = math.nan
    for it in range(1, max_iter + 1):  # noqa: B007 (the count is reported after the loop)
        q = _quad(z, C)
        logdet = math.log(float(np.linalg.det(C).real))
        L, dL, d2L = _loglik_derivs(beta, q, logdet)
        if d2L < 0:
            step = dL / d2L
        else:  # not concave here: an uphill step of bounded size instead of Newton's
            step = -math.copysign(min(abs(dL), 0.1 * beta), dL)
        new = beta - step  # eq 33
        while not (new > BETA_MIN and _loglik_derivs(new, q, logdet)[0] >= L - 1e-12 * abs(L)):
            step *= 0.5
            new = beta - step
            if abs(step) < 1e-14:
                new = beta
                break
        done = abs(new - beta) < tol
        beta = min(max(new, BETA_MIN), BETA_MAX)
        if beta < 1.0:  # eq 34
            c = math.exp(special.gammaln(2 / beta) - special.gammaln(1 / beta))
            q = _quad(z, C)
            wgt = q ** (beta - 1.0)
            zz = np.stack([z, np.conj(z)])
            C = (2 * beta * (0.5 * c) ** beta / z.size) * (zz * wgt) @ zz.conj().T
            C = 0.5 * (C + C.conj().T)
        if done:
            break
    return NoveyFit(beta=float(beta), C=C, beta0=beta0, iterations=it, loglik=float(L))
