"""CA-CFAR and two-parameter CFAR: exact thresholds, calibration, agreement with brute force.

Calibration bound. On M independent clutter pixels the false-alarm count K has mean M*p;
CFAR decisions of neighbouring pixels share ring cells, which adds a small positive
correlation (measured here: variance/mean = 0.8-1.1 over 12 seeds for N = 1240), so we
allow a variance of up to 1.5 * M*p and accept |K - M p| <= 5 * sqrt(1.5 * M p) (about
9.5 % of M p for M = 4.2 Mpx, p = 1e-3: a two-sided tail far below 1e-5 even with the
inflation). Each test also shows the bound *can* fail: the threshold a tool gets by
ignoring the estimation noise of the ring mean lands outside it.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from sarship.pipeline.detectors import ca_cfar, two_parameter
from sarship.pipeline.tiling.windows import mirror_pad

M_SIDE = 2048


def within_bound(count: int, m: int, pfa: float) -> bool:
    mu = m * pfa
    return abs(count - mu) <= 5.0 * np.sqrt(1.5 * mu)


def run_whole(mod, x, p):
    prep = mod.prepare(p)
    h = p.background // 2
    mask, stat = mod.detect(mirror_pad(x, h), h, (-h, -h), p, prep)
    return mask, stat, prep


@pytest.mark.parametrize("looks", [1, 4])
def test_ca_cfar_false_alarm_rate_matches_pfa(looks):
    rng = np.random.default_rng(100 + looks)
    x = rng.gamma(looks, 1.0 / looks, (M_SIDE, M_SIDE)).astype(np.float32)
    p = ca_cfar.CAParams(pfa=1e-3, guard=21, background=41, looks=float(looks))
    mask, _, prep = run_whole(ca_cfar, x, p)
    count = int(mask.sum())
    assert within_bound(count, x.size, p.pfa), (count, x.size * p.pfa)
    # the bound can fail: a threshold 25 % off in PFA lands outside it
    _, stat, _ = run_whole(ca_cfar, x, p)
    off = ca_cfar.threshold(1.25 * p.pfa, looks, p.n_ring)
    assert not within_bound(int((stat > off).sum()), x.size, p.pfa)


def test_ca_cfar_small_ring_needs_exact_threshold():
    """N = 96 ring cells: the large-N gamma quantile threshold (ignoring the noise of the
    ring mean) overshoots the PFA; the exact F threshold does not."""
    rng = np.random.default_rng(11)
    x = rng.exponential(1.0, (M_SIDE, M_SIDE)).astype(np.float32)
    p = ca_cfar.CAParams(pfa=1e-3, guard=5, background=11, looks=1.0)
    mask, stat, prep = run_whole(ca_cfar, x, p)
    assert within_bound(int(mask.sum()), x.size, p.pfa), int(mask.sum())
    naive = stats.gamma.isf(p.pfa, 1.0)
    assert not within_bound(int((stat > naive).sum()), x.size, p.pfa)


def test_ca_cfar_matches_brute_force_and_target_window():
    rng = np.random.default_rng(3)
    x = rng.gamma(2.0, 0.5, (40, 33)).astype(np.float32)
    for target in (1, 3):
        p = ca_cfar.CAParams(pfa=1e-2, target=target, guard=5, background=11, looks=2.0, min_area_px=1)
        mask, stat, prep = run_whole(ca_cfar, x, p)
        P = mirror_pad(x.astype(np.float64), 5)
        ref = np.empty(x.shape)
        for i in range(x.shape[0]):
            for j in range(x.shape[1]):
                w = P[i : i + 11, j : j + 11]
                ring = w.sum() - w[3:8, 3:8].sum()
                t = target // 2
                xt = w[5 - t : 6 + t, 5 - t : 6 + t].mean()
                ref[i, j] = xt / (ring / 96.0)
        np.testing.assert_allclose(stat, ref, rtol=1e-5)
        np.testing.assert_array_equal(mask, ref > prep["threshold"])
        assert prep["threshold"] == pytest.approx(stats.f.isf(1e-2, 2 * 2 * target**2, 2 * 2 * 96))


def test_two_parameter_exact_on_gaussian_data():
    rng = np.random.default_rng(7)
    x = rng.normal(10.0, 2.0, (M_SIDE, M_SIDE)).astype(np.float32)
    # a small ring (N = 96) makes the difference between exact and classical thresholds large
    p = two_parameter.TwoParameterParams(pfa=1e-3, guard=5, background=11)
    mask, stat, prep = run_whole(two_parameter, x, p)
    assert within_bound(int(mask.sum()), x.size, p.pfa), int(mask.sum())
    classical = two_parameter.threshold(p.pfa, p.n_ring, 1, "gaussian")
    assert classical < prep["threshold"]
    assert not within_bound(int((stat > classical).sum()), x.size, p.pfa)


def test_two_parameter_target_window_correction():
    """Target mean of n cells: the t/sqrt(n) rule holds the PFA; the uncorrected one does not."""
    rng = np.random.default_rng(8)
    x = rng.normal(0.0, 1.0, (M_SIDE, M_SIDE)).astype(np.float32)
    p = two_parameter.TwoParameterParams(pfa=1e-3, target=3, guard=9, background=41)
    mask, stat, prep = run_whole(two_parameter, x, p)
    assert within_bound(int(mask.sum()), x.size, p.pfa), int(mask.sum())
    uncorrected = stats.norm.isf(p.pfa)  # SNAP: mu + t sigma with the target mean
    assert int((stat > uncorrected).sum()) < 0.01 * x.size * p.pfa


def test_two_parameter_matches_brute_force():
    rng = np.random.default_rng(9)
    x = rng.gamma(1.0, 1.0, (30, 37)).astype(np.float32)
    for domain in ("intensity", "amplitude", "db"):
        p = two_parameter.TwoParameterParams(pfa=1e-2, guard=3, background=9, domain=domain)
        mask, stat, prep = run_whole(two_parameter, x, p)
        y = {
            "intensity": x.astype(np.float64),
            "amplitude": np.sqrt(x.astype(np.float64)),
            "db": 10 * np.log10(x.astype(np.float64)),
        }[domain]
        P = mirror_pad(y, 4)
        ref = np.empty(x.shape)
        for i in range(x.shape[0]):
            for j in range(x.shape[1]):
                w = P[i : i + 9, j : j + 9].copy()
                ringv = np.concatenate([w[:3].ravel(), w[6:].ravel(), w[3:6, :3].ravel(), w[3:6, 6:].ravel()])
                ref[i, j] = (w[4, 4] - ringv.mean()) / ringv.std(ddof=1)
        np.testing.assert_allclose(stat, ref, rtol=1e-4, atol=1e-5)
