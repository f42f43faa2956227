"""Helpers for tests against a real ``sarship serve`` process (uvicorn on loopback, its own
local Dask cluster, SQLite store): start/kill the server, wait for jobs, check problem bodies."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx


def data_with_scene(root: Path, shape: tuple[int, int] = (300, 260), seed: int = 3, tile: int = 128, **blobs) -> Path:
    """A fresh service data folder ``root/data`` holding one small scene ``s1`` (gamma clutter,
    L = 2, bright blobs; ``blobs`` go to ``conftest.blobs_scene``), written with the project's
    store code."""
    from conftest import blobs_scene, write_scene

    data = root / "data"
    (data / "scenes").mkdir(parents=True)
    write_scene(
        data / "scenes" / "s1.zarr",
        {"intensity": blobs_scene(shape, looks=2.0, seed=seed, **blobs)},
        tile=tile,
        looks=2.0,
    )
    return data


def make_store(data: Path) -> None:
    """Create the job store of ``data`` (in WAL mode) before servers start on it at once: two
    server processes creating one fresh store together can meet "database is locked" (the
    switch to WAL mode of a new database does not wait for the other's lock)."""
    from sarship.service.store import JobStore

    data.mkdir(parents=True, exist_ok=True)
    JobStore(data / "jobs.sqlite").close()


def _ephemeral_range() -> tuple[int, int]:
    try:
        low, high = (int(v) for v in Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split())
        return low, high
    except (OSError, ValueError):
        return 32768, 60999  # Linux's default


def free_port() -> int:
    """A free loopback port BELOW the kernel's ephemeral range: a port the kernel hands out for
    ``bind(0)`` can be handed out again, to the server's own Dask scheduler or a worker, before
    the server binds it, and the readiness poll then speaks HTTP to the scheduler (seen in a
    fresh-clone run: the scheduler read "GET /readyz" as a frame length and the server died).
    Ports below the range are never handed out by ``bind(0)``."""
    import random

    low = _ephemeral_range()[0]
    rng = random.Random()
    for _ in range(200):
        port = rng.randrange(max(low - 12000, 1024), low)
        with socket.socket() as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                continue
            return port
    raise RuntimeError("no free port below the ephemeral range")


class Server:
    def __init__(self, data: Path, port: int, **env):
        self.data, self.port = data, port
        self.url = f"http://127.0.0.1:{port}"
        # worker threads: two worker processes per server cost seconds of start-up on the 2-core test
        # machine; the README walk-through test runs the default worker processes
        self.env = {
            **os.environ,
            "SARSHIP_WORKERS": "2",
            "SARSHIP_WORKER_THREADS": "1",
            "SARSHIP_LEASE_S": "4",
            "CUDA_VISIBLE_DEVICES": "",
            **env,
        }
        self.proc = None

    def start(self, timeout: float = 120.0) -> Server:
        self.log = open(self.data.parent / f"server-{self.port}-{time.time_ns()}.log", "w")
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "sarship", "serve", "--data", str(self.data), "--port", str(self.port)],
            stdout=self.log,
            stderr=subprocess.STDOUT,
            env=self.env,
            start_new_session=True,
        )
        t_end = time.time() + timeout
        while time.time() < t_end:
            if self.proc.poll() is not None:
                raise RuntimeError(f"server exited: {Path(self.log.name).read_text()[-2000:]}")
            try:
                if httpx.get(self.url + "/readyz", timeout=2).status_code == 200:
                    return self
            except httpx.HTTPError:
                pass
            time.sleep(0.05)
        raise RuntimeError("server did not become ready")

    def kill(self, sig=signal.SIGKILL) -> None:
        if self.proc and self.proc.poll() is None:
            os.killpg(self.proc.pid, sig)  # the whole session: uvicorn and its Dask workers
            self.proc.wait(timeout=30)

    def stop(self) -> None:
        self.kill(signal.SIGTERM)


_SHARED: dict[str, Server] = {}


def shared_server(root: Path) -> Server:
    """One plain server (``data_with_scene`` under ``root``, the default settings of
    :class:`Server`) per test process, started by the first module that asks and stopped when
    the process exits: a server start costs seconds of the 2-core CI machine. For modules whose
    tests do not interfere: each writes its own scenes (names of its own) into ``srv.data`` and
    looks at its own jobs only; nothing changes the server's settings. ``root`` is used only
    by the first call (a session-lived folder, e.g. ``tmp_path_factory.getbasetemp()``)."""
    import atexit

    srv = _SHARED.get("plain")
    if srv is None or srv.proc.poll() is not None:
        srv = Server(data_with_scene(Path(root) / f"shared-{time.time_ns()}"), free_port()).start()
        atexit.register(srv.stop)
        _SHARED["plain"] = srv
    return srv


def wait_job(url: str, job_id: str, timeout: float = 120.0) -> dict:
    t_end = time.time() + timeout
    while time.time() < t_end:
        st = httpx.get(f"{url}/jobs/{job_id}").json()
        if st["status"] in ("successful", "failed", "dismissed"):
            return st
        time.sleep(0.05)
    raise AssertionError(f"job {job_id} did not finish: {st}")


def check_problem(r, status: int, *words: str) -> None:
    assert r.status_code == status, (r.status_code, r.text)
    body = r.json()
    assert {"type", "title", "detail"} <= set(body), body
    for w in words:
        assert w in body["detail"], (w, body)


# ----------------------------------------------------------------------------- inbox passes


def tif_bytes(seed: int, shape=(300, 260)) -> bytes:
    """A TIFF of a small gamma scene with bright blobs (``conftest.blobs_scene``), as bytes."""
    import io

    import tifffile
    from conftest import blobs_scene

    buf = io.BytesIO()
    tifffile.imwrite(buf, blobs_scene(shape, looks=2.0, seed=seed))
    return buf.getvalue()


def passes(url: str) -> dict[str, dict]:
    """The newest pass record of each inbox file, by file name."""
    out: dict[str, dict] = {}
    for p in httpx.get(url + "/ingest?limit=1000").json()["passes"]:  # newest first
        out.setdefault(Path(p["file"]).name, p)
    return out


def wait_pass(url: str, name: str, statuses: tuple[str, ...], timeout: float = 60.0) -> dict:
    t_end = time.time() + timeout
    while time.time() < t_end:
        p = passes(url).get(name)
        if p is not None and p["status"] in statuses:
            return p
        time.sleep(0.1)
    raise AssertionError(f"pass {name} did not reach {statuses}: {passes(url).get(name)}")


def png(r):
    """The PNG body of a 200 answer as an array (e.g. a quicklook)."""
    import io

    import numpy as np
    from PIL import Image

    assert r.status_code == 200 and r.headers["content-type"] == "image/png", r.text
    return np.asarray(Image.open(io.BytesIO(r.content)))


def blue(rgb):
    """Pixels of the quicklook's land tint: blue well above red and green (the grey scene has
    r = g = b)."""
    rgb = rgb[..., :3].astype(int)
    return (rgb[..., 2] - rgb[..., 0] >= 40) & (rgb[..., 2] - rgb[..., 1] >= 20)
