"""Detector registry: name -> :class:`~sarship.pipeline.detectors.base.DetectorSpec`."""

from __future__ import annotations

import importlib

from sarship.pipeline.detectors.base import DetectorParams, DetectorSpec
from sarship.pipeline.errors import InputError

#: Module of each detector, by its public name (docs/algorithms/README.md).
_MODULES = {
    "two_parameter": "sarship.pipeline.detectors.two_parameter",
    "ca_cfar": "sarship.pipeline.detectors.ca_cfar",
    "os_cfar": "sarship.pipeline.detectors.os_cfar",
    "apwf": "sarship.pipeline.detectors.apwf",
    "lmm": "sarship.pipeline.detectors.lmm",
    "pcdm": "sarship.pipeline.detectors.pcdm",
    "vb_polsar": "sarship.pipeline.detectors.vb_polsar",
    "gamma_mrf": "sarship.pipeline.detectors.gamma_mrf",
    "g0_cfar": "sarship.pipeline.detectors.g0_cfar",
    "k_cfar": "sarship.pipeline.detectors.k_cfar",
    "ggd_cfar": "sarship.pipeline.detectors.ggd_cfar",
    "csk": "sarship.pipeline.detectors.csk",
    "superpixel_cfar": "sarship.pipeline.detectors.superpixel_cfar",
}


def names() -> list[str]:
    return list(_MODULES)


def get(name: str) -> DetectorSpec:
    """The detector ``name``; :class:`InputError` listing the known ones otherwise."""
    if name not in _MODULES:
        raise InputError(f"unknown detector '{name}' (known: {', '.join(_MODULES)})")
    return importlib.import_module(_MODULES[name]).SPEC


__all__ = ["DetectorParams", "DetectorSpec", "get", "names"]
