"""GPU kernels and end-to-end GPU runs, against the CPU measured in the same run.

Kernel rows: each detector's public ``detect`` on a CuPy block already on the device
(the whole mirror-extended 1000 x 1000 scene of the thesis, or 4096 x 4096), timed with
CUDA events (median of 10 after 2 warm-ups), then the same call on the NumPy block on one
CPU core (best of 3): ``x CPU`` is the ratio. ``min bytes`` counts one read of the input
and one write of the mask and statistic; ``% copy`` is ``min bytes / time`` over the
device-to-device copy bandwidth measured in the same run (bytes read + written). The
kernels write double-precision window sums between passes, so they move several times the
minimum: the column says how far from the memory bound each one is.

End-to-end rows: ``sarship detect`` (``run_detection``, local cluster with one pinned
worker per GPU) on a Sentinel-1 IW GRD sized band, 25000 x 16700 float32 (4.2e8 px) of
simulated gamma clutter in a Zarr scene: Zarr read, transfer, detect, mask write,
labelling, merge, outputs. With ``--gpus 2`` (two visible GPUs) the same run on 1 and 2
GPUs gives the scaling.

Usage: python bench/bench_gpu.py [--sizes 1000,4096] [--band 25000x16700] [--gpus 1|2]
"""

from __future__ import annotations

import argparse
import datetime
import os
import tempfile
import time
from pathlib import Path

import numpy as np
from common import best_of, machine  # noqa: E402

from sarship.pipeline import detectors  # noqa: E402
from sarship.pipeline.tiling.windows import mirror_pad  # noqa: E402

CASES = [
    ("ca_cfar", {"looks": 1.0}, "default (guard 41, background 81)", "intensity"),
    ("two_parameter", {}, "default (guard 21, background 41)", "intensity"),
    ("os_cfar", {"looks": 1.0}, "default (guard 21, background 41, k = 3N/4)", "intensity"),
    ("apwf", {"estimator": "window", "guard": 1, "background": 31, "pfa": 1e-6}, "thesis 31x31 window", "quadpol"),
    ("apwf", {}, "ring guard 41 / background 61", "quadpol"),
    ("pcdm", {"looks_window": 1, "span_rule": "fraction"}, "thesis: single-look C", "quadpol"),
    ("pcdm", {}, "default: 3x3 boxcar", "quadpol"),
    ("vb_polsar", {}, "defaults (pass 2; scene pass on the host)", "quadpol"),
    ("lmm", {}, "defaults: grid (step 5), BIC K' <= 3, predictive tail", "intensity"),
    ("lmm", {"method": "fast"}, "fast form: histogram fit at every pixel", "intensity"),
    ("lmm", {"method": "exact"}, "exact form: fit on the 1240 raw ring samples of every pixel", "intensity"),
]

#: Per-case limits: (GPU timed repeats, CPU reference on sizes up to, largest size run).
LIMITS = {("lmm", "fast"): (1, 0, 1000), ("lmm", "exact"): (1, 0, 1000), ("lmm", None): (3, 1000, 4096)}


def copy_bandwidth(cp) -> float:
    """Device-to-device copy, bytes read + written per second (median of 10)."""
    a = cp.empty(2**28, cp.uint8)
    b = cp.empty_like(a)
    ts = []
    for _ in range(12):
        e0, e1 = cp.cuda.Event(), cp.cuda.Event()
        e0.record()
        b[...] = a
        e1.record()
        e1.synchronize()
        ts.append(cp.cuda.get_elapsed_time(e0, e1) / 1e3)
    return 2 * a.nbytes / float(np.median(ts[2:]))


def gpu_time(cp, fn, reps: int = 10) -> float:
    for _ in range(2 if reps > 1 else 1):
        fn()
    cp.cuda.Device().synchronize()
    ts = []
    for _ in range(reps):
        e0, e1 = cp.cuda.Event(), cp.cuda.Event()
        e0.record()
        fn()
        e1.record()
        e1.synchronize()
        ts.append(cp.cuda.get_elapsed_time(e0, e1) / 1e3)
    return float(np.median(ts))


def box_passes(cp, n: int = 4096, m: int = 81) -> list[str]:
    """Time of each window-sum pass on an n x n float32 block (to see which one dominates)."""
    from sarship.pipeline.gpu import box

    x = cp.asarray(np.random.default_rng(0).random((n + m - 1, n + m - 1), dtype=np.float32))
    H = box._hsum(cp, x, m, 0, n)
    rows = []
    for label, fn in [
        ("horizontal, direct", lambda: box._hsum(cp, x, m, 0, n)),
        ("horizontal, transposed", lambda: box._hsum_transposed(cp, x, m, 0, n)),
        ("vertical", lambda: box._vsum(cp, H, m, 0, n)),
    ]:
        t = gpu_time(cp, fn)
        rows.append(f"# box-sum pass {label}, {n}x{n}, m={m}: {t * 1e3:.2f} ms")
        print(rows[-1], flush=True)
    return rows


def transfers(cp) -> list[str]:
    """Host-to-device copy of one 4096^2 float32 tile with an 81-px halo: from pageable
    memory (what a task does), from pinned memory, and pinned including the copy of the
    tile into the pinned buffer (what using pinned memory in a task would cost)."""
    import cupyx

    n = 4096 + 80
    x = np.random.default_rng(0).random((n, n), dtype=np.float32)
    pinned = cupyx.empty_pinned(x.shape, x.dtype)
    pinned[...] = x
    d = cp.empty(x.shape, x.dtype)
    rows = []

    def pageable():
        d.set(x)

    def from_pinned():
        d.set(pinned)

    def via_pinned():
        pinned[...] = x
        d.set(pinned)

    for label, fn in [("pageable", pageable), ("pinned", from_pinned), ("pinned incl. host copy", via_pinned)]:
        t = best_of(lambda: (fn(), cp.cuda.Device().synchronize()), repeat=5)
        rows.append(
            f"# h2d of a {n}x{n} float32 tile ({x.nbytes / 1e6:.0f} MB), {label}: {t * 1e3:.1f} ms "
            f"({x.nbytes / t / 1e9:.1f} GB/s)"
        )
        print(rows[-1], flush=True)
    return rows


def _inputs(n: int):
    from sarship.pipeline.simulate import SimConfig, simulate_array

    rng = np.random.default_rng(0)
    inten = rng.gamma(1.0, 1.0, (n, n)).astype(np.float32)
    cfg = SimConfig(kind="quadpol", shape=(n, n), ships=max(4, n // 100), seed=1, clutter="rayleigh", scr_db=10.0)
    arrs, _ = simulate_array(cfg)
    X = np.stack([arrs["hh"], arrs["hv"], arrs["vv"]], -1).astype(np.complex64)
    return {"intensity": inten, "quadpol": X}


def kernels(sizes: list[int], bw: float, cp, only: set[str] | None = None) -> list[str]:
    rows = []
    for n in sizes:
        data = _inputs(n)
        for name, kw, label, kind in CASES:
            if only and name not in only:
                continue
            reps, cpu_max, size_max = LIMITS.get((name, kw.get("method")), (10, 10**9, 10**9))
            if n > size_max:
                continue
            spec = detectors.get(name)
            p = spec.params(**kw)
            prep = spec.prepare(p)
            h = spec.halo(p)
            x = data[kind]
            blk = mirror_pad(x, h)
            origin = (-h, -h)
            if spec.scene_pass is not None:
                prep = {**prep, **spec.reduce([spec.scene_pass(blk, h, origin, p, prep)], p, prep)}
            dblk = cp.asarray(blk)
            tg = gpu_time(cp, lambda d=dblk: spec.detect(d, h, origin, p, prep), reps)
            if n <= cpu_max:
                tc = best_of(
                    lambda: spec.detect(blk, h, origin, p, prep), repeat=1 if (n > 2000 or name == "lmm") else 3
                )
                cpu = f"{tc:.3f} | {tc / tg:,.0f}x"
            else:
                cpu = "- | -"
            mbytes = x.nbytes + n * n * 5  # input once, mask (1 B) + stat (4 B)
            rows.append(
                f"| {name} | {label} | {n}x{n} | {tg * 1e3:.2f} | {n * n / tg / 1e6:,.2f} | "
                f"{cpu} | {mbytes / 1e6:.0f} MB | {100 * mbytes / tg / bw:.0f}% |"
            )
            print(rows[-1], flush=True)
            del dblk
            cp.get_default_memory_pool().free_all_blocks()
    return rows


def write_band(path: Path, shape: tuple[int, int], tile: int) -> None:
    """Gamma clutter (L = 1) with a few bright ships, written tile by tile on 16 threads."""
    from concurrent.futures import ThreadPoolExecutor

    from sarship.pipeline.scene import create_scene, finalize_scene, tile_slices

    g = create_scene(
        path, shape, {"intensity": np.dtype(np.float32)}, tile=tile, attrs={"kind": "intensity", "looks": 1.0}
    )
    arr = g["intensity"]

    def one(t):
        i, j, r0, r1, c0, c1 = t
        rng = np.random.default_rng([i, j])
        x = rng.standard_exponential((r1 - r0, c1 - c0), dtype=np.float32)
        for _ in range(3):
            a, b = rng.integers(0, max(r1 - r0 - 20, 1)), rng.integers(0, max(c1 - c0 - 60, 1))
            x[a : a + 12, b : b + 50] += 200.0
        arr[r0:r1, c0:c1] = x

    with ThreadPoolExecutor(16) as ex:
        list(ex.map(one, tile_slices(shape, tile)))
    finalize_scene(path)


def end_to_end(
    band: tuple[int, int], n_gpus: list[int], tile: int, threads: list[int], dets: tuple[str, ...] = ("ca_cfar",)
) -> list[str]:
    from sarship.workers.cluster import connect
    from sarship.workers.gpus import visible_gpus
    from sarship.workers.jobs import run_detection

    rows = []
    vis = visible_gpus()
    with tempfile.TemporaryDirectory(dir=os.environ.get("SARSHIP_BENCH_TMP")) as td:
        scene = Path(td) / "band.zarr"
        t = time.perf_counter()
        write_band(scene, band, tile)
        print(f"# band {band[0]}x{band[1]} written in {time.perf_counter() - t:.1f} s", flush=True)
        for det, k, nt in [(d, k, nt) for d in dets for k in n_gpus for nt in threads]:
            if k > len(vis):
                continue
            os.environ["CUDA_VISIBLE_DEVICES"] = ",".join(vis[:k])
            with connect(gpus=True, echo=False, dashboard_address=":0", gpu_threads=nt) as client:
                for _rep in range(2):  # first: compile + warm caches; second: measured
                    t = time.perf_counter()
                    run = run_detection(
                        scene,
                        det,
                        {},
                        out_dir=Path(td) / f"out{k}",
                        client=client,
                        device="gpu",
                        progress=False,
                        overwrite=True,
                    )
                    el = time.perf_counter() - t
                per = run["tiles"]["per_tile"]
                ker = sum(p["detect_s"] - p["h2d_s"] - p["d2h_s"] for p in per)
                rows.append(
                    f"| {det} e2e | {k} GPU, {nt} thread(s) each | {band[0]}x{band[1]} | {el:.2f} s | "
                    f"{band[0] * band[1] / el / 1e6:,.0f} Mpx/s | read {sum(p['read_s'] for p in per):.1f} s, "
                    f"h2d {sum(p['h2d_s'] for p in per):.2f} s, kernel {ker:.2f} s, "
                    f"d2h {sum(p['d2h_s'] for p in per):.2f} s, write {sum(p['write_s'] for p in per):.1f} s, "
                    f"label {sum(p['label_s'] for p in per):.1f} s (task sums); "
                    f"{run['detections']} detections |"
                )
                print(rows[-1], flush=True)
            os.environ["CUDA_VISIBLE_DEVICES"] = ",".join(vis)
    return rows


def thesis_scenes(cases=None, devices=("gpu", "cpu")) -> list[str]:
    """End to end per detector on 1000 x 1000 scenes (the thesis' size) in Zarr: local
    cluster with one pinned GPU worker, then the same with CPU workers (all host cores)."""
    from sarship.pipeline.simulate import SimConfig, simulate
    from sarship.workers.cluster import connect
    from sarship.workers.gpus import visible_gpus
    from sarship.workers.jobs import run_detection

    rows = []
    vis = visible_gpus()
    with tempfile.TemporaryDirectory(dir=os.environ.get("SARSHIP_BENCH_TMP")) as td:
        scenes = {}
        for kind in ("intensity", "quadpol"):
            cfg = SimConfig(
                kind=kind,
                shape=(1000, 1000),
                ships=10,
                seed=3,
                clutter="gamma" if kind == "intensity" else "rayleigh",
                scr_db=10.0,
            )
            scenes[kind] = Path(td) / f"{kind}.zarr"
            simulate(scenes[kind], cfg, tile=512)
        for dev in devices:
            os.environ["CUDA_VISIBLE_DEVICES"] = vis[0] if dev == "gpu" else ""
            with connect(gpus=dev == "gpu", echo=False, dashboard_address=":0") as client:
                for name, kw, label, kind in cases or [c for c in CASES if c[1].get("method") not in ("fast", "exact")]:
                    settings = {k: v for k, v in kw.items()}
                    best = float("inf")
                    for _ in range(3):
                        t = time.perf_counter()
                        run = run_detection(
                            scenes[kind],
                            name,
                            settings,
                            out_dir=Path(td) / "o",
                            client=client,
                            device=dev,
                            progress=False,
                            overwrite=True,
                        )
                        best = min(best, time.perf_counter() - t)
                    rows.append(
                        f"| {name} | {label} | 1000x1000 e2e | {dev} | {best:.3f} s | {run['device']} | "
                        f"{run['detections']} detections |"
                    )
                    print(rows[-1], flush=True)
        os.environ["CUDA_VISIBLE_DEVICES"] = ",".join(vis)
    return rows


def main() -> None:
    import cupy as cp

    ap = argparse.ArgumentParser()
    ap.add_argument("--sizes", default="1000,4096")
    ap.add_argument("--band", default="25000x16700")
    ap.add_argument("--gpus", default="1", help="comma list of GPU counts for the end-to-end rows")
    ap.add_argument("--tile", type=int, default=4096)
    ap.add_argument("--gpu-threads", default="1,2", help="comma list of tile tasks per GPU worker")
    ap.add_argument("--skip-kernels", action="store_true")
    ap.add_argument("--skip-thesis-e2e", action="store_true")
    ap.add_argument("--only", default="", help="comma list of detectors for the kernel rows (default: all)")
    ap.add_argument("--band-detectors", default="ca_cfar", help="comma list of detectors for the band rows")
    ap.add_argument(
        "--skip-slow", action="store_true", help="skip the lmm fast/exact rows and lmm's CPU reference (minutes each)"
    )
    a = ap.parse_args()
    props = cp.cuda.runtime.getDeviceProperties(0)
    print(f"# {datetime.date.today()} {props['name'].decode()} x{cp.cuda.runtime.getDeviceCount()}; host {machine()}")
    bw = copy_bandwidth(cp)
    print(f"# device-to-device copy: {bw / 1e12:.2f} TB/s (read + write)")
    only = {s for s in a.only.split(",") if s} or None
    if a.skip_slow:
        LIMITS.update({("lmm", "fast"): (1, 0, 0), ("lmm", "exact"): (1, 0, 0), ("lmm", None): (3, 0, 4096)})
    if not a.skip_kernels:
        transfers(cp)
        box_passes(cp)
        print("| detector | setting | size | GPU ms | Mpx/s | CPU s (1 core) | x CPU | min bytes | % copy |")
        print("|---|---|---|---|---|---|---|---|---|")
        kernels([int(s) for s in a.sizes.split(",")], bw, cp, only)
    if not a.skip_thesis_e2e:
        print("| detector | setting | scene | device asked | best of 3 (wall, with scene pass) | ran on | detections |")
        print("|---|---|---|---|---|---|---|")
        thesis_scenes(
            [c for c in CASES if c[1].get("method") not in ("fast", "exact") and (only is None or c[0] in only)]
        )
    if a.band != "none":
        r, c = (int(v) for v in a.band.lower().split("x"))
        end_to_end(
            (r, c),
            [int(k) for k in a.gpus.split(",")],
            a.tile,
            [int(t) for t in a.gpu_threads.split(",")],
            tuple(a.band_detectors.split(",")),
        )


if __name__ == "__main__":
    main()
