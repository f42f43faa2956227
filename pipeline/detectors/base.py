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
sums therefore use :mod:`sarship.pipeline.tiling.boxsum`, whose association order is fixed by global
pixel coordinates.

How to add a detector (module, registry entry, scene pass, GPU twin, tests):
docs/adding-a-detector.md.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

AREA_HELP = (
    "smallest detection kept, in pixels; unset: automatic (the size rule): the detector's pixel "
    "default when the scene's pixel spacing is unknown, else the pixel count of the detector's "
    "smallest area in square metres, with min_length_m ('sarship detectors --json': size_defaults)"
)
LENGTH_HELP = (
    "shortest ship kept, in metres (needs the scene's pixel spacing); unset: automatic (the size "
    "rule): the detector's default length when the spacing is known and min_area_px is unset; "
    "0 turns it off"
)


#: Defaults of the line rule (pipeline/targets/lines.py): the gap chosen on half A of the shared chips
#: (bench/REALDATA.md, "Issue 31: kept-detection masks and line discrimination"; the angle and
#: the dominance setting made no difference there and keep their prior values).
LINE_GAP_PX = 16
LINE_ANGLE_DEG = 10.0
LINE_DOMINANT_DB = 10.0

#: Smallest ``pfa`` accepted: every detector's threshold is a finite float64 down to it (checked
#: by tests/service/test_pfa_bounds.py); below it a request is refused (a pfa of 1e-320 is not a
#: probability any threshold can honour: subnormal, its quantiles overflow).
PFA_MIN = 1e-15


class DetectorParams(BaseModel):
    """Parameters shared by every detector (their names are public: docs/algorithms/README.md).

    Every float parameter of every detector must be finite (``allow_inf_nan=False``): NaN,
    ``Infinity``, a JSON ``1e999`` (which parses to infinity) and strings such as ``"nan"`` or
    ``"inf"`` are refused when the parameters are parsed, naming the parameter. None of them
    has a meaning no finite value or None already gives: ``nodata`` NaN or infinity would mark
    what is always absent (non-finite pixels are never data), an infinite ``max_length_m`` or
    ``max_elongation`` is None (no limit).
    """

    model_config = ConfigDict(extra="forbid", validate_assignment=True, allow_inf_nan=False)

    pfa: float = Field(
        1e-5, ge=PFA_MIN, lt=0.5, description=f"probability of false alarm per pixel ({PFA_MIN:g} to 0.5)"
    )
    target: int = Field(1, ge=1, le=255, description="target window side (odd, pixels)")
    guard: int = Field(41, ge=1, le=511, description="guard window side (odd, pixels)")
    background: int = Field(61, ge=3, le=1023, description="background window side (odd, pixels)")
    looks: float | None = Field(
        None,
        gt=0.0,
        le=1e4,
        description="equivalent number of looks; default: the scene's 'looks' attribute",
    )
    #: The automatic size rule (:func:`resolve_size`), per detector: with ``min_area_px`` and
    #: ``min_length_m`` both unset, a scene whose pixel spacing is known keeps components at
    #: least ``auto_min_length_m`` metres long and ``auto_min_area_m2`` square metres large
    #: (as a pixel count: ``min_area_px`` = ceil(auto_min_area_m2 / pixel area), at least 1);
    #: a scene without spacing keeps components of at least ``auto_min_area_px`` pixels.
    auto_min_area_px: ClassVar[int] = 10
    auto_min_length_m: ClassVar[float] = 20.0
    auto_min_area_m2: ClassVar[float] = 200.0

    min_area_px: int | None = Field(None, ge=1, description=AREA_HELP)
    max_area_px: int | None = Field(None, ge=1, description="largest detection kept, in pixels")
    min_length_m: float | None = Field(None, ge=0.0, description=LENGTH_HELP)
    max_length_m: float | None = Field(None, gt=0.0, description="longest ship kept (needs pixel spacing)")
    max_elongation: float | None = Field(
        15.0,
        ge=1.0,
        description="longest length / width kept (moment length and width, in metres when the pixel "
        "spacing is known): ships are at most ~11 times as long as wide, so a thinner "
        "detection is a wake, a line or a structure; None keeps every shape",
    )
    min_contrast_db: float | None = Field(
        None,
        ge=-30.0,
        le=60.0,
        description="drop detections whose local contrast contrast_db (mean power over the mean power of the clutter "
        "ring around them, land and detections left out; pipeline/targets/local_contrast.py) is below this many "
        "dB, measured only when set (-30 measures every detection, dropping practically none); None keeps "
        "every detection (default: the detector's; 7 for superpixel_cfar)",
    )
    merge_px: int = Field(2, ge=0, le=64, description="fragments whose gap is at most this many pixels are one ship")
    # discrimination of lines, smear and land edges (pipeline/targets/lines.py, docs/algorithms/discrimination.md)
    line_gap_px: int | None = Field(
        LINE_GAP_PX,
        ge=0,
        le=256,
        description="lines: collinear detections (same orientation within line_angle_deg, one's end within this many "
        "pixels of the next one's along their common axis) are joined into one object before the "
        "max_elongation / max_length_m test, which drops the pieces of a line together; None turns the "
        "join off",
    )
    line_angle_deg: float = Field(
        LINE_ANGLE_DEG, ge=0.0, le=45.0, description="lines: largest orientation difference (degrees) of joined pieces"
    )
    line_dominant_db: float | None = Field(
        LINE_DOMINANT_DB,
        ge=0.0,
        le=60.0,
        description="lines: a piece whose peak is at least this many dB above the median peak of the rest of its line "
        "is a ship with its smear or wake: kept (the rest dropped); None keeps no piece of a line",
    )
    land_gap_px: int | None = Field(
        None,
        ge=0,
        le=1000,
        description="land edges: drop detections with land within this many pixels of their bounding box (0: "
        "touching it), where a land mask is in use; None (default) keeps them (ships moored at quays)",
    )
    sidelobes: bool = Field(
        True,
        description="cross-sidelobe suppression: length, width and heading measured on the "
        "ship core where a sidelobe cross is found (docs/algorithms/sidelobes.md)",
    )
    # azimuth-ambiguity flags (pipeline/targets/ambiguity.py, docs/algorithms/ambiguity.md; defaults = its DEFAULT_*)
    ambiguities: bool = Field(
        True,
        description="flag detections that are azimuth ambiguities (ghosts) of a brighter "
        "detection: property ambiguity_of (docs/algorithms/ambiguity.md)",
    )
    ambiguity_tol_px: float = Field(
        8.0,
        ge=0.0,
        le=1000.0,
        description="ambiguities: tolerance in pixels between a detection and a brighter "
        "one's expected ghost position (range: plus the TOPS spread)",
    )
    ambiguity_min_db: float = Field(
        10.0, ge=0.0, le=60.0, description="ambiguities: a ghost's peak is at least this many dB below its parent's"
    )
    # sea-land segmentation (pipeline/land/landmask.py, docs/algorithms/landmask.md): land pixels are
    # absent (NaN) for the detector: never tested, in no clutter ring, in no scene-wide statistic
    land_mask: str | None = Field(
        None,
        min_length=1,
        max_length=4096,
        description="land mask: none, texture (local amplitude variance + Gaussian mixture, "
        "sea = the low-texture class), coastline (the GSHHG shoreline on a georeferenced scene, "
        "widened by land_buffer_m; extra 'coastline'), coastline+texture (their union), or a FILE: a raster of the scene's shape (GeoTIFF, PNG, "
        ".npy, Zarr; non-zero = land) or GeoJSON polygons (lon/lat, or scene pixels with "
        '"pixel_coordinates": true); default: the detector\'s (texture for ca_cfar, os_cfar, '
        "two_parameter, g0_cfar, k_cfar, ggd_cfar, gamma_mrf and superpixel_cfar; none for the "
        "others)",
    )
    land_buffer_m: float = Field(
        250.0,
        ge=0.0,
        le=5000.0,
        description="land_mask=coastline: the GSHHG land is widened by this many metres (pixels within it of land "
        "are land too; the shoreline's position error at its 1:250 000 scale, docs/algorithms/landmask.md)",
    )
    land_window: int = Field(15, ge=3, le=101, description="land_mask=texture: texture window side (odd, pixels)")
    land_classes: int = Field(
        2, ge=2, le=6, description="land_mask=texture: Gaussian mixture classes (sea = lowest texture)"
    )
    land_open_px: int = Field(
        51,
        ge=1,
        le=255,
        description="land_mask=texture: opening square side (odd, pixels): land narrower "
        "than this (e.g. a ship's texture) is sea",
    )
    land_close_px: int = Field(
        5,
        ge=1,
        le=255,
        description="land_mask=texture: closing square side (odd, pixels): sea gaps "
        "narrower than this inside land are land",
    )

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
        for name in ("land_window", "land_open_px", "land_close_px"):
            v = getattr(self, name)
            if v % 2 == 0:
                raise ValueError(f"{name} must be odd, got {v}")
        if self.land_mask is not None:
            self.__dict__["land_mask"] = normalize_land_mask(self.land_mask)
        if self.max_area_px is not None and self.min_area_px is not None and self.max_area_px < self.min_area_px:
            raise ValueError(f"max_area_px ({self.max_area_px}) must be >= min_area_px ({self.min_area_px})")
        if self.min_length_m is not None and self.max_length_m is not None and self.max_length_m < self.min_length_m:
            raise ValueError(f"max_length_m ({self.max_length_m}) must be >= min_length_m ({self.min_length_m})")
        return self

    @property
    def n_ring(self) -> int:
        """Number of clutter cells in the ring between guard and background windows."""
        return self.background**2 - self.guard**2


#: The keyword land masks (``land_mask``); several joined by ``+`` are their union
#: (docs/algorithms/landmask.md). Any other value is a FILE.
LAND_KEYWORDS = ("coastline", "texture")


def land_mask_parts(value: str | None) -> tuple[frozenset[str], str | None]:
    """The keyword masks and the FILE of a ``land_mask`` value: ``(frozenset(), None)`` for none;
    ``({"coastline", "texture"}, None)`` for ``coastline+texture`` (any order and case, spaces
    around ``+`` allowed); ``(frozenset(), value)`` for anything else (a FILE path, which may
    itself contain ``+``)."""
    if value is None:
        return frozenset(), None
    s = value.strip().lower()
    if s in ("none", "null", ""):
        return frozenset(), None
    parts = [p.strip() for p in s.split("+")]
    if all(p in LAND_KEYWORDS for p in parts):
        if len(set(parts)) != len(parts):
            raise ValueError(f"land_mask: '{value}' names a mask twice")
        return frozenset(parts), None
    return frozenset(), value


def normalize_land_mask(value: str | None) -> str | None:
    """``land_mask`` in canonical form: None, the keywords sorted and joined by ``+``
    (``coastline``, ``texture``, ``coastline+texture``), or the FILE as given."""
    keys, path = land_mask_parts(value)
    if path is not None:
        return path
    return "+".join(sorted(keys)) if keys else None


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


def with_defaults(
    base: type[DetectorParams],
    name: str,
    *,
    auto_min_area_px: int | None = None,
    auto_min_length_m: float | None = None,
    auto_min_area_m2: float | None = None,
    **defaults: Any,
) -> type[DetectorParams]:
    """A subclass of ``base`` whose listed fields have other defaults (constraints kept).

    Detectors tune their own defaults (see ``bench/REALDATA.md``) while sharing one
    definition, with its bounds and validators, of every shared parameter. ``auto_*`` set the
    detector's automatic size rule (:func:`resolve_size`); the help texts of ``min_area_px``
    and ``min_length_m`` then state its values.
    """
    from pydantic import create_model
    from pydantic.fields import FieldInfo

    fields = {}
    for key, value in defaults.items():
        f = base.model_fields[key]
        fields[key] = (f.annotation, FieldInfo.merge_field_infos(f, default=value))
    auto = {
        k: v
        for k, v in (
            ("auto_min_area_px", auto_min_area_px),
            ("auto_min_length_m", auto_min_length_m),
            ("auto_min_area_m2", auto_min_area_m2),
        )
        if v is not None
    }
    if auto:
        px = auto.get("auto_min_area_px", base.auto_min_area_px)
        m = auto.get("auto_min_length_m", base.auto_min_length_m)
        a = auto.get("auto_min_area_m2", base.auto_min_area_m2)
        helps = {
            "min_area_px": (
                f"smallest detection kept, in pixels; unset: automatic (the size rule): {px} px when "
                f"the scene's pixel spacing is unknown; when it is known, the pixels of {a:g} m^2 "
                "(ceil(area / pixel area), e.g. 2 px at 10 m), with min_length_m"
            ),
            "min_length_m": (
                f"shortest ship kept, in metres (needs the scene's pixel spacing); unset: automatic "
                f"(the size rule): {m:g} m when the spacing is known and min_area_px is unset; "
                "0 turns it off"
            ),
        }
        for key, text in helps.items():
            if key not in fields:
                f = base.model_fields[key]
                fields[key] = (f.annotation, FieldInfo.merge_field_infos(f, description=text))
    model = create_model(name, __base__=base, **fields)
    for k, v in auto.items():
        setattr(model, k, v)
    return model


def size_defaults(params: type[DetectorParams]) -> dict:
    """What :func:`resolve_size` makes of a parameter model's defaults, with pixel spacing
    known (shown for 10 m x 10 m pixels; ``min_area_m2`` gives the area whose pixel count
    ``min_area_px`` is at other spacings, None when the pixel default applies at every
    spacing) and unknown (``sarship detectors --json``: ``size_defaults``)."""
    p = params()
    r, rule = resolve_size(p, (10.0, 10.0))
    metres = p.min_area_px is None and (p.min_length_m is not None or params.auto_min_length_m is not None)
    u, urule = resolve_size(p, None)
    return {
        "spacing_known": {
            "min_length_m": r.min_length_m,
            "min_area_m2": params.auto_min_area_m2 if metres else None,
            "min_area_px": r.min_area_px,
            "at_spacing_m": [10.0, 10.0],
            "rule": rule,
        },
        "spacing_unknown": {"min_area_px": u.min_area_px, "min_length_m": u.min_length_m, "rule": urule},
    }


def resolve_size(params: DetectorParams, spacing) -> tuple[DetectorParams, str]:
    """The effective size filter of ``params`` for a scene with pixel ``spacing`` (None: unknown).

    Returns ``(params, rule)``: ``params`` with ``min_area_px`` (and, when the metre rule
    applies by default, ``min_length_m``) filled in, and a one-line ``rule`` saying which rule
    applied (``run.json``'s ``size_rule``). The rule, for values left unset (None):

    - explicit values always win: a given ``min_area_px`` is used as it is and the default
      metre rule is then off (a pixel rule asked for); a given ``min_length_m`` is used where
      the spacing is known (``min_area_px`` unset: the detector's area in m^2 as pixels);
    - neither given, spacing known: ``min_length_m`` = the detector's ``auto_min_length_m``
      and ``min_area_px`` = ceil(``auto_min_area_m2`` / pixel area), at least 1 (sizes in
      metres mean the same ship at 1 m and at 10 m pixels);
    - neither given, spacing unknown: ``min_area_px`` = the detector's ``auto_min_area_px``
      (a given ``min_length_m`` cannot apply: ``run.json`` warns).

    An automatic ``min_area_px`` never exceeds a given ``max_area_px``.
    """
    cls = type(params)
    given = params.model_fields_set
    area, length = params.min_area_px, params.min_length_m

    def src(name: str) -> str:
        return "given" if name in given else "detector default"

    def cap(v: int) -> int:
        return min(v, params.max_area_px) if params.max_area_px is not None else v

    if area is not None:
        if length is not None and spacing is not None:
            return params, (
                f"metres and pixels: min_length_m {length:g} m ({src('min_length_m')}), "
                f"min_area_px {area} ({src('min_area_px')})"
            )
        rule = f"pixels: min_area_px {area} ({src('min_area_px')})"
        if length is not None:
            rule += "; min_length_m ignored: the scene's pixel spacing is unknown"
        return params, rule
    if spacing is None:
        px = cap(cls.auto_min_area_px)
        rule = f"pixels (the default when the scene's pixel spacing is unknown): min_area_px {px}"
        if length is not None:
            rule += "; min_length_m ignored: the scene's pixel spacing is unknown"
        return params.model_copy(update={"min_area_px": px}), rule
    px = cap(area_px(cls.auto_min_area_m2, spacing))
    area = f"min_area_px {px} (= {cls.auto_min_area_m2:g} m^2 at {spacing[0]:g} x {spacing[1]:g} m)"
    if length is not None:
        return params.model_copy(update={"min_area_px": px}), (
            f"metres: min_length_m {length:g} m ({src('min_length_m')}), {area}"
        )
    if cls.auto_min_length_m is None:
        px = cap(cls.auto_min_area_px)
        return params.model_copy(update={"min_area_px": px}), f"pixels (the detector's default): min_area_px {px}"
    return params.model_copy(update={"min_area_px": px, "min_length_m": float(cls.auto_min_length_m)}), (
        f"metres (the default when the scene's pixel spacing is known): min_length_m "
        f"{cls.auto_min_length_m:g} m, {area}"
    )


def area_px(area_m2: float, spacing) -> int:
    """Pixels of ``area_m2`` square metres at pixel ``spacing`` (azimuth, range): ceil, at least 1
    (a relative 1e-9 slack so that an exact multiple is not rounded up by float error)."""
    return max(1, math.ceil(float(area_m2) / (float(spacing[0]) * float(spacing[1])) * (1.0 - 1e-9)))


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
    #: with ``input == "polarimetric"``: whether it also reads a covariance (C3/C2) scene
    #: (:func:`sarship.pipeline.tiling.inputs.detector_source` refuses the scene otherwise)
    covariance: bool = True
    needs_looks: bool = False
    #: Scene-wide statistics before detection (two passes): ``scene_pass(block, halo,
    #: origin, params, prep) -> dict`` runs on every tile (same block as ``detect``), and
    #: ``reduce(list_of_dicts, params, prep) -> dict`` combines them; the result is merged
    #: into ``prep`` before ``detect`` runs, so every tile sees the same scene-wide values.
    scene_pass: Callable[..., dict] | None = None
    reduce: Callable[..., dict] | None = None
    #: More than one scene pass: ``reduce`` may return ``"another_pass": True`` (the key is
    #: dropped) to have every tile run ``scene_pass`` again with the merged ``prep`` (e.g.
    #: ``gamma_mrf``: one pass a re-estimation of its class means); at most this many passes.
    scene_passes_max: int = 1
    #: ``discriminate(records, params, prep) -> bool array``: the detector's own rules on whole
    #: components (after the tiles are merged and the size rule applied; the records of
    #: :mod:`sarship.pipeline.targets.components`: ``n``, ``peak``, ``sumv``, ...), e.g. a peak rule.
    discriminate: Callable[..., np.ndarray] | None = None
    #: ``detection_properties(feats, records, read, read_mask, shape, merge_r, params, prep) ->
    #: feats``: properties computed from the scene's pixels under each whole detection, added
    #: to its ``properties`` after the merge, the size rule and the sidelobe step (``read``: the
    #: detector's input reader, ``read_mask``: the detection mask; keyword arguments ``spacing``
    #: and ``geo``: the scene's pixel spacing in metres or None, its georeference attributes, to
    #: re-measure geometry), e.g. ``csk``'s complex statistics, RFI flag and ship segmentation.
    detection_properties: Callable[..., list] | None = None
    #: ``for_scene(params, shape, spacing) -> (params, warnings)``: settings chosen for the scene's
    #: shape (rows, cols) and ground pixel spacing in metres (None: unknown) before any work (e.g.
    #: ``gamma_mrf``'s EM sample on a small chip, ``superpixel_cfar``'s largest ship); raises
    #: :class:`~sarship.pipeline.errors.InputError` when the scene is too small for the method.
    #: The returned parameters are the run's (``run.json`` ``parameters``), the lines its warnings.
    for_scene: Callable[..., tuple[Any, list[str]]] | None = None
    #: ``halo_fn(params) -> int`` for detectors whose context is not ``background // 2``.
    halo_fn: Callable[[Any], int] | None = None
    halo_rule: str = "background // 2"
    #: The GPU twin, when ``detect`` (and ``scene_pass``) accept a CuPy block and run on its GPU:
    #: ``"package.module:function"`` or ``"package.module"`` under :mod:`sarship.pipeline.gpu`,
    #: resolved on first use by :meth:`twin`; None: GPU workers run the CPU code for this detector.
    gpu: str | None = None
    #: with ``gpu``: the scene pass runs on the device too (else on the host block)
    scene_pass_gpu: bool = True
    #: with ``gpu``: ``gpu_params(params) -> bool``, whether these parameters have GPU code
    #: (e.g. ``lmm``'s censored and refused fits have none); False sends the tiles to CPU
    #: workers as for a detector without GPU code (:meth:`gpu_for`).
    gpu_params: Callable[[Any], bool] | None = None

    def gpu_for(self, params: DetectorParams) -> bool:
        """Whether a job with ``params`` runs on GPU workers' devices (``gpu`` and, where the
        detector says which, GPU code for these parameters)."""
        return bool(self.gpu and (self.gpu_params is None or self.gpu_params(params)))

    def twin(self) -> Any:
        """The GPU twin named by ``gpu`` (its function, or its module), imported on first use."""
        if not self.gpu:
            raise ValueError(f"{self.name}: no GPU twin")
        from sarship.pipeline.gpu import twin

        return twin(self.gpu)

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
            "gpu": bool(self.gpu),
            "halo_default_px": self.halo(self.params()),
            "parameters": schema.get("properties", {}),
            "defaults": defaults,
            # min_area_px / min_length_m default to None = this rule (resolve_size)
            "size_defaults": size_defaults(self.params),
        }
