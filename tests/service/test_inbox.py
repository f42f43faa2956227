"""Scheduled ingest of satellite passes (the inbox loop): its pure parts (which files are
passes, the settle rule, streamed hashing, quarantine moves, settings validation), then
against real ``sarship serve`` processes (uvicorn, a local Dask cluster, the SQLite store):
a pass ingested once with its detector job, duplicates, files still being written, ``.done``
markers, quarantine, ``/ingest`` and ``/metrics``, two API processes on one store, and a
``kill -9`` followed by a restart."""

from __future__ import annotations

import hashlib
import io
import json
import os
import subprocess
import sys
import time

import numpy as np
import pytest

httpx = pytest.importorskip("httpx")
from conftest import blobs_scene  # noqa: E402
from svc import Server, check_problem, free_port, passes, tif_bytes, wait_job, wait_pass  # noqa: E402

from sarship.service.inbox import Schedule  # noqa: E402
from sarship.service.inbox_files import (  # noqa: E402
    Signature,
    list_passes,
    marker,
    move_into,
    quarantine_target,
    scene_key,
    settled,
    sha256_of,
    signature,
    write_reason,
)

DETECTOR = [{"detector": "os_cfar", "guard": 11, "background": 31}]


def jobs_by_process(url: str) -> dict[str, list[str]]:
    out: dict[str, list[str]] = {}
    for j in httpx.get(url + "/jobs").json()["jobs"]:
        out.setdefault(j["processID"], []).append(j["jobID"])
    return out


# ----------------------------------------------------------------------------- pure parts


def test_settle_rule():
    assert not settled(100.0, 100.5, 1.0, False)  # changed half a second ago: still being written
    assert settled(100.0, 101.0, 1.0, False)
    assert settled(100.0, 100.0, 60.0, True)  # FILE.done: at once
    assert settled(100.0, 100.0, 0.0, False)


def test_hash_is_streamed_and_is_the_upload_scheme(tmp_path):
    data = os.urandom(1000)
    f = tmp_path / "a.tif"
    f.write_bytes(data)
    calls = []
    sha = sha256_of(f, on_chunk=lambda: calls.append(1), chunk=64)
    assert sha == hashlib.sha256(data).hexdigest() and len(calls) == -(-1000 // 64)
    assert scene_key(sha) == hashlib.sha256(data).hexdigest()[:16]  # POST /scenes names scenes so

    def abort():
        raise RuntimeError("lease lost")

    with pytest.raises(RuntimeError, match="lease"):
        sha256_of(f, on_chunk=abort, chunk=64)
    z = tmp_path / "s.zarr"
    (z / "intensity" / "c").mkdir(parents=True)
    (z / "zarr.json").write_text("{}")
    (z / "intensity" / "c" / "0").write_bytes(b"abc")
    h1 = sha256_of(z)
    assert sha256_of(z) == h1 and signature(z).files == 2
    (z / "intensity" / "c" / "0").write_bytes(b"abd")
    h2 = sha256_of(z)
    assert h2 != h1
    (z / "intensity" / "c" / "0").rename(z / "intensity" / "c" / "1")  # same bytes, another chunk
    assert sha256_of(z) != h2


def test_which_files_are_passes(tmp_path):
    for name in [
        "a.tif",
        "B.TIFF",
        "c.npy",
        "d.png",
        "e.jpeg",
        "f.jpg",
        ".hidden.tif",
        "g.tif.part",
        "h.tif~",
        "a.tif.done",
        "notes.txt",
        "x.tif.reason.txt",
        "~lock.tif",
        "k.tmp",
    ]:
        (tmp_path / name).write_bytes(b"x")
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "i.tif").write_bytes(b"x")
    (tmp_path / ".cache").mkdir()
    (tmp_path / ".cache" / "j.tif").write_bytes(b"x")
    (tmp_path / "scene.zarr" / "v").mkdir(parents=True)
    (tmp_path / "scene.zarr" / "zarr.json").write_text("{}")
    (tmp_path / "scene.zarr" / "v" / "k.tif").write_bytes(b"x")  # inside a Zarr folder: part of it
    (tmp_path / "quarantine").mkdir()
    (tmp_path / "quarantine" / "bad.tif").write_bytes(b"x")
    found = {p.relative_to(tmp_path).as_posix() for p in list_passes(tmp_path, skip=(tmp_path / "quarantine",))}
    assert found == {"a.tif", "B.TIFF", "c.npy", "d.png", "e.jpeg", "f.jpg", "sub/i.tif", "scene.zarr"}
    assert marker(tmp_path / "a.tif").name == "a.tif.done"


def test_signature_and_quarantine_moves(tmp_path):
    f = tmp_path / "in" / "bad.tif"
    f.parent.mkdir()
    f.write_bytes(b"12345")
    s1 = signature(f)
    assert s1.size == 5 and s1.files == 1 and isinstance(s1, Signature)
    with open(f, "ab") as fh:
        fh.write(b"6")
    assert signature(f) != s1 and signature(tmp_path / "gone.tif") is None
    q = tmp_path / "q"
    dest = quarantine_target(q, f, "0123456789abcdef")
    assert dest == q / "bad.tif"
    move_into(f, dest)
    assert not f.exists() and dest.read_bytes() == b"123456"
    note = write_reason(dest, {"reason": "unrecognised\nformat", "file": str(f)})
    assert note.name == "bad.tif.reason.txt" and note.read_text().startswith("reason: unrecognised format\n")
    f.write_bytes(b"other")  # another file of the same name: not over the first one
    dest2 = quarantine_target(q, f, "0123456789abcdef")
    assert dest2.name == "bad-0123456789abcdef.tif"
    with pytest.raises(FileExistsError):
        move_into(f, dest)
    assert not [p for p in q.iterdir() if p.name.startswith(".")]  # nothing half-written left


def test_inbox_settings_are_validated(tmp_path, monkeypatch):
    from pydantic import ValidationError

    from sarship.service.settings import Settings

    for k in list(os.environ):
        if k.startswith("SARSHIP_"):
            monkeypatch.delenv(k)
    inbox = tmp_path / "in"
    inbox.mkdir()

    def error(**kw) -> str:
        with pytest.raises(ValidationError) as ei:
            Settings(**kw)
        e = ei.value.errors()[0]
        return f"{e['loc'][0]}: {e['msg']}"

    assert Settings().inbox == [] and Settings().inbox_schedule == {"interval_s": 30.0, "cron": None}
    s = Settings(inbox=f"{inbox},{inbox}", inbox_detectors="os_cfar, ca_cfar", inbox_cron="*/10 * * * *")
    assert s.inbox == [inbox.resolve()] and [d["detector"] for d in s.inbox_detectors] == ["os_cfar", "ca_cfar"]
    assert s.inbox_schedule == {"interval_s": None, "cron": "*/10 * * * *"}
    assert s.quarantine_dir == s.data / "quarantine"
    monkeypatch.setenv("SARSHIP_INBOX", json.dumps([str(inbox)]))
    monkeypatch.setenv("SARSHIP_INBOX_DETECTORS", json.dumps([{"detector": "os_cfar", "pfa": 1e-6, "device": "cpu"}]))
    s = Settings()
    assert s.inbox == [inbox.resolve()] and s.inbox_detectors == [{"detector": "os_cfar", "pfa": 1e-6, "device": "cpu"}]
    monkeypatch.delenv("SARSHIP_INBOX_DETECTORS")
    assert "inbox_cron" in error(inbox_cron="61 * * * *") and "cron" in error(inbox_cron="every day")
    assert "not both" in error(inbox_interval_s=10, inbox_cron="* * * * *")
    assert "unknown detector 'nope'" in error(inbox_detectors="os_cfar,nope")
    msg = error(inbox_detectors=json.dumps([{"detector": "os_cfar", "pfa": 2}]))
    assert msg.startswith("inbox_detectors: entry 0 (os_cfar): parameter 'pfa'"), msg
    assert "unknown parameter 'bogus'" in error(inbox_detectors=json.dumps([{"detector": "ca_cfar", "bogus": 1}]))
    assert "guard must be odd" in error(inbox_detectors=json.dumps([{"detector": "ca_cfar", "guard": 10}]))
    assert "'scene'" in error(inbox_detectors=json.dumps([{"detector": "ca_cfar", "scene": "x"}]))
    assert "'device'" in error(inbox_detectors=json.dumps([{"detector": "ca_cfar", "device": "tpu"}]))
    assert "'detector'" in error(inbox_detectors=json.dumps([{"pfa": 1e-3}]))
    assert "JSON" in error(inbox_detectors="[{oops")
    assert "does not exist" in error(inbox=str(tmp_path / "missing"))
    assert "inbox_settle_s" in error(inbox_settle_s=-1)


def test_schedule():
    t = 1_700_000_000.0  # 2023-11-14T22:13:20Z
    assert Schedule(interval_s=12.5).next_after(t) == t + 12.5
    assert Schedule(cron="*/10 * * * *").next_after(t) == 1_700_000_400.0  # 22:20:00 UTC
    assert Schedule(cron="0 3 * * *").next_after(t) == 1_700_017_200.0  # 03:00 UTC the next day


def test_serve_exits_2_on_bad_inbox_settings(tmp_path, monkeypatch, capsys):
    """``sarship serve`` with a bad inbox setting: exit status 2, one line naming the setting.
    The first case runs the command as a process; the others call its ``main`` in this process
    (the same code from the settings on; a process start-up costs seconds on the CI machine)."""
    from sarship.cli import main

    inbox = tmp_path / "in"
    inbox.mkdir()
    cases = {
        "cron": ({"SARSHIP_INBOX_CRON": "61 * * * *"}, "inbox_cron"),
        "detector": ({"SARSHIP_INBOX_DETECTORS": "os_cfar,nope"}, "nope"),
        "parameter": ({"SARSHIP_INBOX_DETECTORS": '[{"detector": "os_cfar", "pfa": 2}]'}, "'pfa'"),
    }
    env = {k: v for k, v in os.environ.items() if not k.startswith("SARSHIP_")}
    args = ["serve", "--data", str(tmp_path / "d"), "--port", str(free_port()), "--inbox", str(inbox)]
    for k in list(os.environ):
        if k.startswith("SARSHIP_"):
            monkeypatch.delenv(k)
    for k, (name, (extra, word)) in enumerate(cases.items()):
        if k == 0:
            p = subprocess.run(
                [sys.executable, "-m", "sarship", *args],
                env={**env, **extra},
                capture_output=True,
                text=True,
                timeout=60,
            )
            rc, err = p.returncode, p.stderr
        else:
            with monkeypatch.context() as m:
                for key, value in extra.items():
                    m.setenv(key, value)
                rc = main(args)
            err = capsys.readouterr().err
        lines = err.strip().splitlines()
        assert rc == 2 and len(lines) == 1, (name, rc, err)
        assert lines[0].startswith("sarship serve: error: setting 'inbox_") and word in lines[0], lines
    assert not (tmp_path / "d").exists()  # refused before anything was created


def test_pass_records_change_once(tmp_path):
    """The store's transitions are compare-and-set: taking a pass, marking it and submitting
    its jobs happen once however often (or by however many loops) they are attempted."""
    from sarship.service.inbox_store import InboxStore
    from sarship.service.store import JobStore

    jobs = JobStore(tmp_path / "jobs.sqlite")
    db = InboxStore(jobs)
    assert db.lead("a", 5.0) and not db.lead("b", 5.0) and db.lead("a", 5.0)
    assert db.lead("b", 5.0, now=time.time() + 6)  # a's lease expired: b takes over
    db.release("b")
    assert db.state()["owner"] is None and db.lead("a", 5.0)
    sig = Signature(10, 123, 1)
    db.add_waiting("/in/a.tif", sig, 1.0)
    db.add_waiting("/in/a.tif", sig, 2.0)  # seen again while waiting: still one record
    db.add_waiting("/in/b.tif", sig, 1.0)
    a, b = db.rows("waiting")
    plan = [{"detector": "os_cfar", "guard": 11}]
    inputs = {"path": "/in/a.tif", "scene_id": "k" * 16}
    assert db.take(a["id"], Signature(11, 123, 1), "s" * 64, "k" * 16, False, plan, inputs) is None  # changed since
    assert db.take(a["id"], sig, "s" * 64, "k" * 16, False, plan, inputs) == "ingesting"
    assert db.take(a["id"], sig, "s" * 64, "k" * 16, False, plan, inputs) is None  # taken already
    assert db.take(b["id"], sig, "s" * 64, "k" * 16, False, plan, {**inputs, "path": "/in/b.tif"}) == "duplicate"
    assert [j["process"] for j in jobs.list()] == ["ingest"]
    assert db.mark(a["id"], "ingesting", "ingested") and not db.mark(a["id"], "ingesting", "ingested")
    ids = db.submit(a["id"], lambda e: (e["detector"], {"scene": "k" * 16, "guard": e["guard"]}))
    assert len(ids) == 1 and db.submit(a["id"], lambda e: (e["detector"], {})) == []
    assert sorted(j["process"] for j in jobs.list()) == ["ingest", "os_cfar"]
    assert jobs.get(ids[0])["inputs"] == {"scene": "k" * 16, "guard": 11}
    row = db.list()[-1]
    assert row["status"] == "submitted" and json.loads(row["jobs"]) == ids
    assert db.counts()["submitted"] == 1 and db.counts()["duplicate"] == 1 and db.backlog() == 0


def test_scene_lookups_use_the_ingest_indexes(tmp_path):
    """GET /scenes and GET /scenes/{id} find ingest jobs through indexes, not by reading the
    job table (which holds every detection job too)."""
    from sarship.service.store import JobStore

    jobs = JobStore(tmp_path / "jobs.sqlite")
    for _k in range(50):
        jobs.create("os_cfar", {"scene": "s1"})
    first, new = jobs.create_ingest({"scene_id": "abc", "upload": "/u/abc.tif"})
    again, new2 = jobs.create_ingest({"scene_id": "abc", "upload": "/u/abc.tif"})
    assert new and not new2 and again["id"] == first["id"]  # one ingest of a scene at a time
    assert jobs.ingest_job_for_scene("abc")["id"] == first["id"] and jobs.ingest_job_for_scene("x") is None
    assert [j["id"] for j in jobs.ingest_jobs(("accepted",))] == [first["id"]]
    c = jobs._conn()
    plan = " ".join(
        str(tuple(r))
        for r in c.execute(
            "EXPLAIN QUERY PLAN SELECT * FROM jobs WHERE process = 'ingest' AND json_extract(inputs, '$.scene_id') = ? "
            "ORDER BY created DESC LIMIT 1",
            ("abc",),
        )
    )
    assert "jobs_ingest_scene" in plan, plan
    plan = " ".join(
        str(tuple(r))
        for r in c.execute(
            "EXPLAIN QUERY PLAN SELECT * FROM jobs WHERE process = 'ingest' AND status IN (?, ?) ORDER BY created DESC",
            ("accepted", "failed"),
        )
    )
    assert "jobs_ingest_status" in plan, plan


AIS_CSV = "mmsi,time,lon,lat,sog,cog\n219000001,2024-05-01T10:00:00Z,10.5,55.5,12.0,90\n"


def _ais_folder(root):
    """An AIS folder: three CSVs of known ages and sizes, a gzip, and files that are not AIS."""
    import gzip

    d = root / "ais"
    (d / "sub").mkdir(parents=True)
    for name, age in (("old.csv", 300), ("mid.csv", 200), ("sub/new.csv", 100)):
        (d / name).write_text(AIS_CSV)
        os.utime(d / name, (time.time() - age, time.time() - age))
    (d / "day.csv.gz").write_bytes(gzip.compress(AIS_CSV.encode()))
    os.utime(d / "day.csv.gz", (time.time() - 400, time.time() - 400))
    (d / "README.txt").write_text("AIS files of the harbour feed\n")  # not AIS: left out
    (d / ".hidden.csv").write_text(AIS_CSV)
    (d / "next.csv.part").write_text(AIS_CSV)  # being downloaded
    (d / "mid.csv.done").write_text("")
    return d


def test_ais_folder_files_newest_first_within_the_bounds(tmp_path):
    from sarship.service.inbox_files import ais_files

    d = _ais_folder(tmp_path)
    names = lambda c: [os.path.relpath(p, d.resolve()) for p in c.paths]  # noqa: E731
    every = ais_files(d, 100, 1 << 30)
    assert names(every) == ["sub/new.csv", "mid.csv", "old.csv", "day.csv.gz"], every
    assert all(os.path.isabs(p) for p in every.paths)
    assert every.left_out == ("1 file(s) of the AIS folder that are not AIS left out",)
    two = ais_files(d, 2, 1 << 30)
    assert (
        names(two) == ["sub/new.csv", "mid.csv"]
        and "2 older AIS file(s) beyond inbox_ais_max_files (2)" in (two.left_out[0])
    )
    size = len(AIS_CSV)
    small = ais_files(d, 100, 2 * size)  # two CSVs fit; the gzip (smaller) after them does not
    assert names(small)[:2] == ["sub/new.csv", "mid.csv"] and any("inbox_ais_max_mb" in n for n in small.left_out)
    assert ais_files(tmp_path / "empty-or-missing", 10, 1 << 20) == ((), ())


def test_inbox_ais_setting_is_checked(tmp_path, monkeypatch):
    from pydantic import ValidationError

    from sarship.service.settings import Settings

    for k in list(os.environ):
        if k.startswith("SARSHIP_"):
            monkeypatch.delenv(k)
    inbox, ais = tmp_path / "in", tmp_path / "ais"
    (inbox / "ais").mkdir(parents=True)
    ais.mkdir()
    s = Settings(inbox=str(inbox), inbox_ais=str(ais))
    assert s.inbox_ais == ais.resolve() and Settings().inbox_ais is None
    assert s.inbox_ais_max_files == 100 and s.inbox_ais_max_mb == 16384
    for bad, word in (
        (tmp_path / "missing", "does not exist"),
        (inbox / "ais", "overlaps the inbox folder"),
        (inbox, "overlaps the inbox folder"),
        (tmp_path, "overlaps the inbox folder"),
    ):
        with pytest.raises(ValidationError) as ei:
            Settings(inbox=str(inbox), inbox_ais=str(bad))
        e = ei.value.errors()[0]
        assert e["loc"][0] == "inbox_ais" and word in e["msg"], e
    with pytest.raises(ValidationError, match="inbox_ais_max_files"):
        Settings(inbox_ais_max_files=0)


def test_serve_exits_2_on_a_missing_ais_folder(tmp_path, monkeypatch, capsys):
    from sarship.cli import main

    inbox = tmp_path / "in"
    inbox.mkdir()
    for k in list(os.environ):
        if k.startswith("SARSHIP_"):
            monkeypatch.delenv(k)
    args = ["serve", "--data", str(tmp_path / "d"), "--port", str(free_port()), "--inbox", str(inbox)]
    rc = main([*args, "--inbox-ais", str(tmp_path / "nope")])
    lines = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(lines) == 1 and lines[0].startswith("sarship serve: error: setting 'inbox_ais'"), lines
    assert "nope" in lines[0] and not (tmp_path / "d").exists()
    monkeypatch.setenv("SARSHIP_INBOX_AIS", str(inbox))  # the environment variable, checked the same
    rc = main(args)
    lines = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(lines) == 1 and "setting 'inbox_ais'" in lines[0] and "overlaps" in lines[0], lines


def test_a_pass_s_jobs_get_the_ais_folder_or_say_why_not(tmp_path, monkeypatch):
    """Without a server: passes whose scenes are in the store are submitted by
    :meth:`Inbox.advance`; a georeferenced scene with a time gets the AIS folder's files as its
    jobs' ``ais`` (which the runner's request carries), one without a time or georeference
    gets none, and its jobs and pass say why."""
    from sarship.pipeline.scene import create_scene
    from sarship.service.inbox import Inbox
    from sarship.service.settings import Settings
    from sarship.service.store import JobStore
    from sarship.workers.request import JobRequest

    for k in list(os.environ):
        if k.startswith("SARSHIP_"):
            monkeypatch.delenv(k)
    inbox, data = tmp_path / "in", tmp_path / "data"
    inbox.mkdir()
    ais = _ais_folder(tmp_path)
    settings = Settings(data=data, inbox=str(inbox), inbox_ais=str(ais), inbox_detectors=json.dumps(DETECTOR))
    geo = {"crs": "EPSG:4326", "transform": [0.001, 0, 10.0, 0, -0.001, 56.0]}
    scenes = {
        "a" * 16: {**geo, "acquired": "2024-05-01T10:00:00Z"},
        "b" * 16: geo,  # no time
        "c" * 16: {"acquired": "2024-05-01T10:00:00Z"},  # no georeference
    }
    for key, attrs in scenes.items():
        create_scene(settings.scenes_dir / f"{key}.zarr", (8, 8), {"intensity": "float32"}, attrs=attrs)
    jobs = JobStore(settings.db_path)
    box = Inbox(settings, jobs, "me")
    for n, key in enumerate(scenes):
        box.db.add_waiting(f"/in/{n}.tif", Signature(1, n, 1), 1.0)
        row = box.db.rows("waiting")[-1]
        assert (
            box.db.take(row["id"], Signature(1, n, 1), key * 4, key, True, settings.inbox_detectors, {}) == "ingested"
        )
    box.advance()
    by_scene = {j["inputs"]["scene"]: j for j in jobs.list() if j["process"] == "os_cfar"}
    a, b, c = (by_scene[k] for k in scenes)
    want = [str((ais / p).resolve()) for p in ("sub/new.csv", "mid.csv", "old.csv", "day.csv.gz")]
    assert a["inputs"]["ais"] == want and a["inputs"]["guard"] == 11
    assert "not AIS left out" in a["message"]
    req = JobRequest.from_stored("os_cfar", a["inputs"])
    assert req.ais == tuple(want) and "ais" not in req.params
    JobRequest.from_inputs("os_cfar", a["inputs"])  # what the inbox stores is a valid request
    from sarship.service.ais_files import ais_paths

    assert ais_paths(settings, req.ais) == tuple(want)  # the runner's check of the paths accepts them
    assert "ais" not in b["inputs"] and "no AIS matching: the scene states no acquisition time" in b["message"]
    assert "ais" not in c["inputs"] and "no AIS matching: the scene is not georeferenced" in c["message"]
    reasons = {p["scene_id"]: p["reason"] for p in box.db.list()}
    assert reasons["b" * 16].startswith("scene already in the store; no AIS matching: the scene states no")
    monkeypatch.setattr(settings, "inbox_ais", None)
    assert box.ais_for("a" * 16) == ((), "")  # no AIS folder: the jobs as before


# ----------------------------------------------------------------------------- one server


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    root = tmp_path_factory.mktemp("inbox")
    data, inbox = root / "data", root / "inbox"
    data.mkdir()
    inbox.mkdir()
    srv = Server(
        data,
        free_port(),
        SARSHIP_INBOX=json.dumps([str(inbox)]),
        SARSHIP_INBOX_INTERVAL_S="0.2",
        SARSHIP_INBOX_SETTLE_S="2",
        SARSHIP_INBOX_DETECTORS=json.dumps(DETECTOR),
    ).start()
    srv.inbox = inbox
    yield srv
    srv.stop()


def test_a_pass_is_ingested_once_and_its_detector_runs(server):
    u = server.url
    raw = tif_bytes(seed=11)
    (server.inbox / "pass1.tif").write_bytes(raw)
    p = wait_pass(u, "pass1.tif", ("submitted", "quarantined", "failed"))
    key = hashlib.sha256(raw).hexdigest()[:16]
    assert p["status"] == "submitted" and p["key"] == key and p["sceneID"] == key and len(p["jobs"]) == 1, p
    assert httpx.get(f"{u}/jobs/{p['ingestJob']}").json()["processID"] == "ingest"
    st = wait_job(u, p["jobs"][0])
    assert st["status"] == "successful" and st["processID"] == "os_cfar", st
    assert httpx.get(f"{u}/jobs/{p['jobs'][0]}/results/detections").json()["type"] == "FeatureCollection"
    sc = httpx.get(f"{u}/scenes/{key}").json()
    assert sc["status"] == "ready" and sc["shape"] == [300, 260]
    before = jobs_by_process(u)
    # the same content under another name: recorded as a duplicate, not ingested or submitted again
    (server.inbox / "pass1-again.tif").write_bytes(raw)
    dup = wait_pass(u, "pass1-again.tif", ("duplicate", "submitted", "ingesting", "ingested"))
    assert dup["status"] == "duplicate" and dup["sceneID"] == key and dup["jobs"] == [], dup
    assert "pass1.tif" in dup["reason"]
    # the upload of that content is the same scene, already there
    up = httpx.post(u + "/scenes?filename=up.tif", content=raw)
    assert up.status_code == 200 and up.json()["sceneID"] == key and up.json()["status"] == "ready"
    more_scans(u, 3)
    assert jobs_by_process(u) == before
    assert passes(u)["pass1.tif"]["jobs"] == p["jobs"]


def test_a_pass_reads_its_sidecar_from_the_inbox_but_never_from_above_it(server):
    """The SNAP sidecar search of an inbox pass stops at the inbox folder: a ``Metadata.xml``
    in the folder above the inbox belongs to somebody else; one beside the pass is its own."""
    from sarship.pipeline.scene import open_scene
    from tests.pipeline.test_ingest_checks import snap_xml

    u = server.url
    above = server.inbox.parent / "Metadata.xml"
    above.write_text(snap_xml(pols=("VV",), sample_type="DETECTED", az=13.9, rg=2.33))
    try:
        (server.inbox / "far.tif").write_bytes(tif_bytes(seed=41))
        marker(server.inbox / "far.tif").touch()  # complete: taken at once (the settle rule: the tests below)
        p = wait_pass(u, "far.tif", ("submitted", "quarantined", "failed"))
        assert wait_job(u, p["ingestJob"])["status"] == "successful", p
        attrs = open_scene(server.data / "scenes" / f"{p['sceneID']}.zarr").attrs
        assert "pixel_spacing_m" not in attrs and "metadata_sidecar" not in attrs, attrs
        (server.inbox / "near.xml").write_text(snap_xml(pols=("VV",), sample_type="DETECTED", az=9.5, rg=8.5))
        (server.inbox / "near.tif").write_bytes(tif_bytes(seed=42))
        marker(server.inbox / "near.tif").touch()
        p = wait_pass(u, "near.tif", ("submitted", "quarantined", "failed"))
        assert wait_job(u, p["ingestJob"])["status"] == "successful", p
        attrs = open_scene(server.data / "scenes" / f"{p['sceneID']}.zarr").attrs
        assert attrs["pixel_spacing_m"] == [9.5, 8.5] and attrs["metadata_sidecar"] == "near.xml", attrs
    finally:
        above.unlink()


@pytest.mark.slow  # 4 s of appends; test_faults.py::test_a_done_marker_is_consumed_with_its_pass (a file still being written, no fresh marker) and test_settle_rule keep the rule in the default run
def test_a_file_still_being_written_is_not_taken(server):
    u = server.url
    raw = tif_bytes(seed=12)
    f = server.inbox / "growing.tif"
    half = len(raw) // 2
    f.write_bytes(raw[:half])
    pieces = np.linspace(half, len(raw), 19).astype(int)
    for a, b in zip(pieces[:-2], pieces[1:-1]):  # 17 appends, 0.25 s apart: 4.25 s in all, longer than the
        # 2 s settle time; each gap (0.25 s and a status request) well under it, also on a loaded CI machine
        time.sleep(0.25)
        assert passes(u).get("growing.tif", {"status": "waiting"})["status"] == "waiting"
        with open(f, "ab") as fh:
            fh.write(raw[a:b])
    assert passes(u)["growing.tif"]["status"] == "waiting"
    with open(f, "ab") as fh:
        fh.write(raw[pieces[-2] :])
    p = wait_pass(u, "growing.tif", ("submitted", "quarantined", "failed"))
    assert p["status"] == "submitted" and p["key"] == hashlib.sha256(raw).hexdigest()[:16], p
    assert wait_job(u, p["jobs"][0])["status"] == "successful"


def test_bad_files_are_quarantined_and_the_loop_goes_on(server):
    u = server.url
    good = blobs_scene((200, 150), looks=2.0, seed=13)
    (server.inbox / "junk.tif").write_bytes(b"this is not a TIFF at all " * 40)
    (server.inbox / "cut.tif").write_bytes(tif_bytes(seed=14)[:50_000])  # truncated
    buf = io.BytesIO()
    np.save(buf, good)
    (server.inbox / "after.npy").write_bytes(buf.getvalue())
    for name in ("junk.tif", "cut.tif", "after.npy"):  # complete: taken at once (the settle rule: the tests above)
        marker(server.inbox / name).touch()
    q = server.data / "quarantine"
    for name in ("junk.tif", "cut.tif"):
        p = wait_pass(u, name, ("quarantined", "failed", "submitted"))
        assert p["status"] == "quarantined" and p["reason"] and name in p["reason"], p
        assert not (server.inbox / name).exists() and (q / name).is_file()
        note = (q / f"{name}.reason.txt").read_text()
        sha = hashlib.sha256((q / name).read_bytes()).hexdigest()
        assert f"reason: {p['reason']}" in note and f"sha256: {sha}" in note
    assert (q / "junk.tif").read_bytes().startswith(b"this is not a TIFF")
    p = wait_pass(u, "after.npy", ("submitted", "quarantined", "failed"))
    assert p["status"] == "submitted", p
    assert wait_job(u, p["jobs"][0])["status"] == "successful"


def test_a_zarr_scene_folder_is_one_pass(server, tmp_path):
    from conftest import write_scene

    from sarship.pipeline.scene import open_scene

    z = write_scene(
        tmp_path / "pass.zarr", {"intensity": blobs_scene((180, 170), looks=2.0, seed=15)}, tile=64, looks=2.0
    )
    key = scene_key(sha256_of(z))
    z.rename(server.inbox / "pass.zarr")  # complete when it arrives; the marker says so at once
    marker(server.inbox / "pass.zarr").touch()
    p = wait_pass(server.url, "pass.zarr", ("submitted", "quarantined", "failed"))
    assert p["status"] == "submitted" and p["key"] == key, p
    assert wait_job(server.url, p["jobs"][0])["status"] == "successful"
    assert open_scene(server.data / "scenes" / f"{key}.zarr").shape == (180, 170)


def test_ingest_document_scan_request_and_metrics(server):
    u = server.url
    doc = httpx.get(u + "/ingest").json()
    assert set(doc) == {
        "enabled",
        "inboxes",
        "schedule",
        "leader",
        "last_scan",
        "next_scan",
        "backlog",
        "counts",
        "passes",
    }
    assert doc["enabled"] and doc["inboxes"] == [str(server.inbox.resolve())]
    assert doc["schedule"] == {"interval_s": 0.2, "cron": None} and doc["leader"] and doc["backlog"] == 0
    assert doc["counts"]["submitted"] >= 4 and doc["counts"]["quarantined"] >= 2 and doc["counts"]["duplicate"] >= 1
    assert set(doc["passes"][0]) >= {"key", "file", "status", "sceneID", "jobs", "reason", "seen", "updated"}
    seen = [p["seen"] for p in doc["passes"]]
    assert seen == sorted(seen, reverse=True)  # newest first
    assert len(httpx.get(u + "/ingest?limit=1").json()["passes"]) == 1
    check_problem(httpx.get(u + "/ingest?limit=0"), 400, "limit")
    check_problem(httpx.get(u + "/ingest?limit=many"), 400, "limit")
    last = doc["last_scan"]
    r = httpx.post(u + "/ingest/scan")
    assert r.status_code == 202, r.text
    t_end = time.time() + 10
    while httpx.get(u + "/ingest").json()["last_scan"] == last and time.time() < t_end:
        time.sleep(0.1)
    assert httpx.get(u + "/ingest").json()["last_scan"] > last
    text = httpx.get(u + "/metrics").text
    lines = {ln.split(" ")[0]: float(ln.split()[-1]) for ln in text.splitlines() if ln and not ln.startswith("#")}
    assert lines["sarship_ingest_backlog"] == 0
    assert lines['sarship_inbox_passes{status="submitted"}'] >= 3
    assert lines['sarship_inbox_passes{status="duplicate"}'] >= 1
    assert lines["sarship_inbox_quarantined_total"] >= 2
    assert lines["sarship_inbox_last_scan_timestamp_seconds"] > time.time() - 60


# ----------------------------------------------------------------------------- several processes


def more_scans(url: str, n: int, timeout: float = 60.0) -> None:
    """Wait until the inbox loop has finished ``n`` more scans (``last_scan`` of ``/ingest``)."""
    seen = [httpx.get(url + "/ingest").json()["last_scan"]]
    t_end = time.time() + timeout
    while len(seen) <= n:
        assert time.time() < t_end, f"fewer than {n} scans: {seen}"
        time.sleep(0.05)
        last = httpx.get(url + "/ingest").json()["last_scan"]
        if last != seen[-1]:
            seen.append(last)


def _pid(owner: str) -> int:
    return int(owner.split("-")[-2])  # host-PID-random (service.runner.Runner.owner)


@pytest.mark.slow  # kill -9 and restart of two servers; test_service.py::test_jobs_survive_kill_9 keeps one in the default run
def test_two_processes_one_store_kill_9_and_restart(tmp_path):
    """Two API processes on one store with the same inbox: one loop leads; passes marked done
    are taken at once (the settle time is 60 s here), each ingested and submitted once; the
    leader is killed with SIGKILL mid-way and the other takes over; then the survivor is
    killed too and a fresh process on the same data takes nothing again."""
    data, inbox = tmp_path / "data", tmp_path / "inbox"
    data.mkdir()
    inbox.mkdir()
    env = dict(
        SARSHIP_WORKERS="1",
        SARSHIP_INBOX=json.dumps([str(inbox)]),
        SARSHIP_INBOX_INTERVAL_S="0.5",
        SARSHIP_INBOX_SETTLE_S="60",
        SARSHIP_INBOX_DETECTORS=json.dumps(DETECTOR),
    )
    servers = [Server(data, free_port(), **env), Server(data, free_port(), **env)]
    try:
        from concurrent.futures import ThreadPoolExecutor

        with ThreadPoolExecutor(2) as pool:  # start both at once
            list(pool.map(Server.start, servers))
        raws = {f"m{k}.tif": tif_bytes(seed=20 + k, shape=(160, 140)) for k in range(3)}
        for name, raw in raws.items():
            (inbox / name).write_bytes(raw)
            marker(inbox / name).touch()
        (inbox / "z-m0-copy.tif").write_bytes(raws["m0.tif"])
        marker(inbox / "z-m0-copy.tif").touch()
        (inbox / "slow.tif").write_bytes(tif_bytes(seed=30, shape=(100, 90)))  # no marker: waits 60 s
        u = servers[0].url
        t_end = time.time() + 60
        while not any(p["status"] != "waiting" for p in passes(u).values()) and time.time() < t_end:
            time.sleep(0.05)
        leader = httpx.get(u + "/ingest").json()["leader"]
        lead = next(s for s in servers if s.proc.pid == _pid(leader))
        other = next(s for s in servers if s is not lead)
        lead.kill()  # SIGKILL, mid-way
        u = other.url
        done = {n: wait_pass(u, n, ("submitted", "quarantined", "failed"), timeout=90) for n in raws}
        assert all(p["status"] == "submitted" and len(p["jobs"]) == 1 for p in done.values()), done
        for p in done.values():
            assert wait_job(u, p["jobs"][0])["status"] == "successful"
        assert wait_pass(u, "z-m0-copy.tif", ("duplicate",))["sceneID"] == done["m0.tif"]["sceneID"]
        doc = httpx.get(u + "/ingest").json()
        assert _pid(doc["leader"]) == other.proc.pid
        assert passes(u)["slow.tif"]["status"] == "waiting" and doc["backlog"] == 1
        text = httpx.get(u + "/metrics").text
        assert "sarship_ingest_backlog 1.0" in text and 'sarship_inbox_passes{status="waiting"} 1.0' in text
        jobs = jobs_by_process(u)
        assert len(jobs["ingest"]) == 3 and len(jobs["os_cfar"]) == 3, jobs  # each pass once
        assert sorted(jobs["os_cfar"]) == sorted(p["jobs"][0] for p in done.values())
        other.kill()
        # a fresh process on the same data: it leads once the old lease expires, scans, takes nothing again
        fresh = Server(data, free_port(), **env).start()
        servers.append(fresh)
        started = time.time()
        t_end = time.time() + 60
        while time.time() < t_end:
            doc = httpx.get(fresh.url + "/ingest").json()
            if (
                doc["leader"]
                and _pid(doc["leader"]) == fresh.proc.pid
                and doc["last_scan"]
                and doc["last_scan"] > _iso(started)
            ):
                break
            time.sleep(0.2)
        else:
            raise AssertionError(f"the fresh process did not lead: {doc}")
        time.sleep(1.5)  # a few more rounds
        assert jobs_by_process(fresh.url) == jobs
        after = passes(fresh.url)
        assert {n: (after[n]["status"], after[n]["jobs"]) for n in raws} == {
            n: (p["status"], p["jobs"]) for n, p in done.items()
        }
        assert after["slow.tif"]["status"] == "waiting"
    finally:
        for s in servers:
            s.kill()


def _iso(t: float) -> str:
    from sarship.service.store import iso

    return iso(t)
