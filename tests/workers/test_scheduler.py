"""Integration: `sarship detect --scheduler` against real `dask scheduler` / `dask worker` processes."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import blobs_scene, dask_processes, write_scene


@pytest.fixture()
def two_workers(tmp_path):
    yield from dask_processes(tmp_path, {"alpha": [], "beta": []})


def test_detect_on_existing_scheduler(tmp_path, two_workers):
    x = blobs_scene((300, 260), looks=2.0, seed=3)
    scene = write_scene(tmp_path / "s.zarr", {"intensity": x}, tile=64, looks=2.0)
    out = tmp_path / "o"
    res = subprocess.run(
        [
            sys.executable,
            "-m",
            "sarship",
            "detect",
            str(scene),
            "--detector",
            "ca_cfar",
            "--scheduler",
            two_workers,
            "--out",
            str(out),
            "--tile",
            "64",
            "--set",
            "guard=11",
            "--set",
            "background=31",
            "--set",
            "min_area_px=1",
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert res.returncode == 0, res.stderr
    assert two_workers in res.stderr
    run = json.loads((out / "run.json").read_text())
    workers = {t["worker"] for t in run["tiles"]["per_tile"]}
    assert workers <= {"alpha", "beta"} and workers, workers
    assert run["tiles"]["count"] == 5 * 5
    assert run["detections"] >= 5


def test_scheduler_from_the_environment(tmp_path, two_workers):
    """Without --scheduler, `sarship detect` uses SARSHIP_SCHEDULER (a cluster kept running);
    `--scheduler local` starts a local cluster even so."""
    import os

    x = blobs_scene((200, 180), looks=2.0, seed=4)
    scene = write_scene(tmp_path / "s.zarr", {"intensity": x}, tile=64, looks=2.0)
    args = [
        sys.executable,
        "-m",
        "sarship",
        "detect",
        str(scene),
        "--detector",
        "ca_cfar",
        "--tile",
        "64",
        "--set",
        "guard=11",
        "--set",
        "background=31",
    ]
    env = {**os.environ, "SARSHIP_SCHEDULER": two_workers}
    res = subprocess.run([*args, "--out", str(tmp_path / "env")], capture_output=True, text=True, timeout=300, env=env)
    assert res.returncode == 0, res.stderr
    assert f"using Dask scheduler {two_workers}" in res.stderr
    run = json.loads((tmp_path / "env" / "run.json").read_text())
    assert {t["worker"] for t in run["tiles"]["per_tile"]} <= {"alpha", "beta"}
    res = subprocess.run(
        [*args, "--out", str(tmp_path / "loc"), "--scheduler", "local"],
        capture_output=True,
        text=True,
        timeout=300,
        env=env,
    )
    assert res.returncode == 0, res.stderr
    assert "local Dask cluster" in res.stderr and two_workers not in res.stderr
    local = json.loads((tmp_path / "loc" / "detections.geojson").read_text())["features"]
    remote = json.loads((tmp_path / "env" / "detections.geojson").read_text())["features"]
    assert [f["properties"] for f in local] == [f["properties"] for f in remote] and local


def test_unreachable_scheduler(tmp_path):
    x = np.ones((32, 32), np.float32)
    scene = write_scene(tmp_path / "s.zarr", {"intensity": x}, tile=32, looks=1.0)
    res = subprocess.run(
        [
            sys.executable,
            "-m",
            "sarship",
            "detect",
            str(scene),
            "--detector",
            "ca_cfar",
            "--scheduler",
            "tcp://127.0.0.1:9",
            "--out",
            str(tmp_path / "o"),
            "--set",
            "guard=5",
            "--set",
            "background=9",
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert res.returncode == 2
    assert "cannot reach Dask scheduler" in res.stderr and "Traceback" not in res.stderr
    assert len(res.stderr.strip().splitlines()) == 1
    assert not Path(tmp_path / "o" / "run.json").exists()


def test_worker_with_another_version_is_refused(tmp_path):
    """Tasks run the workers' own sarship: a worker of another version stops the run before
    any tile is sent, naming the worker (exit 2, one line, no output written)."""
    preload = tmp_path / "other_version.py"
    preload.write_text("import sarship.pipeline\nsarship.pipeline.__version__ = '0.0.1-other'\n")
    gen = dask_processes(tmp_path, {"same": [], "stale": ["--preload", str(preload)]})
    address = next(gen)
    try:
        x = np.ones((32, 32), np.float32)
        scene = write_scene(tmp_path / "s.zarr", {"intensity": x}, tile=32, looks=1.0)
        res = subprocess.run(
            [
                sys.executable,
                "-m",
                "sarship",
                "detect",
                str(scene),
                "--detector",
                "ca_cfar",
                "--scheduler",
                address,
                "--out",
                str(tmp_path / "o"),
                "--set",
                "guard=5",
                "--set",
                "background=9",
            ],
            capture_output=True,
            text=True,
            timeout=300,
        )
    finally:
        gen.close()
    assert res.returncode == 2, res.stderr
    err = res.stderr.strip().splitlines()
    assert (
        "stale at tcp://" in err[-1]
        and "(0.0.1-other)" in err[-1]
        and "same version" in err[-1]
        and "Traceback" not in res.stderr
    )
    assert not (tmp_path / "o").exists()
