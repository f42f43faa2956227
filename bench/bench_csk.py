"""``csk`` speed: the detector's kernel on one core against a plain SciPy version of the same
window CSK (``scipy.ndimage.uniform_filter`` on the four moment images), in one run.

``python bench/bench_csk.py [--side 4096] [--window 7]`` (one core: OMP/BLAS threads 1).
Prints Mpx/s of each and their ratio; also the one-off cost of ``prepare`` (the null-law
simulation, once per job on the client).
"""

from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402
from common import best_of, machine  # noqa: E402
from scipy import ndimage  # noqa: E402

from sarship.pipeline.detectors import csk  # noqa: E402
from sarship.pipeline.tiling.windows import mirror_pad  # noqa: E402


def scipy_csk(z: np.ndarray, w: int) -> np.ndarray:
    """The same statistic with uniform_filter (mirror border; not tiling-invariant, no absent pixels)."""
    zr, zi = z.real.astype(np.float64), z.imag.astype(np.float64)
    p = zr * zr + zi * zi
    f = lambda a: ndimage.uniform_filter(a, w, mode="mirror")  # noqa: E731
    m11, m22, mr, mi = f(p), f(p * p), f(zr * zr - zi * zi), f(2 * zr * zi)
    return m22 / (m11 * m11) - 2.0 - (mr * mr + mi * mi) / (m11 * m11)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--side", type=int, default=4096)
    ap.add_argument("--window", type=int, default=7)
    a = ap.parse_args()
    n = a.side
    rng = np.random.default_rng(0)
    z = (
        (rng.standard_normal((n, n), np.float32) + 1j * rng.standard_normal((n, n), np.float32)) * np.float32(0.7071)
    ).astype(np.complex64)
    p = csk.CSKParams(window=a.window)
    t = time.perf_counter()
    prep = csk.prepare(p)
    t_prep = time.perf_counter() - t
    h = a.window // 2
    block = mirror_pad(z, h)
    t_det = best_of(lambda: csk.detect(block, h, (-h, -h), p, prep), repeat=2)
    t_ref = best_of(lambda: scipy_csk(z, a.window), repeat=2)
    k_ref = scipy_csk(z, a.window)
    k_det = csk.csk_window(
        block,
        h,
        (-h, -h),
        a.window,
        None,
        __import__("sarship.pipeline.tiling.boxsum", fromlist=["x"]).centered_box_sum,
        np,
    )[0]
    mpx = n * n / 1e6
    print(f"Machine: {machine()}; {time.strftime('%Y-%m-%d')}; {n}x{n} complex64, window {a.window}, one core")
    print("| what | seconds | Mpx/s |\n|---|---|---|")
    print(
        f"| csk detect (box sums of pipeline/tiling/boxsum.py, decision, float32 stat) | {t_det:.2f} | {mpx / t_det:.1f} |"
    )
    print(f"| SciPy uniform_filter CSK (statistic only) | {t_ref:.2f} | {mpx / t_ref:.1f} |")
    print(f"| ratio SciPy / csk | {t_ref / t_det:.2f}x | |")
    print(
        f"| prepare (null law, n = {a.window**2}, {prep['distribution'].split('(')[1].split(',')[0]}) | {t_prep:.2f} | |"
    )
    print(f"max |CSK difference| vs SciPy: {np.max(np.abs(k_det - k_ref)):.2e}")


if __name__ == "__main__":
    main()
