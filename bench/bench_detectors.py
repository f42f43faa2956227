"""Detector throughput on a 4096x4096 scene, against NumPy/SciPy references and copyto.

Prints, per detector, Mpx/s of
- ``kernel 1 core``: the detector's pure function over 2048-pixel tiles with halo, one process;
- ``dask run``: ``sarship detect`` end to end from a Zarr scene on a local Dask cluster
  (one worker process per core, mask + detections written);
- ``reference``: a straightforward NumPy/SciPy implementation of the same detector
  (``scipy.ndimage.uniform_filter`` window means; ``percentile_filter`` for OS-CFAR, timed on
  a 512x512 crop because it is too slow for the whole scene);
and the memory-bandwidth bound, ``numpy.copyto`` of the same float32 array (one core).

Usage: python bench/bench_detectors.py [--side 4096] [--detectors ca_cfar,two_parameter,os_cfar]
"""

from __future__ import annotations

import argparse
import datetime
import logging
import os
import tempfile
import time

import numpy as np
from common import best_of, machine  # noqa: E402
from scipy import ndimage

from sarship.pipeline import detectors  # noqa: E402
from sarship.pipeline.tiling.windows import padded_block  # noqa: E402


def ref_ca(x, p, prep):
    b, g = p.background, p.guard
    sb = ndimage.uniform_filter(x.astype(np.float64), b, mode="mirror") * b * b
    sg = ndimage.uniform_filter(x.astype(np.float64), g, mode="mirror") * g * g
    return x > prep["threshold"] * (sb - sg) / p.n_ring


def ref_two(x, p, prep):
    b, g = p.background, p.guard
    x = x.astype(np.float64)
    s1 = ndimage.uniform_filter(x, b, mode="mirror") * b * b - ndimage.uniform_filter(x, g, mode="mirror") * g * g
    s2 = (
        ndimage.uniform_filter(x * x, b, mode="mirror") * b * b
        - ndimage.uniform_filter(x * x, g, mode="mirror") * g * g
    )
    mu = s1 / p.n_ring
    sd = np.sqrt(np.maximum((s2 - s1 * mu) / (p.n_ring - 1), 0))
    return x > mu + prep["threshold"] * sd


def ref_os(x, p, prep):
    fp = np.ones((p.background, p.background), bool)
    o = (p.background - p.guard) // 2
    fp[o : o + p.guard, o : o + p.guard] = False
    return x > prep["alpha"] * ndimage.rank_filter(x, int(prep["k"]) - 1, footprint=fp, mode="mirror")


REFS = {"ca_cfar": (ref_ca, None), "two_parameter": (ref_two, None), "os_cfar": (ref_os, 512)}


def kernel_one_core(spec, p, prep, x, tile=2048):
    H, W = x.shape
    h = spec.halo(p)

    def go():
        for r0 in range(0, H, tile):
            for c0 in range(0, W, tile):
                blk = padded_block(
                    lambda a, b, c, d: x[a:b, c:d], x.shape, r0, min(r0 + tile, H), c0, min(c0 + tile, W), h
                )
                spec.detect(blk, h, (r0 - h, c0 - h), p, prep)

    return go


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--side", type=int, default=4096)
    ap.add_argument("--detectors", default="ca_cfar,two_parameter,os_cfar")
    ap.add_argument("--no-dask", action="store_true")
    a = ap.parse_args()
    rng = np.random.default_rng(0)
    x = rng.gamma(4.0, 0.25, (a.side, a.side)).astype(np.float32)
    npx = x.size / 1e6
    y = np.empty_like(x)
    t_copy = best_of(lambda: np.copyto(y, x), 5)
    print(f"# {datetime.date.today()} {machine()}")
    print(f"# scene {a.side}x{a.side} float32 gamma L=4, each detector's default parameters")
    print(f"copyto (bandwidth bound, 1 core): {npx / t_copy:9.1f} Mpx/s")
    client = None
    tmp = tempfile.mkdtemp(prefix="sarship-bench-")
    if not a.no_dask:
        from distributed import Client, LocalCluster

        from sarship.pipeline.scene import create_scene, finalize_scene

        cluster = LocalCluster(
            n_workers=os.cpu_count(), threads_per_worker=1, dashboard_address=":0", silence_logs=logging.ERROR
        )
        client = Client(cluster)
        g = create_scene(
            f"{tmp}/s.zarr", x.shape, {"intensity": "float32"}, tile=2048, attrs={"kind": "intensity", "looks": 4.0}
        )
        g["intensity"][:] = x
        finalize_scene(f"{tmp}/s.zarr")
    print(
        f"{'detector':<14} {'kernel 1 core':>14} {'dask run':>10} {'reference':>10} {'x ref':>6} "
        f"{'copyto/kernel':>13} {'copyto/dask':>11}"
    )
    for name in a.detectors.split(","):
        spec = detectors.get(name)
        p = spec.params(looks=4.0)
        prep = spec.prepare(p)
        t_k = best_of(kernel_one_core(spec, p, prep, x), 3)
        ref, crop = REFS[name]
        xr = x if crop is None else x[:crop, :crop]
        t_r = best_of(lambda: ref(xr, p, prep), 1)
        r_mpx = xr.size / 1e6 / t_r
        d_mpx = float("nan")
        if client is not None:
            from sarship.workers.jobs import run_detection

            run_detection(f"{tmp}/s.zarr", name, {}, out_dir=f"{tmp}/o", client=client, progress=False, overwrite=True)
            t0 = time.perf_counter()
            run_detection(f"{tmp}/s.zarr", name, {}, out_dir=f"{tmp}/o", client=client, progress=False, overwrite=True)
            d_mpx = npx / (time.perf_counter() - t0)
        k_mpx = npx / t_k
        print(
            f"{name:<14} {k_mpx:14.1f} {d_mpx:10.1f} {r_mpx:10.2f} {k_mpx / r_mpx:6.1f} "
            f"{(npx / t_copy) / k_mpx:13.1f} {(npx / t_copy) / d_mpx:11.1f}"
        )
    if client is not None:
        client.close()
        cluster.close()


if __name__ == "__main__":
    main()
