"""``ggd_cfar``: CFAR on generalized-gamma (GGD) intensity, parameters by the method of
log-cumulants on the ring, closed-form incomplete-gamma threshold (docs/algorithms/g0_k_ggd.md).

Baseline of Liu et al. 2017 (docs/references.md#liu2017, seed 003: GGD-CFAR at PFA 1e-3). Model:
Stacy 1962, Li et al. 2011 ((x / sigma)^v kappa ~ Gamma(kappa)); MoLC: Li et al. 2011. Per
pixel, the ring's k1, k2, k3 (eq 1 of :mod:`sarship.pipeline.stats.molc`) give the skewness of ln x,
g1 = k3 / k2^{3/2}, which fixes kappa and sign(v) (eq 7); the threshold is
ln t = k1 + sqrt(k2) D(g1) (eq 8), D from the incomplete-gamma inverses, tabulated per pfa.
The number of looks is not used (the GGD's own shape absorbs it). Statistic: x / t.
"""

from __future__ import annotations

from sarship.pipeline.detectors import molc_cfar
from sarship.pipeline.detectors.base import DetectorSpec, check_windows
from sarship.pipeline.detectors.g0_cfar import MolcParams, halo_of
from sarship.pipeline.stats import molc


class GGDParams(MolcParams):
    """Parameters of ``ggd_cfar`` (shared ones: docs/algorithms/README.md; ``looks`` unused)."""


def prepare(p: GGDParams) -> dict:
    tab = molc.ggd_table(float(p.pfa))
    return {
        "n_ring": p.n_ring,
        "threshold": 1.0,
        "min_ring": molc_cfar.min_ring(p.n_ring),
        "statistic": "x / t, t the GGD MoLC threshold of the ring (eqs 1, 7, 8)",
        "table": {"variable": "g1 = k3 / k2^1.5", "function": "D = (ln t - k1) / sqrt(k2)", **tab.summary()},
    }


def detect(block, halo: int, origin: tuple[int, int], p: GGDParams, prep: dict):
    """(mask, x / t) of the tile's core; a CuPy block runs on its GPU (pipeline.gpu.molc)."""
    b, g = int(p.background), int(p.guard)
    check_windows(halo, b, g)
    tab = molc.ggd_table(float(p.pfa))
    return molc_cfar.detect_block(block, halo, origin, b, g, p.censor, "ggd", tab, 1.0)


SPEC = DetectorSpec(
    name="ggd_cfar",
    summary="Generalized-gamma intensity CFAR: ring log-cumulants (MoLC), incomplete-gamma threshold",
    reference="Liu et al. 2017 (baseline); Li et al. 2011; Qin et al. 2013; docs/algorithms/g0_k_ggd.md",
    params=GGDParams,
    prepare=prepare,
    detect=detect,
    input="intensity",
    needs_looks=False,
    halo_fn=halo_of,
    halo_rule="background // 2 (2 x (background // 2) with censor)",
    gpu=molc_cfar.GPU_TWIN,
)
