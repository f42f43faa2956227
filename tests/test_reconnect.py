"""A cluster whose scheduler goes away: ``sarship worker`` exits non-zero (a service manager
restarts it), and ``sarship serve --scheduler`` reconnects to the restarted scheduler (with a
capped back-off): ``/readyz`` is 200 again and new jobs run. Real ``dask scheduler``,
``sarship worker`` and ``sarship serve`` processes on loopback."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest

httpx = pytest.importorskip("httpx")
from svc import Server, data_with_scene, free_port, wait_job  # noqa: E402

ENV = {**os.environ, "CUDA_VISIBLE_DEVICES": "", "PYTHONUNBUFFERED": "1"}


def scheduler(port: int) -> subprocess.Popen:
    p = subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_scheduler", "--host", "127.0.0.1",
                          "--port", str(port), "--dashboard-address", "127.0.0.1:0", "--no-show"],
                         stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=ENV)
    _wait_port(port, p)
    return p


def _wait_port(port: int, proc: subprocess.Popen, timeout: float = 60.0) -> None:
    import socket

    t_end = time.time() + timeout
    while time.time() < t_end:
        assert proc.poll() is None, "the scheduler exited"
        with socket.socket() as s:
            if s.connect_ex(("127.0.0.1", port)) == 0:
                return
        time.sleep(0.1)
    raise AssertionError(f"no scheduler on port {port}")


def worker(address: str, name: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "sarship", "worker", "--scheduler", address, "--gpus", "none",
                             "--cpus", "1", "--name", name], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            text=True, env=ENV)


def _wait_line(proc: subprocess.Popen, text: str, timeout: float = 60.0) -> list[str]:
    """Read the process's stderr until a line holds ``text`` (the worker announces itself)."""
    seen: list[str] = []
    t_end = time.time() + timeout
    while time.time() < t_end:
        line = proc.stderr.readline()
        if not line:
            raise AssertionError("".join(seen))
        seen.append(line)
        if text in line:
            return seen
    raise AssertionError("".join(seen))


def _end(*procs) -> None:
    for p in procs:
        if p is not None and p.poll() is None:
            p.terminate()
    for p in procs:
        if p is not None:
            try:
                p.wait(timeout=30)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()


def test_worker_exits_nonzero_when_its_scheduler_dies():
    """SIGTERM stops ``sarship worker`` with 0; its scheduler killed, it exits 1 with one line
    naming the scheduler (systemd's ``Restart=on-failure`` then restarts it)."""
    port = free_port()
    addr = f"tcp://127.0.0.1:{port}"
    sched = scheduler(port)
    a = b = None
    try:
        a, b = worker(addr, "a"), worker(addr, "b")
        _wait_line(a, "sarship: worker a-cpu0")
        _wait_line(b, "sarship: worker b-cpu0")
        a.send_signal(signal.SIGTERM)
        assert a.wait(timeout=60) == 0
        sched.kill()
        sched.wait(timeout=30)
        assert b.wait(timeout=60) == 1
        rest = b.stderr.read()
        said = [ln for ln in rest.splitlines() if ln.startswith("sarship worker:")]
        assert len(said) == 1 and addr in said[0] and "went away" in said[0], rest
        assert "Traceback" not in rest.split("sarship worker:")[-1]
    finally:
        _end(a, b, sched)
