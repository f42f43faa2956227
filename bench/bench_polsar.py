"""Polarimetric detectors of the thesis (Sun 2020, docs/references.md#sun2020) against its timings.

Quad-pol complex-Gaussian sea clutter (reflection-symmetric covariance, eq 2-3) with ships,
1000 x 1000 (the thesis' scenes) and 4096 x 4096, one core, each detector's pure function on
the whole mirror-extended scene (kernel time), best of 3:

- ``apwf`` with the thesis' 31 x 31 window (``estimator=window``) and with our default ring
  (guard 41, background 61); thesis: C++ CPU 67.4 s, one Titan V 2.1 s, two 1.27 s.
- ``pcdm`` with the thesis' single-look C (``looks_window=1``) and our default 3x3 boxcar;
  thesis: MATLAB 11.4 s, Titan V 0.67 s.
- ``lmm`` / ``vb_polsar`` when registered (thesis LMM: MATLAB 37.5 s, Titan V 1.73 s).

Usage: python bench/bench_polsar.py [--sizes 1000,4096]
"""

from __future__ import annotations

import argparse
import datetime
import time

import numpy as np
from common import best_of, machine  # noqa: E402

from sarship.pipeline import detectors  # noqa: E402
from sarship.pipeline.simulate import SimConfig, simulate_array  # noqa: E402
from sarship.pipeline.tiling.windows import mirror_pad  # noqa: E402

CASES = [
    (
        "apwf",
        {"estimator": "window", "guard": 1, "background": 31, "pfa": 1e-6},
        "thesis 31x31 window",
        "CPU 67.4 s / Titan V 2.1 s",
    ),
    ("apwf", {}, "ring guard 41 / background 61 (default)", "CPU 67.4 s / Titan V 2.1 s"),
    (
        "pcdm",
        {"looks_window": 1, "span_rule": "fraction"},
        "thesis: single-look C, fraction rule",
        "MATLAB 11.4 s / Titan V 0.67 s",
    ),
    ("pcdm", {}, "default: 3x3 boxcar, lognormal rule", "MATLAB 11.4 s / Titan V 0.67 s"),
    ("vb_polsar", {}, "defaults (scene pass included)", "(not timed in the thesis)"),
    ("lmm", {}, "defaults (grid, BIC K' <= 3, predictive tail), |HH|^2", "MATLAB 37.5 s / Titan V 1.73 s"),
]


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--sizes", default="1000,4096")
    a = ap.parse_args()
    print(f"# {datetime.date.today()} {machine()}")
    print(f"{'detector':<10} {'setting':<42} {'size':>6} {'seconds':>8} {'Mpx/s':>7}  thesis (1000x1000)")
    for n in [int(s) for s in a.sizes.split(",")]:
        cfg = SimConfig(kind="quadpol", shape=(n, n), ships=max(4, n // 100), seed=1, clutter="rayleigh", scr_db=10.0)
        arrs, _ = simulate_array(cfg)
        X = np.stack([arrs["hh"], arrs["hv"], arrs["vv"]], -1)
        for name, kw, label, thesis in CASES:
            if name not in detectors.names():
                continue
            spec = detectors.get(name)
            p = spec.params(**kw)
            prep = spec.prepare(p)
            h = spec.halo(p)
            data = X if spec.input == "polarimetric" else (np.abs(X[..., 0]) ** 2).astype(np.float32)
            blk = mirror_pad(data, h)
            if spec.scene_pass is not None:

                def run_all():
                    pr = {**prep, **spec.reduce([spec.scene_pass(blk, h, (-h, -h), p, prep)], p, prep)}
                    return spec.detect(blk, h, (-h, -h), p, pr)
            else:

                def run_all():
                    return spec.detect(blk, h, (-h, -h), p, prep)

            if name == "lmm" and n > 2000:  # one timed call (compiled on the smaller size)
                t0 = time.perf_counter()
                run_all()
                t = time.perf_counter() - t0
            else:
                t = best_of(run_all, 1 if name == "lmm" else 3)
            print(f"{name:<10} {label:<42} {n:>6} {t:8.3f} {n * n / t / 1e6:7.1f}  {thesis}")


if __name__ == "__main__":
    main()
