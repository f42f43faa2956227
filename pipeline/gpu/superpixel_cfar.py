"""CuPy twin of ``superpixel_cfar``'s per-pixel steps (:mod:`sarship.pipeline.detectors.superpixel_cfar`).

Zhang et al. 2023 (docs/references.md, ``zhang2023``); docs/algorithms/superpixel_cfar.md, "GPU".

Where each step runs, for a CuPy block:

* host (the block is copied to the host once): steps 1-5, :func:`superpixel_cfar.host_steps`:
  the bounded DBSCAN growth and the merge (eq 7-10), shadow and K-means classes, Table 1's
  clutter sets, the Rayleigh-mixture EM (eq 3-6) and ``T_cfar`` (eq 14), and eq 11's sum of
  dissimilarities per target superpixel. They are sequential per seed or per superpixel
  (breadth-first growth, queue-driven Table 1 search, an EM loop per superpixel on a few
  hundred to a few thousand pixels) and produce per-superpixel scalars: nothing there maps to
  one thread a pixel.
* device: step 6 and 7. The amplitude ``A = sqrt(I)``, the 7x7 window sums of ``A``, ``A^2``
  and the present pixels (:func:`sarship.pipeline.gpu.box.centered_box_sum`: the CPU's
  additions in the CPU's order, bit-identical and tiling-invariant), the coefficient of
  variation (eq 13), ``zeta = exp(-CoV / kappa)`` (eq 12), eq 16's ``A zeta sum(Omega) >
  T_cfar`` with ``T_cfar`` and ``sum(Omega)`` gathered by the pixel's superpixel label, the
  ratio ``A C_local / T_cfar``, the detected count per superpixel (``cupy.bincount``), the
  fraction and the superpixel decision (step 7) gathered back to the pixels.

Equality with the CPU path. The kernel runs the CPU's float64 operations in the CPU's order,
compiled without fused multiply-adds (:mod:`sarship.pipeline.gpu.kernels`); the CoV is then
bit-identical (IEEE division and square root). CUDA's ``exp`` may differ from NumPy's in the
last bit, so the product of eq 16 may differ by a few ulps: every pixel whose product lies
within ``TIE_REL`` (relative) of its ``T_cfar`` is recomputed on the host with NumPy's ``exp``
and the CPU's operations (none or a handful per block). Masks, eq 16's pixel decisions and
the detected fractions are therefore identical to the CPU's, bit for bit; the statistic is
bit-identical for ``decision="superpixel"`` (the fraction, a ratio of integers) and within one
float32 rounding (relative 1.2e-7) for ``decision="pixel"`` (``A C_local / T_cfar``).
CuPy is imported lazily.
"""

from __future__ import annotations

import numpy as np

from sarship.pipeline.gpu import kernels

#: Pixels whose eq 16 product is within this relative distance of ``T_cfar`` are decided on the
#: host (the products of the two paths differ by a few ulps, about 1e-15 relative, at most).
TIE_REL = 1e-12

SOURCE = r"""
/* A = sqrt(I) in the block's precision (the CPU's np.sqrt on float32 or float64, IEEE correctly
 * rounded), widened to float64 (exact), 0 where absent; and the present pixels as 1.0 / 0.0. */
#define SPC_AMP_BODY(SQRT)                                                                   \
    long long t = (long long)blockIdx.x * blockDim.x + threadIdx.x;                          \
    if (t >= n) return;                                                                      \
    amp[t] = ok[t] ? (double)SQRT(x[t]) : 0.0;                                               \
    okf[t] = ok[t] ? 1.0 : 0.0;

extern "C" {
__global__ void spc_amp_f32(const float* __restrict__ x, const bool* __restrict__ ok, double* amp, double* okf,
                            long long n) {
    SPC_AMP_BODY(sqrtf)
}
__global__ void spc_amp_f64(const double* __restrict__ x, const bool* __restrict__ ok, double* amp, double* okf,
                            long long n) {
    SPC_AMP_BODY(sqrt)
}

/* eq 13, 12, 16 for the pixels of decided superpixels (labels from the host). s1, s2, cnt: the
 * side x side window sums of A, A^2 and the present pixels on the block less r = side // 2 each
 * side (row length W - 2r); the CoV as superpixels._mean_cov, NaN within r of the block edge. */
__global__ void spc_decide(const double* __restrict__ amp, const int* __restrict__ lab,
                           const bool* __restrict__ decided, const double* __restrict__ thr,
                           const double* __restrict__ somega, const double* __restrict__ s1,
                           const double* __restrict__ s2, const double* __restrict__ cnt,
                           int H, int W, int r, int use_contrast, double kappa, double tie,
                           bool* det, double* ratio, double* cvout, bool* tie_px) {
    long long t = (long long)blockIdx.x * blockDim.x + threadIdx.x;
    if (t >= (long long)H * W) return;
    det[t] = false;
    ratio[t] = 0.0;
    tie_px[t] = false;
    int l = lab[t];
    if (l < 0 || !decided[l]) return;
    double a = amp[t];
    double v;
    if (use_contrast) {
        int i = (int)(t / W), j = (int)(t % W);
        double cv = __longlong_as_double(0x7ff8000000000000LL);
        if (i >= r && i < H - r && j >= r && j < W - r) {
            long long u = (long long)(i - r) * (W - 2 * r) + (j - r);
            double k = cnt[u];
            if (k > 0) {
                double m = s1[u] / k;
                double var = s2[u] / k - m * m;
                cv = (m > 0.0 && var > 0.0) ? sqrt(var) / m : 0.0;
            }
        }
        cvout[t] = cv;
        double z = exp(-cv / kappa);
        v = a * z * somega[l];
    } else {
        v = a;
    }
    double T = thr[l];
    det[t] = v > T;
    ratio[t] = T > 0 ? v / T : (v > 0 ? __longlong_as_double(0x7ff0000000000000LL) : 0.0);
    if (use_contrast && fabs(v - T) <= tie * fabs(T)) tie_px[t] = true;
}
}
"""


def _launch(name: str, n: int, args: tuple) -> None:
    kernels.launch(name, n, args, source=SOURCE)


def device_block(block):
    """The CuPy block as float32/float64, C-contiguous (the CPU's ``float_block``)."""
    import cupy as cp

    if block.ndim != 2:
        raise ValueError(f"block must be 2-D, got shape {block.shape}")
    if block.dtype != cp.float32 and block.dtype != cp.float64:
        block = block.astype(cp.float64)
    return cp.ascontiguousarray(block)


def pixel_steps(xd, res: dict, origin, p) -> dict:
    """Steps 6-7 on the device for the CuPy block ``xd`` (:func:`device_block`) and the host
    steps' result ``res`` (:func:`superpixel_cfar.host_steps` of the same block): CuPy block
    arrays ``pixel_det`` and ``ratio`` and the per-superpixel ``frac``, equal to the CPU's
    :func:`superpixel_cfar.analyse` (module docstring)."""
    import cupy as cp

    from sarship.pipeline.gpu.box import centered_box_sum

    H, W = xd.shape
    n = H * W
    amp = cp.empty((H, W), cp.float64)
    okf = cp.empty((H, W), cp.float64)
    ok = cp.isfinite(xd) & (xd >= 0)  # the CPU's _present (NaN >= 0 is False)
    _launch("spc_amp_f32" if xd.dtype == cp.float32 else "spc_amp_f64", n, (xd, ok, amp, okf, np.int64(n)))
    sp = res["sp"]
    nl = int(sp.size.size)
    lab = cp.asarray(sp.labels.astype(np.int32))
    use_contrast = p.contrast == "paper"
    side = int(p.cov_window)
    r = side // 2
    org = (int(origin[0]), int(origin[1]))
    if use_contrast and H > 2 * r and W > 2 * r:
        s1 = centered_box_sum(amp, side, r, org)
        s2 = centered_box_sum(amp * amp, side, r, org)
        cnt = centered_box_sum(okf, side, r, org)
    else:  # no contrast, or no interior pixel: the CoV is never read (or NaN everywhere)
        s1 = s2 = cnt = cp.zeros(1, cp.float64)
        r = max(H, W)
    decided = cp.asarray(res["decided"])
    thr = cp.asarray(res["threshold"])
    somega = cp.asarray(res["somega"])
    det = cp.empty((H, W), cp.bool_)
    ratio = cp.empty((H, W), cp.float64)
    cv = cp.empty((H, W), cp.float64)
    near = cp.empty((H, W), cp.bool_)
    if nl:
        _launch(
            "spc_decide",
            n,
            (
                amp,
                lab,
                decided,
                thr,
                somega,
                s1,
                s2,
                cnt,
                np.int32(H),
                np.int32(W),
                np.int32(r),
                np.int32(use_contrast),
                np.float64(p.kappa),
                np.float64(TIE_REL),
                det,
                ratio,
                cv,
                near,
            ),
        )
    else:
        det[...] = False
        ratio[...] = 0.0
        near[...] = False
    idx = cp.flatnonzero(near)
    if idx.size:  # near-ties: eq 12 and 16 with NumPy's exp and the CPU's operations
        ih = idx.get()
        lh = sp.labels.ravel()[ih]
        cvh = cv.ravel()[idx].get()
        ah = amp.ravel()[idx].get()
        z = np.exp(-cvh / p.kappa)
        v = ah * z * res["somega"][lh]
        T = res["threshold"][lh]
        with np.errstate(divide="ignore", invalid="ignore"):
            rt = np.where(T > 0, v / np.where(T > 0, T, 1.0), np.where(v > 0, np.inf, 0.0))
        det.ravel()[idx] = cp.asarray(v > T)
        ratio.ravel()[idx] = cp.asarray(rt)
    if nl:
        sel = lab.ravel()[det.ravel()]
        hits = cp.bincount(sel, minlength=nl) if sel.size else cp.zeros(nl, cp.int64)
        npx = cp.asarray(np.diff(res["pix_ptr"]).astype(np.float64))
        frac = cp.where(decided, hits.astype(cp.float64) / cp.maximum(npx, 1.0), 0.0)
    else:
        frac = cp.zeros(0, cp.float64)
    return {"pixel_det": det, "ratio": ratio, "frac": frac, "labels": lab, "near_ties": int(idx.size)}


def detect(block, halo_px: int, origin, p, prep: dict):
    """CuPy ``(mask, stat)`` of the core of a CuPy ``block``, equal to the CPU ``detect``
    (module docstring): steps 1-5 on a host copy of the block, 6-7 on the device."""
    import cupy as cp

    from sarship.pipeline.detectors import superpixel_cfar as D

    xd = device_block(block)
    hp = int(halo_px)
    x = D._check(cp.asnumpy(xd), halo_px, p)
    if p.decision == "boundaries":  # a debugging view of the host segmentation
        mask, stat = D.detect(x, halo_px, origin, p, prep)
        return cp.asarray(mask), cp.asarray(stat)
    res = D.host_steps(x, halo_px, origin, p, prep)
    dev = pixel_steps(xd, res, origin, p)
    core = (slice(hp, xd.shape[0] - hp), slice(hp, xd.shape[1] - hp))
    if p.decision == "pixel":
        mask = dev["pixel_det"][core].copy()
        return mask, D._above(dev["ratio"][core], mask, 1.0)
    lab = dev["labels"][core]
    if res["sp"].size.size == 0:  # nothing present
        return cp.zeros(lab.shape, cp.bool_), cp.zeros(lab.shape, cp.float32)
    # the point targets (small ships) are host arrays of host_steps: the CPU's, bit for bit
    return D.superpixel_mask(
        lab,
        dev["frac"],
        cp.asarray(res["target"]),
        cp.asarray(D._core(res["point"], hp)),
        cp.asarray(D._core(res["point_ratio"], hp)),
        p,
    )
