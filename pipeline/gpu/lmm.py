"""GPU twin of ``lmm`` (:mod:`sarship.pipeline.detectors.lmm`): exact, fast and grid forms.

The CPU detector calls :func:`detect` for a CuPy block, with everything it needs as
arguments; this module depends on the pure per-ring maths (:mod:`sarship.pipeline.stats.lmm_fit`)
and never imports the detector module. One CUDA thread fits one ring (a pixel's, or a grid
node's): the same EM for K' = 1..K, BIC order, damped-Newton ML polish, predictive tail
shift and safeguarded Newton threshold as :func:`sarship.pipeline.stats.lmm_fit.fit_threshold`,
transcribed operation for operation (double precision, no FMA contraction). The ring's
points are read in the CPU's order: raw ring samples in row-major order (exact form), or the
ring histogram's non-empty bins in ascending order (fast and grid forms; the histogram of
each thread lives in a global scratch array, bins by threads so that neighbouring threads'
counts are adjacent). CUDA's ``exp``/``log``/``erfc`` differ from glibc's in the last bits,
so thresholds agree to ~1e-12 relative except where the BIC choice or a Newton acceptance
sits on a tie; the tests hold the GPU masks to the CPU tests' agreement rule (<= 0.1 % of
pixels).
"""

from __future__ import annotations

import numpy as np

from sarship.pipeline.gpu import kernels
from sarship.pipeline.stats.lmm_fit import init_z_table

SOURCE = r"""
#define KMAX 6
#define PMAX 17
#define LOG_SQRT_2PI 0.91893853320467274178
#define INFINITY __longlong_as_double(0x7ff0000000000000LL)
#define NAN __longlong_as_double(0x7ff8000000000000LL)

struct RingSrc {      /* raw ring samples (ln x, NaN = unusable), row-major like the CPU gather */
    const double* Y; long long ld; long long ci, cj; int rb, rg;
    template <class F> __device__ void each(F f) const {
        for (long long r = ci - rb; r <= ci + rb; ++r) {
            bool inner = (r >= ci - rg) && (r <= ci + rg);
            for (long long c = cj - rb; c <= cj + rb; ++c) {
                if (inner && c >= cj - rg && c <= cj + rg) continue;
                double v = Y[r * ld + c];
                if (v == v) f(v, 1.0);
            }
        }
    }
};

struct HistSrc {      /* non-empty histogram bins, ascending: centre ((b - off) + 0.5) h, count */
    const int* hist; long long stride; int nb; int bmin; int off; double bw;
    template <class F> __device__ void each(F f) const {
        for (int q = 0; q < nb; ++q) {
            int cnt = hist[q * stride];
            if (cnt > 0) f(((double)((bmin + q) - off) + 0.5) * bw, (double)cnt);
        }
    }
};

/* one point's log-sum-exp over the live components (live == nullptr: all), as the CPU's
 * _point_terms: lt[k] <- exp(l_k - mx) with l_k = ca[k] - u_k^2 / 2, u_k = (yj - mu[k]) inv[k];
 * *tot <- sum of lt[k]; returns mx = max_k l_k */
__device__ __forceinline__ double point_terms(double yj, int K, const double* mu, const double* ca,
                                              const double* inv, const bool* live, double* lt, double* tot) {
    double mx = -INFINITY;
    for (int k = 0; k < K; ++k) if (!live || live[k]) {
        double u = (yj - mu[k]) * inv[k];
        double t = ca[k] - 0.5 * u * u;
        lt[k] = t;
        if (t > mx) mx = t;
    }
    double sum = 0.0;
    for (int k = 0; k < K; ++k) if (!live || live[k]) { double e = exp(lt[k] - mx); lt[k] = e; sum += e; }
    *tot = sum;
    return mx;
}

template <class S>
__device__ int em_fit(const S& src, int K, const double* init_z, int max_iter, double tol,
                      double* a, double* mu, double* s) {
    double W = 0.0, m = 0.0;
    src.each([&](double y, double w) { W += w; m += w * y; });
    m /= W;
    double v = 0.0;
    src.each([&](double y, double w) { double d = y - m; v += w * d * d; });
    v /= W;
    double floor_ = 1e-4 * v + 1e-12;
    double sd = sqrt(v);
    double mz2 = 0.0;
    for (int k = 0; k < K; ++k) mz2 += init_z[k] * init_z[k];
    mz2 /= K;
    double s0 = sd * sqrt(fmax(1.0 - mz2, 1e-4));
    if (s0 * s0 < floor_) s0 = sqrt(floor_);
    for (int k = 0; k < K; ++k) { a[k] = 1.0 / K; mu[k] = m + sd * init_z[k]; s[k] = s0; }
    double lt[KMAX], sg[KMAX], sgd[KMAX], sgdd[KMAX], ca[KMAX], inv[KMAX];
    bool live[KMAX];
    for (int k = 0; k < K; ++k) live[k] = true;
    double prev = -INFINITY;
    int it = 0;
    while (it < max_iter) {
        it += 1;
        for (int k = 0; k < K; ++k) {
            sg[k] = 0.0; sgd[k] = 0.0; sgdd[k] = 0.0;
            if (live[k]) { ca[k] = log(a[k]) - log(s[k]); inv[k] = 1.0 / s[k]; }
        }
        double ll = 0.0;
        src.each([&](double yj, double wj) {
            double tot;
            double mx = point_terms(yj, K, mu, ca, inv, live, lt, &tot);
            ll += wj * (mx + log(tot));
            double r = wj / tot;
            for (int k = 0; k < K; ++k) if (live[k]) {
                double g = lt[k] * r;
                double d = yj - mu[k];
                sg[k] += g; sgd[k] += g * d; sgdd[k] += g * d * d;
            }
        });
        ll = ll / W - LOG_SQRT_2PI;
        for (int k = 0; k < K; ++k) if (live[k]) {
            if (sg[k] < 1e-9 * W) { live[k] = false; a[k] = 0.0; continue; }
            double dm = sgd[k] / sg[k];
            double var = sgdd[k] / sg[k] - dm * dm;
            mu[k] = mu[k] + dm;
            if (var < floor_) var = floor_;
            s[k] = sqrt(var);
            a[k] = sg[k] / W;
        }
        double ch = ll - prev;
        prev = ll;
        if (-tol < ch && ch < tol) break;
    }
    double tot = 0.0;
    for (int k = 0; k < K; ++k) tot += a[k];
    for (int k = 0; k < K; ++k) a[k] = a[k] / tot;
    return it;
}

__device__ void sf_pdf(double t, const double* a, const double* mu, const double* s, int K, double* S, double* f) {
    double SS = 0.0, ff = 0.0;
    for (int k = 0; k < K; ++k) if (a[k] > 0.0) {
        double u = (t - mu[k]) / s[k];
        SS += a[k] * 0.5 * erfc(u * 0.7071067811865476);
        ff += a[k] * exp(-0.5 * u * u) / (s[k] * 2.5066282746310002);
    }
    *S = SS; *f = ff;
}

__device__ double threshold_log(const double* a, const double* mu, const double* s, int K, double z, double log_pfa) {
    double lo = INFINITY, hi = -INFINITY;
    for (int k = 0; k < K; ++k) if (a[k] > 0.0) {
        double q = mu[k] + s[k] * z;
        if (q < lo) lo = q;
        if (q > hi) hi = q;
    }
    if (!(hi > lo)) return lo;
    double t = 0.5 * (lo + hi);
    for (int i = 0; i < 100; ++i) {
        double S, f;
        sf_pdf(t, a, mu, s, K, &S, &f);
        if (S <= 0.0) { hi = t; t = 0.5 * (lo + hi); continue; }
        double g = log(S) - log_pfa;
        if (g > 0.0) lo = t;
        else if (g < 0.0) hi = t;
        else return t;
        double tn = (f > 0.0) ? t + g * S / f : 0.5 * (lo + hi);
        if (!(lo < tn && tn < hi)) tn = 0.5 * (lo + hi);
        double step = fabs(tn - t);
        t = tn;
        if (step <= 1e-10 * (1.0 + fabs(t)) || (hi - lo) <= 1e-10 * (1.0 + fabs(t))) break;
    }
    return t;
}

template <class S>
__device__ double loglik(const S& src, int K, const double* a, const double* mu, const double* s) {
    double ca[KMAX], inv[KMAX], lt[KMAX];
    for (int k = 0; k < K; ++k) { ca[k] = log(a[k]) - log(s[k]); inv[k] = 1.0 / s[k]; }
    double ll = 0.0, W = 0.0;
    src.each([&](double yj, double wj) {
        double tot;
        double mx = point_terms(yj, K, mu, ca, inv, nullptr, lt, &tot);
        ll += wj * (mx + log(tot));
        W += wj;
    });
    return ll - W * LOG_SQRT_2PI;
}

template <class S>
__device__ double grad_hess(const S& src, int K, const double* a, const double* mu, const double* s,
                            double* G, double* H) {
    int p = 3 * K - 1;
    for (int q = 0; q < p; ++q) { G[q] = 0.0; for (int r = 0; r < p; ++r) H[q * PMAX + r] = 0.0; }
    double ca[KMAX], inv[KMAX], lt[KMAX], Gj[PMAX];
    for (int k = 0; k < K; ++k) { ca[k] = log(a[k]) - log(s[k]); inv[k] = 1.0 / s[k]; }
    double ll = 0.0, W = 0.0;
    src.each([&](double yj, double w) {
        W += w;
        double tot;
        double mx = point_terms(yj, K, mu, ca, inv, nullptr, lt, &tot);
        ll += w * (mx + log(tot));
        double rt = 1.0 / tot;
        for (int q = 0; q < p; ++q) Gj[q] = 0.0;
        for (int k = 0; k < K; ++k) {
            double g = lt[k] * rt;
            double wg = w * g;
            double u = (yj - mu[k]) * inv[k];
            double dmu = u * inv[k];
            double dla = u * u - 1.0;
            int im = K - 1 + k, il = 2 * K - 1 + k;
            for (int m = 0; m < K - 1; ++m) {
                double dm = (m == k ? 1.0 : 0.0) - a[m];
                Gj[m] += g * dm;
                double c = wg * dm;
                for (int m2 = m; m2 < K - 1; ++m2) H[m * PMAX + m2] += c * ((m2 == k ? 1.0 : 0.0) - a[m2]);
                H[m * PMAX + im] += c * dmu;
                H[m * PMAX + il] += c * dla;
            }
            Gj[im] += g * dmu;
            Gj[il] += g * dla;
            H[im * PMAX + im] += wg * (dmu * dmu - inv[k] * inv[k]);
            H[im * PMAX + il] += wg * (dmu * dla - 2.0 * dmu);
            H[il * PMAX + il] += wg * (dla * dla - 2.0 * u * u);
        }
        for (int q = 0; q < p; ++q) {
            double c = w * Gj[q];
            G[q] += c;
            for (int r = q; r < p; ++r) H[q * PMAX + r] -= c * Gj[r];
        }
    });
    for (int m = 0; m < K - 1; ++m)
        for (int m2 = m; m2 < K - 1; ++m2) H[m * PMAX + m2] -= W * ((m == m2 ? a[m] : 0.0) - a[m] * a[m2]);
    for (int q = 0; q < p; ++q) for (int r = 0; r < q; ++r) H[q * PMAX + r] = H[r * PMAX + q];
    return ll - W * LOG_SQRT_2PI;
}

__device__ bool chol_solve(const double* A, const double* b, int p, double* x, double* L) {
    for (int i = 0; i < p; ++i)
        for (int j = 0; j <= i; ++j) {
            double acc = A[i * PMAX + j];
            for (int k = 0; k < j; ++k) acc -= L[i * PMAX + k] * L[j * PMAX + k];
            if (i == j) {
                if (!(acc > 1e-14 * fabs(A[i * PMAX + i]))) return false;
                L[i * PMAX + i] = sqrt(acc);
            } else L[i * PMAX + j] = acc / L[j * PMAX + j];
        }
    for (int i = 0; i < p; ++i) {
        double acc = b[i];
        for (int k = 0; k < i; ++k) acc -= L[i * PMAX + k] * x[k];
        x[i] = acc / L[i * PMAX + i];
    }
    for (int i = p - 1; i >= 0; --i) {
        double acc = x[i];
        for (int k = i + 1; k < p; ++k) acc -= L[k * PMAX + i] * x[k];
        x[i] = acc / L[i * PMAX + i];
    }
    return true;
}

__device__ bool from_theta(int K, const double* th, double* a, double* mu, double* s) {
    double mx = 0.0;
    for (int k = 0; k < K - 1; ++k) if (th[k] > mx) mx = th[k];
    double tot = exp(-mx);
    for (int k = 0; k < K - 1; ++k) tot += exp(th[k] - mx);
    for (int k = 0; k < K - 1; ++k) a[k] = exp(th[k] - mx) / tot;
    a[K - 1] = exp(-mx) / tot;
    bool ok = true;
    for (int k = 0; k < K; ++k) {
        mu[k] = th[K - 1 + k];
        double lam = th[2 * K - 1 + k];
        if (!(-300.0 < lam && lam < 300.0) || !(a[k] > 1e-300) || mu[k] != mu[k]) ok = false;
        else s[k] = exp(lam);
    }
    return ok;
}

struct Work { double H[PMAX * PMAX], M[PMAX * PMAX], L[PMAX * PMAX]; };

template <class S>
__device__ bool ml_newton(const S& src, int K, double* a, double* mu, double* s, double* A, int max_steps,
                          Work& wk, int* steps_out) {
    int p = 3 * K - 1;
    double th[PMAX], G[PMAX], d[PMAX], tn[PMAX], at[KMAX], mt[KMAX], st[KMAX];
    for (int k = 0; k < K - 1; ++k) th[k] = log(a[k]) - log(a[K - 1]);
    for (int k = 0; k < K; ++k) { th[K - 1 + k] = mu[k]; th[2 * K - 1 + k] = log(s[k]); }
    double lam = 0.0;
    int steps = 0;
    bool ok = false;
    double ll = grad_hess(src, K, a, mu, s, G, wk.H);
    while (true) {
        for (int q = 0; q < p; ++q) for (int r = 0; r < p; ++r) A[q * PMAX + r] = -wk.H[q * PMAX + r];
        bool pd = chol_solve(A, G, p, d, wk.L);
        if (pd) {
            double dec = 0.0;
            for (int q = 0; q < p; ++q) dec += G[q] * d[q];
            if (dec < 1e-12) { ok = true; break; }
        }
        if (steps >= max_steps) break;
        steps += 1;
        bool accepted = false;
        for (int rep = 0; rep < 12; ++rep) {
            if (lam > 0.0 || !pd) {
                if (lam == 0.0) lam = 1e-4;
                for (int q = 0; q < p; ++q) {
                    for (int r = 0; r < p; ++r) wk.M[q * PMAX + r] = A[q * PMAX + r];
                    wk.M[q * PMAX + q] = A[q * PMAX + q] + lam * (fabs(A[q * PMAX + q]) + 1e-300);
                }
                if (!chol_solve(wk.M, G, p, d, wk.L)) { lam *= 10.0; continue; }
            }
            for (int q = 0; q < p; ++q) tn[q] = th[q] + d[q];
            double lln = -INFINITY;
            if (from_theta(K, tn, at, mt, st)) lln = loglik(src, K, at, mt, st);
            if (lln >= ll - 1e-13 * fabs(ll)) { accepted = true; break; }
            lam = (lam == 0.0) ? 1e-4 : lam * 10.0;
        }
        if (!accepted) break;
        for (int q = 0; q < p; ++q) th[q] = tn[q];
        from_theta(K, th, a, mu, s);
        lam = (lam > 1e-8) ? lam * 0.01 : 0.0;
        ll = grad_hess(src, K, a, mu, s, G, wk.H);
    }
    *steps_out = steps;
    return ok;
}

__device__ double predictive_shift(double t, int K, const double* a, const double* mu, const double* s,
                                   const double* jac, const double* A, Work& wk) {
    int p = 3 * K - 1;
    double S, f;
    sf_pdf(t, a, mu, s, K, &S, &f);
    if (!(S > 0.0 && f > 0.0)) return NAN;
    double dS[PMAX], x[PMAX];
    for (int k = 0; k < K; ++k) {
        double u = (t - mu[k]) / s[k];
        double ph = exp(-0.5 * u * u) / 2.5066282746310002;
        if (k < K - 1) dS[k] = a[k] * (0.5 * erfc(u * 0.7071067811865476) - S);
        dS[K - 1 + k] = a[k] * ph / s[k];
        dS[2 * K - 1 + k] = a[k] * ph * u * jac[k];
    }
    if (!chol_solve(A, dS, p, x, wk.L)) return NAN;
    double q = 0.0;
    for (int r = 0; r < p; ++r) q += dS[r] * x[r];
    double sh = 0.5 * q / (f * S);
    if (!(sh >= 0.0 && sh < INFINITY)) return NAN;
    return sh;
}

__device__ bool resolved(int K, const double* s, double res) {
    for (int k = 0; k < K; ++k) if (!(s[k] * s[k] > res)) return false;
    return true;
}

template <class S>
__device__ double fit_threshold(const S& src, int K, const double* init_zs, int max_iter, double tol, double shep,
                                bool select, bool predictive, double z, double log_pfa) {
    int Ka[KMAX];
    double ca[KMAX * KMAX], cm[KMAX * KMAX], cs[KMAX * KMAX], bic[KMAX];
    double ta[KMAX], tm[KMAX], ts[KMAX], a[KMAX], mu[KMAX], s[KMAX], jac[KMAX];
    for (int i = 0; i < K; ++i) { Ka[i] = 0; bic[i] = INFINITY;
        for (int j = 0; j < K; ++j) { ca[i * KMAX + j] = 0.0; cm[i * KMAX + j] = 0.0; cs[i * KMAX + j] = 1.0; } }
    double W = 0.0, ym = 0.0;
    src.each([&](double y, double w) { W += w; ym += w * y; });
    ym /= W;
    double vy = 0.0;
    src.each([&](double y, double w) { vy += w * (y - ym) * (y - ym); });
    vy /= W;
    double res = 1.0001e-4 * vy + 1e-12;
    if (4.0 / 3.0 * shep > res) res = 4.0 / 3.0 * shep;
    double lnW = log(W);
    int k0 = select ? 1 : K;
    for (int Kc = k0; Kc <= K; ++Kc) {
        em_fit(src, Kc, init_zs + (Kc - 1) * KMAX, max_iter, tol, ta, tm, ts);
        int m = 0;
        for (int k = 0; k < Kc; ++k) if (ta[k] > 0.0) {
            ca[(Kc - 1) * KMAX + m] = ta[k]; cm[(Kc - 1) * KMAX + m] = tm[k]; cs[(Kc - 1) * KMAX + m] = ts[k]; m += 1;
        }
        Ka[Kc - 1] = m;
        bic[Kc - 1] = -2.0 * loglik(src, m, ca + (Kc - 1) * KMAX, cm + (Kc - 1) * KMAX, cs + (Kc - 1) * KMAX)
                      + (3 * m - 1) * lnW;
    }
    int order[KMAX];                         /* stable sort of bic (mergesort order) */
    for (int i = 0; i < K; ++i) order[i] = i;
    for (int i = 1; i < K; ++i) {
        int v = order[i]; int j = i - 1;
        while (j >= 0 && bic[order[j]] > bic[v]) { order[j + 1] = order[j]; --j; }
        order[j + 1] = v;
    }
    if (predictive) {
        Work wk;
        double A[PMAX * PMAX];
        for (int oi = 0; oi < K - k0 + 1; ++oi) {
            int c = order[oi];
            int m = Ka[c];
            for (int k = 0; k < m; ++k) { a[k] = ca[c * KMAX + k]; mu[k] = cm[c * KMAX + k]; s[k] = cs[c * KMAX + k]; }
            if (!resolved(m, s, res)) continue;
            int st;
            bool ok = ml_newton(src, m, a, mu, s, A, 30, wk, &st);
            if (!(ok && resolved(m, s, res))) continue;
            for (int k = 0; k < m; ++k) {
                double v = s[k] * s[k];
                double q = v - shep;
                q = (q > 0.25 * v) ? q : 0.25 * v;
                jac[k] = v / q;
                s[k] = sqrt(q);
            }
            double t = threshold_log(a, mu, s, m, z, log_pfa);
            double sh = predictive_shift(t, m, a, mu, s, jac, A, wk);
            if (sh == sh) return t + sh;
        }
    }
    int c = order[0];
    int m = Ka[c];
    for (int k = 0; k < m; ++k) {
        a[k] = ca[c * KMAX + k]; mu[k] = cm[c * KMAX + k];
        double v = cs[c * KMAX + k] * cs[c * KMAX + k];
        double q = v - shep;
        s[k] = sqrt((q > 0.25 * v) ? q : 0.25 * v);
    }
    return threshold_log(a, mu, s, m, z, log_pfa);
}

__device__ double target_log(const double* X, long long ld, long long ci, long long cj, int rt) {
    double x;
    if (rt == 0) x = X[ci * ld + cj];
    else {
        double acc = 0.0;
        for (long long a = ci - rt; a <= ci + rt; ++a)
            for (long long b = cj - rt; b <= cj + rt; ++b) acc += X[a * ld + b];
        x = acc / (double)((2 * rt + 1) * (2 * rt + 1));
    }
    if (x > 0.0 && x < INFINITY) return log(x);
    return NAN;
}

__device__ void decide(double lx, double t, long long idx, unsigned char* mask, float* stat) {
    if (lx > t) {
        mask[idx] = 1;
        float r = (float)exp(lx - t);
        if (!(r > 1.0f)) r = nextafterf(1.0f, __int_as_float(0x7f800000));
        stat[idx] = r;
    }
}

/* histogram of the ring around (ci, cj) into this thread's column of the scratch */
__device__ int build_hist(const int* B, long long ld, long long ci, long long cj, int rb, int rg,
                          int* hist, long long stride, int nb, int bmin) {
    for (int q = 0; q < nb; ++q) hist[q * stride] = 0;
    int ntot = 0;
    for (long long r = ci - rb; r <= ci + rb; ++r) {
        bool inner = (r >= ci - rg) && (r <= ci + rg);
        for (long long c = cj - rb; c <= cj + rb; ++c) {
            if (inner && c >= cj - rg && c <= cj + rg) continue;
            int b = B[r * ld + c];
            if (b >= 0) { hist[(b - bmin) * stride] += 1; ntot += 1; }
        }
    }
    return ntot;
}

extern "C" {

__global__ void lmm_exact(const double* X, const double* Y, long long ld, long long h, long long w, long long t0,
                          long long nt, int halo, int rb, int rg, int rt, int K, const double* init_zs, int max_iter,
                          double tol, int select, int predictive, double z, double log_pfa, int nmin,
                          unsigned char* mask, float* stat) {
    long long q = (long long)blockIdx.x * blockDim.x + threadIdx.x;
    if (q >= nt) return;
    long long t = t0 + q;
    long long i = t / w, j = t % w, ci = i + halo, cj = j + halo;
    double lx = target_log(X, ld, ci, cj, rt);
    if (lx != lx) return;
    RingSrc src{Y, ld, ci, cj, rb, rg};
    int n = 0;
    src.each([&](double, double) { n += 1; });
    if (n < nmin) return;
    double th = fit_threshold(src, K, init_zs, max_iter, tol, 0.0, select != 0, predictive != 0, z, log_pfa);
    decide(lx, th, t, mask, stat);
}

/* fast form at listed cells: idx[q] = flat index into a (h2 x w2) grid of cells whose block
 * coordinates are (r0 + i * step, c0 + j * step); writes T (NaN: too few samples) */
__global__ void lmm_hist_fit(const int* B, long long ld, const long long* idx, long long n_idx, long long w2,
                             long long r0, long long c0, int step, int rb, int rg, int* scratch, int nb, int bmin,
                             int off, double bw, int K, const double* init_zs, int max_iter, double tol, int select,
                             int predictive, double z, double log_pfa, int nmin, double* T) {
    long long q = (long long)blockIdx.x * blockDim.x + threadIdx.x;
    if (q >= n_idx) return;
    long long t = idx[q];
    long long ci = r0 + (t / w2) * step, cj = c0 + (t % w2) * step;
    int* hist = scratch + q;
    int ntot = build_hist(B, ld, ci, cj, rb, rg, hist, n_idx, nb, bmin);
    if (ntot < nmin) { T[t] = NAN; return; }
    HistSrc src{hist, n_idx, nb, bmin, off, bw};
    T[t] = fit_threshold(src, K, init_zs, max_iter, tol, bw * bw / 12.0, select != 0, predictive != 0, z, log_pfa);
}

/* fast form decision from per-pixel thresholds T (NaN: skip) */
__global__ void lmm_decide(const double* X, long long ld, long long h, long long w, int halo, int rt, const double* T,
                           unsigned char* mask, float* stat) {
    long long t = (long long)blockIdx.x * blockDim.x + threadIdx.x;
    if (t >= h * w) return;
    double th = T[t];
    if (th != th) return;
    double lx = target_log(X, ld, t / w + halo, t % w + halo, rt);
    if (lx != lx) return;
    decide(lx, th, t, mask, stat);
}

/* grid form, per pixel: interpolate the node thresholds; candidates (lx > tmin - refine) get
 * cand = 1 and are decided later by their own fit; others decided here (refine = 0). */
__global__ void lmm_grid_pixels(const double* X, long long ld, long long h, long long w, int halo, int rt,
                                const double* Tn, long long nc, long long kr0, long long kc0, long long g0r,
                                long long g0c, int step, double refine, unsigned char* cand,
                                unsigned char* mask, float* stat) {
    long long t = (long long)blockIdx.x * blockDim.x + threadIdx.x;
    if (t >= h * w) return;
    long long i = t / w, j = t % w;
    cand[t] = 0;
    long long gr = g0r + i, gc = g0c + j;
    long long kr = gr / step, kc = gc / step;        /* gr, gc >= 0 */
    long long u = kr - kr0, v = kc - kc0;
    double inv_step = 1.0 / step;
    double fr = (double)(gr - kr * step) * inv_step, fc = (double)(gc - kc * step) * inv_step;
    double lx = target_log(X, ld, i + halo, j + halo, rt);
    if (lx != lx) return;
    double num = 0.0, den = 0.0;
    double w00 = (1.0 - fr) * (1.0 - fc), w01 = (1.0 - fr) * fc, w10 = fr * (1.0 - fc), w11 = fr * fc;
    double t00 = Tn[u * nc + v], t01 = Tn[u * nc + v + 1], t10 = Tn[(u + 1) * nc + v], t11 = Tn[(u + 1) * nc + v + 1];
    if (w00 > 0.0 && t00 == t00) { num += w00 * t00; den += w00; }
    if (w01 > 0.0 && t01 == t01) { num += w01 * t01; den += w01; }
    if (w10 > 0.0 && t10 == t10) { num += w10 * t10; den += w10; }
    if (w11 > 0.0 && t11 == t11) { num += w11 * t11; den += w11; }
    if (!(den > 0.0)) return;
    double th = (den == 1.0) ? num : num / den;
    double tmin = th;
    if (t00 < tmin) tmin = t00;
    if (t01 < tmin) tmin = t01;
    if (t10 < tmin) tmin = t10;
    if (t11 < tmin) tmin = t11;
    if (refine > 0.0 && lx > tmin - refine) { cand[t] = 1; return; }
    decide(lx, th, t, mask, stat);
}

}  /* extern "C" */
"""

THREADS = 128


def _launch(name: str, n: int, args: tuple) -> None:
    kernels.launch(name, n, args, source=SOURCE, std="c++17", threads=THREADS)


#: Largest histogram scratch (bytes) one launch may use; cells are fitted in chunks.
SCRATCH_BYTES = 256 * 2**20


def _init_zs(K: int) -> np.ndarray:
    """:func:`~sarship.pipeline.stats.lmm_fit.init_z_table` in rows of KMAX = 6 (the kernels' layout)."""
    t = np.zeros((K, 6))
    t[:, :K] = init_z_table(K)
    return t


def _bins(cp, X64, bw: float):
    """Global ln-x bin of every value (the CPU's ``_bin_index``) and the block's bin range."""
    inv_h = 1.0 / bw
    off = 1 + int(np.ceil(800.0 * inv_h))
    ok = (X64 > 0.0) & (X64 < np.inf)
    with np.errstate(all="ignore"):
        B = cp.where(ok, cp.floor(cp.log(cp.where(ok, X64, 1.0)) * inv_h).astype(cp.int32) + off, -1)
    B = B.astype(cp.int32)
    if not bool(ok.any()):
        return B, off, 0, -1
    valid = B[ok]
    return B, off, int(valid.min()), int(valid.max())


def _hist_fits(cp, B, ld, cells, w2, r0, c0, step, rb, rg, nb, bmin, off, bw, common, T):
    """Fast-form fits at the listed cells, in chunks bounded by :data:`SCRATCH_BYTES`."""
    chunk = max(1024, SCRATCH_BYTES // (4 * max(nb, 1)))
    for s in range(0, int(cells.size), chunk):
        part = cells[s : s + chunk]
        n = int(part.size)
        scratch = cp.empty(nb * n, cp.int32)
        _launch(
            "lmm_hist_fit",
            n,
            (
                B,
                np.int64(ld),
                part,
                np.int64(n),
                np.int64(w2),
                np.int64(r0),
                np.int64(c0),
                np.int32(step),
                np.int32(rb),
                np.int32(rg),
                scratch,
                np.int32(nb),
                np.int32(bmin),
                np.int32(off),
                np.float64(bw),
                *common,
                T,
            ),
        )
        del scratch


# argument lists laid out by hand, kept from the formatter
# fmt: off
def detect(block, halo: int, origin, rb: int, rg: int, rt: int, K: int, prep: dict, method: str,
           step: int, refine: float):
    """``lmm`` on a CuPy block (same arguments as the CPU kernels; see the module docstring)."""
    import cupy as cp

    X64 = cp.ascontiguousarray(block, dtype=cp.float64)
    h, w = X64.shape[0] - 2 * halo, X64.shape[1] - 2 * halo
    ld = X64.shape[1]
    mask = cp.zeros((h, w), cp.bool_)
    stat = cp.zeros((h, w), cp.float32)
    if h <= 0 or w <= 0:
        return mask, stat
    init_zs = cp.asarray(_init_zs(K))
    common = (np.int32(K), init_zs, np.int32(int(prep["max_iter"])), np.float64(float(prep["tol"])),
              np.int32(prep.get("select", "bic") == "bic"), np.int32(prep.get("tail", "predictive") == "predictive"),
              np.float64(float(prep["z"])), np.float64(float(prep["log_pfa"])),
              np.int32(max(8, 3 * K, ((2 * rb + 1) ** 2 - (2 * rg + 1) ** 2 + 1) // 2)))  # lmm.min_usable
    if method == "exact":
        ok = (X64 > 0.0) & (X64 < np.inf)
        Y = cp.where(ok, cp.log(cp.where(ok, X64, 1.0)), cp.nan)
        total = h * w
        chunk = 1 << 18
        for t0 in range(0, total, chunk):
            nt = min(chunk, total - t0)
            _launch("lmm_exact", nt, (X64, Y, np.int64(ld), np.int64(h), np.int64(w), np.int64(t0), np.int64(nt),
                                      np.int32(halo), np.int32(rb), np.int32(rg), np.int32(rt), *common, mask, stat))
        return mask, stat
    bw = float(prep["bin_width"])
    B, off, bmin, bmax = _bins(cp, X64, bw)
    if bmax < 0:
        return mask, stat
    nb = bmax - bmin + 1
    if method == "fast":
        T = cp.full(h * w, cp.nan, cp.float64)
        _hist_fits(cp, B, ld, cp.arange(h * w, dtype=cp.int64), w, halo, halo, 1, rb, rg, nb, bmin, off, bw,
                   common, T)
        _launch("lmm_decide", h * w, (X64, np.int64(ld), np.int64(h), np.int64(w), np.int32(halo), np.int32(rt),
                                      T, mask, stat))
        return mask, stat
    # grid: node fits, interpolation, candidates refitted at their own pixel
    g0r, g0c = int(origin[0]) + halo, int(origin[1]) + halo
    kr0, kr1 = g0r // step, (g0r + h - 1) // step + 1
    kc0, kc1 = g0c // step, (g0c + w - 1) // step + 1
    nr, nc = kr1 - kr0 + 1, kc1 - kc0 + 1
    Tn = cp.full(nr * nc, cp.nan, cp.float64)
    _hist_fits(cp, B, ld, cp.arange(nr * nc, dtype=cp.int64), nc, kr0 * step - g0r + halo, kc0 * step - g0c + halo,
               step, rb, rg, nb, bmin, off, bw, common, Tn)
    cand = cp.empty((h, w), cp.uint8)
    _launch("lmm_grid_pixels", h * w, (X64, np.int64(ld), np.int64(h), np.int64(w), np.int32(halo), np.int32(rt),
                                       Tn, np.int64(nc), np.int64(kr0), np.int64(kc0), np.int64(g0r), np.int64(g0c),
                                       np.int32(step), np.float64(refine), cand, mask, stat))
    cells = cp.flatnonzero(cand).astype(cp.int64)
    if cells.size:
        T = cp.full(h * w, cp.nan, cp.float64)
        _hist_fits(cp, B, ld, cells, w, halo, halo, 1, rb, rg, nb, bmin, off, bw, common, T)
        _launch("lmm_decide", h * w, (X64, np.int64(ld), np.int64(h), np.int64(w), np.int32(halo), np.int32(rt),
                                      T, mask, stat))
    return mask, stat
# fmt: on
