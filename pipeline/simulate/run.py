"""Entry points: :func:`simulate_array` (in memory) and :func:`simulate` (writes the store)."""

from __future__ import annotations

import contextlib
import json
import os
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from sarship.pipeline.errors import InputError
from sarship.pipeline.simulate.ais_reports import AisOptions, ais_reports, csv_text
from sarship.pipeline.simulate.config import SimConfig, scene_time, validate, variables
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
    """The scene's ISO 8601 acquisition (first line) time: ``cfg.time``, else a fixed time
    derived from the seed (:func:`~sarship.pipeline.simulate.config.scene_time`)."""
    return scene_time(cfg)


def _writable_dir(p: Path, what: str) -> None:
    if not p.is_dir():
        raise InputError(f"{what} folder '{p}' does not exist or is not a folder")
    if not os.access(p, os.W_OK | os.X_OK):
        raise InputError(f"{what} folder '{p}' is not writable")


def _check_ais_path(ais_path: str | os.PathLike | None, cfg: SimConfig, out: Path, truth: Path) -> Path | None:
    """The AIS file's path, checked before any work (None without one)."""
    if ais_path is None:
        return None
    if not cfg.ais:
        raise InputError("AIS file: the simulation needs ais=True (--ais) to have AIS reports")
    ais = Path(ais_path)
    _writable_dir(ais.parent if str(ais.parent) else Path("."), "AIS file")
    if ais.resolve() in (out.resolve(), truth.resolve()) or out.resolve() in ais.resolve().parents:
        raise InputError(
            f"AIS file '{ais}' must differ from the scene and truth paths and not be inside the scene store"
        )
    if ais.is_dir():
        raise InputError(f"AIS file '{ais}' is a folder")
    return ais


def simulate(
    out: str | os.PathLike,
    cfg: SimConfig,
    tile: int = 2048,
    truth_path: str | os.PathLike | None = None,
    progress: Callable[[int, int], None] | None = None,
    overwrite: bool = True,
    ais_path: str | os.PathLike | None = None,
    ais_options: AisOptions | None = None,
) -> Path:
    """Write the scene store ``out`` tile by tile (bounded memory) and its truth GeoJSON.

    The truth goes to ``truth_path`` (default ``f"{out}.truth.geojson"``). ``progress(done,
    total)`` is called after each tile. With ``ais_path`` (a scene with ``ais``) the scene's AIS
    reports go there as a plain AIS CSV (:mod:`~sarship.pipeline.simulate.ais_reports`, drawn with
    ``ais_options``). On any failure nothing is left behind (the store is written to a temporary
    sibling and renamed; the truth and AIS file likewise). With ``overwrite=False`` an existing
    store, truth or AIS file is refused (:class:`InputError`). Returns the store path.
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
    ais = _check_ais_path(ais_path, cfg, out, truth)
    if ais_options is not None:
        ais_options.validated()
    if not overwrite:
        for p, what in ((out, "scene"), (truth, "truth file"), (ais, "AIS file")):
            if p is not None and (p.exists() or p.is_symlink()):
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
        # where azimuth ghosts fall (issue 16), line times and look directions (issue 33)
        "sar_geometry": sar_geometry(cfg.shape, cfg.pixel_spacing_m, scene_time(cfg), cfg.geo is not None),
    }
    if cfg.kind == "quadpol":
        attrs["polarizations"] = ["hh", "hv", "vv"]
    if cfg.geo is not None:  # georeferenced scene (pipeline/simulate/land.py: geo_attrs)
        from sarship.pipeline.simulate.land import geo_attrs

        attrs.update(geo_attrs(cfg))
    tmp_truth = truth.parent / f".{truth.name}.partial-{uuid.uuid4().hex[:8]}"
    tmp_ais = ais.parent / f".{ais.name}.partial-{uuid.uuid4().hex[:8]}" if ais is not None else tmp_truth
    slices = list(tile_slices((H, W), tile))
    published: list[Path] = []
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
            if ais is not None:
                with open(tmp_ais, "w", encoding="utf-8", newline="") as fh:
                    fh.write(csv_text(*ais_reports(cfg, ais_options)))
                os.replace(tmp_ais, ais)
                published.append(ais)
            os.replace(tmp_truth, truth)
            published.append(truth)
    except BaseException:
        for p in (tmp_truth, tmp_ais):
            with contextlib.suppress(OSError):
                p.unlink()
        if published and not out.exists():
            for p in published:
                with contextlib.suppress(OSError):
                    p.unlink()
        raise
    return out
