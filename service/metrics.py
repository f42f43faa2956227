"""Prometheus metrics of one API process (``GET /metrics``), prefix ``sarship_``.

Job counts by status and the inbox figures (ingest backlog, passes by status, quarantined
total, last and next scan) are read from the shared store at scrape time (so every API
process reports the same totals); durations, tiles, pixels and the AIS counts of finished jobs
(``sarship_ais_*``: detections matched, dark, vessels unmatched) are this process's own
counters. No job IDs or file names as labels (unbounded cardinality).
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import TYPE_CHECKING, Any

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, generate_latest
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric

from sarship.pipeline import __version__

if TYPE_CHECKING:
    from sarship.service.inbox_store import InboxStore
    from sarship.service.store import JobStore


class _JobCounts:
    def __init__(self, store: JobStore) -> None:
        self.store = store

    def collect(self) -> Iterator[Metric]:
        g = GaugeMetricFamily("sarship_jobs", "jobs in the store by status", labels=["status"])
        for status, n in self.store.counts().items():
            g.add_metric([status], n)
        yield g


class _InboxFigures:
    def __init__(self, db: InboxStore) -> None:
        self.db = db

    def collect(self) -> Iterator[Metric]:
        counts = self.db.counts()
        st = self.db.state()
        yield GaugeMetricFamily(
            "sarship_ingest_backlog",
            "inbox files seen but not yet ingested (waiting for their writer to finish, or ingesting)",
            value=self.db.backlog(counts),
        )
        g = GaugeMetricFamily("sarship_inbox_passes", "inbox passes by status", labels=["status"])
        for status, n in counts.items():
            g.add_metric([status], n)
        yield g
        yield CounterMetricFamily(
            "sarship_inbox_quarantined",
            "inbox files moved to the quarantine folder",
            value=counts.get("quarantined", 0),
        )
        yield GaugeMetricFamily(
            "sarship_inbox_last_scan_timestamp_seconds",
            "when the inbox was last scanned (0: never)",
            value=st["last_scan"] or 0.0,
        )
        yield GaugeMetricFamily(
            "sarship_inbox_next_scan_timestamp_seconds",
            "when the next inbox scan is due (0: none planned)",
            value=st["next_scan"] or 0.0,
        )


class Metrics:
    def __init__(self) -> None:
        self.registry = CollectorRegistry()
        r = self.registry
        self.build = Gauge("sarship_build_info", "build information", ["version"], registry=r)
        self.build.labels(__version__).set(1)
        self.duration = Histogram(
            "sarship_job_duration_seconds",
            "wall time of finished jobs",
            ["process", "status"],
            registry=r,
            buckets=(0.5, 1, 2, 5, 10, 30, 60, 120, 300, 600, 1800, 3600),
        )
        self.tiles = Counter("sarship_tiles_processed", "tiles processed by this API process's jobs", registry=r)
        self.pixels = Counter("sarship_pixels_processed", "scene pixels processed by successful jobs", registry=r)
        self.requests = Counter("sarship_jobs_submitted", "jobs accepted by this API process", ["process"], registry=r)
        # AIS (docs/ais.md): over the successful jobs given AIS files that this process finished
        self.ais_jobs = Counter("sarship_ais_jobs", "successful jobs matched to AIS files", registry=r)
        self.ais_detections = Counter("sarship_ais_detections", "detections of jobs matched to AIS", registry=r)
        self.ais_matched = Counter("sarship_ais_matched", "detections matched to an AIS vessel", registry=r)
        self.ais_dark = Counter(
            "sarship_ais_dark", "dark detections: no AIS vessel matched where the AIS covers the scene", registry=r
        )
        self.ais_unmatched = Counter(
            "sarship_ais_unmatched_vessels",
            "AIS vessels that reported inside a scene's footprint and matched no detection",
            registry=r,
        )

    def watch_store(self, store: JobStore) -> None:
        """Report the job counts and the inbox figures of the shared store."""
        from sarship.service.inbox_store import InboxStore

        self.registry.register(_JobCounts(store))
        self.registry.register(_InboxFigures(InboxStore(store)))

    def count_ais(self, record: dict[str, Any]) -> None:
        """Count a finished job's ``run.json`` ``ais`` record (``dark`` is null where the AIS
        does not cover the scene: counted as none)."""
        self.ais_jobs.inc()
        self.ais_detections.inc(int(record.get("detections") or 0))
        self.ais_matched.inc(int(record.get("matched") or 0))
        self.ais_dark.inc(int(record.get("dark") or 0))
        self.ais_unmatched.inc(int(record.get("unmatched_in_footprint") or 0))

    def render(self) -> bytes:
        return generate_latest(self.registry)
