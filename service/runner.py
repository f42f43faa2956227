"""Job runner: threads of one API process that claim jobs from the store and run them on the
Dask cluster with :func:`sarship.workers.jobs.run_request` (outputs in ``DATA/jobs/ID``).

Each running job holds a lease in the store, renewed by a heartbeat and at every finished
tile (which also records ``progress``); if the job is dismissed meanwhile, the next tile
callback raises :class:`Dismissed` and ``run_request`` cancels the job's Dask futures and
removes its partial outputs.
"""

from __future__ import annotations

import logging
import os
import shutil
import socket
import threading
import time
import traceback
import uuid
from pathlib import Path
from typing import Any, Optional

from sarship.pipeline.errors import InputError
from sarship.service.settings import Settings
from sarship.service.store import INGEST, JobStore

log = logging.getLogger("sarship.service")

__all__ = ["INGEST", "Dismissed", "Runner", "scene_path", "wait_final"]


class Dismissed(Exception):
    """The job was dismissed (or re-claimed elsewhere) while it ran."""


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


class Runner:
    """``settings.concurrency`` worker threads plus a lease heartbeat."""

    def __init__(self, settings: Settings, store: JobStore, client, metrics=None):
        self.settings = settings
        self.store = store
        self.client = client
        self.metrics = metrics
        self.owner = f"{socket.gethostname()}-{os.getpid()}-{uuid.uuid4().hex[:6]}"
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._running: dict[str, float] = {}
        self._lock = threading.Lock()
        self.wake = threading.Event()

    def start(self) -> None:
        # outputs of dismissed jobs renamed aside (DELETE /jobs/ID) but not removed: the process stopped
        for stale in self.settings.jobs_dir.glob(".dismissed-*") if self.settings.jobs_dir.is_dir() else ():
            shutil.rmtree(stale, ignore_errors=True)
        for k in range(self.settings.concurrency):
            t = threading.Thread(target=self._loop, name=f"sarship-runner-{k}", daemon=True)
            t.start()
            self._threads.append(t)
        hb = threading.Thread(target=self._heartbeat, name="sarship-lease", daemon=True)
        hb.start()
        self._threads.append(hb)

    def stop(self) -> None:
        self._stop.set()
        self.wake.set()
        for t in self._threads:
            t.join(timeout=5)

    def _heartbeat(self) -> None:
        period = max(self.settings.lease_s / 3.0, 0.5)
        while not self._stop.wait(period):
            with self._lock:
                ids = list(self._running)
            for job_id in ids:
                self.store.renew(job_id, self.owner, self.settings.lease_s)

    def _loop(self) -> None:
        while not self._stop.is_set():
            try:
                job = self.store.claim(self.owner, self.settings.lease_s)
            except Exception:  # a locked database under load: try again shortly
                log.exception("claim failed")
                job = None
            if job is None:
                self.wake.wait(0.5)
                self.wake.clear()
                continue
            self._run(job)

    def _run(self, job: dict) -> None:
        from sarship.workers.jobs import run_request
        from sarship.workers.request import JobRequest

        job_id = job["id"]
        with self._lock:
            self._running[job_id] = time.time()
        out_dir = self.settings.jobs_dir / job_id
        inputs = dict(job["inputs"])
        # a previous attempt killed mid-run left its temporary folder: the job is ours now
        for stale in out_dir.glob(".sarship-partial-*") if out_dir.is_dir() else ():
            shutil.rmtree(stale, ignore_errors=True)

        def on_tile(done: int, total: int) -> None:
            pct = int(100 * done / max(total, 1))
            if self.metrics is not None:
                self.metrics.tiles.inc()
            if not self.store.renew(job_id, self.owner, self.settings.lease_s, min(pct, 99)):
                raise Dismissed(job_id)

        if job["process"] == INGEST:
            self._ingest(job)
            with self._lock:
                self._running.pop(job_id, None)
            return
        if job.get("waits_for") and not self._ingest_done(job):
            with self._lock:
                self._running.pop(job_id, None)
            return
        try:
            request = JobRequest.from_inputs(job["process"], inputs)
            scene = scene_path(self.settings, request.scene)
            run = run_request(request.model_copy(update={"scene": str(scene)}), out_dir=out_dir,
                              client=self.client, progress=False, on_tile=on_tile, overwrite=True)
            summary: dict[str, Any] = {"detections": run["detections"], "detected_px": run["detected_px"],
                                       "outputs": run["outputs"], "timings": run["timings"]}
            if not self.store.finish(job_id, self.owner, "successful",
                                     f"{run['detections']} detections in {run['timings']['total_s']:.1f} s",
                                     summary):
                after = self.store.get(job_id)
                if after is not None and after["status"] == "dismissed":  # dismissed as it finished
                    shutil.rmtree(out_dir, ignore_errors=True)
            if self.metrics is not None:
                H, W = run["scene"]["shape"]
                self.metrics.pixels.inc(H * W)
                self.metrics.duration.labels(job["process"], "successful").observe(run["timings"]["total_s"])
        except Dismissed:
            log.info("job %s dismissed while running", job_id)
        except InputError as exc:
            self.store.finish(job_id, self.owner, "failed", str(exc))
            self._observe_failure(job)
        except Exception as exc:  # never lose the job: record why it failed
            log.error("job %s failed: %s", job_id, traceback.format_exc())
            self.store.finish(job_id, self.owner, "failed", f"internal error: {type(exc).__name__}: {exc}")
            self._observe_failure(job)
        finally:
            with self._lock:
                self._running.pop(job_id, None)

    def _ingest_done(self, job: dict) -> bool:
        """A job that waited for its scene's ingest job (``waits_for``, see
        :meth:`JobStore.create`): True when that ingest succeeded (the job runs now); else the
        job is failed with the ingest's error and False."""
        scene = job["inputs"].get("scene")
        dep = self.store.get(job["waits_for"])
        if dep is not None and dep["status"] == "successful":
            return True
        try:  # (an ingest dismissed after it succeeded keeps its scene)
            scene_path(self.settings, str(scene))
            return True
        except InputError:
            pass
        if dep is None:
            why = f"scene {scene}: its ingest job {job['waits_for']} is gone"
        elif dep["status"] == "failed":
            why = f"scene {scene} could not be ingested (ingest job {dep['id']}): {dep['message']}"
        elif dep["status"] == "dismissed":
            why = f"scene {scene}: its ingest job {dep['id']} was dismissed"
        else:  # (claim never hands out a job whose ingest is still accepted or running)
            why = f"scene {scene}: its ingest job {dep['id']} is {dep['status']}"
        self.store.finish(job["id"], self.owner, "failed", why)
        self._observe_failure(job)
        return False

    def _ingest(self, job: dict) -> None:
        """A scene file (an upload, input ``upload``, or an inbox pass, input ``path``) to the
        scene store ``DATA/scenes/ID.zarr`` (written aside and renamed into place by
        :func:`sarship.pipeline.readers.ingest`'s atomic store), in a child process with a memory
        cap and the service's input limits (:mod:`sarship.service.ingest_proc`): never in this
        API process. A failure caused by the file itself (refused by the limits, unreadable,
        beyond the memory cap) records ``{"bad_input": true}`` as the job's result, so that the
        inbox quarantines the file; other failures do not."""
        from sarship.service.ingest_proc import IngestCrashed, IngestRefused, ingest_in_child

        job_id, inputs = job["id"], job["inputs"]

        def progress(done: int, total: int) -> None:
            if not self.store.renew(job_id, self.owner, self.settings.lease_s, int(99 * done / max(total, 1))):
                raise Dismissed(job_id)

        out = self.settings.scenes_dir / f"{inputs['scene_id']}.zarr"
        try:
            if not out.exists():
                if inputs.get("path"):  # an inbox pass: its product sidecar lies within the inbox
                    src = Path(inputs["path"])
                    root = next((d for d in self.settings.inbox
                                 if Path(os.path.abspath(d)) in Path(os.path.abspath(src)).parents), False)
                else:  # an upload is one file: nothing beside it in the uploads folder is its
                    src, root = Path(inputs["upload"]), False
                st = self.settings
                ingest_in_child(src, out, sidecar_root=root, progress=progress, memory_mb=st.ingest_memory_mb or None,
                                limits={"max_pixels": st.max_pixels, "max_chunk_mb": st.max_chunk_mb,
                                        "max_ratio": st.max_ratio})
            self.store.finish(job_id, self.owner, "successful", f"scene {inputs['scene_id']} ready",
                              {"scene": inputs["scene_id"]})
        except Dismissed:
            pass
        except IngestRefused as exc:
            self.store.finish(job_id, self.owner, "failed", str(exc), {"bad_input": True})
        except IngestCrashed as exc:
            log.error("ingest %s failed: %s", job_id, exc)
            self.store.finish(job_id, self.owner, "failed", f"ingest failed: {exc}")
        except Exception as exc:
            log.error("ingest %s failed: %s", job_id, traceback.format_exc())
            self.store.finish(job_id, self.owner, "failed", f"internal error: {type(exc).__name__}: {exc}")

    def _observe_failure(self, job: dict) -> None:
        if self.metrics is not None:
            took = time.time() - (job["started"] or time.time())
            self.metrics.duration.labels(job["process"], "failed").observe(took)

    def running(self) -> list[str]:
        with self._lock:
            return list(self._running)


def wait_final(store: JobStore, job_id: str, timeout: float) -> Optional[dict]:
    """Poll the store until the job is final (or ``timeout``): the job row."""
    t_end = time.time() + timeout
    while True:
        job = store.get(job_id)
        if job is None or job["status"] in ("successful", "failed", "dismissed") or time.time() > t_end:
            return job
        time.sleep(0.2)
