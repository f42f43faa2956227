"""Issue #30 (the service's submission checks, scenes, non-finite parameters, land-mask files),
without a server: every float parameter of every detector refuses non-finite values; the one
detector/scene check (vb_polsar on a covariance scene) and land-mask files that are no regular
file, nested too deep or too large are one line and exit 2 on the command line; the scene
retention and deletion keep scenes that queued jobs name; job errors lose the data folder."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time

import numpy as np
import pytest
from conftest import blobs_scene, cov_scene, write_scene

from sarship.pipeline.errors import InputError

NON_FINITE = ("nan", "-Infinity", "1e999", float("inf"))


def test_every_float_parameter_refuses_non_finite_values():
    from sarship.pipeline import detectors
    from sarship.workers.request import JobRequest

    checked = 0  # (--set values reach the same parser: sarship detect --set max_elongation=1e999 exits 2)
    for name in detectors.names():
        for key, field in detectors.get(name).params.model_fields.items():
            if "float" not in str(field.annotation):
                continue
            for v in NON_FINITE:
                with pytest.raises(InputError, match=f"parameter '{key}': .*finite"):
                    JobRequest.from_inputs(name, {"scene": "x", key: v})
                checked += 1
    assert checked > 100
    # finite values still pass, nodata 0 among them
    JobRequest.from_inputs("ca_cfar", {"scene": "x", "nodata": 0, "max_length_m": 400.0, "max_elongation": "12"})


def test_channel_is_a_variable_name_never_a_path():
    from sarship.workers.request import JobRequest

    for bad in ("../../s1.zarr/intensity", "/etc/passwd", "a\\b", "..", " ", "hh;rm"):
        with pytest.raises(InputError, match="channel"):
            JobRequest.from_inputs("ca_cfar", {"scene": "x", "channel": bad})
    assert JobRequest.from_inputs("apwf", {"scene": "x", "channel": "hh, vv"}).channel == "hh, vv"


def sarship(*args, timeout=60, **env):
    return subprocess.run(
        [sys.executable, "-m", "sarship", *map(str, args)],
        capture_output=True,
        text=True,
        timeout=timeout,
        env={**os.environ, **env},
    )


def one_line_exit_2(r, *words):
    assert r.returncode == 2, (r.returncode, r.stderr[-2000:])
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in r.stderr, r.stderr
    for w in words:
        assert w in lines[0], (w, lines[0])


def test_detector_scene_mismatch_is_one_check(tmp_path):
    """vb_polsar reads complex channels: on a covariance scene the one check
    (``detector_source``) refuses it with one line, and ``sarship detect`` exits 2 before any
    cluster starts; apwf and pcdm read the same scene."""
    from sarship.pipeline import detectors
    from sarship.pipeline.scene import open_scene
    from sarship.pipeline.tiling.inputs import detector_source

    sc = open_scene(cov_scene(tmp_path / "cov.zarr", shape=(48, 40)))
    with pytest.raises(InputError, match="vb_polsar.*covariance"):
        detector_source(detectors.get("vb_polsar"), sc)
    for ok in ("apwf", "pcdm"):
        assert detector_source(detectors.get(ok), sc)[1] == "covariance"
    assert detector_source(detectors.get("ca_cfar"), sc) == ("c11", "real")
    r = sarship("detect", tmp_path / "cov.zarr", "--detector", "vb_polsar", "--out", tmp_path / "out")
    one_line_exit_2(r, "vb_polsar", "covariance", "apwf")
    assert not (tmp_path / "out").exists()


def test_land_mask_fifo_deep_and_oversize(tmp_path, monkeypatch):
    """A FIFO as land_mask is refused from its stat (the command line exits 2 at once instead of
    blocking); a GeoJSON nested 200 000 deep is one line (no RecursionError); a GeoJSON larger
    than SARSHIP_LAND_MAX_MB is refused before it is read."""
    from sarship.pipeline.land.landmask_files import check_land_path, open_land_file

    fifo = tmp_path / "land.fifo"
    os.mkfifo(fifo)
    with pytest.raises(InputError, match="not a regular file"):
        open_land_file(str(fifo), (10, 10), {})
    deep = tmp_path / "deep.geojson"
    deep.write_bytes(b'{"type": "FeatureCollection", "features": ' + b"[" * 200_000 + b"]" * 200_000 + b"}")
    with pytest.raises(InputError, match="nested deeper than") as e:
        open_land_file(str(deep), (10, 10), {})
    assert "\n" not in str(e.value)
    big = tmp_path / "big.geojson"
    big.write_bytes(b" " * (2 * 2**20) + b"{}")
    monkeypatch.setenv("SARSHIP_LAND_MAX_MB", "1")
    with pytest.raises(InputError, match="SARSHIP_LAND_MAX_MB"):
        check_land_path(big)
    with pytest.raises(InputError, match="larger than"):
        open_land_file(str(big), (10, 10), {})
    monkeypatch.delenv("SARSHIP_LAND_MAX_MB")
    # a small valid GeoJSON (pixel coordinates) still reads
    ok = tmp_path / "ok.geojson"
    ok.write_text(
        json.dumps({"type": "Polygon", "coordinates": [[[0, 0], [5, 0], [5, 5], [0, 5]]], "pixel_coordinates": True})
    )
    assert open_land_file(str(ok), (10, 10), {}).read(0, 10, 0, 10).sum() == 25
    write_scene(tmp_path / "s.zarr", {"intensity": blobs_scene((40, 40))}, tile=64, looks=2.0)
    t0 = time.monotonic()
    r = sarship(
        "detect",
        tmp_path / "s.zarr",
        "--detector",
        "ca_cfar",
        "--set",
        f"land_mask={fifo}",
        "--out",
        tmp_path / "o",
        timeout=30,
    )
    one_line_exit_2(r, "land_mask", "not a regular file")
    assert time.monotonic() - t0 < 30


def test_json_depth_streams_in_chunks():
    """The land mask's depth scan, chunk by chunk, counts as the request body's one-shot scan
    does, across chunk borders inside escapes and strings."""
    from sarship.pipeline.land.landmask_files import json_depth
    from sarship.service.common import json_depth as whole

    docs = [
        b'{"a": [1, "[\\\\", {"b": "\\"[["}], "c": [[[]]]}',
        b'["\\\\\\"[", [[{"x": "}}"}]]]',
        json.dumps({"k": [["\\" * n + "[" for n in range(6)], {"q": '"[{'}]}).encode(),
    ]
    for raw in docs:
        for chunk in (1, 2, 3, 5, 8, 1 << 22):
            assert json_depth(raw, chunk) == whole(raw), (raw, chunk)


def test_hide_paths(tmp_path):
    from sarship.service.settings import Settings

    data = tmp_path / "d"
    (tmp_path / "link").symlink_to(tmp_path, target_is_directory=True)
    s = Settings(data=tmp_path / "link" / "d")
    text = (
        f"scene '{data}/scenes/s1.zarr' has no hh; '{s.data}/uploads/a.tif' bad; {data}: full; "
        f"{data}x stays; {s.data}/scenes"
    )
    assert s.hide_paths(text) == (
        f"scene 's1.zarr' has no hh; 'uploads/a.tif' bad; the data folder: full; {data}x stays; the scene folder"
    )


def test_scene_retention_and_deletion(tmp_path):
    """Scenes older than scene_retention_days go unless an accepted or running job names them
    (by id or by path); retention off keeps everything; a deletion interrupted after its rename
    is finished by the next pass."""
    from sarship.service.scenes import SceneInUse, delete_scene, expire_scenes, label_scene
    from sarship.service.settings import Settings
    from sarship.service.store import JobStore

    s = Settings(data=tmp_path / "data")
    s.scenes_dir.mkdir(parents=True)
    s.uploads_dir.mkdir()
    store = JobStore(s.db_path)
    old = time.time() - 10 * 86400
    for sid in ("old", "old_used", "old_by_path", "new"):
        p = write_scene(s.scenes_dir / f"{sid}.zarr", {"intensity": blobs_scene((32, 32))}, tile=64, looks=2.0)
        if sid.startswith("old"):
            for f in (p, p / "zarr.json"):
                os.utime(f, (old, old))
    (s.uploads_dir / "old.tif").write_bytes(b"x")
    label_scene(s.scenes_dir / "new.zarr", "new.tif")  # ingested now (recorded)
    store.create("ca_cfar", {"scene": "old_used"})
    store.create("ca_cfar", {"scene": str(s.scenes_dir / "old_by_path.zarr")})
    (s.scenes_dir / ".deleted-x-abc123").mkdir()
    assert expire_scenes(s, store) == []  # retention off
    assert not (s.scenes_dir / ".deleted-x-abc123").exists()
    s7 = Settings(data=s.data, scene_retention_days=7)
    assert expire_scenes(s7, store) == ["old"]
    assert sorted(p.name for p in s.scenes_dir.iterdir()) == ["new.zarr", "old_by_path.zarr", "old_used.zarr"]
    assert not (s.uploads_dir / "old.tif").exists()
    with pytest.raises(SceneInUse):
        delete_scene(s, store, "old_used")
    assert delete_scene(s, store, "new") and not delete_scene(s, store, "new")
    assert expire_scenes(Settings(data=s.data, scene_retention_days=0), store) == []


def test_land_file_is_parsed_in_a_capped_child(tmp_path):
    """The service's land_mask FILE is parsed and rasterised by a spawned child under the ingest's
    memory cap (the API process never parses it): a small GeoJSON becomes the job's raster; a
    27 MB one, whose parse needs more than the 350 MiB cap, is one line saying so (the parent
    unharmed)."""
    import zarr

    from sarship.service.ingest_proc import land_in_child

    small = tmp_path / "small.geojson"
    small.write_text(
        json.dumps({"type": "Polygon", "coordinates": [[[0, 0], [8, 0], [8, 4], [0, 4]]], "pixel_coordinates": True})
    )
    out = tmp_path / "land.zarr"
    seen = []
    # the small file under a roomier cap: writing the raster starts zarr's and the codecs' threads,
    # whose stacks count in the address space (350 MiB once failed there: "can't start new thread")
    answer = land_in_child(
        small,
        out,
        shape=(16, 20),
        attrs={},
        tile=8,
        max_bytes=2**30,
        memory_mb=1024.0,
        progress=lambda done, total: seen.append((done, total)),
    )
    assert answer == {
        "kind": "vector",
        "format": "geojson",
        "info": {"polygons": 1, "coordinates": "pixel", "overlaps_scene": True},
    }
    land = np.asarray(zarr.open_group(str(out), mode="r")["land"][...])
    assert land.shape == (16, 20) and land[:4, :8].all() and land.sum() == 32
    assert seen[-1] == (16, 16)
    big = tmp_path / "big.geojson"  # two million positions
    big.write_bytes(
        b'{"type": "Polygon", "pixel_coordinates": true, "coordinates": [[[0, 0], '
        + b"[12.5, 3.25], " * 2_000_000
        + b"[0, 0]]]}"
    )
    with pytest.raises(InputError, match="needs more memory than the cap of 350 MiB"):
        land_in_child(
            big,
            tmp_path / "big.zarr",
            shape=(16, 20),
            attrs={},
            tile=8,
            max_bytes=2**30,
            memory_mb=350.0,
            progress=lambda done, total: None,
        )


def test_ais_input_is_parsed_and_checked_by_the_service_in_one_line(tmp_path):
    """``ais``: one path or a list (JobRequest, as the command line passes it), bad shapes named in
    one line; the service takes files inside its allowed folders only (a 400 in one line
    otherwise: no job reads a file outside them) and keeps them as resolved absolute paths."""
    from sarship.service.common import Problem
    from sarship.service.job_inputs import validate_inputs
    from sarship.service.settings import Settings
    from sarship.workers.request import JobRequest

    (tmp_path / "data" / "scenes").mkdir(parents=True)
    scene = str(write_scene(tmp_path / "data" / "scenes" / "s.zarr", {"intensity": blobs_scene((64, 64))}))
    assert JobRequest.from_inputs("ca_cfar", {"scene": scene, "ais": "a.csv"}).ais == ("a.csv",)
    req = JobRequest.from_inputs("ca_cfar", {"scene": scene, "ais": ["a.csv", "b.nmea"]})
    assert req.ais == ("a.csv", "b.nmea") and req.inputs()["ais"] == ["a.csv", "b.nmea"]
    assert JobRequest.from_stored("ca_cfar", req.inputs()).ais == req.ais
    for bad in (3, ["a.csv", 4], [""], {"f": 1}):
        with pytest.raises(InputError, match="input 'ais' must be a path or a list"):
            JobRequest.from_inputs("ca_cfar", {"scene": scene, "ais": bad})
    settings = Settings(data=tmp_path / "data")
    with pytest.raises(Problem) as exc:
        validate_inputs(settings, "ca_cfar", {"inputs": {"scene": scene, "ais": "/etc/passwd"}})
    assert exc.value.status == 400 and "outside the allowed scene folders" in exc.value.detail
    assert "\n" not in exc.value.detail
    (tmp_path / "data" / "scenes" / "day.csv").write_text("mmsi,time,lon,lat\n")
    inputs = validate_inputs(settings, "ca_cfar", {"inputs": {"scene": scene, "ais": ["day.csv", "./day.csv"]}})
    assert inputs["ais"] == [str((tmp_path / "data" / "scenes" / "day.csv").resolve())]
    for bad, words in (("nope.csv", "no file 'nope.csv'"), ("0123456789abcdef", "no uploaded AIS file")):
        with pytest.raises(Problem) as exc:
            validate_inputs(settings, "ca_cfar", {"inputs": {"scene": scene, "ais": bad}})
        assert exc.value.status == 400 and words in exc.value.detail, exc.value.detail
