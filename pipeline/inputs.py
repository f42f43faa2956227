"""The quantity a detector reads from a scene, cut out tile by tile.

Single-channel detectors (``two_parameter``, ``ca_cfar``, ``os_cfar``) read intensity:
the scene's ``intensity`` variable, else |S|^2 of a complex channel (``hh`` first, then
``vv``, ``vh``, ``hv``), else the covariance diagonal ``c11``. The ``channel`` parameter
(any scene variable) overrides the choice.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from pipeline.errors import InputError
from pipeline.scene import Scene

_PREFERENCE = ("intensity", "hh", "vv", "vh", "hv", "c11")


def intensity_source(scene: Scene, channel: str | None = None) -> tuple[str, str]:
    """``(variable, transform)`` giving intensity; transform is ``real`` or ``abs2``."""
    if channel is not None:
        if channel not in scene.variables:
            raise InputError(
                f"parameter 'channel': scene has no variable '{channel}' (has: {', '.join(scene.variables)})"
            )
        var = channel
    else:
        var = next((v for v in _PREFERENCE if v in scene.variables), None)
        if var is None:
            raise InputError(
                f"scene '{scene.path}' has no intensity, complex channel or c11 variable "
                f"(has: {', '.join(scene.variables)})"
            )
    transform = "abs2" if "complex" in scene.variables[var] else "real"
    return var, transform


def make_reader(path: str, var: str, transform: str) -> Callable[[int, int, int, int], np.ndarray]:
    """``read(ra, rb, ca, cb)`` -> float32 intensity of the scene rectangle."""
    import zarr

    arr = zarr.open_array(f"{path}/{var}", mode="r")

    def read(ra: int, rb: int, ca: int, cb: int) -> np.ndarray:
        a = arr[ra:rb, ca:cb]
        if transform == "abs2":
            return (a.real.astype(np.float32) ** 2 + a.imag.astype(np.float32) ** 2).astype(np.float32)
        return np.asarray(a, dtype=np.float32)

    return read
