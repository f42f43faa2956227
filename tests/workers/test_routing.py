"""Tile placement (GPU / CPU workers) and ``sarship worker``, on CPU-only machines.

The GPU side of routing (tiles landing on pinned GPU workers) is in tests/workers/test_gpu.py and
runs where a GPU exists; here: the placement rules, a real ``dask scheduler`` with
``sarship worker`` CPU processes next to a worker that advertises ``GPU=1``, and errors.
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import time

import pytest
from conftest import blobs_scene as _blobs
from conftest import write_scene

from sarship.pipeline.errors import InputError
from sarship.workers.gpus import parse_gpus, worker_specs
from sarship.workers.routing import plan

GPU_W = {"tcp://a:1": {"resources": {"GPU": 1}}}
CPU_W = {"tcp://b:1": {"resources": {"CPU": 1}}, "tcp://b:2": {"resources": {"CPU": 1}}}
PLAIN_W = {"tcp://c:1": {"resources": {}}}


def test_plan_rules():
    assert plan("auto", "ca_cfar", True, {**GPU_W, **CPU_W}).submit == {"resources": {"GPU": 1}}
    assert plan("gpu", "ca_cfar", True, GPU_W).device == "gpu"
    p = plan("auto", "os_cfar", False, {**GPU_W, **CPU_W})
    assert p.device == "cpu" and p.submit == {"resources": {"CPU": 1}} and "no GPU code" in p.reason
    assert plan("cpu", "ca_cfar", True, {**GPU_W, **CPU_W}).submit == {"resources": {"CPU": 1}}
    assert plan("auto", "ca_cfar", True, CPU_W).device == "cpu"
    # plain workers (no resources) cannot match a resource restriction: an address list
    p = plan("cpu", "ca_cfar", True, {**GPU_W, **CPU_W, **PLAIN_W})
    assert p.submit["workers"] == sorted([*CPU_W, *PLAIN_W]) and p.submit["allow_other_workers"] is False
    assert plan("auto", "ca_cfar", True, PLAIN_W).submit == {}  # a plain cluster: unrestricted
    assert plan("cpu", "ca_cfar", True, GPU_W).submit == {}  # GPU-only cluster runs CPU code too
    with pytest.raises(InputError, match="no GPU worker"):
        plan("gpu", "ca_cfar", True, CPU_W)
    with pytest.raises(InputError, match="no GPU implementation"):
        plan("gpu", "os_cfar", False, GPU_W)
    with pytest.raises(InputError, match="auto, cpu or gpu"):
        plan("tpu", "ca_cfar", True, GPU_W)


def test_worker_specs_pin_and_advertise():
    specs = worker_specs(["0", "3"], 2, prefix="h-")
    assert list(specs) == ["h-gpu0", "h-gpu3", "h-cpu0", "h-cpu1"]
    g = specs["h-gpu3"]["options"]
    assert g["env"]["CUDA_VISIBLE_DEVICES"] == "3" and g["resources"] == {"GPU": 2} and g["nthreads"] == 2
    one = worker_specs(["0"], 0, prefix="h-", gpu_threads=1)["h-gpu0"]["options"]
    assert one["resources"] == {"GPU": 1} and one["nthreads"] == 1
    c = specs["h-cpu1"]["options"]
    assert c["resources"] == {"CPU": 1} and c["env"]["CUDA_VISIBLE_DEVICES"] == ""  # hidden, NVML-safe


def test_worker_specs_processes_per_gpu(monkeypatch):
    """gpu_procs > 1: that many pinned worker processes per GPU, each advertising its threads;
    the local cluster's count: SARSHIP_GPU_PROCS, else a quarter of the cores per GPU, at most 4 per GPU
    and 4 in all (one per GPU beyond four)."""

    from sarship.workers import cluster

    specs = worker_specs(["0", "1"], 1, prefix="h-", gpu_procs=3)
    assert list(specs) == ["h-gpu0-0", "h-gpu0-1", "h-gpu0-2", "h-gpu1-0", "h-gpu1-1", "h-gpu1-2", "h-cpu0"]
    assert {specs[n]["options"]["env"]["CUDA_VISIBLE_DEVICES"] for n in ("h-gpu1-0", "h-gpu1-2")} == {"1"}
    assert all(specs[n]["options"]["resources"] == {"GPU": 2} for n in specs if "gpu" in n)
    monkeypatch.setenv("SARSHIP_GPU_PROCS", "6")
    assert cluster.gpu_procs(2) == 6
    monkeypatch.setenv("SARSHIP_GPU_PROCS", "many")
    with pytest.raises(InputError, match="SARSHIP_GPU_PROCS"):
        cluster.gpu_procs(1)
    monkeypatch.delenv("SARSHIP_GPU_PROCS")
    monkeypatch.setattr(cluster.os, "cpu_count", lambda: 16)
    assert (cluster.gpu_procs(1), cluster.gpu_procs(2), cluster.gpu_procs(8)) == (4, 2, 1)
    monkeypatch.setattr(cluster.os, "cpu_count", lambda: 64)
    assert (cluster.gpu_procs(1), cluster.gpu_procs(2), cluster.gpu_procs(3), cluster.gpu_procs(4)) == (4, 2, 1, 1)
    # the warm cluster starts once: a quarter of the cores per GPU, at most 4 per GPU, no cap in all
    assert [cluster.gpu_procs(n, long_lived=True) for n in (1, 2, 4, 8)] == [4, 4, 4, 2]
    monkeypatch.setattr(cluster.os, "cpu_count", lambda: 4)
    assert cluster.gpu_procs(1) == 1


def test_parse_gpus(monkeypatch):
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "2,5")
    assert parse_gpus("all") == ["2", "5"] and parse_gpus("5") == ["5"] and parse_gpus("none") == []
    with pytest.raises(InputError, match="GPU 7 not visible"):
        parse_gpus("7")
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "-1")
    assert parse_gpus("all") == []
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "")
    assert parse_gpus("all") == []
    with pytest.raises(InputError, match="no GPU is visible"):
        parse_gpus("0")


@pytest.fixture
def blobs_scene(tmp_path):
    return write_scene(tmp_path / "s.zarr", {"intensity": _blobs((300, 260))}, tile=64, looks=1.0)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _cli(*args, timeout=300):
    return subprocess.run(
        [sys.executable, "-m", "sarship", *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        env={**os.environ, "CUDA_VISIBLE_DEVICES": ""},
    )


@pytest.mark.slow  # ~30 s of worker processes; the placement rules are tested without them above
def test_mixed_cluster_cpu_tiles_avoid_gpu_worker(tmp_path, blobs_scene):
    """Real processes: ``dask scheduler``, ``sarship worker --gpus none --cpus 2`` and a
    ``dask worker`` advertising GPU=1. CPU tiles must all run on the two CPU workers (a
    detector without GPU code is refused by ``plan``: test_plan_rules; every detector has GPU
    code in this version)."""
    port = _free_port()
    addr = f"tcp://127.0.0.1:{port}"
    env = {**os.environ, "CUDA_VISIBLE_DEVICES": ""}  # "" hides GPUs ("-1" fails Dask's NVML monitor on GPU hosts)
    procs = [
        subprocess.Popen(
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
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            env=env,
        )
    ]
    try:
        time.sleep(2)
        procs.append(
            subprocess.Popen(
                [
                    sys.executable,
                    "-m",
                    "sarship",
                    "worker",
                    "--scheduler",
                    addr,
                    "--gpus",
                    "none",
                    "--cpus",
                    "2",
                    "--name",
                    "cpuhost",
                ],
                stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL,
                env=env,
            )
        )
        procs.append(
            subprocess.Popen(
                [
                    sys.executable,
                    "-m",
                    "distributed.cli.dask_worker",
                    addr,
                    "--nthreads",
                    "1",
                    "--resources",
                    "GPU=1",
                    "--name",
                    "gpuhost-gpu0",
                    "--no-dashboard",
                ],
                stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL,
                env=env,
            )
        )
        from distributed import Client

        with Client(addr, timeout="30s") as client:
            client.wait_for_workers(3, timeout=120)
            names = {w["name"]: w["resources"] for w in client.scheduler_info(n_workers=-1)["workers"].values()}
        assert names["cpuhost-cpu0"] == {"CPU": 1} and names["gpuhost-gpu0"] == {"GPU": 1}
        out = _cli(
            "detect",
            str(blobs_scene),
            "--detector",
            "ca_cfar",
            "--out",
            str(tmp_path / "o"),
            "--scheduler",
            addr,
            "--device",
            "cpu",
        )
        assert out.returncode == 0, out.stderr
        run = json.loads((tmp_path / "o" / "run.json").read_text())
        per = run["tiles"]["per_tile"]
        assert len(per) > 4
        assert {t["worker"] for t in per} <= {"cpuhost-cpu0", "cpuhost-cpu1"}
        assert {t["device"] for t in per} == {"cpu"} and run["device"] == "cpu"
        assert run["placement"]["restriction"] == {"resources": {"CPU": 1}}
    finally:
        for p in reversed(procs):
            p.terminate()
        for p in procs:
            try:
                p.wait(timeout=30)
            except subprocess.TimeoutExpired:
                p.kill()


def test_gpu_device_without_gpu_workers_is_refused(tmp_path, blobs_scene, client):
    from sarship.workers.jobs import run_detection

    with pytest.raises(InputError, match="no GPU worker"):
        run_detection(blobs_scene, "ca_cfar", out_dir=tmp_path / "o", client=client, device="gpu", progress=False)
    assert not (tmp_path / "o" / "run.json").exists()


def test_parameters_without_gpu_code_go_to_cpu_workers(tmp_path, blobs_scene, client):
    """lmm's default fit (the contamination refusal) and its censored fits have no CUDA code:
    such a job is placed like a detector without GPU code (CPU workers under --device auto,
    one line under --device gpu), not run by the CPU code inside GPU workers' processes."""
    from sarship.pipeline import detectors
    from sarship.workers.jobs import run_detection

    spec = detectors.get("lmm")
    assert spec.gpu and not spec.gpu_for(spec.params())
    assert spec.gpu_for(spec.params(refuse_weight=0))
    assert not spec.gpu_for(spec.params(refuse_weight=0, censor=0.1))
    assert detectors.get("ca_cfar").gpu_for(detectors.get("ca_cfar").params())
    with pytest.raises(InputError, match="no GPU implementation for these parameters"):
        run_detection(blobs_scene, "lmm", out_dir=tmp_path / "o", client=client, device="gpu", progress=False)
    assert not (tmp_path / "o").exists()
    # a cluster with a GPU worker: auto places lmm's default on the CPU workers, refuse_weight=0 on the GPU
    workers = {"tcp://a:1": {"resources": {"GPU": 1}}, "tcp://b:1": {"resources": {"CPU": 1}}}
    assert plan("auto", "lmm", spec.gpu_for(spec.params()), workers).device == "cpu"
    assert plan("auto", "lmm", spec.gpu_for(spec.params(refuse_weight=0)), workers).device == "gpu"


def test_worker_cli_errors():
    out = _cli("worker", "--scheduler", "tcp://127.0.0.1:1", "--gpus", "0", timeout=60)
    assert out.returncode == 2 and "no GPU is visible" in out.stderr and "Traceback" not in out.stderr
    out = _cli("worker", "--scheduler", "tcp://127.0.0.1:1", "--gpus", "none", "--cpus", "0", timeout=60)
    assert out.returncode == 2 and "nothing to start" in out.stderr
    # no scheduler at the address: the check the command makes before it starts a worker, with a
    # shorter wait than the command's 10 s (the command itself: the slow test below)
    import asyncio

    from sarship.workers.worker import _reachable

    addr = f"tcp://127.0.0.1:{_free_port()}"
    with pytest.raises(InputError, match=f"cannot reach Dask scheduler at '{addr}'"):
        asyncio.run(_reachable(addr, timeout=1.0))


@pytest.mark.slow  # waits out the command's 10 s connection timeout; its check, sooner: test_worker_cli_errors
def test_worker_cli_without_a_scheduler_is_one_line():
    out = _cli("worker", "--scheduler", f"tcp://127.0.0.1:{_free_port()}", "--gpus", "none", "--cpus", "1", timeout=60)
    assert out.returncode == 2 and "cannot reach Dask scheduler" in out.stderr and "Traceback" not in out.stderr


def test_kept_blocks_never_pull_tiles_onto_workers_the_placement_excludes(tmp_path):
    """A cluster whose workers do not all match the placement (a worker advertising only GPU
    next to a CPU worker, device cpu): a texture-masked run keeps every tile on the CPU worker,
    every detection takes its tile's land-pass read, and no worker is lost. Dask's work stealing
    ignores a resource restriction for a task whose worker preference is loose
    (distributed/stealing.py ``_get_thief``): when each detection asked for the worker that had
    kept its block (``workers=[...]``, ``allow_other_workers``), tiles were stolen by the GPU
    worker, whose task state then failed (KeyError 'CPU') and which left the cluster. The reads
    are now Dask data the tasks depend on, which stealing moves only among valid workers."""
    import logging

    import dask
    import numpy as np
    from distributed import Client, Scheduler, SpecCluster, Worker

    from sarship.workers.jobs import run_detection

    rng = np.random.default_rng(11)
    x = rng.gamma(4.0, 0.25, (1536, 1536)).astype(np.float32)
    for r, c in ((40, 40), (700, 900), (1400, 100)):
        x[r : r + 4, c : c + 8] += 60.0
    scene = write_scene(tmp_path / "s.zarr", {"intensity": x}, tile=128, looks=4.0)
    workers = {
        "cpu0": {"cls": Worker, "options": {"name": "cpu0", "nthreads": 1, "resources": {"CPU": 1}}},
        "gpu0": {"cls": Worker, "options": {"name": "gpu0", "nthreads": 2, "resources": {"GPU": 1}}},
    }
    # stealing rebalances every 5 ms instead of 100 (the tiles take milliseconds here, seconds on a band)
    with (
        dask.config.set({"distributed.scheduler.work-stealing-interval": "5ms"}),
        SpecCluster(
            workers=workers,
            scheduler={"cls": Scheduler, "options": {"dashboard_address": ":0"}},
            silence_logs=logging.CRITICAL,
        ) as cluster,
        Client(cluster) as client,
    ):
        client.wait_for_workers(2, timeout=60)
        run = run_detection(
            scene,
            "ca_cfar",
            {"land_mask": "texture", "guard": 41, "background": 81},
            out_dir=tmp_path / "o",
            client=client,
            device="cpu",
            progress=False,
            tile=128,
        )
        time.sleep(1.0)  # a worker whose task state failed is gone by now
        names = sorted(w["name"] for w in client.scheduler_info(n_workers=-1)["workers"].values())
    assert names == ["cpu0", "gpu0"]
    per = run["tiles"]["per_tile"]
    assert len(per) == 144 and {t["worker"] for t in per} == {"cpu0"}
    assert {t["block_from"] for t in per} == {"land pass"}
    assert run["detections"] >= 3


def _plugins_and_warmup(dask_worker):
    import threading

    for t in threading.enumerate():
        if t.name == "sarship-cuda-warmup":
            t.join(timeout=60)
    return sorted(dask_worker.plugins), any(
        t.name == "sarship-cuda-warmup" and t.is_alive() for t in threading.enumerate()
    )


def test_gpu_worker_spec_starts_with_its_cuda_warmup():
    """A GPU worker of :func:`worker_specs` (a real Nanny process) starts with the CUDA warm-up
    plugin, whose thread finishes once the worker runs: it creates the context on a GPU host
    and does nothing where CuPy or the GPU is missing (this CPU machine), without failing the
    worker."""
    from distributed import Client, Scheduler, SpecCluster

    from sarship.workers.gpus import CudaWarmup

    specs = worker_specs(["0"], 0, prefix="w-", gpu_procs=1, gpu_threads=1, silence_logs=50)
    assert any(isinstance(p, CudaWarmup) for p in specs["w-gpu0"]["options"]["plugins"])
    with (
        SpecCluster(
            workers=specs, scheduler={"cls": Scheduler, "options": {"dashboard_address": ":0"}}, silence_logs=50
        ) as cluster,
        Client(cluster) as client,
    ):
        client.wait_for_workers(1, timeout=60)
        ((plugins, alive),) = client.run(_plugins_and_warmup).values()
    assert "sarship-cuda-warmup" in plugins and not alive
