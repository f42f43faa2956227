"""What every detector declares: parameters (validated), input, halo, and pure array maths.

A detector is a :class:`DetectorSpec`. Its maths is two pure functions:

``prepare(params) -> dict``
    scene-independent scalars computed once on the client (thresholds from the PFA, ring
    size, ...). They are recorded in ``run.json``.

``detect(block, halo, origin, params, prep) -> (mask, stat)``
    ``block`` is the tile *with its halo*: a 2-D float array of shape
    ``(h + 2*halo, w + 2*halo)`` cut from the mirror-extended scene (numpy ``reflect``
    extension, the seed's choice), whose element ``[0, 0]`` is scene pixel ``origin``
    (row, col; negative inside the mirrored border). It returns the boolean ``mask`` and
    the float32 detector statistic ``stat`` of the ``(h, w)`` core; ``stat > threshold``
    wherever ``mask`` is set. ``stat`` need only be meaningful where ``mask`` is set (it is
    used for the ``score`` of detections).

Results must not depend on where the tile starts: the whole scene processed as one block
and the same scene processed in tiles give bit-identical masks (tests check it). Window
sums therefore use :mod:`sarship.pipeline.boxsum`, whose association order is fixed by global
pixel coordinates.

How to add a detector (module, registry entry, scene pass, GPU twin, tests):
docs/adding-a-detector.md.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Optional

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator


class DetectorParams(BaseModel):
    """Parameters shared by every detector (their names are public: docs/algorithms/README.md)."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True)

    pfa: float = Field(1e-5, gt=0.0, lt=0.5, description="probability of false alarm per pixel")
    target: int = Field(1, ge=1, le=255, description="target window side (odd, pixels)")
    guard: int = Field(41, ge=1, le=511, description="guard window side (odd, pixels)")
    background: int = Field(61, ge=3, le=1023, description="background window side (odd, pixels)")
    looks: Optional[float] = Field(
        None, gt=0.0, le=1e4,
        description="equivalent number of looks; default: the scene's 'looks' attribute",
    )
    min_area_px: int = Field(3, ge=1, description="smallest detection kept, in pixels")
    max_area_px: Optional[int] = Field(None, ge=1, description="largest detection kept, in pixels")
    min_length_m: Optional[float] = Field(None, ge=0.0, description="shortest ship kept (needs pixel spacing)")
    max_length_m: Optional[float] = Field(None, gt=0.0, description="longest ship kept (needs pixel spacing)")
    merge_px: int = Field(2, ge=0, le=64, description="fragments whose gap is at most this many pixels are one ship")

    @model_validator(mode="after")
    def _windows(self):
        for name in ("target", "guard", "background"):
            v = getattr(self, name)
            if v % 2 == 0:
                raise ValueError(f"{name} must be odd, got {v}")
        if self.target > self.guard:
            raise ValueError(f"target ({self.target}) must not exceed guard ({self.guard})")
        if self.guard >= self.background:
            raise ValueError(f"background ({self.background}) must be larger than guard ({self.guard})")
        if self.max_area_px is not None and self.max_area_px < self.min_area_px:
            raise ValueError(f"max_area_px ({self.max_area_px}) must be >= min_area_px ({self.min_area_px})")
        if (self.min_length_m is not None and self.max_length_m is not None
                and self.max_length_m < self.min_length_m):
            raise ValueError(f"max_length_m ({self.max_length_m}) must be >= min_length_m ({self.min_length_m})")
        return self

    @property
    def n_ring(self) -> int:
        """Number of clutter cells in the ring between guard and background windows."""
        return self.background**2 - self.guard**2


def check_windows(halo: int, *sides: int) -> None:
    """Each window side must be odd and fit in the block's halo (``side // 2 <= halo``)."""
    for m in sides:
        if m % 2 != 1:
            raise ValueError(f"window side must be odd, got {m}")
        if m // 2 > halo:
            raise ValueError(f"window {m} needs a halo of {m // 2}, block has {halo}")


def float_block(block: np.ndarray, ndim: int = 2) -> np.ndarray:
    """A C-contiguous float32/float64 view or copy of a detector's input block."""
    block = np.asarray(block)
    if block.ndim != ndim:
        raise ValueError(f"block must be {ndim}-D, got shape {block.shape}")
    if block.dtype != np.float32 and block.dtype != np.float64:
        block = block.astype(np.float64)
    return np.ascontiguousarray(block)


def with_defaults(base: type[DetectorParams], name: str, **defaults: Any) -> type[DetectorParams]:
    """A subclass of ``base`` whose listed fields have other defaults (constraints kept).

    Detectors tune their own defaults (see ``bench/REALDATA.md``) while sharing one
    definition, with its bounds and validators, of every shared parameter.
    """
    from pydantic import create_model
    from pydantic.fields import FieldInfo

    fields = {}
    for key, value in defaults.items():
        f = base.model_fields[key]
        fields[key] = (f.annotation, FieldInfo.merge_field_infos(f, default=value))
    return create_model(name, __base__=base, **fields)


@dataclass(frozen=True)
class DetectorSpec:
    """A detector: name, parameter model, input, halo rule and its pure maths."""

    name: str
    summary: str
    reference: str
    params: type[DetectorParams]
    prepare: Callable[[Any], dict]
    detect: Callable[..., tuple[np.ndarray, np.ndarray]]
    input: str = "intensity"  # the scene quantity the detector reads (see pipeline.inputs)
    needs_looks: bool = False
    #: Scene-wide statistics before detection (two passes): ``scene_pass(block, halo,
    #: origin, params, prep) -> dict`` runs on every tile (same block as ``detect``), and
    #: ``reduce(list_of_dicts, params, prep) -> dict`` combines them; the result is merged
    #: into ``prep`` before ``detect`` runs, so every tile sees the same scene-wide values.
    scene_pass: Optional[Callable[..., dict]] = None
    reduce: Optional[Callable[..., dict]] = None
    #: ``halo_fn(params) -> int`` for detectors whose context is not ``background // 2``.
    halo_fn: Optional[Callable[[Any], int]] = None
    halo_rule: str = "background // 2"
    #: ``detect`` (and ``scene_pass``) accept a CuPy block and run on its GPU
    #: (:mod:`sarship.pipeline.gpu`); otherwise GPU workers run the CPU code for this detector.
    gpu: bool = False
    #: with ``gpu``: the scene pass runs on the device too (else on the host block)
    scene_pass_gpu: bool = True

    def halo(self, params: DetectorParams) -> int:
        """Pixels of context each side of a tile: half the largest window by default."""
        if self.halo_fn is not None:
            return int(self.halo_fn(params))
        return int(params.background) // 2

    def describe(self) -> dict:
        schema = self.params.model_json_schema()
        defaults = {k: f.default for k, f in self.params.model_fields.items()}
        return {
            "name": self.name,
            "summary": self.summary,
            "reference": self.reference,
            "input": self.input,
            "halo": self.halo_rule,
            "scene_wide_pass": self.scene_pass is not None,
            "gpu": self.gpu,
            "halo_default_px": self.halo(self.params()),
            "parameters": schema.get("properties", {}),
            "defaults": defaults,
        }
