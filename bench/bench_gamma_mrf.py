"""``gamma_mrf`` speed: the mixture fit (EM) and the ICM on one core, beside the paper's MATLAB times.

Liu et al. 2017 (docs/references.md, [liu2017]) section 4: on ~1500 x 1500 images (2.25 Mpx),
MATLAB 2016 on a Core i5 at 3.3 GHz, the mixture fit took ~3 s (0.75 Mpx/s) and the ICM ~14 s
(0.16 Mpx/s). Here, on a two-class gamma sea with ships (``--side`` squared, default 4096^2):

- mixture: the scene pass's grid sample (``sample_stride``) and EM on it;
- ICM: one ``detect`` of the whole scene (mixture-MAP labels + ``sweeps`` colour-phase sweeps);
- the whole classification with the per-sweep re-estimation (every scene pass + detect);
- references measured in the same run: plain NumPy EM iterations and one NumPy ICM sweep
  (vectorised over a colour), the speed a straightforward array implementation gets;
- the CuPy twin when a GPU is present (``detect`` on a device block).

Times are wall and CPU (this thread), one core (Numba kernels are single-threaded; set
``OMP_NUM_THREADS=1`` for the NumPy references). ``python bench/bench_gamma_mrf.py [--side N]``.
"""

from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("MKL_NUM_THREADS", "1")

import numpy as np  # noqa: E402
from common import machine  # noqa: E402

from sarship.pipeline import detectors  # noqa: E402
from sarship.pipeline.detectors import gamma_mrf as gm  # noqa: E402
from sarship.pipeline.tiling.windows import mirror_pad  # noqa: E402

PAPER = {"mixture_s": 3.0, "icm_s": 14.0, "px": 1500 * 1500}


def timed(fn):
    t, c = time.perf_counter(), time.thread_time()
    out = fn()
    return out, time.perf_counter() - t, time.thread_time() - c


def scene(side: int, L: float, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    z = rng.random((side, side)) < 0.7
    x = np.where(z, rng.gamma(L, 1 / L, (side, side)), rng.gamma(L, 3 / L, (side, side))).astype(np.float32)
    for _ in range(side // 64):
        r, c = rng.integers(0, side - 12, 2)
        x[r : r + 12, c : c + 4] = rng.gamma(L, 40 / L, (12, 4))
    return x


def numpy_em(y: np.ndarray, L: float, w: np.ndarray, mu: np.ndarray, iters: int) -> None:
    """The textbook vectorised EM iteration (responsibilities as an (n, K) array)."""
    for _ in range(iters):
        lj = np.log(w)[None] - L * np.log(mu)[None] - L * y[:, None] / mu[None]
        m = lj.max(1, keepdims=True)
        e = np.exp(lj - m)
        tau = e / e.sum(1, keepdims=True)
        nk = tau.sum(0)
        w, mu = nk / y.size, (tau * y[:, None]).sum(0) / nk


def numpy_sweep(y: np.ndarray, lab: np.ndarray, a: np.ndarray, b: np.ndarray, beta: float) -> np.ndarray:
    """One 8-neighbourhood ICM sweep in NumPy: four colour phases, each vectorised (counts of
    neighbour labels by shifted comparisons, energies as a (H, W, K) array)."""
    H, W = y.shape
    K = len(a)
    unary = a[None, None] + b[None, None] * y[..., None]
    rr, cc = np.meshgrid(np.arange(H) & 1, np.arange(W) & 1, indexing="ij")
    colour = rr * 2 + cc
    for col in range(4):
        cnt = np.zeros((H, W, K), np.int16)
        for di in (-1, 0, 1):
            for dj in (-1, 0, 1):
                if di == 0 and dj == 0:
                    continue
                sh = np.full((H, W), -1, np.int8)
                sh[max(-di, 0) : H + min(-di, 0), max(-dj, 0) : W + min(-dj, 0)] = lab[
                    max(di, 0) : H + min(di, 0), max(dj, 0) : W + min(dj, 0)
                ]
                for k in range(K):
                    cnt[..., k] += sh == k
        n = cnt.sum(-1, keepdims=True)
        new = np.argmin(unary + beta * (n - cnt), -1).astype(np.int8)
        sel = colour == col
        lab[sel] = new[sel]
    return lab


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--side", type=int, default=4096)
    ap.add_argument("--looks", type=float, default=4.0)
    ap.add_argument("--ref-side", type=int, default=1024, help="side of the NumPy ICM reference block")
    a = ap.parse_args()
    spec = detectors.get("gamma_mrf")
    x = scene(a.side, a.looks)
    Mpx = x.size / 1e6
    p = spec.params(looks=a.looks)
    h = spec.halo(p)
    P = mirror_pad(x, h)
    print(f"# gamma_mrf bench, {a.side}^2 = {Mpx:.1f} Mpx, L = {a.looks:g}; {machine()}")
    print(
        f"# defaults: K {p.classes}, beta {p.beta:g}, {p.neighbourhood}-neighbourhood, {p.sweeps} sweeps, "
        f"sample_stride {p.sample_stride}, reestimate {p.reestimate}"
    )
    small = spec.params(looks=a.looks, sweeps=2)  # compile every kernel on a small block first
    hs = spec.halo(small)
    spx = mirror_pad(x[:256, :256], hs)
    pr = spec.prepare(small)
    while True:
        v = spec.reduce([spec.scene_pass(spx, hs, (-hs, -hs), small, pr)], small, pr)
        again = v.pop(gm.ANOTHER_PASS, False)
        pr.update(v)
        if not again:
            break
    spec.detect(spx, hs, (-hs, -hs), small, pr)
    prep0 = spec.prepare(p)

    part, tw_s, tc_s = timed(lambda: spec.scene_pass(P, h, (-h, -h), p, prep0))
    vals, tw_em, tc_em = timed(lambda: spec.reduce([part], p, prep0))
    vals.pop(gm.ANOTHER_PASS, None)
    mix = vals["mixture"]
    n = part["y"].size
    print(
        f"mixture: sample {n} px {tw_s:.2f} s wall; EM {mix['iterations']} iterations {tw_em:.2f} s wall "
        f"{tc_em:.2f} s CPU ({tc_em / mix['iterations'] * 1e3:.1f} ms/iteration); "
        f"{Mpx / (tc_s + tc_em):.2f} Mpx/s of scene (CPU); paper: {PAPER['mixture_s']} s on 2.25 Mpx = "
        f"{PAPER['px'] / 1e6 / PAPER['mixture_s']:.2f} Mpx/s"
    )
    w0, mu0 = np.asarray(mix["weights"]), np.asarray(mix["means"])
    _, _, tc_ref = timed(lambda: numpy_em(part["y"], a.looks, w0, mu0, 10))
    print(
        f"  reference NumPy EM: {tc_ref / 10 * 1e3:.1f} ms/iteration CPU "
        f"(Numba {tc_em / mix['iterations'] * 1e3:.1f} ms: x{tc_ref / 10 / (tc_em / mix['iterations']):.1f})"
    )

    # the whole classification: every re-estimation pass on the whole scene, then detect
    prep = {**prep0, **vals}
    t_all, c_all = time.perf_counter(), time.thread_time() - tc_em
    passes = []
    while True:
        part2, tw, _ = timed(lambda: spec.scene_pass(P, h, (-h, -h), p, prep))
        v = spec.reduce([part2], p, prep)
        again = v.pop(gm.ANOTHER_PASS, False)
        prep = {**prep, **v}
        passes.append(tw)
        if not again:
            break
    (mask, _), tw_icm, tc_icm = timed(lambda: spec.detect(P, h, (-h, -h), p, prep))
    t_all = time.perf_counter() - t_all + tw_em
    c_all = time.thread_time() - c_all
    sweeps = len(prep["sweep_means"])
    print(
        f"ICM: detect ({sweeps} sweeps + initial labels) {tw_icm:.2f} s wall {tc_icm:.2f} s CPU = "
        f"{Mpx / tc_icm:.2f} Mpx/s (CPU; {Mpx * sweeps / tc_icm:.1f} Mpx-sweeps/s); paper: {PAPER['icm_s']} s on "
        f"2.25 Mpx = {PAPER['px'] / 1e6 / PAPER['icm_s']:.2f} Mpx/s"
    )
    print(
        f"  whole classification (EM, {len(passes)} re-estimation passes of 0..{sweeps - 1} sweeps, detect): "
        f"{t_all:.2f} s wall {c_all:.2f} s CPU = {Mpx / c_all:.2f} Mpx/s (CPU); without the re-estimation "
        f"(reestimate=false): EM + one detect, {tc_em + tc_icm:.2f} s CPU = {Mpx / (tc_em + tc_icm):.2f} Mpx/s"
    )
    print(f"  detected {int(mask.sum())} px")
    r = min(a.ref_side, a.side)
    xs = x[:r, :r].astype(np.float64)
    A, B = gm.energies(prep, p)[2:]
    lab0 = np.where(
        np.isfinite(xs),
        np.argmin(gm.energies(prep, p)[0][None, None] + gm.energies(prep, p)[1][None, None] * xs[..., None], -1),
        -1,
    )
    lab0 = lab0.astype(np.int8)
    _, _, tw_np = timed(lambda: numpy_sweep(xs, lab0.copy(), A[0], B[0], p.beta))
    one = tc_icm / (sweeps + 1) / Mpx  # CPU s per Mpx-sweep, Numba (initial labels counted as a sweep)
    print(
        f"  reference NumPy sweep on {r}^2: {r * r / 1e6 / tw_np:.2f} Mpx/s CPU (Numba ~{1 / one:.1f} Mpx/s a "
        f"sweep: x{tw_np / (r * r / 1e6) / one:.1f})"
    )
    try:
        import cupy as cp

        from sarship.pipeline.gpu import available

        if not available():
            raise ImportError
        Pd = cp.asarray(P)
        spec.detect(Pd, h, (-h, -h), p, prep)
        cp.cuda.Device().synchronize()
        t = time.perf_counter()
        mg, _ = spec.detect(Pd, h, (-h, -h), p, prep)
        cp.cuda.Device().synchronize()
        tg = time.perf_counter() - t
        print(
            f"GPU ICM (detect on a device block): {tg:.3f} s = {Mpx / tg:.0f} Mpx/s; mask equal to the CPU's: "
            f"{bool((mg.get() == mask).all())}"
        )
    except ImportError:
        print("GPU: skipped (no CuPy / CUDA device)")


if __name__ == "__main__":
    main()
