"""One job's latency through the running service: POST to ``successful`` (issue 17's service target).

Starts a real ``sarship serve`` (its own temporary data folder, the scene under ``scenes/``, its
own warm local Dask cluster: ``SARSHIP_WORKERS`` CPU worker processes, or the GPU workers it
starts on a GPU host, or ``--scheduler`` an existing cluster), runs one warm-up job (the
workers' first compile and imports are not a job's latency), then ``--jobs`` jobs one after the
other: each ``POST /processes/{detector}/execution`` (asynchronous), then ``GET /jobs/{id}``
every ``--poll`` seconds until ``successful``. It reports each job's latency (POST sent to the
status read as ``successful``: the client's view, including the poll interval's granularity),
the server's own ``started - created`` and ``finished - started`` from the job record, and the
stages of the job's ``run.json`` (land pass, tiles, merge...).

Reference, measured in the same run: the same detection by ``sarship detect`` as a user types it
(a fresh process with its own local cluster, second run), so the ratio shows what a warm
service saves.

The scene: ``--side`` square float32 1-look gamma sea with ships (``bench_end_to_end.make_npy``),
``sarship ingest`` (tile 2048), or ``--scene`` an existing store (hard-linked into the service's scenes folder).

Usage: python bench/bench_service_latency.py [--side 8192] [--jobs 5] [--set looks=1] [--workers 2]
    [--device auto] [--json out.json]
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from bench_end_to_end import make_npy  # noqa: E402
from bench_profile import key_values, sarship_exe, stages  # noqa: E402
from bench_service_load import free_port, start_server, stop_server  # noqa: E402
from common import machine  # noqa: E402


def _iso(s: str) -> float:
    return datetime.datetime.fromisoformat(s.replace("Z", "+00:00")).timestamp()


def one_job(url: str, detector: str, inputs: dict, poll: float, timeout: float = 600.0) -> dict:
    import httpx

    t0 = time.perf_counter()
    r = httpx.post(f"{url}/processes/{detector}/execution", json={"inputs": inputs}, timeout=60)
    if r.status_code != 201:
        raise RuntimeError(f"POST refused: {r.status_code} {r.text[:500]}")
    job = r.json()["jobID"]
    t_post = time.perf_counter() - t0
    with httpx.Client(timeout=60) as c:
        while True:
            st = c.get(f"{url}/jobs/{job}").json()
            if st["status"] in ("successful", "failed", "dismissed"):
                break
            if time.perf_counter() - t0 > timeout:
                raise RuntimeError(f"job {job} not finished after {timeout:.0f} s")
            time.sleep(poll)
    latency = time.perf_counter() - t0
    if st["status"] != "successful":
        raise RuntimeError(f"job {job} {st['status']}: {st.get('message')}")
    return {
        "job": job,
        "latency_s": latency,
        "post_s": t_post,
        "queued_s": _iso(st["started"]) - _iso(st["created"]),
        "server_run_s": _iso(st["finished"]) - _iso(st["started"]),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--side", type=int, default=8192)
    ap.add_argument("--scene", help="an existing scene store instead of making one")
    ap.add_argument("--detector", default="ca_cfar")
    ap.add_argument("--set", action="append", default=["looks=1"], metavar="K=V")
    ap.add_argument("--device", default="auto", choices=("auto", "cpu", "gpu"))
    ap.add_argument("--jobs", type=int, default=5)
    ap.add_argument("--poll", type=float, default=0.02, help="status poll interval, seconds")
    ap.add_argument("--workers", type=int, default=os.cpu_count() or 1, help="SARSHIP_WORKERS (CPU processes)")
    ap.add_argument("--scheduler", help="SARSHIP_SCHEDULER: an existing Dask cluster")
    ap.add_argument("--no-reference", action="store_true")
    ap.add_argument("--json")
    ap.add_argument("--workdir")
    a = ap.parse_args()
    work = Path(tempfile.mkdtemp(prefix="sarship-latency-", dir=a.workdir))
    record: dict = {
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "machine": machine(),
        "detector": a.detector,
        "set": a.set,
        "device": a.device,
        "workers": a.workers,
        "scheduler": a.scheduler,
        "jobs": [],
    }
    proc = None
    try:
        data = work / "data"
        (data / "scenes").mkdir(parents=True)
        scene = data / "scenes" / "s1.zarr"
        if a.scene:  # hard links (a copy across file systems): the service refuses a symlink out of its folders

            def link(src, dst):
                try:
                    os.link(src, dst)
                except OSError:
                    shutil.copy2(src, dst)

            shutil.copytree(Path(a.scene).resolve(), scene, copy_function=link)
        else:
            npy = work / "s.npy"
            make_npy(str(npy), a.side, 1.0)
            p = subprocess.run(
                [sarship_exe(), "ingest", str(npy), "--out", str(scene), "--kind", "intensity", "--looks", "1"],
                capture_output=True,
                text=True,
            )
            if p.returncode != 0:
                raise SystemExit(f"ingest failed: {p.stderr[-2000:]}")
            npy.unlink()
        from sarship.pipeline.scene import open_scene

        H, W = open_scene(scene).shape
        record["scene"] = {"shape": [H, W]}
        port = free_port()
        url = f"http://127.0.0.1:{port}"
        t = time.perf_counter()
        proc = start_server(data, port, a.workers, 1, work / "server.log", a.scheduler, gpus=a.device != "cpu")
        record["server_start_s"] = round(time.perf_counter() - t, 3)
        inputs = {"scene": "s1", "device": a.device, **key_values(a.set)}
        for k, v in list(inputs.items()):  # numbers as numbers (the REST inputs are JSON)
            try:
                inputs[k] = json.loads(v) if isinstance(v, str) and k not in ("scene", "device") else v
            except json.JSONDecodeError:
                pass
        warm = one_job(url, a.detector, inputs, a.poll)
        record["warmup"] = warm
        print(f"# {record['date']}  {record['machine']}")
        print(
            f"# service: {a.detector} {inputs} on {H}x{W} ({H * W / 1e6:.1f} Mpx); server start "
            f"{record['server_start_s']:.1f} s; warm-up job {warm['latency_s']:.2f} s"
        )
        for i in range(a.jobs):
            j = one_job(url, a.detector, inputs, a.poll)
            run = json.loads((data / "jobs" / j["job"] / "run.json").read_text())
            j["stages"] = {
                n: round(s, 4)
                for n, s in stages(run, run["timings"]["total_s"])
                if n not in ("outside run_detection", "unaccounted")
            }
            record["jobs"].append(j)
            top = sorted(j["stages"].items(), key=lambda kv: -kv[1])[:4]
            print(
                f"job {i + 1}: POST -> successful {j['latency_s']:.2f} s (queued {j['queued_s']:.2f}, server run "
                f"{j['server_run_s']:.2f}); " + ", ".join(f"{n} {s:.2f}" for n, s in top)
            )
        lat = [j["latency_s"] for j in record["jobs"]]
        record["latency_best_s"], record["latency_median_s"] = min(lat), statistics.median(lat)
        print(
            f"latency best {min(lat):.2f} s, median {statistics.median(lat):.2f} s "
            f"({H * W / 1e6 / statistics.median(lat):.1f} Mpx/s)"
        )
        stop_server(proc)
        proc = None
        if not a.no_reference:
            out = work / "ref"
            cmd = [
                sarship_exe(),
                "detect",
                str(scene),
                "--detector",
                a.detector,
                "--device",
                a.device,
                "--out",
                str(out),
                "--overwrite",
            ] + sum((["--set", s] for s in a.set), [])
            walls = []
            for _ in range(2):
                t = time.perf_counter()
                p = subprocess.run(cmd, capture_output=True, text=True)
                walls.append(time.perf_counter() - t)
                if p.returncode != 0:
                    raise SystemExit(f"sarship detect failed: {p.stderr[-2000:]}")
            record["reference"] = {
                "what": "sarship detect as a user types it (own local cluster), second run",
                "seconds": walls[-1],
                "first_s": walls[0],
            }
            print(
                f"reference: sarship detect {walls[-1]:.2f} s (first {walls[0]:.2f}); service median latency is "
                f"{walls[-1] / statistics.median(lat):.2f}x faster"
            )
        if a.json:
            Path(a.json).write_text(json.dumps(record, indent=1))
            print(f"# record: {a.json}")
    finally:
        if proc is not None:
            stop_server(proc)
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
