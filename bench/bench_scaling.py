"""Multi-GPU scaling of ``sarship detect`` as a user runs it (issue 18): one, two and four GPUs of
one host, and two GPU workers on one host driven through an external ``dask scheduler``.

Each configuration is :mod:`bench_profile` (the benchmark of record of issue 17) run as a
subprocess on the same scene store: ``--runs`` commands in a row, run 1 cold, the others warm,
with every stage's share of the wall time from ``run.json``. The configurations:

- ``local-N``: ``sarship detect --device gpu`` with its own local cluster and
  ``CUDA_VISIBLE_DEVICES`` = the first N GPUs (the local cluster puts its GPU worker processes on
  every visible GPU: ``SARSHIP_GPU_PROCS`` per GPU, workers/cluster.py);
- ``external-N``: ``dask scheduler`` + one ``sarship worker --gpus 0,..,N-1 --cpus 0`` command
  (its default ``--gpu-procs`` worker processes per GPU, as the local cluster) + ``sarship detect
  --scheduler``: the deployment of docs/deploy, warm (the workers are started once, before the
  runs). On a one-GPU host ``--external 2`` is the dry run of the path: two ``sarship worker
  --gpus 0`` commands sharing GPU 0.
- ``warm-N``: ``sarship warm start --device gpu`` with ``CUDA_VISIBLE_DEVICES`` = the first N
  GPUs (a warm cluster kept between commands, sarship/warm.py: its GPU worker processes per GPU
  are not capped in all, ``gpu_procs(long_lived=True)``), then ``sarship detect`` as typed: the
  commands run on it.

The reference measured in the same run is the one-GPU run of the same kind (``local-1``,
``external-1``; the same host, the same scene): each configuration's speed-up is that run's best
warm wall over its own (also recorded against ``local-1``). Targets
(issue 18): two GPUs >= 1.8x one GPU, four >= 3.4x.

Usage (on the GPU host, the scene made once by ``sarship ingest``)::

    python bench/bench_scaling.py --scene /tmp/band.zarr --local 1,2,4 --external 1,2,4 --warm 1,2,4 \\
        --runs 3 --json scaling.json [--set land_mask=none]
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import shutil
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from common import machine  # noqa: E402

HERE = Path(__file__).resolve().parent
STAGES = (
    "outside run_detection",
    "cluster start",
    "land pass",
    "prepare, rest",
    "tiles",
    "cluster close",
    "merge",
    "geojson",
)


def visible_gpus() -> int:
    try:
        out = subprocess.run(["nvidia-smi", "-L"], capture_output=True, text=True, timeout=30).stdout
    except (OSError, subprocess.SubprocessError):
        return 0
    return sum(1 for line in out.splitlines() if line.startswith("GPU "))


def profile(
    scene: str,
    runs: int,
    sets: list[str],
    env: dict,
    json_out: Path,
    scheduler: str | None = None,
    detector: str = "ca_cfar",
    extra: list[str] | None = None,
) -> dict:
    cmd = [
        sys.executable,
        str(HERE / "bench_profile.py"),
        "--scene",
        scene,
        "--detector",
        detector,
        "--device",
        "gpu",
        "--runs",
        str(runs),
        "--no-reference",
        "--json",
        str(json_out),
        *(extra or []),
    ]
    for s in sets:
        cmd += ["--set", s]
    if scheduler:
        cmd += ["--scheduler", scheduler]
    p = subprocess.run(cmd, env=env, capture_output=True, text=True)
    if p.returncode != 0:
        raise RuntimeError(f"bench_profile failed ({p.returncode}):\n{p.stdout[-2000:]}\n{p.stderr[-3000:]}")
    print(p.stdout, flush=True)
    return json.loads(json_out.read_text())


def summary(rec: dict) -> dict:
    warm = [r for r in rec["runs"] if r["label"] == "warm"] or rec["runs"]
    best = min(warm, key=lambda r: r["wall_s"])
    return {
        "warm_best_s": best["wall_s"],
        "warm_median_s": statistics.median(r["wall_s"] for r in warm),
        "cold_s": rec["runs"][0]["wall_s"],
        "workers": best["workers"],
        "tiles": best["tiles"],
        "detections": best["detections"],
        "shares": {k: best["stages"][k]["share"] for k in STAGES if k in best["stages"]},
        "seconds": {k: best["stages"][k]["s"] for k in STAGES if k in best["stages"]},
    }


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_workers(address: str, want: int, timeout: float = 180.0) -> int:
    """Wait until at least ``want`` workers are registered and their count has been stable for 5 s."""
    from distributed import Client

    with Client(address, timeout=60) as c:
        t0 = time.time()
        last, since = -1, time.time()
        while time.time() - t0 < timeout:
            n = len(c.scheduler_info(n_workers=-1)["workers"])
            if n != last:
                last, since = n, time.time()
            if n >= want and time.time() - since > 5:
                return n
            time.sleep(0.5)
    raise RuntimeError(f"only {last} workers registered at {address} after {timeout:.0f} s (wanted {want})")


def external(scene: str, runs: int, sets: list[str], n: int, have: int, work: Path, detector: str) -> dict:
    """``sarship worker --gpus 0,..,n-1`` on an external scheduler (``n`` > ``have``: ``n``
    commands on GPU 0, the dry run of the path on a smaller host)."""
    from sarship.workers.cluster import gpu_procs

    port = free_port()
    address = f"tcp://127.0.0.1:{port}"
    env = {k: v for k, v in os.environ.items() if k != "CUDA_VISIBLE_DEVICES"}
    dask_exe = shutil.which("dask") or str(Path(sys.executable).with_name("dask"))
    sarship_exe = shutil.which("sarship") or str(Path(sys.executable).with_name("sarship"))
    commands = [",".join(str(i) for i in range(n))] if n <= have else ["0"] * n
    logs = [open(work / f"{name}.log", "w") for name in ["scheduler"] + [f"worker{k}" for k in range(len(commands))]]
    procs = [
        subprocess.Popen(
            [dask_exe, "scheduler", "--host", "127.0.0.1", "--port", str(port), "--dashboard-address", ":0"],
            env=env,
            stdout=logs[0],
            stderr=subprocess.STDOUT,
        )
    ]
    try:
        time.sleep(2.0)
        for k, gids in enumerate(commands):
            procs.append(
                subprocess.Popen(
                    [sarship_exe, "worker", "--scheduler", address, "--gpus", gids, "--cpus", "0", "--name", f"gw{k}"],
                    env=env,
                    stdout=logs[k + 1],
                    stderr=subprocess.STDOUT,
                )
            )
        per = gpu_procs(n) if n <= have else gpu_procs(1)  # each command's --gpu-procs default
        registered = wait_workers(address, n * per)
        rec = profile(scene, runs, sets, env, work / f"external{n}.json", scheduler=address, detector=detector)
        rec["external"] = {
            "commands": [f"sarship worker --gpus {g} --cpus 0" for g in commands],
            "registered_workers": registered,
            "what": "dask scheduler + sarship worker command(s), warm across runs",
        }
        return rec
    finally:
        for p in reversed(procs):
            p.terminate()
        for p in reversed(procs):
            try:
                p.wait(timeout=30)
            except subprocess.TimeoutExpired:
                p.kill()
        for f in logs:
            f.close()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scene", required=True, help="the scene store (e.g. the band ingested by sarship ingest)")
    ap.add_argument(
        "--local",
        default="1,2,4",
        help="GPU counts of the local-cluster runs (those above the host's are skipped; 1 always runs: the reference)",
    )
    ap.add_argument("--external", default="", help="GPU counts of the external-scheduler runs, e.g. 1,2,4")
    ap.add_argument("--runs", type=int, default=3, help="commands per configuration (1 cold, then warm)")
    ap.add_argument("--detector", default="ca_cfar")
    ap.add_argument("--set", action="append", default=["looks=1"], metavar="K=V")
    ap.add_argument(
        "--warm",
        default="",
        help="GPU counts of the warm-cluster runs (`sarship warm start --device "
        "gpu` with CUDA_VISIBLE_DEVICES = the first N GPUs), e.g. 1,2,4",
    )
    ap.add_argument("--json", help="write the record here")
    a = ap.parse_args()
    have = visible_gpus()
    if have == 0:
        raise SystemExit("no GPU visible (nvidia-smi -L lists none): this benchmark needs a GPU host")
    counts = [n for n in (int(x) for x in a.local.split(",") if x) if 1 <= n <= have]
    if counts and 1 not in counts:
        counts = [1] + counts  # the reference
    record = {
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "machine": machine(),
        "gpus_visible": have,
        "cores": os.cpu_count(),
        "scene": a.scene,
        "detector": a.detector,
        "set": a.set,
        "configs": {},
    }
    work = Path(tempfile.mkdtemp(prefix="sarship-scaling-"))
    try:
        for n in counts:
            env = {**os.environ, "CUDA_VISIBLE_DEVICES": ",".join(str(i) for i in range(n))}
            print(f"\n# local-{n}: CUDA_VISIBLE_DEVICES={env['CUDA_VISIBLE_DEVICES']}", flush=True)
            rec = profile(a.scene, a.runs, a.set, env, work / f"local{n}.json", detector=a.detector)
            record["configs"][f"local-{n}"] = {"gpus": n, **summary(rec), "record": rec}
        for n in (int(x) for x in a.external.split(",") if x):
            print(f"\n# external-{n}: dask scheduler + sarship worker", flush=True)
            rec = external(a.scene, a.runs, a.set, n, have, work, a.detector)
            record["configs"][f"external-{n}"] = {"gpus": min(have, n), **summary(rec), "record": rec}
        warm_counts = [n for n in (int(x) for x in a.warm.split(",") if x) if 1 <= n <= have]
        if warm_counts and 1 not in warm_counts:
            warm_counts = [1] + warm_counts
        for n in warm_counts:
            env = {**os.environ, "CUDA_VISIBLE_DEVICES": ",".join(str(i) for i in range(n))}
            print(
                f"\n# warm-{n}: sarship warm start --device gpu, CUDA_VISIBLE_DEVICES={env['CUDA_VISIBLE_DEVICES']}",
                flush=True,
            )
            rec = profile(
                a.scene, a.runs, a.set, env, work / f"warm{n}.json", detector=a.detector, extra=["--warm", "gpu"]
            )
            record["configs"][f"warm-{n}"] = {"gpus": n, **summary(rec), "record": rec}
        first = next(iter(record["configs"].values()))

        def base(name: str) -> float:  # the same family's one-GPU run, else local-1 (else the first)
            fam = name.rsplit("-", 1)[0]
            return record["configs"].get(f"{fam}-1", record["configs"].get("local-1", first))["warm_best_s"]

        print(f"\n# {record['date']}  {record['machine']}  {have} GPU(s), {record['cores']} cores")
        print(
            "| config | GPUs | workers | warm best s | warm median s | cold s | speed-up vs its 1-GPU run | "
            + " | ".join(STAGES)
            + " |"
        )
        print("|---" * (7 + len(STAGES)) + "|")
        for name, c in record["configs"].items():
            c["speedup"] = round(base(name) / c["warm_best_s"], 3)
            if "local-1" in record["configs"]:
                c["speedup_vs_local_1"] = round(record["configs"]["local-1"]["warm_best_s"] / c["warm_best_s"], 3)
            shares = " | ".join(f"{100 * c['shares'].get(k, 0):.0f}%" for k in STAGES)
            print(
                f"| {name} | {c['gpus']} | {c['workers']} | {c['warm_best_s']:.2f} | {c['warm_median_s']:.2f} | "
                f"{c['cold_s']:.2f} | {c['speedup']:.2f}x | {shares} |"
            )
        if a.json:
            Path(a.json).write_text(json.dumps(record, indent=1))
            print(f"# record: {a.json}")
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
