"""End to end on a large scene: ingest (.npy -> Zarr), detect on a local Dask cluster, write.

Creates a ``side x side`` float32 L-look gamma scene with bright ships as a ``.npy`` file
on disk (written strip by strip, never held in memory), then times
``sarship ingest`` (library call) and ``sarship detect`` (local cluster, one worker
process per core), and samples the resident memory of this process and all its children
(the Dask scheduler, nanny and workers) every 50 ms for the peak.

Usage: python bench/bench_end_to_end.py [--side 16384] [--detector ca_cfar] [--tile 2048]
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


def make_npy(path: str, side: int, looks: float = 4.0, seed: int = 0) -> None:
    arr = np.lib.format.open_memmap(path, mode="w+", dtype=np.float32, shape=(side, side))
    rng = np.random.default_rng(seed)
    strip = 512
    for r in range(0, side, strip):
        blk = rng.gamma(looks, 1.0 / looks, (min(strip, side - r), side)).astype(np.float32)
        for _ in range(4):  # a few bright extended targets per strip
            rr = int(rng.integers(0, max(blk.shape[0] - 8, 1)))
            cc = int(rng.integers(0, max(side - 40, 1)))
            blk[rr : rr + 6, cc : cc + 30] += 50.0
        arr[r : r + blk.shape[0]] = blk
    arr.flush()
    del arr


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--side", type=int, default=16384)
    ap.add_argument("--detector", default="ca_cfar")
    ap.add_argument("--tile", type=int, default=2048)
    ap.add_argument("--workdir", default=None)
    a = ap.parse_args()
    from distributed import Client, LocalCluster

    from sarship.pipeline.readers import ingest
    from sarship.workers.jobs import run_detection

    work = tempfile.mkdtemp(prefix="sarship-e2e-", dir=a.workdir)
    try:
        npy = os.path.join(work, "scene.npy")
        t = time.perf_counter()
        make_npy(npy, a.side)
        t_make = time.perf_counter() - t
        npx = a.side * a.side / 1e6
        print(f"# {datetime.date.today()} {machine()}")
        print(
            f"# scene {a.side}x{a.side} float32 ({a.side * a.side * 4 / 2**30:.2f} GiB), tile {a.tile}, "
            f"detector {a.detector} (default parameters); input written in {t_make:.1f} s"
        )
        mem = TreeMemory()
        with mem.watch():
            t = time.perf_counter()
            ingest([npy], os.path.join(work, "scene.zarr"), kind="intensity", tile=a.tile, looks=4.0)
            t_ing = time.perf_counter() - t
        peak_ing = mem.peak
        with mem.watch():
            t = time.perf_counter()
            cluster = LocalCluster(
                n_workers=os.cpu_count(), threads_per_worker=1, dashboard_address=":0", silence_logs=logging.ERROR
            )
            client = Client(cluster)
            t_cluster = time.perf_counter() - t
            t = time.perf_counter()
            run = run_detection(
                os.path.join(work, "scene.zarr"),
                a.detector,
                {},
                out_dir=os.path.join(work, "out"),
                client=client,
                progress=False,
                overwrite=True,
            )
            t_det = time.perf_counter() - t
            client.close()
            cluster.close()
        peak_det = mem.peak
        print(f"ingest  {t_ing:7.1f} s  {npx / t_ing:7.1f} Mpx/s  peak RSS {peak_ing / 2**30:.2f} GiB")
        print(f"cluster {t_cluster:7.1f} s  (start-up, not in the rates)")
        print(
            f"detect  {t_det:7.1f} s  {npx / t_det:7.1f} Mpx/s  peak RSS {peak_det / 2**30:.2f} GiB "
            f"(scheduler + {os.cpu_count()} workers + client), {run['detections']} detections"
        )
        total = t_ing + t_det
        print(f"total   {total:7.1f} s  {npx / total:7.1f} Mpx/s end to end (ingest + detect + write)")
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
