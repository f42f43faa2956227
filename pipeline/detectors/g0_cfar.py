"""``g0_cfar``: CFAR on G0-distributed intensity, parameters by the method of log-cumulants on
the ring, closed-form threshold (docs/algorithms/g0_k_ggd.md).

Baseline of Liu et al. 2017 (docs/references.md#liu2017, seed 003: G0-CFAR at PFA 1e-3 with a
land mask and bright-pixel censoring). Model: Frery et al. 1997 (G0 intensity, x = (gamma / L)
S / G); MoLC: Nicolas 2002, Tison et al. 2004. Per pixel, the ring's log-cumulants k1, k2
(eq 1 of :mod:`sarship.pipeline.stats.molc`) give u = k2 - psi_1(L) = psi_1(a) and
gamma (eq 2); the threshold t solves P(x > t) = pfa in closed form through the Beta quantile
(eq 3), tabulated as ln t - k1 = H(u). Statistic: x / t (> 1 is a detection).
"""

from __future__ import annotations

from pydantic import Field, model_validator

from sarship.pipeline.detectors import molc_cfar
from sarship.pipeline.detectors.base import DetectorParams, DetectorSpec, check_windows, with_defaults
from sarship.pipeline.stats import molc

CENSOR_HELP = (
    "bright-pixel censoring of the ring: a ring sample brighter than CENSOR x the mean of its own "
    "background-size window is left out of the fit (halo grows to 2 x (background // 2)); "
    "unset: off (the calibrated default; docs/algorithms/g0_k_ggd.md)"
)


class MolcParams(with_defaults(DetectorParams, "MolcDefaults", pfa=1e-3, guard=41, background=81, land_mask="texture")):
    """The parameters of the three MoLC CFARs (``g0_cfar``, ``k_cfar``, ``ggd_cfar``; shared ones:
    docs/algorithms/README.md): PFA 1e-3 and the sea-land segmentation as in the seed (the land
    mask raised the held-out real-chip scores of all three on both folds, bench/REALDATA.md), the
    optional censoring, single-pixel targets."""

    censor: float | None = Field(None, gt=1.0, le=1e6, description=CENSOR_HELP)

    @model_validator(mode="after")
    def _single_pixel_target(self):
        if self.target != 1:
            raise ValueError(f"target must be 1 for this detector (it tests single pixels), got {self.target}")
        return self


class G0Params(MolcParams):
    """Parameters of ``g0_cfar``."""


def halo_of(p) -> int:
    """background // 2, or 2 (background // 2) with censoring."""
    b = int(p.background)
    return molc_cfar.censor_halo(b) if p.censor is not None else b // 2


def prepare(p: G0Params) -> dict:
    if p.looks is None:
        raise ValueError("looks must be resolved before prepare()")
    tab = molc.g0_table(float(p.pfa), float(p.looks))
    return {
        "n_ring": p.n_ring,
        "looks": float(p.looks),
        "threshold": 1.0,
        "min_ring": molc_cfar.min_ring(p.n_ring),
        "statistic": "x / t, t the G0 MoLC threshold of the ring (eqs 1-3)",
        "table": {"variable": "w = ln(1 + k2 - psi_1(L))", "function": "H = ln t - k1", **tab.summary()},
    }


def detect(block, halo: int, origin: tuple[int, int], p: G0Params, prep: dict):
    """(mask, x / t) of the tile's core; a CuPy block runs on its GPU (pipeline.gpu.molc)."""
    b, g = int(p.background), int(p.guard)
    check_windows(halo, b, g)
    looks = float(prep["looks"])
    tab = molc.g0_table(float(p.pfa), looks)
    return molc_cfar.detect_block(block, halo, origin, b, g, p.censor, "g0", tab, looks)


SPEC = DetectorSpec(
    name="g0_cfar",
    summary="G0 intensity CFAR: ring log-cumulants (MoLC), closed-form Beta-quantile threshold",
    reference="Liu et al. 2017 (baseline); Frery et al. 1997; Tison et al. 2004; docs/algorithms/g0_k_ggd.md",
    params=G0Params,
    prepare=prepare,
    detect=detect,
    input="intensity",
    needs_looks=True,
    halo_fn=halo_of,
    halo_rule="background // 2 (2 x (background // 2) with censor)",
    gpu=molc_cfar.GPU_TWIN,
)
