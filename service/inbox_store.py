"""The inbox's records in the job store's SQLite file: one row per pass (a file version seen
in an inbox) and one row of loop state (the leader's lease, scan times, a requested scan).

Every change of a pass is one ``BEGIN IMMEDIATE`` transaction that first checks the row is
still in the state the caller saw (compare and set), and the jobs a pass creates are inserted
in the same transaction that records their IDs. So a crash (even ``kill -9``) at any point
leaves either the old state, to be redone, or the new one with its jobs, never a job without
its record; and two loops (a leader whose lease lapsed while it stalled and its successor)
can never ingest or submit a pass twice. A unique index allows one active pass (ingesting,
ingested, submitted) per scene key: another file of the same content is a ``duplicate``.

Pass statuses: ``waiting`` (seen, not yet complete), ``ingesting`` (its ingest job is
accepted or running), ``ingested`` (scene ready; final when no detectors are configured),
``submitted`` (detector jobs created), ``duplicate`` (the same content as an active pass: not
ingested again), ``quarantined`` (the file could not be ingested and was moved aside),
``failed`` (anything else: the ingest job failed for a reason not the file's, was dismissed,
or the file vanished before it was hashed).
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from typing import Any

from sarship.service.inbox_files import Signature
from sarship.service.store import INGEST, JobStore, active_ingest, insert_job, iso

STATUSES = ("waiting", "ingesting", "ingested", "submitted", "duplicate", "quarantined", "failed")
#: Passes that hold their scene key (a new file of the same content is a duplicate of them).
ACTIVE = ("ingesting", "ingested", "submitted")
#: Seen but not yet ingested: the ingest backlog.
BACKLOG = ("waiting", "ingesting")

_SCHEMA = """
CREATE TABLE IF NOT EXISTS inbox_passes (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    path TEXT NOT NULL,
    size INTEGER NOT NULL,
    mtime_ns INTEGER NOT NULL,
    nfiles INTEGER NOT NULL DEFAULT 1,
    stable_since REAL NOT NULL,
    key TEXT,
    sha256 TEXT,
    status TEXT NOT NULL,
    reason TEXT NOT NULL DEFAULT '',
    scene_id TEXT,
    ingest_job TEXT,
    plan TEXT NOT NULL DEFAULT '[]',
    jobs TEXT NOT NULL DEFAULT '[]',
    quarantine TEXT,
    seen REAL NOT NULL,
    updated REAL NOT NULL
);
CREATE INDEX IF NOT EXISTS inbox_passes_path ON inbox_passes (path, id);
CREATE INDEX IF NOT EXISTS inbox_passes_status ON inbox_passes (status, id);
CREATE UNIQUE INDEX IF NOT EXISTS inbox_passes_waiting ON inbox_passes (path) WHERE status = 'waiting';
CREATE UNIQUE INDEX IF NOT EXISTS inbox_passes_key ON inbox_passes (key)
    WHERE status IN ('ingesting', 'ingested', 'submitted');
CREATE TABLE IF NOT EXISTS inbox_state (
    id INTEGER PRIMARY KEY CHECK (id = 1),
    owner TEXT,
    lease_until REAL,
    last_scan REAL,
    next_scan REAL,
    scan_requested REAL
);
INSERT OR IGNORE INTO inbox_state (id) VALUES (1);
"""


class InboxStore:
    """Pass records and loop state, sharing the :class:`JobStore`'s connections (so that a
    pass and its jobs are written in one transaction)."""

    def __init__(self, jobs: JobStore):
        self.jobs = jobs
        jobs._conn().executescript(_SCHEMA)

    # ------------------------------------------------------------------ leader lease

    def lead(self, owner: str, lease_s: float, now: float | None = None) -> bool:
        """Whether ``owner`` leads the inbox loop now: it holds the lease (renewed when a third
        of it is used up) or takes it because it is free or expired. Reads first, so that
        followers do not write on every tick."""
        now = time.time() if now is None else now
        st = self.state()
        mine = st["owner"] == owner and (st["lease_until"] or 0) > now
        if mine and st["lease_until"] - now > lease_s * 2 / 3:
            return True
        if not mine and st["owner"] not in (None, owner) and (st["lease_until"] or 0) > now:
            return False
        with self.jobs._tx() as c:
            cur = c.execute(
                "UPDATE inbox_state SET owner = ?, lease_until = ? WHERE id = 1 AND "
                "(owner IS NULL OR owner = ? OR lease_until IS NULL OR lease_until <= ?)",
                (owner, now + lease_s, owner, now),
            )
            return cur.rowcount == 1

    def release(self, owner: str) -> None:
        """Give the lease up (a clean stop), so that another process takes over at once."""
        with self.jobs._tx() as c:
            c.execute("UPDATE inbox_state SET owner = NULL, lease_until = NULL WHERE id = 1 AND owner = ?", (owner,))

    def state(self) -> dict[str, Any]:
        return dict(self.jobs._conn().execute("SELECT * FROM inbox_state WHERE id = 1").fetchone())

    def scan_started(self, next_scan: float) -> None:
        with self.jobs._tx() as c:
            c.execute("UPDATE inbox_state SET next_scan = ?, scan_requested = NULL WHERE id = 1", (next_scan,))

    def scan_done(self, started: float) -> None:
        with self.jobs._tx() as c:
            c.execute("UPDATE inbox_state SET last_scan = ? WHERE id = 1", (started,))

    def request_scan(self) -> None:
        """Ask the leader (whichever process it is) for a scan now."""
        with self.jobs._tx() as c:
            c.execute("UPDATE inbox_state SET scan_requested = ? WHERE id = 1", (time.time(),))

    # ------------------------------------------------------------------ passes seen

    def latest_by_path(self) -> dict[str, dict[str, Any]]:
        """The newest record of every path."""
        rows = (
            self.jobs._conn()
            .execute("SELECT * FROM inbox_passes WHERE id IN (SELECT MAX(id) FROM inbox_passes GROUP BY path)")
            .fetchall()
        )
        return {r["path"]: dict(r) for r in rows}

    def add_waiting(self, path: str, sig: Signature, now: float) -> None:
        """A new file (or a new version of a file already handled): ``waiting``."""
        with self.jobs._tx() as c:
            c.execute(
                "INSERT OR IGNORE INTO inbox_passes (path, size, mtime_ns, nfiles, stable_since, status, "
                "seen, updated) VALUES (?, ?, ?, ?, ?, 'waiting', ?, ?)",
                (path, sig.size, sig.mtime_ns, sig.files, now, now, now),
            )

    def changed(self, pass_id: int, sig: Signature, now: float) -> None:
        """A waiting file changed (still being written): its settle time starts again."""
        with self.jobs._tx() as c:
            c.execute(
                "UPDATE inbox_passes SET size = ?, mtime_ns = ?, nfiles = ?, stable_since = ?, updated = ? "
                "WHERE id = ? AND status = 'waiting'",
                (sig.size, sig.mtime_ns, sig.files, now, now, pass_id),
            )

    def forget(self, pass_id: int) -> None:
        """A waiting file vanished before it was complete (renamed or deleted by its writer):
        it never was a pass."""
        with self.jobs._tx() as c:
            c.execute("DELETE FROM inbox_passes WHERE id = ? AND status = 'waiting'", (pass_id,))

    def rows(self, status: str, limit: int = 1000) -> list[dict[str, Any]]:
        rows = (
            self.jobs._conn()
            .execute("SELECT * FROM inbox_passes WHERE status = ? ORDER BY id LIMIT ?", (status, limit))
            .fetchall()
        )
        return [dict(r) for r in rows]

    # ------------------------------------------------------------------ transitions

    def take(
        self,
        pass_id: int,
        sig: Signature,
        sha256: str,
        key: str,
        scene_ready: bool,
        plan: list[dict[str, Any]],
        ingest_inputs: dict[str, Any],
    ) -> str | None:
        """A complete, hashed file becomes a pass, in one transaction: ``duplicate`` when an
        active pass holds its key; else ``ingested`` when the scene is already in the store
        (uploaded before), else ``ingesting`` with its ingest job (an accepted or running
        ingest of the same scene is reused) created here. ``plan`` (the detector jobs to submit
        once the scene is ready) is fixed now. The new status, or None when the row is no
        longer this waiting version of the file."""
        now = time.time()
        with self.jobs._tx() as c:
            row = c.execute(
                "SELECT * FROM inbox_passes WHERE id = ? AND status = 'waiting' AND size = ? AND "
                "mtime_ns = ? AND nfiles = ?",
                (pass_id, sig.size, sig.mtime_ns, sig.files),
            ).fetchone()
            if row is None:
                return None
            holder = c.execute(
                "SELECT path, status FROM inbox_passes WHERE key = ? AND status IN "
                "('ingesting', 'ingested', 'submitted')",
                (key,),
            ).fetchone()
            if holder is not None:
                c.execute(
                    "UPDATE inbox_passes SET status = 'duplicate', key = ?, sha256 = ?, scene_id = ?, "
                    "reason = ?, updated = ? WHERE id = ?",
                    (key, sha256, key, f"same content as {holder['path']} (not ingested again)", now, pass_id),
                )
                return "duplicate"
            job_id = None
            if not scene_ready:
                job_id = active_ingest(c, key) or insert_job(c, INGEST, ingest_inputs)
            status = "ingested" if scene_ready else "ingesting"
            c.execute(
                "UPDATE inbox_passes SET status = ?, key = ?, sha256 = ?, scene_id = ?, ingest_job = ?, "
                "plan = ?, reason = ?, updated = ? WHERE id = ?",
                (
                    status,
                    key,
                    sha256,
                    key,
                    job_id,
                    json.dumps(plan),
                    "scene already in the store" if scene_ready else "",
                    now,
                    pass_id,
                ),
            )
            return status

    def mark(self, pass_id: int, from_status: str, to_status: str, reason: str | None = None) -> bool:
        """``from_status`` -> ``to_status`` (with a reason); False if the row was not in
        ``from_status`` any more."""
        now = time.time()
        with self.jobs._tx() as c:
            if reason is None:
                cur = c.execute(
                    "UPDATE inbox_passes SET status = ?, updated = ? WHERE id = ? AND status = ?",
                    (to_status, now, pass_id, from_status),
                )
            else:
                cur = c.execute(
                    "UPDATE inbox_passes SET status = ?, reason = ?, updated = ? WHERE id = ? AND status = ?",
                    (to_status, reason, now, pass_id, from_status),
                )
            return cur.rowcount == 1

    def set_quarantine(self, pass_id: int, dest: str) -> bool:
        """Record where an ``ingesting`` pass's file is about to be moved (before moving it,
        so that a crash mid-way finds the same destination)."""
        with self.jobs._tx() as c:
            cur = c.execute(
                "UPDATE inbox_passes SET quarantine = ?, updated = ? WHERE id = ? AND "
                "status = 'ingesting' AND quarantine IS NULL",
                (dest, time.time(), pass_id),
            )
            return cur.rowcount == 1

    def submit(
        self, pass_id: int, inputs_of: Callable[[dict[str, Any]], tuple[str, dict[str, Any]]], note: str = ""
    ) -> list[str]:
        """An ``ingested`` pass's planned detector jobs, created in the transaction that
        records their IDs and marks the pass ``submitted`` (so they are created exactly once).
        ``inputs_of(entry) -> (process, inputs)``; ``note`` (e.g. why the jobs run without AIS)
        becomes the jobs' first message and is added to the pass's reason. The job IDs ([] if already
        submitted)."""
        now = time.time()
        with self.jobs._tx() as c:
            row = c.execute("SELECT plan FROM inbox_passes WHERE id = ? AND status = 'ingested'", (pass_id,)).fetchone()
            if row is None:
                return []
            ids = [insert_job(c, *inputs_of(entry), message=note) for entry in json.loads(row["plan"])]
            c.execute(
                "UPDATE inbox_passes SET status = 'submitted', jobs = ?, updated = ?, reason = CASE "
                "WHEN ? = '' THEN reason WHEN reason = '' THEN ? ELSE reason || '; ' || ? END WHERE id = ?",
                (json.dumps(ids), now, note, note, note, pass_id),
            )
            return ids

    def to_submit(self, limit: int = 100) -> list[dict[str, Any]]:
        """Ingested passes with detector jobs planned and not yet created."""
        rows = (
            self.jobs._conn()
            .execute(
                "SELECT * FROM inbox_passes WHERE status = 'ingested' AND plan != '[]' ORDER BY id LIMIT ?", (limit,)
            )
            .fetchall()
        )
        return [dict(r) for r in rows]

    # ------------------------------------------------------------------ reading

    def counts(self) -> dict[str, int]:
        out = {s: 0 for s in STATUSES}
        for r in self.jobs._conn().execute("SELECT status, COUNT(*) AS n FROM inbox_passes GROUP BY status"):
            out[r["status"]] = r["n"]
        return out

    def backlog(self, counts: dict[str, int] | None = None) -> int:
        counts = counts if counts is not None else self.counts()
        return sum(counts.get(s, 0) for s in BACKLOG)

    def list(self, limit: int = 100) -> list[dict[str, Any]]:
        """The newest ``limit`` passes, newest first."""
        rows = self.jobs._conn().execute("SELECT * FROM inbox_passes ORDER BY id DESC LIMIT ?", (limit,)).fetchall()
        return [dict(r) for r in rows]


def pass_doc(row: dict[str, Any]) -> dict[str, Any]:
    """A pass as ``GET /ingest`` lists it."""
    return {
        "key": row["key"],
        "file": row["path"],
        "status": row["status"],
        "sceneID": row["scene_id"],
        "jobs": json.loads(row["jobs"]),
        "ingestJob": row["ingest_job"],
        "reason": row["reason"] or None,
        "seen": iso(row["seen"]),
        "updated": iso(row["updated"]),
    }
