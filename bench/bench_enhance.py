"""Issue 13 benchmarks: destriping and cross-sidelobe suppression, speed and quality.

Speed (one core: BLAS/FFT threads pinned to 1 before numpy loads), on a 4096^2 K-sea scene:

* destripe, the three parts a run does: the scene pass (``segment_sums`` of the whole scene),
  the client's estimate (spectrum, Otsu, Hough, profile) and the per-pixel filter
  (``apply_gain``), in Mpx/s;
* sidelobes: the per-pixel ratio line detector (``line_response``, both directions) over the
  whole scene in Mpx/s, and ``refine_features`` per detection (os_cfar detections of the
  scene, windows read from memory);
* reference in the same run: ``numpy.fft.rfft`` along one axis of the same scene (float64),
  in Mpx/s; every rate is also given as a ratio to it.

Quality (the tables of docs/algorithms/destripe.md and sidelobes.md): stripe-to-background
ratio before/after on simulated K sea with the simulator's stripes, and ship length error
with and without sidelobe suppression against the truth.

    python bench/bench_enhance.py [--quick]      # --quick: speed only, 2048^2

With CuPy and a GPU the same speed parts run on the device too (``--gpu``).
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402
from common import best_of, machine  # noqa: E402

from sarship.pipeline import detectors  # noqa: E402
from sarship.pipeline.image import destripe as D  # noqa: E402
from sarship.pipeline.simulate import SimConfig, simulate_array  # noqa: E402
from sarship.pipeline.targets import sidelobes as S  # noqa: E402
from sarship.pipeline.targets.components import tile_components  # noqa: E402
from sarship.pipeline.targets.ship_features import features  # noqa: E402


def _detect(I: np.ndarray, spacing, pfa=1e-7, merge_px=4):
    spec = detectors.get("os_cfar")
    p = spec.params(pfa=pfa, looks=1, merge_px=merge_px, min_area_px=1)
    halo = spec.halo(p)
    mask, stat = spec.detect(np.pad(I, halo, mode="reflect"), halo, (-halo, -halo), p, spec.prepare(p))
    r = (merge_px + 1) // 2
    recs = tile_components(np.pad(mask, r), I, stat, r, (0, 0), (0, 0)).complete
    return mask, recs, r


def speed(n: int, gpu: bool) -> None:
    cfg = SimConfig(
        shape=(n, n),
        ships=60,
        seed=7,
        clutter="k",
        looks=1,
        stripes=True,
        sidelobes=True,
        scr_db=25,
        pixel_spacing_m=(3.0, 3.0),
        length_m=(20.0, 200.0),
    )
    I = simulate_array(cfg)[0]["intensity"]
    mpx = n * n / 1e6
    ref = best_of(lambda: np.fft.rfft(I.astype(np.float64), axis=1), 2)
    print(f"\n## speed, {n}x{n} K sea, one core ({machine()})")
    print(f"reference numpy.fft.rfft along rows (float64): {mpx / ref:8.1f} Mpx/s")
    p = D.DestripeParams()
    t_pass = best_of(lambda: D.segment_sums(I, 0, 0, p), 2)
    parts = [D.segment_sums(I, 0, 0, p)]
    t_est = best_of(lambda: D.estimate(*D.assemble(parts, I.shape, p), p), 2)
    est = D.estimate(*D.assemble(parts, I.shape, p), p)
    t_apply = best_of(lambda: D.apply_gain(I, est.profile, p), 2)
    tot = t_pass + t_est + t_apply
    print(f"destripe scene pass (segment_sums):  {mpx / t_pass:8.1f} Mpx/s  ({ref / t_pass:.2f}x the FFT reference)")
    print(f"destripe estimate (client, {est.segments} segments x {n}): {t_est * 1e3:8.1f} ms")
    print(f"destripe filter (apply_gain):         {mpx / t_apply:8.1f} Mpx/s  ({ref / t_apply:.2f}x)")
    print(
        f"destripe total:                       {mpx / tot:8.1f} Mpx/s  ({ref / tot:.2f}x); "
        f"stop bins {np.flatnonzero(est.stop).tolist()}"
    )
    t_line = best_of(lambda: (S.line_response(I, "row"), S.line_response(I, "col")), 2)
    print(f"ratio line detector, both directions: {mpx / t_line:8.1f} Mpx/s  ({ref / t_line:.2f}x)")
    mask, recs, r = _detect(I, cfg.pixel_spacing_m)
    feats = features(recs, cfg.pixel_spacing_m, None)

    def refine():
        S.refine_features(
            [{**f, "properties": dict(f["properties"])} for f in feats],
            recs,
            lambda a, b, c, d: I[a:b, c:d],
            lambda a, b, c, d: mask[a:b, c:d],
            I.shape,
            r,
            cfg.pixel_spacing_m,
            None,
        )

    t_ref = best_of(refine, 2)
    out = S.refine_features(
        [{**f, "properties": dict(f["properties"])} for f in feats],
        recs,
        lambda a, b, c, d: I[a:b, c:d],
        lambda a, b, c, d: mask[a:b, c:d],
        I.shape,
        r,
        cfg.pixel_spacing_m,
        None,
    )
    nfl = sum(f["properties"]["sidelobes"] for f in out)
    print(
        f"sidelobe refinement: {len(recs)} detections ({nfl} with sidelobes) in {t_ref * 1e3:.1f} ms = "
        f"{t_ref / max(len(recs), 1) * 1e3:.2f} ms per detection; {mpx / t_ref:.1f} Mpx/s of scene"
    )
    if gpu:
        import cupy as cp

        d = cp.asarray(I)

        def sync(fn):
            def run():
                fn()
                cp.cuda.Device().synchronize()

            return run

        g_pass = best_of(sync(lambda: D.segment_sums(d, 0, 0, p)), 3)
        g_apply = best_of(sync(lambda: D.apply_gain(d, est.profile, p)), 3)
        g_line = best_of(sync(lambda: (S.line_response(d, "row"), S.line_response(d, "col"))), 3)
        print(
            f"GPU ({cp.cuda.runtime.getDeviceProperties(0)['name'].decode()}): scene pass {mpx / g_pass:.0f} Mpx/s, "
            f"filter {mpx / g_apply:.0f} Mpx/s, line detector {mpx / g_line:.0f} Mpx/s (device-resident)"
        )


def destripe_quality() -> None:
    from sarship.pipeline.simulate.artefacts import _stripes_gain
    from sarship.pipeline.simulate.land import _land_mask, _land_model

    print("\n## destripe quality: K sea 2048x1024, simulator stripes; SBR vs the same scene without stripes")
    print("| scene | gain rms dB | SBR before dB | SBR after dB | residual gain rms dB | stop bins |")
    print("|---|---|---|---|---|---|")
    for seed, land in ((1, False), (2, True), (3, True), (4, False)):
        kw = dict(shape=(2048, 1024), ships=8, seed=seed, clutter="k", looks=1, land=land, sidelobes=True)
        cfg = SimConfig(stripes=True, **kw)
        I = simulate_array(cfg)[0]["intensity"]
        ref = simulate_array(SimConfig(stripes=False, **kw))[0]["intensity"]
        sea = ~_land_mask(cfg, _land_model(cfg), 0, 2048, 0, 1024) if land else None
        p = D.DestripeParams()
        est = D.estimate(*D.assemble([D.segment_sums(I, 0, 0, p)], I.shape, p), p)
        out = D.apply_gain(I, est.profile, p)
        g = np.log(_stripes_gain(cfg).astype(np.float64))
        g -= g.mean()
        pr = est.profile - est.profile.mean()
        cols = sea.mean(axis=0) > 0.5 if sea is not None else np.ones(g.size, bool)
        k = 10 / np.log(10)
        side = _land_model(cfg).side if land else "none"
        print(
            f"| seed {seed}, land {side} | {k * g[cols].std():.2f} | "
            f"{D.stripe_to_background_db(I, reference=ref, valid=sea):.1f} | "
            f"{D.stripe_to_background_db(out, reference=ref, valid=sea):.1f} | {k * (g - pr)[cols].std():.2f} | "
            f"{np.flatnonzero(est.stop).tolist()} |"
        )


def sidelobe_quality() -> None:
    print("\n## sidelobe suppression: length error |L/L_true - 1| vs truth (os_cfar pfa 1e-7, merge_px 4, SCR 25 dB)")
    print(
        "| scenes | matched | flagged | mean raw | mean core | median raw | median core "
        "| flagged mean raw | flagged mean core | flagged worst core |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    for sp, lm, seeds in (((3.0, 3.0), (20.0, 200.0), (3, 4, 5, 6)), ((10.0, 10.0), (20.0, 400.0), (3, 4, 5))):
        for sl in (True, False):
            rows = []
            for seed in seeds:
                cfg = SimConfig(
                    shape=(1024, 1024),
                    ships=20,
                    seed=seed,
                    clutter="k",
                    looks=1,
                    sidelobes=sl,
                    scr_db=25,
                    pixel_spacing_m=sp,
                    length_m=lm,
                )
                data, truth = simulate_array(cfg)
                I = data["intensity"]
                mask, recs, r = _detect(I, sp)
                raw = features(recs, sp, None)
                ref = S.refine_features(
                    features(recs, sp, None),
                    recs,
                    lambda a, b, c, d: I[a:b, c:d],
                    lambda a, b, c, d: mask[a:b, c:d],
                    I.shape,
                    r,
                    sp,
                    None,
                )
                for tf in truth["features"]:
                    t = tf["properties"]
                    r0, c0, r1, c1 = t["bbox_px"]
                    inside = [
                        i
                        for i, f in enumerate(raw)
                        if r0 - 2 <= f["properties"]["centroid_px"][0] <= r1 + 2
                        and c0 - 2 <= f["properties"]["centroid_px"][1] <= c1 + 2
                    ]
                    if inside:
                        i = max(inside, key=lambda i: raw[i]["properties"]["area_px"])
                        rows.append(
                            (
                                t["length_m"],
                                raw[i]["properties"]["length_m"],
                                ref[i]["properties"]["length_m"],
                                ref[i]["properties"]["sidelobes"],
                            )
                        )
            a = np.array(rows, float)
            er, ec, fl = np.abs(a[:, 1] / a[:, 0] - 1), np.abs(a[:, 2] / a[:, 0] - 1), a[:, 3] > 0

            def fmt(x):
                return f"{100 * x:.1f} %"

            flag = f"{fmt(er[fl].mean())} | {fmt(ec[fl].mean())} | {fmt(ec[fl].max())}" if fl.any() else "- | - | -"
            print(
                f"| {sp[0]:g} m, {lm[0]:g}-{lm[1]:g} m ships, seeds {seeds}, sidelobes {sl} | {len(a)} | {fl.sum()} | "
                f"{fmt(er.mean())} | {fmt(ec.mean())} | {fmt(np.median(er))} | {fmt(np.median(ec))} | {flag} |"
            )


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--gpu", action="store_true")
    a = ap.parse_args()
    t0 = time.perf_counter()
    speed(2048 if a.quick else 4096, a.gpu)
    if not a.quick:
        destripe_quality()
        sidelobe_quality()
    print(f"\n(total {time.perf_counter() - t0:.0f} s)")


if __name__ == "__main__":
    main()
