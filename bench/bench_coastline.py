"""Cost of the coastline land mask (``land_mask=coastline``, pipeline/land/coastline.py).

A north-up scene of ``--shape`` pixels of ``--spacing`` metres centred on ``--at LON,LAT`` (default:
the Oslofjord at 10 m, a long, fractal, island-strewn coast: a hard case), rasterised strip by
strip exactly as a detection job does (``Coastline.read`` over full-width strips of ``--strip``
rows), without and with the buffer. Reference, measured in the same run: the exact GSHHG test
(``roaring_landmask.contains_many``) on every pixel in scan order, timed on about ``--sample``
pixels of evenly spaced full rows; the lattice result is checked equal to the exact test on every pixel of the most
coastal of 16 ``--ref`` square crops.

    python bench/bench_coastline.py [--shape 8192x8192] [--at 10.6,59.8] [--spacing 10] [--buffer 250]

Prints Mpx/s of each and the ratio to the reference.
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np

from sarship.pipeline.land import coastline as co


def scene_attrs(lon: float, lat: float, shape: tuple[int, int], sp: float) -> dict:
    dlat = sp / 111_320.0
    dlon = sp / (111_320.0 * math.cos(math.radians(lat)))
    H, W = shape
    return {
        "crs": "EPSG:4326",
        "transform": [lon - W / 2 * dlon, dlon, 0.0, lat + H / 2 * dlat, 0.0, -dlat],
        "pixel_spacing_m": [sp, sp],
    }


def run_strips(cl: co.Coastline, shape: tuple[int, int], strip: int) -> tuple[float, int]:
    H, W = shape
    t = time.perf_counter()
    n = 0
    for r0 in range(0, H, strip):
        n += int(cl.read(r0, min(r0 + strip, H), 0, W).sum())
    return time.perf_counter() - t, n


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--shape", default="8192x8192")
    ap.add_argument("--at", default="10.6,59.8")
    ap.add_argument("--spacing", type=float, default=10.0)
    ap.add_argument("--buffer", type=float, default=co.DEFAULT_BUFFER_M)
    ap.add_argument("--strip", type=int, default=2048)
    ap.add_argument("--ref", type=int, default=1024, help="side of the coastal crop checked against the exact test")
    ap.add_argument("--sample", type=int, default=1_000_000, help="pixels (whole rows) timing the exact test")
    a = ap.parse_args()
    H, W = (int(x) for x in a.shape.lower().split("x"))
    lon, lat = (float(x) for x in a.at.split(","))
    attrs = scene_attrs(lon, lat, (H, W), a.spacing)
    t = time.perf_counter()
    co.shoreline()
    print(f"load GSHHG (roaring-landmask): {time.perf_counter() - t:.1f} s")
    npx = H * W
    for buf in (0.0, a.buffer):
        cl = co.open_coastline(attrs, (H, W), buf)
        dt, n = run_strips(cl, (H, W), a.strip)
        st = cl.stats
        print(
            f"coastline buffer {buf:g} m: {H}x{W} in {dt:.2f} s = {npx / dt / 1e6:.1f} Mpx/s; land {n / npx:.3f}; "
            f"step {cl.step} px, lattice points {st['lattice_points']}, refined {st['refined_px'] / st['pixels']:.3%} "
            f"of evaluated pixels"
        )
        if buf == 0.0:
            lattice_rate = npx / dt
    cl = co.open_coastline(attrs, (H, W), 0.0)
    # the reference: the exact test on every pixel in scan order, timed on evenly spaced full rows
    k = max(1, min(H, a.sample // W))
    rows = np.linspace(0, H - 1, k).round()
    R, C = np.meshgrid(rows, np.arange(W, dtype=np.float64), indexing="ij")
    t = time.perf_counter()
    land_px = int(cl._test(R, C).sum())  # one batch: multi-threaded like the refinement's
    rate = k * W / (time.perf_counter() - t)
    print(
        f"reference, the exact test on every pixel (timed on {k} evenly spaced full rows): "
        f"{rate / 1e6:.2f} Mpx/s (land {land_px / (k * W):.3f})"
    )
    print(f"lattice / reference: {lattice_rate / rate:.1f}x (no buffer)")
    # the lattice equals the exact test on the most coastal of 16 crops
    best = None
    for i in range(4):
        for j in range(4):
            r0 = int((H - a.ref) * (i + 0.5) / 4)
            c0 = int((W - a.ref) * (j + 0.5) / 4)
            f = float(cl.land(r0, r0 + a.ref, c0, c0 + a.ref)[::8, ::8].mean())
            if best is None or abs(f - 0.5) < abs(best[0] - 0.5):
                best = (f, r0, c0)
    _, r0, c0 = best
    ref = co.brute_force(cl, r0, r0 + a.ref, c0, c0 + a.ref)
    got = cl.land(r0, r0 + a.ref, c0, c0 + a.ref)
    print(
        f"lattice == exact test on every pixel of the {a.ref}x{a.ref} crop at ({r0}, {c0}) "
        f"(land {ref.mean():.3f}): {bool(np.array_equal(got, ref))}"
    )


if __name__ == "__main__":
    main()
