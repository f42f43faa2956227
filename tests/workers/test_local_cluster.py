"""``sarship detect``'s local cluster: a small scene runs on an in-process threaded worker (no
worker processes to start), a large one on one worker process per core; the size is a setting
(``SARSHIP_THREADS_MAX_PX``), checked before any work; the processes are forked on Linux
(``SARSHIP_WORKER_START``)."""

from __future__ import annotations

import json
import os
import sys

import numpy as np
import pytest

from tests.cli.test_cli import assert_clean_error, sarship, sarship_here
from tests.conftest import write_scene


@pytest.fixture()
def scene(tmp_path):
    rng = np.random.default_rng(3)
    x = rng.gamma(2.0, 0.5, (96, 80)).astype(np.float32)
    x[40:44, 30:36] += 60.0
    return write_scene(tmp_path / "small.zarr", {"intensity": x}, tile=64, looks=2.0)


def _cluster_line(stderr: str) -> str:
    lines = [ln for ln in stderr.splitlines() if ln.startswith("sarship: local Dask cluster")]
    assert len(lines) == 1, stderr
    return lines[0]


def _detect(scene, out, **env):
    return sarship("detect", scene, "--detector", "ca_cfar", "--out", out, env=env)


def _nolooks_scene(tmp_path, shape, ship_row, tile):
    rng = np.random.default_rng(4)
    x = rng.gamma(2.0, 0.5, shape).astype(np.float32)
    x[ship_row : ship_row + 6, 200:230] += 80.0
    return write_scene(tmp_path / "nolooks.zarr", {"intensity": x}, tile=tile)  # no looks attribute


def _has_ship_at(out, row) -> None:
    run = json.loads((out / "run.json").read_text())
    assert run["looks_source"].startswith("estimated from the scene")
    feats = json.loads((out / "detections.geojson").read_text())["features"]
    assert len(feats) >= 1 and any(f["properties"]["bbox_px"][0] <= row < f["properties"]["bbox_px"][2] for f in feats)


def test_small_scene_runs_on_threads_and_the_setting_switches_to_processes(tmp_path):
    """The scene has no ``looks``: the command samples it through the scene reader before its
    cluster forks the worker processes, which then read the tiles with the same library
    (tensorstore's threads do not survive a fork; its state must not hang the children)."""
    scene = _nolooks_scene(tmp_path, (300, 280), 150, 128)
    # the threaded cluster in this process (tests/cli/test_cli.py sarship_here), the forked one below as a command
    threaded = sarship_here(
        "detect", scene, "--detector", "ca_cfar", "--out", tmp_path / "a", env={"SARSHIP_THREADS_MAX_PX": ""}
    )
    assert threaded.returncode == 0, threaded.stderr
    assert "threads in this process" in _cluster_line(threaded.stderr)
    procs = _detect(scene, tmp_path / "b", SARSHIP_THREADS_MAX_PX="0", SARSHIP_READER="tensorstore")
    assert procs.returncode == 0, procs.stderr
    line = _cluster_line(procs.stderr)
    assert "worker processes" in line
    # the command's own cluster forks its workers on Linux (workers/cluster.worker_start_method)
    if sys.platform.startswith("linux"):
        assert "(fork)" in line, line
    _has_ship_at(tmp_path / "b", 150)
    # the same detections either way
    a = json.loads((tmp_path / "a" / "detections.geojson").read_text())
    b = json.loads((tmp_path / "b" / "detections.geojson").read_text())
    assert [f["properties"] for f in a["features"]] == [f["properties"] for f in b["features"]]
    assert len(a["features"]) >= 1


@pytest.mark.slow  # spawned workers each start a fresh interpreter; the fork and thread paths: above
def test_spawned_workers_give_what_threads_give(scene, tmp_path):
    threaded = _detect(scene, tmp_path / "a", SARSHIP_THREADS_MAX_PX="")
    assert threaded.returncode == 0, threaded.stderr
    spawned = _detect(scene, tmp_path / "s", SARSHIP_THREADS_MAX_PX="0", SARSHIP_WORKER_START="spawn")
    assert spawned.returncode == 0, spawned.stderr
    assert "worker processes (spawn)" in _cluster_line(spawned.stderr)
    a = json.loads((tmp_path / "a" / "detections.geojson").read_text())
    s = json.loads((tmp_path / "s" / "detections.geojson").read_text())
    assert [f["properties"] for f in a["features"]] == [f["properties"] for f in s["features"]]


def test_a_bad_setting_is_one_line_and_leaves_nothing(scene, tmp_path):
    res = _detect(scene, tmp_path / "c", SARSHIP_THREADS_MAX_PX="many")
    assert_clean_error(res, "SARSHIP_THREADS_MAX_PX", "many")
    assert not (tmp_path / "c").exists()


def test_a_bad_start_method_is_one_line_and_leaves_nothing(scene, tmp_path):
    # in this process (tests/cli/test_cli.py sarship_here); a real process's refusal of a setting: above
    res = sarship_here(
        "detect",
        scene,
        "--detector",
        "ca_cfar",
        "--out",
        tmp_path / "c",
        env={"SARSHIP_THREADS_MAX_PX": "0", "SARSHIP_WORKER_START": "vfork"},
    )
    assert_clean_error(res, "SARSHIP_WORKER_START", "vfork")
    assert not (tmp_path / "c").exists()


def test_worker_start_method_rule(monkeypatch):
    from sarship.pipeline.errors import InputError
    from sarship.workers.cluster import cuda_initialised, worker_start_method

    monkeypatch.delenv("SARSHIP_WORKER_START", raising=False)
    assert worker_start_method(short_lived=False) == "spawn"  # the service's long-lived cluster
    if sys.platform.startswith("linux") and not cuda_initialised():
        assert worker_start_method() == "fork"
    for m in ("spawn", "forkserver", "fork"):
        monkeypatch.setenv("SARSHIP_WORKER_START", m)
        assert worker_start_method() == m == worker_start_method(short_lived=False)
    monkeypatch.setenv("SARSHIP_WORKER_START", "threads")
    with pytest.raises(InputError, match="SARSHIP_WORKER_START"):
        worker_start_method()


def test_threads_max_px_setting():
    from sarship.pipeline.errors import InputError
    from sarship.workers.cluster import THREADS_MAX_PX, threads_max_px

    old = os.environ.pop("SARSHIP_THREADS_MAX_PX", None)
    try:
        assert threads_max_px() == THREADS_MAX_PX
        os.environ["SARSHIP_THREADS_MAX_PX"] = "1e6"
        assert threads_max_px() == 1_000_000
        os.environ["SARSHIP_THREADS_MAX_PX"] = "-1"
        with pytest.raises(InputError, match="SARSHIP_THREADS_MAX_PX"):
            threads_max_px()
    finally:
        os.environ.pop("SARSHIP_THREADS_MAX_PX", None)
        if old is not None:
            os.environ["SARSHIP_THREADS_MAX_PX"] = old


@pytest.mark.parametrize("short_lived", [False, True])
def test_worker_processes_start_without_dask_malloc_trim(short_lived, monkeypatch):
    """Spawned (service) and forked (``sarship detect``) worker processes get Dask's pre-spawn
    environment without MALLOC_TRIM_THRESHOLD_ (glibc's dynamic mmap threshold stays on: tile
    buffers are reused, not mapped afresh on every read), and keep the rest of it."""
    import dask
    import distributed  # noqa: F401

    from sarship.workers.cluster import connect, nanny_environ

    assert "MALLOC_TRIM_THRESHOLD_" in dask.config.get("distributed.nanny.pre-spawn-environ")  # Dask's default
    assert "MALLOC_TRIM_THRESHOLD_" not in nanny_environ() and nanny_environ()["OMP_NUM_THREADS"] in (1, "1")
    # a user's own setting is inherited by design; this test process may carry Dask's, set by a
    # nanny of another test's cluster started with Dask's defaults (nannies set it in their own process)
    monkeypatch.delenv("MALLOC_TRIM_THRESHOLD_", raising=False)
    with connect(n_workers=1, echo=False, short_lived=short_lived) as client:
        env = client.run(lambda: (os.environ.get("MALLOC_TRIM_THRESHOLD_"), os.environ.get("OMP_NUM_THREADS")))
    assert list(env.values()) == [(None, "1")], env


@pytest.mark.slow  # its forked run on a smaller scene: test_small_scene_runs_on_threads_and_the_setting_...
def test_forked_workers_read_after_the_command_itself_read_the_scene(tmp_path):
    """A scene without ``looks`` is sampled by the command (the client) through the scene reader
    before its cluster forks the worker processes, which then read the tiles with the same
    library (tensorstore's threads do not survive a fork; its state must not hang the children).
    That both readers give the same detections is tests/workers/test_data_path.py's (in one process)."""
    scene = _nolooks_scene(tmp_path, (640, 600), 300, 256)
    res = _detect(scene, tmp_path / "ts", SARSHIP_THREADS_MAX_PX="0", SARSHIP_READER="tensorstore")
    assert res.returncode == 0, res.stderr
    if sys.platform.startswith("linux"):
        assert "(fork)" in _cluster_line(res.stderr)
    _has_ship_at(tmp_path / "ts", 300)


def test_cluster_host_setting(monkeypatch):
    """Loopback unless ``SARSHIP_CLUSTER_HOST`` says otherwise; a bad value is refused."""
    from sarship.pipeline.errors import InputError
    from sarship.workers.cluster import cluster_host

    monkeypatch.delenv("SARSHIP_CLUSTER_HOST", raising=False)
    assert cluster_host() == "127.0.0.1"
    for value, want in (
        ("10.0.0.5", "10.0.0.5"),
        ("[::1]", "::1"),
        ("gpu-host.example", "gpu-host.example"),
        ("0.0.0.0", "0.0.0.0"),
    ):
        monkeypatch.setenv("SARSHIP_CLUSTER_HOST", value)
        assert cluster_host() == want
    monkeypatch.setenv("SARSHIP_CLUSTER_HOST", "tcp://x:1")
    with pytest.raises(InputError, match="SARSHIP_CLUSTER_HOST"):
        cluster_host()


def test_gpu_cluster_spec_carries_the_host():
    """The GPU local cluster's scheduler and every nanny (GPU and CPU) get the cluster's host
    (before: none, so they bound every interface); checked without a GPU."""
    from sarship.workers.cluster import gpu_cluster_spec

    for host in ("127.0.0.1", "10.1.2.3"):
        spec = gpu_cluster_spec(["0", "1"], 2, "127.0.0.1:0", host, gpu_threads=2, per_gpu=2)
        assert spec["scheduler"]["options"]["host"] == host
        assert spec["scheduler"]["options"]["dashboard_address"] == "127.0.0.1:0"
        assert len(spec["workers"]) == 2 * 2 + 2
        for name, w in spec["workers"].items():
            assert w["options"]["host"] == host, name
        gpu = [w["options"] for w in spec["workers"].values() if "GPU" in w["options"]["resources"]]
        assert sorted(o["env"]["CUDA_VISIBLE_DEVICES"] for o in gpu) == ["0", "0", "1", "1"]


def _listening(procs) -> set[tuple[str, int]]:
    import psutil

    out = set()
    for p in procs:
        try:
            conns = p.net_connections(kind="inet")
        except (psutil.NoSuchProcess, psutil.AccessDenied):
            continue
        out |= {(c.laddr.ip, c.laddr.port) for c in conns if c.status == psutil.CONN_LISTEN}
    return out


@pytest.mark.parametrize("branch", ["processes", "threads", "gpu"])
def test_local_cluster_listens_on_loopback_only(branch, monkeypatch):
    """Every socket a started local cluster listens on (scheduler, nannies, workers, their HTTP
    servers, the dashboard) is on loopback. The GPU branch runs with a GPU ID given (``--gpus 0``):
    its pinned worker process starts without a GPU here (it only runs no GPU tile)."""
    import psutil

    from sarship.workers.cluster import connect

    monkeypatch.delenv("SARSHIP_CLUSTER_HOST", raising=False)
    # one worker process for the GPU (the default is a quarter of the cores, up to 4: 4 on a 16-core
    # GPU host, where this test runs for real)
    monkeypatch.setenv("SARSHIP_GPU_PROCS", "1")
    me = psutil.Process()
    before = _listening([me, *me.children(recursive=True)])
    kw = {"gpus": ["0"], "cpu_workers": 0} if branch == "gpu" else {"n_workers": 1, "threads": branch == "threads"}
    with connect(echo=False, short_lived=True, dashboard_address="127.0.0.1:0", **kw) as client:
        n = len(client.scheduler_info()["workers"])
        assert n == 1
        if branch == "gpu":
            assert list(client.scheduler_info()["workers"].values())[0]["resources"].get("GPU") == 2
        addresses = [client.scheduler.address, *client.scheduler_info()["workers"]]
        opened = _listening([me, *me.children(recursive=True)]) - before
    assert all(a.startswith("tcp://127.0.0.1:") for a in addresses), addresses
    # at least the scheduler, its dashboard and the worker (with its nanny, for processes)
    assert len(opened) >= 3, opened
    assert {ip for ip, _ in opened} == {"127.0.0.1"}, opened
