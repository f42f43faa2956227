"""Faults that must not lose or stall good work, against real processes (``sarship serve`` on
loopback with its local Dask cluster and SQLite store, ``sarship ingest``):

1. a full data disk is a fault of ours, not bad input: an inbox pass is retried with back-off
   (never quarantined) and ingested once space returns; ``/readyz`` says not ready while the
   data folder has less free space than ``SARSHIP_MIN_FREE_MB``;
2. a ``NAME.done`` marker is consumed by the pass it marked: the next file of that name is not
   taken while it is still being written;
3. no ``.partial`` store is left behind by ``kill -9`` of a server mid-ingest (after the
   restart, also for an ingest dismissed meanwhile) or by SIGTERM of ``sarship ingest``;
4. a runner stopped (SIGSTOP) past its lease while another runner re-runs the job cannot
   publish its outputs: the job's results are those of the attempt that finished it, once.

The full disk is real: the server process runs with ``RLIMIT_FSIZE`` (inherited by its ingest
child), so a write past the limit fails with ``EFBIG`` as it fails with ``ENOSPC`` on a full
disk. A process cannot be given back a larger limit from outside, so "space returns" is a
restart of the server without the limit on the same data folder.
"""

from __future__ import annotations

import io
import json
import os
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

httpx = pytest.importorskip("httpx")
from conftest import fsize_limit, write_scene  # noqa: E402
from svc import Server, free_port, make_store, passes, tif_bytes, wait_job, wait_pass  # noqa: E402

from sarship.service.inbox_files import marker  # noqa: E402


def npy_bytes(a: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, a)
    return buf.getvalue()


def partials(scenes: Path) -> list[str]:
    """Temporary scene stores (``.ID.zarr.partial-*`` and the like) left in ``scenes``."""
    return sorted(p.name for p in scenes.iterdir() if p.name.startswith(".")) if scenes.is_dir() else []


def start_live(srv: Server, preexec=None, timeout: float = 120.0) -> Server:
    """Start ``srv`` (optionally with a ``preexec_fn``) and wait until it answers with its
    workers up, whatever ``/readyz`` says about the disk."""
    srv.log = open(srv.data.parent / f"server-{srv.port}-{time.time_ns()}.log", "w")
    srv.proc = subprocess.Popen(
        [sys.executable, "-m", "sarship", "serve", "--data", str(srv.data), "--port", str(srv.port)],
        stdout=srv.log,
        stderr=subprocess.STDOUT,
        env=srv.env,
        start_new_session=True,
        preexec_fn=preexec,
    )
    t_end = time.time() + timeout
    while time.time() < t_end:
        assert srv.proc.poll() is None, Path(srv.log.name).read_text()[-2000:]
        try:
            r = httpx.get(srv.url + "/readyz", timeout=2)
            if r.json().get("checks", {}).get("workers", 0) > 0:
                return srv
        except (httpx.HTTPError, ValueError):
            pass
        time.sleep(0.3)
    raise RuntimeError("server did not come up")


def test_a_full_disk_is_retried_not_quarantined_and_readyz_says_so(tmp_path):
    data, inbox = tmp_path / "data", tmp_path / "inbox"
    data.mkdir()
    inbox.mkdir()
    # one 2048 x 2048 tile of float32 noise: a shard of ~14 MB, past the 8 MiB file-size limit
    img = np.random.default_rng(1).gamma(2.0, 0.5, (2048, 2048)).astype(np.float32)
    (inbox / "big.npy").write_bytes(npy_bytes(img))
    marker(inbox / "big.npy").touch()
    env = dict(
        SARSHIP_WORKERS="1",
        SARSHIP_INBOX=json.dumps([str(inbox)]),
        SARSHIP_INBOX_INTERVAL_S="0.5",
        SARSHIP_INBOX_SETTLE_S="1",
        SARSHIP_RETRY_S="0.5",
        SARSHIP_RETRY_MAX_S="1",
    )
    full = Server(data, free_port(), SARSHIP_MIN_FREE_MB=str(2**40), **env)  # "less free than 1 EiB"
    try:
        start_live(full, preexec=fsize_limit(8 << 20))
        r = httpx.get(full.url + "/readyz")
        assert r.status_code == 503 and r.json()["status"] == "not ready", r.text
        assert "min_free_mb" in r.json()["checks"]["disk"], r.json()
        t_end = time.time() + 60
        while True:  # the ingest fails for want of space and is retried, the pass stays ingesting
            p = passes(full.url).get("big.npy")
            job = httpx.get(f"{full.url}/jobs/{p['ingestJob']}").json() if p and p["ingestJob"] else None
            if job is not None and job["attempts"] >= 2 and job["status"] == "accepted":
                break
            assert time.time() < t_end and (p is None or p["status"] in ("waiting", "ingesting")), (p, job)
            time.sleep(0.2)
        assert "File too large" in job["message"] and "retry" in job["message"], job
        assert (inbox / "big.npy").is_file() and not (data / "quarantine" / "big.npy").exists()
        assert not (data / "scenes" / f"{p['sceneID']}.zarr").exists()
    finally:
        full.kill()
    # space returns: the same data folder without the limit; the pass is ingested
    srv = Server(data, free_port(), **env).start()  # (start waits for /readyz 200)
    try:
        assert httpx.get(srv.url + "/readyz").json()["checks"]["disk"] == "ok"
        assert httpx.post(srv.url + "/ingest/scan").status_code == 202
        done = wait_pass(srv.url, "big.npy", ("ingested", "quarantined", "failed"))
        assert done["status"] == "ingested", done
        assert wait_job(srv.url, done["ingestJob"])["status"] == "successful"
        assert (data / "scenes" / f"{done['sceneID']}.zarr").is_dir() and partials(data / "scenes") == []
        assert not (data / "quarantine" / "big.npy").exists()
    finally:
        srv.kill()


# ----------------------------------------------------------------------------- 2. markers


@pytest.fixture(scope="module")
def inbox_server(tmp_path_factory):
    root = tmp_path_factory.mktemp("faults-inbox")
    data, inbox = root / "data", root / "inbox"
    data.mkdir()
    inbox.mkdir()
    srv = Server(
        data,
        free_port(),
        SARSHIP_INBOX=json.dumps([str(inbox)]),
        SARSHIP_INBOX_INTERVAL_S="0.3",
        SARSHIP_INBOX_SETTLE_S="4",
    ).start()  # 4 s: appends 0.25 s apart (plus a status request each,
    # which a loaded 2-core CI machine can take a second to answer) never look settled
    srv.inbox = inbox
    yield srv
    srv.stop()


def test_a_done_marker_is_consumed_with_its_pass(inbox_server):
    u, inbox = inbox_server.url, inbox_server.inbox
    f = inbox / "same.tif"
    f.write_bytes(tif_bytes(seed=51))
    marker(f).touch()
    p = wait_pass(u, "same.tif", ("ingested", "quarantined", "failed"))
    assert p["status"] == "ingested", p
    assert not marker(f).exists()  # taken with its pass
    f.unlink()  # the operator clears the inbox; the next pass of that name arrives slowly
    marker(f).touch()  # and an old marker (of another time) lies there too
    old = time.time() - 3600
    os.utime(marker(f), (old, old))
    raw = tif_bytes(seed=52)
    half = len(raw) // 2
    f.write_bytes(raw[:half])
    pieces = np.linspace(half, len(raw), 9).astype(int)
    for a, b in zip(pieces[:-2], pieces[1:-1]):  # appends 0.25 s apart, within the 4 s settle time
        time.sleep(0.25)
        assert passes(u)["same.tif"]["status"] in ("waiting", "ingested"), passes(u)["same.tif"]
        with open(f, "ab") as fh:
            fh.write(raw[a:b])
    with open(f, "ab") as fh:
        fh.write(raw[pieces[-2] :])
    t_end = time.time() + 30
    while True:  # the newest record of same.tif is the new content's, taken once complete
        p = passes(u)["same.tif"]
        if p["key"] == _key(raw) and p["status"] not in ("waiting", "ingesting"):
            break
        assert time.time() < t_end and p["status"] not in ("quarantined", "failed"), p
        time.sleep(0.1)
    assert p["status"] == "ingested", p


def _key(raw: bytes) -> str:
    import hashlib

    return hashlib.sha256(raw).hexdigest()[:16]


# ----------------------------------------------------------------------------- 3. partial stores


def test_sigterm_of_sarship_ingest_leaves_no_partial(tmp_path):
    src = tmp_path / "big.npy"
    np.save(src, np.random.default_rng(2).gamma(2.0, 0.5, (4000, 4000)).astype(np.float32))
    out = tmp_path / "out" / "big.zarr"
    out.parent.mkdir()
    p = subprocess.Popen(
        [sys.executable, "-m", "sarship", "ingest", str(src), "--out", str(out), "--tile", "256"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )
    try:
        err = b""
        t_end = time.time() + 60
        while b"ingest" not in err or b"/" not in err:  # its progress line: tiles done / total
            assert p.poll() is None and time.time() < t_end, err
            err += os.read(p.stderr.fileno(), 4096)
        assert list(out.parent.iterdir()), "no partial store yet"
        p.send_signal(signal.SIGTERM)
        rc = p.wait(timeout=30)
    finally:
        p.kill()
    err += p.stderr.read()
    assert rc == 143, (rc, err[-500:])
    assert list(out.parent.iterdir()) == [], list(out.parent.iterdir())  # no scene, no .partial


def _upload(url: str, name: str, raw: bytes) -> dict:
    r = httpx.post(f"{url}/scenes?filename={name}", content=raw, timeout=60)
    assert r.status_code == 201, r.text
    return r.json()


def test_kill_9_mid_ingest_leaves_no_partial_after_restart(tmp_path):
    data = tmp_path / "data"
    data.mkdir()
    scenes = data / "scenes"
    rng = np.random.default_rng(3)
    raws = [npy_bytes(rng.gamma(2.0, 0.5, (3000, 3000)).astype(np.float32)) for _ in range(2)]
    # a 2 s lease (the least allowed is above 1 s): after the restart the killed ingest runs again that much sooner
    srv = Server(data, free_port(), SARSHIP_WORKERS="1", SARSHIP_LEASE_S="2").start()
    try:
        docs = [_upload(srv.url, f"p{k}.npy", raw) for k, raw in enumerate(raws)]
        t_end = time.time() + 60
        while len([n for n in partials(scenes) if ".partial-" in n]) < 2:  # both being written
            assert time.time() < t_end, partials(scenes)
            time.sleep(0.05)
        srv.kill()  # SIGKILL, mid-ingest: the server, its Dask workers and the ingest children
    finally:
        srv.kill()
    assert len(partials(scenes)) >= 2
    from sarship.service.store import JobStore

    store = JobStore(data / "jobs.sqlite")
    assert store.dismiss(docs[1]["jobID"])[1] == "running"  # what DELETE /jobs/ID does, the server down
    store.close()
    srv = Server(data, free_port(), SARSHIP_WORKERS="1", SARSHIP_LEASE_S="2").start()
    try:
        st = wait_job(srv.url, docs[0]["jobID"], timeout=120)
        assert st["status"] == "successful" and st["attempts"] == 2, st
        assert (scenes / f"{docs[0]['sceneID']}.zarr").is_dir()
        assert not (scenes / f"{docs[1]['sceneID']}.zarr").exists()
        t_end = time.time() + 20  # the dismissed one's partial goes too (swept at start and every lease)
        while partials(scenes) and time.time() < t_end:
            time.sleep(0.2)
        assert partials(scenes) == []
    finally:
        srv.stop()


# ----------------------------------------------------------------------------- 4. fencing


def many_blobs(shape, n: int, seed: int, looks: float = 2.0, amp: float = 40.0) -> np.ndarray:
    """``conftest.blobs_scene`` vectorised (its loop takes seconds for 100 000 blobs): gamma
    clutter with ``n`` bright rectangles of 1-5 x 1-11 pixels at random places."""
    rng = np.random.default_rng(seed)
    x = rng.gamma(looks, 1.0 / looks, shape).astype(np.float32)
    r = rng.integers(0, shape[0] - 6, n)
    c = rng.integers(0, shape[1] - 12, n)
    hh, ww = rng.integers(1, 6, n), rng.integers(1, 12, n)
    for h in range(1, 6):
        for w in range(1, 12):
            k = (hh == h) & (ww == w)
            rows = (r[k, None, None] + np.arange(h)[None, :, None]).repeat(w, axis=2)
            cols = (c[k, None, None] + np.arange(w)[None, None, :]).repeat(h, axis=1)
            vals = amp * rng.random(rows.shape).astype(np.float32) + amp / 4
            np.add.at(x, (rows, cols), vals)
    return x


def _job_row(data: Path, job_id: str) -> dict:
    c = sqlite3.connect(data / "jobs.sqlite", timeout=30)
    c.row_factory = sqlite3.Row
    try:
        return dict(c.execute("SELECT * FROM jobs WHERE id = ?", (job_id,)).fetchone())
    finally:
        c.close()


@pytest.mark.slow  # two servers and a 2000 x 2000 job run twice; test_the_store_fences_a_stale_attempt_of_the_same_owner keeps the rule in the default run
def test_a_runner_stopped_past_its_lease_cannot_publish(tmp_path):
    """Two API processes on one store; the one running a job is stopped (SIGSTOP, its Dask
    workers too) once the job's last tile is done, past its lease: the other re-runs the job
    and publishes; the stopped one, continued, finishes its run but publishes nothing."""
    data = tmp_path / "data"
    (data / "scenes").mkdir(parents=True)
    write_scene(
        data / "scenes" / "many.zarr", {"intensity": many_blobs((2000, 2000), n=100_000, seed=1)}, tile=512, looks=2.0
    )
    env = dict(SARSHIP_WORKERS="1", SARSHIP_LEASE_S="2", SARSHIP_CONCURRENCY="1")
    make_store(data)  # (before the two start at once)
    servers = [Server(data, free_port(), **env), Server(data, free_port(), **env)]
    stopped = None
    try:
        from concurrent.futures import ThreadPoolExecutor

        with ThreadPoolExecutor(2) as pool:
            list(pool.map(Server.start, servers))
        u = servers[0].url
        r = httpx.post(
            u + "/processes/ca_cfar/execution",
            json={"inputs": {"scene": "many", "guard": 5, "background": 15, "min_area_px": 1}},
        )
        job_id = r.json()["jobID"]
        t_end = time.time() + 120
        while True:  # every tile done: the runner merges and writes its outputs now
            row = _job_row(data, job_id)
            if row["status"] == "running" and row["progress"] >= 99:
                break
            assert row["status"] in ("accepted", "running") and time.time() < t_end, row
            time.sleep(0.01)
        pid = int(row["lease_owner"].split("-")[-2])
        stopped = next(s for s in servers if s.proc.pid == pid)
        os.killpg(stopped.proc.pid, signal.SIGSTOP)
        other = next(s for s in servers if s is not stopped)
        st = wait_job(other.url, job_id, timeout=120)
        assert st["status"] == "successful" and st["attempts"] == 2, st
        os.killpg(stopped.proc.pid, signal.SIGCONT)
        time.sleep(3)  # the stopped runner finishes its run meanwhile (under a second)
        after = httpx.get(f"{other.url}/jobs/{job_id}").json()
        assert after["status"] == "successful" and after["finished"] == st["finished"], (st, after)
        assert after["message"] == st["message"]
        # the published outputs are those of the attempt that finished the job
        run = httpx.get(f"{other.url}/jobs/{job_id}/results/metrics").json()
        assert st["message"] == f"{run['detections']} detections in {run['timings']['total_s']:.1f} s", (st, run)
        out = data / "jobs" / job_id
        assert {p.name for p in out.iterdir()} >= {"detections.geojson", "mask.zarr", "run.json"}
        assert not [p.name for p in out.iterdir() if p.name.startswith(".")], list(out.iterdir())
        on_disk = json.loads((out / "run.json").read_text())["outputs"]
        assert all(Path(v).parent == out.resolve() for v in on_disk.values()), on_disk
        # the API names them relative to the data folder, never by the server's path
        assert run["outputs"] == {k: f"jobs/{job_id}/{k}" for k in on_disk}, run["outputs"]
    finally:
        if stopped is not None:
            os.killpg(stopped.proc.pid, signal.SIGCONT)
        for s in servers:
            s.kill()


def test_the_store_fences_a_stale_attempt_of_the_same_owner(tmp_path):
    """Two runner threads of one process share an owner: after a stall past the lease, the
    other thread may take the job again. The stale attempt can then neither renew, nor
    finish, nor publish; the new one can. A job put back for a fault of ours is claimed
    again only after its back-off (or at once when asked)."""
    from sarship.service.store import JobStore

    store = JobStore(tmp_path / "jobs.sqlite")
    job = store.create("os_cfar", {"scene": "s1"})
    first = store.claim("host-1-abc", lease_s=0.05)
    assert first["attempts"] == 1
    time.sleep(0.1)  # stalled past the lease
    second = store.claim("host-1-abc", lease_s=30)
    assert second["id"] == job["id"] and second["attempts"] == 2
    published = []
    assert not store.renew(job["id"], "host-1-abc", 30, attempt=1)
    assert not store.finish(
        job["id"], "host-1-abc", "successful", "stale", attempt=1, publish=lambda: published.append(1)
    )
    assert published == [] and store.get(job["id"])["status"] == "running"
    assert store.renew(job["id"], "host-1-abc", 30, attempt=2)
    assert store.finish(job["id"], "host-1-abc", "successful", "done", attempt=2, publish=lambda: published.append(2))
    assert published == [2] and store.get(job["id"])["message"] == "done"
    # a retry waits for its back-off; a scan request lets it run at once
    other = store.create("ingest", {"scene_id": "k" * 16, "upload": "/u/x.npy"})
    got = store.claim("o", 30)
    assert got["id"] == other["id"]
    assert store.retry_later(other["id"], "o", got["attempts"], 60, "the data folder is full; retrying in 60 s")
    row = store.get(other["id"])
    assert row["status"] == "accepted" and "full" in row["message"] and store.claim("o", 30) is None
    assert store.retry_now("ingest") == 1 and store.claim("o", 30)["attempts"] == 2
