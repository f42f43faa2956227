"""CGGD shape estimation: Novey's ML (eq 32-34) vs the CSK route (eq 37, eq 39 inverted), seed 004 fig 12-13.

The paper's experiment (Leng et al. 2020, docs/references.md#leng2020, section 4.3.2): beta from
0.1 to 4 in steps of 0.1, 100 samples of each size N in {500, 1500, 5000, 50000} per beta, C drawn
at random each time; MSE of the estimated beta (fig 12) and the mean time of one estimate
(fig 13: Novey 8.3e-2 s vs CSK 1.5e-3 s at N = 500, 55x; 6.3 s vs 4.5e-3 s at N = 50 000,
1400x; MATLAB, machine not given). Here, in one run on this machine, for each N:

- bias and RMSE of beta for Novey's ML (:func:`sarship.pipeline.stats.cggd.beta_novey`), the CSK route
  with the paper's 1e-3 table (``method="table"``), with the exact inversion (``"exact"``), and
  the exact inversion after whitening (``whiten_first=True``);
- two settings of C: circular (tau = 0, s2 = 10^U(-1, 1): eq 39's assumption) and non-circular
  (|tau| / s2 ~ U(0, 0.9), random phase): the paper says only "C random";
- CPU time of one estimate (this thread, ``time.thread_time``), mean over the run, and the
  ratio Novey / CSK(table), the paper's speed comparison.

``python bench/bench_cggd.py [--reps 10] [--sizes 500,1500,5000,50000]`` (one core; prints
Markdown for bench/RESULTS.md).
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

from sarship.pipeline.stats import cggd  # noqa: E402

PAPER_S = {500: (8.3e-2, 1.5e-3), 50_000: (6.3, 4.5e-3)}
METHODS = ("novey", "csk_table", "csk_exact", "csk_white")


def estimate(method: str, z: np.ndarray) -> float:
    if method == "novey":
        return cggd.beta_novey(z).beta
    if method == "csk_table":
        return cggd.beta_csk(z, method="table")
    if method == "csk_exact":
        return cggd.beta_csk(z, method="exact")
    return cggd.beta_csk(z, method="exact", whiten_first=True)


def random_c(rng: np.random.Generator, circular: bool) -> np.ndarray:
    s2 = 10.0 ** rng.uniform(-1.0, 1.0)
    tau = 0.0 if circular else s2 * rng.uniform(0.0, 0.9) * np.exp(2j * np.pi * rng.random())
    return cggd.augmented_covariance(s2, tau)


def run(sizes: list[int], reps: int, betas: np.ndarray, seed: int) -> dict:
    rng = np.random.default_rng(seed)
    out: dict = {}
    for circular in (True, False):
        for n in sizes:
            err = {m: [] for m in METHODS}
            cpu = {m: 0.0 for m in METHODS}
            count = 0
            for b in betas:
                for _ in range(reps):
                    z = cggd.sample(float(b), random_c(rng, circular), n, rng)
                    for m in METHODS:
                        t = time.thread_time()
                        e = estimate(m, z)
                        cpu[m] += time.thread_time() - t
                        err[m].append((float(b), e - float(b)))
                    count += 1
            out[(circular, n)] = {
                "err": {m: np.array(v) for m, v in err.items()},
                "sec": {m: cpu[m] / count for m in METHODS},
            }
    return out


def report(res: dict, sizes: list[int], reps: int, betas: np.ndarray) -> str:
    lines = [
        f"Machine: {machine()}; {time.strftime('%Y-%m-%d')}; beta {betas[0]:.1f}..{betas[-1]:.1f} "
        f"step 0.1, {reps} samples per beta and N (the paper: 100).",
        "",
    ]
    for circular in (True, False):
        lines += [
            f"**C {'circular (tau = 0)' if circular else 'non-circular (|tau|/s2 ~ U(0, 0.9))'}**: "
            "bias / RMSE of beta over all beta (and RMSE for beta <= 2.5 | > 2.5)",
            "",
            "| N | " + " | ".join(METHODS) + " |",
            "|---|" + "---|" * len(METHODS),
        ]
        for n in sizes:
            cells = []
            for m in METHODS:
                a = res[(circular, n)]["err"][m]
                lo, hi = a[a[:, 0] <= 2.5, 1], a[a[:, 0] > 2.5, 1]
                cells.append(
                    f"{a[:, 1].mean():+.3f} / {np.sqrt(np.mean(a[:, 1] ** 2)):.3f} "
                    f"({np.sqrt(np.mean(lo**2)):.3f} \\| {np.sqrt(np.mean(hi**2)):.3f})"
                )
            lines.append(f"| {n} | " + " | ".join(cells) + " |")
        lines.append("")
    lines += [
        "CPU time of one estimate (mean over both settings; one core) and the speed ratio:",
        "",
        "| N | Novey (s) | CSK table (s) | CSK exact (s) | CSK whitened (s) | Novey / CSK table | paper |",
        "|---|---|---|---|---|---|---|",
    ]
    for n in sizes:
        s = {m: 0.5 * (res[(True, n)]["sec"][m] + res[(False, n)]["sec"][m]) for m in METHODS}
        paper = (
            f"{PAPER_S[n][0]:.2g} s / {PAPER_S[n][1]:.2g} s = {PAPER_S[n][0] / PAPER_S[n][1]:.0f}x"
            if n in PAPER_S
            else ""
        )
        lines.append(
            f"| {n} | {s['novey']:.3g} | {s['csk_table']:.3g} | {s['csk_exact']:.3g} | {s['csk_white']:.3g} "
            f"| {s['novey'] / s['csk_table']:.0f}x | {paper} |"
        )
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reps", type=int, default=10)
    ap.add_argument("--sizes", default="500,1500,5000,50000")
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    sizes = [int(s) for s in a.sizes.split(",")]
    betas = np.round(np.arange(1, 41) * 0.1, 1)
    cggd.csk_table()  # built once, as the paper's table is (not timed)
    res = run(sizes, a.reps, betas, a.seed)
    print(report(res, sizes, a.reps, betas))


if __name__ == "__main__":
    main()
