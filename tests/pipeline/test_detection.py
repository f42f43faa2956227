"""Detection of known ships on simulated scenes (ground truth the detectors never see)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from sarship.pipeline.products.scoring import evaluate, match
from sarship.pipeline.products.truth import load_detections, load_ships
from sarship.pipeline.simulate import SimConfig, simulate
from sarship.workers.jobs import run_detection
from tests.conftest import write_scene

SENSIBLE = {
    "ca_cfar": {"pfa": "1e-6", "min_area_px": "2", "merge_px": "5"},
    "os_cfar": {"pfa": "1e-6", "min_area_px": "2", "merge_px": "5"},
    "two_parameter": {"pfa": "1e-9", "min_area_px": "3", "merge_px": "5", "domain": "intensity"},
}


@pytest.fixture(scope="module")
def ship_scenes(tmp_path_factory):
    root = tmp_path_factory.mktemp("ships")
    out = {}
    for clutter, looks in (("rayleigh", 1.0), ("gamma", 4.0)):
        cfg = SimConfig(
            kind="intensity", shape=(2048, 2048), ships=25, seed=3, looks=looks, clutter=clutter, scr_db=12.0
        )
        scene = root / f"{clutter}.zarr"
        simulate(scene, cfg, tile=1024, truth_path=root / f"{clutter}.truth.geojson")
        out[clutter] = (scene, root / f"{clutter}.truth.geojson")
    return out


@pytest.mark.parametrize(
    "clutter,det",
    [
        ("gamma", "ca_cfar"),
        ("gamma", "os_cfar"),
        ("gamma", "two_parameter"),
        ("rayleigh", "ca_cfar"),
        ("rayleigh", "os_cfar"),
    ],
)
def test_fom_on_simulated_ships(ship_scenes, client, tmp_path, clutter, det):
    scene, truth = ship_scenes[clutter]
    run_detection(scene, det, SENSIBLE[det], out_dir=tmp_path / "o", client=client, progress=False)
    s = evaluate(tmp_path / "o" / "detections.geojson", truth)
    assert s["n_truth"] == 25
    assert s["fom"] >= 0.9, s


def test_ship_geometry_estimates(ship_scenes, client, tmp_path):
    scene, truth_path = ship_scenes["gamma"]
    run_detection(scene, "ca_cfar", SENSIBLE["ca_cfar"], out_dir=tmp_path / "o", client=client, progress=False)
    dets = load_detections(tmp_path / "o" / "detections.geojson")
    truth, _ = load_ships(truth_path)
    pairs = match(dets, truth)
    assert len(pairs) >= 23
    errs_len, errs_head = [], []
    for d, t in pairs:
        tp, dp = truth[t].properties, dets[d].properties
        if tp["length_px"] >= 12:  # long enough for a heading to mean something
            errs_len.append(abs(dp["length_m"] - tp["length_m"]) / tp["length_m"])
            dh = abs(dp["heading_deg"] - tp["heading_deg"]) % 180.0
            errs_head.append(min(dh, 180.0 - dh))
    assert len(errs_len) >= 8
    assert np.median(errs_len) < 0.25, errs_len
    assert np.median(errs_head) < 10.0, errs_head


def test_georeferenced_geometry_and_looks_estimated(client, tmp_path):
    rng = np.random.default_rng(2)
    x = rng.gamma(3.0, 1 / 3.0, (300, 300)).astype(np.float32)
    x[100:104, 150:170] += 80.0  # a ship 20 px long along columns: heading 90
    # no 'looks' attribute: the run estimates it from the data
    scene = write_scene(
        tmp_path / "g.zarr",
        {"intensity": x},
        tile=128,
        crs="EPSG:4326",
        transform=[10.0, 1e-4, 0.0, 50.0, 0.0, -1e-4],
        pixel_spacing_m=[11.1, 7.1],
    )
    run = run_detection(
        scene,
        "ca_cfar",
        {"pfa": "1e-6", "guard": "31", "background": "51"},
        out_dir=tmp_path / "o",
        client=client,
        progress=False,
    )
    assert run["looks_source"].startswith("estimated")
    assert 2.5 < run["parameters"]["looks"] < 3.5
    fc = json.loads((tmp_path / "o" / "detections.geojson").read_text())
    assert len(fc["features"]) == 1
    f = fc["features"][0]
    p = f["properties"]
    assert p["bbox_px"] == [100, 150, 104, 170]
    assert p["centroid_px"] == pytest.approx([102.0, 160.0])
    assert p["heading_deg"] == pytest.approx(90.0, abs=1.0)
    assert p["length_px"] == pytest.approx(20.0, rel=0.02) and p["width_px"] == pytest.approx(4.0, rel=0.05)
    assert p["length_m"] == pytest.approx(20 * 7.1, rel=0.02)
    ring = np.array(f["geometry"]["coordinates"][0])
    assert f["geometry"]["type"] == "Polygon" and ring.shape == (5, 2)
    lon_c, lat_c = ring[:4].mean(axis=0)
    assert lon_c == pytest.approx(10.0 + 160.0 * 1e-4) and lat_c == pytest.approx(50.0 - 102.0 * 1e-4)
