"""Our tile scheme against ``dask.array.map_overlap`` + ``to_zarr`` for the same detector.

Both run CA-CFAR (default parameters) over the same Zarr scene on the same local cluster
(one worker process per core) and write a uint8 mask to Zarr:

- ``sarship``: one task per output tile reads tile + halo straight from the store,
  detects, writes its mask chunk, labels and returns component moments
  (``workers.jobs.run_detection``, detections and run.json included);
- ``map_overlap``: ``da.from_zarr`` -> ``map_overlap(depth=halo, boundary="reflect")`` ->
  ``to_zarr`` (mask only: no labelling, no detections). Note dask's ``reflect`` repeats the
  edge pixel (numpy ``symmetric``), not the thesis' mirror; only the timing is compared.

Usage: python bench/bench_tiling.py [--side 8192] [--tile 2048]
"""

from __future__ import annotations

import argparse
import datetime
import logging
import os
import shutil
import tempfile
import time

import numpy as np
from common import TreeMemory, machine  # noqa: E402


def _mask_block(block, halo, p, prep):
    from sarship.pipeline.detectors import ca_cfar

    mask, _ = ca_cfar.detect(block, halo, (0, 0), p, prep)  # origin only fixes rounding order
    out = np.zeros(block.shape, np.uint8)
    out[halo : block.shape[0] - halo, halo : block.shape[1] - halo] = mask
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--side", type=int, default=8192)
    ap.add_argument("--tile", type=int, default=2048)
    a = ap.parse_args()
    import dask.array as da
    from distributed import Client, LocalCluster

    from sarship.pipeline.detectors import ca_cfar
    from sarship.pipeline.scene import create_scene, finalize_scene
    from sarship.workers.jobs import run_detection

    work = tempfile.mkdtemp(prefix="sarship-tiling-")
    try:
        g = create_scene(
            f"{work}/s.zarr",
            (a.side, a.side),
            {"intensity": "float32"},
            tile=a.tile,
            attrs={"kind": "intensity", "looks": 4.0},
        )
        rng = np.random.default_rng(0)
        for r in range(0, a.side, a.tile):
            g["intensity"][r : r + a.tile] = rng.gamma(4.0, 0.25, (min(a.tile, a.side - r), a.side)).astype(np.float32)
        finalize_scene(f"{work}/s.zarr")
        p = ca_cfar.CAParams(looks=4.0)
        prep = ca_cfar.prepare(p)
        halo = ca_cfar.SPEC.halo(p)
        npx = a.side * a.side / 1e6
        print(f"# {datetime.date.today()} {machine()}")
        print(f"# scene {a.side}x{a.side} float32, tile {a.tile}, ca_cfar defaults (halo {halo})")
        with (
            LocalCluster(
                n_workers=os.cpu_count(), threads_per_worker=1, dashboard_address=":0", silence_logs=logging.ERROR
            ) as cluster,
            Client(cluster) as client,
        ):
            results = {}
            for rep in range(2):  # second round is warm (Numba compiled in the workers)
                mem = TreeMemory()
                with mem.watch():
                    t = time.perf_counter()
                    run_detection(
                        f"{work}/s.zarr",
                        "ca_cfar",
                        {},
                        out_dir=f"{work}/o",
                        client=client,
                        progress=False,
                        overwrite=True,
                    )
                    results["sarship (tile tasks, + labelling)"] = (time.perf_counter() - t, mem.peak)
                mem = TreeMemory()
                with mem.watch():
                    t = time.perf_counter()
                    x = da.from_zarr(f"{work}/s.zarr/intensity", chunks=(a.tile, a.tile))
                    m = x.map_overlap(
                        _mask_block,
                        depth=halo,
                        boundary="reflect",
                        dtype=np.uint8,
                        trim=True,
                        halo=halo,
                        p=p,
                        prep=prep,
                    )
                    m.to_zarr(f"{work}/m_{rep}.zarr", overwrite=True)  # chunks = tiles: one writer each
                    results["dask map_overlap + to_zarr (mask only)"] = (time.perf_counter() - t, mem.peak)
            for k, (dt, peak) in results.items():
                print(f"{k:<42} {dt:6.2f} s {npx / dt:7.1f} Mpx/s  peak RSS {peak / 2**30:.2f} GiB")
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
