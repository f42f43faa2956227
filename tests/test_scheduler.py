"""Integration: `sarship detect --scheduler` against real `dask scheduler` / `dask worker` processes."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import blobs_scene, write_scene

#: the dask command of this interpreter (its bin folder need not be on PATH, e.g. a virtualenv run by path)
DASK = shutil.which("dask", path=os.path.dirname(sys.executable)) or shutil.which("dask")


@pytest.fixture()
def dask_processes(tmp_path):
    yield from _dask_processes(tmp_path, {"alpha": [], "beta": []})


def _dask_processes(tmp_path, workers: dict[str, list[str]]):
    """A `dask scheduler` and one `dask worker` per name (with its extra arguments)."""
    if DASK is None:
        pytest.skip("the 'dask' command is not on PATH")
    sched_file = tmp_path / "scheduler.json"
    env = {**os.environ, "DASK_DISTRIBUTED__LOGGING__DISTRIBUTED": "error"}
    procs = [subprocess.Popen([DASK, "scheduler", "--scheduler-file", str(sched_file), "--port", "0",
                               "--dashboard-address", ":0", "--host", "127.0.0.1"],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env)]
    try:
        for _ in range(300):
            if sched_file.exists() and sched_file.stat().st_size > 0:
                break
            time.sleep(0.1)
        else:
            pytest.fail("dask scheduler did not start")
        address = json.loads(sched_file.read_text())["address"]
        for name, extra in workers.items():
            procs.append(subprocess.Popen([DASK, "worker", address, "--nthreads", "1", "--name", name,
                                           "--no-dashboard", *extra], stdout=subprocess.DEVNULL,
                                          stderr=subprocess.DEVNULL, env=env))
        from distributed import Client

        with Client(address, timeout="20s") as c:
            c.wait_for_workers(len(workers), timeout=60)
        yield address
    finally:
        for p in procs[::-1]:
            p.terminate()
        for p in procs:
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                p.kill()


def test_detect_on_existing_scheduler(tmp_path, dask_processes):
    x = blobs_scene((300, 260), looks=2.0, seed=3)
    scene = write_scene(tmp_path / "s.zarr", {"intensity": x}, tile=64, looks=2.0)
    out = tmp_path / "o"
    res = subprocess.run([sys.executable, "-m", "sarship", "detect", str(scene), "--detector", "ca_cfar",
                          "--scheduler", dask_processes, "--out", str(out), "--tile", "64",
                          "--set", "guard=11", "--set", "background=31", "--set", "min_area_px=1"],
                         capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    assert dask_processes in res.stderr
    run = json.loads((out / "run.json").read_text())
    workers = {t["worker"] for t in run["tiles"]["per_tile"]}
    assert workers <= {"alpha", "beta"} and workers, workers
    assert run["tiles"]["count"] == 5 * 5
    assert run["detections"] >= 5


def test_unreachable_scheduler(tmp_path):
    x = np.ones((32, 32), np.float32)
    scene = write_scene(tmp_path / "s.zarr", {"intensity": x}, tile=32, looks=1.0)
    res = subprocess.run([sys.executable, "-m", "sarship", "detect", str(scene), "--detector", "ca_cfar",
                          "--scheduler", "tcp://127.0.0.1:9", "--out", str(tmp_path / "o"),
                          "--set", "guard=5", "--set", "background=9"],
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 2
    assert "cannot reach Dask scheduler" in res.stderr and "Traceback" not in res.stderr
    assert len(res.stderr.strip().splitlines()) == 1
    assert not Path(tmp_path / "o" / "run.json").exists()


def test_worker_with_another_version_is_refused(tmp_path):
    """Tasks run the workers' own sarship: a worker of another version stops the run before
    any tile is sent, naming the worker (exit 2, one line, no output written)."""
    preload = tmp_path / "other_version.py"
    preload.write_text("import sarship.pipeline\nsarship.pipeline.__version__ = '0.0.1-other'\n")
    gen = _dask_processes(tmp_path, {"same": [], "stale": ["--preload", str(preload)]})
    address = next(gen)
    try:
        x = np.ones((32, 32), np.float32)
        scene = write_scene(tmp_path / "s.zarr", {"intensity": x}, tile=32, looks=1.0)
        res = subprocess.run([sys.executable, "-m", "sarship", "detect", str(scene), "--detector", "ca_cfar",
                              "--scheduler", address, "--out", str(tmp_path / "o"),
                              "--set", "guard=5", "--set", "background=9"],
                             capture_output=True, text=True, timeout=300)
    finally:
        gen.close()
    assert res.returncode == 2, res.stderr
    err = res.stderr.strip().splitlines()
    assert "stale at tcp://" in err[-1] and "(0.0.1-other)" in err[-1] and "same version" in err[-1] and "Traceback" not in res.stderr
    assert not (tmp_path / "o").exists()
