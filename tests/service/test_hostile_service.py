"""A real ``sarship serve`` (uvicorn on loopback, its own local Dask cluster, SQLite store)
against hostile or unlucky clients: preview sizes that would fill the disk, huge and deeply
nested bodies, a crowd of ``Prefer: respond-sync`` requests, NUL characters and lone
surrogates in names, a full disk, the Dask dashboard's address, and a scene symlinked out of
the allowed folders. Nothing of it may answer a 500; every error is a problem document."""

from __future__ import annotations

import io
import os
import signal
import subprocess
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor

import pytest

httpx = pytest.importorskip("httpx")
from conftest import blobs_scene, fsize_limit, write_scene  # noqa: E402
from svc import Server, check_problem, data_with_scene, free_port, wait_job  # noqa: E402

PREVIEW_CACHE_MB = 0.25
MAX_SYNC_WAITS = 3
#: how long the synchronous clients of the test wait before they leave
WAIT_S = 8.0
SYNC_TIMEOUT_S = 60
FAST = {"guard": 11, "background": 31, "min_area_px": 1}
#: a job that runs long on one worker (lmm exact, ~0.6 s per 32x32 tile, 90 tiles): it holds
#: the only runner thread while the jobs queued behind it wait
SLOW = {"scene": "s1_tiles32", "method": "exact", "guard": 5, "background": 13}
#: generous timeouts: the machine running the tests may be busy
http = httpx.Client(timeout=60)


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    data = data_with_scene(tmp_path_factory.mktemp("hostile"))
    write_scene(
        data / "scenes" / "s1_tiles32.zarr",
        {"intensity": blobs_scene((300, 260), looks=2.0, seed=3)},
        tile=32,
        looks=2.0,
    )
    srv = Server(
        data,
        free_port(),
        SARSHIP_WORKERS="1",
        SARSHIP_CONCURRENCY="1",
        SARSHIP_PREVIEW_CACHE_MB=str(PREVIEW_CACHE_MB),
        SARSHIP_MAX_SYNC_WAITS=str(MAX_SYNC_WAITS),
        SARSHIP_SYNC_TIMEOUT_S=str(SYNC_TIMEOUT_S),
    ).start()
    yield srv
    srv.kill()


@pytest.fixture(scope="module")
def done_job(server) -> str:
    r = http.post(server.url + "/processes/ca_cfar/execution", json={"inputs": {"scene": "s1", **FAST}})
    assert r.status_code == 201, r.text
    assert wait_job(server.url, r.json()["jobID"])["status"] == "successful"
    return r.json()["jobID"]


def dismiss_all(u: str) -> None:
    for st in ("accepted", "running"):
        for j in http.get(f"{u}/jobs?status={st}").json()["jobs"]:
            http.delete(f"{u}/jobs/{j['jobID']}")


# ----------------------------------------------------------------------------- 1. previews


def test_preview_sizes_and_cache_are_bounded(server, done_job):
    """40 different ``size`` values render a few fixed sizes, and the cached previews of all
    jobs stay under ``preview_cache_mb`` (oldest removed)."""
    from PIL import Image

    u, jobs = server.url, server.data / "jobs"
    sizes = [64 + 103 * k for k in range(40)]  # 64 .. 4081
    for size in sizes:
        r = http.get(f"{u}/jobs/{done_job}/preview.png?size={size}")
        assert r.status_code == 200, (size, r.status_code, r.text[:300])
        img = Image.open(io.BytesIO(r.content))
        assert max(img.size) <= size and r.headers["content-type"] == "image/png"
    files = list(jobs.glob("*/preview-*.png"))
    assert len(list((jobs / done_job).glob("preview-*.png"))) <= 6, sorted(p.name for p in files)
    assert sum(p.stat().st_size for p in files) <= PREVIEW_CACHE_MB * 2**20, [(p.name, p.stat().st_size) for p in files]
    # the same level, the same picture (and ETag); a cached preview is served after eviction too
    a = http.get(f"{u}/jobs/{done_job}/preview.png?size=4096")
    b = http.get(f"{u}/jobs/{done_job}/preview.png?size=3000")
    assert a.headers["etag"] == b.headers["etag"] and a.content == b.content
    check_problem(http.get(f"{u}/jobs/{done_job}/preview.png?size=5000"), 400, "size")


# ----------------------------------------------------------------------------- 2. bodies


def test_large_bodies_are_refused_before_reading(server):
    u = server.url
    ex = u + "/processes/ca_cfar/execution"
    big = b'{"inputs": {"scene": "s1", "pad": "' + b"x" * (2 << 20) + b'"}}'
    # Content-Length over the limit (1 MiB by default): 413 at once
    r = http.post(ex, content=big, headers={"content-type": "application/json"})
    check_problem(r, 413, "limit")

    def chunks():  # no Content-Length: chunked transfer, counted as it arrives
        for k in range(0, len(big), 1 << 16):
            yield big[k : k + (1 << 16)]

    r = http.post(ex, content=chunks(), headers={"content-type": "application/json"})
    assert "content-length" not in r.request.headers
    check_problem(r, 413, "limit")
    # under the limit: read and answered as before (an unknown parameter)
    small = b'{"inputs": {"scene": "s1", "pad": "' + b"x" * 1000 + b'"}}'
    check_problem(http.post(ex, content=small, headers={"content-type": "application/json"}), 400, "pad")
    # the upload route keeps its own limit (max_upload_mb): 2 MiB is taken
    up = http.post(u + "/scenes?filename=big.txt", content=os.urandom(2 << 20))
    assert up.status_code == 201, up.text
    assert http.get(u + "/livez").status_code == 200


def test_deep_json_is_a_400(server):
    ex = server.url + "/processes/ca_cfar/execution"
    for body in (
        b"[" * 100000 + b"]" * 100000,
        b'{"inputs": {"scene": "s1", "x": ' + b"[" * 50000 + b"1" + b"]" * 50000 + b"}}",
        b'{"inputs": ' + b'{"a": ' * 20000 + b"1" + b"}" * 20000 + b"}",
    ):
        check_problem(http.post(ex, content=body, headers={"content-type": "application/json"}), 400, "nested")
    # brackets inside strings are not nesting ('outputs' is accepted and ignored)
    r = http.post(ex, json={"inputs": {"scene": "s1", **FAST}, "outputs": {"mask": {"note": "[" * 100}}})
    assert r.status_code == 201, r.text
    http.delete(f"{server.url}/jobs/{r.json()['jobID']}")


# ----------------------------------------------------------------------------- 3. sync waits


def test_sync_waits_are_capped_and_leave_the_server_responsive(server):
    u = server.url
    ex = u + "/processes/ca_cfar/execution"
    slow = http.post(u + "/processes/lmm/execution", json={"inputs": SLOW}).json()["jobID"]
    try:
        t_end = time.time() + 60
        while http.get(f"{u}/jobs/{slow}").json()["status"] != "running":
            assert time.time() < t_end
            time.sleep(0.2)
        sync = {"Prefer": "respond-sync"}
        body = {"inputs": {"scene": "s1", **FAST}}
        with ThreadPoolExecutor(MAX_SYNC_WAITS) as pool:
            # clients that wait WAIT_S, then leave (their jobs stay queued behind the slow one)
            waiting = [
                pool.submit(http.post, ex, json=body, headers=sync, timeout=WAIT_S) for _ in range(MAX_SYNC_WAITS)
            ]
            t0 = time.time()
            while len(http.get(f"{u}/jobs?status=accepted").json()["jobs"]) < MAX_SYNC_WAITS:
                assert time.time() < t0 + WAIT_S / 2
                time.sleep(0.05)
            for _ in range(6):  # one more than the cap: 503 with Retry-After, at once, no job created
                r = http.post(ex, json=body, headers=sync, timeout=WAIT_S)
                check_problem(r, 503, "max_sync_waits")
                assert int(r.headers["retry-after"]) > 0
            assert len(http.get(f"{u}/jobs?status=accepted").json()["jobs"]) == MAX_SYNC_WAITS
            # the probes, the lists and dismissal answer while the waits go on
            for path in ("/livez", "/readyz", "/processes", "/jobs"):
                assert http.get(u + path, timeout=WAIT_S).status_code == 200, path
            gone = http.post(ex, json=body).json()["jobID"]
            assert http.delete(f"{u}/jobs/{gone}", timeout=WAIT_S).json()["status"] == "dismissed"
            assert time.time() - t0 < WAIT_S - 0.5  # all of it while the waiting clients were still there
            for f in waiting:
                with pytest.raises(httpx.TimeoutException):
                    f.result()
        # the clients left: their slots are free again (new waits are taken, not refused)
        time.sleep(1.0)
        with ThreadPoolExecutor(MAX_SYNC_WAITS) as pool:
            again = [pool.submit(http.post, ex, json=body, headers=sync, timeout=2.5) for _ in range(MAX_SYNC_WAITS)]
            for f in again:
                with pytest.raises(httpx.TimeoutException):
                    f.result()
    finally:
        http.delete(f"{u}/jobs/{slow}")
        dismiss_all(u)


def test_sigterm_is_prompt_with_sync_waiters(tmp_path):
    data = data_with_scene(tmp_path)
    write_scene(
        data / "scenes" / "s1_tiles32.zarr",
        {"intensity": blobs_scene((300, 260), looks=2.0, seed=3)},
        tile=32,
        looks=2.0,
    )
    # worker processes (the default deployment): threads of the API process cannot be cut short
    srv = Server(data, free_port(), SARSHIP_WORKERS="1", SARSHIP_CONCURRENCY="1", SARSHIP_WORKER_THREADS="0").start()
    try:
        ex = srv.url + "/processes/lmm/execution"
        answers: list = []

        def wait_sync():
            try:
                answers.append(http.post(ex, json={"inputs": SLOW}, headers={"Prefer": "respond-sync"}, timeout=60))
            except httpx.HTTPError as exc:
                answers.append(exc)

        threads = [threading.Thread(target=wait_sync) for _ in range(3)]
        for t in threads:
            t.start()
        t_end = time.time() + 60
        while len(http.get(srv.url + "/jobs").json()["jobs"]) < 3:
            assert time.time() < t_end
            time.sleep(0.1)
        t0 = time.time()
        os.kill(srv.proc.pid, signal.SIGTERM)  # the API process, as `kill PID` or systemd would
        srv.proc.wait(timeout=40)
        took = time.time() - t0
        for t in threads:
            t.join(timeout=5)
        assert took < 20, took
        # each waiting client got an answer: the job's status (it stays in the store)
        assert len(answers) == 3 and all(isinstance(a, httpx.Response) and a.status_code == 201 for a in answers), (
            answers
        )
    finally:
        srv.kill()


# ----------------------------------------------------------------------------- 4. NUL, surrogates


def test_nul_and_lone_surrogates_are_400(server, done_job):
    u = server.url
    ex = u + "/processes/ca_cfar/execution"
    js = {"content-type": "application/json"}
    for raw in (
        b'{"inputs": {"scene": "a\\u0000b"}}',
        b'{"inputs": {"scene": "\\ud800"}}',
        b'{"inputs": {"scene": "s1\\udfff.zarr"}}',
        b'{"inputs": {"scene": "/tmp/\\u0000"}}',
        b'{"inputs": {"scene": "s1", "method": "\\ud800"}}',
        b'{"inputs": {"scene": "s1", "\\ud800": 1}}',
        b'{"inputs": {"scene": "s1", "channel": "a\\u0000"}}',
    ):
        check_problem(http.post(ex, content=raw, headers=js), 400)
    check_problem(
        http.post(
            u + "/processes/lmm/execution", content=b'{"inputs": {"scene": "s1", "method": "\\ud800"}}', headers=js
        ),
        400,
    )
    for path in (
        "/scenes/a%00b",
        "/scenes/%00",
        "/jobs/a%00b",
        "/jobs/a%00b/results",
        "/jobs/%00/preview.png",
        "/jobs/a%00b/results/detections",
        f"/jobs/{done_job}%00",
        "/processes/ca%00cfar",
        "/jobs/a%00b/tiles/0/0/0.png",
        "/scenes/%ED%A0%80",
        "/jobs/%ED%A0%80",
    ):
        r = http.get(u + path)
        assert 400 <= r.status_code < 500, (path, r.status_code, r.text)
        check_problem(r, r.status_code)
    check_problem(http.delete(u + "/jobs/a%00b"), 400)
    r = http.post(u + "/scenes?filename=a%00b.tif", content=b"abc")
    assert 400 <= r.status_code < 500, r.text
    check_problem(http.get(u + "/jobs?status=%00"), 400)


# ----------------------------------------------------------------------------- 5. disk full


def test_full_disk_is_507(tmp_path):
    """The server process may write no file past 2 MiB (RLIMIT_FSIZE, a real limit of the
    kernel: writes fail with EFBIG as they would with ENOSPC on a full disk): an upload past
    it, and job inserts once the job store's write-ahead log reaches it, are 507 problems."""
    data = data_with_scene(tmp_path)
    limit = 2 << 20
    srv = Server(data, free_port(), SARSHIP_WORKERS="1", SARSHIP_MAX_UPLOAD_MB="8")
    log = open(tmp_path / "server.log", "w")
    srv.log = log
    srv.proc = subprocess.Popen(
        [sys.executable, "-m", "sarship", "serve", "--data", str(data), "--port", str(srv.port)],
        stdout=log,
        stderr=subprocess.STDOUT,
        env=srv.env,
        start_new_session=True,
        preexec_fn=fsize_limit(limit),
    )
    try:
        t_end = time.time() + 120
        while True:
            assert srv.proc.poll() is None and time.time() < t_end, (tmp_path / "server.log").read_text()[-2000:]
            try:
                if http.get(srv.url + "/readyz", timeout=2).status_code == 200:
                    break
            except httpx.HTTPError:
                pass
            time.sleep(0.3)
        u = srv.url
        r = http.post(u + "/scenes?filename=big.tif", content=os.urandom(3 << 20), timeout=30)
        check_problem(r, 507, "full")
        assert not [p for p in (data / "uploads").iterdir() if p.name.startswith(".upload-")]
        # job rows of ~300 kB: the store's write-ahead log passes 2 MiB after a few
        inputs = {"scene": "s1" + " " * 300_000}  # (blanks around a scene id are stripped; kept in the row)
        codes = []
        for _ in range(20):
            r = http.post(u + "/processes/ca_cfar/execution", json={"inputs": inputs}, timeout=30)
            codes.append(r.status_code)
            if r.status_code != 201:
                break
        check_problem(r, 507, "job store")
        assert 500 not in codes, codes
        assert http.get(u + "/livez").status_code == 200
    finally:
        srv.kill()


# ----------------------------------------------------------------------------- 6. dashboard


def test_dask_dashboard_listens_where_the_api_does(server):
    psutil = pytest.importorskip("psutil")
    main = psutil.Process(server.proc.pid)
    listening = {}
    for p in [main, *main.children(recursive=True)]:
        try:
            for c in p.net_connections(kind="inet"):
                if c.status == psutil.CONN_LISTEN:
                    listening[(c.laddr.ip, c.laddr.port)] = p.pid
        except (psutil.NoSuchProcess, psutil.AccessDenied):
            continue
    assert ("127.0.0.1", server.port) in listening
    wide = {a: pid for a, pid in listening.items() if a[0] not in ("127.0.0.1", "::1")}
    assert not wide, f"listening beyond the API's address 127.0.0.1: {wide}"
    r = http.get(server.url + "/dashboard", follow_redirects=False)
    assert r.status_code == 307 and r.headers["location"].startswith("http://127.0.0.1:"), r.headers


# ----------------------------------------------------------------------------- 7. symlinks out


def test_scene_symlinked_outside_is_not_listed(server, tmp_path):
    outside = tmp_path / "elsewhere.zarr"
    write_scene(outside, {"intensity": blobs_scene((64, 64), looks=2.0, seed=1)}, tile=64, looks=2.0)
    link = server.data / "scenes" / "outx.zarr"
    link.symlink_to(outside)
    try:
        u = server.url
        listed = {s["sceneID"] for s in http.get(u + "/scenes").json()["scenes"]}
        assert "s1" in listed and "outx" not in listed, listed
        check_problem(http.get(u + "/scenes/outx"), 404, "outx")
        check_problem(http.post(u + "/processes/ca_cfar/execution", json={"inputs": {"scene": "outx"}}), 400, "outside")
        # a symlink inside the scene folder stays a scene
        inside = server.data / "scenes" / "inx.zarr"
        inside.symlink_to(server.data / "scenes" / "s1.zarr")
        assert "inx" in {s["sceneID"] for s in http.get(u + "/scenes").json()["scenes"]}
        assert http.get(u + "/scenes/inx").json()["status"] == "ready"
        inside.unlink()
    finally:
        link.unlink()
