"""What a job names, checked before it runs: its scene store, its land-mask file, the coastline's needs.

Each raises :class:`~sarship.pipeline.errors.InputError` (a 4xx for the API). Used when a job is
posted (``service/app.py``) and again when the runner starts it (``service/runner.py``), and by the
scene routes (``service/scenes.py``) to find the jobs that name a scene.
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

from sarship.pipeline.errors import InputError
from sarship.service.settings import Settings


def scene_path(settings: Settings, scene: str) -> Path:
    """The scene store a job names: a scene id (``DATA/scenes/ID.zarr``) or a path inside
    an allowed root. Raises :class:`InputError` (a 4xx for the API) otherwise."""
    if not isinstance(scene, str) or not scene.strip():
        raise InputError("input 'scene' must be a scene id or a path")
    s = scene.strip()
    if "://" in s:
        raise InputError(f"input 'scene': only local paths and scene ids are accepted, got '{s}'")
    roots = settings.roots()
    cand = Path(s)
    if not cand.is_absolute() and "/" not in s and "\\" not in s and not s.endswith(".zarr"):
        cand = settings.scenes_dir / f"{s}.zarr"  # a scene id
    try:
        real = cand.resolve(strict=True)
    except (OSError, RuntimeError):
        raise InputError(f"input 'scene': no scene '{s}'") from None
    if not any(real == r or r in real.parents for r in roots):
        raise InputError(f"input 'scene': '{s}' is outside the allowed scene folders")
    return real


def land_file_path(settings: Settings, request) -> Optional[Path]:
    """The ``land_mask`` FILE a job names, resolved and required to lie inside an allowed scene
    folder (the service reads no other file of its host); None for none/texture. InputError
    (a 4xx for the API) otherwise."""
    from sarship.pipeline.detectors.base import land_mask_parts

    lm = land_mask_parts(request.detector_params().land_mask)[1]
    if lm is None:  # none, texture, coastline, coastline+texture
        return None
    s = lm.strip()
    if "://" in s:
        raise InputError(f"parameter 'land_mask': only local files are accepted, got '{s}'")
    cand = Path(s)
    if not cand.is_absolute():
        cand = settings.scenes_dir / cand
    try:
        real = cand.resolve(strict=True)
    except (OSError, RuntimeError):
        raise InputError(f"parameter 'land_mask': no file '{s}' (a path inside the allowed scene folders, "
                         "or relative to the scene folder)") from None
    if not any(real == r or r in real.parents for r in settings.roots()):
        raise InputError(f"parameter 'land_mask': '{s}' is outside the allowed scene folders")
    from sarship.pipeline.landmask_files import check_land_path

    # from its stat alone (the API process opens no user file): a regular file or a Zarr folder,
    # a GeoJSON within land_max_mb; the job's capped child parses it (Runner._land_file)
    check_land_path(real, int(settings.land_max_mb * 2**20))
    return real


def check_coastline(request, path: Optional[Path]) -> None:
    """``land_mask=coastline`` needs its package and a georeferenced scene: an InputError (a 400)
    when the job is posted rather than a failed job (``path``: the scene, None while it is still
    being ingested: then only the package is checked)."""
    from sarship.pipeline.detectors.base import land_mask_parts

    if "coastline" not in land_mask_parts(request.detector_params().land_mask)[0]:
        return
    from sarship.pipeline.coastline import check_scene
    from sarship.pipeline.scene import open_scene

    check_scene(open_scene(path).attrs if path is not None else None)
