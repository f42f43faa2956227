"""The OpenSARShip GRD chips' own ships matched to their own MMSI (issue 33; bench/realdata_ais.py,
bench/REALDATA.md "AIS matching on OpenSARShip (issue 33)").

Each product's scene is built as a reader would from its SNAP metadata (line times, range table,
platform velocity, tie-point georeference); its ships' AIS reports (Ship.xml) are written as a
plain AIS CSV and read back with ``read_ais``; each chip is detected with ``ca_cfar``'s
defaults on the session's Dask cluster and the product's detections are matched to its vessels
(:func:`bench.realdata_ais.load`, ``match_chips``). Checked, with the shipped ``MatchParams()``:

- the time and displacement corrections bring the AIS reports to the detections (median 281 m
  raw, 135 m corrected; the dataset's own ``Distance_error``: 133 m);
- the shipped defaults are those chosen on half A of the fixed split (``choose``);
- on the held-out half B: no wrong match, and the issue's target (>= 95 % of chips matched to
  their own MMSI) on the chips whose AIS report is self-consistent (13 of 13). On all of B the
  target is not met (13 of 18): the 5 others are reports whose ``Time`` disagrees by 109-425 s
  with the time the dataset itself moved them by (``report_check``, from the dataset's fields
  alone) -- ``test_target_on_all_of_half_b`` is a strict expected failure that says so.
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

from sarship.pipeline.ais.match import MatchParams
from tests.pipeline.test_opensarship_ais import GRD_PRODUCTS, OSS

REPO = Path(__file__).resolve().parents[2]

pytestmark = [
    pytest.mark.realdata,
    pytest.mark.skipif(
        not GRD_PRODUCTS, reason=f"OpenSARShip GRD products not found at {OSS} (see shared/data/README.md)"
    ),
]

#: measured (bench/REALDATA.md): half B, all 18 chips: 13 matched with the shipped defaults
B_MATCHED = 13
#: measured: median (c) 135 m over the 37 chips (the dataset's Distance_error: 133 m); under way
#: with a consistent report: max (c) 276 m
MEDIAN_CORRECTED_M = 160.0
MAX_CORRECTED_UNDER_WAY_M = 320.0


def _bench():
    """bench/realdata_ais.py as a module (registered: its dataclasses need it)."""
    if "realdata_ais" not in sys.modules:
        spec = importlib.util.spec_from_file_location("realdata_ais", REPO / "bench" / "realdata_ais.py")
        mod = importlib.util.module_from_spec(spec)
        sys.modules["realdata_ais"] = mod
        spec.loader.exec_module(mod)
    return sys.modules["realdata_ais"]


@pytest.fixture(scope="module")
def bench():
    pytest.importorskip("tifffile")
    return _bench()


@pytest.fixture(scope="module")
def chips(bench, client, tmp_path_factory):
    return bench.load(client, tmp_path_factory.mktemp("ais_match"))


@pytest.fixture(scope="module")
def per_chip(bench, chips):
    """Distances and the report check of each scored chip."""
    return [{**bench.distances(c), **bench.report_check(c)} for c in chips if c.scored]


@pytest.fixture(scope="module")
def shipped(bench, chips):
    """The shipped defaults' match, per scored chip."""
    return bench.match_chips(chips, MatchParams())


def test_corrections_bring_ais_to_the_detections(per_chip):
    assert len(per_chip) == 37
    a, b, c = (np.array([r[k] for r in per_chip]) for k in ("raw_m", "time_m", "time_disp_m"))
    assert np.median(c) < np.median(a) and np.median(c) <= MEDIAN_CORRECTED_M, (np.median(a), np.median(c))
    ds = np.median([r["dataset_m"] for r in per_chip])
    assert abs(np.median(c) - ds) <= 40.0, (np.median(c), ds)
    held_out = [r for r in per_chip if r["half"] == "B"]
    assert np.median([r["time_disp_m"] for r in held_out]) < np.median([r["raw_m"] for r in held_out])
    # ships under way with a self-consistent report: each correction helps, the displacement most
    way = [k for k, r in enumerate(per_chip) if r["sog_kn"] >= 2.0 and r["consistent"]]
    assert len(way) == 18
    assert np.median(c[way]) < np.median(b[way]) < np.median(a[way]), (a[way], b[way], c[way])
    assert c[way].max() <= MAX_CORRECTED_UNDER_WAY_M, c[way]
    # ships at rest: the corrections change nothing that matters
    rest = [k for k, r in enumerate(per_chip) if r["sog_kn"] < 2.0]
    assert np.all(np.abs(c[rest] - a[rest]) <= 15.0), (a[rest], c[rest])


def test_shipped_defaults_are_the_half_a_choice(bench, chips):
    keys = bench.settings()
    chosen = bench.choose(bench.sweep(chips, keys), keys, bench.SHIP_FOLD)
    assert bench.SHIP_FOLD == "A"
    assert chosen == {k: getattr(MatchParams(), k) for k in bench.GRID}, chosen


def test_held_out_half_b(shipped, per_chip):
    consistent = {r["chip"] for r in per_chip if r["consistent"]}
    assert not [r for r in shipped if r["wrong"]], "a detection matched to another ship's MMSI"
    half_a = [r for r in shipped if r["half"] == "A"]
    assert sum(r["ok"] for r in half_a) == len(half_a) == 19  # in-sample: the half it was chosen on
    half_b = [r for r in shipped if r["half"] == "B"]
    assert len(half_b) == 18 and sum(r["ok"] for r in half_b) >= B_MATCHED
    good = [r for r in half_b if r["chip"] in consistent]
    assert len(good) == 13 and sum(r["ok"] for r in good) >= 0.95 * len(good), good
    missed = {r["chip"] for r in half_b if not r["ok"]}
    assert not missed & consistent, missed  # every miss is a report whose Time the dataset contradicts


@pytest.mark.xfail(
    strict=True,
    raises=AssertionError,
    reason="5 of half B's 18 AIS reports carry a Time 109-425 s off the time the dataset itself "
    "moved them by (bench/REALDATA.md, AIS matching on OpenSARShip): 13 of 18 matched",
)
def test_target_on_all_of_half_b(shipped):
    half_b = [r for r in shipped if r["half"] == "B"]
    assert sum(r["ok"] for r in half_b) >= 0.95 * len(half_b)
