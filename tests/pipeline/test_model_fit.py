"""Does the detector's clutter model fit the scene (pipeline/stats/model_fit.py), and ``--detector auto``.

Simulated seas: L-look gamma speckle (ca_cfar's model) and K (gamma texture of shape 2, drawn per
pixel, times 4-look speckle: k_cfar's model, heavier-tailed than gamma). Small scenes (256 x 256,
the sample grid every 2nd pixel: 16 384 cells, 16 expected exceedances at the probe PFA 1e-3),
land mask off: the fit is what is tested here.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.stats import beta

from sarship.pipeline.stats import model_fit
from tests.cli.test_cli import assert_clean_error, sarship
from tests.conftest import write_scene

NO_LAND = {"land_mask": "none"}


def sea(kind: str, shape=(256, 256), looks: float = 4.0, nu: float = 2.0, seed: int = 1) -> np.ndarray:
    """Gamma (``kind="gamma"``) or K (``"k"``) intensity of mean 1, with a few bright ships."""
    rng = np.random.default_rng(seed)
    x = rng.gamma(looks, 1.0 / looks, shape)
    if kind == "k":
        x = x * rng.gamma(nu, 1.0 / nu, shape)
    for r, c in ((60, 70), (180, 150)):
        x[r : r + 4, c : c + 9] += 200.0
    return x.astype(np.float32)


@pytest.fixture(scope="module")
def seas(tmp_path_factory):
    d = tmp_path_factory.mktemp("seas")
    return {k: write_scene(d / f"{k}.zarr", {"intensity": sea(k)}, tile=128, looks=4.0) for k in ("gamma", "k")}


def _run(client, scene, detector, tmp_path, tile=None, **settings):
    from sarship.workers.jobs import run_detection

    return run_detection(
        scene,
        detector,
        {**NO_LAND, **settings},
        out_dir=tmp_path / f"{detector}-{tile}",
        tile=tile,
        client=client,
        progress=False,
    )


# ----------------------------------------------------------------------------- the maths


def test_interval_is_clopper_pearson():
    """Eq 1: the beta quantiles of the exact binomial interval."""
    lo, hi = model_fit.interval(17, 16384)
    assert lo == pytest.approx(beta.ppf(0.025, 17, 16384 - 17 + 1), rel=1e-9)
    assert hi == pytest.approx(beta.ppf(0.975, 18, 16384 - 17), rel=1e-9)
    assert model_fit.interval(0, 1000)[0] == 0.0


@pytest.mark.parametrize(
    "k,n,pfa,expected",
    [
        (16, 16384, 1e-3, "fits"),  # 1x
        (40, 16384, 1e-3, "fits"),  # 2.4x: the interval reaches below 2x the PFA
        (500, 16384, 1e-3, "too many false alarms"),
        (0, 16384, 1e-3, "too few"),
        (0, 16384, 1e-5, "undetermined"),  # 0.16 expected: the sample cannot resolve 1e-5
        (0, 0, 1e-3, "undetermined"),
    ],
)
def test_verdict(k, n, pfa, expected):
    assert model_fit.verdict(pfa, k, n)[0] == expected


def test_grid_is_global_and_targets_are_excluded():
    """The sample grid is fixed by scene coordinates (a tile starting anywhere gets the cells
    row % stride == col % stride == 0); cells within the margin of a detection's box are cleared."""
    rs, cs, gi, gj = model_fit.grid_slices(5, 7, 10, 10, 4)
    assert (rs.start, cs.start, gi, gj) == (3, 1, 2, 2)  # scene rows 8, 12; columns 8, 12, 16
    grid = np.ones((10, 10), np.uint8)
    cleared = model_fit.exclude_targets(grid, 4, np.array([[20, 20, 22, 22]]), margin=4)
    # rows/cols 16..25 are within 4 px of [20, 22): grid indices 4, 5, 6
    assert cleared == 9 and not grid[4:7, 4:7].any() and grid[3, 4] == 1 and grid[7, 4] == 1


def test_choose_rule():
    rec = {"verdict": "too many false alarms", "exceedances": 300, "sample": 10000, "probe_pfa": 1e-3, "ratio": 30.0}
    fits = {**rec, "verdict": "fits", "exceedances": 10, "ratio": 1.0}
    few = {**rec, "verdict": "too few", "exceedances": 0, "ratio": 0.0}
    assert model_fit.choose({"ca_cfar": rec, "k_cfar": fits, "g0_cfar": fits})[0] == "k_cfar"
    assert model_fit.choose({"ca_cfar": fits, "k_cfar": fits, "g0_cfar": few})[0] == "ca_cfar"
    # auto's tolerance (8x, chosen on half A of the real chips): 4x and 0 of 10 expected fit there
    four = {**rec, "exceedances": 40, "ratio": 4.0}
    assert model_fit.choose({"ca_cfar": four, "k_cfar": fits, "g0_cfar": fits})[0] == "ca_cfar"
    assert model_fit.choose({"ca_cfar": rec, "k_cfar": few, "g0_cfar": fits})[0] == "k_cfar"
    # none fits: the nearest on a log scale (30x, 15x, 300x)
    name, why = model_fit.choose(
        {
            "ca_cfar": rec,
            "k_cfar": {**rec, "exceedances": 150, "ratio": 15.0},
            "g0_cfar": {**rec, "exceedances": 3000, "ratio": 300.0},
        }
    )
    assert name == "k_cfar" and "no candidate" in why


# ----------------------------------------------------------------------------- through the workers


def test_gamma_sea_ca_cfar_fits(client, seas, tmp_path):
    run = _run(client, seas["gamma"], "ca_cfar", tmp_path)
    mf = run["model_fit"]
    assert mf["detector"] == "ca_cfar" and mf["verdict"] == "fits", mf
    assert [m["pfa"] for m in mf["measurements"]] == [1e-5, 1e-3] and mf["probe_pfa"] == 1e-3
    assert mf["stride_px"] == 2 and 16000 < mf["sample"] <= 128 * 128
    assert mf["excluded_near_detections"] > 0  # the two ships' cells are not clutter
    lo, hi = mf["interval"]
    assert lo <= 1e-3 <= hi and not any("model fit" in w for w in run["warnings"])


def test_k_sea_ca_cfar_too_many_k_cfar_fits(client, seas, tmp_path):
    run = _run(client, seas["k"], "ca_cfar", tmp_path)
    ca = run["model_fit"]
    assert ca["verdict"] == "too many false alarms" and ca["ratio"] > 10, ca
    # the line stderr gets (sarship detect prints run.json's warnings, one line each)
    line = [w for w in run["warnings"] if w.startswith("model fit")]
    assert len(line) == 1 and "heavier-tailed than ca_cfar's model" in line[0], run["warnings"]
    assert (
        f"(exceedance {ca['ratio']:.3g}x the PFA at 0.001" in line[0] and "try --detector k_cfar or g0_cfar" in line[0]
    )
    k = _run(client, seas["k"], "k_cfar", tmp_path)
    assert k["model_fit"]["verdict"] == "fits", k["model_fit"]
    assert [m["pfa"] for m in k["model_fit"]["measurements"]] == [1e-3]  # its default PFA is the probe


def test_os_cfar_on_k_sea_too_many(client, seas, tmp_path):
    mf = _run(client, seas["k"], "os_cfar", tmp_path)["model_fit"]
    assert [m["pfa"] for m in mf["measurements"]] == [1e-6, 1e-3] and mf["probe_by"] == "ca_cfar"
    assert mf["verdict"] == "too many false alarms" and mf["ratio"] > 10, mf


def test_record_is_identical_for_two_tilings(client, seas, tmp_path):
    a = _run(client, seas["k"], "ca_cfar", tmp_path, tile=64)
    b = _run(client, seas["k"], "ca_cfar", tmp_path, tile=256)
    assert a["tiles"]["count"] == 16 and b["tiles"]["count"] == 1
    assert a["model_fit"] == b["model_fit"]
    assert a["model_fit"]["excluded_near_detections"] > 0


def test_fit_measured_for_the_cfar_detectors_only():
    """The tiles' fit settings: a probe beyond the asked PFA below 1e-3 (ca_cfar's from its
    statistic, the others' by detecting again), none at 1e-3, no fit for other detectors."""
    from sarship.pipeline import detectors
    from sarship.pipeline.run.plan import fit_config as _fit_config

    ca = detectors.get("ca_cfar")
    cfg = _fit_config("ca_cfar", ca, ca.params(looks=4.0), (800, 800))
    assert cfg["stride"] == 2 and [p["pfa"] for p in cfg["probes"]] == [1e-3] and cfg["probes"][0]["statistic"]
    assert cfg["probes"][0]["prep"]["threshold"] == ca.prepare(ca.params(looks=4.0, pfa=1e-3))["threshold"]
    k = detectors.get("k_cfar")
    assert _fit_config("k_cfar", k, k.params(looks=4.0), (800, 800))["probes"] == []
    assert _fit_config("k_cfar", k, k.params(looks=4.0), (8000, 8000))["stride"] == 16
    os_ = detectors.get("os_cfar")  # its probe: its gamma model's cell-averaging decision, same windows
    (probe,) = _fit_config("os_cfar", os_, os_.params(looks=4.0), (800, 800))["probes"]
    assert probe["detector"] == "ca_cfar" and probe["params"]["guard"] == os_.params().guard
    assert (
        probe["prep"]["threshold"] == ca.prepare(ca.params(looks=4.0, pfa=1e-3, guard=21, background=41))["threshold"]
    )
    for name in ("lmm", "superpixel_cfar", "gamma_mrf", "csk"):
        assert _fit_config(name, None, None, (800, 800)) is None


def test_auto_on_gamma_sea_picks_ca_cfar(client, seas, tmp_path):
    run = _run(client, seas["gamma"], "auto", tmp_path)
    auto = run["detector_auto"]
    assert run["detector"] == "ca_cfar" == auto["chosen"], auto
    assert auto["candidates"] == ["ca_cfar", "k_cfar", "g0_cfar"] and auto["fits"]["ca_cfar"]["verdict"] == "fits"
    assert run["model_fit"]["detector"] == "ca_cfar" and run["detections"] == 2


def test_cli_auto_on_k_sea_picks_k_cfar(client, seas, tmp_path):
    out = tmp_path / "out"
    res = sarship(
        "detect",
        seas["k"],
        "--detector",
        "auto",
        "--set",
        "land_mask=none",
        "--out",
        out,
        "--scheduler",
        client.scheduler.address,
    )
    assert res.returncode == 0, res.stderr
    run = json.loads((out / "run.json").read_text())
    auto = run["detector_auto"]
    assert auto["fits"]["ca_cfar"]["verdict"] == "too many false alarms"
    assert auto["chosen"] == "k_cfar" == run["detector"] and auto["fits"]["k_cfar"]["verdict"] == "fits"
    assert "detector auto: k_cfar" in res.stderr
    assert sorted(p.name for p in out.iterdir()) == ["detections.geojson", "mask.zarr", "run.json"]


def test_cli_auto_refuses_a_parameter_a_candidate_lacks(seas, tmp_path):
    res = sarship("detect", seas["gamma"], "--detector", "auto", "--set", "censor=5", "--out", tmp_path / "o")
    assert_clean_error(res, "auto", "censor", "ca_cfar")
    assert not (tmp_path / "o").exists()
