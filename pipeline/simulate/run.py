"""Entry points: :func:`simulate_array` (in memory) and :func:`simulate` (writes the store)."""

from __future__ import annotations

import contextlib
import datetime as _dt
import json
import os
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from sarship.pipeline.errors import InputError
from sarship.pipeline.simulate.config import SimConfig, validate, variables
from sarship.pipeline.simulate.geometry import sar_geometry
from sarship.pipeline.simulate.ground_truth import _collect_tile, _new_ship_buffers, _truth
from sarship.pipeline.simulate.model import _model
from sarship.pipeline.simulate.render import simulate_tile


def simulate_array(cfg: SimConfig) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """The whole scene in memory and its truth (small scenes, tests)."""
    cfg = validate(cfg)
    H, W = cfg.shape
    data = simulate_tile(cfg, 0, H, 0, W)
    m = _model(cfg)
    bufs = _new_ship_buffers(m)
    _collect_tile(m, bufs, data, 0, 0)
    return data, _truth(m, bufs)


def acquired_time(cfg: SimConfig) -> str:
    """A fixed ISO 8601 acquisition time derived from the seed."""
    t0 = _dt.datetime(2020, 1, 1, tzinfo=_dt.UTC)
    t = t0 + _dt.timedelta(seconds=int(cfg.seed) % (5 * 365 * 86400))
    return t.strftime("%Y-%m-%dT%H:%M:%SZ")


def _writable_dir(p: Path, what: str) -> None:
    if not p.is_dir():
        raise InputError(f"{what} folder '{p}' does not exist or is not a folder")
    if not os.access(p, os.W_OK | os.X_OK):
        raise InputError(f"{what} folder '{p}' is not writable")


def simulate(
    out: str | os.PathLike,
    cfg: SimConfig,
    tile: int = 2048,
    truth_path: str | os.PathLike | None = None,
    progress: Callable[[int, int], None] | None = None,
    overwrite: bool = True,
) -> Path:
    """Write the scene store ``out`` tile by tile (bounded memory) and its truth GeoJSON.

    The truth goes to ``truth_path`` (default ``f"{out}.truth.geojson"``). ``progress(done,
    total)`` is called after each tile. On any failure nothing is left behind (the store is
    written to a temporary sibling and renamed; the truth likewise). With ``overwrite=False``
    an existing store or truth file is refused (:class:`InputError`). Returns the store path.
    """
    from sarship.pipeline import __version__
    from sarship.pipeline.scene import atomic_store, create_scene, finalize_scene, tile_slices

    cfg = validate(cfg)
    if isinstance(tile, bool) or not isinstance(tile, (int, np.integer)) or not 16 <= tile <= 65536:
        raise InputError(f"tile: must be an integer in [16, 65536] (got {tile!r})")
    tile = int(tile)
    out = Path(out)
    truth = Path(truth_path) if truth_path is not None else Path(f"{out}.truth.geojson")
    _writable_dir(out.parent if str(out.parent) else Path("."), "output")
    _writable_dir(truth.parent if str(truth.parent) else Path("."), "truth")
    if truth.resolve() == out.resolve():
        raise InputError(f"truth path '{truth}' must differ from the scene path")
    if truth.resolve() == out.resolve() or out.resolve() in truth.resolve().parents:
        raise InputError(f"truth path '{truth}' must not be inside the scene store '{out}'")
    if not overwrite:
        for p, what in ((out, "scene"), (truth, "truth file")):
            if p.exists() or p.is_symlink():
                raise InputError(f"{what} '{p}' already exists: pass --overwrite to replace it")
    m = _model(cfg)  # ship placement errors before anything is written
    H, W = cfg.shape
    attrs = {
        "kind": cfg.kind,
        "looks": m.looks,
        "pixel_spacing_m": list(cfg.pixel_spacing_m),
        "sensor": "sarship-simulator",
        "acquired": acquired_time(cfg),
        "source": "simulated",
        "looks_source": "simulator",
        "sarship_version": __version__,
        "simulation": cfg.as_dict(),
        "truth": truth.name,
        "sar_geometry": sar_geometry(cfg.shape, cfg.pixel_spacing_m),  # where azimuth ghosts fall (issue 16)
    }
    if cfg.kind == "quadpol":
        attrs["polarizations"] = ["hh", "hv", "vv"]
    if cfg.geo is not None:  # georeferenced scene (pipeline/simulate/land.py: geo_attrs)
        from sarship.pipeline.simulate.land import geo_attrs

        attrs.update(geo_attrs(cfg))
    tmp_truth = truth.parent / f".{truth.name}.partial-{uuid.uuid4().hex[:8]}"
    slices = list(tile_slices((H, W), tile))
    moved = False
    try:
        with atomic_store(out) as tmp:
            g = create_scene(tmp, (H, W), variables(cfg), tile=tile, attrs=attrs)
            arrays = {name: g[name] for name in variables(cfg)}
            bufs = _new_ship_buffers(m)
            for done, (_i, _j, r0, r1, c0, c1) in enumerate(slices, 1):
                data = simulate_tile(cfg, r0, r1, c0, c1)
                for name, a in arrays.items():
                    a[r0:r1, c0:c1] = data[name]
                _collect_tile(m, bufs, data, r0, c0)
                del data
                if progress is not None:
                    progress(done, len(slices))
            finalize_scene(tmp, attrs)
            with open(tmp_truth, "w", encoding="utf-8") as fh:
                json.dump(_truth(m, bufs), fh, indent=1)
                fh.write("\n")
            os.replace(tmp_truth, truth)
            moved = True
    except BaseException:
        with contextlib.suppress(OSError):
            tmp_truth.unlink()
        if moved and not out.exists():
            with contextlib.suppress(OSError):
                truth.unlink()
        raise
    return out
