"""``superpixel_cfar`` (seed 002): speed on one core, pure-clutter false alarms, extended ships.

Zhang et al. 2023 (docs/references.md, ``zhang2023``); docs/algorithms/superpixel_cfar.md.

1. Speed: a K-sea scene with extended ships (``--side`` squared, default 1000) as one block
   (mirror halo), the scene pass (segmentation + histogram) and ``detect`` (segmentation,
   classes, Table 1, EM, threshold, contrast, decision) timed separately, best of 3, one core;
   ``two_parameter`` at its defaults on the same scene in the same run (ratio).
2. Pure clutter, ``--clutter-side`` squared (default 2048: 4.2 Mpx), Rayleigh and K (nu = 4):
   the calibration mode (every superpixel tested against its neighbours, eq 15, pixel
   decision) with M_a = 1 and M_a = 3, pixel false alarms against M pfa; the defaults (final
   superpixel mask); the paper's plain K-means (``min_separation_db=0``).
3. Extended ships (tests/pipeline/test_superpixel_cfar.py: ``hires_scene``, 60-400 px, scatterers and
   dark gaps, K sea, SCR 13 dB): components per ship (fragments within each detector's
   ``merge_px`` joined, components under 10 px dropped, as a job does), FoM, pixel TPR/FPR,
   for superpixel_cfar, two_parameter and ca_cfar at their defaults.

``python bench/bench_superpixel.py [--side 1000] [--clutter-side 2048] [--scenes 10]``
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("NUMBA_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402
from common import best_of, machine  # noqa: E402
from tests.test_superpixel_cfar import CAL, hires_scene, k_sea, objects  # noqa: E402

from sarship.pipeline import detectors  # noqa: E402
from sarship.pipeline.detectors import superpixel_cfar as D  # noqa: E402
from sarship.pipeline.tiling.windows import mirror_pad  # noqa: E402


def run_whole(name: str, x: np.ndarray, **kw):
    spec = detectors.get(name)
    p = spec.params(looks=1.0, **kw)
    prep = spec.prepare(p)
    if spec.scene_pass is not None:
        prep = D.scene_prep(x, p, prep)
    h = spec.halo(p)
    return spec.detect(mirror_pad(x, h), h, (-h, -h), p, prep)[0], p


def speed(side: int) -> None:
    x, _ = hires_scene(1, shape=(side, side), n_ships=max(1, side // 200))
    p = D.SuperpixelCFARParams(looks=1.0)
    h = D.halo(p)
    P = mirror_pad(x, h)
    prep = D.scene_prep(x, p)
    t_pass = best_of(lambda: D.scene_pass(P, h, (-h, -h), p, prep))
    t_det = best_of(lambda: D.detect(P, h, (-h, -h), p, prep))
    tp = detectors.get("two_parameter")
    q = tp.params(looks=1.0)
    hq = tp.halo(q)
    Q = mirror_pad(x.astype(np.float32), hq)
    pq = tp.prepare(q)
    t_tp = best_of(lambda: tp.detect(Q, hq, (-hq, -hq), q, pq))
    mpx = side * side / 1e6
    tot = t_pass + t_det
    print(f"speed {side}x{side} (block with halo {h}: {P.shape[0]}x{P.shape[1]}), one core:")
    print(
        f"  scene pass {t_pass:.3f} s, detect {t_det:.3f} s, total {tot:.3f} s = {mpx / tot:.2f} Mpx/s "
        f"({prep['target_count']} target superpixels of {prep['superpixels']})"
    )
    print(
        f"  two_parameter (defaults, 81x81 ring) {t_tp:.3f} s = {mpx / t_tp:.1f} Mpx/s; "
        f"superpixel_cfar / two_parameter time ratio {tot / t_tp:.2f}"
    )


def clutter(side: int) -> None:
    rng = np.random.default_rng(5)
    scenes = {"rayleigh": rng.exponential(1.0, (side, side)), "K nu=4": k_sea(rng, (side, side))}
    M = side * side
    for name, x in scenes.items():
        for comps in (1, 3):
            p = D.SuperpixelCFARParams(pfa=1e-3, **{**CAL, "components": comps})
            t = time.perf_counter()
            m, _ = run_whole(
                "superpixel_cfar",
                x,
                pfa=1e-3,
                **{**{k: v for k, v in CAL.items() if k != "looks"}, "components": comps},
            )
            K = int(m.sum())
            print(
                f"clutter {name} {side}^2, calibration mode M_a={comps}: {K} pixel false alarms, expected "
                f"{M * p.pfa:.0f} (ratio {K / (M * p.pfa):.3f}); {time.perf_counter() - t:.1f} s"
            )
        for label, kw in (("defaults", {}), ("paper K-means (min_separation_db=0)", {"min_separation_db": 0.0})):
            m, p = run_whole("superpixel_cfar", x, **kw)
            print(f"clutter {name}: {label}, pfa {p.pfa:g}: final mask {int(m.sum())} px, rate {m.mean():.3e}")


def ships(n_scenes: int) -> None:
    rows = {}
    for name in ("superpixel_cfar", "two_parameter", "ca_cfar"):
        per, false, tp, tr, fp, cl, t = [], 0, 0, 0, 0, 0, 0.0
        for s in range(n_scenes):
            x, truth = hires_scene(100 + s)
            t0 = time.perf_counter()
            m, p = run_whole(name, x.astype(np.float32) if name != "superpixel_cfar" else x)
            t += time.perf_counter() - t0
            ps, f = objects(m, truth, p.merge_px, 10)
            per += ps
            false += f
            tp += int((m & (truth > 0)).sum())
            tr += int((truth > 0).sum())
            fp += int((m & (truth == 0)).sum())
            cl += int((truth == 0).sum())
        per = np.array(per)
        hits = int((per >= 1).sum())
        rows[name] = (
            len(per),
            (per == 1).mean(),
            per[per > 0].mean(),
            per.max(),
            hits / (false + len(per)),
            false,
            tp / tr,
            fp / cl,
            t / n_scenes,
        )
    print(f"ships: {n_scenes} scenes 600x600, K sea, 5 ships each (60-400 px, scatterers, dark gaps), defaults")
    print("  detector          ships  one-piece  mean pieces (found)  max  FoM    false  TPR    FPR       s/scene")
    for k, r in rows.items():
        print(
            f"  {k:16s} {r[0]:5d}  {r[1]:9.3f}  {r[2]:19.2f}  {r[3]:3d}  {r[4]:.3f}  {r[5]:5d}  {r[6]:.3f}  "
            f"{r[7]:.2e}  {r[8]:.2f}"
        )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--side", type=int, default=1000)
    ap.add_argument("--clutter-side", type=int, default=2048)
    ap.add_argument("--scenes", type=int, default=10)
    ap.add_argument("--skip", default="", help="comma list of parts to skip: speed, clutter, ships")
    a = ap.parse_args()
    print(machine(), time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()))
    skip = set(a.skip.split(","))
    if "speed" not in skip:
        speed(a.side)
    if "clutter" not in skip:
        clutter(a.clutter_side)
    if "ships" not in skip:
        ships(a.scenes)


if __name__ == "__main__":
    main()
