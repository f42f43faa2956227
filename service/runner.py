"""Job runner: threads of one API process that claim jobs from the store and run them on the
Dask cluster with :func:`sarship.workers.jobs.run_request` (outputs in ``DATA/jobs/ID``).

Each running job holds a lease in the store, renewed by a heartbeat thread and at every
finished tile (which also records ``progress``); if the job is dismissed meanwhile, or its
lease lapsed and another runner took it, the next tile callback raises :class:`Dismissed` and
``run_request`` cancels the job's Dask futures and removes its partial outputs.

Publication is fenced. A runner stopped longer than its lease (``SIGSTOP``, a VM paused:
every thread of the process stops, the heartbeat too) loses the job to another runner, which
runs it again (``attempts`` 2): a job runs *at least* once. Its results are published once:
an attempt writes its outputs aside, once (``DATA/jobs/ID/.sarship-partial-*``, handed back by
``run_request``'s ``publish_with``; an ingest ``DATA/scenes/.ID.zarr.attempt-N-*``), and
:func:`sarship.pipeline.run.outputs.publish` moves them into place inside the store transaction
that finishes the job, which checks that the job is still running under this owner *and this
attempt*; a stale attempt's outputs are discarded. A job's request is the normalized one the API
validated and stored (:meth:`~sarship.workers.request.JobRequest.from_stored`): not validated again.

A failure that is a fault of the service, not of the job's input (:func:`transient_reason`:
the data folder full, the job store busy, the Dask scheduler unreachable), puts the job back
to ``accepted`` to be tried again after a back-off (``SARSHIP_RETRY_S``, doubled per attempt
up to ``SARSHIP_RETRY_MAX_S``): such a job is never failed for it, and an inbox pass never
quarantined.

Temporary scene stores of ingests that no live runner writes (a runner killed mid-ingest, an
ingest dismissed while its runner was down) are removed before a scene is ingested again, at
start-up, and then every lease period (:meth:`Runner.sweep_partials`).
"""

from __future__ import annotations

import logging
import os
import re
import shutil
import socket
import threading
import time
import traceback
import uuid
from asyncio import CancelledError
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from sarship.pipeline.errors import InputError
from sarship.service.ais_files import ais_paths
from sarship.service.job_inputs import land_file_path, scene_path
from sarship.service.settings import Settings
from sarship.service.store import INGEST, Job, JobStore

if TYPE_CHECKING:
    from distributed import Client

    from sarship.service.metrics import Metrics
    from sarship.service.scheduler_link import SchedulerLink

log = logging.getLogger("sarship.service")

__all__ = ["INGEST", "Dismissed", "Runner", "scene_path", "transient_reason", "wait_final"]


#: A running job's progress is stored at most this often (seconds; and on its last tile).
PROGRESS_EVERY_S = 0.25


class Dismissed(Exception):
    """The job was dismissed (or re-claimed elsewhere) while it ran."""


def transient_reason(exc: BaseException, client: Client | SchedulerLink | None = None) -> str | None:
    """Why ``exc`` is a fault of the service rather than of the job's input, or None: a write
    that failed for want of space (``ENOSPC``, ``EDQUOT``, ``EFBIG``, also behind an
    :class:`InputError`), a busy, locked or full job store, or a Dask scheduler that cannot
    be reached (a closed comm, a refused connection, the client not connected)."""
    import sqlite3

    from sarship.service.ingest_proc import transient_fault

    fault = transient_fault(exc)
    if fault is not None:
        return f"the data folder is full: [Errno {fault.errno}] {fault.strerror or fault}"
    if isinstance(exc, sqlite3.OperationalError):
        text = str(exc)
        if any(w in text for w in ("locked", "busy", "disk is full", "disk I/O")):
            return f"the job store is unavailable: {text}"
    comm_closed: tuple[type[BaseException], ...]
    try:
        from distributed.comm.core import CommClosedError

        comm_closed = (CommClosedError,)
    except ImportError:  # pragma: no cover
        comm_closed = ()  # (ConnectionError, checked anyway, stood in for it)
    from concurrent.futures import CancelledError as FuturesCancelled  # (distributed's FutureCancelledError)

    if isinstance(exc, (*comm_closed, ConnectionError, FuturesCancelled, CancelledError)) or (
        client is not None and getattr(client, "status", "running") not in ("running", None)
    ):
        return f"the Dask scheduler is unreachable: {type(exc).__name__}: {exc}"
    return None


#: Temporary stores of a scene ID in ``DATA/scenes``: ``.ID.zarr.partial-*`` (an ingest's atomic
#: store), ``.ID.zarr.attempt-*`` (an attempt's output, published when it finishes the job) and
#: ``..ID.zarr.attempt-*.partial-*`` (the atomic store of that output).
_SCENE_TEMP = re.compile(r"^\.{1,2}(?P<id>[^./]+)\.zarr\.(partial|attempt)-")


class Runner:
    """``settings.concurrency`` worker threads plus a lease heartbeat."""

    def __init__(
        self, settings: Settings, store: JobStore, client: Client | SchedulerLink, metrics: Metrics | None = None
    ):
        self.settings = settings
        self.store = store
        self.client = client
        self.metrics = metrics
        self.owner = f"{socket.gethostname()}-{os.getpid()}-{uuid.uuid4().hex[:6]}"
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._running: dict[str, int] = {}  # job ID -> the attempt this runner runs
        self._lock = threading.Lock()
        self.wake = threading.Event()

    def start(self) -> None:
        # outputs of dismissed jobs renamed aside (DELETE /jobs/ID) but not removed: the process stopped
        for stale in self.settings.jobs_dir.glob(".dismissed-*") if self.settings.jobs_dir.is_dir() else ():
            shutil.rmtree(stale, ignore_errors=True)
        try:
            self.sweep_partials()
        except Exception:  # a busy store at start-up: swept again at the next heartbeat
            log.exception("sweeping temporary scene stores failed")
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
        last_sweep = time.time()
        while not self._stop.wait(period):
            with self._lock:
                ids = dict(self._running)
            for job_id, attempt in ids.items():
                try:
                    if not self.store.renew(job_id, self.owner, self.settings.lease_s, attempt=attempt):
                        log.info(
                            "job %s (attempt %d): no longer held by this runner (finished, dismissed, or "
                            "taken over after its lease lapsed: then it publishes nothing)",
                            job_id,
                            attempt,
                        )
                except Exception:  # a busy store: the next beat tries again
                    log.exception("renewing the lease of job %s failed", job_id)
            if time.time() - last_sweep >= self.settings.lease_s:
                last_sweep = time.time()
                try:
                    self.sweep_partials()
                except Exception:
                    log.exception("sweeping temporary scene stores failed")

    def sweep_partials(self, scene_id: str | None = None) -> list[str]:
        """Remove the temporary stores in ``DATA/scenes`` (of ``scene_id``, or of every scene)
        of scenes the service ingests (an ingest job names them) that no runner writes now: no
        ingest job of the scene is running under a live lease. Listed before the store is
        asked, so a store that a runner starts writing meanwhile is not seen. The names
        removed."""
        d = self.settings.scenes_dir
        if not d.is_dir():
            return []
        found: dict[str, list[Path]] = {}
        for p in d.iterdir():
            m = _SCENE_TEMP.match(p.name)
            if m and (scene_id is None or m["id"] == scene_id):
                found.setdefault(m["id"], []).append(p)
        if not found:
            return []
        live = self.store.live_ingest_scenes()
        gone = []
        for sid, paths in found.items():
            if sid in live or (scene_id is None and self.store.ingest_job_for_scene(sid) is None):
                continue  # being written; or not the service's (e.g. a `sarship ingest` into DATA/scenes)
            for p in paths:
                _remove(p)
                gone.append(p.name)
        if gone:
            log.info("removed temporary scene stores no runner writes: %s", ", ".join(sorted(gone)))
        return gone

    def _loop(self) -> None:
        while not self._stop.is_set():
            # no cluster now (an external scheduler gone, its link reconnecting: scheduler_link.py):
            # jobs wait in the store instead of being claimed and failed over to their retry again and again
            if not getattr(self.client, "connected", True):
                self.wake.wait(0.5)
                self.wake.clear()
                continue
            try:
                job = self.store.claim(self.owner, self.settings.lease_s)
            except Exception:  # a locked database under load: try again shortly
                log.exception("claim failed")
                job = None
            if job is None:
                self.wake.wait(0.5)
                self.wake.clear()
                continue
            with self._lock:
                self._running[job["id"]] = int(job["attempts"])
            try:
                self._run(job)
            except (Exception, CancelledError):  # e.g. the store locked as the job finished: re-run after the lease
                log.exception("job %s: the runner failed; it runs again when its lease expires", job["id"])
            finally:
                with self._lock:
                    self._running.pop(job["id"], None)

    def _retry(self, job: Job, why: str) -> None:
        """Put a job that failed for a fault of ours back, to be tried again after a back-off."""
        n = max(int(job["attempts"]), 1)
        delay = min(self.settings.retry_s * 2 ** min(n - 1, 30), self.settings.retry_max_s)
        log.warning("job %s (attempt %d): %s; retrying in %g s", job["id"], n, why, delay)
        try:
            self.store.retry_later(
                job["id"], self.owner, n, delay, self._public(f"{why}; retrying in {delay:g} s (attempt {n})")
            )
        except Exception:  # the store itself is unavailable: the lease lapses and the job runs again
            log.exception("job %s: could not record the retry", job["id"])

    def _run(self, job: Job) -> None:
        """Run a claimed job: an ingest (:meth:`_ingest`), else a detector job on the cluster
        (once the ingest it waits for, if any, has succeeded: :meth:`_ingest_done`), whose
        outputs are published by the transaction that finishes it."""
        job_id, attempt = job["id"], int(job["attempts"])
        out_dir = self.settings.jobs_dir / job_id
        inputs = dict(job["inputs"])

        if job["process"] == INGEST:
            self._ingest(job)
            return
        if job.get("waits_for") and not self._ingest_done(job):
            return
        # the job is ours now: what earlier attempts left (killed, or stale and still running
        # elsewhere: they cannot publish) goes; this attempt writes aside and publishes when it finishes
        for stale in [*out_dir.glob(".sarship-partial-*"), *out_dir.glob(".attempt-*")] if out_dir.is_dir() else ():
            _remove(stale)
        land_raster = out_dir / f".attempt-{attempt}-{uuid.uuid4().hex[:6]}-land.zarr"
        staged: list[Path] = []  # the run's temporary folder, published in the store's transaction
        try:
            run = self._detect(job, inputs, out_dir, land_raster, staged)
            self._publish_run(job, run, out_dir, staged)
        except Dismissed:
            log.info("job %s (attempt %d) dismissed or taken over while running", job_id, attempt)
        except (Exception, CancelledError) as exc:  # (Dask's futures cancelled: the scheduler went away)
            self._run_failed(job, exc)
        finally:
            for p in staged:  # (gone once published)
                _remove(p)
            _remove(land_raster)

    def _detect(
        self, job: Job, inputs: dict[str, Any], out_dir: Path, land_raster: Path, staged: list[Path]
    ) -> dict[str, Any]:
        """Run a detector job's request on the cluster, its ``land_mask`` FILE (if any)
        rasterised first into ``land_raster``; the run writes its outputs aside, in a temporary
        folder appended to ``staged``. The run's ``run.json`` content."""
        from sarship.workers.jobs import run_request
        from sarship.workers.request import JobRequest

        job_id, attempt = job["id"], int(job["attempts"])
        # the request validated when the job was posted, as stored: not validated again (its
        # parameters are parsed once, here, and the run reads those)
        request = JobRequest.from_stored(job["process"], inputs)
        scene = scene_path(self.settings, request.scene)
        land = land_file_path(self.settings, request)
        if request.ais:  # (checked when posted; a file may have gone or been deleted meanwhile)
            request = request.model_copy(update={"ais": ais_paths(self.settings, request.ais)})
        land_source = None
        if land is not None:  # parsed and rasterised in a memory-capped child: the job reads that raster
            land_src = self._land_file(land, scene, land_raster, self._still_ours(job_id, attempt))
            request = request.with_param("land_mask", str(land_src["raster"]))
            info = land_src["answer"]  # run.json names the file the job named, not the raster
            land_source = {"path": str(land), "kind": info["kind"], "format": info["format"], **info["info"]}
        # staged once: the run writes its outputs (run.json naming DATA/jobs/ID) in its temporary
        # folder, which is published by the transaction that finishes the job (fenced: a stale
        # attempt publishes nothing)
        return run_request(
            request.model_copy(update={"scene": str(scene)}),
            out_dir=out_dir,
            client=self.client,
            progress=False,
            on_tile=self._tile_progress(job_id, attempt),
            overwrite=True,
            publish_with=lambda tmp, _out: staged.append(tmp),
            land_source=land_source,
        )

    def _tile_progress(self, job_id: str, attempt: int) -> Callable[[int, int], None]:
        """The run's ``on_tile(done, total)``: counts the tile; stores the job's progress, and
        checks that the job is still ours (else :class:`Dismissed`), at most every
        :data:`PROGRESS_EVERY_S` seconds and on the last tile."""
        last_saved = 0.0

        def on_tile(done: int, total: int) -> None:
            nonlocal last_saved
            if self.metrics is not None:
                self.metrics.tiles.inc()
            # progress (and the check that the job is still ours) at most every PROGRESS_EVERY_S
            # seconds, not per tile: a store write per tile is in the tile results' path
            now = time.monotonic()
            if now - last_saved < PROGRESS_EVERY_S and done < total:
                return
            last_saved = now
            pct = int(100 * done / max(total, 1))
            if not self.store.renew(job_id, self.owner, self.settings.lease_s, min(pct, 99), attempt=attempt):
                raise Dismissed(job_id)

        return on_tile

    def _still_ours(self, job_id: str, attempt: int) -> Callable[[int, int], None]:
        """A progress callback (the land_mask child's) that renews the job's lease, and raises
        :class:`Dismissed` once the job is no longer ours."""

        def still_ours(done: int, total: int) -> None:
            if not self.store.renew(job_id, self.owner, self.settings.lease_s, attempt=attempt):
                raise Dismissed(job_id)

        return still_ours

    def _publish_run(self, job: Job, run: dict[str, Any], out_dir: Path, staged: list[Path]) -> None:
        """Finish a detector job whose run succeeded: its summary recorded and its staged
        outputs published into ``out_dir`` in one fenced transaction (a job that is no longer
        ours publishes nothing); then its metrics."""
        from sarship.pipeline.run.outputs import publish

        job_id, attempt = job["id"], int(job["attempts"])
        summary: dict[str, Any] = {
            "detections": run["detections"],
            "detected_px": run["detected_px"],
            "outputs": run["outputs"],
            "timings": run["timings"],
        }
        if isinstance(run.get("ais"), dict):  # the AIS counts (the whole record: results/metrics)
            summary["ais"] = {k: run["ais"].get(k) for k in ("covered", "matched", "dark", "unmatched_in_footprint")}
        if not self.store.finish(
            job_id,
            self.owner,
            "successful",
            f"{run['detections']} detections in {run['timings']['total_s']:.1f} s",
            summary,
            attempt=attempt,
            publish=lambda: publish(staged[0], out_dir),
        ):
            log.warning(
                "job %s (attempt %d) finished, but the job is no longer ours (dismissed, or re-run "
                "after its lease lapsed): its results are discarded",
                job_id,
                attempt,
            )
            return
        if self.metrics is not None:
            H, W = run["scene"]["shape"]
            self.metrics.pixels.inc(H * W)
            self.metrics.duration.labels(job["process"], "successful").observe(run["timings"]["total_s"])
            if isinstance(run.get("ais"), dict):
                self.metrics.count_ais(run["ais"])

    def _run_failed(self, job: Job, exc: BaseException) -> None:
        """A detector job's run raised ``exc`` (called while it is handled): discarded when the
        job is no longer ours; put back for a fault of the service (:func:`transient_reason`);
        else failed with the reason (an unexpected error logged with its traceback)."""
        job_id, attempt = job["id"], int(job["attempts"])
        why = transient_reason(exc, self.client)
        if not self._holds(job_id, attempt):  # (e.g. its outputs removed by the attempt that took over)
            log.info(
                "job %s (attempt %d) ended (%s: %s) after it was dismissed or taken over: discarded",
                job_id,
                attempt,
                type(exc).__name__,
                exc,
            )
        elif why is not None:
            self._retry(job, why)
        elif isinstance(exc, InputError):
            if self.store.finish(job_id, self.owner, "failed", self._public(str(exc)), attempt=attempt):
                self._observe_failure(job)
        else:  # never lose the job: record why it failed
            log.error("job %s failed: %s", job_id, traceback.format_exc())
            if self.store.finish(
                job_id,
                self.owner,
                "failed",
                self._public(f"internal error: {type(exc).__name__}: {exc}"),
                attempt=attempt,
            ):
                self._observe_failure(job)

    def _land_file(self, land: Path, scene: Path, out: Path, progress: Callable[[int, int], None]) -> dict[str, Any]:
        """The ``land_mask`` FILE ``land`` checked and rasterised onto the scene's grid into the
        Zarr group ``out`` by a child process under ``ingest_memory_mb``
        (:func:`~sarship.service.ingest_proc.land_in_child`): ``{"raster": out, "answer":
        the file's kind, format and info}``. InputError for a bad file; a full data folder is
        raised as an ``OSError`` (ENOSPC: the job is retried)."""
        import errno

        from sarship.pipeline.scene import open_scene
        from sarship.service.ingest_proc import IngestTransient, land_in_child

        sc = open_scene(scene)
        out.parent.mkdir(parents=True, exist_ok=True)
        attrs: dict[str, Any] = {k: sc.attrs[k] for k in ("crs", "transform", "gcps") if k in sc.attrs}
        st = self.settings
        try:
            answer = land_in_child(
                land,
                out,
                shape=sc.shape,
                attrs=attrs,
                tile=sc.tile,
                max_bytes=int(st.land_max_mb * 2**20),
                memory_mb=st.ingest_memory_mb or None,
                progress=progress,
            )
        except IngestTransient as exc:
            raise OSError(errno.ENOSPC, str(exc)) from None
        return {"raster": out, "answer": answer}

    def _public(self, message: str) -> str:
        """A job's message as clients see it (stored, then listed): no server data path
        (:meth:`Settings.hide_paths`); the log keeps the full text."""
        return self.settings.hide_paths(message)

    def _holds(self, job_id: str, attempt: int) -> bool:
        """Whether this runner still holds the job as ``attempt`` (renews its lease)."""
        try:
            return self.store.renew(job_id, self.owner, self.settings.lease_s, attempt=attempt)
        except Exception:  # the store unavailable: assume so (its finish is fenced anyway)
            return True

    def _ingest_done(self, job: Job) -> bool:
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
        if self.store.finish(job["id"], self.owner, "failed", self._public(why), attempt=int(job["attempts"])):
            self._observe_failure(job)
        return False

    def _ingest(self, job: Job) -> None:
        """A scene file (an upload, input ``upload``, or an inbox pass, input ``path``) to the
        scene store ``DATA/scenes/ID.zarr``, in a child process with a memory cap and the
        service's input limits (:mod:`sarship.service.ingest_proc`): never in this API
        process. The child writes ``DATA/scenes/.ID.zarr.attempt-N-*`` (through
        :func:`sarship.pipeline.readers.ingest`'s atomic store), renamed to ``ID.zarr`` in the
        transaction that finishes the job (a stale attempt publishes nothing). A failure caused
        by the file itself (refused by the limits, unreadable, beyond the memory cap) records
        ``{"bad_input": true}`` as the job's result, so that the inbox quarantines the file; a
        fault of ours (the data folder full) is retried after a back-off; other failures fail
        the job."""
        from sarship.service.ingest_proc import IngestCrashed, IngestRefused, IngestTransient, ingest_in_child

        job_id, inputs, attempt = job["id"], job["inputs"], int(job["attempts"])

        def progress(done: int, total: int) -> None:
            if not self.store.renew(
                job_id, self.owner, self.settings.lease_s, int(99 * done / max(total, 1)), attempt=attempt
            ):
                raise Dismissed(job_id)

        sid = inputs["scene_id"]
        out = self.settings.scenes_dir / f"{sid}.zarr"
        stage = self.settings.scenes_dir / f".{sid}.zarr.attempt-{attempt}-{uuid.uuid4().hex[:6]}"
        # the ingest job of a scene is the only writer of its temporary stores (one active ingest
        # job per scene, and it is ours now): what a killed or stale attempt left goes
        for p in self.settings.scenes_dir.iterdir() if self.settings.scenes_dir.is_dir() else ():
            m = _SCENE_TEMP.match(p.name)
            if m and m["id"] == sid:
                _remove(p)

        def publish() -> None:
            if stage.is_dir() and not out.exists():
                os.rename(stage, out)

        try:
            if not out.exists():
                if inputs.get("path"):  # an inbox pass: its product sidecar lies within the inbox
                    src = Path(inputs["path"])
                    root = next(
                        (
                            d
                            for d in self.settings.inbox
                            if Path(os.path.abspath(d)) in Path(os.path.abspath(src)).parents
                        ),
                        False,
                    )
                else:  # an upload is one file: nothing beside it in the uploads folder is its
                    src, root = Path(inputs["upload"]), False
                st = self.settings
                ingest_in_child(
                    src,
                    stage,
                    sidecar_root=root,
                    progress=progress,
                    memory_mb=st.ingest_memory_mb or None,
                    limits={
                        "max_pixels": st.max_pixels,
                        "max_chunk_mb": st.max_chunk_mb,
                        "max_ratio": st.max_ratio,
                        "max_xml_mb": st.max_xml_mb,
                    },
                )
                from sarship.service.scenes import label_scene  # GET /scenes: the file name, the ingest time

                label_scene(stage, inputs.get("filename") or src.name)
            if not self.store.finish(
                job_id, self.owner, "successful", f"scene {sid} ready", {"scene": sid}, attempt=attempt, publish=publish
            ):
                log.warning(
                    "ingest %s (attempt %d) finished, but the job is no longer ours: discarded", job_id, attempt
                )
        except Dismissed:
            pass
        except IngestRefused as exc:
            self.store.finish(
                job_id, self.owner, "failed", self._public(str(exc)), {"bad_input": True}, attempt=attempt
            )
        except IngestTransient as exc:
            self._retry(job, f"the data folder is full: {exc}")
        except IngestCrashed as exc:
            log.error("ingest %s failed: %s", job_id, exc)
            self.store.finish(job_id, self.owner, "failed", self._public(f"ingest failed: {exc}"), attempt=attempt)
        except Exception as exc:
            why = transient_reason(exc)
            if why is not None:
                self._retry(job, why)
                return
            log.error("ingest %s failed: %s", job_id, traceback.format_exc())
            self.store.finish(
                job_id,
                self.owner,
                "failed",
                self._public(f"internal error: {type(exc).__name__}: {exc}"),
                attempt=attempt,
            )
        finally:
            _remove(stage)

    def _observe_failure(self, job: Job) -> None:
        if self.metrics is not None:
            took = time.time() - (job["started"] or time.time())
            self.metrics.duration.labels(job["process"], "failed").observe(took)

    def running(self) -> list[str]:
        with self._lock:
            return list(self._running)


def _remove(p: Path) -> None:
    if p.is_dir() and not p.is_symlink():
        shutil.rmtree(p, ignore_errors=True)
    elif p.exists() or p.is_symlink():
        try:
            p.unlink()
        except OSError:
            pass


def wait_final(store: JobStore, job_id: str, timeout: float) -> Job | None:
    """Poll the store until the job is final (or ``timeout``): the job row."""
    t_end = time.time() + timeout
    while True:
        job = store.get(job_id)
        if job is None or job["status"] in ("successful", "failed", "dismissed") or time.time() > t_end:
            return job
        time.sleep(0.2)
