"""Shared fixtures: a real Dask LocalCluster (processes), scene helpers, shared data paths."""

from __future__ import annotations

import json
import logging
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"


def _generous_http_timeouts() -> None:
    """httpx's module functions (``httpx.get``/``post``/...) time out after 5 s; on the 2-core CI
    machine running two test processes, each with its servers and Dask workers, a server's
    first request (it imports a detector, opens the store) can take longer. The tests wait
    for real servers: give those calls 60 s unless a test sets its own timeout."""
    import functools

    try:
        import httpx
    except ImportError:
        return
    for name in ("request", "get", "post", "put", "patch", "delete", "head", "options", "stream"):
        f = getattr(httpx, name, None)
        if f is None or getattr(f, "_sarship_tests", False):
            continue

        @functools.wraps(f)
        def call(*args, _f=f, **kw):
            kw.setdefault("timeout", 60.0)
            return _f(*args, **kw)

        call._sarship_tests = True
        setattr(httpx, name, call)


_generous_http_timeouts()
REAL = SHARED / "data" / "real"

# A warm cluster the developer keeps running (sarship warm start) must not take the tests'
# commands: they look for one at a socket path of their own, where none runs unless a test
# starts it (tests/cli/test_warm.py).
os.environ["SARSHIP_WARM_SOCKET"] = f"/tmp/sarship-tests-{os.getuid()}-{os.getpid()}/none/warm.sock"


@pytest.fixture(scope="session")
def client():
    """A real two-process Dask cluster, shared by the tests that need one."""
    from distributed import Client, LocalCluster

    cluster = LocalCluster(
        n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0", silence_logs=logging.ERROR
    )
    c = Client(cluster)
    yield c
    c.close()
    cluster.close()


def fsize_limit(limit: int):
    """A ``preexec_fn`` for a subprocess that may write no file past ``limit`` bytes: such
    writes fail with EFBIG, which a process meets as it would a full disk's ENOSPC (a real
    kernel limit, inherited by its children; SIGXFSZ ignored, as CPython does itself)."""
    import resource
    import signal

    def preexec():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    return preexec


def write_scene(path, arrays: dict, tile: int = 256, **attrs):
    """Write arrays into a scene store with the project's own store code."""
    from sarship.pipeline.scene import create_scene, finalize_scene

    shape = next(iter(arrays.values())).shape
    g = create_scene(
        path, shape, {k: v.dtype for k, v in arrays.items()}, tile=tile, attrs={"kind": "intensity", **attrs}
    )
    for k, v in arrays.items():
        g[k][:] = v
    finalize_scene(path)
    return Path(path)


def blobs_scene(shape=(301, 257), looks=2.0, seed=0, n=12, amp=40.0):
    """Gamma clutter with bright rectangular blobs (some across typical tile borders)."""
    rng = np.random.default_rng(seed)
    x = rng.gamma(looks, 1.0 / looks, shape).astype(np.float32)
    for _ in range(n):
        r = int(rng.integers(0, shape[0] - 6))
        c = int(rng.integers(0, shape[1] - 12))
        hh, ww = int(rng.integers(1, 6)), int(rng.integers(1, 12))
        x[r : r + hh, c : c + ww] += amp * rng.random((hh, ww)).astype(np.float32) + amp / 4
    return x


#: the dask command of this interpreter (its bin folder need not be on PATH, e.g. a virtualenv run by path)
DASK = shutil.which("dask", path=os.path.dirname(sys.executable)) or shutil.which("dask")


def dask_processes(tmp_path, workers: dict[str, list[str]], cwd=None):
    """A `dask scheduler` and one `dask worker` per name (with its extra arguments), started in
    ``cwd`` (default: this process's folder); a generator yielding the scheduler address."""
    if DASK is None:
        pytest.skip("the 'dask' command is not on PATH")
    sched_file = tmp_path / "scheduler.json"
    env = {**os.environ, "DASK_DISTRIBUTED__LOGGING__DISTRIBUTED": "error"}
    procs = [
        subprocess.Popen(
            [
                DASK,
                "scheduler",
                "--scheduler-file",
                str(sched_file),
                "--port",
                "0",
                "--dashboard-address",
                ":0",
                "--host",
                "127.0.0.1",
            ],
            cwd=cwd,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            env=env,
        )
    ]
    try:
        for _ in range(300):
            if sched_file.exists() and sched_file.stat().st_size > 0:
                break
            time.sleep(0.1)
        else:
            pytest.fail("dask scheduler did not start")
        address = json.loads(sched_file.read_text())["address"]
        for name, extra in workers.items():
            procs.append(
                subprocess.Popen(
                    [DASK, "worker", address, "--nthreads", "1", "--name", name, "--no-dashboard", *extra],
                    cwd=cwd,
                    stdout=subprocess.DEVNULL,
                    stderr=subprocess.DEVNULL,
                    env=env,
                )
            )
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


def cov_scene(path, shape=(64, 64)):
    """A C3 covariance scene (c11 ... c33), as `sarship ingest` writes PolSARpro C3 folders."""
    rng = np.random.default_rng(0)
    k = (rng.normal(size=(*shape, 3)) + 1j * rng.normal(size=(*shape, 3))).astype(np.complex64)
    arrays = {}
    for i, j in ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)):
        c = k[..., i] * np.conj(k[..., j])
        arrays[f"c{i + 1}{j + 1}"] = c.real.astype(np.float32) if i == j else c.astype(np.complex64)
    return write_scene(path, arrays, tile=64, kind="covariance", looks=1.0)
