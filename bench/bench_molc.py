"""``g0_cfar``, ``k_cfar``, ``ggd_cfar`` (issue 13): Mpx/s on one CPU core for a 4096 x 4096 scene,
against ``ca_cfar`` measured in the same run and the MATLAB times of the seed-003 paper
(Liu et al. 2017, docs/references.md#liu2017: "parameter estimation, modelling and threshold"
of G0-CFAR, K-CFAR and GGD-CFAR close to 1 s per ~1500 x 1500 image, i.e. ~2.25 Mpx/s, on an
Intel Core i5 at 3.30 GHz, MATLAB 2016); and on the GPU when CuPy and a device are present.

Each detector runs its public ``detect`` on the whole mirror-extended scene (default windows,
guard 41 / background 81, pfa 1e-3) of its own clutter model (i.i.d. G0 a = 3 / K nu = 2 /
GGD v = 0.7 kappa = 3, L = 2). CPU: one thread (``NUMBA_NUM_THREADS`` / ``OMP_NUM_THREADS``
set to 1 before the imports), best of ``--repeat`` after one warm-up, timed both as wall
time and as the process's CPU time (``time.process_time``: on a shared, oversubscribed
machine the wall time includes waiting for a core, the CPU time does not); Mpx/s are from
the CPU time. The per-(pfa, L) table is built once per process (``prepare``), timed apart
(CPU time too). GPU: the CuPy block
already on the device, CUDA events, median of 5 after 2 warm-ups, then the false-alarm counts
of both devices.

Usage: python bench/bench_molc.py [--size 4096] [--repeat 2] [--censor C]
"""

from __future__ import annotations

import os

for _v in ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import datetime  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402
from common import machine  # noqa: E402

from sarship.pipeline import detectors  # noqa: E402
from sarship.pipeline.gpu import available  # noqa: E402
from sarship.pipeline.stats import molc  # noqa: E402
from sarship.pipeline.tiling.windows import mirror_pad  # noqa: E402

L = 2.0
PAPER_MPX_S = 1500 * 1500 / 1.0 / 1e6  # ~1 s per ~1500^2 image (MATLAB, Core i5 3.3 GHz)


def clutter(det: str, n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    if det == "g0_cfar":
        x = 2.0 * rng.gamma(L, 1 / L, (n, n)) / rng.gamma(3.0, 1.0, (n, n))
    elif det == "k_cfar":
        x = rng.gamma(2.0, 0.5, (n, n)) * rng.gamma(L, 1 / L, (n, n))
    elif det == "ggd_cfar":
        x = (rng.gamma(3.0, 1.0, (n, n)) / 3.0) ** (1 / 0.7)
    else:
        x = rng.gamma(L, 1 / L, (n, n))
    return x.astype(np.float32)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--size", type=int, default=4096)
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--censor", type=float, default=None, help="also time with bright-pixel censoring")
    a = ap.parse_args()
    n = a.size
    print(f"{datetime.date.today()}  {machine()}  scene {n} x {n} ({n * n / 1e6:.1f} Mpx), one CPU thread")
    print(f"paper (MATLAB, Core i5 3.3 GHz): ~{PAPER_MPX_S:.2f} Mpx/s (~1 s per ~1500^2 image)")
    rows = []
    cases = [("ca_cfar", {}), ("g0_cfar", {}), ("k_cfar", {}), ("ggd_cfar", {})]
    if a.censor is not None:
        cases += [(d, {"censor": a.censor}) for d in ("g0_cfar", "k_cfar", "ggd_cfar")]
    gpu = available()
    ref = None
    print(
        f"{'detector':<22}{'table s':>9}{'wall s':>9}{'CPU s':>9}{'Mpx/s':>9}{'x ca_cfar':>11}{'x paper':>9}{'alarms':>9}"
        + (f"{'GPU ms':>9}{'GPU Mpx/s':>11}{'GPU alarms':>12}" if gpu else "")
    )
    for det, extra in cases:
        spec = detectors.get(det)
        p = spec.params(looks=L, pfa=1e-3, **extra)
        h = spec.halo(p)
        blk = mirror_pad(clutter(det, n), h)
        t0 = time.perf_counter()
        prep = spec.prepare(p)
        t_tab = time.perf_counter() - t0
        if det != "ca_cfar":  # the table alone (prepare builds it; clear and rebuild to time it)
            for f in (molc.g0_table, molc.k_table, molc.ggd_table):
                f.cache_clear()
            t0 = time.process_time()
            prep = spec.prepare(p)
            t_tab = time.process_time() - t0
        out = {}

        def run():
            out["m"] = spec.detect(blk, h, (-h, -h), p, prep)[0]

        run()
        t, wall = float("inf"), float("inf")
        for _ in range(a.repeat):
            c0, w0 = time.process_time(), time.perf_counter()
            run()
            t, wall = min(t, time.process_time() - c0), min(wall, time.perf_counter() - w0)
        mpx = n * n / t / 1e6
        if det == "ca_cfar":
            ref = mpx
        name = det + (f" censor={extra['censor']:g}" if extra else "")
        line = (
            f"{name:<22}{t_tab:>9.2f}{wall:>9.2f}{t:>9.2f}{mpx:>9.2f}{mpx / ref:>11.2f}{mpx / PAPER_MPX_S:>9.2f}"
            f"{int(out['m'].sum()):>9d}"
        )
        if gpu:
            import cupy

            dblk = cupy.asarray(blk)
            for _ in range(2):
                spec.detect(dblk, h, (-h, -h), p, prep)
            times = []
            for _ in range(5):
                e0, e1 = cupy.cuda.Event(), cupy.cuda.Event()
                e0.record()
                mg, _ = spec.detect(dblk, h, (-h, -h), p, prep)
                e1.record()
                e1.synchronize()
                times.append(cupy.cuda.get_elapsed_time(e0, e1))
            ms = float(np.median(times))
            line += f"{ms:>9.1f}{n * n / (ms / 1e3) / 1e6:>11.0f}{int(mg.sum()):>12d}"
        rows.append(line)
        print(line, flush=True)


if __name__ == "__main__":
    main()
