"""CuPy twin of ``gamma_mrf``'s per-pixel parts: the mixture-MAP initial labels and the ICM
colour phases (:func:`sarship.pipeline.detectors.gamma_mrf.icm`), one CUDA thread a pixel.

Same energies in the same order of operations as the Numba kernel (``a_k + b_k y + beta *
(n_present - n_k)`` in float64, ties to the lower class), compiled without fused multiply-adds
(:mod:`sarship.pipeline.gpu.kernels`), so labels, gaps and masks are bit-identical to the CPU's.
A colour phase only writes pixels of one colour and only reads their neighbours (other
colours), so one launch per phase is race-free and equals the CPU's sequential order.
The EM fit and the scene-pass reduction stay on the host (small). CuPy is imported lazily.
"""

from __future__ import annotations

import numpy as np

from sarship.pipeline.gpu import kernels

SOURCE = r"""
#define GM_INF __longlong_as_double(0x7ff0000000000000LL)
#define INIT_BODY(T)                                                                       \
    long long t = (long long)blockIdx.x * blockDim.x + threadIdx.x;                        \
    if (t >= n) return;                                                                    \
    gap[t] = 0.0;                                                                          \
    if (!ok[t]) { lab[t] = -1; return; }                                                   \
    double v = (double)y[t];                                                               \
    int best = 0; double ebest = GM_INF;                                                \
    for (int k = 0; k < K; ++k) {                                                          \
        double e = a0[k] + b0[k] * v;                                                      \
        if (e < ebest) { ebest = e; best = k; }                                            \
    }                                                                                      \
    lab[t] = (signed char)best;                                                            \
    if (best >= ks) {                                                                      \
        double eo = GM_INF;                                                             \
        for (int k = 0; k < ks; ++k) {                                                  \
            double e = a0[k] + b0[k] * v;                                                  \
            if (e < eo) eo = e;                                                            \
        }                                                                                  \
        gap[t] = eo - ebest;                                                               \
    }

#define PHASE_BODY(T)                                                                      \
    long long t = (long long)blockIdx.x * blockDim.x + threadIdx.x;                        \
    if (t >= (long long)H * W) return;                                                     \
    int i = (int)(t / W), j = (int)(t % W);                                                \
    int gr = (int)((r0 + i) & 1LL), gc = (int)((c0 + j) & 1LL);                            \
    int c = nbh == 4 ? (gr ^ gc) : ((gr << 1) | gc);                                       \
    if (c != col || !ok[t]) return;                                                        \
    int cnt[8];                                                                            \
    for (int k = 0; k < K; ++k) cnt[k] = 0;                                                \
    int npres = 0;                                                                         \
    for (int di = -1; di <= 1; ++di) {                                                     \
        int ii = i + di;                                                                   \
        if (ii < 0 || ii >= H) continue;                                                   \
        for (int dj = -1; dj <= 1; ++dj) {                                                 \
            if (di == 0 && dj == 0) continue;                                              \
            if (nbh == 4 && di != 0 && dj != 0) continue;                                  \
            int jj = j + dj;                                                               \
            long long u = (long long)ii * W + jj;                                          \
            if (jj < 0 || jj >= W || !ok[u]) continue;                                     \
            npres += 1;                                                                    \
            cnt[lab[u]] += 1;                                                              \
        }                                                                                  \
    }                                                                                      \
    double v = (double)y[t];                                                               \
    int best = 0; double ebest = GM_INF, eother = GM_INF;                                  \
    for (int k = 0; k < K; ++k) {                                                          \
        double e = a[k] + b[k] * v + beta * (double)(npres - cnt[k]);                      \
        if (e < ebest) { ebest = e; best = k; }                                            \
        if (k < ks && e < eother) eother = e;                                              \
    }                                                                                      \
    lab[t] = (signed char)best;                                                            \
    gap[t] = best >= ks ? eother - ebest : 0.0;

extern "C" {
__global__ void gm_init_f32(const float* __restrict__ y, const bool* __restrict__ ok, signed char* lab,
                            double* gap, const double* a0, const double* b0, int K, int ks, long long n) { INIT_BODY(float) }
__global__ void gm_init_f64(const double* __restrict__ y, const bool* __restrict__ ok, signed char* lab,
                            double* gap, const double* a0, const double* b0, int K, int ks, long long n) { INIT_BODY(double) }
__global__ void gm_phase_f32(const float* __restrict__ y, const bool* __restrict__ ok, signed char* lab,
                             double* gap, const double* a, const double* b, double beta, int nbh, int K,
                             int ks, int H, int W, long long r0, long long c0, int col) { PHASE_BODY(float) }
__global__ void gm_phase_f64(const double* __restrict__ y, const bool* __restrict__ ok, signed char* lab,
                             double* gap, const double* a, const double* b, double beta, int nbh, int K,
                             int ks, int H, int W, long long r0, long long c0, int col) { PHASE_BODY(double) }
}
"""


def _launch(name: str, n: int, args: tuple) -> None:
    kernels.launch(name, n, args, source=SOURCE)


def icm(y, ok, r0: int, c0: int, a0, b0, A, B, beta: float, nbh: int, ks: int):
    """Device twin of the CPU ``icm``: returns CuPy ``(lab, prev, gap)``."""
    import cupy as cp

    if y.dtype not in (cp.float32, cp.float64):
        y = y.astype(cp.float64)
    y = cp.ascontiguousarray(y)
    ok = cp.ascontiguousarray(ok)
    H, W = y.shape
    sfx = "f32" if y.dtype == cp.float32 else "f64"
    K = int(len(a0))
    lab = cp.empty((H, W), cp.int8)
    gap = cp.empty((H, W), cp.float64)
    n = H * W
    _launch(
        f"gm_init_{sfx}",
        n,
        (
            y,
            ok,
            lab,
            gap,
            cp.asarray(a0, cp.float64),
            cp.asarray(b0, cp.float64),
            np.int32(K),
            np.int32(ks),
            np.int64(n),
        ),
    )
    S = int(A.shape[0])
    ncol = 2 if int(nbh) == 4 else 4
    prev = lab.copy() if S == 0 else None
    for s in range(S):
        if s == S - 1:
            prev = lab.copy()
        a, b = cp.asarray(A[s], cp.float64), cp.asarray(B[s], cp.float64)
        for col in range(ncol):
            _launch(
                f"gm_phase_{sfx}",
                n,
                (
                    y,
                    ok,
                    lab,
                    gap,
                    a,
                    b,
                    np.float64(beta),
                    np.int32(nbh),
                    np.int32(K),
                    np.int32(ks),
                    np.int32(H),
                    np.int32(W),
                    np.int64(r0),
                    np.int64(c0),
                    np.int32(col),
                ),
            )
    return lab, prev, gap


def _present(cp, x, nodata):
    ok = cp.isfinite(x) & (x >= 0)  # NaN >= 0 is False
    if nodata is not None:
        ok &= x != x.dtype.type(nodata)
    return ok


def labels(block, halo_px: int, origin, p, prep: dict):
    """CuPy ``(lab, prev)`` of the block after the sweeps known in ``prep`` (the scene pass)."""
    import cupy as cp

    from sarship.pipeline.detectors.gamma_mrf import energies

    a0, b0, A, B = energies(prep, p)
    lab, prev, _ = icm(
        block,
        _present(cp, block, p.nodata),
        int(origin[0]),
        int(origin[1]),
        a0,
        b0,
        A,
        B,
        float(p.beta),
        int(p.neighbourhood),
        int(prep["ship_from"]),
    )
    return lab, prev


def detect(block, halo_px: int, origin, p, prep: dict):
    """CuPy ``(mask, stat)`` of the core, as the CPU ``detect``."""
    import cupy as cp

    from sarship.pipeline.detectors.gamma_mrf import energies, halo

    hp = int(halo_px)
    if hp < halo(p):
        raise ValueError(f"gamma_mrf needs a halo of {halo(p)} (sweeps x colours), block has {hp}")
    a0, b0, A, B = energies(prep, p)
    ok = _present(cp, block, p.nodata)
    lab, _, gap = icm(
        block,
        ok,
        int(origin[0]),
        int(origin[1]),
        a0,
        b0,
        A,
        B,
        float(p.beta),
        int(p.neighbourhood),
        int(prep["ship_from"]),
    )
    H, W = block.shape
    core = (slice(hp, H - hp), slice(hp, W - hp))
    mask = ok[core] & (lab[core] >= int(prep["ship_from"]))
    if p.scatter == "quantile":
        mask &= block[core].astype(cp.float64) > cp.float64(prep["scatter_threshold"])
    stat = cp.where(mask, gap[core], 0.0).astype(cp.float32)
    tiny = np.nextafter(np.float32(0), np.float32(1))
    stat[mask & (stat <= 0)] = tiny
    return mask, stat
