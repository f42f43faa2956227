"""What a job names, checked before it runs: its request, scene store, land-mask file, AIS files, the coastline's needs.

:func:`validate_inputs` is the one validation of a posted job (``service/processes.py``): it
returns the normalized request the job store keeps and the runner runs
(:meth:`~sarship.workers.request.JobRequest.from_stored`), parsed once. The path checks raise
:class:`~sarship.pipeline.errors.InputError` (a 4xx for the API); they run when a job is posted
and again when the runner starts it (``service/runner.py``: a file may have gone meanwhile), and
the scene routes (``service/scenes.py``) use them to find the jobs that name a scene.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from sarship.pipeline.errors import InputError
from sarship.service.ais_files import ais_paths
from sarship.service.common import Problem, check_text
from sarship.service.settings import Settings
from sarship.service.store import JobStore
from sarship.workers.request import JobRequest


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


def land_file_path(settings: Settings, request: JobRequest) -> Path | None:
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
        raise InputError(
            f"parameter 'land_mask': no file '{s}' (a path inside the allowed scene folders, "
            "or relative to the scene folder)"
        ) from None
    if not any(real == r or r in real.parents for r in settings.roots()):
        raise InputError(f"parameter 'land_mask': '{s}' is outside the allowed scene folders")
    from sarship.pipeline.land.landmask_files import check_land_path

    # from its stat alone (the API process opens no user file): a regular file or a Zarr folder,
    # a GeoJSON within land_max_mb; the job's capped child parses it (Runner._land_file)
    check_land_path(real, int(settings.land_max_mb * 2**20))
    return real


def check_coastline(request: JobRequest, path: Path | None) -> None:
    """``land_mask=coastline`` needs its package and a georeferenced scene: an InputError (a 400)
    when the job is posted rather than a failed job (``path``: the scene, None while it is still
    being ingested: then only the package is checked)."""
    from sarship.pipeline.detectors.base import land_mask_parts

    if "coastline" not in land_mask_parts(request.detector_params().land_mask)[0]:
        return
    from sarship.pipeline.land.coastline import check_scene
    from sarship.pipeline.scene import open_scene

    check_scene(open_scene(path).attrs if path is not None else None)


def validate_inputs(settings: Settings, name: str, body: Any, store: JobStore | None = None) -> dict[str, Any]:
    """The job's normalized inputs (:meth:`JobRequest.inputs`: what the job store keeps),
    validated now, once (so that bad input is a 400, not a failed job): the execution body's
    envelope here, the inputs by :class:`~sarship.workers.request.JobRequest` (the same model
    the command line and the runner use; its parameters parsed once), the scene against the
    allowed folders. With ``store``, a scene id that is not in the scene store yet but whose
    ingest job is accepted or running (an upload still being ingested) is valid too: see
    :func:`pending_ingest`. A 400 :class:`~sarship.service.common.Problem` otherwise."""
    if not isinstance(body, dict) or not isinstance(body.get("inputs"), dict):
        raise Problem(400, "bad request", 'the body must be a JSON object {"inputs": {"scene": ..., ...}}')
    if body.get("response", "document") not in ("document", "raw"):
        raise Problem(400, "bad request", f"'response' must be 'document' or 'raw', got {body['response']!r}")
    if not isinstance(body.get("outputs", {}), dict):
        raise Problem(400, "bad request", "'outputs' must be an object (output name -> options)")
    scene = body["inputs"].get("scene")
    if isinstance(scene, str):  # a NUL or a lone surrogate: no file, no store key can have it
        check_text(scene, "input 'scene'")
    try:
        request = JobRequest.from_inputs(name, body["inputs"])
        if request.ais:  # uploaded ids or files inside the allowed folders, kept as resolved paths
            request = request.model_copy(update={"ais": ais_paths(settings, request.ais)})
        land_file_path(settings, request)
        try:
            path: Path | None = scene_path(settings, request.scene)
        except InputError:
            path = None
            if store is None or pending_ingest(settings, store, request.scene) is None:
                scene_path(settings, request.scene)  # raises again, unless an ingest finished meanwhile
        if path is not None:  # the detector against the scene (csk on amplitude, vb_polsar on a covariance
            check_scene_input(path, request)  # scene, a channel the scene lacks): a 400, not a failed job
        check_coastline(request, path)  # land_mask=coastline: its package, a georeferenced scene
    except InputError as exc:
        title = "missing input" if "is required" in str(exc) else "invalid input"
        detail = str(exc)
        if store is not None and "no scene" in detail and scene_id_like(request_scene(body)):
            last = store.ingest_job_for_scene(request_scene(body).strip())
            if last is not None and last["status"] in ("failed", "dismissed"):
                detail += f" (its ingest job {last['id']} {last['status']}: {last['message']})"
        raise Problem(400, title, detail) from None
    return request.inputs()


def check_scene_input(path: Path, request: JobRequest) -> None:
    """:class:`InputError` when the request's detector cannot read the scene at ``path`` (its
    ``channel`` a variable the scene lacks or of the wrong kind, a complex-SLC detector on
    amplitude data, a complex-channel detector on a covariance scene): the check the job
    itself makes (:func:`sarship.pipeline.tiling.inputs.detector_source`). A store that cannot be
    opened is left to the job, as for every detector."""
    from sarship.pipeline.scene import open_scene
    from sarship.pipeline.tiling.inputs import detector_source

    try:
        scene = open_scene(path)
    except Exception:
        return
    detector_source(request.spec, scene, request.channel)
    if request.spec.for_scene is not None:  # a scene too small for the method (gamma_mrf): a 400
        request.spec.for_scene(request.detector_params(), scene.shape, scene.ground_spacing_m)


def request_scene(body: dict[str, Any]) -> str:
    """The execution body's ``scene`` input when it is a string, else ``""``."""
    s = body["inputs"].get("scene")
    return s if isinstance(s, str) else ""


def scene_id_like(s: str) -> bool:
    """A scene id (``DATA/scenes/ID.zarr``) rather than a path."""
    s = s.strip()
    return bool(s) and s.replace("_", "").replace("-", "").isalnum()


def pending_ingest(settings: Settings, store: JobStore, scene: str) -> dict[str, Any] | None:
    """The accepted or running ingest job of scene id ``scene`` (an upload being ingested,
    ``POST /scenes``, or an inbox pass), if the scene is not in the scene store yet."""
    if not scene_id_like(scene):
        return None
    return store.active_ingest(scene.strip())
