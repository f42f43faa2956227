"""Detector registry: name -> :class:`~pipeline.detectors.base.DetectorSpec`."""

from __future__ import annotations

import importlib

from pipeline.detectors.base import DetectorParams, DetectorSpec
from pipeline.errors import InputError

#: Module of each detector, by CONTRACT name.
_MODULES = {
    "two_parameter": "pipeline.detectors.two_parameter",
    "ca_cfar": "pipeline.detectors.ca_cfar",
    "os_cfar": "pipeline.detectors.os_cfar",
    "apwf": "pipeline.detectors.apwf",
    "lmm": "pipeline.detectors.lmm",
    "pcdm": "pipeline.detectors.pcdm",
    "vb_polsar": "pipeline.detectors.vb_polsar",
}


def names() -> list[str]:
    return list(_MODULES)


def get(name: str) -> DetectorSpec:
    """The detector ``name``; :class:`InputError` listing the known ones otherwise."""
    if name not in _MODULES:
        raise InputError(f"unknown detector '{name}' (known: {', '.join(_MODULES)})")
    return importlib.import_module(_MODULES[name]).SPEC


__all__ = ["DetectorParams", "DetectorSpec", "get", "names"]
