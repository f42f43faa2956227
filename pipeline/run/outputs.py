"""A run's output folder: checked before any work, written under a temporary name, published by renames.

Outputs (docs/interfaces/files.md) in ``DIR``: ``mask.zarr``, ``detections.geojson``, ``run.json``
and, with a land mask, ``land.zarr``; with AIS files, ``ais_unmatched.geojson``. They are written under a temporary folder inside ``DIR``
(:func:`prepare_out`) and renamed into place only when the run has succeeded (:func:`publish`),
so a failed or interrupted run leaves the previous outputs (or nothing) behind.
"""

from __future__ import annotations

import os
import shutil
import uuid
from pathlib import Path

from sarship.pipeline.errors import InputError
from sarship.pipeline.scene import CLAIM_SUFFIX

OUTPUTS = ("mask.zarr", "detections.geojson", "run.json", "land.zarr", "ais_unmatched.geojson")
#: Outputs a run writes only with some parameters (``land.zarr``: with ``land_mask``;
#: ``ais_unmatched.geojson``: with AIS files); an older
#: one in the folder is removed when the new run has none.
OPTIONAL_OUTPUTS = ("land.zarr", "ais_unmatched.geojson")
#: The AIS stage's output (written after ``run.json`` is laid out, so listed by the stage's outcome).
AIS_OUTPUT = "ais_unmatched.geojson"
#: The temporary folder's name prefix inside ``DIR`` (``sarship/temporaries.py`` removes leftovers).
PARTIAL_PREFIX = ".sarship-partial-"


def check_out_path(out_dir: Path, scene_path: Path) -> None:
    """Refuse an output folder inside (or equal to) the scene store, and one whose outputs
    would replace the scene itself."""
    out, scene = out_dir.resolve(), scene_path.resolve()
    if out == scene or scene in out.parents:
        raise InputError(
            f"--out '{out_dir}' is inside the scene store '{scene_path}': "
            "choose a folder outside it (not even --overwrite writes into an input)"
        )
    if scene in {out / name for name in OUTPUTS}:
        raise InputError(f"--out '{out_dir}' would replace the scene '{scene_path}' itself: choose another folder")


def check_out(out_dir: Path, scene_path: Path, overwrite: bool) -> None:
    """:func:`check_out_path`, and refuse an existing non-empty folder unless ``overwrite``
    (its claim file, :func:`sarship.pipeline.scene.claim_output`, aside)."""
    check_out_path(out_dir, scene_path)
    out = out_dir.resolve()
    if not overwrite and out.is_dir() and any(p.name != CLAIM_SUFFIX for p in out.iterdir()):
        raise InputError(
            f"output folder '{out_dir}' exists and is not empty: pass --overwrite to replace "
            f"its {', '.join(OUTPUTS)}, or choose another folder"
        )


def prepare_out(out_dir: Path) -> Path:
    """Create ``out_dir`` (and its parents) if needed and a fresh temporary folder inside it;
    returns the temporary folder. One-line InputError when the folder cannot be written."""
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"cannot create output folder '{out_dir}': {exc.strerror}") from None
    if not out_dir.is_dir():
        raise InputError(f"output '{out_dir}' is not a folder")
    if not os.access(out_dir, os.W_OK):
        raise InputError(f"output folder '{out_dir}' is not writable")
    tmp = out_dir / f"{PARTIAL_PREFIX}{uuid.uuid4().hex[:8]}"
    try:
        tmp.mkdir()
    except OSError as exc:
        raise InputError(f"output folder '{out_dir}' is not writable: {exc.strerror}") from None
    return tmp


def publish(tmp: Path, out_dir: Path) -> None:
    """Move a complete run's outputs from its temporary folder ``tmp`` into ``out_dir``, each by
    a rename (an older output moved aside first and removed after; an optional output this run
    lacks is stale and removed), then remove ``tmp``. Raises FileNotFoundError at a required
    output that is missing (the run's code writes every one of them before it publishes)."""
    for name in OUTPUTS:
        src, dst = tmp / name, out_dir / name
        if not src.exists() and name not in OPTIONAL_OUTPUTS:
            raise FileNotFoundError(src)
        old = None
        if dst.exists():  # moved aside first; an optional output this run lacks is stale: removed
            old = out_dir / f".{name}.old-{uuid.uuid4().hex[:8]}"
            os.replace(dst, old)
        if src.exists():
            os.replace(src, dst)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True) if old.is_dir() else old.unlink()
    shutil.rmtree(tmp, ignore_errors=True)
