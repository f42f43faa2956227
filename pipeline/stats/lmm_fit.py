r"""Per-ring fit of the ``lmm`` detector: a Gaussian mixture of y = ln x and its tail threshold.

The maths of one cell of the lognormal-mixture CFAR (:mod:`sarship.pipeline.detectors.lmm`),
on weighted points (weights 1: the raw ring samples; weights = counts: the ring histogram's
bin centres), after chapter 3 of SUN Tianyu, *基于 GPU 的极化 SAR 图像舰船检测算法设计* ("Design
of GPU-based ship detection algorithms for polarimetric SAR images"), thesis, Department of
Electronic Engineering, Tsinghua University, 2020 ([sun2020] in ``docs/references.md``):

- :func:`em_fit_points`: EM for a K-component Gaussian mixture of y (the lognormal mixture
  of x, eq 3-1, is a Gaussian mixture of ln x, eq 3-3), updates of eq 3-4, deterministic
  quantile initialisation, collapse guards;
- :func:`mixture_threshold_log`: ``t = ln T`` with ``S(t) = 1 - F(t) = PFA`` (eq 3-5, 3-7),
  safeguarded Newton (eq 3-6, in the log domain) in a guaranteed bracket;
- :func:`mixture_loglik`, :func:`mixture_grad_hess`, :func:`ml_newton`: the likelihood, its
  analytic gradient and Hessian, and the damped-Newton polish of an EM fit to the ML;
- :func:`predictive_shift`: the delta-method predictive correction of the threshold;
- :func:`fit_threshold`: the whole per-ring fit (K' <= K by BIC, ML polish, predictive tail,
  Sheppard correction for binned points), with the refusal of a light tail component foreign
  to the others (a ship's own pixels in the ring: refit with those samples right-censored)
  and the opt-in censored fits (right, two passes; left);
- :func:`censored_loglik`, :func:`censored_grad_hess`: the censored samples' term
  ``n_c ln S(c)`` (or ``n_l ln F(c_l)``) of the likelihood, its gradient and Hessian.

Derivations, the bracket proof, the calibration measurements and the defaults:
``docs/algorithms/lmm.md``. The GPU twin (:mod:`sarship.pipeline.gpu.lmm`) is a line-by-line
CUDA transcription of these functions. All kernels: Numba ``@njit(nogil=True, cache=True)``,
no fastmath, single-threaded. The module is pure (no detector, tiling or GPU imports) and
sits beside :mod:`sarship.pipeline.tiling.boxsum`, the other maths shared by the detectors and
:mod:`sarship.pipeline.gpu`, so that both the detector and its GPU twin can import it
without importing each other.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from scipy import special

__all__ = [
    "censored_grad_hess",
    "censored_loglik",
    "em_fit_points",
    "fit_threshold",
    "init_z_table",
    "mixture_grad_hess",
    "mixture_loglik",
    "mixture_sf_log",
    "mixture_threshold_log",
    "ml_newton",
    "predictive_shift",
]


def init_z_table(K: int) -> np.ndarray:
    """Row K' - 1 holds the EM's initial normal quantiles ``Phi^-1((k + 1/2)/K')``, k < K'."""
    t = np.zeros((K, K))
    for k1 in range(1, K + 1):
        t[k1 - 1, :k1] = special.ndtri((np.arange(k1) + 0.5) / k1)
    return t


# ---------------------------------------------------------------------------------------
# EM on weighted points (weights = 1: raw samples; weights = counts: histogram bins)

_LOG_SQRT_2PI = 0.5 * math.log(2.0 * math.pi)


@njit(nogil=True, cache=True, inline="always")
def _moments(y, wt, n_pts):
    """Total weight W, weighted mean m and variance v (about m) of the points, summed in order."""
    W = 0.0
    m = 0.0
    for j in range(n_pts):
        W += wt[j]
        m += wt[j] * y[j]
    m /= W
    v = 0.0
    for j in range(n_pts):
        d = y[j] - m
        v += wt[j] * d * d
    v /= W
    return W, m, v


@njit(nogil=True, cache=True, inline="always")
def _point_terms(yj, K, mu, ca, inv, live, lt):
    """One point's log-sum-exp over the live components: with ``l_k = ca_k - u_k^2 / 2``,
    ``u_k = (yj - mu_k) inv_k`` (``ca_k = ln a_k - ln s_k``, ``inv_k = 1 / s_k``), returns
    ``(mx, tot)`` with ``mx = max_k l_k`` and ``tot = sum_k exp(l_k - mx)`` and leaves
    ``lt[k] = exp(l_k - mx)`` (so ``ln f(yj) = mx + ln tot - ln sqrt(2 pi)`` and the
    responsibilities are ``lt[k] / tot``)."""
    mx = -np.inf
    for k in range(K):
        if live[k]:
            u = (yj - mu[k]) * inv[k]
            t = ca[k] - 0.5 * u * u
            lt[k] = t
            if t > mx:
                mx = t
    tot = 0.0
    for k in range(K):
        if live[k]:
            e = math.exp(lt[k] - mx)
            lt[k] = e
            tot += e
    return mx, tot


@njit(nogil=True, cache=True, inline="always")
def _component_terms(K, a, s):
    """``ca_k = ln a_k - ln s_k``, ``inv_k = 1 / s_k`` (all a_k > 0), with the work array
    ``lt`` and an all-live mask for :func:`_point_terms`."""
    ca = np.empty(K)
    inv = np.empty(K)
    for k in range(K):
        ca[k] = math.log(a[k]) - math.log(s[k])
        inv[k] = 1.0 / s[k]
    return ca, inv, np.empty(K), np.ones(K, np.bool_)


@njit(nogil=True, cache=True, inline="always")
def _log_q(u):
    """ln Q(u), Q = 1 - Phi, accurate in both tails (asymptotic series beyond u = 30)."""
    if u < 30.0:
        return math.log(0.5 * math.erfc(u * 0.7071067811865476))
    iu2 = 1.0 / (u * u)
    return -0.5 * u * u - math.log(u) - _LOG_SQRT_2PI + math.log(1.0 - iu2 + 3.0 * iu2 * iu2)


@njit(nogil=True, cache=True)
def _censored_estep(c, nc, K, a, mu, s, live, lt, sg, sgd, sgdd, sgn=1.0):
    """E-step of the censored weight nc into the shifted sums; returns nc ln P(censored).
    ``sgn = 1``: right-censored (y > c), P = S(c); ``sgn = -1``: left-censored (y < c),
    P = F(c), the mirror image (y -> -y: ``al_k = sgn (c - mu_k)/s_k``, the mean moment
    changes sign)."""
    mx = -np.inf
    for k in range(K):
        if live[k]:
            lt[k] = math.log(a[k]) + _log_q(sgn * (c - mu[k]) / s[k])
            mx = max(mx, lt[k])
    tot = 0.0
    for k in range(K):
        if live[k]:
            lt[k] = math.exp(lt[k] - mx)
            tot += lt[k]
    for k in range(K):
        if live[k]:
            al = sgn * (c - mu[k]) / s[k]
            lam = math.exp(-0.5 * al * al - _LOG_SQRT_2PI - _log_q(al))  # phi / Q
            g = nc * lt[k] / tot
            sg[k] += g
            sgd[k] += g * sgn * s[k] * lam
            sgdd[k] += g * s[k] * s[k] * (1.0 + al * lam)
    return nc * (mx + math.log(tot))


@njit(nogil=True, cache=True)
def em_fit_points(y, wt, n_pts, K, init_z, max_iter, tol, a, mu, s, c=np.inf, nc=0.0, cl=-np.inf, nl=0.0):
    """EM (eq 3-4) on weighted points; returns the iteration count (docs/algorithms/lmm.md, "EM").

    Each iteration: E-step with the current parameters (responsibilities g_jk, log-sum-exp
    relative to the largest term), accumulating sum g, sum g y, sum g y^2 per component;
    M-step mu = sum g y / sum g, s^2 = sum g y^2 / sum g - mu^2 computed about the
    *previous* mean (shifted sums, no cancellation), a = sum g / W. Stops when the mean
    log-likelihood (of the parameters entering the iteration) changes by < tol.

    Right-censored weight ``nc > 0`` (samples known only to exceed ``c``; docs/algorithms/lmm.md,
    "Contamination and quantisation"): the E-step of a censored sample (Dempster, Laird & Rubin 1977, sec
    4.2; Lee & Scott 2012) gives component k the responsibility ``a_k Q(al_k) / S(c)``,
    ``al_k = (c - mu_k)/s_k``, and the truncated-normal moments
    ``E[y - mu_k | y > c] = s_k lam_k``, ``E[(y - mu_k)^2 | y > c] = s_k^2 (1 + al_k lam_k)``
    (``lam = phi/Q``, the inverse Mills ratio); W includes nc and the log-likelihood gains
    ``nc ln S(c)``. Left-censored weight ``nl > 0`` (samples known only to lie below ``cl``):
    the mirror image, ``a_k F_k(cl) / F(cl)``, ``E[y - mu_k | y < cl] = -s_k lam_k`` with
    ``al_k = (mu_k - cl)/s_k``. ``nc = nl = 0``: the uncensored EM, bit for bit.
    """
    W, m, v = _moments(y, wt, n_pts)
    Wp = W
    W = Wp + nc + nl
    floor = 1e-4 * v + 1e-12
    sd = math.sqrt(v)
    mz2 = 0.0
    for k in range(K):
        mz2 += init_z[k] * init_z[k]
    mz2 /= K
    s0 = sd * math.sqrt(max(1.0 - mz2, 1e-4))
    if s0 * s0 < floor:
        s0 = math.sqrt(floor)
    for k in range(K):
        a[k] = 1.0 / K
        mu[k] = m + sd * init_z[k]
        s[k] = s0
    lt = np.empty(K)
    sg = np.empty(K)
    sgd = np.empty(K)
    sgdd = np.empty(K)
    ca = np.empty(K)
    inv = np.empty(K)
    live = np.ones(K, np.bool_)
    prev = -np.inf
    it = 0
    while it < max_iter:
        it += 1
        for k in range(K):
            sg[k] = 0.0
            sgd[k] = 0.0
            sgdd[k] = 0.0
            if live[k]:
                ca[k] = math.log(a[k]) - math.log(s[k])
                inv[k] = 1.0 / s[k]
        ll = 0.0
        for j in range(n_pts):
            yj = y[j]
            mx, tot = _point_terms(yj, K, mu, ca, inv, live, lt)
            wj = wt[j]
            ll += wj * (mx + math.log(tot))
            r = wj / tot
            for k in range(K):
                if live[k]:
                    g = lt[k] * r
                    d = yj - mu[k]
                    sg[k] += g
                    sgd[k] += g * d
                    sgdd[k] += g * d * d
        ll = ll / Wp - _LOG_SQRT_2PI
        if nc > 0.0 or nl > 0.0:
            ll = ll * Wp
            if nc > 0.0:
                ll += _censored_estep(c, nc, K, a, mu, s, live, lt, sg, sgd, sgdd)
            if nl > 0.0:
                ll += _censored_estep(cl, nl, K, a, mu, s, live, lt, sg, sgd, sgdd, -1.0)
            ll = ll / W
        for k in range(K):
            if live[k]:
                if sg[k] < 1e-9 * W:
                    live[k] = False
                    a[k] = 0.0
                    continue
                dm = sgd[k] / sg[k]
                var = sgdd[k] / sg[k] - dm * dm
                mu[k] = mu[k] + dm
                if var < floor:
                    var = floor
                s[k] = math.sqrt(var)
                a[k] = sg[k] / W
        ch = ll - prev
        prev = ll
        if -tol < ch < tol:
            break
    # normalise the weights (they sum to 1 up to rounding)
    tot = 0.0
    for k in range(K):
        tot += a[k]
    for k in range(K):
        a[k] = a[k] / tot
    return it


# ---------------------------------------------------------------------------------------
# threshold


@njit(nogil=True, cache=True)
def _sf_and_pdf(t, a, mu, s, K):
    """S(t) = sum a Q((t-mu)/s) and its density f(t) = sum a phi((t-mu)/s)/s (log domain)."""
    S = 0.0
    f = 0.0
    for k in range(K):
        if a[k] > 0.0:
            u = (t - mu[k]) / s[k]
            S += a[k] * 0.5 * math.erfc(u * 0.7071067811865476)
            f += a[k] * math.exp(-0.5 * u * u) / (s[k] * 2.5066282746310002)
    return S, f


@njit(nogil=True, cache=True)
def mixture_sf_log(t, a, mu, s):
    """ln S(t) for the mixture (a, mu, s): the log of the exceedance probability of ln x > t."""
    S, f = _sf_and_pdf(t, a, mu, s, a.shape[0])
    return math.log(S) if S > 0.0 else -np.inf


@njit(nogil=True, cache=True)
def mixture_threshold_log(a, mu, s, K, z, log_pfa):
    """t = ln T with S(t) = PFA: Newton on ln S - ln PFA safeguarded by bisection.

    Bracket [min_i(mu_i + s_i z), max_i(mu_i + s_i z)] (proof: docs/algorithms/lmm.md, "Threshold").
    """
    lo = np.inf
    hi = -np.inf
    for k in range(K):
        if a[k] > 0.0:
            q = mu[k] + s[k] * z
            if q < lo:
                lo = q
            if q > hi:
                hi = q
    if not (hi > lo):
        return lo
    t = 0.5 * (lo + hi)
    for _ in range(100):
        S, f = _sf_and_pdf(t, a, mu, s, K)
        if S <= 0.0:  # far beyond every component: t is above the root
            hi = t
            t = 0.5 * (lo + hi)
            continue
        g = math.log(S) - log_pfa
        if g > 0.0:
            lo = t
        elif g < 0.0:
            hi = t
        else:
            return t
        if f > 0.0:
            tn = t + g * S / f  # Newton: g' = -f/S
        else:
            tn = 0.5 * (lo + hi)
        if not (lo < tn < hi):
            tn = 0.5 * (lo + hi)
        step = abs(tn - t)
        t = tn
        if step <= 1e-10 * (1.0 + abs(t)) or (hi - lo) <= 1e-10 * (1.0 + abs(t)):
            break
    return t


# ---------------------------------------------------------------------------------------
# ML polish, choice of K and the predictive tail (docs/algorithms/lmm.md, "Calibration")


@njit(nogil=True, cache=True)
def mixture_loglik(y, wt, n_pts, K, a, mu, s):
    """sum_j wt_j ln f(y_j) for the Gaussian mixture (a, mu, s) of K components, a_k > 0."""
    ca, inv, lt, live = _component_terms(K, a, s)
    ll = 0.0
    W = 0.0
    for j in range(n_pts):
        mx, tot = _point_terms(y[j], K, mu, ca, inv, live, lt)
        ll += wt[j] * (mx + math.log(tot))
        W += wt[j]
    return ll - W * _LOG_SQRT_2PI


@njit(nogil=True, cache=True)
def mixture_grad_hess(y, wt, n_pts, K, a, mu, s, G, H):
    """Log-likelihood with its gradient ``G`` and Hessian ``H`` (filled in) in the
    unconstrained parameters theta = (eta_0..eta_{K-2}, mu_0..mu_{K-1}, lambda_0..lambda_{K-1}),
    ``a = softmax(eta_0, .., eta_{K-2}, 0)``, ``s = exp(lambda)``: p = 3K - 1 of them.

    Per point, ``ln f = logsumexp_k l_k`` with ``l_k = ln a_k - lambda_k - u_k^2/2 - ln sqrt(2 pi)``,
    ``u_k = (y - mu_k)/s_k``. With the responsibilities ``g_k`` and the scores ``d_k = grad l_k``
    (``d eta_m = [k == m] - a_m``, ``d mu_k = u_k/s_k``, ``d lambda_k = u_k^2 - 1``):
    ``grad ln f = sum_k g_k d_k`` and
    ``Hess ln f = sum_k g_k (Hess l_k + d_k d_k^T) - grad grad^T``, where ``Hess l_k`` is
    ``-(diag a - a a^T)`` on the etas and ``[[-1/s_k^2, -2 u_k/s_k], [., -2 u_k^2]]`` on
    ``(mu_k, lambda_k)``.
    """
    p = 3 * K - 1
    for q in range(p):
        G[q] = 0.0
        for r in range(p):
            H[q, r] = 0.0
    ca, inv, lt, live = _component_terms(K, a, s)
    Gj = np.empty(p)
    ll = 0.0
    W = 0.0
    for j in range(n_pts):
        w = wt[j]
        W += w
        yj = y[j]
        mx, tot = _point_terms(yj, K, mu, ca, inv, live, lt)
        ll += w * (mx + math.log(tot))
        rt = 1.0 / tot
        for q in range(p):
            Gj[q] = 0.0
        # upper triangle (q <= r) of sum_k g_k (Hess l_k + d_k d_k^T), then grad
        for k in range(K):
            g = lt[k] * rt
            wg = w * g
            u = (yj - mu[k]) * inv[k]
            dmu = u * inv[k]
            dla = u * u - 1.0
            im = K - 1 + k
            il = 2 * K - 1 + k
            for m in range(K - 1):
                dm = (1.0 if m == k else 0.0) - a[m]
                Gj[m] += g * dm
                c = wg * dm
                for m2 in range(m, K - 1):
                    H[m, m2] += c * ((1.0 if m2 == k else 0.0) - a[m2])
                H[m, im] += c * dmu
                H[m, il] += c * dla
            Gj[im] += g * dmu
            Gj[il] += g * dla
            H[im, im] += wg * (dmu * dmu - inv[k] * inv[k])
            H[im, il] += wg * (dmu * dla - 2.0 * dmu)
            H[il, il] += wg * (dla * dla - 2.0 * u * u)
        for q in range(p):
            c = w * Gj[q]
            G[q] += c
            for r in range(q, p):
                H[q, r] -= c * Gj[r]
    for m in range(K - 1):
        for m2 in range(m, K - 1):
            H[m, m2] -= W * ((a[m] if m == m2 else 0.0) - a[m] * a[m2])
    for q in range(p):
        for r in range(q):
            H[q, r] = H[r, q]
    return ll - W * _LOG_SQRT_2PI


@njit(nogil=True, cache=True)
def censored_loglik(K, a, mu, s, c, nc, sgn=1.0):
    """The censored samples' term ``nc ln S(c)`` of the log-likelihood (0 if nc = 0);
    ``sgn = -1``: left-censored, ``nc ln F(c)``."""
    if not (nc > 0.0):
        return 0.0
    mx = -np.inf
    lq = np.empty(K)
    for k in range(K):
        lq[k] = math.log(a[k]) + _log_q(sgn * (c - mu[k]) / s[k])
        mx = max(mx, lq[k])
    tot = 0.0
    for k in range(K):
        tot += math.exp(lq[k] - mx)
    return nc * (mx + math.log(tot))


@njit(nogil=True, cache=True)
def censored_grad_hess(K, a, mu, s, c, nc, G, H, sgn=1.0):
    """Adds the gradient and Hessian (in theta, as :func:`mixture_grad_hess`) of the censored
    term ``nc ln S(c)``, ``S = sum_k a_k Q(u_k)``, ``u_k = (c - mu_k)/s_k``, to ``G`` and ``H``
    (all of H, both triangles); returns the term. With ``phi_k = phi(u_k)``:
    ``dS/d eta_m = a_m (Q_m - S)``, ``dS/d mu_k = a_k phi_k / s_k``, ``dS/d lambda_k = a_k phi_k u_k``;
    ``d2S/d eta_m d eta_n = a_m ([m = n] - a_n)(Q_m - S) - a_m a_n (Q_n - S)``,
    ``d2S/d eta_m d mu_k = a_m ([m = k] - a_k) phi_k / s_k`` (lambda_k: ``... phi_k u_k``),
    ``d2S/d mu_k^2 = a_k u_k phi_k / s_k^2``, ``d2S/d mu_k d lambda_k = a_k phi_k (u_k^2 - 1) / s_k``,
    ``d2S/d lambda_k^2 = a_k phi_k u_k (u_k^2 - 1)``; then
    ``Hess ln S = Hess S / S - grad S grad S^T / S^2``. S, Q and phi are scaled by exp(-max_k
    ln(a_k Q_k)) (ratios only), so the far tail does not underflow.
    ``sgn = -1``: the left-censored term ``nc ln F(c)``, the mirror image y -> -y
    (``u_k = (mu_k - c)/s_k``; the derivatives in mu_k change sign, ``d/d mu_k = -d/d mu'_k``)."""
    if not (nc > 0.0):
        return 0.0
    p = 3 * K - 1
    lq = np.empty(K)
    mx = -np.inf
    for k in range(K):
        lq[k] = math.log(a[k]) + _log_q(sgn * (c - mu[k]) / s[k])
        mx = max(mx, lq[k])
    Q = np.empty(K)  # Q_k / scale
    ph = np.empty(K)  # phi_k / scale
    u = np.empty(K)
    S = 0.0
    for k in range(K):
        u[k] = sgn * (c - mu[k]) / s[k]
        Q[k] = math.exp(lq[k] - mx) / a[k]
        ph[k] = math.exp(-0.5 * u[k] * u[k] - _LOG_SQRT_2PI - mx)
        S += a[k] * Q[k]
    dS = np.zeros(p)
    HS = np.zeros((p, p))
    for k in range(K):
        im = K - 1 + k
        il = 2 * K - 1 + k
        if k < K - 1:
            dS[k] = a[k] * (Q[k] - S)
        dS[im] = a[k] * ph[k] / s[k]
        dS[il] = a[k] * ph[k] * u[k]
        HS[im, im] = a[k] * u[k] * ph[k] / (s[k] * s[k])
        HS[im, il] = a[k] * ph[k] * (u[k] * u[k] - 1.0) / s[k]
        HS[il, im] = HS[im, il]
        HS[il, il] = a[k] * ph[k] * u[k] * (u[k] * u[k] - 1.0)
        for m in range(K - 1):
            dk = (1.0 if m == k else 0.0) - a[k]
            HS[m, im] = a[m] * dk * ph[k] / s[k]
            HS[im, m] = HS[m, im]
            HS[m, il] = a[m] * dk * ph[k] * u[k]
            HS[il, m] = HS[m, il]
    for m in range(K - 1):
        for n in range(K - 1):
            HS[m, n] = a[m] * ((1.0 if m == n else 0.0) - a[n]) * (Q[m] - S) - a[m] * a[n] * (Q[n] - S)
    if sgn < 0.0:  # mirror: the mu coordinates change sign
        for k in range(K):
            im = K - 1 + k
            dS[im] = -dS[im]
            for q in range(p):
                if not (K - 1 <= q < 2 * K - 1):
                    HS[q, im] = -HS[q, im]
                    HS[im, q] = -HS[im, q]
    for q in range(p):
        G[q] += nc * dS[q] / S
        for r in range(p):
            H[q, r] += nc * (HS[q, r] / S - dS[q] * dS[r] / (S * S))
    return nc * (mx + math.log(S))


@njit(nogil=True, cache=True)
def _chol_solve(A, b, p, x, L):
    """x = A^-1 b for symmetric positive definite A (p x p) by Cholesky (L: work).
    Returns False, leaving x undefined, if A is not numerically positive definite."""
    for i in range(p):
        for j in range(i + 1):
            acc = A[i, j]
            for k in range(j):
                acc -= L[i, k] * L[j, k]
            if i == j:
                if not (acc > 1e-14 * abs(A[i, i])):
                    return False
                L[i, i] = math.sqrt(acc)
            else:
                L[i, j] = acc / L[j, j]
    for i in range(p):
        acc = b[i]
        for k in range(i):
            acc -= L[i, k] * x[k]
        x[i] = acc / L[i, i]
    for i in range(p - 1, -1, -1):
        acc = x[i]
        for k in range(i + 1, p):
            acc -= L[k, i] * x[k]
        x[i] = acc / L[i, i]
    return True


@njit(nogil=True, cache=True)
def _from_theta(K, th, a, mu, s):
    """(a, mu, s) from theta; False if a weight or scale under/overflows."""
    mx = 0.0
    for k in range(K - 1):
        if th[k] > mx:
            mx = th[k]
    tot = math.exp(-mx)
    for k in range(K - 1):
        tot += math.exp(th[k] - mx)
    for k in range(K - 1):
        a[k] = math.exp(th[k] - mx) / tot
    a[K - 1] = math.exp(-mx) / tot
    ok = True
    for k in range(K):
        mu[k] = th[K - 1 + k]
        lam = th[2 * K - 1 + k]
        if not (-300.0 < lam < 300.0) or not (a[k] > 1e-300) or mu[k] != mu[k]:
            ok = False
        else:
            s[k] = math.exp(lam)
    return ok


@njit(nogil=True, cache=True)
def ml_newton(y, wt, n_pts, K, a, mu, s, A, max_steps, c=np.inf, nc=0.0, cl=-np.inf, nl=0.0):
    """Maximum likelihood from the start (a, mu, s) (all a_k > 0): damped Newton
    (Levenberg-Marquardt) on theta (see :func:`mixture_grad_hess`). A step is the Newton
    step when the observed information ``A = -Hess`` is positive definite, else (or if it
    does not increase the likelihood) a damped one, ``(A + lam diag|A|) d = grad``, lam
    x10 until it does. Converged when the Newton decrement ``grad^T A^-1 grad`` (~ twice
    the log-likelihood still to gain) is below 1e-12. (a, mu, s) are updated in place and
    ``A`` (p x p) holds the observed information at them. Returns (steps, converged,
    log-likelihood). ``nc > 0``: the censored likelihood, plus ``nc ln S(c)``
    (:func:`censored_grad_hess`); ``nl > 0``: plus the left-censored ``nl ln F(cl)``."""
    p = 3 * K - 1
    th = np.empty(p)
    for k in range(K - 1):
        th[k] = math.log(a[k]) - math.log(a[K - 1])
    for k in range(K):
        th[K - 1 + k] = mu[k]
        th[2 * K - 1 + k] = math.log(s[k])
    G = np.empty(p)
    H = np.empty((p, p))
    M = np.empty((p, p))
    L = np.empty((p, p))
    d = np.empty(p)
    tn = np.empty(p)
    at = np.empty(K)
    mt = np.empty(K)
    st = np.empty(K)
    lam = 0.0
    steps = 0
    ok = False
    ll = mixture_grad_hess(y, wt, n_pts, K, a, mu, s, G, H)
    if nc > 0.0:
        ll += censored_grad_hess(K, a, mu, s, c, nc, G, H)
    if nl > 0.0:
        ll += censored_grad_hess(K, a, mu, s, cl, nl, G, H, -1.0)
    while True:
        for q in range(p):
            for r in range(p):
                A[q, r] = -H[q, r]
        pd = _chol_solve(A, G, p, d, L)
        if pd:
            dec = 0.0
            for q in range(p):
                dec += G[q] * d[q]
            if dec < 1e-12:
                ok = True
                break
        if steps >= max_steps:
            break
        steps += 1
        accepted = False
        for _ in range(12):
            if lam > 0.0 or not pd:
                if lam == 0.0:
                    lam = 1e-4
                for q in range(p):
                    for r in range(p):
                        M[q, r] = A[q, r]
                    M[q, q] = A[q, q] + lam * (abs(A[q, q]) + 1e-300)
                if not _chol_solve(M, G, p, d, L):
                    lam *= 10.0
                    continue
            for q in range(p):
                tn[q] = th[q] + d[q]
            lln = -np.inf
            if _from_theta(K, tn, at, mt, st):
                lln = mixture_loglik(y, wt, n_pts, K, at, mt, st)
                if nc > 0.0:
                    lln += censored_loglik(K, at, mt, st, c, nc)
                if nl > 0.0:
                    lln += censored_loglik(K, at, mt, st, cl, nl, -1.0)
            if lln >= ll - 1e-13 * abs(ll):
                accepted = True
                break
            lam = 1e-4 if lam == 0.0 else lam * 10.0
        if not accepted:
            break
        for q in range(p):
            th[q] = tn[q]
        _from_theta(K, th, a, mu, s)
        lam = lam * 0.01 if lam > 1e-8 else 0.0
        ll = mixture_grad_hess(y, wt, n_pts, K, a, mu, s, G, H)
        if nc > 0.0:
            ll += censored_grad_hess(K, a, mu, s, c, nc, G, H)
        if nl > 0.0:
            ll += censored_grad_hess(K, a, mu, s, cl, nl, G, H, -1.0)
    return steps, ok, ll


@njit(nogil=True, cache=True)
def predictive_shift(t, K, a, mu, s, jac, A):
    """The predictive correction ``0.5 q / (f S)`` of the plug-in threshold ``t`` (nepers),
    ``q = dS^T A^-1 dS``: ``dS`` the gradient of ``S(t) = sum a_k Q((t - mu_k)/s_k)`` in theta
    (``dS/d eta_m = a_m (Q_m - S)``, ``dS/d mu_k = a_k phi(u_k)/s_k``,
    ``dS/d lambda_k = a_k phi(u_k) u_k jac_k``, jac: d lambda / d lambda_fitted, the Sheppard
    correction's), ``A`` the observed information, ``f`` the log-domain density at t.
    ``q / f^2`` is the delta-method variance of the fitted threshold. NaN when A is not
    positive definite or the tail is degenerate."""
    p = 3 * K - 1
    S, f = _sf_and_pdf(t, a, mu, s, K)
    if not (S > 0.0 and f > 0.0):
        return np.nan
    dS = np.empty(p)
    for k in range(K):
        u = (t - mu[k]) / s[k]
        ph = math.exp(-0.5 * u * u) / 2.5066282746310002
        if k < K - 1:
            dS[k] = a[k] * (0.5 * math.erfc(u * 0.7071067811865476) - S)
        dS[K - 1 + k] = a[k] * ph / s[k]
        dS[2 * K - 1 + k] = a[k] * ph * u * jac[k]
    x = np.empty(p)
    L = np.empty((p, p))
    if not _chol_solve(A, dS, p, x, L):
        return np.nan
    q = 0.0
    for r in range(p):
        q += dS[r] * x[r]
    sh = 0.5 * q / (f * S)
    if not (sh >= 0.0 and sh < np.inf):
        return np.nan
    return sh


@njit(nogil=True, cache=True)
def _observed(K, mu, cl, cy):
    """Every component's mean lies below the right-censoring point, ``mu_k < cy`` (a
    component centred among the censored points is known only by its mass there: not
    identified). Always true without right-censoring."""
    for k in range(K):
        if not (mu[k] < cy):
            return False
    return True


@njit(nogil=True, cache=True)
def _resolved(K, s, res):
    for k in range(K):
        if not (s[k] * s[k] > res):
            return False
    return True


# argument lists laid out by hand, kept from the formatter
# fmt: off
@njit(nogil=True, cache=True)
def fit_threshold(y, wt, n_pts, K, init_zs, max_iter, tol, shep, select, predictive, z, log_pfa,
                  a, mu, s, cens=0.0, cens_q=0.0, lcens=0.0, refuse=0.0):
    """The threshold t = ln T for one ring (weighted points y, wt); returns (t, work, K').

    1. EM (:func:`em_fit_points`) for K' = 1..K (``select``), or K' = K only; components
       frozen at weight 0 are dropped; the candidates are ordered by their BIC
       ``-2 ln L + (3K' - 1) ln n`` (n = sum wt, L at the EM's stopping point).
    2. ``predictive``: in BIC order, a candidate whose components are all resolved
       (variance above the EM's floor, 1e-4 of the sample variance, and for a histogram
       above h^2/9 = 4/3 shep) is polished to the ML by :func:`ml_newton` (<= 30 steps);
       the first that converges, stays resolved and has a finite predictive shift is used:
       ``t = t_plug + shift`` (``t_plug``: 1 - F = PFA for the ML mixture after the
       Sheppard correction ``s^2 - shep``, floored at s^2/4; shift:
       :func:`predictive_shift`). If none qualifies (degenerate rings: constant or
       quantised data), the plug-in threshold of the best-BIC EM fit.
       Not ``predictive``: the plug-in threshold of the best-BIC EM fit (``select=False``
       too: the thesis' EM + eq 3-5, the earlier behaviour bit for bit).
    ``init_zs[K' - 1, :K']``: the initial normal quantiles per K'. (a, mu, s) receive the
    chosen fit (first K' entries). ``work``: EM iterations (all K') + Newton steps.

    Censoring (``y`` must then be in ascending order; docs/algorithms/lmm.md, "Censored ring
    fit"): every fit uses the censored likelihood
    ``sum_kept wt ln f(y) + n_c ln S(c) + n_l ln F(c_l)`` (EM, BIC, ML, information,
    predictive shift; type-I censoring, Cohen 1959; EM: Dempster, Laird & Rubin 1977 sec 4.2).

    - ``lcens > 0``: the darkest points, at most ``floor(lcens * n)`` of the weight and never
      part of a run of equal values, are left-censored at ``c_l`` = the lowest kept point
      (- half a bin, ``sqrt(3 shep)``, for a histogram).
    - ``cens > 0``: right-censoring in two passes. Pass 1: the brightest points, at most
      ``floor(cens * n)`` of the weight, censored at ``c1`` = the largest kept point (+ half
      a bin); the censored fit gives the clutter level ``c2`` with ``S(c2) = q``
      (``q = cens_q``, or 1/n if 0; predictive, like the threshold). Pass 2: only the points
      above ``max(c2, c1)`` are censored; threshold ``S(t) = PFA``.
    - ``refuse > 0``: a fit whose brightest component (largest mu) has weight <= ``refuse``
      and lies beyond the other components' own tail (their mixture's exceedance at its mean
      below 1/n) is refused as contamination: the points above ``c2``, the other
      components' 1 - 1/n level, are right-censored and the ring fitted again.

    ``cens = lcens = refuse = 0``: bit for bit the uncensored fit.
    """
    if not (cens > 0.0 or lcens > 0.0 or refuse > 0.0):
        return _fit_core(y, wt, n_pts, K, init_zs, max_iter, tol, shep, select, predictive, z, log_pfa, a, mu, s,
                         np.inf, 0.0)
    hb = math.sqrt(3.0 * shep)  # half a bin (0 for raw samples)
    Wall = 0.0
    for j in range(n_pts):
        Wall += wt[j]
    # left censoring: the darkest points, at most floor(lcens W) of the weight
    nl = 0.0
    j0 = 0
    cl = -np.inf
    if lcens > 0.0:
        lim = math.floor(lcens * Wall)
        while j0 < n_pts - 1 and nl + wt[j0] <= lim:
            nl += wt[j0]
            j0 += 1
        while j0 > 0 and not (y[j0] > y[j0 - 1]):  # keep runs of ties whole
            j0 -= 1
            nl -= wt[j0]
        if nl > 0.0:
            cl = y[j0] - hb
    ys = y[j0:]
    ws = wt[j0:]
    npk = n_pts - j0
    work = 0
    if cens > 0.0:
        # pass 1: the brightest points, at most floor(cens W) of the weight, censored
        nc = 0.0
        lim = math.floor(cens * Wall)
        j = npk - 1
        while j > 0 and nc + ws[j] <= lim:
            nc += ws[j]
            j -= 1
        n1 = j + 1
        while n1 < npk and not (ys[n1] > ys[n1 - 1]):  # keep runs of ties whole
            nc -= ws[n1]
            n1 += 1
        if nc > 0.0:
            q = cens_q if cens_q > 0.0 else 1.0 / Wall
            c2, work, _ = _fit_core(ys, ws, n1, K, init_zs, max_iter, tol, shep, select, predictive,
                                    _z_of(q), math.log(q), a, mu, s, ys[n1 - 1] + hb, nc, cl, nl)
            t, w2, m = _fit_right(ys, ws, npk, n1, c2, hb, K, init_zs, max_iter, tol, shep, select, predictive,
                                  z, log_pfa, a, mu, s, cl, nl)
        else:
            t, w2, m = _fit_core(ys, ws, npk, K, init_zs, max_iter, tol, shep, select, predictive, z, log_pfa,
                                 a, mu, s, np.inf, 0.0, cl, nl)
        work += w2
    else:
        t, work, m = _fit_core(ys, ws, npk, K, init_zs, max_iter, tol, shep, select, predictive, z, log_pfa,
                               a, mu, s, np.inf, 0.0, cl, nl)
    cprev = np.inf
    for _ in range(3 if refuse > 0.0 else 0):
        if m < 2:
            break
        c2 = _refused_level(m, a, mu, s, t, refuse, 1.0 / Wall, z)
        if not (c2 < cprev):
            break
        cprev = c2
        t2, w2, m2 = _fit_right(ys, ws, npk, 0, c2, hb, K, init_zs, max_iter, tol, shep, select, predictive,
                                z, log_pfa, a, mu, s, cl, nl)
        work += w2
        if not (t2 == t2):
            break
        t = t2
        m = m2
    return t, work, m
# fmt: on


@njit(nogil=True, cache=True)
def _fit_right(
    ys, ws, npk, n1, c2, hb, K, init_zs, max_iter, tol, shep, select, predictive, z, log_pfa, a, mu, s, cl, nl
):
    """The fit with the points above ``c2`` (but none of the first ``n1``) right-censored."""
    n2 = npk
    while n2 > n1 and ys[n2 - 1] > c2:
        n2 -= 1
    nc = 0.0
    for j in range(n2, npk):
        nc += ws[j]
    if not (nc > 0.0) or n2 < 1:
        return _fit_core(
            ys, ws, npk, K, init_zs, max_iter, tol, shep, select, predictive, z, log_pfa, a, mu, s, np.inf, 0.0, cl, nl
        )
    return _fit_core(
        ys,
        ws,
        n2,
        K,
        init_zs,
        max_iter,
        tol,
        shep,
        select,
        predictive,
        z,
        log_pfa,
        a,
        mu,
        s,
        ys[n2 - 1] + hb,
        nc,
        cl,
        nl,
    )


#: Phi^-1(1 - 1e-5): a refused component's mean lies beyond the others' threshold at PFA 1e-5 at least.
_Z_FAR = 4.264890793922825


@njit(nogil=True, cache=True)
def _refused_level(m, a, mu, s, t, wmax, q, z):
    """If the component that dominates the tail at t (largest a_k Q((t - mu_k)/s_k)) weighs
    <= wmax and is foreign to the others, i.e. its mean lies beyond their own threshold
    (their renormalised mixture's S = Q(max(z, Z_FAR))) or its spread is at least twice
    the largest of theirs, the others' level c with S_rest(c) = q; else NaN."""
    kt = 0
    best = -np.inf
    for k in range(m):
        v = math.log(a[k]) + _log_q((t - mu[k]) / s[k])
        if v > best:
            best = v
            kt = k
    if not (a[kt] <= wmax):
        return np.nan
    ra = np.empty(m - 1)
    rm = np.empty(m - 1)
    rs = np.empty(m - 1)
    r = 0
    for k in range(m):
        if k != kt:
            ra[r] = a[k] / (1.0 - a[kt])
            rm[r] = mu[k]
            rs[r] = s[k]
            r += 1
    zf = z if z > _Z_FAR else _Z_FAR
    far = mu[kt] > mixture_threshold_log(ra, rm, rs, m - 1, zf, _log_q(zf))
    wide = True
    for r in range(m - 1):
        if not (s[kt] >= 2.0 * rs[r]):
            wide = False
    if not (far or wide):
        return np.nan
    return mixture_threshold_log(ra, rm, rs, m - 1, _z_of(q), math.log(q))


@njit(nogil=True, cache=True)
def _z_of(q):
    """Phi^-1(1 - q) for 0 < q < 1/2: Newton on ln Q(z) = ln q (convex, from above: monotone)."""
    lq = math.log(q)
    z = math.sqrt(-2.0 * lq)  # above the root (Q(z) < exp(-z^2/2))
    for _ in range(60):
        g = _log_q(z) - lq
        # d ln Q / dz = -phi/Q
        d = -math.exp(-0.5 * z * z - _LOG_SQRT_2PI - _log_q(z))
        zn = z - g / d
        if abs(zn - z) <= 1e-13 * (1.0 + abs(z)):
            return zn
        z = zn
    return z


@njit(nogil=True, cache=True)
def _fit_core(
    y, wt, n_pts, K, init_zs, max_iter, tol, shep, select, predictive, z, log_pfa, a, mu, s, cy, nc, cl=-np.inf, nl=0.0
):
    """:func:`fit_threshold` on the first ``n_pts`` points, weight ``nc`` right-censored at ``cy``."""
    Ka = np.zeros(K, np.int64)
    ca = np.zeros((K, K))
    cm = np.zeros((K, K))
    cs = np.ones((K, K))
    bic = np.full(K, np.inf)
    ta = np.empty(K)
    tm = np.empty(K)
    ts = np.empty(K)
    W, _, vy = _moments(y, wt, n_pts)
    # smallest resolvable component variance: the EM's floor (1e-4 of the sample variance),
    # and for a histogram (shep = h^2/12 > 0) h^2/9, below which the Sheppard correction
    # is floored too (a component narrower than about a bin is not resolved by the counts)
    res = 1.0001e-4 * vy + 1e-12
    if 4.0 / 3.0 * shep > res:
        res = 4.0 / 3.0 * shep
    lnW = math.log(W + nc + nl)
    work = 0
    k0 = 1 if select else K
    for Kc in range(k0, K + 1):
        work += em_fit_points(y, wt, n_pts, Kc, init_zs[Kc - 1, :Kc], max_iter, tol, ta, tm, ts, cy, nc, cl, nl)
        m = 0
        for k in range(Kc):
            if ta[k] > 0.0:
                ca[Kc - 1, m] = ta[k]
                cm[Kc - 1, m] = tm[k]
                cs[Kc - 1, m] = ts[k]
                m += 1
        Ka[Kc - 1] = m
        ll = mixture_loglik(y, wt, n_pts, m, ca[Kc - 1], cm[Kc - 1], cs[Kc - 1])
        if nc > 0.0:
            ll += censored_loglik(m, ca[Kc - 1], cm[Kc - 1], cs[Kc - 1], cy, nc)
        if nl > 0.0:
            ll += censored_loglik(m, ca[Kc - 1], cm[Kc - 1], cs[Kc - 1], cl, nl, -1.0)
        bic[Kc - 1] = -2.0 * ll + (3 * m - 1) * lnW
    order = np.argsort(bic, kind="mergesort")  # stable: on a tie the smaller K' first
    jac = np.empty(K)
    if predictive:
        for oi in range(K - k0 + 1):
            c = order[oi]
            m = Ka[c]
            for k in range(m):
                a[k] = ca[c, k]
                mu[k] = cm[c, k]
                s[k] = cs[c, k]
            if not (_resolved(m, s, res) and _observed(m, mu, cl, cy)):
                continue
            A = np.empty((3 * m - 1, 3 * m - 1))
            st, ok, _ = ml_newton(y, wt, n_pts, m, a, mu, s, A, 30, cy, nc, cl, nl)
            work += st
            if not (ok and _resolved(m, s, res) and _observed(m, mu, cl, cy)):
                continue
            for k in range(m):
                v = s[k] * s[k]
                q = v - shep
                q = q if q > 0.25 * v else 0.25 * v
                jac[k] = v / q
                s[k] = math.sqrt(q)
            t = mixture_threshold_log(a, mu, s, m, z, log_pfa)
            sh = predictive_shift(t, m, a, mu, s, jac, A)
            if sh == sh:
                return t + sh, work, m
    c = order[0]
    m = Ka[c]
    for k in range(m):
        a[k] = ca[c, k]
        mu[k] = cm[c, k]
        v = cs[c, k] * cs[c, k]
        q = v - shep
        s[k] = math.sqrt(q if q > 0.25 * v else 0.25 * v)
    return mixture_threshold_log(a, mu, s, m, z, log_pfa), work, m
