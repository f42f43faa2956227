"""Scheduled ingest of satellite passes: the inbox loop.

One thread per API process; only the holder of the inbox lease (a row in the shared SQLite
store, taken with ``BEGIN IMMEDIATE``, renewed while it works and taken over when it expires)
does anything, so a deployment of several API processes on one store runs one loop. A new
leader scans at once (catching up on what arrived while no one led), then on the schedule
(``SARSHIP_INBOX_INTERVAL_S`` or ``SARSHIP_INBOX_CRON``, UTC) or when ``POST /ingest/scan``
asks. Every tick (at most a second apart) the leader also:

1. re-checks the ``waiting`` files: a file is taken once its size and mtime have been the
   same for ``SARSHIP_INBOX_SETTLE_S`` seconds, or at once when ``FILE.done`` exists and is not
   older than the file (:func:`~sarship.service.inbox_files.marked_done`; a marker is
   consumed, removed, when its file is taken, so it never marks the next file of that name);
2. takes a complete file: streams it through SHA-256 (in this thread, never the event loop's;
   the lease is renewed between chunks), and records it as a pass whose scene key is the
   first 16 hex digits, the scheme of ``POST /scenes``: an ``ingest`` job is created in the
   same transaction (or the pass is a ``duplicate`` of an earlier file of that content);
3. follows the ingest jobs (the runners of any API process run them): a success submits the
   configured detector jobs, created in the transaction that marks the pass ``submitted``
   (with ``SARSHIP_INBOX_AIS``, each gets that folder's AIS files as its ``ais`` input, unless
   the scene has no georeference or time: :meth:`Inbox.ais_for`, docs/ais.md); a
   failure caused by the file moves it to the quarantine folder with ``NAME.reason.txt``
   beside it, and the loop goes on. A fault of ours (the data folder full) is no failure: the
   runner tries the ingest job again after a back-off, and the pass stays ``ingesting``.
   ``POST /ingest/scan`` retries such jobs at once, and takes again the passes that ``failed``
   for a reason not the file's (not those whose ingest job was dismissed).

Ingested files are left where they are: the scene store holds the data from then on, the
pass record (path, size, mtime, content hash) keeps the loop from taking them again, an inbox
may be a read-only or shared mount, and moving a multi-gigabyte pass out of it could mean a
copy across file systems. Delete them whenever convenient; a file whose size or mtime changes
is a new version and is looked at again (by content: the same content is a ``duplicate``).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any

from sarship.service.inbox_files import (
    Signature,
    ais_files,
    list_passes,
    marked_done,
    marker,
    move_into,
    quarantine_target,
    scene_key,
    settled,
    sha256_of,
    signature,
    write_reason,
)
from sarship.service.inbox_store import InboxStore
from sarship.service.settings import DEFAULT_INBOX_INTERVAL_S, Settings
from sarship.service.store import INGEST, JobStore, iso

if TYPE_CHECKING:
    from sarship.service.runner import Runner

log = logging.getLogger("sarship.inbox")


class LostLease(Exception):
    """Another process leads the inbox now (this one stalled past its lease), or we stop."""


class Schedule:
    """When the inbox is scanned: every ``interval_s`` seconds, or at the times of a cron
    expression (evaluated in UTC: pass schedules are in UTC)."""

    def __init__(self, interval_s: float | None = None, cron: str | None = None):
        self.cron = cron
        self.interval_s = None if cron else (interval_s or DEFAULT_INBOX_INTERVAL_S)

    def next_after(self, t: float) -> float:
        if self.cron:
            from croniter import croniter

            return float(croniter(self.cron, datetime.fromtimestamp(t, UTC)).get_next(float))
        assert self.interval_s is not None  # (set by __init__ whenever there is no cron)
        return t + self.interval_s


class Inbox:
    """The inbox loop of one API process (see the module docstring)."""

    def __init__(self, settings: Settings, store: JobStore, owner: str, wake_runner: Callable[[], None] | None = None):
        self.settings = settings
        self.store = store
        self.db = InboxStore(store)
        self.owner = owner
        self.wake_runner = wake_runner or (lambda: None)
        self.enabled = bool(settings.inbox)
        sched = settings.inbox_schedule
        self.schedule = Schedule(sched["interval_s"], sched["cron"])
        self.lease_s = settings.lease_s
        base = min(self.schedule.interval_s or 1.0, settings.inbox_settle_s or 1.0)
        self.tick_s = min(1.0, max(0.1, base / 2))
        self._stop = threading.Event()
        self._wake = threading.Event()
        self._thread: threading.Thread | None = None
        self._leading = False
        self._renewed = 0.0
        self._missing: set[Path] = set()

    # ------------------------------------------------------------------ life cycle

    def start(self) -> None:
        if not self.enabled:
            return
        self.settings.quarantine_dir.mkdir(parents=True, exist_ok=True)
        self._thread = threading.Thread(target=self._loop, name="sarship-inbox", daemon=True)
        self._thread.start()
        log.info(
            "inbox: watching %s (%s)",
            ", ".join(map(str, self.settings.inbox)),
            f"cron {self.schedule.cron} UTC" if self.schedule.cron else f"every {self.schedule.interval_s:g} s",
        )

    def stop(self) -> None:
        self._stop.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout=30)
            try:
                self.db.release(self.owner)
            except Exception:  # the store may be gone at shutdown: the lease then just expires
                log.exception("inbox: could not release the lease")

    def request_scan(self) -> None:
        """A scan now, by whichever process leads (``POST /ingest/scan``): ingest jobs waiting to
        be retried (a full disk) may run at once, and passes that failed for a reason not the
        file's are taken again."""
        self.db.request_scan()
        self.store.retry_now(INGEST)
        self._wake.set()

    def _loop(self) -> None:
        while not self._stop.is_set():
            try:
                self.tick()
            except LostLease:
                self._leading = False
            except Exception:  # the store locked for long, a file system error: log, go on
                log.exception("inbox: tick failed")
            self._wake.wait(self.tick_s)
            self._wake.clear()

    def tick(self) -> None:
        """One round: lead or not; if leading, scan when due, then follow waiting files and
        ingest jobs."""
        now = time.time()
        if not self.db.lead(self.owner, self.lease_s, now):
            if self._leading:
                log.warning("inbox: lease lost to another process")
            self._leading = False
            return
        if not self._leading:
            log.info("inbox: %s leads the inbox loop", self.owner)
        new_leader, self._leading, self._renewed = not self._leading, True, now
        st = self.db.state()
        if new_leader or st["scan_requested"] or st["next_scan"] is None or now >= st["next_scan"]:
            self.scan(now, retry_failed=bool(st["scan_requested"]))
        self.follow_waiting()
        self.advance()

    def _busy(self) -> None:
        """Called often during long work: stop promptly, keep the lease, or give up if it
        went to another process."""
        if self._stop.is_set():
            raise LostLease("stopping")
        now = time.time()
        if now - self._renewed > self.lease_s / 3:
            if not self.db.lead(self.owner, self.lease_s, now):
                raise LostLease("lease lost")
            self._renewed = now

    # ------------------------------------------------------------------ scanning

    def scan(self, now: float, retry_failed: bool = False) -> int:
        """Record every new file (or new version of a file) in the inboxes as ``waiting``
        (with ``retry_failed``, a scan asked for: also the files whose pass failed for a
        reason not the file's, unless its ingest job was dismissed); the number recorded."""
        self.db.scan_started(self.schedule.next_after(now))
        known = self.db.latest_by_path()
        skip = (self.settings.quarantine_dir.resolve(), self.settings.data.resolve())
        added = 0
        for root in self.settings.inbox:
            if not root.is_dir():
                if root not in self._missing:
                    log.warning("inbox: folder %s is missing; it is scanned again when it is back", root)
                    self._missing.add(root)
                continue
            self._missing.discard(root)
            for p in list_passes(root, skip):
                self._busy()
                row = known.get(str(p))
                if row is not None and row["status"] == "waiting":
                    continue  # followed by follow_waiting
                sig = signature(p)
                if sig is None:
                    continue
                if (
                    row is not None
                    and row["status"] != "quarantined"
                    and _sig(row) == sig
                    and not (retry_failed and row["status"] == "failed" and "dismissed" not in row["reason"])
                ):
                    continue  # this version was handled; a quarantined file put back is tried again
                self.db.add_waiting(str(p), sig, now)
                added += 1
        self.db.scan_done(now)
        return added

    def follow_waiting(self) -> None:
        """Take the waiting files that are complete; restart the settle time of those that
        changed; forget those that vanished."""
        for row in self.db.rows("waiting"):
            self._busy()
            p = Path(row["path"])
            sig = signature(p)
            now = time.time()
            if sig is None:
                self.db.forget(row["id"])
                continue
            has_marker = marked_done(p, sig)
            if sig != _sig(row):
                self.db.changed(row["id"], sig, now)
                if not has_marker:
                    continue
                row = {**row, "stable_since": now}
            if settled(row["stable_since"], now, self.settings.inbox_settle_s, has_marker):
                self._take(row, p, sig, has_marker)

    def _take(self, row: dict[str, Any], p: Path, sig: Signature, has_marker: bool) -> None:
        try:
            sha = sha256_of(p, on_chunk=self._busy)
        except OSError as exc:  # vanished or unreadable mid-way: looked at again next round
            log.warning("inbox: cannot read %s: %s", p, exc)
            return
        after = signature(p)
        if after != sig and not has_marker:  # written to while we hashed: not complete after all
            if after is None:
                self.db.forget(row["id"])
            else:
                self.db.changed(row["id"], after, time.time())
            return
        key = scene_key(sha)
        ready = (self.settings.scenes_dir / f"{key}.zarr").is_dir()
        inputs = {
            "path": str(p),
            "scene_id": key,
            "filename": p.name,
            "sha256": sha,
            "bytes": sig.size,
            "origin": "inbox",
        }
        status = self.db.take(row["id"], sig, sha, key, ready, self.settings.inbox_detectors, inputs)
        if status is not None:
            log.info("inbox: %s -> %s (scene %s)", p, status, key)
            if has_marker:  # consumed with its pass: it must not mark the next file of this name
                try:
                    marker(p).unlink(missing_ok=True)
                except OSError as exc:  # (a read-only inbox: the mtime rule still holds)
                    log.warning("inbox: cannot remove the marker of %s: %s", p, exc)
        if status == "ingesting":
            self.wake_runner()

    # ------------------------------------------------------------------ following jobs

    def advance(self) -> None:
        """Move passes on as their ingest jobs finish; submit the detector jobs of ingested
        passes."""
        for row in self.db.rows("ingesting"):
            self._busy()
            job = self.store.get(row["ingest_job"]) if row["ingest_job"] else None
            if job is None:
                self.db.mark(row["id"], "ingesting", "failed", f"its ingest job {row['ingest_job']} is gone")
            elif job["status"] == "successful":
                if self.db.mark(row["id"], "ingesting", "ingested"):
                    log.info("inbox: %s ingested as scene %s", row["path"], row["scene_id"])
            elif job["status"] == "failed":
                if (job["result"] or {}).get("bad_input"):
                    self._quarantine(row, job["message"])
                else:
                    self.db.mark(row["id"], "ingesting", "failed", f"ingest failed: {job['message']}")
            elif job["status"] == "dismissed":
                self.db.mark(row["id"], "ingesting", "failed", "its ingest job was dismissed")
        for row in self.db.to_submit():
            self._busy()
            ais, note = self.ais_for(row["scene_id"])
            extra = {"ais": list(ais)} if ais else {}

            def job_of(
                entry: dict[str, Any], scene: str = row["scene_id"], extra: dict[str, Any] = extra
            ) -> tuple[str, dict[str, Any]]:
                params = {k: v for k, v in entry.items() if k != "detector"}
                return entry["detector"], {"scene": scene, **params, **extra}

            ids = self.db.submit(row["id"], job_of, note)
            if ids:
                log.info("inbox: scene %s: submitted %s", row["scene_id"], ", ".join(ids))
                if note:
                    log.warning("inbox: scene %s: %s", row["scene_id"], note)
                self.wake_runner()

    def ais_for(self, scene_id: str) -> tuple[tuple[str, ...], str]:
        """The ``ais`` input of a pass's detector jobs (``SARSHIP_INBOX_AIS``'s files,
        :func:`~sarship.service.inbox_files.ais_files`) and a note for the jobs and the pass
        (empty when there is nothing to say). A scene without georeference or time gets no AIS
        (its jobs run, and the note says why), never a failure."""
        folder = self.settings.inbox_ais
        if folder is None:
            return (), ""
        why = scene_lacks_ais_needs(self.settings.scenes_dir / f"{scene_id}.zarr")
        if why:
            return (), f"no AIS matching: {why}"
        if not folder.is_dir():
            return (), f"no AIS matching: the AIS folder {folder} is missing"
        choice = ais_files(folder, self.settings.inbox_ais_max_files, int(self.settings.inbox_ais_max_mb * 2**20))
        if not choice.paths:
            return (), "; ".join(("no AIS matching: no AIS file in the AIS folder", *choice.left_out))
        return choice.paths, "; ".join(choice.left_out)

    def _quarantine(self, row: dict[str, Any], reason: str) -> None:
        """Move a file that failed to ingest to the quarantine folder, ``NAME.reason.txt``
        beside it; then record the pass ``quarantined``. Each step can be redone after a crash:
        the destination is recorded before the move, and the move is skipped once done."""
        src = Path(row["path"])
        dest = (
            Path(row["quarantine"])
            if row["quarantine"]
            else quarantine_target(self.settings.quarantine_dir, src, row["key"])
        )
        if not row["quarantine"] and not self.db.set_quarantine(row["id"], str(dest)):
            return
        try:
            if src.exists() or src.is_symlink():
                move_into(src, dest)
            note = "" if dest.exists() else " (the file was gone before it could be moved)"
            write_reason(
                dest,
                {
                    "reason": reason + note,
                    "file": str(src),
                    "sha256": row["sha256"],
                    "scene": row["key"],
                    "ingest_job": row["ingest_job"],
                    "time": iso(time.time()),
                },
            )
            marker(src).unlink(missing_ok=True)
        except OSError as exc:
            self.db.mark(row["id"], "ingesting", "failed", f"{reason}; it could not be quarantined: {exc}")
            log.error("inbox: %s could not be quarantined: %s", src, exc)
            return
        if self.db.mark(row["id"], "ingesting", "quarantined", reason):
            log.warning("inbox: %s quarantined to %s: %s", src, dest, reason)

    # ------------------------------------------------------------------ reading

    def status(self, limit: int = 100) -> dict[str, Any]:
        """The ``GET /ingest`` document (from the store: the same in every API process)."""
        from sarship.service.inbox_store import pass_doc

        st = self.db.state()
        counts = self.db.counts()
        leader = st["owner"] if st["owner"] and (st["lease_until"] or 0) > time.time() else None
        return {
            "enabled": self.enabled,
            "inboxes": [str(p) for p in self.settings.inbox],
            "schedule": self.settings.inbox_schedule,
            "leader": leader,
            "last_scan": iso(st["last_scan"]),
            "next_scan": iso(st["next_scan"]) if self.enabled else None,
            "backlog": self.db.backlog(counts),
            "counts": counts,
            "passes": [pass_doc(r) for r in self.db.list(limit)],
        }


def _sig(row: dict[str, Any]) -> Signature:
    return Signature(row["size"], row["mtime_ns"], row["nfiles"])


def scene_lacks_ais_needs(scene: Path) -> str:
    """Why the scene store ``scene`` cannot be matched with AIS (no georeference, no time: the
    run's own check, :func:`~sarship.pipeline.run.ais.ais_options`), or ``""`` when it can."""
    import numpy as np
    import zarr

    from sarship.pipeline.ais.scene_time import line_times

    try:
        attrs = dict(zarr.open_group(str(scene), mode="r").attrs)
    except Exception as exc:  # (zarr raises several types; the run reports a bad store itself)
        return f"the scene's attributes cannot be read ({type(exc).__name__})"
    if not any(k in attrs for k in ("crs", "transform", "gcps")):
        return "the scene is not georeferenced (no transform or GCPs), so its detections have no lon/lat"
    if line_times(attrs, np.zeros(1)) is None:
        return "the scene states no acquisition time (sar_geometry.first_line_time, acquisition_start or acquired)"
    return ""


def start_inbox(settings: Settings, store: JobStore, runner: Runner) -> Inbox:
    """The inbox loop of this API process, started (idle unless ``settings.inbox``)."""
    inbox = Inbox(settings, store, runner.owner, runner.wake.set)
    inbox.start()
    return inbox
