"""The job API against a real ``sarship serve`` (uvicorn on loopback, a real local Dask
cluster, SQLite store): OGC state machine, results, errors, sync execution, dismissal, and
durability across ``kill -9``."""

from __future__ import annotations

import time

import numpy as np
import pytest

httpx = pytest.importorskip("httpx")
from conftest import blobs_scene, cov_scene, write_scene  # noqa: E402
from svc import Server, check_problem, data_with_scene, free_port, make_store, wait_job  # noqa: E402


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    import os

    data = data_with_scene(tmp_path_factory.mktemp("svc"))
    # a scene last written 400 days ago: the retention (365 days) removes it at start-up
    old = write_scene(data / "scenes" / "old.zarr", {"intensity": blobs_scene((32, 32))}, tile=64, looks=2.0)
    t = time.time() - 400 * 86400
    for f in (old, old / "zarr.json"):
        os.utime(f, (t, t))
    srv = Server(
        data, free_port(), SARSHIP_MAX_UPLOAD_MB="1", SARSHIP_LAND_MAX_MB="1", SARSHIP_SCENE_RETENTION_DAYS="365"
    ).start()
    yield srv
    srv.stop()


def test_ogc_state_machine_and_results(server):
    u = server.url
    land = httpx.get(u + "/").json()
    assert {"service-desc", "http://www.opengis.net/def/rel/ogc/1.0/processes"} <= {x["rel"] for x in land["links"]}
    assert any(c.endswith("/conf/core") for c in httpx.get(u + "/conformance").json()["conformsTo"])
    procs = {p["id"] for p in httpx.get(u + "/processes").json()["processes"]}
    assert {"ca_cfar", "os_cfar", "two_parameter", "apwf", "lmm", "pcdm", "vb_polsar"} <= procs
    desc = httpx.get(u + "/processes/ca_cfar").json()
    assert desc["inputs"]["pfa"]["schema"]["exclusiveMaximum"] == 0.5 and "scene" in desc["inputs"]
    r = httpx.post(
        u + "/processes/ca_cfar/execution",
        headers={"Prefer": "respond-async"},
        json={"inputs": {"scene": "s1", "pfa": 1e-4, "guard": 11, "background": 31, "min_area_px": 1}},
    )
    assert r.status_code == 201, r.text
    job_id = r.json()["jobID"]
    assert r.headers["location"].endswith(f"/jobs/{job_id}") and r.json()["status"] in ("accepted", "running")
    st = wait_job(u, job_id)
    assert st["status"] == "successful" and st["progress"] == 100 and st["finished"] >= st["started"], st
    res = httpx.get(f"{u}/jobs/{job_id}/results").json()
    assert set(res) == {"detections", "mask", "metrics", "stac"}
    det = httpx.get(res["detections"]["href"])
    assert det.headers["content-type"].startswith("application/geo+json")
    fc = det.json()
    assert fc["type"] == "FeatureCollection" and len(fc["features"]) >= 5
    met = httpx.get(res["metrics"]["href"]).json()
    assert met["detector"] == "ca_cfar" and met["detections"] == len(fc["features"])
    tif = httpx.get(res["mask"]["href"])
    assert tif.status_code == 200
    import io

    import tifffile

    m = tifffile.imread(io.BytesIO(tif.content))
    assert m.shape == (300, 260) and m.dtype == np.uint8 and m.sum() == met["mask_px"] > 0
    listed = [j["jobID"] for j in httpx.get(u + "/jobs").json()["jobs"]]
    assert listed.count(job_id) == 1


def test_sync_execution_returns_results(server):
    r = httpx.post(
        server.url + "/processes/os_cfar/execution",
        headers={"Prefer": "respond-sync"},
        json={"inputs": {"scene": "s1", "guard": 11, "background": 31}},
        timeout=120,
    )
    assert r.status_code == 200, r.text
    assert set(r.json()) == {"detections", "mask", "metrics", "stac"}


def test_bad_requests_are_problems(server):
    u = server.url
    check_problem(httpx.get(u + "/processes/nope"), 404, "nope")
    check_problem(httpx.post(u + "/processes/nope/execution", json={"inputs": {"scene": "s1"}}), 404)
    ex = u + "/processes/ca_cfar/execution"
    check_problem(httpx.post(ex, json={"inputs": {"scene": "s1", "pfa": 2}}), 400, "pfa")
    check_problem(httpx.post(ex, json={"inputs": {"scene": "s1", "bogus": 1}}), 400, "bogus")
    check_problem(httpx.post(ex, json={"inputs": {"scene": "s1", "guard": 10}}), 400, "odd")
    check_problem(httpx.post(ex, json={"inputs": {"pfa": 1e-3}}), 400, "scene")
    check_problem(httpx.post(ex, json={"inputs": {"scene": "s1", "device": "tpu"}}), 400, "device")
    check_problem(httpx.post(ex, content=b"{not json", headers={"content-type": "application/json"}), 400, "JSON")
    check_problem(httpx.post(ex, json=[1, 2]), 400, "inputs")
    check_problem(httpx.post(ex, json={"inputs": {"scene": "../../../etc"}}), 400, "scene")
    check_problem(httpx.post(ex, json={"inputs": {"scene": "/etc"}}), 400, "outside")
    check_problem(httpx.post(ex, json={"inputs": {"scene": "s3://bucket/x.zarr"}}), 400, "local")
    outside = server.data.parent / "elsewhere.zarr"
    outside.mkdir(exist_ok=True)
    link = server.data / "scenes" / "link.zarr"
    if not link.exists():
        link.symlink_to(outside)
    check_problem(httpx.post(ex, json={"inputs": {"scene": "link"}}), 400, "outside")  # symlink out of the root
    check_problem(httpx.get(u + "/jobs/doesnotexist"), 404, "doesnotexist")
    check_problem(httpx.get(u + "/jobs/doesnotexist/results"), 404)
    check_problem(httpx.get(u + "/jobs?status=weird"), 400, "status")
    # nothing of the above was accepted as a job
    assert all(j["processID"] in ("ca_cfar", "os_cfar") for j in httpx.get(u + "/jobs").json()["jobs"])


def test_dismiss(server):
    u = server.url
    # many short tasks (lmm exact, ~0.6 s per 32^2 tile, ~25 s per job): a job is still running
    # when it is dismissed, and what it already sent to the workers ends within a second
    write_scene(
        server.data / "scenes" / "s1_tiles32.zarr",
        {"intensity": blobs_scene((300, 260), looks=2.0, seed=3)},
        tile=32,
        looks=2.0,
    )
    slow = {"scene": "s1_tiles32", "method": "exact", "guard": 5, "background": 13}
    ids = [httpx.post(u + "/processes/lmm/execution", json={"inputs": slow}).json()["jobID"] for _ in range(3)]
    last = httpx.delete(f"{u}/jobs/{ids[-1]}")
    assert last.status_code == 200 and last.json()["status"] == "dismissed"
    first = httpx.delete(f"{u}/jobs/{ids[0]}").json()
    assert first["status"] == "dismissed"
    check_problem(httpx.get(f"{u}/jobs/{ids[0]}/results"), 404, "dismissed")
    httpx.delete(f"{u}/jobs/{ids[1]}")
    time.sleep(1.0)
    for i in ids:  # dismissed stays dismissed: the runner does not overwrite it
        assert httpx.get(f"{u}/jobs/{i}").json()["status"] == "dismissed"


def test_jobs_survive_kill_9(tmp_path):
    """Jobs accepted, some running, when the server is killed with SIGKILL: after a restart
    each job runs to success exactly once in the job list, and no output is half-written."""
    data = tmp_path / "data"
    (data / "scenes").mkdir(parents=True)
    write_scene(
        data / "scenes" / "s2.zarr", {"intensity": blobs_scene((256, 256), looks=2.0, seed=5)}, tile=64, looks=2.0
    )
    # a 2 s lease (the least allowed is above 1 s): the restarted server re-runs the killed job that much sooner
    srv = Server(data, free_port(), SARSHIP_CONCURRENCY="1", SARSHIP_LEASE_S="2").start()
    try:
        # the first (lmm defaults: ~2 s on 2 workers) runs, the two behind it (short ca_cfar jobs) wait
        ex = srv.url + "/processes/{}/execution"
        ids = [
            httpx.post(ex.format(p), json={"inputs": {"scene": "s2", **extra}}).json()["jobID"]
            for p, extra in (
                ("lmm", {}),
                ("ca_cfar", {"guard": 11, "background": 31}),
                ("ca_cfar", {"guard": 11, "background": 31}),
            )
        ]
        t_end = time.time() + 60
        while httpx.get(f"{srv.url}/jobs/{ids[0]}").json()["status"] != "running" and time.time() < t_end:
            time.sleep(0.1)
        srv.kill()  # SIGKILL, mid-run
    finally:
        srv.kill()
    srv2 = Server(data, free_port(), SARSHIP_LEASE_S="2").start()
    try:
        for i in ids:
            st = wait_job(srv2.url, i, timeout=180)
            assert st["status"] == "successful", st
        jobs = httpx.get(srv2.url + "/jobs").json()["jobs"]
        assert sorted(j["jobID"] for j in jobs) == sorted(ids)  # each exactly once
        assert next(j for j in jobs if j["jobID"] == ids[0])["attempts"] == 2  # re-run after the kill
        for i in ids:
            out = data / "jobs" / i
            assert {"detections.geojson", "mask.zarr", "run.json"} <= {p.name for p in out.iterdir()}
            assert not [p for p in out.iterdir() if p.name.startswith(".sarship-partial")]
    finally:
        srv2.stop()


#: a runner of its own: claims jobs of the store at argv[1] until none is left, finishing each (as
#: service/runner.py does, as its attempt); prints the IDs it ran
CLAIMER = """
import sys, time
from sarship.service.store import JobStore
store, owner, ran = JobStore(sys.argv[1]), sys.argv[2], []
while time.time() < float(sys.argv[3]):
    job = store.claim(owner, 30.0)
    if job is None:
        break
    assert store.finish(job["id"], owner, "successful", "done", attempt=job["attempts"])
    ran.append(job["id"])
print(" ".join(ran))
"""


def test_two_processes_on_one_store_never_claim_a_job_twice(tmp_path):
    """The rule of the two-server test below (slow), on the store alone: two processes claiming
    from one job store at once each take a job at most once, and every job is run once."""
    import subprocess
    import sys

    from sarship.service.store import JobStore

    store = JobStore(tmp_path / "jobs.sqlite")
    ids = [store.create("os_cfar", {"scene": "s3"})["id"] for _ in range(200)]
    start = time.time() + 1.0  # both processes start claiming at this moment (once imported)
    args = [
        sys.executable,
        "-c",
        f"import time; time.sleep(max(0, {start} - time.time()))\n{CLAIMER}",
        str(tmp_path / "jobs.sqlite"),
    ]
    procs = [
        subprocess.Popen([*args, f"host-{k}-x", str(start + 60)], stdout=subprocess.PIPE, text=True) for k in range(2)
    ]
    ran = [p.communicate(timeout=120)[0].split() for p in procs]
    assert all(p.returncode == 0 for p in procs)
    assert sorted(ran[0] + ran[1]) == sorted(ids)  # each job once, by one of the two
    assert all(store.get(i)["attempts"] == 1 and store.get(i)["status"] == "successful" for i in ids)


@pytest.mark.slow  # two servers; test_two_processes_on_one_store_never_claim_a_job_twice keeps the rule in the default run
def test_two_api_processes_share_a_store_without_running_a_job_twice(tmp_path):
    data = tmp_path / "data"
    (data / "scenes").mkdir(parents=True)
    write_scene(
        data / "scenes" / "s3.zarr", {"intensity": blobs_scene((200, 180), looks=2.0, seed=6)}, tile=64, looks=2.0
    )
    make_store(data)  # (before the two start at once)
    a = Server(data, free_port(), SARSHIP_WORKERS="1")
    b = Server(data, free_port(), SARSHIP_WORKERS="1")
    try:
        from concurrent.futures import ThreadPoolExecutor

        with ThreadPoolExecutor(2) as pool:  # start both at once
            list(pool.map(Server.start, (a, b)))
        ids = []
        for k in range(8):
            srv = a if k % 2 == 0 else b
            r = httpx.post(
                srv.url + "/processes/os_cfar/execution",
                json={"inputs": {"scene": "s3", "guard": 11, "background": 31}},
            )
            assert r.status_code == 201
            ids.append(r.json()["jobID"])
        for i in ids:
            assert wait_job(a.url, i)["status"] == "successful"
        jobs = {j["jobID"]: j for j in httpx.get(b.url + "/jobs").json()["jobs"]}
        assert sorted(jobs) == sorted(ids)
        assert all(jobs[i]["attempts"] == 1 for i in ids), [jobs[i]["attempts"] for i in ids]  # never twice
    finally:
        a.stop()
        b.stop()


def test_metrics_and_readiness(server):
    u = server.url
    assert httpx.get(u + "/livez").json() == {"status": "ok"}
    ready = httpx.get(u + "/readyz").json()
    # svc.py's servers: SARSHIP_WORKERS=2 as threads of one in-process worker
    assert ready["status"] == "ok" and ready["checks"]["workers"] == 1 and ready["checks"]["threads"] == 2, ready
    dash = httpx.get(u + "/dashboard", follow_redirects=False)
    assert dash.status_code == 307 and dash.headers["location"].startswith("http")
    r = httpx.post(u + "/processes/ca_cfar/execution", json={"inputs": {"scene": "s1", "guard": 11, "background": 31}})
    assert wait_job(u, r.json()["jobID"])["status"] == "successful"
    text = httpx.get(u + "/metrics").text
    lines = {ln.split(" ")[0]: ln for ln in text.splitlines() if ln and not ln.startswith("#")}
    assert 'sarship_build_info{version="' in text
    assert float(lines['sarship_jobs{status="successful"}'].split()[-1]) >= 1
    assert float(lines["sarship_tiles_processed_total"].split()[-1]) >= 9  # 3 x 3 tiles of 128 px
    assert float(lines["sarship_pixels_processed_total"].split()[-1]) >= 300 * 260
    assert 'sarship_job_duration_seconds_count{process="ca_cfar",status="successful"}' in lines
    assert "jobID" not in text and r.json()["jobID"] not in text  # no job IDs as labels


def test_tokens(tmp_path):
    """Tokens (two of them) with protect_reads: POST, DELETE and reads need one; /livez and
    /metrics stay open. (Reads open without protect_reads: test_fuzz.py's tokens test, whose
    server has tokens only.)"""
    data = tmp_path / "data"
    (data / "scenes").mkdir(parents=True)
    write_scene(
        data / "scenes" / "s4.zarr", {"intensity": blobs_scene((100, 90), looks=2.0, seed=7)}, tile=64, looks=2.0
    )
    srv = Server(
        data, free_port(), SARSHIP_WORKERS="1", SARSHIP_TOKENS='["t0ken-a", "t0ken-b"]', SARSHIP_PROTECT_READS="true"
    ).start()
    try:
        ex = srv.url + "/processes/ca_cfar/execution"
        body = {"inputs": {"scene": "s4", "guard": 5, "background": 15}}
        r = httpx.post(ex, json=body)
        check_problem(r, 401, "Bearer")
        assert r.headers["www-authenticate"] == "Bearer"
        check_problem(httpx.post(ex, json=body, headers={"Authorization": "Bearer wrong"}), 403)
        ok = httpx.post(ex, json=body, headers={"Authorization": "Bearer t0ken-b"})
        assert ok.status_code == 201
        check_problem(httpx.delete(f"{srv.url}/jobs/{ok.json()['jobID']}"), 401)
        assert httpx.get(srv.url + "/metrics").status_code == 200
        check_problem(httpx.get(srv.url + "/jobs"), 401)
        for token in ("t0ken-a", "t0ken-b"):
            assert httpx.get(srv.url + "/jobs", headers={"Authorization": f"Bearer {token}"}).status_code == 200
        assert httpx.get(srv.url + "/livez").status_code == 200
    finally:
        srv.stop()


def test_scene_upload_ingest_and_detect(server, tmp_path):
    import io

    import tifffile

    u = server.url
    x = blobs_scene((120, 110), looks=2.0, seed=9)
    buf = io.BytesIO()
    tifffile.imwrite(buf, x)
    raw = buf.getvalue()
    r = httpx.post(u + "/scenes?filename=pass1.tif", content=raw, headers={"content-type": "application/octet-stream"})
    assert r.status_code == 201, r.text
    doc = r.json()
    import hashlib

    assert doc["sha256"] == hashlib.sha256(raw).hexdigest() and doc["bytes"] == len(raw)
    assert wait_job(u, doc["jobID"])["status"] == "successful"
    # an ingest job's result is its scene; it has no detection products
    res = httpx.get(f"{u}/jobs/{doc['jobID']}/results").json()
    assert res["scene"]["href"].endswith(f"/scenes/{doc['sceneID']}"), res
    for product in ("detections", "metrics", "mask", "stac"):
        check_problem(httpx.get(f"{u}/jobs/{doc['jobID']}/results/{product}"), 404, "ingest")
    check_problem(httpx.get(f"{u}/jobs/{doc['jobID']}/tiles.json"), 404, "ingest")
    sc = httpx.get(f"{u}/scenes/{doc['sceneID']}").json()
    assert sc["status"] == "ready" and sc["shape"] == [120, 110]
    assert doc["sceneID"] in {s["sceneID"] for s in httpx.get(u + "/scenes").json()["scenes"]}
    # the same content again (multipart this time): the same scene, no new ingest
    again = httpx.post(u + "/scenes", files={"file": ("copy.tif", raw, "image/tiff")})
    assert again.status_code == 200 and again.json()["sceneID"] == doc["sceneID"]
    job = httpx.post(
        u + "/processes/ca_cfar/execution", json={"inputs": {"scene": doc["sceneID"], "guard": 11, "background": 31}}
    ).json()
    assert wait_job(u, job["jobID"])["status"] == "successful"
    # garbage: accepted as bytes, its ingest fails with the reader's message, and is listed as failed
    bad = httpx.post(u + "/scenes?filename=junk.tif", content=b"not a tiff at all" * 10)
    assert bad.status_code == 201
    st = wait_job(u, bad.json()["jobID"])
    assert st["status"] == "failed" and st["message"] and "internal error" not in st["message"], st
    listed = {s["sceneID"]: s for s in httpx.get(u + "/scenes").json()["scenes"]}
    assert listed[bad.json()["sceneID"]]["status"] == "failed"
    # too large (limit 1 MiB here), no name, empty: 4xx problems and nothing left behind
    big = np.zeros(2**21 // 4 + 10, np.float32).tobytes()
    check_problem(httpx.post(u + "/scenes?filename=big.npy", content=big), 413, "limit")
    check_problem(httpx.post(u + "/scenes", content=raw), 400, "name")
    check_problem(httpx.post(u + "/scenes?filename=e.tif", content=b""), 400, "empty")
    assert not [p for p in (server.data / "uploads").iterdir() if p.name.startswith(".upload-")]
    check_problem(httpx.get(u + "/scenes/nosuchscene"), 404, "nosuchscene")


def test_preview_png(server):
    import io

    from PIL import Image

    u = server.url
    r = httpx.post(
        u + "/processes/ca_cfar/execution",
        json={"inputs": {"scene": "s1", "guard": 11, "background": 31, "min_area_px": 1}},
    )
    job_id = r.json()["jobID"]
    assert wait_job(u, job_id)["status"] == "successful"
    png = httpx.get(f"{u}/jobs/{job_id}/preview.png?size=128")
    assert png.status_code == 200 and png.headers["content-type"] == "image/png"
    img = np.asarray(Image.open(io.BytesIO(png.content)).convert("RGB"))
    assert max(img.shape[:2]) <= 128 and img.shape[:2] == (-(-300 // 3), -(-260 // 3))
    red = (img[..., 0] == 255) & (img[..., 1] == 40)
    yellow = (img[..., 0] == 255) & (img[..., 1] == 220)
    assert red.sum() > 0 and yellow.sum() > 0  # detected pixels and their boxes are drawn
    full = np.asarray(Image.open(io.BytesIO(httpx.get(f"{u}/jobs/{job_id}/preview.png?size=1024").content)))
    assert full.shape[:2] == (300, 260)
    check_problem(httpx.get(f"{u}/jobs/{job_id}/preview.png?size=5"), 400, "size")


def test_serve_start_problems_are_one_line(tmp_path, monkeypatch, capsys):
    """What the operator got wrong stops ``sarship serve`` before it starts: exit 2, one line
    naming the problem, no traceback (service/preflight.py). The unreachable scheduler (a 10 s
    connection timeout) runs as a process; meanwhile the other cases call the command's ``main``
    in this process, one after the other (the same code from the arguments on; seven process
    start-ups at once cost the 2-core CI machine seconds)."""
    import os
    import socket
    import subprocess
    import sys

    from sarship.cli import main

    (tmp_path / "afile").write_text("not a folder")
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / "jobs.sqlite").write_bytes(b"garbage " * 64)
    busy = socket.socket()
    busy.bind(("127.0.0.1", 0))
    busy.listen()
    cases = [
        (["--data", str(tmp_path / "afile")], "is not a folder"),
        (["--data", str(tmp_path / "afile" / "sub")], "Not a directory"),
        (["--data", str(tmp_path / "bad")], "not a database"),
        (["--data", str(tmp_path / "ok"), "--port", str(busy.getsockname()[1])], "Address already in use"),
        (["--data", str(tmp_path / "ok"), "--host", "no-such-host.invalid"], "cannot resolve"),
        (
            ["--data", str(tmp_path / "ok"), "--scheduler", f"tcp://127.0.0.1:{free_port()}"],
            "cannot reach Dask scheduler",
        ),
        (["--data", str(tmp_path / "ok"), "--gpus", "0"], "no GPU is visible"),
    ]  # (GPUs hidden below)
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "")
    for k in list(os.environ):  # (the test process's own settings, if any, are not the operator's)
        if k.startswith("SARSHIP_"):
            monkeypatch.delenv(k)

    def check(args, words, rc, err):
        lines = [ln for ln in err.splitlines() if ln.strip()]
        assert rc == 2 and len(lines) == 1 and words in lines[0], (args, rc, err)
        assert lines[0].startswith("sarship serve: error: ") and "Traceback" not in err

    remote = next(c for c in cases if "--scheduler" in c[0])
    proc = subprocess.Popen(
        [sys.executable, "-m", "sarship", "serve", *remote[0]],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=dict(os.environ),
    )
    try:
        for args, words in cases:
            if (args, words) != remote:
                rc = main(["serve", *args])
                check(args, words, rc, capsys.readouterr().err)
        _, err = proc.communicate(timeout=120)
        check(remote[0], remote[1], proc.returncode, err)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        busy.close()
    assert (tmp_path / "bad" / "jobs.sqlite").read_bytes() == b"garbage " * 64  # a bad store is left as it was


def no_server_path(server, text: str) -> None:
    """``text`` (a problem body, a job's message) names no path of the server's data folder."""
    for form in {str(server.data), str(server.data.resolve())}:
        assert form not in text, text


def test_submission_checks_and_no_server_paths(server):
    """A detector that cannot read the scene (vb_polsar on a covariance scene, csk on intensity),
    a channel that is a path or a variable the scene lacks, non-finite parameters (NaN,
    Infinity, 1e999, "nan"), and land_mask FILEs that are no regular file or too large: each a
    400 at submission naming the problem, and no 4xx body, nor a failed job's message (a
    GeoJSON nested 200 000 deep, parsed in the job's capped child), shows the data folder."""
    import os

    u = server.url
    scenes = server.data / "scenes"
    cov_scene(scenes / "cov.zarr")
    ex = u + "/processes/{}/execution"
    bodies = []

    def refused(detector, inputs, *words, raw=None):
        r = (
            httpx.post(ex.format(detector), content=raw, headers={"content-type": "application/json"})
            if raw
            else httpx.post(ex.format(detector), json={"inputs": inputs})
        )
        check_problem(r, 400, *words)
        bodies.append(r.text)

    refused("vb_polsar", {"scene": "cov"}, "vb_polsar", "covariance")
    refused("csk", {"scene": "s1"}, "complex")
    refused("ca_cfar", {"scene": "s1", "channel": "../../s1.zarr/intensity"}, "channel", "never a path")
    refused("ca_cfar", {"scene": "s1", "channel": "hh"}, "channel", "no variable 'hh'")
    refused("ca_cfar", {}, "nodata", "finite", raw=b'{"inputs": {"scene": "s1", "nodata": NaN}}')
    refused("ca_cfar", {}, "max_length_m", "finite", raw=b'{"inputs": {"scene": "s1", "max_length_m": 1e999}}')
    refused("ca_cfar", {}, "max_elongation", "finite", raw=b'{"inputs": {"scene": "s1", "max_elongation": Infinity}}')
    refused("ca_cfar", {"scene": "s1", "min_length_m": "nan"}, "min_length_m", "finite")
    os.mkfifo(scenes / "land.fifo")
    refused("ca_cfar", {"scene": "s1", "land_mask": "land.fifo"}, "land_mask", "not a regular file")
    (scenes / "big.geojson").write_bytes(b" " * 2**20 + b"{}")  # beyond land_max_mb (1 MiB here)
    refused("ca_cfar", {"scene": "s1", "land_mask": "big.geojson"}, "land_mask", "SARSHIP_LAND_MAX_MB")
    (scenes / "big.geojson").unlink()
    refused("ca_cfar", {"scene": str(scenes / "nope.zarr")}, "scene")
    for b in bodies:
        no_server_path(server, b)
    # apwf reads the covariance scene (the same check accepts it)
    r = httpx.post(ex.format("apwf"), json={"inputs": {"scene": "cov", "guard": 5, "background": 9}})
    assert r.status_code == 201, r.text
    # a GeoJSON nested 200 000 deep: accepted (only its stat is checked here), then refused by the
    # job's child process with one line (no RecursionError), naming the file as the client did
    (scenes / "deep.geojson").write_bytes(b"[" * 200_000 + b"]" * 200_000)
    r = httpx.post(ex.format("ca_cfar"), json={"inputs": {"scene": "s1", "land_mask": "deep.geojson"}})
    assert r.status_code == 201, r.text
    st = wait_job(u, r.json()["jobID"])
    assert st["status"] == "failed" and "nested deeper than" in st["message"], st
    assert "'deep.geojson'" in st["message"] and "\n" not in st["message"], st
    no_server_path(server, st["message"])
    assert (
        wait_job(
            u,
            httpx.post(ex.format("apwf"), json={"inputs": {"scene": "cov", "guard": 5, "background": 9}}).json()[
                "jobID"
            ],
        )["status"]
        == "successful"
    )


def test_scene_retention_at_start_up(server):
    """SARSHIP_SCENE_RETENTION_DAYS=365: the scene last written 400 days ago was removed when the
    server started; the fresh one stays."""
    t_end = time.time() + 30
    while (server.data / "scenes" / "old.zarr").exists() and time.time() < t_end:
        time.sleep(0.1)
    assert not (server.data / "scenes" / "old.zarr").exists()
    assert (server.data / "scenes" / "s1.zarr").is_dir()
    check_problem(httpx.get(server.url + "/scenes/old"), 404, "old")


def test_scene_names_and_delete(server):
    """GET /scenes lists each scene's uploaded file name, product name and acquisition time;
    DELETE /scenes/{id} refuses (409) while a queued job names the scene, then removes the
    store and its upload (404 afterwards)."""
    import io

    import tifffile

    from sarship.service.store import JobStore

    u = server.url
    buf = io.BytesIO()
    tifffile.imwrite(buf, blobs_scene((64, 72), looks=2.0, seed=21))
    r = httpx.post(u + "/scenes?filename=../harbour_2026.tif", content=buf.getvalue())
    assert r.status_code == 201, r.text
    sid = r.json()["sceneID"]
    st = wait_job(u, r.json()["jobID"])
    assert st["status"] == "successful", st
    doc = httpx.get(f"{u}/scenes/{sid}").json()
    assert doc["filename"] == "harbour_2026.tif" and doc["product"] == "harbour_2026", doc
    assert doc["acquired"] is None and doc["ingested"].endswith("Z"), doc
    listed = {s["sceneID"]: s for s in httpx.get(u + "/scenes").json()["scenes"]}
    assert listed[sid]["filename"] == "harbour_2026.tif" and {"product", "acquired"} <= set(listed["s1"])
    # a job queued for later (a retry's back-off) names the scene: 409, nothing removed
    store = JobStore(server.data / "jobs.sqlite")
    queued = store.create("ca_cfar", {"scene": sid})
    store._conn().execute("UPDATE jobs SET not_before = ? WHERE id = ?", (time.time() + 3600, queued["id"]))
    check_problem(httpx.delete(f"{u}/scenes/{sid}"), 409, queued["id"])
    assert (server.data / "scenes" / f"{sid}.zarr").is_dir()
    httpx.delete(f"{u}/jobs/{queued['id']}")
    r = httpx.delete(f"{u}/scenes/{sid}")
    assert r.status_code == 200 and r.json() == {"sceneID": sid, "status": "deleted"}, r.text
    assert not (server.data / "scenes" / f"{sid}.zarr").exists()
    assert not list((server.data / "uploads").glob(f"{sid}.*"))
    assert not [p for p in (server.data / "scenes").iterdir() if p.name.startswith(".deleted-")]
    check_problem(httpx.get(f"{u}/scenes/{sid}"), 404, sid)
    check_problem(httpx.delete(f"{u}/scenes/{sid}"), 404, sid)
    assert sid not in {s["sceneID"] for s in httpx.get(u + "/scenes").json()["scenes"]}
    check_problem(httpx.post(u + "/processes/ca_cfar/execution", json={"inputs": {"scene": sid}}), 400, "no scene")
