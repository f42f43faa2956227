"""``sarship detect`` end to end against the plain CA-CFAR of the ``grdl`` package, side by side.

Issue 17's CPU target: an 8192 x 8192 scene through ``sarship detect --detector ca_cfar --set
looks=1`` (the installed command, a fresh process: local cluster start, reading the Zarr
scene, the outputs written; its *second* run) at least 6x faster end to end than
``grdl.image_processing.detection.cfar.CACFARDetector.detect`` on the same image held in
memory (goal 10x).

One script, one image: a ``side`` x ``side`` float32 1-look gamma sea with bright ships is
written as ``.npy`` and ingested with ``sarship ingest``; ``sarship detect`` runs twice per
configuration (``--config``; default: the detector's defaults, i.e. ``land_mask=texture``,
and ``land_mask=none``, which is grdl's setting: no land mask); then grdl runs in its own
Python (``--grdl-python``: a virtualenv where ``pip install grdl`` was done; grdl is not a
dependency of sarship) on the ``.npy`` loaded into memory, the ``detect`` call timed (best
of ``--grdl-repeat``; its import and the load are not counted). grdl's window is set to
ours: guard_cells 20 / training_cells 40 (a 41-px guard and 81-px background square, the
ca_cfar defaults), pfa 1e-5 (ca_cfar's default), ``assumption='exponential'`` (the 1-look
intensity CA-CFAR, the model of ``looks=1``), min_pixels 10 (our pixel size rule). The
kernel of ours alone (bench_profile.reference_kernel) is timed on the same array too.

Usage: python bench/bench_grdl.py [--side 8192] [--grdl-python /tmp/grdl-venv/bin/python]
    [--config "looks=1" --config "looks=1,land_mask=none"] [--json out.json]
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

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from bench_profile import key_values, make_npy, reference_kernel, sarship_exe, stages  # noqa: E402
from common import machine  # noqa: E402

GRDL_CHILD = r"""
import json, sys, time
import numpy as np
import grdl
from grdl.image_processing.detection.cfar import CACFARDetector
path, repeat = sys.argv[1], int(sys.argv[2])
img = np.load(path)
det = CACFARDetector(guard_cells=20, training_cells=40, pfa=1e-5, min_pixels=10, assumption="exponential")
times, n = [], None
for _ in range(repeat):
    t = time.perf_counter()
    out = det.detect(img)
    times.append(time.perf_counter() - t)
    n = len(out)
print(json.dumps({"version": getattr(grdl, "__version__", "?"), "seconds": times, "detections": n}))
"""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--side", type=int, default=8192)
    ap.add_argument(
        "--grdl-python",
        default="/tmp/grdl-venv/bin/python",
        help="a Python where grdl is installed (not sarship's environment)",
    )
    ap.add_argument("--grdl-repeat", type=int, default=2)
    ap.add_argument(
        "--config",
        action="append",
        default=None,
        help="comma-separated K=V settings of one `sarship detect` configuration (repeatable)",
    )
    ap.add_argument("--device", default="cpu", choices=("cpu", "gpu", "auto"))
    ap.add_argument("--env", action="append", default=[], metavar="K=V", help="environment of the commands")
    ap.add_argument("--json")
    ap.add_argument("--workdir")
    a = ap.parse_args()
    configs = a.config or ["looks=1", "looks=1,land_mask=none"]
    if not os.path.exists(a.grdl_python):
        raise SystemExit(
            f"no Python at {a.grdl_python}: python3 -m venv /tmp/grdl-venv && /tmp/grdl-venv/bin/pip install grdl"
        )
    exe = sarship_exe()
    env = {**os.environ, **key_values(a.env)}
    if a.workdir:
        Path(a.workdir).mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix="sarship-grdl-", dir=a.workdir))
    mpx = a.side * a.side / 1e6
    rec: dict = {
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "machine": machine(),
        "side": a.side,
        "env": a.env,
        "ours": [],
    }
    try:
        npy, scene = work / "scene.npy", work / "scene.zarr"
        make_npy(str(npy), a.side, 1.0)
        t = time.perf_counter()
        subprocess.run(
            [exe, "ingest", str(npy), "--out", str(scene), "--kind", "intensity", "--looks", "1"],
            env=env,
            check=True,
            capture_output=True,
        )
        rec["ingest_s"] = round(time.perf_counter() - t, 3)
        print(f"# {rec['date']}  {rec['machine']}")
        print(
            f"# {a.side}x{a.side} float32 1-look gamma sea + ships ({mpx:.1f} Mpx); "
            f"`sarship ingest` {rec['ingest_s']:.1f} s (not counted below)"
        )
        out = work / "out"
        for cfg in configs:
            sets = [s for s in cfg.split(",") if s]
            cmd = [
                exe,
                "detect",
                str(scene),
                "--detector",
                "ca_cfar",
                "--device",
                a.device,
                "--out",
                str(out),
                "--overwrite",
            ]
            for s in sets:
                cmd += ["--set", s]
            walls, runs = [], []
            for _ in range(2):
                t = time.perf_counter()
                p = subprocess.run(cmd, env=env, capture_output=True, text=True)
                walls.append(time.perf_counter() - t)
                if p.returncode:
                    raise SystemExit(p.stderr[-2000:])
                runs.append(json.loads((out / "run.json").read_text()))
            top = sorted(stages(runs[1], walls[1]), key=lambda r: -r[1])[:4]
            rec["ours"].append(
                {
                    "settings": sets,
                    "cold_s": round(walls[0], 3),
                    "warm_s": round(walls[1], 3),
                    "detections": runs[1]["detections"],
                    "warm_stages": {n: round(s, 3) for n, s in stages(runs[1], walls[1])},
                }
            )
            print(
                f"sarship detect ca_cfar {' '.join('--set ' + s for s in sets)} --device {a.device}: "
                f"cold {walls[0]:.2f} s, warm {walls[1]:.2f} s ({mpx / walls[1]:.1f} Mpx/s), "
                f"{runs[1]['detections']} detections; warm's largest stages: "
                + ", ".join(f"{n} {s:.2f} s" for n, s in top)
            )
        ref = reference_kernel(str(scene), "ca_cfar", {"looks": "1"})
        rec["our_kernel_s"] = ref["seconds"]
        print(
            f"our ca_cfar kernel alone on the array (in memory, this process): {ref['seconds']:.2f} s "
            f"({mpx / ref['seconds']:.1f} Mpx/s)"
        )
        p = subprocess.run(
            [a.grdl_python, "-c", GRDL_CHILD, str(npy), str(a.grdl_repeat)], capture_output=True, text=True
        )
        if p.returncode:
            raise SystemExit(f"grdl failed: {p.stderr[-2000:]}")
        g = json.loads(p.stdout.strip().splitlines()[-1])
        gs = min(g["seconds"])
        rec["grdl"] = {**g, "best_s": round(gs, 3)}
        print(
            f"grdl {g['version']} CACFARDetector.detect on the array (in memory): best of {len(g['seconds'])} "
            f"{gs:.2f} s ({mpx / gs:.1f} Mpx/s; runs {', '.join(f'{s:.2f}' for s in g['seconds'])}), "
            f"{g['detections']} detections"
        )
        print(f"kernel vs kernel: ours {gs / ref['seconds']:.1f}x faster than grdl's detect")
        for o in rec["ours"]:
            o["ratio_grdl_over_warm"] = round(gs / o["warm_s"], 3)
            o["ratio_grdl_over_cold"] = round(gs / o["cold_s"], 3)
            print(
                f"RATIO grdl detect / sarship detect ({','.join(o['settings'])}): warm {o['ratio_grdl_over_warm']:.2f}x"
                f", cold {o['ratio_grdl_over_cold']:.2f}x  (target >= 6x warm, goal 10x)"
            )
        if a.json:
            Path(a.json).write_text(json.dumps(rec, indent=1))
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
