"""Issue 12: ``pfa`` is bounded to what float64 thresholds can honour. ``pfa: 1e-320`` was
accepted (201) and the job failed with an internal JSON error (an infinite threshold): every
detector refuses a pfa below :data:`PFA_MIN`, and at PFA_MIN every detector's prepared
values are finite JSON."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest
from pydantic import ValidationError

from sarship.pipeline import detectors
from sarship.pipeline.detectors.base import PFA_MIN


def _spec(name):
    return detectors.get(name)


@pytest.mark.parametrize("name", detectors.names())
def test_every_detector_refuses_a_pfa_below_the_floor_and_is_finite_at_it(name):
    spec = _spec(name)
    extra = {"looks": 2.0} if "looks" in spec.params.model_fields else {}
    for bad in (1e-320, PFA_MIN / 2, 0.0, -1e-3):
        with pytest.raises(ValidationError, match="pfa"):
            spec.params(pfa=bad, **extra)
    prep = spec.prepare(spec.params(pfa=PFA_MIN, **extra))
    json.dumps(prep, allow_nan=False, default=str)  # a non-finite threshold would raise here


def test_cli_refuses_tiny_pfa_in_one_line(tmp_path):
    import numpy as np
    from conftest import write_scene

    scene = write_scene(tmp_path / "s.zarr", {"intensity": np.ones((32, 32), np.float32)}, tile=32, looks=1.0)
    res = subprocess.run(
        [
            sys.executable,
            "-m",
            "sarship",
            "detect",
            str(scene),
            "--detector",
            "ca_cfar",
            "--out",
            str(tmp_path / "o"),
            "--set",
            "pfa=1e-320",
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert res.returncode == 2 and "pfa" in res.stderr and "1e-15" in res.stderr, res.stderr
    assert len(res.stderr.strip().splitlines()) == 1 and not (tmp_path / "o").exists()
