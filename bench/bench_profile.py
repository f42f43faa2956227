"""Per-stage profile of ``sarship detect`` as a user runs it: the benchmark of record of issue 17.

Runs the installed ``sarship`` command as a subprocess (a fresh Python process each time:
interpreter, imports, local cluster start, detection, outputs, exit) ``--runs`` times on one
scene: run 1 is *cold* (the first command after the scene was written: Numba's on-disk cache
and the OS page cache as they are), runs 2.. are *warm* (the same command again, a second
process; the scene and the compiled kernels are then cached). For each run it prints and
records the wall time of the command and, from its ``run.json`` (docs/interfaces/files.md),
each stage's seconds and share of the wall:

- ``outside run_detection``: wall - ``timings.total_s`` (interpreter start, imports, CLI,
  writing run.json, renaming the outputs into place, the process's exit),
- ``cluster start``, ``land pass`` (``land.seconds``), ``scene pass`` (``scene_pass.seconds``),
  the rest of ``prepare_s`` (opening the scene, creating the mask store, placement),
- ``tiles`` (``tiles_s``), ``cluster close``, ``consolidate``, ``merge``, ``geojson``,

and, within the tiles, the per-tile stages summed over tiles (``read_s``, ``land_s``,
``detect_s``, ``write_s``, ``label_s``, ``h2d_s``, ``d2h_s``: worker-seconds, shown with their
share of tiles_s x workers; an in-process threaded worker runs a tile per core at once, so
there the share can pass 100 %). Rates are scene Mpx / wall. The reference, measured in the same
run after the commands: the detector's kernel alone (``spec.detect``) on the whole scene array
in this process, without a land mask (``--set`` values passed on otherwise); the ratio is
wall / kernel.

With ``--warm DEVICE`` the commands run on a warm cluster (``sarship warm start``, started
first and timed on its own; sarship/warm.py): run 1 is then the first command on it.

Usage:
    python bench/bench_profile.py --side 8192 --detector ca_cfar --set looks=1 [--device cpu]
        [--tile 2048] [--runs 2] [--json out.json] [--scene PATH] [--env K=V ...]
        [--warm auto|gpu|cpu [--warm-workers N]]
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from bench_end_to_end import make_npy  # noqa: E402  (the scene maker of the end-to-end bench)
from common import machine  # noqa: E402

TILE_KEYS = ("read_s", "land_s", "detect_s", "write_s", "label_s", "h2d_s", "d2h_s")


def sarship_exe() -> str:
    exe = shutil.which("sarship") or str(Path(sys.executable).with_name("sarship"))
    if not os.path.exists(exe):
        raise SystemExit("the installed `sarship` command was not found (pip install -e . in this environment)")
    return exe


def stages(run: dict, wall: float) -> list[tuple[str, float]]:
    """(stage, seconds) covering the wall time of one command, from its run.json."""
    t = run["timings"]
    land = float((run.get("land") or {}).get("seconds") or 0.0)
    spass = float((run.get("scene_pass") or {}).get("seconds") or 0.0)
    cstart = float(t.get("cluster_start_s") or 0.0)
    rows = [
        ("outside run_detection", wall - t["total_s"]),
        ("cluster start", cstart),
        ("land pass", land),
        ("scene pass", spass),
        ("prepare, rest", t["prepare_s"] - cstart - land - spass),
        ("tiles", t["tiles_s"]),
        ("cluster close", float(t.get("cluster_close_s") or 0.0)),
        ("consolidate", float(t.get("consolidate_s") or 0.0)),
        ("merge", t["merge_s"]),
        ("geojson", float(t.get("geojson_s") or 0.0)),
    ]
    covered = sum(s for _, s in rows)
    rows.append(("unaccounted", wall - covered))
    return rows


def tile_sums(run: dict) -> dict[str, float]:
    per = run["tiles"]["per_tile"]
    return {k: float(sum(p.get(k, 0.0) for p in per)) for k in TILE_KEYS}


def run_once(cmd: list[str], env: dict, out: Path) -> tuple[float, dict, str]:
    t = time.perf_counter()
    p = subprocess.run(cmd, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t
    if p.returncode != 0:
        raise SystemExit(f"command failed ({p.returncode}): {' '.join(cmd)}\n{p.stderr[-3000:]}")
    run = json.loads((out / "run.json").read_text())
    return wall, run, p.stderr


def reference_kernel(scene_path: str, detector: str, settings: dict) -> dict:
    """The detector's kernel alone on the whole scene array (read into memory first, padded with
    the halo by mirror as the tiles are), land mask off; best of 2 after a warm-up on a crop."""
    from sarship.pipeline.detectors.base import resolve_size
    from sarship.pipeline.scene import open_scene
    from sarship.pipeline.tiling.inputs import intensity_source, make_reader
    from sarship.pipeline.tiling.windows import padded_block
    from sarship.workers.request import JobRequest

    scene = open_scene(scene_path)
    req = JobRequest.from_inputs(detector, {**settings, "land_mask": None, "scene": scene_path, "device": "cpu"})
    spec = req.spec
    if spec.scene_pass is not None or spec.input != "intensity":
        return {"what": f"none: {detector} has a scene pass or a non-intensity input", "seconds": None}
    params = req.detector_params()
    if spec.needs_looks and params.looks is None:
        params = params.model_copy(update={"looks": scene.looks or 1.0})
    params, _ = resolve_size(params, scene.pixel_spacing_m)
    prep = spec.prepare(params)
    halo = spec.halo(params)
    var, transform = intensity_source(scene, None)
    H, W = scene.shape
    t = time.perf_counter()
    block = padded_block(make_reader(str(scene.path), var, transform), (H, W), 0, H, 0, W, halo)
    t_read = time.perf_counter() - t
    small = block[: min(H, 256) + 2 * halo, : min(W, 256) + 2 * halo]
    spec.detect(np.ascontiguousarray(small), halo, (-halo, -halo), params, prep)  # compile / warm
    best = float("inf")
    for _ in range(2):
        t = time.perf_counter()
        spec.detect(block, halo, (-halo, -halo), params, prep)
        best = min(best, time.perf_counter() - t)
    return {
        "what": f"{detector} kernel alone (spec.detect, this process, land_mask none) on the whole "
        f"{H}x{W} array, best of 2",
        "seconds": best,
        "read_whole_s": t_read,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--side", type=int, default=8192, help="side of the scene made here (ignored with --scene)")
    ap.add_argument("--looks", type=float, default=1.0, help="looks of the scene made here (gamma sea)")
    ap.add_argument("--scene", help="an existing scene store instead of making one")
    ap.add_argument("--detector", default="ca_cfar")
    ap.add_argument("--device", choices=("cpu", "gpu", "auto"), default="auto")
    ap.add_argument("--tile", type=int, help="processing tile (default: the scene's)")
    ap.add_argument("--ingest-tile", type=int, default=2048, help="tile of the scene made here")
    ap.add_argument("--set", action="append", default=[], metavar="K=V", help="detector parameter (repeatable)")
    ap.add_argument("--env", action="append", default=[], metavar="K=V", help="environment of the commands")
    ap.add_argument("--runs", type=int, default=2, help="commands in a row (1 cold, then warm)")
    ap.add_argument("--no-reference", action="store_true", help="skip the kernel-alone reference")
    ap.add_argument("--json", help="write the record here")
    ap.add_argument("--label", default="", help="a label for this configuration in the record")
    ap.add_argument("--workdir", help="folder for the temporary scene and outputs")
    ap.add_argument(
        "--scheduler",
        help="run the commands on this Dask scheduler (`sarship detect --scheduler`) "
        "instead of the local cluster each command starts",
    )
    ap.add_argument(
        "--warm",
        choices=("auto", "gpu", "cpu"),
        help="run the commands on a warm cluster (`sarship warm start --device WARM` first, "
        "`sarship warm stop` after; sarship/warm.py) instead of a cluster per command",
    )
    ap.add_argument("--warm-workers", type=int, help="`sarship warm start --workers N` (CPU workers)")
    a = ap.parse_args()

    exe = sarship_exe()
    env = {**os.environ, **key_values(a.env)}
    work = Path(tempfile.mkdtemp(prefix="sarship-profile-", dir=a.workdir))
    os.chmod(work, 0o700)
    env["SARSHIP_WARM_SOCKET"] = str(work / "warm.sock")  # this run's own (none unless --warm)
    record: dict = {
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "machine": machine(),
        "label": a.label,
        "detector": a.detector,
        "device": a.device,
        "set": a.set,
        "env": a.env,
        "tile": a.tile,
        "scheduler": a.scheduler,
        "runs": [],
    }
    try:
        if a.scene:
            scene = a.scene
        else:
            npy = work / "scene.npy"
            t = time.perf_counter()
            make_npy(str(npy), a.side, a.looks)
            t_make = time.perf_counter() - t
            scene = str(work / "scene.zarr")
            t = time.perf_counter()
            p = subprocess.run(
                [
                    exe,
                    "ingest",
                    str(npy),
                    "--out",
                    scene,
                    "--kind",
                    "intensity",
                    "--tile",
                    str(a.ingest_tile),
                    "--looks",
                    str(a.looks),
                ],
                env=env,
                capture_output=True,
                text=True,
            )
            if p.returncode != 0:
                raise SystemExit(f"ingest failed: {p.stderr[-2000:]}")
            t_ing = time.perf_counter() - t
            npy.unlink()
            record["scene_made"] = {
                "side": a.side,
                "looks": a.looks,
                "make_npy_s": round(t_make, 3),
                "ingest_s": round(t_ing, 3),
                "ingest_tile": a.ingest_tile,
            }
        from sarship.pipeline.scene import open_scene

        sc = open_scene(scene)
        H, W = sc.shape
        mpx = H * W / 1e6
        record["scene"] = {"path": scene if a.scene else "(made here)", "shape": [H, W], "tile": sc.tile}
        print(f"# {record['date']}  {record['machine']}")
        print(
            f"# sarship detect {a.detector} --device {a.device} {' '.join('--set ' + s for s in a.set)}"
            f"{' --tile ' + str(a.tile) if a.tile else ''}  on {H}x{W} ({mpx:.1f} Mpx, scene tile {sc.tile})"
            f"{'  env ' + ' '.join(a.env) if a.env else ''}"
        )
        if "scene_made" in record:
            m = record["scene_made"]
            print(
                f"# scene made: {a.looks:g}-look gamma + ships, .npy in {m['make_npy_s']:.1f} s, "
                f"`sarship ingest` {m['ingest_s']:.1f} s ({mpx / m['ingest_s']:.1f} Mpx/s)"
            )
        if a.warm:
            wcmd = [exe, "warm", "start", "--device", a.warm, "--dashboard", "127.0.0.1:0"]
            if a.warm_workers is not None:
                wcmd += ["--workers", str(a.warm_workers)]
            t = time.perf_counter()
            p = subprocess.run(wcmd, env=env, capture_output=True, text=True)
            if p.returncode != 0:
                raise SystemExit(f"sarship warm start failed: {p.stderr[-2000:]}")
            record["warm_start"] = {"s": round(time.perf_counter() - t, 3), "line": p.stdout.strip()}
            print(f"# `sarship warm start --device {a.warm}`: {record['warm_start']['s']:.2f} s: {p.stdout.strip()}")
        out = work / "out"
        cmd = [exe, "detect", scene, "--detector", a.detector, "--device", a.device, "--out", str(out), "--overwrite"]
        for s in a.set:
            cmd += ["--set", s]
        if a.tile:
            cmd += ["--tile", str(a.tile)]
        if a.scheduler:
            cmd += ["--scheduler", a.scheduler]
        for i in range(a.runs):
            wall, run, err = run_once(cmd, env, out)
            if a.warm and "sarship: warm cluster," not in err:
                raise SystemExit(f"the command did not run on the warm cluster:\n{err[-2000:]}")
            label = "cold" if i == 0 else "warm"
            rows = stages(run, wall)
            sums = tile_sums(run)
            nw = max(len(run["cluster"]["workers"]), 1)
            tiles_s = run["timings"]["tiles_s"]
            print(
                f"\n## run {i + 1} ({label}: {'first' if i == 0 else 'a further'} `sarship detect` process)  "
                f"wall {wall:.2f} s  {mpx / wall:.1f} Mpx/s  device {run['device']}  "
                f"{run['tiles']['count']} tiles on {nw} worker(s)  {run['detections']} detections"
            )
            print(f"{'stage':24s} {'s':>8s} {'share':>7s}")
            for name, s in rows:
                print(f"{name:24s} {s:8.3f} {100 * s / wall:6.1f}%")
            print(f"{'per tile (summed)':24s} {'s':>8s} {'of tiles_s x workers':>21s}")
            for k in TILE_KEYS:
                if sums[k] or k in ("read_s", "detect_s", "write_s", "label_s"):
                    print(f"  {k:22s} {sums[k]:8.3f} {100 * sums[k] / max(tiles_s * nw, 1e-9):6.1f}%")
            record["runs"].append(
                {
                    "run": i + 1,
                    "label": label,
                    "wall_s": round(wall, 4),
                    "mpx_per_s": round(mpx / wall, 3),
                    "stages": {n: {"s": round(s, 4), "share": round(s / wall, 4)} for n, s in rows},
                    "per_tile_sums": {k: round(v, 4) for k, v in sums.items()},
                    "workers": nw,
                    "tiles": run["tiles"]["count"],
                    "detections": run["detections"],
                    "device": run["device"],
                    "timings": run["timings"],
                    "land": run.get("land"),
                    "scene_pass_s": (run.get("scene_pass") or {}).get("seconds"),
                    "mask_bytes": sum(f.stat().st_size for f in (out / "mask.zarr").rglob("*") if f.is_file()),
                }
            )
        if not a.no_reference:
            ref = reference_kernel(scene, a.detector, key_values(a.set))
            record["reference"] = ref
            if ref["seconds"]:
                print(
                    f"\n# reference: {ref['what']}: {ref['seconds']:.2f} s ({mpx / ref['seconds']:.1f} Mpx/s); "
                    f"reading the whole array {ref['read_whole_s']:.2f} s"
                )
                for r in record["runs"]:
                    r["ratio_to_kernel"] = round(r["wall_s"] / ref["seconds"], 3)
                    print(f"#   run {r['run']} ({r['label']}): wall = {r['ratio_to_kernel']:.2f} x the kernel alone")
            else:
                print(f"\n# reference: {ref['what']}")
        if a.json:
            Path(a.json).write_text(json.dumps(record, indent=1))
            print(f"# record: {a.json}")
    finally:
        if a.warm:
            subprocess.run([exe, "warm", "stop"], env=env, capture_output=True, text=True)
        shutil.rmtree(work, ignore_errors=True)


def key_values(pairs: list[str]) -> dict:
    """``K=V`` strings as a dict (``--set`` and ``--env`` values)."""
    out = {}
    for kv in pairs:
        k, _, v = kv.partition("=")
        out[k] = v
    return out


if __name__ == "__main__":
    main()
