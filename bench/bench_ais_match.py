"""AIS matching speed (issue 33 target: 10 000 detections against 1 M AIS reports in < 2 s on
the 2-core machine).

A synthetic scene (as tests/pipeline/test_ais_match.py, vectorised and simpler: straight
tracks, one report interval per vessel, 10 m GNSS noise, 30 m georeferencing error) of
``--reports`` reports from ``--vessels`` vessels over the 170 km x 250 km footprint and a 50 km
band around it, reports over +-``--span`` s about the scene; the detections are the ships inside
the footprint (displaced along the flight by ``R v_los / V``) plus dark ones up to
``--detections``. Timed, best of ``--repeat`` after a warm-up, in one process:

- ``vessel_states`` (1 M reports -> one state per vessel) and ``match`` (KD-tree candidates,
  scores, the global assignment), together: the target;
- references measured in the same run: scipy's ``cKDTree`` build + ``query_ball_point`` alone
  over the same points at a fixed 2 km radius (the floor of any gated search), and a dense
  ``linear_sum_assignment`` on a 2000 x 4000 subset of the detections and vessels (what one
  global dense Hungarian costs; the full 10 000 x 20 000 matrix alone is 1.6 GB).

``python bench/bench_ais_match.py [--vessels 20000] [--reports 1000000] [--detections 10000]``
prints Markdown for bench/RESULTS.md.
"""

from __future__ import annotations

import argparse
import datetime as dt
import time

import numpy as np
from common import best_of, machine

from sarship.pipeline.ais.displacement import LookGeometry
from sarship.pipeline.ais.match import Detections, MatchParams, match
from sarship.pipeline.ais.reports import Reports, VesselInfo
from sarship.pipeline.ais.tracks import vessel_states

K = 6_371_008.8 * np.pi / 180.0
KN = 1852.0 / 3600.0
LON0, LAT0, HEADING = 3.0, 54.0, 193.0
ALONG, ACROSS, V, T0, DUR = 170e3, 250e3, 7590.0, 1.7e9, 25.0


def _unit(deg: float) -> np.ndarray:
    return np.array([np.sin(np.radians(deg)), np.cos(np.radians(deg))])


def world(rng, n_vessels: int, n_reports: int, n_det: int, span: float):
    uf, ur = _unit(HEADING), _unit(HEADING + 90)
    a = rng.uniform(-ALONG / 2 - 50e3, ALONG / 2 + 50e3, n_vessels)
    x = rng.uniform(-ACROSS / 2 - 50e3, ACROSS / 2 + 50e3, n_vessels)
    e, n = a * uf[0] + x * ur[0], a * uf[1] + x * ur[1]
    speed = np.where(rng.random(n_vessels) < 0.2, 0.0, rng.uniform(2, 25, n_vessels)) * KN
    cog = rng.uniform(0, 360, n_vessels)
    ve, vn = speed * np.sin(np.radians(cog)), speed * np.cos(np.radians(cog))
    per = np.full(n_vessels, n_reports // n_vessels)
    per[: n_reports - per.sum()] += 1
    step = 2 * span / per
    vid = np.repeat(np.arange(n_vessels), per)
    k = np.arange(vid.size) - np.repeat(np.cumsum(per) - per, per)
    t_mid = T0 + DUR / 2
    t = t_mid - span + (k + rng.random(vid.size)) * step[vid]
    pe = e[vid] + ve[vid] * (t - t_mid) + rng.normal(0, 10, vid.size)
    pn = n[vid] + vn[vid] * (t - t_mid) + rng.normal(0, 10, vid.size)
    lon, lat = LON0 + pe / (K * np.cos(np.radians(LAT0))), LAT0 + pn / K
    f = np.float32
    sog, c = (speed[vid] / KN).astype(f), cog[vid].astype(f)
    rep = Reports(vid.astype(np.int64) + 200_000_000, t, lon, lat, sog, c, np.full(vid.size, np.nan, f))
    info = {
        200_000_000 + i: VesselInfo(200_000_000 + i, length_m=float(L))
        for i, L in enumerate(rng.uniform(15, 300, n_vessels))
    }
    # detections: the ships inside the footprint at their line time, displaced; then dark ones
    t_det = T0 + (a + ALONG / 2) / (ALONG / DUR)
    inside = (np.abs(a) <= ALONG / 2) & (np.abs(x) <= ACROSS / 2)
    idx = np.flatnonzero(inside)[:n_det]
    n_dark = max(n_det - idx.size, 0)
    ad, xd = rng.uniform(-ALONG / 2, ALONG / 2, n_dark), rng.uniform(-ACROSS / 2, ACROSS / 2, n_dark)
    g = 400e3 + np.concatenate([x[idx], xd]) + ACROSS / 2
    R = np.hypot(693e3, g)
    sin_i = g / R
    vel = np.concatenate([ve[idx], np.zeros(n_dark)]), np.concatenate([vn[idx], np.zeros(n_dark)])
    dx = R * (-(vel[0] * ur[0] + vel[1] * ur[1]) * sin_i) / V
    td = np.concatenate([t_det[idx], T0 + (ad + ALONG / 2) / (ALONG / DUR)])
    de = np.concatenate([e[idx] + ve[idx] * (t_det[idx] - t_mid), ad * uf[0] + xd * ur[0]]) + dx * uf[0]
    dn = np.concatenate([n[idx] + vn[idx] * (t_det[idx] - t_mid), ad * uf[1] + xd * ur[1]]) + dx * uf[1]
    de, dn = de + rng.normal(0, 30, de.size), dn + rng.normal(0, 30, dn.size)
    one = np.ones(de.size)
    geo = LookGeometry(uf[0] * one, uf[1] * one, ur[0] * one, ur[1] * one, R, V * one, sin_i)
    det = Detections(
        LON0 + de / (K * np.cos(np.radians(LAT0))), LAT0 + dn / K, td, info_lengths(info, idx, n_dark, rng), geo
    )
    truth = np.concatenate([idx + 200_000_000, np.full(n_dark, -1)])
    return rep.sorted(), info, det, truth


def xyz(lon: np.ndarray, lat: np.ndarray) -> np.ndarray:
    lo, la = np.radians(lon), np.radians(lat)
    return 6_371_008.8 * np.stack([np.cos(la) * np.cos(lo), np.cos(la) * np.sin(lo), np.sin(la)], -1)


def info_lengths(info, idx, n_dark, rng):
    L = np.array([info[200_000_000 + i].length_m for i in idx])
    return np.concatenate([L * np.exp(rng.normal(0, 0.25, L.size)), rng.uniform(15, 300, n_dark)])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--vessels", type=int, default=20_000)
    ap.add_argument("--reports", type=int, default=1_000_000)
    ap.add_argument("--detections", type=int, default=10_000)
    ap.add_argument("--span", type=float, default=1800.0)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    rng = np.random.default_rng(args.seed)
    rep, info, det, truth = world(rng, args.vessels, args.reports, args.detections, args.span)
    t_mid = T0 + DUR / 2
    out: dict = {}

    def run():
        st = vessel_states(rep, t_mid)
        out["a"] = match(det, st, info, MatchParams())
        out["n_states"] = len(st)

    t_total = best_of(run, args.repeat)
    t_states = best_of(lambda: vessel_states(rep, t_mid), args.repeat)
    st = vessel_states(rep, t_mid)
    from scipy.optimize import linear_sum_assignment
    from scipy.spatial import cKDTree

    t_kd = best_of(
        lambda: cKDTree(xyz(det.lon, det.lat)).query_ball_point(xyz(st.lon, st.lat), 2000.0, workers=2), args.repeat
    )
    sub = np.random.default_rng(1).random((2000, 4000))
    t0 = time.perf_counter()
    linear_sum_assignment(sub)
    t_dense = time.perf_counter() - t0
    a = out["a"]
    matched, ais = a.vessel >= 0, truth >= 0
    right = matched & (a.mmsi == truth)
    print(f"## AIS matching speed ({dt.date.today().isoformat()}; {machine()})\n")
    print(
        f"{len(rep):,} reports of {args.vessels:,} vessels ({out['n_states']:,} states at the scene time), {len(det):,} detections ({ais.sum():,} with AIS)\n"
    )
    print("| step | s | ratio to the KD-tree query alone |")
    print("|---|---:|---:|")
    print(f"| vessel_states + match (target < 2 s) | {t_total:.3f} | {t_total / t_kd:.1f} |")
    print(f"| of which vessel_states | {t_states:.3f} | {t_states / t_kd:.1f} |")
    print(f"| reference: cKDTree build + query_ball_point (2 km) | {t_kd:.3f} | 1.0 |")
    print(f"| reference: dense linear_sum_assignment 2000 x 4000 | {t_dense:.3f} | {t_dense / t_kd:.1f} |")
    print(
        f"\npairs scored {a.pairs:,}, acceptable {a.acceptable:,}, components {a.components:,}; "
        f"precision {right.sum() / max(matched.sum(), 1):.4f}, recall {right[ais].sum() / ais.sum():.4f}, "
        f"dark recall {(~matched[~ais]).sum() / max((~ais).sum(), 1):.4f}"
    )


if __name__ == "__main__":
    main()
