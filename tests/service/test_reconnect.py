"""A cluster whose scheduler goes away: ``sarship worker`` exits non-zero (a service manager
restarts it), and ``sarship serve --scheduler`` reconnects to the restarted scheduler (with a
capped back-off): ``/readyz`` is 200 again and new jobs run. Real ``dask scheduler``,
``sarship worker`` and ``sarship serve`` processes on loopback."""

from __future__ import annotations

import json
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
    p = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "distributed.cli.dask_scheduler",
            "--host",
            "127.0.0.1",
            "--port",
            str(port),
            "--dashboard-address",
            "127.0.0.1:0",
            "--no-show",
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        env=ENV,
    )
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
    return subprocess.Popen(
        [
            sys.executable,
            "-m",
            "sarship",
            "worker",
            "--scheduler",
            address,
            "--gpus",
            "none",
            "--cpus",
            "1",
            "--name",
            name,
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        env=ENV,
    )


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


def _ready(url: str) -> tuple[int, dict]:
    try:
        r = httpx.get(url + "/readyz", timeout=5)
        return r.status_code, r.json()
    except httpx.HTTPError as exc:
        return 0, {"error": str(exc)}


def _wait_ready(url: str, want: int, timeout: float) -> dict:
    t_end = time.time() + timeout
    while True:
        code, body = _ready(url)
        if code == want or time.time() > t_end:
            assert code == want, body
            return body
        time.sleep(0.3)


@pytest.mark.slow  # ~25 s (Dask's client retries 10 s first); test_link_reconnects_... covers the rule cheaply
def test_service_reconnects_after_the_scheduler_restarts(tmp_path):
    """``sarship serve --scheduler``: the scheduler killed (its worker exits 1, as a service
    manager would restart it) and started again on the same address after the API's Dask client
    gave up: ``/readyz`` says 503 with the reason meanwhile, a job posted meanwhile waits (no
    retries), ``/readyz`` returns to 200 once the API has reconnected (capped back-off), and jobs
    succeed on the new cluster."""
    port = free_port()
    addr = f"tcp://127.0.0.1:{port}"
    data = data_with_scene(tmp_path, shape=(200, 180))
    sched = scheduler(port)
    w = srv = None
    try:
        w = worker(addr, "one")
        _wait_line(w, "sarship: worker one-cpu0")
        srv = Server(
            data, free_port(), SARSHIP_SCHEDULER=addr, SARSHIP_RECONNECT_S="0.5", SARSHIP_RECONNECT_MAX_S="2"
        ).start()
        sched.kill()
        sched.wait(timeout=30)
        assert w.wait(timeout=60) == 1
        down = _wait_ready(srv.url, 503, 60)
        assert "scheduler" in json.dumps(down), down
        # down past the client's own reconnection window (distributed's Client gives up and closes,
        # 10 s): the link's own tries then fail, and /readyz says why
        t_end = time.time() + 60
        while "cannot reach Dask scheduler" not in json.dumps(_ready(srv.url)[1]) and time.time() < t_end:
            time.sleep(0.5)
        code, body = _ready(srv.url)
        assert code == 503 and f"Dask scheduler at '{addr}' is unreachable (reconnecting" in json.dumps(body), body
        # a job posted meanwhile waits in the store (not claimed, so not failed over to the retry)
        r = httpx.post(
            srv.url + "/processes/ca_cfar/execution", json={"inputs": {"scene": "s1", "pfa": 1e-4, "min_area_px": 1}}
        )
        assert r.status_code == 201, r.text
        waiting = r.json()["jobID"]
        time.sleep(2)
        st = httpx.get(f"{srv.url}/jobs/{waiting}").json()
        assert st["status"] == "accepted" and "retrying" not in st.get("message", ""), st
        sched = scheduler(port)
        w = worker(addr, "two")
        _wait_line(w, "sarship: worker two-cpu0")
        up = _wait_ready(srv.url, 200, 60)
        assert up["checks"]["workers"] == 1, up
        r = httpx.post(
            srv.url + "/processes/ca_cfar/execution", json={"inputs": {"scene": "s1", "pfa": 1e-4, "min_area_px": 1}}
        )
        assert r.status_code == 201, r.text
        st = wait_job(srv.url, r.json()["jobID"], timeout=120)
        assert st["status"] == "successful", st
        met = httpx.get(f"{srv.url}/jobs/{st['jobID']}/results/metrics").json()
        assert {t["worker"] for t in met["tiles"]["per_tile"]} == {"two-cpu0"}
        assert wait_job(srv.url, waiting, timeout=120)["status"] == "successful"
    finally:
        if srv is not None:
            srv.stop()
        _end(w, sched)


def test_backoff_doubles_up_to_its_cap():
    from sarship.service.scheduler_link import backoff

    assert [backoff(0.5, 4.0, n) for n in range(6)] == [0.5, 1.0, 2.0, 4.0, 4.0, 4.0]
    assert backoff(1.0, 30.0, 10**6) == 30.0


def test_link_reconnects_to_a_restarted_scheduler():
    """The cheap sibling of the service test: a :class:`SchedulerLink` to an in-process
    scheduler that is closed (uses raise ConnectionError naming it, never a stale answer) and
    started again on the same port: the link makes a new client and tasks run on the new cluster."""
    from distributed import LocalCluster

    from sarship.service.scheduler_link import SchedulerLink, _client

    port = free_port()
    addr = f"tcp://127.0.0.1:{port}"

    def cluster():
        return LocalCluster(
            n_workers=1,
            threads_per_worker=1,
            processes=False,
            protocol="tcp://",
            host="127.0.0.1",
            scheduler_port=port,
            dashboard_address=None,
        )

    first = cluster()
    link = SchedulerLink(addr, first_s=0.2, max_s=1.0, connect=lambda: _client(addr, timeout_s=1.0))
    second = None
    try:
        assert link.submit(lambda x: x + 1, 1).result(timeout=30) == 2
        first.close()
        t_end = time.time() + 30
        while link.connected and time.time() < t_end:
            time.sleep(0.1)
        with pytest.raises(ConnectionError, match=f"Dask scheduler at '{addr}' is unreachable"):
            link.scheduler_info()
        time.sleep(3)  # past the client's own window: it has closed; the link's tries fail meanwhile
        assert link.status == "closed" and link.last_error
        second = cluster()
        t_end = time.time() + 30
        while not link.connected and time.time() < t_end:
            time.sleep(0.1)
        assert link.reconnects == 1 and link.last_error is None
        assert list(link.scheduler_info()["workers"]) == list(second.scheduler_info["workers"])
        assert link.submit(lambda x: x * 3, 3).result(timeout=30) == 9
    finally:
        link.close()
        if second is not None:
            second.close()
