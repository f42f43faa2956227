"""Scene quicklooks of a finished job: the scene grey-stretched with one range per job.

Every picture of a job (the preview PNG, every XYZ tile of :mod:`sarship.service.tiles`) uses the same
stretch, computed once from a decimated read of the scene and cached in the job folder, so
neighbouring tiles and the preview match. The stretch depends on what the scene's samples were
(:func:`display_scale`, from the scene attributes the ingest wrote):

- ``db`` (float or 16-bit data: calibrated intensity, GRD digital numbers ...): the intensity in
  dB, linear between its 2 and 98 % percentiles;
- ``amplitude`` (8-bit amplitude: PNG/JPEG chips such as HRSID's or SSDD's, 8-bit GeoTIFFs): those
  samples were already scaled for display by whoever made them (often log-like), so the dB of
  their square compresses them twice and the sea comes out light grey with the ships barely
  brighter; the amplitude (the square root of the stored intensity) is stretched linearly between
  its 2 and 99 % percentiles instead;
- ``linear`` (8-bit samples of another quantity): the stored value, linear 2-99 %.

Zero (no signal, no data) is black in all three; percentiles are taken over the other pixels.

The band is the one the job's detector read when that was a single channel (``run.json`` ``channel``), else
:func:`sarship.pipeline.tiling.inputs.intensity_source`'s choice (``intensity``, else ``|hh|^2`` ... for complex
and quad-pol scenes, else ``c11`` for covariance scenes).

Reads are strided (``zarr`` slicing with a step), so a decimated picture of a 25000-pixel scene
holds only the decimated pixels in memory; :func:`grey_base` keeps a small decimated grey
image (at most :data:`BASE_MAX` pixels a side) in the job folder for the coarse zoom levels.
"""

from __future__ import annotations

import json
import threading
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

import numpy as np

from sarship.service.cache import build_once

if TYPE_CHECKING:
    import zarr

#: Longest side of the cached decimated grey image that serves the coarse zooms (and gives the
#: stretch): 2048 px = 4 MiB of uint8 at most, ~4 M samples for the percentiles.
BASE_MAX = 2048
#: Rows read per strided strip (in output pixels) when decimating the whole scene.
STRIP_OUT = 256


#: Quicklook scales (:func:`display_scale`) and their percentile range.
PERCENTILES = {"db": (2.0, 98.0), "amplitude": (2.0, 99.0), "linear": (2.0, 99.0)}
#: Suffixes of the 8-bit picture formats the ingest reads (PNG / JPEG amplitude).
EIGHT_BIT_FILES = (".png", ".jpg", ".jpeg")


@dataclass(frozen=True)
class Source:
    """Where a job's quicklook intensity comes from."""

    path: str
    var: str
    transform: str  # "real" or "abs2"
    shape: tuple[int, int]
    scale: str = "db"


def display_scale(attrs: dict[str, Any]) -> str:
    """How a scene's quicklook maps its intensity to grey (see the module doc).

    Parameters
    ----------
    attrs : dict
        The scene's attributes (``sample_dtype``, ``source``, ``quantity`` as the ingest writes them).

    Returns
    -------
    str
        ``"amplitude"`` for 8-bit amplitude samples (an 8-bit ``sample_dtype``, or a PNG / JPEG
        source, whose grey may have been averaged from RGB into float), ``"linear"`` for 8-bit
        samples of another quantity, else ``"db"``.
    """
    sources = attrs.get("source") or []
    if isinstance(sources, str):
        sources = [sources]
    eight_bit = str(attrs.get("sample_dtype", "")) in ("uint8", "int8") or any(
        str(f).lower().endswith(EIGHT_BIT_FILES) for f in sources
    )
    if not eight_bit:
        return "db"
    return "amplitude" if str(attrs.get("quantity", "")).lower().startswith("amplitude") else "linear"


def job_run(job_dir: Path) -> dict[str, Any]:
    run: dict[str, Any] = json.loads((job_dir / "run.json").read_text())
    return run


def scene_source(job_dir: Path) -> Source:
    """The scene band a job's quicklooks show (see the module doc)."""
    from sarship.pipeline.scene import open_scene
    from sarship.pipeline.tiling.inputs import intensity_source

    run = job_run(job_dir)
    scene = open_scene(run["scene"]["path"])
    ch = run.get("channel")
    var, transform = intensity_source(scene, ch if isinstance(ch, str) and ch in scene.variables else None)
    # the 8-bit rule concerns the stored samples: a complex channel's |z|^2 is always shown in dB
    scale = display_scale(scene.attrs) if transform == "real" else "db"
    return Source(str(scene.path), var, transform, scene.shape, scale)


def strided_reader(src: Source) -> Callable[[int, int, int, int, int], np.ndarray]:
    """``read(r0, r1, c0, c1, step)`` -> float32 intensity of rows ``r0:r1:step``, columns
    ``c0:c1:step`` (only the chunks under the window are decompressed; only the picked pixels
    are kept)."""
    import zarr

    arr = zarr.open_array(f"{src.path}/{src.var}", mode="r")

    def read(r0: int, r1: int, c0: int, c1: int, step: int = 1) -> np.ndarray:
        a = cast(np.ndarray, arr[r0:r1:step, c0:c1:step])  # a slice of an array: an array, never a scalar
        if src.transform == "abs2":
            return (a.real.astype(np.float32) ** 2 + a.imag.astype(np.float32) ** 2).astype(np.float32)
        return np.asarray(a, dtype=np.float32)

    return read


def to_db(x: np.ndarray) -> np.ndarray:
    """10 log10 x, NaN where x is not positive or not finite."""
    with np.errstate(all="ignore"):
        return (10.0 * np.log10(np.where(np.isfinite(x) & (x > 0), x, np.nan))).astype(np.float32)


def to_level(x: np.ndarray, scale: str = "db") -> np.ndarray:
    """The quantity a quicklook stretches linearly, from the intensity ``x``: its dB
    (:func:`to_db`), its amplitude ``sqrt(x)`` (``scale="amplitude"``) or ``x`` itself
    (``"linear"``); NaN where ``x`` is not positive or not finite (drawn black)."""
    if scale == "db":
        return to_db(x)
    with np.errstate(all="ignore"):
        ok = np.where(np.isfinite(x) & (x > 0), x, np.nan).astype(np.float32)
    return np.sqrt(ok) if scale == "amplitude" else ok


def percentile_range(db: np.ndarray, lo_pct: float = 2.0, hi_pct: float = 98.0) -> tuple[float, float]:
    """The ``lo_pct``-``hi_pct`` % range of the finite values (0, 1 when there are none; widened
    to a non-empty range when constant)."""
    fin = db[np.isfinite(db)]
    if fin.size == 0:
        return 0.0, 1.0
    lo, hi = (float(v) for v in np.percentile(fin, [lo_pct, hi_pct]))
    if hi <= lo:
        hi = lo + 1e-3
    return lo, hi


def stretch(db: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """Levels (dB, or :func:`to_level`'s) to uint8 grey, linear between ``lo`` (0) and ``hi`` (255);
    NaN (no signal) is black."""
    g = (np.nan_to_num(db, nan=lo) - lo) * (255.0 / (hi - lo))
    out: np.ndarray = np.clip(g + 0.5, 0, 255).astype(np.uint8)
    return out


def base_step(shape: tuple[int, int], base_max: int = BASE_MAX) -> int:
    """Power-of-two decimation of the cached grey base: the smallest with max side <= base_max."""
    step = 1
    while -(-max(shape) // step) > base_max:
        step *= 2
    return step


def _decimate(read: Callable[[int, int, int, int, int], np.ndarray], shape: tuple[int, int], step: int) -> np.ndarray:
    H, W = shape
    rows = STRIP_OUT * step
    return np.concatenate([read(r0, min(r0 + rows, H), 0, W, step) for r0 in range(0, H, rows)])


_mem_lock = threading.Lock()
_mem: OrderedDict[tuple[str, str], Any] = OrderedDict()


def _memo(key: tuple[str, str], make: Callable[[], Any], size: int = 32) -> Any:
    """A small in-process LRU over products already on disk (saves re-reading them per tile)."""
    with _mem_lock:
        if key in _mem:
            _mem.move_to_end(key)
            return _mem[key]
    v = make()
    with _mem_lock:
        _mem[key] = v
        while len(_mem) > size:
            _mem.popitem(last=False)
    return v


def _base_path(job_dir: Path, base_max: int) -> Path:
    return job_dir / f"quicklook-base-{base_max}.npy"


def job_stretch(job_dir: Path) -> dict[str, Any]:
    """The job's quicklook settings, made once (``JOB/quicklook.json``): the band (``path``,
    ``var``, ``transform``, ``shape``), its ``scale`` (:func:`display_scale`) and the scene-wide
    percentile range ``lo``, ``hi`` of that scale (:data:`PERCENTILES`: 2-98 % of the dB, 2-99 %
    of an 8-bit amplitude), taken from the scene decimated by ``step`` (a power of two, at most
    :data:`BASE_MAX` px a side); that decimated grey image is kept too (:func:`grey_base`).
    Settings written before ``scale`` existed read as ``db``, as they were made."""
    out = job_dir / "quicklook.json"

    def build(tmp: Path) -> None:
        src = scene_source(job_dir)
        step = base_step(src.shape)
        lev = to_level(_decimate(strided_reader(src), src.shape, step), src.scale)
        pct = PERCENTILES[src.scale]
        lo, hi = percentile_range(lev, *pct)
        build_once(_base_path(job_dir, BASE_MAX), lambda t: _save_npy(t, stretch(lev, lo, hi)))
        tmp.write_text(
            json.dumps(
                {
                    "lo": lo,
                    "hi": hi,
                    "scale": src.scale,
                    "percentiles": list(pct),
                    "step": step,
                    "path": src.path,
                    "var": src.var,
                    "transform": src.transform,
                    "shape": list(src.shape),
                }
            )
        )

    meta: dict[str, Any] = _memo(("stretch", str(out)), lambda: json.loads(build_once(out, build).read_text()))
    return meta


def source_of(meta: dict[str, Any]) -> Source:
    return Source(
        meta["path"],
        meta["var"],
        meta["transform"],
        (int(meta["shape"][0]), int(meta["shape"][1])),
        meta.get("scale", "db"),
    )


def grey(src: Source, x: np.ndarray, meta: dict[str, Any]) -> np.ndarray:
    """The job's grey of the intensity ``x`` read from ``src``: its level in the job's scale,
    stretched over the job's range."""
    return stretch(to_level(x, src.scale), meta["lo"], meta["hi"])


def grey_base(job_dir: Path, base_max: int = BASE_MAX) -> tuple[int, np.ndarray]:
    """``(step, grey)``: the scene decimated by ``step`` = :func:`base_step` (rows and columns
    ``0, step, 2 step, ...``) in the job's stretch, made once (``JOB/quicklook-base-N.npy``)."""
    meta = job_stretch(job_dir)
    src = source_of(meta)
    step = base_step(src.shape, base_max)
    path = _base_path(job_dir, base_max)

    def build(tmp: Path) -> None:
        _save_npy(tmp, grey(src, _decimate(strided_reader(src), src.shape, step), meta))

    return step, _memo(("base", str(path)), lambda: np.load(build_once(path, build)))


def _save_npy(path: Path, a: np.ndarray) -> None:
    with open(path, "wb") as fh:
        np.save(fh, a)


#: The land tint of the quicklooks: land pixels are (1 - LAND_ALPHA) grey + LAND_ALPHA LAND_RGB.
LAND_RGB = (40, 110, 255)
LAND_ALPHA = 0.45


def land_array(job_dir: Path) -> zarr.Array[Any] | None:
    """The job's land mask array (``land.zarr``, written when the job ran with ``land_mask``), or None."""
    import zarr

    if not (job_dir / "land.zarr").is_dir():
        return None
    # "land" is the array the job wrote (workers/jobs.py), never a group
    return cast("zarr.Array[Any]", zarr.open_group(str(job_dir / "land.zarr"), mode="r")["land"])


def tint_land(rgb: np.ndarray, land: np.ndarray) -> np.ndarray:
    """``rgb`` (uint8, (..., 3)) with the ``land`` pixels tinted blue (LAND_RGB at LAND_ALPHA)."""
    out = rgb.copy()
    tint = (1.0 - LAND_ALPHA) * rgb[land].astype(np.float32) + LAND_ALPHA * np.asarray(LAND_RGB, np.float32)
    out[land] = np.clip(np.rint(tint), 0, 255).astype(np.uint8)
    return out


def preview_png(job_dir: Path, size: int) -> Path:
    """Quicklook of a finished job (made once per size, atomically): the scene in the job's
    stretch (:func:`job_stretch`) decimated to at most ``size`` pixels a side, the land mask of a
    job run with ``land_mask`` (``land.zarr``) as a blue tint (:func:`tint_land`), detected pixels
    in red (max-pooled, so that small ships stay visible), detection boxes in yellow. Read in
    strips: memory is the output plus a strip of mask rows."""
    import zarr
    from PIL import Image, ImageDraw

    from sarship.service.cog import maxpool

    def build(tmp: Path) -> None:
        meta = job_stretch(job_dir)
        src = source_of(meta)
        H, W = src.shape
        step = max(1, -(-max(H, W) // size))
        read = strided_reader(src)
        m = cast("zarr.Array[Any]", zarr.open_group(str(job_dir / "mask.zarr"), mode="r")["mask"])  # an array
        land = land_array(job_dir)
        rows = step * max(1, 512 // step)
        greys, marks, lands = [], [], []
        for r0 in range(0, H, rows):
            r1 = min(r0 + rows, H)
            greys.append(grey(src, read(r0, r1, 0, W, step), meta))
            marks.append(maxpool(np.asarray(m[r0:r1, :], np.uint8), step) > 0)
            if land is not None:
                lands.append(np.asarray(land[r0:r1:step, 0:W:step]) > 0)
        g = np.concatenate(greys)
        rgb = np.stack([g, g, g], -1)
        if lands:
            rgb = tint_land(rgb, np.concatenate(lands))
        rgb[np.concatenate(marks)] = (255, 40, 40)
        img = Image.fromarray(rgb)
        draw = ImageDraw.Draw(img)
        fc = json.loads((job_dir / "detections.geojson").read_text())
        for f in fc.get("features", []):
            bb = f["properties"].get("bbox_px")
            if bb:
                r0, c0, r1, c1 = bb
                draw.rectangle([c0 // step - 2, r0 // step - 2, c1 // step + 2, r1 // step + 2], outline=(255, 220, 0))
        img.save(tmp, format="PNG")

    return build_once(job_dir / f"preview-{size}.png", build)
