"""AIS through the REST API against a real ``sarship serve`` (issue 33; docs/ais.md, "Service"):
an AIS CSV uploaded (``POST /ais``), listed and named by its id in a job's ``ais`` input, or named
by its path inside an allowed folder; the job's detections carry ``ais``/``dark``, its
``ais_unmatched`` result is served and its metrics document holds the run's ``ais`` record;
``/metrics`` counts the matched, dark and unmatched; refusals (outside the allowed folders,
unknown id, too many files, an oversize or non-AIS upload) are problem documents in one line.

The scene: a small simulated georeferenced scene with moving ships and their AIS reports
(``SimConfig(geo=..., moving=True, ais=True)``), written into the server's scene folder.
"""

from __future__ import annotations

import json
import shutil

import pytest

httpx = pytest.importorskip("httpx")
from svc import Server, check_problem, data_with_scene, free_port, wait_job  # noqa: E402

SCENE = dict(
    shape=(512, 512),
    ships=12,
    seed=11,
    looks=4.0,
    scr_db=18.0,
    geo=(5.5, 56.5),
    moving=True,
    ais=True,
    dark_fraction=0.25,
)
#: the upload limit of this module's server (SARSHIP_MAX_AIS_UPLOAD_MB), bytes; the CSV is ~190 kB
LIMIT = int(0.5 * 2**20)


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    from sarship.pipeline.simulate import SimConfig, simulate

    root = tmp_path_factory.mktemp("ais_svc")
    data = data_with_scene(root)
    shared = root / "shared"
    shared.mkdir()
    simulate(data / "scenes" / "sim.zarr", SimConfig(**SCENE), tile=256, ais_path=shared / "day.csv")
    srv = Server(
        data,
        free_port(),
        SARSHIP_MAX_AIS_UPLOAD_MB="0.5",
        SARSHIP_ALLOWED_ROOTS=json.dumps([str(shared)]),
    ).start()
    srv.shared = shared
    yield srv
    srv.stop()


def one_line(r, status: int, *words: str) -> None:
    check_problem(r, status, *words)
    assert "\n" not in r.json()["detail"], r.json()


def test_upload_job_results_and_metrics(server):
    u = server.url
    csv = (server.shared / "day.csv").read_bytes()
    assert len(csv) < LIMIT
    r = httpx.post(u + "/ais", params={"filename": "day.csv"}, content=csv)
    assert r.status_code == 201, r.text
    up = r.json()
    ais_id = up["aisID"]
    assert up["bytes"] == len(csv) and up["filename"] == "day.csv" and r.headers["location"].endswith(f"/ais/{ais_id}")
    # the same content again (multipart this time): the same file, 200
    r = httpx.post(u + "/ais", files={"file": ("again.csv", csv, "text/csv")})
    assert r.status_code == 200 and r.json()["aisID"] == ais_id, r.text
    assert [d["aisID"] for d in httpx.get(u + "/ais").json()["ais"]] == [ais_id]
    assert httpx.get(f"{u}/ais/{ais_id}").json()["sha256"] == up["sha256"]

    desc = httpx.get(u + "/processes/ca_cfar").json()
    assert "ais" in desc["inputs"] and "ais_unmatched" in desc["outputs"]
    spec = httpx.get(u + "/openapi.json").json()
    assert "/ais" in spec["paths"] and "/jobs/{job_id}/results/ais_unmatched" in spec["paths"]

    r = httpx.post(u + "/processes/ca_cfar/execution", json={"inputs": {"scene": "sim", "ais": [ais_id]}})
    assert r.status_code == 201, r.text
    job_id = r.json()["jobID"]
    # an accepted or running job names the file: it cannot be deleted under it
    one_line(httpx.delete(f"{u}/ais/{ais_id}"), 409, ais_id, job_id)
    st = wait_job(u, job_id)
    assert st["status"] == "successful", st
    res = httpx.get(f"{u}/jobs/{job_id}/results").json()
    assert res["ais_unmatched"]["href"].endswith(f"/jobs/{job_id}/results/ais_unmatched")

    feats = httpx.get(f"{u}/jobs/{job_id}/results/detections").json()["features"]
    assert feats and all("ais" in f["properties"] and isinstance(f["properties"]["dark"], bool) for f in feats)
    matched = [f["properties"]["ais"] for f in feats if f["properties"]["ais"] is not None]
    dark = [f for f in feats if f["properties"]["dark"]]
    assert matched and dark, (len(matched), len(dark))
    assert all(isinstance(a["mmsi"], int) and a["score"] >= 0.01 for a in matched)

    r = httpx.get(f"{u}/jobs/{job_id}/results/ais_unmatched")
    assert r.status_code == 200 and r.headers["content-type"].startswith("application/geo+json")
    unmatched = r.json()["features"]
    assert unmatched and all(f["geometry"]["type"] == "Point" and "mmsi" in f["properties"] for f in unmatched)

    rec = httpx.get(f"{u}/jobs/{job_id}/results/metrics").json()["ais"]
    assert rec["covered"] is True and rec["matched"] == len(matched) and rec["dark"] == len(dark)
    assert rec["matched"] + rec["dark"] == rec["detections"] == len(feats)
    assert rec["unmatched_in_footprint"] == len(unmatched)
    assert rec["files"] == [f"ais/{ais_id}"], rec["files"]  # named without the server's data folder

    # the same AIS by its path inside an allowed folder (the module's SARSHIP_ALLOWED_ROOTS)
    r = httpx.post(
        u + "/processes/ca_cfar/execution",
        json={"inputs": {"scene": "sim", "ais": str(server.shared / "day.csv")}},
        headers={"Prefer": "respond-sync"},
    )
    assert r.status_code == 200 and "ais_unmatched" in r.json(), r.text

    text = httpx.get(u + "/metrics").text
    lines = {ln.split(" ")[0]: float(ln.split()[-1]) for ln in text.splitlines() if ln and not ln.startswith("#")}
    assert lines["sarship_ais_jobs_total"] == 2
    assert lines["sarship_ais_matched_total"] == 2 * rec["matched"]
    assert lines["sarship_ais_dark_total"] == 2 * rec["dark"]
    assert lines["sarship_ais_unmatched_vessels_total"] == 2 * rec["unmatched_in_footprint"]
    assert lines["sarship_ais_detections_total"] == 2 * rec["detections"]

    # deleted once no accepted or running job names it; then a job naming it is refused
    assert httpx.delete(f"{u}/ais/{ais_id}").json() == {"aisID": ais_id, "status": "deleted"}
    one_line(httpx.get(f"{u}/ais/{ais_id}"), 404, ais_id)
    assert httpx.get(u + "/ais").json() == {"ais": []}
    r = httpx.post(u + "/processes/ca_cfar/execution", json={"inputs": {"scene": "sim", "ais": ais_id}})
    one_line(r, 400, "no uploaded AIS file", ais_id)


def test_refusals_are_one_line_problems(server, tmp_path):
    u = server.url

    def post(ais):
        return httpx.post(u + "/processes/ca_cfar/execution", json={"inputs": {"scene": "sim", "ais": ais}})

    outside = tmp_path / "day.csv"
    shutil.copy(server.shared / "day.csv", outside)
    one_line(post(str(outside)), 400, "input 'ais'", "outside the allowed scene folders")
    one_line(post("/etc/passwd"), 400, "outside the allowed scene folders")
    one_line(post("0123456789abcdef"), 400, "no uploaded AIS file '0123456789abcdef'")
    one_line(post(str(server.shared / "nope.csv")), 400, "no file")
    one_line(post("http://example.com/day.csv"), 400, "only local files")
    (server.shared / "folder.csv").mkdir(exist_ok=True)
    one_line(post(str(server.shared / "folder.csv")), 400, "not a regular file")
    one_line(post([str(server.shared / "day.csv")] * 1001), 400, "1001 files, more than the 1000")
    one_line(post(3), 400, "input 'ais' must be a path or a list")
    # uploads: over the limit (announced, and streamed without a length), not AIS, empty, bad name
    big = b"mmsi,time,lon,lat\n" + b"x" * (LIMIT + 2**17)
    one_line(httpx.post(u + "/ais", content=big), 413, "max_ais_upload_mb")
    one_line(httpx.post(u + "/ais", content=iter([big[i : i + 65536] for i in range(0, len(big), 65536)])), 413)
    one_line(httpx.post(u + "/ais", params={"filename": "x.csv"}, content=b"hello,world\n1,2\n"), 400, "not AIS")
    one_line(httpx.post(u + "/ais", content=b""), 400, "empty")
    one_line(httpx.post(u + "/ais", params={"filename": ".."}, content=b"mmsi,time,lon,lat\n"), 400, "file name")
    assert not [p for p in (server.data / "ais").iterdir() if p.name.startswith(".")]  # no temporary file left
    one_line(httpx.delete(u + "/ais/0123456789abcdef"), 404)
    # a job given no AIS files has no ais_unmatched
    r = httpx.post(
        u + "/processes/ca_cfar/execution", json={"inputs": {"scene": "s1"}}, headers={"Prefer": "respond-sync"}
    )
    assert r.status_code == 200 and "ais_unmatched" not in r.json(), r.text
    job_id = r.headers["location"].rsplit("/", 1)[-1]
    one_line(httpx.get(f"{u}/jobs/{job_id}/results/ais_unmatched"), 404, "no AIS files")
    assert "ais" not in httpx.get(f"{u}/jobs/{job_id}/results/metrics").json()
