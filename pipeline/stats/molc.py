"""Method of log-cumulants (MoLC) for G0, K and generalized-gamma intensity clutter, and the
CFAR thresholds of ``g0_cfar``, ``k_cfar`` and ``ggd_cfar`` (docs/algorithms/g0_k_ggd.md).

Pure maths, NumPy/SciPy (the per-pixel parts also take CuPy arrays: ``xp`` is the array's
module). Equation numbers below are those of docs/algorithms/g0_k_ggd.md (section "Equations").

Log-cumulants (Nicolas 2002, docs/references.md#nicolas2002). For a ring of n present
samples with logs y_i = ln x_i, the k-statistics (unbiased cumulant estimators)

    k1 = S1 / n,  k2 = (S2 - n k1^2) / (n - 1),
    k3 = n / ((n - 1)(n - 2)) (S3 - 3 k1 S2 + 2 n k1^3)                               (1)

with S_j = sum y_i^j: window sums (tiling-invariant :mod:`sarship.pipeline.tiling.boxsum`), ring =
background box minus guard box, in float64.

Models (x intensity, L looks known; polygamma psi_m, psi = psi_0):

* G0 (Frery et al. 1997): x = (gamma / L) S / G, S ~ Gamma(L, 1), G ~ Gamma(a, 1), a = -alpha > 0:
  k1 = ln(gamma / L) + psi(L) - psi(a),  k2 = psi_1(L) + psi_1(a)                        (2)
  (Tison et al. 2004); P(x > t) = P(B < c) with B = G / (S + G) ~ Beta(a, L), c = 1 / (1 + L t / gamma):
  t = (gamma / L) (1 - c) / c,  c = I^{-1}_{a, L}(pfa)                                   (3)
  (closed form, no bracket needed: ``scipy.special`` / ``scipy.stats.beta.isf``).
* K (Jakeman & Pusey 1976; Oliver & Quegan 1998): x = mu (G / nu) (S / L), G ~ Gamma(nu, 1):
  k1 = ln mu + psi(nu) - ln nu + psi(L) - ln L,  k2 = psi_1(nu) + psi_1(L)               (4)
  P(x > mu tau) = E_G[Q(L, L nu tau / G)] (Q: regularised upper incomplete gamma),       (5)
  integrated by the trapezoidal rule in s = ln(G / nu) (spectrally accurate for a smooth,
  rapidly decaying integrand on the line), inverted by regula falsi (Illinois) inside the
  proven bracket (6).
* Generalized gamma GGD (Stacy 1962; Li et al. 2011): (x / sigma)^v kappa ~ Gamma(kappa, 1):
  k1 = ln sigma + (psi(kappa) - ln kappa) / v,  k2 = psi_1(kappa) / v^2,
  k3 = psi_2(kappa) / v^3                                                               (7)
  so the skewness of ln x, g1 = k3 / k2^{3/2} = sign(v) psi_2(kappa) / psi_1(kappa)^{3/2}, fixes
  kappa (|g1| < 2, monotone) and sign(v) (= -sign(k3)); the threshold is
  ln t = k1 + sqrt(k2) D(g1), D the upper-pfa quantile of the standardised ln x:       (8)
  D = (ln Q^{-1}(kappa, pfa) - psi(kappa)) / sqrt(psi_1(kappa)) for v > 0,
  D = -(ln P^{-1}(kappa, pfa) - psi(kappa)) / sqrt(psi_1(kappa)) for v < 0, D(0) = z_pfa
  (the lognormal limit).

With L known, G0 and K both depend on the ring through u = k2 - psi_1(L) = psi_1(shape) and
ln t = k1 + H(u) (eqs 2-5), so each detector reads one function H of one variable, tabulated
here per (pfa, L) on a uniform grid of w = ln(1 + u max(1, 1 / psi_1(L))) and interpolated
linearly (:func:`interp`: the same few IEEE operations on CPU and GPU). u <= 0 (a ring lighter-tailed than L-look gamma)
is the gamma limit H(0) (shape -> infinity). The tables are *computed* (never copied), cached
per process; their interpolation error is bounded by tests (tests/pipeline/test_molc.py).
"""

from __future__ import annotations

import functools
import math

import numpy as np
from scipy import special

#: Smallest shape (a = -alpha for G0, nu for K) in the tables: u = psi_1(0.05) = 401.5. A ring
#: with a larger u (log-variance) is outside the model: the pixel is not tested.
SHAPE_MIN = 0.05
#: Smallest GGD kappa in the table: |g1| <= G1_MAX = 1.98882 (the GGD bound is 2).
KAPPA_MIN = 0.05
#: Grid sizes of the per-pixel tables (uniform grids, linear interpolation): G0 / K, GGD.
N_TABLE = 16384
N_TABLE_GGD = 8192
#: K: exact nodes, then a cubic spline onto the N_TABLE grid (the K tail is an integral).
N_K_EXACT = 129
#: Trapezoid points of the K tail integral (5).
N_K_QUAD = 400
#: Shapes above this are the gamma limit in the table builders (u < 1e-12).
SHAPE_INF = 1e12


def trigamma(a):
    return special.polygamma(1, a)


def _bisect_newton(f, df, target, lo: float, hi: float, n_bisect: int = 16, n_newton: int = 5):
    """z with f(z) = target for f increasing on [lo, hi] (vectorised over ``target``): bisection
    to a bracket of width (hi - lo) / 2^n_bisect (<= 8e-4 here), then Newton steps clipped to
    that bracket (quadratic convergence: float64-exact after 4 steps; round trips are tested
    to 1e-12)."""
    t = np.asarray(target, np.float64)
    a = np.full(t.shape, float(lo))
    b = np.full(t.shape, float(hi))
    for _ in range(n_bisect):
        mid = 0.5 * (a + b)
        low = f(mid) < t
        a = np.where(low, mid, a)
        b = np.where(low, b, mid)
    z = 0.5 * (a + b)
    for _ in range(n_newton):
        d = df(z)
        step = np.where(d > 0, (f(z) - t) / np.where(d > 0, d, 1.0), 0.0)
        z = np.clip(z - step, a, b)
    return z


def inv_trigamma(u: np.ndarray) -> np.ndarray:
    """a > 0 with psi_1(a) = u (u > 0): on z = ln a over [ln 1e-8, ln 1e14], -psi_1(e^z) is
    increasing (psi_1 decreases from +inf to 0), so the root is bracketed whenever
    psi_1(1e14) < u < psi_1(1e-8); bisection then Newton (:func:`_bisect_newton`)."""
    f = lambda z: -special.polygamma(1, np.exp(z))  # noqa: E731
    df = lambda z: -np.exp(z) * special.polygamma(2, np.exp(z))  # noqa: E731
    return np.exp(_bisect_newton(f, df, -np.asarray(u, np.float64), math.log(1e-8), math.log(1e14)))


def ggd_skew(kappa):
    """g(kappa) = psi_2(kappa) / psi_1(kappa)^{3/2}, increasing from -2 (kappa -> 0) to 0."""
    return special.polygamma(2, kappa) / special.polygamma(1, kappa) ** 1.5


G1_MAX = float(-ggd_skew(KAPPA_MIN))


def inv_ggd_skew(g: np.ndarray) -> np.ndarray:
    """kappa with g(kappa) = -|g| (0 < |g| < 2), on z = ln kappa over [ln 1e-6, ln 1e16]
    (g increasing), bisection then Newton; dg/dz = kappa (psi_3 / psi_1^{3/2} - 1.5 psi_2^2 / psi_1^{5/2})."""

    def df(z):
        k = np.exp(z)
        p1, p2, p3 = (special.polygamma(m, k) for m in (1, 2, 3))
        return k * (p3 / p1**1.5 - 1.5 * p2 * p2 / p1**2.5)

    f = lambda z: ggd_skew(np.exp(z))  # noqa: E731
    return np.exp(_bisect_newton(f, df, -np.abs(np.asarray(g, np.float64)), math.log(1e-6), math.log(1e16)))


# --------------------------------------------------------------------------- estimators


def sample_log_cumulants(x: np.ndarray) -> tuple[float, float, float]:
    """(k1, k2, k3) of eq (1) from samples (float64 arithmetic; the reference the window sums
    are checked against)."""
    y = np.log(np.asarray(x, np.float64))
    n = y.size
    s1, s2, s3 = y.sum(), (y * y).sum(), (y * y * y).sum()
    return k_statistics(float(n), s1, s2, s3)


def k_statistics(n, s1, s2, s3):
    """Eq (1) from the power sums (any array module; n >= 3)."""
    k1 = s1 / n
    k2 = (s2 - n * k1 * k1) / (n - 1.0)
    k3 = (s3 - 3.0 * k1 * s2 + 2.0 * n * k1 * k1 * k1) * (n / ((n - 1.0) * (n - 2.0)))
    return k1, k2, k3


def g0_fit(k1, k2, looks: float):
    """MoLC for G0 intensity, eq (2): (a = -alpha, gamma); a = inf where k2 <= psi_1(L)."""
    u = np.asarray(k2, np.float64) - trigamma(looks)
    a = np.where(u > 0, inv_trigamma(np.where(u > 0, u, 1.0)), np.inf)
    with np.errstate(invalid="ignore"):
        gam = looks * np.exp(np.asarray(k1) - special.digamma(looks) + special.digamma(a))
        gam = np.where(np.isinf(a), np.nan, gam)
    return a, gam


def k_fit(k1, k2, looks: float):
    """MoLC for K intensity, eq (4): (nu, mu); nu = inf where k2 <= psi_1(L)."""
    u = np.asarray(k2, np.float64) - trigamma(looks)
    nu = np.where(u > 0, inv_trigamma(np.where(u > 0, u, 1.0)), np.inf)
    with np.errstate(invalid="ignore"):
        c = np.where(np.isinf(nu), 0.0, special.digamma(nu) - np.log(nu))
    mu = np.exp(np.asarray(k1) - c - special.digamma(looks) + math.log(looks))
    return nu, mu


def ggd_fit(k1, k2, k3):
    """MoLC for the generalized gamma, eq (7): (sigma, v, kappa) (Li et al. 2011)."""
    k1, k2, k3 = (np.asarray(v, np.float64) for v in (k1, k2, k3))
    g1 = k3 / k2**1.5
    kappa = inv_ggd_skew(g1)
    v = -np.sign(k3) * np.sqrt(special.polygamma(1, kappa) / k2)
    sigma = np.exp(k1 - (special.digamma(kappa) - np.log(kappa)) / v)
    return sigma, v, kappa


# --------------------------------------------------------------------------- exact thresholds


def g0_log_odds(a, looks: float, pfa: float):
    """ln((1 - c) / c) of eq (3), c = I^{-1}_{a, L}(pfa) the lower-pfa quantile of Beta(a, L)
    and r = 1 - c the upper-pfa quantile of Beta(L, a); both are computed as quantiles
    (``betaincinv``, ``beta.isf``), so the smaller of c and r keeps its relative precision
    (r is small when a is large, c when a is small)."""
    from scipy import stats  # lazy: importing scipy.stats costs every command start-up time

    a = np.asarray(a, np.float64)
    c = special.betaincinv(a, looks, pfa)
    r = stats.beta.isf(pfa, looks, a)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(r < 0.5, np.log(r) - np.log1p(-r), np.log1p(-c) - np.log(c))


def g0_threshold(a, gam, looks: float, pfa: float):
    """Eq (3): the G0 intensity t with P(x > t) = pfa."""
    return gam / looks * np.exp(g0_log_odds(a, looks, pfa))


def g0_sf(t, a, gam, looks: float):
    """P(x > t) for G0 intensity (the CDF the closed form (3) inverts)."""
    c = 1.0 / (1.0 + looks * np.asarray(t) / gam)
    return special.betainc(a, looks, c)


def gamma_H(looks: float, pfa: float) -> float:
    """H(0), the gamma limit of G0 and K: ln t - k1 = ln Q^{-1}(L, pfa) - psi(L)."""
    return float(np.log(special.gammainccinv(looks, pfa)) - special.digamma(looks))


def g0_H(u, looks: float, pfa: float):
    """H(u) = ln t - k1 for G0 (eqs 2, 3): psi(a) - psi(L) + ln((1 - c) / c), a = psi_1^{-1}(u)."""
    u = np.atleast_1d(np.asarray(u, np.float64))
    out = np.full(u.shape, gamma_H(looks, pfa))
    pos = u > trigamma(SHAPE_INF)
    if pos.any():
        a = inv_trigamma(u[pos])
        out[pos] = special.digamma(a) - special.digamma(looks) + g0_log_odds(a, looks, pfa)
    return out


def k_sf(tau, nu, looks: float, n_quad: int = N_K_QUAD):
    """P(x > mu tau) for K intensity, eq (5), vectorised over (tau, nu) (broadcast).

    Trapezoid in s = ln g, g = G / nu ~ Gamma(nu, 1/nu), on [s_lo, s_hi]: beyond s_hi the
    texture's mass is < 1e-40 (``gammainccinv(nu, 1e-40)``); below s_lo both the texture's
    mass (``gammaincinv(nu, 1e-40)``) or the speckle tail Q(L, L tau / g) (< 1e-40 once
    L tau / g > ``gammainccinv(L, 1e-40)``) are negligible: the truncation error is < 2e-40.
    """
    tau, nu = np.broadcast_arrays(np.asarray(tau, np.float64), np.asarray(nu, np.float64))
    s_hi = np.log(special.gammainccinv(nu, 1e-40) / nu)
    with np.errstate(divide="ignore"):
        s_lo_g = np.log(special.gammaincinv(nu, 1e-40) / nu)
    s_lo_q = np.log(looks * tau / special.gammainccinv(looks, 1e-40))
    s_lo = np.maximum(s_lo_g, s_lo_q)
    s_lo = np.minimum(s_lo, s_hi - 1e-3)
    k = np.linspace(0.0, 1.0, n_quad)
    s = s_lo[..., None] + (s_hi - s_lo)[..., None] * k
    g = np.exp(s)
    nu_ = nu[..., None]
    # log density of s = ln g: nu ln nu + nu s - nu g - lgamma(nu)
    logf = nu_ * np.log(nu_) + nu_ * s - nu_ * g - special.gammaln(nu_)
    q = special.gammaincc(looks, looks * tau[..., None] / g)
    f = q * np.exp(logf)
    h = (s_hi - s_lo) / (n_quad - 1)
    return h * (f.sum(-1) - 0.5 * (f[..., 0] + f[..., -1]))


def k_bracket(nu, looks: float, pfa: float):
    """A proven bracket [tau_lo, tau_hi] of the K quantile, eq (6): with g = G / nu, y = S / L
    independent, P(g y > q_g(p) q_y(p)) >= p^2 (both exceed their upper-p quantiles), so
    tau_lo = q_g(sqrt pfa) q_y(sqrt pfa) has tail >= pfa; and P(g y > a b) <= P(g > a) + P(y > b)
    (if g <= a and y <= b then g y <= a b), so tau_hi = q_g(pfa/2) q_y(pfa/2) has tail <= pfa."""
    nu = np.asarray(nu, np.float64)
    qg = lambda p: special.gammainccinv(nu, p) / nu  # noqa: E731
    qy = lambda p: special.gammainccinv(looks, p) / looks  # noqa: E731
    r = math.sqrt(pfa)
    return qg(r) * qy(r), qg(pfa / 2) * qy(pfa / 2)


def k_tau(nu, looks: float, pfa: float, iters: int = 16):
    """tau with P(x > mu tau) = pfa for K intensity, vectorised over nu: regula falsi with the
    Illinois modification on f(z) = ln P(x > mu e^z) - ln pfa (decreasing in z), started on the
    proven bracket (6), which it keeps at every step (so it cannot leave it); 16 steps reach
    float64 accuracy (12 suffice over nu in [0.05, 1e4], L in [0.6, 50], pfa in [1e-15, 0.3];
    checked against bisection and Monte Carlo in tests/pipeline/test_molc.py)."""
    nu = np.atleast_1d(np.asarray(nu, np.float64))
    lo, hi = k_bracket(nu, looks, pfa)
    a, b = np.log(lo), np.log(hi)
    lp = math.log(pfa)
    f = lambda z: np.log(k_sf(np.exp(z), nu, looks)) - lp  # noqa: E731
    fa, fb = f(a), f(b)  # fa >= 0 >= fb (the bracket); the signs of fa, fb stay opposite
    for _ in range(iters):
        d = fb - fa
        ok = d != 0
        c = np.where(ok, b - fb * (b - a) / np.where(ok, d, 1.0), b)
        c = np.clip(c, np.minimum(a, b), np.maximum(a, b))
        fc = f(c)
        flip = fc * fb < 0  # root between b and c: c replaces a's role
        a, fa = np.where(flip, b, a), np.where(flip, fb, 0.5 * fa)
        b, fb = c, fc
    return np.exp(b)


def k_tau_bisect(nu, looks: float, pfa: float, iters: int = 60):
    """Plain bisection on the same bracket (the reference :func:`k_tau` is tested against)."""
    nu = np.atleast_1d(np.asarray(nu, np.float64))
    lo, hi = k_bracket(nu, looks, pfa)
    lo, hi = np.log(lo), np.log(hi)
    for _ in range(iters):
        mid = 0.5 * (lo + hi)
        above = k_sf(np.exp(mid), nu, looks) > pfa
        lo = np.where(above, mid, lo)
        hi = np.where(above, hi, mid)
    return np.exp(0.5 * (lo + hi))


def k_H(u, looks: float, pfa: float):
    """H(u) = ln t - k1 for K (eqs 4, 5): ln tau(nu) - (psi(nu) - ln nu) - (psi(L) - ln L)."""
    u = np.atleast_1d(np.asarray(u, np.float64))
    out = np.full(u.shape, gamma_H(looks, pfa))
    pos = u > trigamma(SHAPE_INF)
    if pos.any():
        nu = inv_trigamma(u[pos])
        out[pos] = (
            np.log(k_tau(nu, looks, pfa))
            - (special.digamma(nu) - np.log(nu))
            - (special.digamma(looks) - math.log(looks))
        )
    return out


def ggd_D(g1, pfa: float):
    """D(g1) of eq (8): the upper-pfa quantile of the standardised ln x of a GGD whose ln x has
    skewness g1 (|g1| < 2); D(0) = z_pfa (lognormal limit)."""
    from scipy import stats  # lazy: importing scipy.stats costs every command start-up time

    g1 = np.atleast_1d(np.asarray(g1, np.float64))
    out = np.full(g1.shape, float(stats.norm.isf(pfa)))
    nz = np.abs(g1) > 1e-7
    if nz.any():
        kap = inv_ggd_skew(g1[nz])
        psi, s = special.digamma(kap), np.sqrt(special.polygamma(1, kap))
        up = (np.log(special.gammainccinv(kap, pfa)) - psi) / s  # v > 0: g1 < 0
        dn = -(np.log(special.gammaincinv(kap, pfa)) - psi) / s  # v < 0: g1 > 0
        out[nz] = np.where(g1[nz] < 0, up, dn)
    return out


def ggd_threshold(sigma, v, kappa, pfa: float):
    """The GGD t with P(x > t) = pfa, closed form through the incomplete-gamma inverses."""
    q = np.where(np.asarray(v) > 0, special.gammainccinv(kappa, pfa), special.gammaincinv(kappa, pfa))
    return sigma * (q / kappa) ** (1.0 / np.asarray(v))


def ggd_sf(t, sigma, v, kappa):
    """P(x > t) for the GGD (the CDF (7) the threshold inverts)."""
    z = kappa * (np.asarray(t) / sigma) ** v
    return np.where(np.asarray(v) > 0, special.gammaincc(kappa, z), special.gammainc(kappa, z))


# --------------------------------------------------------------------------- per-pixel tables


class Table:
    """Values ``f`` of a function on the uniform grid ``x0 + i h`` (i = 0..n), read by
    :func:`interp`. Immutable, hashable by its key."""

    __slots__ = ("key", "x0", "h", "inv_h", "n", "f")

    def __init__(self, key: tuple, x0: float, h: float, f: np.ndarray):
        self.key = key
        self.x0 = float(x0)
        self.h = float(h)
        self.inv_h = 1.0 / float(h)
        self.n = int(f.size - 1)
        self.f = np.ascontiguousarray(f, np.float64)
        self.f.flags.writeable = False

    @property
    def x1(self) -> float:
        return self.x0 + self.n * self.h

    def summary(self) -> dict:
        """JSON-safe description (for run.json): grid and a few values."""
        return {
            "x0": self.x0,
            "x1": self.x1,
            "nodes": self.n + 1,
            "f_first": float(self.f[0]),
            "f_mid": float(self.f[self.n // 2]),
            "f_last": float(self.f[-1]),
        }


def interp(xp, tab_f, x0: float, inv_h: float, n: int, x):
    """Linear interpolation on a uniform grid: ``p = (x - x0) * inv_h``, ``i = clip(floor(p),
    0, n - 1)``, ``f[i] + (p - i) * (f[i + 1] - f[i])`` (the same IEEE operations in NumPy and
    CuPy; ``x`` is expected inside [x0, x0 + n h])."""
    p = (x - x0) * inv_h
    i = xp.clip(xp.floor(p), 0.0, float(n - 1))
    ii = i.astype(xp.int64)
    f0 = tab_f[ii]
    return f0 + (p - i) * (tab_f[ii + 1] - f0)


def u_scale(looks: float) -> float:
    """max(1, 1 / psi_1(L)): the G0 / K table variable is w = ln(1 + u scale); for L >~ 1.5 it is
    the log of one plus the ratio of the texture's log-variance to the speckle's, so that the
    grid resolves the transition at u ~ psi_1(L) ~ 1 / L whatever L (a grid in ln(1 + u) does
    not for L >~ 100); for smaller L, ln(1 + u)."""
    return float(max(1.0, 1.0 / trigamma(looks)))


def w_of_u(xp, u, scale: float):
    """The table variable of G0 / K: w = ln(1 + max(u, 0) scale), scale = :func:`u_scale`."""
    return xp.log1p(xp.maximum(u, 0.0) * scale)


def w_max(looks: float) -> float:
    """The table's upper end: w of u = psi_1(SHAPE_MIN)."""
    return float(np.log1p(trigamma(SHAPE_MIN) * u_scale(looks)))


def u_of_w(w, looks: float):
    return np.expm1(w) / u_scale(looks)


@functools.lru_cache(maxsize=64)
def g0_table(pfa: float, looks: float) -> Table:
    """H of G0 on N_TABLE + 1 nodes of w in [0, w_max(L)] (exact at every node, eq 3)."""
    wm = w_max(looks)
    w = np.linspace(0.0, wm, N_TABLE + 1)
    f = g0_H(u_of_w(w, looks), looks, pfa)
    f[0] = gamma_H(looks, pfa)
    return Table(("g0", pfa, looks), 0.0, wm / N_TABLE, f)


@functools.lru_cache(maxsize=64)
def k_table(pfa: float, looks: float) -> Table:
    """H of K on N_TABLE + 1 nodes of w in [0, w_max(L)]: exact (eqs 5, 6) on N_K_EXACT nodes
    (Chebyshev-Lobatto points, denser at both ends), cubic spline in between."""
    from scipy import interpolate  # lazy: importing scipy.interpolate costs every command start-up time

    wm = w_max(looks)
    j = np.arange(N_K_EXACT)
    we = 0.5 * wm * (1.0 - np.cos(np.pi * j / (N_K_EXACT - 1)))
    fe = k_H(u_of_w(we, looks), looks, pfa)
    fe[0] = gamma_H(looks, pfa)
    w = np.linspace(0.0, wm, N_TABLE + 1)
    f = interpolate.CubicSpline(we, fe)(w)
    return Table(("k", pfa, looks), 0.0, wm / N_TABLE, f)


@functools.lru_cache(maxsize=64)
def ggd_table(pfa: float) -> Table:
    """D of the GGD on N_TABLE_GGD + 1 nodes of g1 in [-G1_MAX, G1_MAX] (exact at every node, eq 8)."""
    g = np.linspace(-G1_MAX, G1_MAX, N_TABLE_GGD + 1)
    g[N_TABLE_GGD // 2] = 0.0
    return Table(("ggd", pfa), -G1_MAX, 2.0 * G1_MAX / N_TABLE_GGD, ggd_D(g, pfa))
