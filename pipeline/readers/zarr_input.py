"""A Zarr scene as input (a folder with ``zarr.json``): re-tiled / copied with its attributes
(``kind``, ``band`` and ``channels`` are then ignored; ``looks`` overrides)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from sarship.pipeline.errors import InputError
from sarship.pipeline.readers.common import _one_line
from sarship.pipeline.readers.writing import _estimate_scene_looks, _rank_one_looks, _write_tiles, choose_codec
from sarship.pipeline.scene import DEFAULT_INGEST_CODEC, atomic_store, create_scene, finalize_scene, open_scene


def _ingest_zarr(src: Path, outp: Path, tile: int, progress, looks, codec: str = DEFAULT_INGEST_CODEC) -> None:
    sc = open_scene(src)
    attrs = dict(sc.attrs)
    arrays = {name: sc.array(name) for name in sc.variables}
    variables = {name: np.dtype(dt) for name, dt in sc.variables.items()}
    attrs["tile"] = tile
    attrs.setdefault("source", [src.name])
    attrs.setdefault("kind", "intensity")
    if looks is not None:
        attrs["looks"], attrs["looks_source"] = float(looks), "argument"
        attrs.pop("looks_note", None)

    def read_tile(r0, r1, c0, c1):
        out = {}
        for name, a in arrays.items():
            try:
                out[name] = np.asarray(a[r0:r1, c0:c1])
            except Exception as exc:
                raise InputError(
                    f"'{src}': cannot read '{name}' rows {r0}:{r1}, cols {c0}:{c1} ({_one_line(exc)})"
                ) from None
        return out

    attrs.pop("codec_choice", None)  # the source's choice is not this store's
    if codec == "auto":
        codec, chosen = choose_codec(sc.shape, tile, read_tile, variables)
        attrs.update(chosen)
    else:
        attrs["codec"] = codec
    with atomic_store(outp) as tmp:
        g = create_scene(tmp, sc.shape, variables, tile=tile, attrs=attrs, codec=codec)
        _write_tiles(g, sc.shape, tile, variables, read_tile, progress, store=tmp)
        if attrs.get("looks") is None:
            if attrs["kind"] in ("slc", "quadpol"):
                attrs["looks"], attrs["looks_source"] = 1.0, "single-look complex"
            else:
                var = "intensity" if "intensity" in variables else ("c11" if "c11" in variables else None)
                if attrs["kind"] == "covariance" and "c12" in variables:
                    attrs.update(_rank_one_looks(tmp, list(variables), sc.shape, tile))
                if var is not None and attrs.get("looks") is None:
                    attrs.update(_estimate_scene_looks(tmp, var, sc.shape, tile))
        finalize_scene(tmp, attrs)
