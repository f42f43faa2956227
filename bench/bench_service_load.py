"""The job service under load: many small jobs submitted at once while clients poll status.

Starts a real ``sarship serve`` (its own temporary data folder with one small scene, its own
local Dask cluster, ``SARSHIP_WORKERS`` worker processes, ``SARSHIP_CONCURRENCY`` jobs at
once), then on loopback

- submits ``--jobs`` small ``ca_cfar`` jobs (one tile each) from one asyncio client with
  ``--submitters`` POSTs in flight,
- while ``--pollers`` processes poll ``GET /jobs/{id}`` of the submitted jobs as fast as they
  can (each bounded by ``--max-polls`` requests and the run by ``--timeout`` seconds),

and reports the submit rate, jobs/s completed (first submit to last ``finished``), Mpx/s,
status-poll and submit latency p50/p99/max, and the most jobs in flight (accepted, not yet
finished) and running at once (from the store's own timestamps). It then checks that no job
was lost: every job reached ``successful``, appears exactly once in ``GET /jobs``, ran once
(``attempts == 1``), and the store holds no other job; the exit status is 1 if not.

Reference, measured in the same run after the server is stopped: the same jobs run by
``workers.jobs.run_detection`` directly on a LocalCluster of the same size, ``--concurrency``
at a time, without the service; ``ratio`` = service Mpx/s / reference Mpx/s shows what the
API, the SQLite store and the runner cost.

Usage: python bench/bench_service_load.py [--jobs 200] [--pollers 4] [--concurrency 2] [--out r.json]
"""

from __future__ import annotations

import argparse
import datetime
import json
import logging
import os
import random
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
from common import machine  # noqa: E402

PARAMS = {"pfa": 1e-4, "guard": 11, "background": 31, "min_area_px": 1}


def make_scene(path: Path, side: int, tile: int, seed: int = 1) -> None:
    """An L = 2 gamma clutter scene with a few bright ships, written with the project's store."""
    from sarship.pipeline.scene import create_scene, finalize_scene

    rng = np.random.default_rng(seed)
    x = rng.gamma(2.0, 0.5, (side, side)).astype(np.float32)
    for _ in range(max(side // 32, 2)):
        r, c = int(rng.integers(0, side - 6)), int(rng.integers(0, side - 12))
        x[r : r + 4, c : c + 10] += 30.0
    g = create_scene(path, (side, side), {"intensity": x.dtype}, tile=tile, attrs={"kind": "intensity", "looks": 2.0})
    g["intensity"][:] = x
    finalize_scene(path)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start_cluster(workers: int, log: Path) -> tuple[subprocess.Popen, str]:
    """A Dask scheduler and ``workers`` CPU worker processes (``sarship worker``), each in its
    own process group; the scheduler address."""
    from distributed import Client

    port = free_port()
    addr = f"tcp://127.0.0.1:{port}"
    env = {**os.environ, "CUDA_VISIBLE_DEVICES": ""}
    out = open(log, "w")
    sched = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "distributed.cli.dask_scheduler",
            "--host",
            "127.0.0.1",
            "--port",
            str(port),
            "--dashboard-address",
            ":0",
        ],
        stdout=out,
        stderr=subprocess.STDOUT,
        env=env,
        cwd=REPO,
        start_new_session=True,
    )
    wk = subprocess.Popen(
        [sys.executable, "-m", "sarship", "worker", "--scheduler", addr, "--gpus", "none", "--cpus", str(workers)],
        stdout=out,
        stderr=subprocess.STDOUT,
        env=env,
        cwd=REPO,
        start_new_session=True,
    )
    t_end = time.time() + 120
    while time.time() < t_end:
        try:
            with Client(addr, timeout="2s") as c:
                if len(c.scheduler_info(n_workers=-1)["workers"]) >= workers:
                    return (sched, wk), addr
        except OSError:
            pass
        time.sleep(0.5)
    raise RuntimeError(f"the Dask cluster did not start: {log.read_text()[-2000:]}")


def start_server(
    data: Path, port: int, workers: int, concurrency: int, log: Path, scheduler: str | None = None, gpus: bool = False
) -> subprocess.Popen:
    """``sarship serve`` on ``data``; its local cluster has ``workers`` CPU worker processes and,
    with ``gpus``, its GPU workers (hidden otherwise)."""
    import httpx

    env = {**os.environ, "SARSHIP_WORKERS": str(workers), "SARSHIP_CONCURRENCY": str(concurrency)}
    if not gpus:
        env["CUDA_VISIBLE_DEVICES"] = ""
    if scheduler:
        env["SARSHIP_SCHEDULER"] = scheduler
    proc = subprocess.Popen(
        [sys.executable, "-m", "sarship", "serve", "--data", str(data), "--port", str(port)],
        stdout=open(log, "w"),
        stderr=subprocess.STDOUT,
        env=env,
        cwd=REPO,
        start_new_session=True,
    )
    t_end = time.time() + 180
    while time.time() < t_end:
        if proc.poll() is not None:
            raise RuntimeError(f"server exited: {log.read_text()[-2000:]}")
        try:
            if httpx.get(f"http://127.0.0.1:{port}/readyz", timeout=2).status_code == 200:
                return proc
        except httpx.HTTPError:
            pass
        time.sleep(0.3)
    stop_server(proc)
    raise RuntimeError("server did not become ready")


def stop_server(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGTERM)  # uvicorn and its Dask cluster
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(timeout=30)


def pct(xs: list[float], q: float) -> float:
    return float(np.percentile(np.asarray(xs), q)) if xs else float("nan")


def ts(s: str | None) -> float | None:
    return datetime.datetime.fromisoformat(s).timestamp() if s else None


def max_overlap(intervals: list[tuple[float, float]]) -> int:
    ev = sorted([(a, 1) for a, _ in intervals] + [(b, -1) for _, b in intervals], key=lambda e: (e[0], e[1]))
    cur = best = 0
    for _, d in ev:
        cur += d
        best = max(best, cur)
    return best


def poller(url: str, ids_q, out_q, max_polls: int, deadline: float, seed: int) -> None:
    """One polling client (its own process, so that its latencies are not GIL waits behind the
    other clients): GET /jobs/{id} of a random submitted job, back to back, until told to stop
    (``None`` on its queue), ``max_polls`` or ``deadline``; sends back its latencies."""
    import queue

    import httpx

    rng = random.Random(seed)
    ids: list[str] = []
    lat: list[float] = []
    errors: list[str] = []
    stop = False
    with httpx.Client(timeout=60) as c:
        while not stop and len(lat) < max_polls and time.time() < deadline:
            try:
                while True:
                    x = ids_q.get(block=not ids, timeout=1.0) if not ids else ids_q.get_nowait()
                    if x is None:
                        stop = True
                        break
                    ids.extend(x)
            except queue.Empty:
                pass
            if stop or not ids:
                continue
            job = ids[rng.randrange(len(ids))]
            t = time.perf_counter()
            r = c.get(f"{url}/jobs/{job}")
            lat.append(time.perf_counter() - t)
            if r.status_code != 200:
                errors.append(f"GET {job}: {r.status_code} {r.text[:200]}")
    out_q.put((lat, errors))


async def submit_all(url: str, n: int, concurrency: int, on_ids) -> tuple[list[str], list[float], list[str]]:
    """``n`` POSTs, ``concurrency`` at a time, from one asyncio client; job ids as they come."""
    import asyncio

    import httpx

    ids: list[str] = []
    lat: list[float] = []
    errors: list[str] = []
    sem = asyncio.Semaphore(concurrency)
    body = {"inputs": {"scene": "s1", **PARAMS}}
    async with httpx.AsyncClient(timeout=60, limits=httpx.Limits(max_connections=concurrency)) as c:

        async def one(k: int) -> None:
            async with sem:
                t = time.perf_counter()
                r = await c.post(f"{url}/processes/ca_cfar/execution", json=body)
                lat.append(time.perf_counter() - t)
            if r.status_code != 201:
                errors.append(f"POST {k}: {r.status_code} {r.text[:200]}")
                return
            ids.append(r.json()["jobID"])
            on_ids([ids[-1]])

        await asyncio.gather(*(one(k) for k in range(n)))
    return ids, lat, errors


def load(url: str, a) -> dict:
    """Submit ``a.jobs`` jobs while ``a.pollers`` processes poll their status; wait for all."""
    import asyncio
    import multiprocessing as mp

    import httpx

    ctx = mp.get_context("spawn")
    deadline = time.time() + a.timeout
    queues = [ctx.Queue() for _ in range(a.pollers)]
    out_q = ctx.Queue()
    procs = [
        ctx.Process(target=poller, args=(url, q, out_q, a.max_polls, deadline, i), daemon=True)
        for i, q in enumerate(queues)
    ]
    for p in procs:
        p.start()
    time.sleep(2.0)  # the pollers' interpreters start (spawn) before the clock does

    def share(new: list[str]) -> None:
        for q in queues:
            q.put(new)

    t0 = time.time()
    ids, post_lat, errors = asyncio.run(submit_all(url, a.jobs, a.submitters, share))
    t_submitted = time.time()
    # completion: one watcher reads the whole list (cheap) until every job is final
    with httpx.Client(timeout=60) as c:
        mine = set(ids)
        while time.time() < deadline:
            listed = [j for j in c.get(f"{url}/jobs", params={"limit": 10000}).json()["jobs"] if j["jobID"] in mine]
            if len(listed) >= len(ids) and all(j["status"] in ("successful", "failed", "dismissed") for j in listed):
                break
            time.sleep(0.25)
    t_end = time.time()
    for q in queues:
        q.put(None)
    poll_lat: list[float] = []
    for _ in procs:
        lat, errs = out_q.get(timeout=120)
        poll_lat += lat
        errors += errs
    for p in procs:
        p.join(timeout=30)
    return {
        "ids": ids,
        "post_lat": post_lat,
        "poll_lat": poll_lat,
        "errors": errors,
        "t0": t0,
        "t_submitted": t_submitted,
        "t_end": t_end,
    }


def check(url: str, ids: list[str], n_expected: int) -> tuple[list[str], list[dict]]:
    """Problems found (empty: no job lost) and the final job documents."""
    import httpx

    listed = httpx.get(f"{url}/jobs", params={"limit": 10000}, timeout=60).json()["jobs"]
    problems = []
    if len(ids) != n_expected:
        problems.append(f"{n_expected - len(ids)} submissions were not accepted")
    if len(set(ids)) != len(ids):
        problems.append("duplicate job ids returned by POST")
    counts: dict[str, int] = {}
    for j in listed:
        counts[j["jobID"]] = counts.get(j["jobID"], 0) + 1
    for i in ids:
        if counts.get(i, 0) != 1:
            problems.append(f"job {i} listed {counts.get(i, 0)} times")
    extra = set(counts) - set(ids)
    if extra:
        problems.append(f"{len(extra)} jobs in the store that nobody submitted")
    mine = {j["jobID"]: j for j in listed if j["jobID"] in set(ids)}
    for i, j in mine.items():
        if j["status"] != "successful":
            problems.append(f"job {i} ended {j['status']}: {j['message']}")
        elif j["attempts"] != 1:
            problems.append(f"job {i} ran {j['attempts']} times")
    return problems, list(mine.values())


def reference(scene: Path, work: Path, n: int, workers: int, concurrency: int) -> float:
    """Wall time of the same ``n`` jobs by ``run_detection`` on a LocalCluster, no service."""
    from distributed import Client, LocalCluster

    from sarship.workers.jobs import run_detection

    with (
        LocalCluster(
            n_workers=workers, threads_per_worker=1, dashboard_address=":0", silence_logs=logging.ERROR
        ) as cluster,
        Client(cluster) as client,
    ):
        run_detection(
            scene, "ca_cfar", dict(PARAMS), out_dir=work / "warm", client=client, progress=False, overwrite=True
        )
        t = time.perf_counter()
        with ThreadPoolExecutor(concurrency) as pool:
            list(
                pool.map(
                    lambda k: run_detection(
                        scene,
                        "ca_cfar",
                        dict(PARAMS),
                        out_dir=work / f"ref{k}",
                        client=client,
                        progress=False,
                        overwrite=True,
                    ),
                    range(n),
                )
            )
        return time.perf_counter() - t


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--jobs", type=int, default=200)
    ap.add_argument("--pollers", type=int, default=4, help="processes polling GET /jobs/{id} as fast as they can")
    ap.add_argument("--submitters", type=int, default=8, help="POSTs in flight at once while submitting")
    ap.add_argument("--concurrency", type=int, default=2, help="SARSHIP_CONCURRENCY: jobs the server runs at once")
    ap.add_argument("--workers", type=int, default=2, help="SARSHIP_WORKERS: Dask worker processes")
    ap.add_argument("--side", type=int, default=128, help="scene side (pixels)")
    ap.add_argument("--tile", type=int, default=128)
    ap.add_argument("--max-polls", type=int, default=200_000, help="most requests per poller")
    ap.add_argument("--timeout", type=float, default=900.0, help="longest run (seconds)")
    ap.add_argument(
        "--external-cluster",
        action="store_true",
        help="run the Dask scheduler and workers as their own processes (SARSHIP_SCHEDULER) instead of "
        "the server's local cluster, whose scheduler shares the API process",
    )
    ap.add_argument("--no-reference", action="store_true")
    ap.add_argument("--out", type=Path, help="write the results here (JSON)")
    ap.add_argument("--workdir", default=None)
    a = ap.parse_args()

    work = Path(tempfile.mkdtemp(prefix="sarship-load-", dir=a.workdir))
    proc = None
    cluster: tuple[subprocess.Popen, ...] = ()
    try:
        data = work / "data"
        (data / "scenes").mkdir(parents=True)
        make_scene(data / "scenes" / "s1.zarr", a.side, a.tile)
        port = free_port()
        url = f"http://127.0.0.1:{port}"
        t = time.perf_counter()
        scheduler = None
        if a.external_cluster:
            cluster, scheduler = start_cluster(a.workers, work / "cluster.log")
        proc = start_server(data, port, a.workers, a.concurrency, work / "server.log", scheduler)
        t_start = time.perf_counter() - t
        import httpx

        # warm-up: one job (first Numba compile in the workers is not part of the load)
        r = httpx.post(
            f"{url}/processes/ca_cfar/execution",
            headers={"Prefer": "respond-sync"},
            json={"inputs": {"scene": "s1", **PARAMS}},
            timeout=300,
        )
        assert r.status_code == 200, r.text
        warm_id = r.headers["location"].rsplit("/", 1)[-1]
        res = load(url, a)
        ids = res["ids"]
        problems, final = check(url, ids + [warm_id], a.jobs + 1)
        final = [j for j in final if j["jobID"] != warm_id]
        stop_server(proc)
        proc = None
        for p in cluster:
            stop_server(p)
        cluster = ()

        fin = [ts(j["finished"]) for j in final if j["finished"]]
        wall = (max(fin) if fin else res["t_end"]) - res["t0"]
        n_ok = sum(j["status"] == "successful" for j in final)
        mpx = a.side * a.side * n_ok / 1e6
        in_flight = max_overlap([(ts(j["created"]), ts(j["finished"])) for j in final if j["finished"]])
        running = max_overlap([(ts(j["started"]), ts(j["finished"])) for j in final if j["finished"]])
        queue_s = [ts(j["started"]) - ts(j["created"]) for j in final if j["started"]]
        run_s = [ts(j["finished"]) - ts(j["started"]) for j in final if j["finished"]]
        out = {
            "date": str(datetime.date.today()),
            "machine": machine(),
            "jobs": a.jobs,
            "pollers": a.pollers,
            "submitters": a.submitters,
            "concurrency": a.concurrency,
            "workers": a.workers,
            "external_cluster": a.external_cluster,
            "scene": [a.side, a.side],
            "tile": a.tile,
            "params": PARAMS,
            "server_start_s": t_start,
            "submit_s": res["t_submitted"] - res["t0"],
            "submit_rate": len(ids) / (res["t_submitted"] - res["t0"]),
            "wall_s": wall,
            "jobs_per_s": n_ok / wall,
            "mpx_per_s": mpx / wall,
            "polls": len(res["poll_lat"]),
            "polls_per_s": len(res["poll_lat"]) / (res["t_end"] - res["t0"]),
            "poll_p50_ms": 1e3 * pct(res["poll_lat"], 50),
            "poll_p99_ms": 1e3 * pct(res["poll_lat"], 99),
            "poll_max_ms": 1e3 * max(res["poll_lat"], default=float("nan")),
            "post_p50_ms": 1e3 * pct(res["post_lat"], 50),
            "post_p99_ms": 1e3 * pct(res["post_lat"], 99),
            "post_max_ms": 1e3 * max(res["post_lat"], default=float("nan")),
            "max_in_flight": in_flight,
            "max_running": running,
            "queue_p50_s": pct(queue_s, 50),
            "run_p50_s": pct(run_s, 50),
            "run_p99_s": pct(run_s, 99),
            "request_errors": res["errors"][:20],
            "n_request_errors": len(res["errors"]),
            "lost": problems,
        }
        print(f"# {out['date']} {out['machine']}")
        print(
            f"# {a.jobs} ca_cfar jobs on a {a.side}x{a.side} scene (tile {a.tile}), server: {a.workers} Dask "
            f"workers, concurrency {a.concurrency}; {a.submitters} POSTs in flight, {a.pollers} poller processes"
        )
        print(
            f"submit     {out['submit_s']:6.2f} s  {out['submit_rate']:7.1f} jobs/s   POST p50 "
            f"{out['post_p50_ms']:.1f} ms  p99 {out['post_p99_ms']:.1f} ms  max {out['post_max_ms']:.1f} ms"
        )
        print(
            f"complete   {wall:6.2f} s  {out['jobs_per_s']:7.2f} jobs/s  {out['mpx_per_s']:.3f} Mpx/s   "
            f"run p50 {out['run_p50_s'] * 1e3:.0f} ms  p99 {out['run_p99_s'] * 1e3:.0f} ms"
        )
        print(
            f"status     {out['polls']} polls  {out['polls_per_s']:7.0f} /s   GET p50 {out['poll_p50_ms']:.1f} ms  "
            f"p99 {out['poll_p99_ms']:.1f} ms  max {out['poll_max_ms']:.1f} ms"
        )
        print(f"in flight  max {in_flight} accepted-not-finished, max {running} running at once")
        if not a.no_reference:
            ref = reference(data / "scenes" / "s1.zarr", work, a.jobs, a.workers, a.concurrency)
            out["reference_s"] = ref
            out["reference_mpx_per_s"] = a.side * a.side * a.jobs / 1e6 / ref
            out["ratio"] = out["mpx_per_s"] / out["reference_mpx_per_s"]
            print(
                f"reference  {ref:6.2f} s  {a.jobs / ref:7.2f} jobs/s  {out['reference_mpx_per_s']:.3f} Mpx/s  "
                f"(run_detection on a LocalCluster, {a.concurrency} at a time, no service)"
            )
            print(f"ratio      {out['ratio']:.2f} (service / reference Mpx/s)")
        if res["errors"]:
            print(f"request errors: {len(res['errors'])}, first: {res['errors'][0]}")
        print("no job lost" if not problems else f"LOST OR WRONG: {len(problems)} problems, first: {problems[:5]}")
        if a.out:  # (no NaN in the file: a statistic of nothing is null)
            clean = {k: None if isinstance(v, float) and v != v else v for k, v in out.items()}
            a.out.write_text(json.dumps(clean, indent=1))
        return 1 if problems or res["errors"] else 0
    finally:
        if proc is not None:
            stop_server(proc)
        for p in cluster:
            stop_server(p)
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    sys.exit(main())
