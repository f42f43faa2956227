"""AIS in a detection run (issue 33; docs/ais.md): ``sarship detect --ais``, ``sarship match``.

A simulated georeferenced scene with moving ships (rendered at their Doppler-displaced positions)
and its AIS reports (class A/B intervals, gaps, position noise, a dark fraction, vessels outside the
swath and too small to see: pipeline/simulate), detected and matched through the run; the truth
(which ship is dark, its MMSI) is never seen by the run. Checked against the issue's targets on
detected ships: AIS precision >= 0.98 and recall >= 0.95, dark recall >= 0.95, at most 2 % of the
reporting ships called dark; the run's records and files; ``sarship match`` on the finished run
gives the same answer without detecting again; bad input refused in one line, nothing written.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from sarship.pipeline.simulate import SimConfig, simulate
from sarship.workers.jobs import run_detection
from tests.cli.test_cli import assert_clean_error, listing, sarship, sarship_here

SCENE = dict(
    shape=(1024, 1024),
    ships=30,
    seed=11,
    looks=4.0,
    scr_db=18.0,
    geo=(5.5, 56.5),
    moving=True,
    ais=True,
    dark_fraction=0.2,
)


@pytest.fixture(scope="module")
def ais_run(client, tmp_path_factory):
    tmp = tmp_path_factory.mktemp("ais_run")
    scene = tmp / "s.zarr"
    simulate(scene, SimConfig(**SCENE), tile=512, ais_path=tmp / "ais.csv")
    run = run_detection(
        scene,
        "ca_cfar",
        {"ais": [str(tmp / "ais.csv")]},
        out_dir=tmp / "run",
        client=client,
        progress=False,
    )
    truth = json.loads(Path(f"{scene}.truth.geojson").read_text())
    return tmp, run, truth


def _hits(truth: dict, feats: list[dict]) -> list[int]:
    """The truth ship each detection hits (its centroid inside the ship's box grown by 3 px), or -1."""
    boxes = np.array([f["properties"]["bbox_px"] for f in truth["features"]], float)
    out = []
    for f in feats:
        r, c = f["properties"]["centroid_px"]
        inside = (boxes[:, 0] - 3 <= r) & (r <= boxes[:, 2] + 3) & (boxes[:, 1] - 3 <= c) & (c <= boxes[:, 3] + 3)
        out.append(int(np.argmax(inside)) if inside.any() else -1)
    return out


def _scores(truth: dict, feats: list[dict]) -> dict[str, float]:
    tp = [f["properties"] for f in truth["features"]]
    matched = correct = 0
    reporting, reporting_ok, reporting_dark, dark, dark_ok = set(), set(), set(), set(), set()
    for f, k in zip(feats, _hits(truth, feats)):
        if k < 0:
            continue
        p, t = f["properties"], tp[k]
        if p["ais"] is not None:
            matched += 1
            correct += p["ais"]["mmsi"] == t["mmsi"]
        if t["mmsi"] is not None:
            reporting.add(k)
            if p["ais"] is not None and p["ais"]["mmsi"] == t["mmsi"]:
                reporting_ok.add(k)
            if p["dark"]:
                reporting_dark.add(k)
        else:
            dark.add(k)
            if p["dark"]:
                dark_ok.add(k)
    assert reporting and dark, "the scene must have both reporting and dark ships detected"
    return {
        "ais_precision": correct / matched,
        "ais_recall": len(reporting_ok) / len(reporting),
        "dark_recall": len(dark_ok) / len(dark),
        "reporting_called_dark": len(reporting_dark) / len(reporting),
    }


def test_detect_with_ais_meets_the_targets(ais_run):
    tmp, run, truth = ais_run
    feats = json.loads((tmp / "run" / "detections.geojson").read_text())["features"]
    s = _scores(truth, feats)
    assert s["ais_precision"] >= 0.98 and s["ais_recall"] >= 0.95, s
    assert s["dark_recall"] >= 0.95 and s["reporting_called_dark"] <= 0.02, s
    # every detection says it: a record or null, and dark true/false (the AIS covers the scene)
    assert all("ais" in f["properties"] and isinstance(f["properties"]["dark"], bool) for f in feats)
    for f in feats:
        a = f["properties"]["ais"]
        if a is not None:
            assert set(a) == {"mmsi", "name", "score", "distance_m", "dt_s", "ais_length_m", "displacement_m"}
            assert 0.01 <= a["score"] <= 1.0 and a["distance_m"] < 2000.0 and a["name"]


def test_run_records_and_unmatched_vessels(ais_run):
    tmp, run, truth = ais_run
    rec = run["ais"]
    assert rec["covered"] is True and rec["read"]["rejected"] == 0 and rec["read"]["kept"] > 0
    assert rec["matched"] + rec["dark"] == rec["detections"] == run["detections"]
    unmatched = json.loads((tmp / "run" / "ais_unmatched.geojson").read_text())["features"]
    assert run["outputs"]["ais_unmatched.geojson"] == str((tmp / "run" / "ais_unmatched.geojson").resolve())
    assert len(unmatched) == rec["unmatched_in_footprint"]
    # the AIS-only vessels too small to see are unmatched and not detectable; those outside the
    # swath are not in the footprint; every reporting ship left unmatched was missed by the detector
    vessels = truth["ais"]["vessels"]
    small = {v["mmsi"] for v in vessels if v["kind"] == "small"}
    outside = {v["mmsi"] for v in vessels if v["kind"] == "outside"}
    got = {f["properties"]["mmsi"]: f["properties"] for f in unmatched}
    assert small <= set(got) and not (outside & set(got))
    assert all(got[m]["detectable"] is False for m in small)
    feats = json.loads((tmp / "run" / "detections.geojson").read_text())["features"]
    detected = {truth["features"][k]["properties"]["mmsi"] for k in _hits(truth, feats) if k >= 0}
    assert not (set(got) - small) & detected


def test_match_again_gives_the_same_answer(ais_run, tmp_path):
    tmp, run, _ = ais_run
    copy = tmp_path / "run"
    shutil.copytree(tmp / "run", copy)
    before = json.loads((copy / "detections.geojson").read_text())
    res = sarship_here("match", copy, "--ais", tmp / "ais.csv")
    assert_clean_error(res, "already matched", "--overwrite")  # the run has its AIS results
    for f in before["features"]:  # a run detected without AIS: nothing to keep
        f["properties"].pop("ais"), f["properties"].pop("dark")
    (copy / "detections.geojson").write_text(json.dumps(before))
    res = sarship("match", copy, "--ais", tmp / "ais.csv", "--overwrite")  # a real process for one command
    assert res.returncode == 0, res.stderr
    assert f"{run['ais']['matched']} of {run['detections']} detections matched" in res.stdout
    again = json.loads((copy / "detections.geojson").read_text())["features"]
    first = json.loads((tmp / "run" / "detections.geojson").read_text())["features"]
    assert [f["properties"]["ais"] for f in again] == [f["properties"]["ais"] for f in first]
    assert [f["properties"]["dark"] for f in again] == [f["properties"]["dark"] for f in first]
    rec = json.loads((copy / "run.json").read_text())["ais"]
    assert (
        rec["matched"] == run["ais"]["matched"]
        and rec["unmatched_in_footprint"] == run["ais"]["unmatched_in_footprint"]
    )


def test_bad_ais_input_is_refused_before_any_work(ais_run, tmp_path):
    tmp, _, _ = ais_run
    scene = tmp / "s.zarr"
    res = sarship_here(
        "detect", scene, "--detector", "ca_cfar", "--ais", tmp_path / "nope.csv", "--out", tmp_path / "o"
    )
    assert_clean_error(res, "nope.csv", "no such file")
    (tmp_path / "notais.csv").write_text("a,b,c\n1,2,3\n")
    res = sarship_here("match", tmp / "run", "--ais", tmp_path / "notais.csv", "--overwrite")
    assert_clean_error(res, "notais.csv")
    plain = tmp_path / "plain.zarr"  # a scene without a georeference: no lon/lat to match
    simulate(plain, SimConfig(shape=(256, 256), ships=2, seed=1), tile=256)
    res = sarship_here("detect", plain, "--detector", "ca_cfar", "--ais", tmp / "ais.csv", "--out", tmp_path / "o")
    assert_clean_error(res, "not georeferenced")
    assert not (tmp_path / "o").exists() or listing(tmp_path / "o") == []
