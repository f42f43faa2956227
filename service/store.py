"""Durable job store: one SQLite file, safe for several API processes.

A job accepted is a row committed before the API answers ``201``, so it survives any crash.
Runners *claim* jobs with a lease (``lease_owner``, ``lease_until``) in one ``BEGIN
IMMEDIATE`` transaction, so two processes never run the same job at once; a runner renews
its lease while the job runs. A job whose lease has expired (its runner died, even by
``kill -9``, or was stopped longer than the lease) is claimable again and re-run from scratch
in the same row (``attempts`` counts the runs): it stays exactly once in the job list.

A job therefore *runs* at least once, and more than once when a runner stalls past its lease;
its results are *published* once. Every claim is an attempt (``attempts``); renewing and
finishing are fenced by owner and attempt, and the outputs an attempt wrote aside are moved
into place inside the transaction that finishes the job (:meth:`JobStore.finish` with
``publish``): a stale attempt can neither finish the job nor publish or overwrite outputs.

A job that failed for a fault of the service (a full disk, a busy job store, an unreachable
scheduler) is put back to ``accepted`` with a time before which it is not claimed
(``not_before``, :meth:`JobStore.retry_later`).

A job submitted for a scene whose upload is still being ingested records that ingest job in
``waits_for``: it is not claimed while the ingest job is accepted or running (so this holds
across restarts too); the runner then runs it, or fails it with the ingest's error.

The scheduled ingest keeps its pass records and its loop lease in the same file (tables
``inbox_passes`` and ``inbox_state``, :mod:`sarship.service.inbox_store`), so that a pass and the
jobs it creates are written in one transaction.
"""

from __future__ import annotations

import json
import sqlite3
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, TypeAlias, overload

STATUSES = ("accepted", "running", "successful", "failed", "dismissed")
FINAL = ("successful", "failed", "dismissed")

_SCHEMA = """
CREATE TABLE IF NOT EXISTS jobs (
    id TEXT PRIMARY KEY,
    process TEXT NOT NULL,
    inputs TEXT NOT NULL,
    status TEXT NOT NULL,
    progress INTEGER NOT NULL DEFAULT 0,
    message TEXT NOT NULL DEFAULT '',
    created REAL NOT NULL,
    started REAL,
    finished REAL,
    updated REAL NOT NULL,
    lease_owner TEXT,
    lease_until REAL,
    attempts INTEGER NOT NULL DEFAULT 0,
    result TEXT,
    waits_for TEXT,
    not_before REAL
);
CREATE INDEX IF NOT EXISTS jobs_status ON jobs (status, created);
-- ingest jobs by scene id and by status: GET /scenes and GET /scenes/{id} without a scan of
-- the job table (partial indexes: only ingest rows are indexed)
CREATE INDEX IF NOT EXISTS jobs_ingest_scene ON jobs (json_extract(inputs, '$.scene_id'), created)
    WHERE process = 'ingest';
CREATE INDEX IF NOT EXISTS jobs_ingest_status ON jobs (status, created) WHERE process = 'ingest';
"""

#: The process name of scene-ingest jobs (uploads and inbox passes).
INGEST = "ingest"

#: A job as the store hands it out: its row's columns, ``inputs`` and ``result`` decoded from JSON.
Job: TypeAlias = dict[str, Any]


@overload
def iso(t: float) -> str: ...
@overload
def iso(t: None) -> None: ...
@overload
def iso(t: float | None) -> str | None: ...
def iso(t: float | None) -> str | None:
    """RFC 3339 UTC timestamp of a POSIX time (None stays None)."""
    if t is None:
        return None
    return datetime.fromtimestamp(t, tz=UTC).isoformat().replace("+00:00", "Z")


class JobStore:
    """Jobs in SQLite (WAL mode, one connection per thread)."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._local = threading.local()
        self._conn().executescript(_SCHEMA)  # (executescript commits by itself)
        self._migrate()

    def _migrate(self) -> None:
        """Columns added since the first schema (a store written by an older version)."""
        c = self._conn()
        cols = {r["name"] for r in c.execute("PRAGMA table_info(jobs)").fetchall()}
        for col, typ in (("waits_for", "TEXT"), ("not_before", "REAL")):
            if col in cols:
                continue
            try:
                c.execute(f"ALTER TABLE jobs ADD COLUMN {col} {typ}")
            except sqlite3.OperationalError as exc:  # another process added it meanwhile
                if "duplicate column" not in str(exc):
                    raise

    def _conn(self) -> sqlite3.Connection:
        c = getattr(self._local, "conn", None)
        if c is None:
            c = sqlite3.connect(self.path, timeout=30.0, isolation_level=None)
            c.row_factory = sqlite3.Row
            c.execute("PRAGMA journal_mode=WAL")
            c.execute("PRAGMA synchronous=FULL")
            self._local.conn = c
        return c

    @contextmanager
    def _tx(self) -> Iterator[sqlite3.Connection]:
        c = self._conn()
        c.execute("BEGIN IMMEDIATE")
        try:
            yield c
        except BaseException:
            c.execute("ROLLBACK")
            raise
        c.execute("COMMIT")

    # ------------------------------------------------------------------ jobs

    def create(self, process: str, inputs: dict[str, Any], waits_for: str | None = None, message: str = "") -> Job:
        """A new accepted job; with ``waits_for`` (an ingest job's ID) it is not claimed until
        that job is final."""
        with self._tx() as c:
            job_id = insert_job(c, process, inputs, waits_for, message)
        return self._created(job_id)

    def _created(self, job_id: str) -> Job:
        """A job this store has just committed (jobs are never deleted: it is there)."""
        job = self.get(job_id)
        assert job is not None, job_id
        return job

    def active_ingest(self, scene_id: str) -> Job | None:
        """The accepted or running ingest job of ``scene_id``, if any."""
        job_id = active_ingest(self._conn(), scene_id)
        return self.get(job_id) if job_id else None

    def create_ingest(self, inputs: dict[str, Any]) -> tuple[Job, bool]:
        """The ingest job of ``inputs["scene_id"]``: the one already accepted or running for
        that scene (so one scene is never written by two jobs at once), else a new one; and
        whether it is new."""
        with self._tx() as c:
            job_id = active_ingest(c, inputs["scene_id"])
            new = job_id is None
            if job_id is None:
                job_id = insert_job(c, INGEST, inputs)
        return self._created(job_id), new

    def ingest_jobs(self, statuses: tuple[str, ...]) -> list[Job]:
        """Ingest jobs in ``statuses``, newest first (the partial index ``jobs_ingest_status``)."""
        marks = ", ".join("?" * len(statuses))
        rows = (
            self._conn()
            .execute(
                f"SELECT * FROM jobs WHERE process = 'ingest' AND status IN ({marks}) ORDER BY created DESC", statuses
            )
            .fetchall()
        )
        return [_row(r) for r in rows]

    def ingest_job_for_scene(self, scene_id: str) -> Job | None:
        """The newest ingest job of a scene (the expression index ``jobs_ingest_scene``)."""
        row: sqlite3.Row | None = (
            self._conn()
            .execute(
                "SELECT * FROM jobs WHERE process = 'ingest' AND "
                "json_extract(inputs, '$.scene_id') = ? ORDER BY created DESC LIMIT 1",
                (scene_id,),
            )
            .fetchone()
        )
        return _row(row)

    def active_jobs(self) -> list[Job]:
        """Accepted and running jobs (every process), oldest first (the index ``jobs_status``):
        what a scene deletion must not pull a scene from under."""
        rows = (
            self._conn()
            .execute("SELECT * FROM jobs WHERE status IN ('accepted', 'running') ORDER BY created")
            .fetchall()
        )
        return [_row(r) for r in rows]

    def get(self, job_id: str) -> Job | None:
        row: sqlite3.Row | None = self._conn().execute("SELECT * FROM jobs WHERE id = ?", (job_id,)).fetchone()
        return _row(row)

    def list(self, limit: int = 1000, offset: int = 0, status: str | None = None) -> list[Job]:
        if status:
            rows = (
                self._conn()
                .execute(
                    "SELECT * FROM jobs WHERE status = ? ORDER BY created DESC LIMIT ? OFFSET ?",
                    (status, limit, offset),
                )
                .fetchall()
            )
        else:
            rows = (
                self._conn()
                .execute("SELECT * FROM jobs ORDER BY created DESC LIMIT ? OFFSET ?", (limit, offset))
                .fetchall()
            )
        return [_row(r) for r in rows]

    def counts(self) -> dict[str, int]:
        rows = self._conn().execute("SELECT status, COUNT(*) AS n FROM jobs GROUP BY status").fetchall()
        out = {s: 0 for s in STATUSES}
        out.update({r["status"]: r["n"] for r in rows})
        return out

    def claim(self, owner: str, lease_s: float) -> Job | None:
        """Take the oldest job that is accepted (waiting for no ingest job still accepted or
        running, and not waiting to be retried: ``not_before``), or running with an expired
        lease (its runner died or stalled): mark it running under ``owner`` until
        ``now + lease_s``, as a new attempt (``attempts`` + 1, the attempt's fencing token)."""
        now = time.time()
        with self._tx() as c:
            row = c.execute(
                "SELECT id FROM jobs j WHERE (status = 'accepted' AND (not_before IS NULL OR not_before <= ?) AND "
                "(waits_for IS NULL OR NOT EXISTS (SELECT 1 FROM jobs d WHERE d.id = j.waits_for AND "
                "d.status IN ('accepted', 'running')))) "
                "OR (status = 'running' AND lease_until < ?) ORDER BY created LIMIT 1",
                (now, now),
            ).fetchone()
            if row is None:
                return None
            c.execute(
                "UPDATE jobs SET status = 'running', lease_owner = ?, lease_until = ?, started = ?, "
                "updated = ?, attempts = attempts + 1, progress = 0, message = ?, not_before = NULL "
                "WHERE id = ?",
                (owner, now + lease_s, now, now, "running", row["id"]),
            )
        return self.get(row["id"])

    def renew(
        self, job_id: str, owner: str, lease_s: float, progress: int | None = None, attempt: int | None = None
    ) -> bool:
        """Extend the lease (and record progress); False if the job is no longer ours to run
        (dismissed, or re-claimed after our lease lapsed: by another runner, or by this one as
        a newer ``attempt``)."""
        now = time.time()
        fence, args = _fence(job_id, owner, attempt)
        with self._tx() as c:
            if progress is None:
                cur = c.execute(
                    f"UPDATE jobs SET lease_until = ?, updated = ? WHERE {fence}", (now + lease_s, now, *args)
                )
            else:
                cur = c.execute(
                    f"UPDATE jobs SET lease_until = ?, updated = ?, progress = ? WHERE {fence}",
                    (now + lease_s, now, int(progress), *args),
                )
            return cur.rowcount == 1

    def finish(
        self,
        job_id: str,
        owner: str,
        status: str,
        message: str,
        result: dict[str, Any] | None = None,
        attempt: int | None = None,
        publish: Callable[[], None] | None = None,
    ) -> bool:
        """Final state of a job this runner holds (as ``attempt``); False if it is not ours any
        more. ``publish()`` (moving the attempt's outputs into place) runs inside the same
        transaction, only when the job is still ours: no other attempt can finish or publish
        meanwhile; if it raises, the job is left as it was and the error is raised."""
        assert status in ("successful", "failed")
        now = time.time()
        fence, args = _fence(job_id, owner, attempt)
        with self._tx() as c:
            cur = c.execute(
                "UPDATE jobs SET status = ?, message = ?, result = ?, finished = ?, updated = ?, "
                "progress = CASE WHEN ? = 'successful' THEN 100 ELSE progress END, lease_owner = NULL, "
                f"lease_until = NULL WHERE {fence}",
                (status, message, json.dumps(result) if result is not None else None, now, now, status, *args),
            )
            if cur.rowcount != 1:
                return False
            if publish is not None:
                publish()
            return True

    def retry_later(self, job_id: str, owner: str, attempt: int | None, delay_s: float, message: str) -> bool:
        """A job this runner holds failed for a fault of the service, not of its input: back to
        ``accepted``, claimable again ``delay_s`` from now (``not_before``), with ``message``
        saying why. False if the job is not ours any more."""
        now = time.time()
        fence, args = _fence(job_id, owner, attempt)
        with self._tx() as c:
            cur = c.execute(
                "UPDATE jobs SET status = 'accepted', message = ?, progress = 0, updated = ?, "
                f"lease_owner = NULL, lease_until = NULL, not_before = ? WHERE {fence}",
                (message, now, now + delay_s, *args),
            )
            return cur.rowcount == 1

    def retry_now(self, process: str | None = None) -> int:
        """Jobs waiting to be retried (``not_before``) may be claimed at once (of ``process``,
        or all); how many."""
        with self._tx() as c:
            cur = c.execute(
                "UPDATE jobs SET not_before = NULL WHERE status = 'accepted' AND not_before IS NOT NULL "
                "AND (? IS NULL OR process = ?)",
                (process, process),
            )
            return cur.rowcount

    def live_ingest_scenes(self) -> set[str]:
        """Scene ids whose ingest job is running under a lease that has not expired (its
        runner, in this or another process, may be writing the scene's temporary store)."""
        rows = (
            self._conn()
            .execute(
                "SELECT json_extract(inputs, '$.scene_id') AS s FROM jobs WHERE "
                "process = 'ingest' AND status = 'running' AND lease_until >= ?",
                (time.time(),),
            )
            .fetchall()
        )
        return {r["s"] for r in rows}

    def dismiss(self, job_id: str) -> tuple[Job | None, str | None]:
        """Dismiss (OGC API - Processes): accepted or running -> dismissed (a running job's
        runner stops at its next tile); successful or failed -> dismissed (the caller removes
        its outputs; ``finished`` keeps the time it finished). A dismissed job stays as it is.
        The job and the status it had before (None: no such job)."""
        now = time.time()
        with self._tx() as c:
            row = c.execute("SELECT status FROM jobs WHERE id = ?", (job_id,)).fetchone()
            before = row["status"] if row else None
            if before in ("accepted", "running"):
                c.execute(
                    "UPDATE jobs SET status = 'dismissed', message = 'dismissed by request', finished = ?, "
                    "updated = ?, lease_owner = NULL, lease_until = NULL WHERE id = ?",
                    (now, now, job_id),
                )
            elif before in ("successful", "failed"):
                c.execute(
                    "UPDATE jobs SET status = 'dismissed', message = ?, updated = ? WHERE id = ?",
                    (f"dismissed by request ({before}; its results are removed)", now, job_id),
                )
        return self.get(job_id), before

    def close(self) -> None:
        c = getattr(self._local, "conn", None)
        if c is not None:
            c.close()
            self._local.conn = None


def _fence(job_id: str, owner: str, attempt: int | None) -> tuple[str, tuple[str | int, ...]]:
    """The WHERE clause of an update by the runner holding a job: the job is running, under
    ``owner`` and (when given) as ``attempt``."""
    if attempt is None:
        return "id = ? AND lease_owner = ? AND status = 'running'", (job_id, owner)
    return "id = ? AND lease_owner = ? AND attempts = ? AND status = 'running'", (job_id, owner, int(attempt))


def insert_job(
    c: sqlite3.Connection, process: str, inputs: dict[str, Any], waits_for: str | None = None, message: str = ""
) -> str:
    """Insert an accepted job inside the caller's transaction (so that callers can record the
    job's ID in the same transaction that creates it); its ID."""
    now = time.time()
    job_id = uuid.uuid4().hex
    c.execute(
        "INSERT INTO jobs (id, process, inputs, status, message, created, updated, waits_for) "
        "VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
        (job_id, process, json.dumps(inputs), "accepted", message, now, now, waits_for),
    )
    return job_id


def active_ingest(c: sqlite3.Connection, scene_id: str) -> str | None:
    """The ID of an accepted or running ingest job of ``scene_id`` (inside a transaction)."""
    row = c.execute(
        "SELECT id FROM jobs WHERE process = 'ingest' AND json_extract(inputs, '$.scene_id') = ? "
        "AND status IN ('accepted', 'running') ORDER BY created LIMIT 1",
        (scene_id,),
    ).fetchone()
    return row["id"] if row else None


@overload
def _row(row: sqlite3.Row) -> Job: ...
@overload
def _row(row: sqlite3.Row | None) -> Job | None: ...
def _row(row: sqlite3.Row | None) -> Job | None:
    if row is None:
        return None
    d = dict(row)
    d["inputs"] = json.loads(d["inputs"])
    d["result"] = json.loads(d["result"]) if d["result"] else None
    return d
