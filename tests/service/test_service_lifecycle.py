"""Job and scene life cycle against a real ``sarship serve`` (issue 11): a job submitted while
its uploaded scene is still being ingested waits for the ingest (and survives ``kill -9``), a
failed ingest is listed as failed with its reason, and dismissing a finished job removes its
results (OGC API - Processes, Dismiss)."""

from __future__ import annotations

import io
import time

import pytest

httpx = pytest.importorskip("httpx")
#: a generous timeout: the first request of a detector imports (compiles) it while the long job
#: keeps the machine busy
http = httpx.Client(timeout=60.0)
from conftest import blobs_scene, write_scene  # noqa: E402
from svc import Server, check_problem, data_with_scene, free_port, shared_server, wait_job  # noqa: E402

CFAR = {"guard": 11, "background": 31, "min_area_px": 1}


def tiff_bytes(shape=(120, 110), seed=9) -> bytes:
    import tifffile

    buf = io.BytesIO()
    tifffile.imwrite(buf, blobs_scene(shape, looks=2.0, seed=seed))
    return buf.getvalue()


def wait_status(url: str, job_id: str, status: str, timeout: float = 60.0) -> dict:
    t_end = time.time() + timeout
    while time.time() < t_end:
        st = http.get(f"{url}/jobs/{job_id}").json()
        if st["status"] == status:
            return st
        time.sleep(0.1)
    raise AssertionError(f"job {job_id} never {status}: {st}")


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    return shared_server(tmp_path_factory.getbasetemp())  # its scene s1; one server per test process


def test_job_on_a_scene_still_ingesting_waits_for_it_and_survives_kill_9(tmp_path):
    """One runner thread, busy with a long job: an upload's ingest job stays accepted, so a
    job submitted for the new scene id is deterministically ahead of its ingest. It is
    accepted (not a 400), waits (also across kill -9 and a restart with two runner threads),
    runs after a successful ingest, and fails with the ingest's error after a failed one."""
    data = data_with_scene(tmp_path)
    write_scene(
        data / "scenes" / "slow.zarr", {"intensity": blobs_scene((300, 260), looks=2.0, seed=3)}, tile=32, looks=2.0
    )
    srv = Server(data, free_port(), SARSHIP_CONCURRENCY="1").start()
    try:
        u = srv.url
        slow = http.post(
            u + "/processes/lmm/execution",
            json={"inputs": {"scene": "slow", "method": "exact", "guard": 5, "background": 13}},
        ).json()["jobID"]
        wait_status(u, slow, "running")
        good = http.post(u + "/scenes?filename=good.tif", content=tiff_bytes()).json()
        bad = http.post(u + "/scenes?filename=notes.txt", content=b"not a scene at all\n" * 20).json()
        assert good["status"] == bad["status"] == "ingesting"
        ex = u + "/processes/ca_cfar/execution"
        r1 = http.post(ex, json={"inputs": {"scene": good["sceneID"], **CFAR}})
        assert r1.status_code == 201, r1.text
        j1 = r1.json()
        assert j1["status"] == "accepted", j1
        assert f"waiting for scene {good['sceneID']}" in j1["message"] and good["jobID"] in j1["message"], j1
        assert any(lk["href"].endswith(f"/jobs/{good['jobID']}") for lk in j1["links"]), j1
        r2 = http.post(ex, json={"inputs": {"scene": bad["sceneID"], **CFAR}})
        assert r2.status_code == 201, r2.text
        j2 = r2.json()
        assert j2["status"] == "accepted" and bad["jobID"] in j2["message"], j2
        # an id with no ingest accepted or running is still a 400
        check_problem(http.post(ex, json={"inputs": {"scene": "0123456789abcdef", **CFAR}}), 400, "0123456789abcdef")
        for ingest in (good, bad):  # the runner is still on the long job
            assert http.get(f"{u}/jobs/{ingest['jobID']}").json()["status"] == "accepted"
        srv.kill()  # kill -9: what the waiting jobs wait for must be in the store
        srv = Server(data, free_port(), SARSHIP_CONCURRENCY="2").start()
        u = srv.url
        assert http.get(f"{u}/jobs/{j1['jobID']}").json()["status"] in ("accepted", "running", "successful")
        http.delete(f"{u}/jobs/{slow}")
        ing = wait_job(u, good["jobID"])
        assert ing["status"] == "successful", ing
        st1 = wait_job(u, j1["jobID"])
        assert st1["status"] == "successful", st1
        assert st1["started"] >= ing["finished"] and st1["attempts"] == 1, (st1, ing)
        assert http.get(f"{u}/jobs/{j1['jobID']}/results/detections").json()["type"] == "FeatureCollection"
        bad_ing = wait_job(u, bad["jobID"])
        st2 = wait_job(u, j2["jobID"])
        assert bad_ing["status"] == "failed" and st2["status"] == "failed", (bad_ing, st2)
        assert bad_ing["message"] in st2["message"] and bad["jobID"] in st2["message"], st2
        assert "internal error" not in st2["message"], st2
        # once the ingest has failed, a new job naming that scene is a 400 that says why
        check_problem(
            http.post(u + "/processes/ca_cfar/execution", json={"inputs": {"scene": bad["sceneID"]}}),
            400,
            bad["sceneID"],
            "failed",
        )
    finally:
        srv.stop()


def test_failed_ingest_is_listed_as_failed_with_its_reason(server):
    u = server.url
    bad = http.post(u + "/scenes?filename=readme.txt", content=b"plain text, no image\n" * 10)
    assert bad.status_code == 201, bad.text
    sid, jid = bad.json()["sceneID"], bad.json()["jobID"]
    st = wait_job(u, jid)
    assert st["status"] == "failed" and "unrecognised format" in st["message"], st
    listed = {s["sceneID"]: s for s in http.get(u + "/scenes").json()["scenes"]}
    doc = listed[sid]
    assert doc["status"] == "failed" and doc["reason"] == st["message"] and doc["jobID"] == jid, doc
    assert listed["s1"]["status"] == "ready" and "reason" not in listed["s1"]
    one = http.get(f"{u}/scenes/{sid}")
    assert one.status_code == 200 and one.json() == doc, one.text
    check_problem(http.post(u + "/processes/ca_cfar/execution", json={"inputs": {"scene": sid}}), 400, sid)
    # a failed upload does not block the same name with other content, nor a new try of the same content
    again = http.post(u + "/scenes?filename=readme.txt", content=b"plain text, no image\n" * 10).json()
    assert again["sceneID"] == sid and again["status"] == "ingesting" and again["jobID"] != jid
    assert wait_job(u, again["jobID"])["status"] == "failed"
    assert http.get(f"{u}/scenes/{sid}").json()["jobID"] == again["jobID"]


def test_dismiss_a_finished_job_removes_its_results(server):
    u = server.url
    job_id = http.post(u + "/processes/ca_cfar/execution", json={"inputs": {"scene": "s1", **CFAR}}).json()["jobID"]
    assert wait_job(u, job_id)["status"] == "successful"
    out = server.data / "jobs" / job_id
    assert http.get(f"{u}/jobs/{job_id}/results/mask").status_code == 200  # a cached product too
    assert (out / "detections.geojson").is_file()
    r = http.delete(f"{u}/jobs/{job_id}")
    assert r.status_code == 200, r.text
    st = r.json()
    assert st["status"] == "dismissed" and "removed" in st["message"] and st["finished"], st
    assert not any(lk["rel"].endswith("/results") for lk in st["links"]), st
    assert not out.exists() and not list((server.data / "jobs").glob(f".dismissed-{job_id}*"))
    assert http.get(f"{u}/jobs/{job_id}").json()["status"] == "dismissed"
    for path in (
        "results",
        "results/detections",
        "results/mask",
        "results/metrics",
        "results/stac",
        "preview.png",
        "tiles.json",
    ):
        check_problem(http.get(f"{u}/jobs/{job_id}/{path}"), 404, "dismissed")
    listed = {j["jobID"]: j for j in http.get(u + "/jobs?status=dismissed").json()["jobs"]}
    assert listed[job_id]["status"] == "dismissed"
    # a second DELETE changes nothing: the same document (DELETE is idempotent)
    again = http.delete(f"{u}/jobs/{job_id}")
    assert again.status_code == 200 and again.json() == st, again.text
    check_problem(http.delete(f"{u}/jobs/nosuchjob"), 404, "nosuchjob")


def test_dismiss_a_finished_ingest_keeps_its_scene(server):
    u = server.url
    up = http.post(u + "/scenes?filename=keep.tif", content=tiff_bytes(seed=11)).json()
    assert wait_job(u, up["jobID"])["status"] == "successful"
    assert http.delete(f"{u}/jobs/{up['jobID']}").json()["status"] == "dismissed"
    assert http.get(f"{u}/scenes/{up['sceneID']}").json()["status"] == "ready"
    job = http.post(u + "/processes/ca_cfar/execution", json={"inputs": {"scene": up["sceneID"], **CFAR}}).json()
    assert wait_job(u, job["jobID"])["status"] == "successful"


def test_an_upload_never_takes_metadata_from_files_around_it(server):
    """An upload is one file: a SNAP sidecar lying in the service's folders (here one in
    DATA and one in DATA/uploads, where the reader's product-folder search would find it)
    is not its metadata."""
    from sarship.pipeline.scene import open_scene
    from tests.pipeline.test_ingest_checks import snap_xml

    (server.data / "uploads").mkdir(exist_ok=True)
    for folder in (server.data, server.data / "uploads"):
        (folder / "Metadata.xml").write_text(
            snap_xml(pols=("VV",), sample_type="DETECTED", az=13.9, rg=2.33, az_looks=4, rg_looks=1)
        )
    try:
        up = http.post(server.url + "/scenes?filename=chip.tif", content=tiff_bytes(seed=21)).json()
        assert wait_job(server.url, up["jobID"])["status"] == "successful"
        attrs = open_scene(server.data / "scenes" / f"{up['sceneID']}.zarr").attrs
        assert "pixel_spacing_m" not in attrs and "metadata_sidecar" not in attrs, attrs
        assert "sensor" not in attrs and attrs.get("channels") != ["vv"], attrs
    finally:
        for folder in (server.data, server.data / "uploads"):
            (folder / "Metadata.xml").unlink()
