"""``k_cfar``: CFAR on K-distributed intensity, parameters by the method of log-cumulants on the
ring, threshold by numerical inversion of the K tail on a proven bracket
(docs/algorithms/g0_k_ggd.md).

Baseline of Liu et al. 2017 (docs/references.md#liu2017, seed 003). Model: Jakeman & Pusey 1976,
Oliver & Quegan 1998 (x = mu (G / nu)(S / L), gamma texture times L-look speckle); MoLC:
Nicolas 2002, Tison et al. 2004. Per pixel, u = k2 - psi_1(L) = psi_1(nu) and mu (eq 4 of
:mod:`sarship.pipeline.stats.molc`); the tail P(x > mu tau) (eq 5, an integral over the texture) is
inverted for tau on the bracket of eq 6, and ln t - k1 = H(u) is tabulated per (pfa, L).
Statistic: x / t.
"""

from __future__ import annotations

from sarship.pipeline.detectors import molc_cfar
from sarship.pipeline.detectors.base import DetectorSpec, check_windows
from sarship.pipeline.detectors.g0_cfar import MolcParams, halo_of
from sarship.pipeline.stats import molc


class KParams(MolcParams):
    """Parameters of ``k_cfar`` (shared ones: docs/algorithms/README.md), PFA 1e-3 as in the seed."""


def prepare(p: KParams) -> dict:
    if p.looks is None:
        raise ValueError("looks must be resolved before prepare()")
    tab = molc.k_table(float(p.pfa), float(p.looks))
    return {
        "n_ring": p.n_ring,
        "looks": float(p.looks),
        "threshold": 1.0,
        "min_ring": molc_cfar.min_ring(p.n_ring),
        "statistic": "x / t, t the K MoLC threshold of the ring (eqs 1, 4-6)",
        "table": {"variable": "w = ln(1 + k2 - psi_1(L))", "function": "H = ln t - k1", **tab.summary()},
    }


def detect(block, halo: int, origin: tuple[int, int], p: KParams, prep: dict):
    """(mask, x / t) of the tile's core; a CuPy block runs on its GPU (pipeline.gpu.molc)."""
    b, g = int(p.background), int(p.guard)
    check_windows(halo, b, g)
    looks = float(prep["looks"])
    tab = molc.k_table(float(p.pfa), looks)
    return molc_cfar.detect_block(block, halo, origin, b, g, p.censor, "k", tab, looks)


SPEC = DetectorSpec(
    name="k_cfar",
    summary="K intensity CFAR: ring log-cumulants (MoLC), K tail inverted on a proven bracket",
    reference="Liu et al. 2017 (baseline); Jakeman & Pusey 1976; Tison et al. 2004; docs/algorithms/g0_k_ggd.md",
    params=KParams,
    prepare=prepare,
    detect=detect,
    input="intensity",
    needs_looks=True,
    halo_fn=halo_of,
    halo_rule="background // 2 (2 x (background // 2) with censor)",
    gpu=molc_cfar.GPU_TWIN,
)
