"""pipeline/stats/tails.py: the CFAR threshold quantiles from scipy.special, against closed forms in the
far tail and against scipy.stats; and the command's import path stays free of scipy.stats (its
import costs every ``sarship`` command about 0.45 s: issue 17)."""

from __future__ import annotations

import math
import subprocess
import sys

import pytest
from scipy import stats

from sarship.pipeline.stats.tails import f_isf, norm_isf, t_isf

PFAS = [1e-1, 1e-3, 1e-5, 1e-7, 1e-9, 1e-12]


@pytest.mark.parametrize("p", PFAS)
@pytest.mark.parametrize("d2", [20.0, 2480.0, 42944.0, 1e6])
def test_f_isf_closed_form_of_f2(p, d2):
    # F(2, d2): P(F > x) = (1 + 2x/d2)^(-d2/2)  =>  x = d2/2 (p^(-2/d2) - 1)
    exact = d2 / 2 * math.expm1(-2.0 / d2 * math.log(p))
    assert f_isf(p, 2.0, d2) == pytest.approx(exact, rel=1e-13)


@pytest.mark.parametrize("p", PFAS)
def test_t_isf_closed_forms(p):
    assert t_isf(p, 1.0) == pytest.approx(1.0 / math.tan(math.pi * p), rel=1e-12)  # Cauchy: cot(pi p)
    assert t_isf(p, 2.0) == pytest.approx((1 - 2 * p) / math.sqrt(2 * p * (1 - p)), rel=1e-12)


def test_norm_isf_known_values():
    assert norm_isf(0.5) == 0.0
    assert norm_isf(1e-5) == pytest.approx(4.264890793922825, rel=1e-14)
    assert norm_isf(1e-9) == pytest.approx(5.997807015007686, rel=1e-14)


@pytest.mark.parametrize("p", PFAS)
def test_agree_with_scipy_stats(p):
    for d1 in (2.0, 8.8, 50.0, 79.2):
        for d2 in (20.0, 2480.0, 42944.0, 12800.0):
            assert f_isf(p, d1, d2) == pytest.approx(stats.f.isf(p, d1, d2), rel=1e-5)
    for df in (3, 10, 1239, 10000):
        assert t_isf(p, df) == pytest.approx(stats.t.isf(p, df), rel=1e-12)
    assert norm_isf(p) == pytest.approx(stats.norm.isf(p), rel=1e-14)


def test_command_path_does_not_import_scipy_stats():
    code = (
        "import sys, sarship.cli, sarship.workers.jobs, sarship.pipeline.detectors as d; "
        "[d.get(n) for n in d.names()]; "
        "print(sorted(m for m in ('scipy.stats', 'scipy.optimize', 'scipy.interpolate') if m in sys.modules))"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "[]", r.stdout
