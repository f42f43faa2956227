"""CUDA kernels (one NVRTC module, compiled once per process and device).

Compiled with ``--fmad=false``: no multiply-add contraction, so each double-precision
operation rounds as the CPU kernels' (Numba/LLVM, no fast-math) do. Division and square
root in double precision are IEEE correctly rounded in CUDA by default.
"""

from __future__ import annotations

import functools

SOURCE = r"""
extern "C" {

__device__ __forceinline__ long long floordiv_ll(long long a, long long b) {
    long long q = a / b;
    if ((a % b != 0) && ((a < 0) != (b < 0))) q -= 1;
    return q;
}

/* ---------------------------------------------------------------------------------
 * Window sums with the van Herk / Gil-Werman order of pipeline/tiling/boxsum.py, bit for bit:
 * blocks of m samples aligned on global coordinates; suffix sums inside a block, prefix
 * sums over the next one; window = suffix[i] (+ prefix[i + m - 1]).
 * Horizontal pass: one thread per (row, column block); vertical pass on its float64
 * output: one thread per (column, row block), adjacent threads on adjacent columns.
 * ------------------------------------------------------------------------------- */

#define HSUM_BODY(T)                                                                    \
    long long t = (long long)blockIdx.x * blockDim.x + threadIdx.x;                     \
    if (t >= (long long)R * nblk) return;                                               \
    int r = (int)(t % R);                                                               \
    long long k = t / R;                                                                \
    long long s = (floordiv_ll(g0, m) + k) * m - g0;                                    \
    if (s >= n_out) return;                                                             \
    const T* xr = x + (long long)r * ldx;                                               \
    double* o = out + (long long)r * ldo;                                               \
    long long e = s + m - 1;                                                            \
    long long lo = s > 0 ? s : 0;                                                       \
    long long hi = (s + m < n_out) ? s + m : n_out;                                     \
    double a = 0.0;                                                                     \
    for (long long c = e; c >= lo; --c) {                                               \
        a = a + (double)xr[c];                                                          \
        if (c < n_out) o[c] = a;                                                        \
    }                                                                                   \
    long long i0 = lo;                                                                  \
    if (i0 == s) i0 += 1;                                                               \
    double p = 0.0;                                                                     \
    for (long long c = s + m; c < i0 + m - 1; ++c) p = p + (double)xr[c];               \
    for (long long i = i0; i < hi; ++i) {                                               \
        p = p + (double)xr[i + m - 1];                                                  \
        o[i] = o[i] + p;                                                                \
    }

__global__ void hsum_f32(const float* __restrict__ x, long long ldx, double* __restrict__ out,
                         long long ldo, int R, long long n_out, int m, long long g0, long long nblk) {
    HSUM_BODY(float)
}

__global__ void hsum_f64(const double* __restrict__ x, long long ldx, double* __restrict__ out,
                         long long ldo, int R, long long n_out, int m, long long g0, long long nblk) {
    HSUM_BODY(double)
}

/* Vertical pass on H (rows R = n_out + m - 1, ld ldh), out (n_out rows, ld ldo), w columns.
 * (Also the horizontal pass of a transposed input: the same additions in the same order.) */
#define VSUM_BODY(T)                                                                    \
    long long t = (long long)blockIdx.x * blockDim.x + threadIdx.x;                     \
    if (t >= w * nblk) return;                                                          \
    long long c = t % w;                                                                \
    long long k = t / w;                                                                \
    long long s = (floordiv_ll(g0, m) + k) * m - g0;                                    \
    if (s >= n_out) return;                                                             \
    long long e = s + m - 1;                                                            \
    long long lo = s > 0 ? s : 0;                                                       \
    long long hi = (s + m < n_out) ? s + m : n_out;                                     \
    double a = 0.0 + (double)H[e * ldh + c];                                            \
    if (e < n_out) out[e * ldo + c] = a;                                                \
    for (long long r = e - 1; r >= lo; --r) {                                           \
        a = a + (double)H[r * ldh + c];                                                 \
        if (r < n_out) out[r * ldo + c] = a;                                            \
    }                                                                                   \
    long long i0 = lo;                                                                  \
    if (i0 == s) i0 += 1;                                                               \
    bool started = false;                                                               \
    double p = 0.0;                                                                     \
    for (long long r = s + m; r < i0 + m - 1; ++r) {                                    \
        double v = (double)H[r * ldh + c];                                              \
        if (!started) { p = 0.0 + v; started = true; }                                  \
        else p = p + v;                                                                 \
    }                                                                                   \
    for (long long i = i0; i < hi; ++i) {                                               \
        double v = (double)H[(i + m - 1) * ldh + c];                                    \
        if (!started) { p = 0.0 + v; started = true; }                                  \
        else p = p + v;                                                                 \
        out[i * ldo + c] = out[i * ldo + c] + p;                                        \
    }

__global__ void vsum(const double* __restrict__ H, long long ldh, double* __restrict__ out,
                     long long ldo, long long w, long long n_out, int m, long long g0, long long nblk) {
    VSUM_BODY(double)
}

__global__ void vsum_f32(const float* __restrict__ H, long long ldh, double* __restrict__ out,
                         long long ldo, long long w, long long n_out, int m, long long g0, long long nblk) {
    VSUM_BODY(float)
}

/* ---------------------------------------------------------------------------------
 * Per-pixel decisions (same arithmetic order as the Numba kernels).
 * ------------------------------------------------------------------------------- */

/* ca_cfar: s = x_t / ((bg - gd) * inv); mask = s > thr (pipeline/detectors/ca_cfar.py). */
__global__ void ca_decide(const double* __restrict__ xt, const double* __restrict__ bg,
                          const double* __restrict__ gd, double inv, double thr, long long n,
                          unsigned char* __restrict__ mask, float* __restrict__ stat) {
    long long j = (long long)blockIdx.x * blockDim.x + threadIdx.x;
    if (j >= n) return;
    double m = (bg[j] - gd[j]) * inv;
    double x = xt[j];
    double s;
    if (m > 0.0) s = x / m;
    else if (x > 0.0) s = __longlong_as_double(0x7ff0000000000000LL);
    else s = 0.0;
    stat[j] = (float)s;
    mask[j] = s > thr;
}

/* two_parameter: mu = s1 / N, var = (s2 - s1 mu) / (N - 1), s = (x_t - mu) / sqrt(var). */
__global__ void tp_decide(const double* __restrict__ xt, const double* __restrict__ s1b,
                          const double* __restrict__ s1g, const double* __restrict__ s2b,
                          const double* __restrict__ s2g, double n_ring, double thr, long long n,
                          unsigned char* __restrict__ mask, float* __restrict__ stat) {
    long long j = (long long)blockIdx.x * blockDim.x + threadIdx.x;
    if (j >= n) return;
    double s1 = s1b[j] - s1g[j];
    double s2 = s2b[j] - s2g[j];
    double mu = s1 / n_ring;
    double var = (s2 - s1 * mu) / (n_ring - 1.0);
    double d = xt[j] - mu;
    double s;
    if (var > 0.0) s = d / sqrt(var);
    else if (d > 0.0) s = __longlong_as_double(0x7ff0000000000000LL);
    else s = 0.0;
    stat[j] = (float)s;
    mask[j] = s > thr;
}

/* y = transform(x) in double: 0 intensity, 1 amplitude sqrt(max(x, 0)), 2 dB. */
__global__ void tp_transform_f32(const float* __restrict__ x, long long n, int mode,
                                 double* __restrict__ y, double* __restrict__ y2) {
    long long j = (long long)blockIdx.x * blockDim.x + threadIdx.x;
    if (j >= n) return;
    double v = (double)x[j];
    if (mode == 1) v = sqrt(v > 0.0 ? v : 0.0);
    else if (mode == 2) v = 10.0 * log10(v > 1e-30 ? v : 1e-30);
    y[j] = v;
    y2[j] = v * v;
}

__global__ void tp_transform_f64(const double* __restrict__ x, long long n, int mode,
                                 double* __restrict__ y, double* __restrict__ y2) {
    long long j = (long long)blockIdx.x * blockDim.x + threadIdx.x;
    if (j >= n) return;
    double v = x[j];
    if (mode == 1) v = sqrt(v > 0.0 ? v : 0.0);
    else if (mode == 2) v = 10.0 * log10(v > 1e-30 ? v : 1e-30);
    y[j] = v;
    y2[j] = v * v;
}

/* ---------------------------------------------------------------------------------
 * Polarimetric: products of X X^H, the adaptive PWF quadratic form, PCDM.
 * ------------------------------------------------------------------------------- */

/* planes[q * n + j]: p^2 real numbers of X X^H (layout of apwf._products); x interleaved
 * complex64 (re, im) with p channels per pixel; scale1: factor on channel 1 (sqrt 2 for
 * pcdm's lexicographic k, 1 for apwf). Pixel j of a (rows, cols) region of a block with row
 * stride ldx pixels. */
__global__ void xxh_planes(const float* __restrict__ x, long long ldx, long long rows, long long cols,
                           int p, double scale1, double* __restrict__ planes) {
    long long t = (long long)blockIdx.x * blockDim.x + threadIdx.x;
    long long n = rows * cols;
    if (t >= n) return;
    long long i = t / cols, jj = t % cols;
    const float* px = x + 2 * p * (i * ldx + jj);
    double kr[3], ki[3];
    for (int c = 0; c < p; ++c) { kr[c] = (double)px[2 * c]; ki[c] = (double)px[2 * c + 1]; }
    if (scale1 != 1.0) { kr[1] *= scale1; ki[1] *= scale1; }
    for (int c = 0; c < p; ++c) planes[c * n + t] = kr[c] * kr[c] + ki[c] * ki[c];
    int q = p;
    for (int a = 0; a < p; ++a)
        for (int b = a + 1; b < p; ++b) {
            /* Re and Im of k_a conj(k_b), in the order of apwf._products / pcdm._planes_from_k */
            planes[q * n + t] = kr[a] * kr[b] + ki[a] * ki[b];
            planes[(q + 1) * n + t] = ki[a] * kr[b] - kr[a] * ki[b];
            q += 2;
        }
}

/* Covariance input (rows, cols, p, p) complex64 -> planes (diagonal, then Re/Im of a < b). */
__global__ void cov_planes(const float* __restrict__ C, long long ldc, long long rows, long long cols,
                           int p, double* __restrict__ planes) {
    long long t = (long long)blockIdx.x * blockDim.x + threadIdx.x;
    long long n = rows * cols;
    if (t >= n) return;
    long long i = t / cols, jj = t % cols;
    const float* pc = C + 2 * p * p * (i * ldc + jj);
    for (int d = 0; d < p; ++d) planes[d * n + t] = (double)pc[2 * (d * p + d)];
    int q = p;
    for (int a = 0; a < p; ++a)
        for (int b = a + 1; b < p; ++b) {
            planes[q * n + t] = (double)pc[2 * (a * p + b)];
            planes[(q + 1) * n + t] = (double)pc[2 * (a * p + b) + 1];
            q += 2;
        }
}

struct cplx { double r, i; };
__device__ __forceinline__ cplx cm(cplx a, cplx b) {      /* numba's complex multiply */
    cplx o; o.r = a.r * b.r - a.i * b.i; o.i = a.r * b.i + a.i * b.r; return o;
}
__device__ __forceinline__ cplx cj(cplx a) { cplx o; o.r = a.r; o.i = -a.i; return o; }
__device__ __forceinline__ cplx cs(cplx a, cplx b) { cplx o; o.r = a.r - b.r; o.i = a.i - b.i; return o; }
__device__ __forceinline__ cplx cre(double a) { cplx o; o.r = a; o.i = 0.0; return o; }

/* PCDM: P over the 8 neighbours (eq 4-7), SPAN_P and PSH (pcdm._pcdm_kernel). C: np planes
 * over (h + 2) x (w + 2) (row stride ldc), outputs h x w. */
__device__ void eig_sym3(double a11, double a22, double a33, double a12, double a13, double a23,
                         double* e1, double* e2, double* e3) {
    double p1 = a12 * a12 + a13 * a13 + a23 * a23;
    double q = (a11 + a22 + a33) / 3.0;
    double b11 = a11 - q, b22 = a22 - q, b33 = a33 - q;
    double p2 = b11 * b11 + b22 * b22 + b33 * b33 + 2.0 * p1;
    if (p2 <= 0.0) { *e1 = q; *e2 = q; *e3 = q; return; }
    double pp = sqrt(p2 / 6.0);
    double inv = 1.0 / pp;
    double c11 = b11 * inv, c22 = b22 * inv, c33 = b33 * inv;
    double c12 = a12 * inv, c13 = a13 * inv, c23 = a23 * inv;
    double det = c11 * (c22 * c33 - c23 * c23) - c12 * (c12 * c33 - c23 * c13) + c13 * (c12 * c23 - c22 * c13);
    double r = det / 2.0;
    double phi;
    const double PI = 3.141592653589793;
    if (r <= -1.0) phi = PI / 3.0;
    else if (r >= 1.0) phi = 0.0;
    else phi = acos(r) / 3.0;
    *e1 = q + 2.0 * pp * cos(phi);
    *e3 = q + 2.0 * pp * cos(phi + 2.0 * PI / 3.0);
    *e2 = 3.0 * q - *e1 - *e3;
}

__global__ void pcdm_kernel(const double* __restrict__ C, long long ldc, long long plane,
                            long long h, long long w, int p,
                            double* __restrict__ span, double* __restrict__ psh) {
    long long t = (long long)blockIdx.x * blockDim.x + threadIdx.x;
    if (t >= h * w) return;
    long long i = t / w, j = t % w;
    int nd = p, npair = (p * (p - 1)) / 2;
    double P[6] = {0.0, 0.0, 0.0, 0.0, 0.0, 0.0};
    long long ci = i + 1, cj = j + 1;
    for (int di = -1; di <= 1; ++di)
        for (int dj = -1; dj <= 1; ++dj) {
            if (di == 0 && dj == 0) continue;
            long long o0 = ci * ldc + cj, o1 = (ci + di) * ldc + (cj + dj);
            for (int k = 0; k < nd; ++k) P[k] += fabs(C[k * plane + o0] - C[k * plane + o1]);
            for (int k = 0; k < npair; ++k) {
                double re = C[(nd + 2 * k) * plane + o0] - C[(nd + 2 * k) * plane + o1];
                double im = C[(nd + 2 * k + 1) * plane + o0] - C[(nd + 2 * k + 1) * plane + o1];
                P[nd + k] += sqrt(re * re + im * im);
            }
        }
    if (p == 3) {
        span[t] = P[0] + P[1] + P[2];
        double e1, e2, e3;
        eig_sym3(P[0], P[1], P[2], P[3], P[4], P[5], &e1, &e2, &e3);
        double m1 = fabs(e1), m2 = fabs(e2), m3 = fabs(e3), tmp;
        if (m1 < m2) { tmp = m1; m1 = m2; m2 = tmp; }
        if (m2 < m3) { tmp = m2; m2 = m3; m3 = tmp; }
        if (m1 < m2) { tmp = m1; m1 = m2; m2 = tmp; }
        double den = m1 + m2;
        psh[t] = den > 0.0 ? m3 / den : 0.0;
    } else {
        span[t] = P[0] + P[1];
        double a11 = P[0], a22 = P[1], a12 = P[2];
        double tr = a11 + a22;
        double dd = (a11 - a22) * (a11 - a22) / 4.0 + a12 * a12;
        double d = sqrt(dd > 0.0 ? dd : 0.0);
        double m1 = fabs(tr / 2.0 + d), m2 = fabs(tr / 2.0 - d), tmp;
        if (m1 < m2) { tmp = m1; m1 = m2; m2 = tmp; }
        psh[t] = m1 > 0.0 ? m2 / m1 : 0.0;
    }
}

/* ---------------------------------------------------------------------------------
 * os_cfar (pipeline/detectors/os_cfar.py): decision by counting the ring samples below
 * c, the smallest value of the block's type with not (alpha * c < x_t): x_t > alpha X_(k)
 * iff at least k ring samples are < c. Exact comparisons only, so the mask is the CPU's.
 * ------------------------------------------------------------------------------- */

#define OS_DECIDE(NAME, T, NEXT, INF)                                                   \
__global__ void NAME(const T* __restrict__ x, long long ld, long long h, long long w, int halo, \
                     int rb, int rg, int rt, long long k, double alpha,                 \
                     unsigned char* __restrict__ mask, double* __restrict__ xt_out) {   \
    long long t = (long long)blockIdx.x * blockDim.x + threadIdx.x;                     \
    if (t >= h * w) return;                                                             \
    long long i = t / w, j = t % w, ci = i + halo, cj = j + halo;                       \
    double xt;                                                                          \
    if (rt == 0) xt = (double)x[ci * ld + cj];                                          \
    else {                                                                              \
        double s = 0.0;                                                                 \
        for (long long a = ci - rt; a <= ci + rt; ++a)                                  \
            for (long long b = cj - rt; b <= cj + rt; ++b) s += (double)x[a * ld + b];  \
        xt = s / (double)((2 * rt + 1) * (2 * rt + 1));                                 \
    }                                                                                   \
    xt_out[t] = xt;                                                                     \
    mask[t] = 0;                                                                        \
    if (!(xt == xt)) return;                                                            \
    T c = (T)(xt / alpha);                                                              \
    if (c != c) return;                                                                 \
    while (alpha * (double)c < xt) c = NEXT(c, INF);                                    \
    while (true) {                                                                      \
        T p = NEXT(c, -INF);                                                            \
        if (p == c || alpha * (double)p < xt) break;                                    \
        c = p;                                                                          \
    }                                                                                   \
    long long n_ring = (long long)(2 * rb + 1) * (2 * rb + 1) - (long long)(2 * rg + 1) * (2 * rg + 1); \
    long long max_above = n_ring - k, below = 0, above = 0;                             \
    bool hit = false;                                                                   \
    for (int a = -rb; a <= rb; ++a) {                                                   \
        const T* row = x + (ci + a) * ld;                                               \
        int cnt = 0, tot;                                                               \
        if (a < -rg || a > rg) {                                                        \
            for (long long b = cj - rb; b <= cj + rb; ++b) cnt += row[b] < c;           \
            tot = 2 * rb + 1;                                                           \
        } else {                                                                        \
            for (long long b = cj - rb; b < cj - rg; ++b) cnt += row[b] < c;            \
            for (long long b = cj + rg + 1; b <= cj + rb; ++b) cnt += row[b] < c;       \
            tot = 2 * (rb - rg);                                                        \
        }                                                                               \
        below += cnt;                                                                   \
        above += tot - cnt;                                                             \
        if (below >= k) { hit = true; break; }                                          \
        if (above > max_above) break;                                                   \
    }                                                                                   \
    mask[t] = hit;                                                                      \
}

OS_DECIDE(os_decide_f32, float, nextafterf, __int_as_float(0x7f800000))
OS_DECIDE(os_decide_f64, double, nextafter, __longlong_as_double(0x7ff0000000000000LL))

/* X_(k) of the ring of each listed pixel, exactly: bisection on order-preserving integer
 * keys of the values (NaN above everything, as np.partition ranks it), then the statistic
 * x_t / X_(k) with the CPU's special cases. */
__device__ __forceinline__ unsigned int key32(float v) {
    unsigned int u = __float_as_uint(v);
    if ((u & 0x7fffffffu) > 0x7f800000u) return 0xffffffffu;
    return (u & 0x80000000u) ? ~u : (u | 0x80000000u);
}
__device__ __forceinline__ float unkey32(unsigned int k) {
    if (k == 0xffffffffu) return __int_as_float(0x7fc00000);
    return __uint_as_float((k & 0x80000000u) ? (k & 0x7fffffffu) : ~k);
}
__device__ __forceinline__ unsigned long long key64(double v) {
    unsigned long long u = (unsigned long long)__double_as_longlong(v);
    if ((u & 0x7fffffffffffffffULL) > 0x7ff0000000000000ULL) return 0xffffffffffffffffULL;
    return (u & 0x8000000000000000ULL) ? ~u : (u | 0x8000000000000000ULL);
}
__device__ __forceinline__ double unkey64(unsigned long long k) {
    if (k == 0xffffffffffffffffULL) return __longlong_as_double(0x7ff8000000000000LL);
    return __longlong_as_double((long long)((k & 0x8000000000000000ULL) ? (k & 0x7fffffffffffffffULL) : ~k));
}

#define OS_STAT(NAME, T, KT, KEY, UNKEY, KMAX)                                          \
__global__ void NAME(const T* __restrict__ x, long long ld, long long w, int halo, int rb, int rg, \
                     long long k, const long long* __restrict__ idx, long long n_idx,   \
                     const double* __restrict__ xt_arr, double alpha, float stat_floor, \
                     float* __restrict__ stat) {                                        \
    long long q = (long long)blockIdx.x * blockDim.x + threadIdx.x;                     \
    if (q >= n_idx) return;                                                             \
    long long t = idx[q];                                                               \
    long long ci = t / w + halo, cj = t % w + halo;                                     \
    KT lo = 0, hi = KMAX;                                                               \
    while (lo < hi) {                                                                   \
        KT mid = lo + (hi - lo) / 2;                                                    \
        long long cnt = 0;                                                              \
        for (int a = -rb; a <= rb; ++a) {                                               \
            const T* row = x + (ci + a) * ld;                                           \
            for (int b = -rb; b <= rb; ++b) {                                           \
                if (a >= -rg && a <= rg && b >= -rg && b <= rg) continue;               \
                cnt += KEY(row[cj + b]) <= mid;                                         \
            }                                                                           \
        }                                                                               \
        if (cnt >= k) hi = mid; else lo = mid + 1;                                      \
    }                                                                                   \
    double xk = (double)UNKEY(lo);                                                      \
    double xt = xt_arr[t];                                                              \
    float r;                                                                            \
    if (xk > 0.0) r = (float)(xt / xk);                                                 \
    else if (xk == 0.0) r = __int_as_float(0x7f800000);                                 \
    else r = stat_floor;                                                                \
    if (!((double)r > alpha)) r = stat_floor;                                           \
    stat[t] = r;                                                                        \
}

OS_STAT(os_stat_f32, float, unsigned int, key32, unkey32, 0xffffffffu)
OS_STAT(os_stat_f64, double, unsigned long long, key64, unkey64, 0xffffffffffffffffULL)

/* ---------------------------------------------------------------------------------
 * vb_polsar pass 2 (pipeline/detectors/vb_polsar.py, _pixels): per pixel, with the
 * scene-wide mixture fixed, init from SPAN, A-22/23 and A-16..A-19 to A-26, A-27.
 * ------------------------------------------------------------------------------- */

__device__ double vb_digamma(double x) {
    double r = 0.0;
    while (x < 6.0) { r -= 1.0 / x; x += 1.0; }
    double f = 1.0 / (x * x);
    return r + log(x) - 0.5 / x - f * (1.0 / 12 - f * (1.0 / 120 - f * (1.0 / 252 - f * (1.0 / 240 - f / 132))));
}

__device__ double vb_expit(double v) {
    if (v >= 0) return 1.0 / (1.0 + exp(-v));
    double e = exp(v);
    return e / (1.0 + e);
}

#define VB_KMAX 16
__global__ void vb_pixels(const float* __restrict__ X, long long n, int p, int K, int D,
                          const double* __restrict__ c, const double* __restrict__ P,
                          const double* __restrict__ m, const double* __restrict__ g1,
                          double t_init, double a0, double b0, int max_iter, double tol, int joint,
                          unsigned char* __restrict__ mask, float* __restrict__ stat) {
    long long t = (long long)blockIdx.x * blockDim.x + threadIdx.x;
    if (t >= n) return;
    const float* px = X + 2 * p * t;
    double d[6];
    const double s2 = 1.0 / sqrt(2.0);
    if (p == 3) {
        double hr = px[0], hi = px[1], vr = px[2], vi = px[3], wr = px[4], wi = px[5];
        /* hh = (hr, hi), hv = (vr, vi), vv = (wr, wi) */
        d[0] = (hr + wr) * s2; d[1] = (hi + wi) * s2;
        d[2] = (hr - wr) * s2; d[3] = (hi - wi) * s2;
        d[4] = (2.0 * vr) * s2; d[5] = (2.0 * vi) * s2;
    } else {
        for (int q = 0; q < 2 * p; ++q) d[q] = (double)px[q];
    }
    double span = 0.0;
    for (int a = 0; a < D; ++a) span += d[a] * d[a];
    double g0[VB_KMAX];
    for (int k = 0; k < K; ++k) {
        double q = 0.0;
        for (int a = 0; a < D; ++a) {
            double da = d[a] - m[k * D + a];
            for (int b = 0; b < D; ++b) q += da * P[(k * D + a) * D + b] * (d[b] - m[k * D + b]);
        }
        g0[k] = c[k] - 0.5 * q;
    }
    double ea, ab;
    if (span > t_init) { ea = 1.0; ab = 0.0; } else { ea = 0.0; ab = 1.0; }
    double lam = 0.0, lam0 = 0.0;
    if (joint) {
        double mx0 = g0[0], mx1 = g1[0];
        for (int k = 1; k < K; ++k) { mx0 = fmax(mx0, g0[k]); mx1 = fmax(mx1, g1[k]); }
        double s0 = 0.0, s1 = 0.0;
        for (int k = 0; k < K; ++k) { s0 += exp(g0[k] - mx0); s1 += exp(g1[k] - mx1); }
        lam0 = (mx1 + log(s1)) - (mx0 + log(s0));
    }
    double rho[VB_KMAX];
    for (int it = 0; it < max_iter; ++it) {
        if (!joint) {
            double mx = -1e300;
            for (int k = 0; k < K; ++k) { rho[k] = ab * g0[k] + ea * g1[k]; mx = fmax(mx, rho[k]); }
            double s = 0.0;
            for (int k = 0; k < K; ++k) { rho[k] = exp(rho[k] - mx); s += rho[k]; }
            lam0 = 0.0;
            for (int k = 0; k < K; ++k) lam0 += rho[k] / s * (g1[k] - g0[k]);
        }
        lam = lam0 + vb_digamma(ea + a0) - vb_digamma(b0 + ab);
        double ea_n = vb_expit(lam), ab_n = vb_expit(-lam);
        double dlt = fabs(ea_n - ea);
        bool conv = dlt == 0.0 || dlt <= tol * ea;
        ea = ea_n; ab = ab_n;
        if (conv) break;
    }
    mask[t] = ab <= a0;
    stat[t] = (float)lam;
}

/* apwf: y = K q / det with q = X^H adj(S) X (apwf._pwf / _adj3, same operation order).
 * S: p^2 planes of the window sums over K[t] valid cells (n pixels); X: the core's complex
 * channels, or for covariance input (is_cov) the core's covariance planes, y = K tr(adj(S) C) / det.
 * Against the per-pixel threshold T[t] (+inf: not tested, mask 0, stat 0); where T != thr
 * (K < N) stat = y (thr / T). With no absent cells K = N and T = thr everywhere. */
__global__ void apwf_decide_valid(const double* __restrict__ S, long long n, const float* __restrict__ x,
                                  long long ldx, long long cols, int p, int is_cov,
                                  const double* __restrict__ Cp, const double* __restrict__ K,
                                  const double* __restrict__ T, double thr, float thr32_above,
                                  unsigned char* __restrict__ mask, float* __restrict__ stat) {
    long long t = (long long)blockIdx.x * blockDim.x + threadIdx.x;
    if (t >= n) return;
    double tt = T[t];
    if (!(tt < __longlong_as_double(0x7ff0000000000000LL))) { mask[t] = 0; stat[t] = 0.0f; return; }
    long long i = t / cols, jj = t % cols;
    double q, det;
    bool nz;
    if (p == 3) {
        double a = S[t], d = S[n + t], f = S[2 * n + t];
        cplx b = {S[3 * n + t], S[4 * n + t]}, c = {S[5 * n + t], S[6 * n + t]}, e = {S[7 * n + t], S[8 * n + t]};
        double A11 = d * f - (e.r * e.r + e.i * e.i);
        double A22 = a * f - (c.r * c.r + c.i * c.i);
        double A33 = a * d - (b.r * b.r + b.i * b.i);
        cplx A12 = cs(cm(c, cj(e)), cm(b, cre(f)));
        cplx A13 = cs(cm(b, e), cm(c, cre(d)));
        cplx A23 = cs(cm(cj(b), c), cm(cre(a), e));
        det = a * A11 + cm(b, cj(A12)).r + cm(c, cj(A13)).r;
        if (!is_cov) {
            const float* px = x + 6 * (i * ldx + jj);
            cplx x0 = {(double)px[0], (double)px[1]}, x1 = {(double)px[2], (double)px[3]},
                 x2 = {(double)px[4], (double)px[5]};
            q = (A11 * (x0.r * x0.r + x0.i * x0.i)
                 + A22 * (x1.r * x1.r + x1.i * x1.i)
                 + A33 * (x2.r * x2.r + x2.i * x2.i)
                 + 2.0 * (cm(cm(cj(x0), A12), x1).r
                          + cm(cm(cj(x0), A13), x2).r
                          + cm(cm(cj(x1), A23), x2).r));
            nz = (x0.r != 0.0 || x0.i != 0.0 || x1.r != 0.0 || x1.i != 0.0 || x2.r != 0.0 || x2.i != 0.0);
        } else {
            double c11 = Cp[t], c22 = Cp[n + t], c33 = Cp[2 * n + t];
            cplx c12 = {Cp[3 * n + t], Cp[4 * n + t]}, c13 = {Cp[5 * n + t], Cp[6 * n + t]},
                 c23 = {Cp[7 * n + t], Cp[8 * n + t]};
            q = (A11 * c11 + A22 * c22 + A33 * c33
                 + 2.0 * (cm(A12, cj(c12)).r + cm(A13, cj(c13)).r + cm(A23, cj(c23)).r));
            nz = (c11 != 0.0 || c22 != 0.0 || c33 != 0.0);
        }
    } else {
        double a = S[t], d = S[n + t];
        cplx b = {S[2 * n + t], S[3 * n + t]};
        det = a * d - (b.r * b.r + b.i * b.i);
        if (!is_cov) {
            const float* px = x + 4 * (i * ldx + jj);
            cplx x0 = {(double)px[0], (double)px[1]}, x1 = {(double)px[2], (double)px[3]};
            q = (d * (x0.r * x0.r + x0.i * x0.i)
                 + a * (x1.r * x1.r + x1.i * x1.i)
                 - 2.0 * cm(cm(cj(x0), b), x1).r);
            nz = (x0.r != 0.0 || x0.i != 0.0 || x1.r != 0.0 || x1.i != 0.0);
        } else {
            double c11 = Cp[t], c22 = Cp[n + t];
            cplx c12 = {Cp[2 * n + t], Cp[3 * n + t]};
            q = d * c11 + a * c22 - 2.0 * cm(b, cj(c12)).r;
            nz = (c11 != 0.0 || c22 != 0.0);
        }
    }
    double y;
    if (det > 0.0) y = K[t] * q / det;
    else if (nz) y = __longlong_as_double(0x7ff0000000000000LL);
    else y = 0.0;
    bool m = y > tt;
    if (tt != thr) y = y * (thr / tt);
    float s = (float)y;
    if (m && s < thr32_above) s = thr32_above;
    mask[t] = m;
    stat[t] = s;
}

}  /* extern "C" */
"""

THREADS = 256


@functools.cache
def compiled(source: str, std: str, device_id: int):
    """``source`` compiled by NVRTC for ``device_id`` (once per process and device), without
    fused multiply-adds so the sums match the CPU's bit for bit."""
    import cupy as cp

    return cp.RawModule(code=source, options=("--fmad=false", f"-std={std}"))


def get(name: str, source: str = SOURCE, std: str = "c++14"):
    """The compiled kernel ``name`` of ``source`` (default: this module's) for the current device."""
    import cupy as cp

    return compiled(source, std, cp.cuda.Device().id).get_function(name)


def launch(name: str, n: int, args: tuple, *, source: str = SOURCE, std: str = "c++14", threads: int = THREADS) -> None:
    """Launch ``name`` over ``n`` threads (1-D grid of ``threads``-thread blocks)."""
    if n <= 0:
        return
    blocks = (int(n) + threads - 1) // threads
    get(name, source, std)((blocks,), (threads,), args)
