"""Digests of every detector's outputs on the bench scenes, to show a refactoring changes no output.

Issue 32 reshapes the run around the detectors, "behaviour unchanged": this runs every registered
detector (and the texture land mask, a coastline-free land case, ``--detector auto``) on small
simulated scenes through :func:`sarship.workers.jobs.run_detection` on one local cluster, and
writes per run the SHA-256 of

- ``detections.geojson`` (the whole file: geometry, properties, parameters; the scene path is the
  same in both runs because the scenes are written to the same folder),
- each array of ``mask.zarr`` (``mask``, ``detected``) and of ``land.zarr``, as raw bytes,
- ``run.json`` without what legitimately differs between two runs: ``timings``, ``tiles.per_tile``'s
  timings and workers, ``cluster``, ``versions``, ``outputs`` and paths.

Usage::

    python bench/run_digest.py --work /tmp/digest --json before.json        # on the old code
    python bench/run_digest.py --work /tmp/digest --json after.json         # on the new code
    python bench/run_digest.py --compare before.json after.json             # exit 1 on any difference

The scenes are simulated with fixed seeds into ``--work/scenes`` (kept, so both runs read the
same stores).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import shutil
import sys
from pathlib import Path

#: (scene name, SimConfig keywords, tile) — intensity with land and ships, quad-pol, SLC
SCENES = {
    "k_land": (dict(shape=(384, 384), ships=6, seed=5, looks=4.0, clutter="k", land=True, scr_db=18.0), 128),
    "gamma": (dict(shape=(320, 320), ships=5, seed=7, looks=1.0, clutter="gamma", land=False, scr_db=16.0), 160),
    "quadpol": (dict(shape=(192, 192), ships=4, seed=3, kind="quadpol", looks=4.0), 96),
    "slc": (dict(shape=(256, 256), ships=4, seed=9, kind="slc", clutter="cggd"), 128),
}
#: detector -> (scene, extra settings) runs; every registered detector appears at least once
RUNS = [
    ("ca_cfar", "k_land", {}),
    ("ca_cfar", "gamma", {"land_mask": "none", "sidelobes": True}),
    ("os_cfar", "k_land", {}),
    ("two_parameter", "gamma", {}),
    ("g0_cfar", "k_land", {}),
    ("k_cfar", "k_land", {}),
    ("ggd_cfar", "gamma", {}),
    ("gamma_mrf", "gamma", {}),
    ("superpixel_cfar", "k_land", {}),
    ("lmm", "gamma", {}),
    ("apwf", "quadpol", {}),
    ("pcdm", "quadpol", {}),
    ("vb_polsar", "quadpol", {}),
    ("csk", "slc", {}),
    ("ca_cfar", "k_land", {"min_contrast_db": 3.0, "line_gap_px": 16, "land_gap_px": 2}),
    ("auto", "k_land", {}),
]
VOLATILE = ("timings", "cluster", "versions", "outputs", "sarship_version")


def _sha(b: bytes) -> str:
    return hashlib.sha256(b).hexdigest()


def _arrays(store: Path) -> dict[str, str]:
    import numpy as np
    import zarr

    if not store.exists():
        return {}
    g = zarr.open_group(str(store), mode="r")
    return {k: _sha(np.ascontiguousarray(g[k][...]).tobytes()) for k in sorted(g.array_keys())}


def _stable_run(run: dict) -> dict:
    r = {k: v for k, v in run.items() if k not in VOLATILE}
    tiles = dict(r.get("tiles") or {})
    tiles["per_tile"] = [
        {k: v for k, v in t.items() if k in ("index", "detected_px", "block_from")} for t in tiles.get("per_tile", [])
    ]
    r["tiles"] = tiles
    land = r.get("land")
    if isinstance(land, dict):
        r["land"] = {k: v for k, v in land.items() if k not in ("seconds",)}
    sp = r.get("scene_pass")
    if isinstance(sp, dict):
        r["scene_pass"] = {k: v for k, v in sp.items() if k != "seconds"}
    return r


def digest(work: Path) -> dict:
    from distributed import Client, LocalCluster

    from sarship.pipeline.simulate import SimConfig, simulate
    from sarship.workers.jobs import run_detection

    scenes = work / "scenes"
    scenes.mkdir(parents=True, exist_ok=True)
    for name, (kw, tile) in SCENES.items():
        if not (scenes / f"{name}.zarr").exists():
            simulate(scenes / f"{name}.zarr", SimConfig(**kw), tile=tile)
    out: dict = {}
    with (
        LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cl,
        Client(cl) as client,
    ):
        for det, scene, settings in RUNS:
            key = f"{det}@{scene}" + (f"+{','.join(sorted(settings))}" if settings else "")
            run_dir = work / "runs" / key.replace("@", "_").replace("+", "_").replace(",", "_")
            shutil.rmtree(run_dir, ignore_errors=True)
            try:
                run = run_detection(
                    scenes / f"{scene}.zarr", det, settings, out_dir=run_dir, client=client, progress=False
                )
            except Exception as exc:  # a refusal is an output too
                out[key] = {"error": f"{type(exc).__name__}: {exc}"}
                continue
            out[key] = {
                "detections": _sha((run_dir / "detections.geojson").read_bytes()),
                "mask": _arrays(run_dir / "mask.zarr"),
                "land": _arrays(run_dir / "land.zarr"),
                "run": _sha(json.dumps(_stable_run(run), sort_keys=True, default=str).encode()),
                "n": run["detections"],
            }
            print(key, out[key]["n"], file=sys.stderr, flush=True)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--work", type=Path, default=Path("/tmp/sarship-digest"))
    ap.add_argument("--json", type=Path)
    ap.add_argument("--compare", nargs=2, type=Path, metavar=("BEFORE", "AFTER"))
    a = ap.parse_args(argv)
    if a.compare:
        before, after = (json.loads(p.read_text()) for p in a.compare)
        diff = [k for k in sorted(set(before) | set(after)) if before.get(k) != after.get(k)]
        for k in diff:
            print(f"DIFFERS {k}: {before.get(k)} -> {after.get(k)}")
        print(f"{len(before)} runs, {len(diff)} differ")
        return 1 if diff else 0
    d = digest(a.work)
    if a.json:
        a.json.write_text(json.dumps(d, indent=1, sort_keys=True))
    print(json.dumps({k: v.get("n", v.get("error")) for k, v in d.items()}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
