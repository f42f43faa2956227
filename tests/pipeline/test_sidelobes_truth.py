"""Sidelobe suppression (default on) against the simulator's truth, for every detector.

Issue #30: the cross detector took a ship's own speckled hull pixels for sidelobe arms and
cut 196 m ships down to 18 m. Here each detector, with its default ``sidelobes=true``, runs
on small simulated scenes with ships of known length and heading: one with the issue's
settings and no sidelobes (gamma sea, single look, 15 dB, 5 m pixels: the code before the
fix cut two of its three ships to 57 % and 2 % of their length), and one with simulated
sidelobe crosses (K sea, 25 dB, 3 m pixels), where crosses must still be cut.

Tolerances: the ships are 24-50 px long. The moment length of a detected hull differs from
the truth by the pixel quantisation of its ends (about a pixel each) and by the speckle of a
single-look hull whose tapered end pixels (area fraction < 1) fall under the threshold (a
pixel or two each end): up to ~4 px of 24, so 20 %. The moment heading of a body L px long
and a few pixels wide is quantised by about atan(2 / L) = 5 deg at 24 px: 8 deg allowed.
Three detectors find less of these single-look hulls, with or without suppression
(``two_parameter``: Gaussian tails; ``ggd_cfar``: generalized-gamma tails; ``lmm``:
lognormal-mixture fits, splitting ships; measured 22-58 % short on their components): for
them the step may not move the geometry further from the truth than their components are
(+ 5 points, + 3 deg). Whatever the
detector, a detection without a cross keeps exactly its component's geometry.
``two_parameter``'s threshold keeps the sidelobe arms out of its mask on the crosses' scene:
there is nothing to cut there.

The detectors whose decision is a per-tile ``detect`` run here directly on the arrays (as
tests/pipeline/test_sidelobes.py does), with the pipeline's components, features and sidelobe step;
those with scene-wide passes, their own discrimination or other scene kinds (``gamma_mrf``,
``superpixel_cfar``, ``csk``, ``apwf``, ``pcdm``, ``vb_polsar``; the simulator writes their
SLC and quad-pol scenes with the same ships) run through ``run_detection`` on the Dask
cluster, with ``sidelobes`` on and off (four runs each; ``gamma_mrf``, ``superpixel_cfar``
and ``csk`` are slow there: the rule they exercise is the same sidelobe step on their masks,
covered by the others in the default run).
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from sarship.pipeline import detectors
from sarship.pipeline.simulate import SimConfig, simulate, simulate_array
from sarship.pipeline.targets import sidelobes as S
from sarship.pipeline.targets.components import merge_radius, tile_components
from sarship.pipeline.targets.ship_features import features

LENGTH_TOL = 0.20  # |length / truth - 1| (module doc)
#: detectors whose components measure less of these single-look hulls (module doc): the
#: step must not move them further from the truth than their components are
SHORT = {"two_parameter", "ggd_cfar", "lmm"}
HEADING_TOL = 8.0  # degrees (module doc)

#: the issue's settings (sarship simulate defaults, --spacing 5), no sidelobes; seed 13: the
#: code before the fix flagged two of its three ships and cut them to 57 % and 2 % of their length
NO_SIDELOBES = SimConfig(shape=(256, 256), ships=3, seed=13, pixel_spacing_m=(5.0, 5.0), length_m=(120.0, 250.0))
#: simulated sidelobe crosses that pass the threshold (seed 0: three detections flagged by os_cfar)
SIDELOBES = SimConfig(
    shape=(256, 256),
    ships=3,
    seed=0,
    clutter="k",
    looks=1,
    sidelobes=True,
    scr_db=25,
    pixel_spacing_m=(3.0, 3.0),
    length_m=(75.0, 150.0),
)

DIRECT = ["two_parameter", "ca_cfar", "os_cfar", "lmm", "g0_cfar", "k_cfar", "ggd_cfar"]
#: through the whole run; the quad-pol ones are cheap on these scenes (~1.5 s for their four
#: runs), the others slow (8-30 s on the shared 2-core machine)
PIPELINE = [
    pytest.param("gamma_mrf", "intensity", marks=pytest.mark.slow),
    pytest.param("superpixel_cfar", "intensity", marks=pytest.mark.slow),
    pytest.param("csk", "slc", marks=pytest.mark.slow),
    ("apwf", "quadpol"),
    ("pcdm", "quadpol"),
    ("vb_polsar", "quadpol"),
]


def _heading_error(a: float, b: float) -> float:
    d = abs(a - b) % 180.0
    return min(d, 180.0 - d)


def _match(truth: dict, feats: list[dict]) -> list[tuple[dict, dict | None]]:
    """Each truth ship and the largest detection whose centroid lies in its box (+2 px)."""
    out = []
    for tf in truth["features"]:
        t = tf["properties"]
        r0, c0, r1, c1 = t["bbox_px"]
        inside = [
            f["properties"]
            for f in feats
            if r0 - 2 <= f["properties"]["centroid_px"][0] <= r1 + 2
            and c0 - 2 <= f["properties"]["centroid_px"][1] <= c1 + 2
        ]
        out.append((t, max(inside, key=lambda p: p["area_px"]) if inside else None))
    return out


def _direct(detector: str, cfg: SimConfig) -> tuple[dict, list[dict], list[dict]]:
    """``detector`` with its default parameters (sidelobes on) on the whole simulated scene:
    mask, the pipeline's components and features, then the sidelobe step as workers/jobs.py
    runs it. Returns the truth, the features after the step and the components' features."""
    data, truth = simulate_array(cfg)
    spec = detectors.get(detector)
    p = spec.params(looks=cfg.looks) if "looks" in spec.params.model_fields else spec.params()
    assert p.sidelobes is True
    feats, raw = _detect_and_refine(data["intensity"], spec, p, cfg.pixel_spacing_m)
    return truth, feats, raw


def _detect_and_refine(image: np.ndarray, spec, p, spacing) -> tuple[list[dict], list[dict]]:
    """``spec`` with parameters ``p`` on the whole ``image``: mask, the pipeline's components, and
    their features after the sidelobe step as workers/jobs.py runs it, and before it."""
    halo = spec.halo(p)
    mask, stat = spec.detect(np.pad(image, halo, mode="reflect"), halo, (-halo, -halo), p, spec.prepare(p))
    r = merge_radius(p.merge_px)
    recs = tile_components(np.pad(mask, r), image, stat, r, (0, 0), (0, 0)).complete
    feats = S.refine_features(
        features(recs, spacing, None),
        recs,
        lambda a, b, c, d: image[a:b, c:d],
        lambda a, b, c, d: mask[a:b, c:d],
        image.shape,
        r,
        spacing,
        None,
    )
    return feats, features(recs, spacing, None)


def _check_truth(truth: dict, feats: list[dict], raw: list[dict] | None = None) -> None:
    """Length and heading of each truth ship's detection within the tolerances (module doc);
    with ``raw`` (the same detections without the sidelobe step, in the same order) also
    whatever is no further from the truth than those (+ 5 points, + 3 deg)."""
    by_raw = {id(f["properties"]): g["properties"] for f, g in zip(feats, raw or [])}
    for t, p in _match(truth, feats):
        assert p is not None, f"ship {t['id']} ({t['length_m']:.0f} m) not detected"
        err = abs(p["length_m"] / t["length_m"] - 1)
        herr = _heading_error(p["heading_deg"], t["heading_deg"])
        tol, htol = LENGTH_TOL, HEADING_TOL
        if raw is not None:
            q = by_raw[id(p)]
            tol = max(tol, abs(q["length_m"] / t["length_m"] - 1) + 0.05)
            htol = max(htol, _heading_error(q["heading_deg"], t["heading_deg"]) + 3.0)
        assert err <= tol and herr <= htol, (
            f"ship {t['id']}: {p['length_m']:.0f} m heading {p['heading_deg']:.0f} deg "
            f"(sidelobes {p.get('sidelobes')}), truth {t['length_m']:.0f} m {t['heading_deg']:.0f} deg"
        )


@pytest.mark.parametrize("detector", DIRECT)
def test_ships_without_sidelobes_keep_their_geometry(detector):
    truth, feats, raw = _direct(detector, NO_SIDELOBES)
    assert not any(f["properties"]["sidelobes"] for f in feats)
    for f, g in zip(feats, raw):  # no cross: the component's geometry, exactly
        assert all(f["properties"][k] == g["properties"][k] for k in S.GEOMETRY_KEYS)
    _check_truth(truth, feats, raw if detector in SHORT else None)


@pytest.mark.parametrize("detector", [pytest.param(d, marks=pytest.mark.slow) if d == "lmm" else d for d in DIRECT])
def test_ships_with_sidelobes_within_tolerance_and_crosses_cut(detector):
    """(``lmm``'s per-cell fits make its two scenes ~5-10 s: slow; its scene without
    sidelobes stays in the default run.)"""
    truth, feats, raw = _direct(detector, SIDELOBES)
    _check_truth(truth, feats, raw if detector in SHORT else None)
    flagged = [f["properties"] for f in feats if f["properties"]["sidelobes"]]
    assert flagged or detector == "two_parameter", "no sidelobe cross cut"  # module doc
    assert all(p["core_area_px"] < p["area_px"] for p in flagged)
    # the same ships without their sidelobes: nothing is cut
    _, plain, _ = _direct(detector, SimConfig(**{**SIDELOBES.__dict__, "sidelobes": False}))
    assert not any(f["properties"]["sidelobes"] for f in plain)


def test_issue_ship_is_not_cut():
    """The issue's own ship: 196 m heading 109 deg in `sarship simulate --shape 4096x4096
    --ships 20 --seed 3 --spacing 5` (reported as 18 m heading 45 deg), in a window around it."""
    cfg = SimConfig(shape=(4096, 4096), ships=20, seed=3, pixel_spacing_m=(5.0, 5.0))
    data, truth = simulate_array(cfg)
    t = next(f["properties"] for f in truth["features"] if abs(f["properties"]["length_m"] - 196) < 1)
    r0, c0, r1, c1 = t["bbox_px"]
    a, c = r0 - 64, c0 - 64
    window = data["intensity"][a : r1 + 64, c : c1 + 64]
    spec = detectors.get("os_cfar")
    feats, _ = _detect_and_refine(window, spec, spec.params(looks=1), cfg.pixel_spacing_m)
    local = {"features": [{"properties": {**t, "bbox_px": [r0 - a, c0 - c, r1 - a, c1 - c]}}]}
    ((_, det),) = _match(local, feats)
    assert det is not None and det["sidelobes"] is False
    assert abs(det["length_m"] / 196 - 1) <= LENGTH_TOL and _heading_error(det["heading_deg"], 109) <= HEADING_TOL


@pytest.mark.parametrize("detector, kind", PIPELINE)
def test_pipeline_detectors_against_truth(detector, kind, tmp_path, client):
    """The other detectors through the whole run, on the same ships in their scene kind: with
    the default ``sidelobes=true`` no further from the truth than the tolerances, or than the
    same run with ``sidelobes=false`` (these detectors' own detections of single-look hulls
    are not all within them: csk's kurtosis, for one, finds part of a 15 dB hull)."""
    from sarship.workers.jobs import run_detection

    for name, cfg in (("plain", NO_SIDELOBES), ("crosses", SIDELOBES)):
        cfg = SimConfig(**{**cfg.__dict__, "kind": kind})
        scene = simulate(tmp_path / f"{name}.zarr", cfg, tile=256)
        feats = {}
        for sl in ("true", "false"):
            run = run_detection(
                scene, detector, {"sidelobes": sl}, out_dir=tmp_path / f"{name}-{sl}", client=client, progress=False
            )
            assert run["parameters"]["sidelobes"] is (sl == "true")
            feats[sl] = json.loads((tmp_path / f"{name}-{sl}" / "detections.geojson").read_text())["features"]
        truth = json.loads((tmp_path / f"{name}.zarr.truth.geojson").read_text())
        assert len(feats["true"]) == len(feats["false"])
        _check_truth(truth, feats["true"], feats["false"])
        if name == "plain":
            assert not any(f["properties"]["sidelobes"] for f in feats["true"])
