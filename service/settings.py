"""Service settings: environment variables with the ``SARSHIP_`` prefix, overridden by
``sarship serve`` flags (``sarship serve --help`` lists them).

The variables the layers below read too (``SARSHIP_SCHEDULER``, ``SARSHIP_LAND_MAX_MB``) are
fields of :mod:`sarship.pipeline.settings`, taken from there (one definition each).

The inbox settings (``SARSHIP_INBOX*``) are checked here, at start-up, so that a bad cron
expression, an unknown detector or a bad detector parameter stops ``sarship serve`` with one
line naming the setting and the key (exit 2) instead of failing pass after pass later.
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Annotated, Any

from pydantic import Field, ValidationInfo, field_validator
from pydantic_core import PydanticCustomError
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict

from sarship.pipeline import settings as env_settings
from sarship.pipeline.readers.limits import (
    DEFAULT_MAX_CHUNK_MB,
    DEFAULT_MAX_PIXELS,
    DEFAULT_MAX_RATIO,
    DEFAULT_MAX_XML_MB,
)

#: Scan interval used when neither an interval nor a cron expression is set.
DEFAULT_INBOX_INTERVAL_S = 30.0
#: The most AIS files of ``inbox_ais`` one pass's jobs are given, by default (docs/ais.md, "Inbox").
DEFAULT_INBOX_AIS_MAX_FILES = 100
#: Their largest total size by default, MiB (a DMA day file is about 2 GB and streams in about 7 s).
DEFAULT_INBOX_AIS_MAX_MB = 16384.0


def _bad(detail: str) -> PydanticCustomError:
    """A validation error whose message is exactly ``detail`` (no "Value error, " prefix)."""
    return PydanticCustomError("value_error", "{detail}", {"detail": detail})


def parse_inbox_detectors(value: Any) -> list[dict[str, Any]]:
    """The detector jobs submitted for each new pass, validated against the detectors'
    parameter models: a JSON list of objects ``[{"detector": "os_cfar", "pfa": 1e-6}]``
    (``device``/``channel`` allowed besides the parameters), a JSON list of names, or a comma
    list of names (``os_cfar,ca_cfar``: the detectors' defaults). Raises ``ValueError`` naming
    the entry and the bad key."""
    from sarship.pipeline import detectors
    from sarship.pipeline.errors import InputError
    from sarship.workers.request import JobRequest

    if value is None:
        return []
    if isinstance(value, str):
        text = value.strip()
        if not text:
            return []
        if text[0] in "[{":
            try:
                value = json.loads(text)
            except ValueError as exc:
                raise ValueError(f"not valid JSON ({exc})") from None
        else:
            value = [n for n in re.split(r"[,\s]+", text) if n]
    if isinstance(value, dict):
        value = [value]
    if not isinstance(value, list):
        raise ValueError("expected a list of detectors (JSON list of objects, or a comma list of names)")
    out: list[dict[str, Any]] = []
    for i, entry in enumerate(value):
        where = f"entry {i}"
        if isinstance(entry, str):
            entry = {"detector": entry}
        if not isinstance(entry, dict):
            raise ValueError(f'{where}: expected a detector name or an object {{"detector": NAME, ...}}')
        entry = dict(entry)
        name = entry.get("detector")
        if not isinstance(name, str):
            raise ValueError(f"{where}: key 'detector' (a detector name) is required")
        if name not in detectors.names():
            raise ValueError(f"{where}: unknown detector '{name}' (known: {', '.join(detectors.names())})")
        where = f"entry {i} ({name})"
        if "scene" in entry:
            raise ValueError(f"{where}: key 'scene' is not allowed (the inbox sets it to each new scene)")
        inputs = {k: v for k, v in entry.items() if k != "detector"}
        try:  # the job each new pass gets, validated by the model every job request uses
            JobRequest.from_inputs(name, {**inputs, "scene": "inbox-pass"})
        except InputError as exc:
            raise ValueError(f"{where}: {exc}") from None
        out.append(entry)
    return out


def check_cron(expr: str) -> str:
    """``expr`` if croniter accepts it (5 fields, or 6 with seconds); ``ValueError`` otherwise."""
    from croniter import croniter

    if not croniter.is_valid(expr):
        raise ValueError(
            f"'{expr}' is not a valid cron expression (5 fields: minute hour day month weekday, e.g. '*/10 * * * *')"
        )
    return expr


class Settings(BaseSettings):
    model_config = SettingsConfigDict(env_prefix="SARSHIP_", extra="ignore")

    data: Path = Field(Path("sarship-data"), description="data folder: job store, scenes, job outputs")
    host: str = Field("127.0.0.1", description="address the API listens on")
    port: int = Field(8080, ge=0, le=65535, description="port the API listens on")
    scheduler: str | None = env_settings.field("scheduler")  # shared with the command line
    workers: int | None = Field(
        None,
        ge=1,
        description="local cluster CPU worker processes (default: all cores; "
        "with GPU workers, all cores less two per GPU, at least 1)",
    )
    worker_threads: bool = Field(
        False,
        description="local cluster CPU workers as threads of the API process "
        "(one worker, --workers threads) instead of worker processes: "
        "starts in about a second, for small deployments and tests; "
        "a crash of a detector takes the API process with it, and "
        "a stop waits for the tiles in flight",
    )
    gpus: str = Field(
        "all",
        description="local cluster GPUs: all (one pinned worker per visible GPU), none, or a "
        "comma list of GPU IDs; tiles go to GPU workers unless a job asks "
        "device=cpu",
    )
    concurrency: int = Field(2, ge=1, le=64, description="jobs this API process runs at once")
    lease_s: float = Field(
        30.0,
        gt=1.0,
        description="job lease: a job whose runner stops renewing it is re-run (the stale run cannot publish)",
    )
    allowed_roots: list[Path] = Field(
        default_factory=list,
        description="folders a job may name scenes, land_mask and ais files in (besides DATA/scenes)",
    )
    sync_timeout_s: float = Field(600.0, gt=0.0, description="longest wait of a 'Prefer: respond-sync' execution")
    max_upload_mb: float = Field(4096.0, gt=0.0, description="largest scene upload (POST /scenes), MiB")
    max_ais_upload_mb: float = Field(
        1024.0, gt=0.0, description="largest AIS file upload (POST /ais), MiB: 413 beyond it"
    )
    max_body_kb: float = Field(
        1024.0,
        gt=0.0,
        description="largest request body of every other route (the JSON of an execution), KiB: 413 beyond it",
    )
    max_sync_waits: int = Field(
        8,
        ge=0,
        le=10000,
        description="'Prefer: respond-sync' executions waiting at once in this API process; "
        "one more is answered 503 with Retry-After (0: no synchronous execution)",
    )
    max_pixels: float = Field(
        DEFAULT_MAX_PIXELS,
        gt=0.0,
        description="largest image an ingest takes, rows x columns (checked from the header)",
    )
    max_chunk_mb: float = Field(
        DEFAULT_MAX_CHUNK_MB, gt=0.0, description="largest decoded compressed TIFF strip/tile an ingest takes, MiB"
    )
    max_ratio: float = Field(
        DEFAULT_MAX_RATIO,
        gt=0.0,
        description="largest ratio of declared decoded bytes to file size of a compressed or "
        "sparse TIFF an ingest takes",
    )
    max_xml_mb: float = Field(
        DEFAULT_MAX_XML_MB,
        gt=0.0,
        description="largest XML member (annotation, manifest...) of a Sentinel-1 SAFE product "
        "an ingest takes, MiB (checked before it is inflated)",
    )
    ingest_memory_mb: float = Field(
        4096.0,
        ge=0.0,
        description="address-space cap of the child process each ingest runs in, MiB "
        "(0: no cap); an ingest beyond it fails its job, the file is refused",
    )
    land_max_mb: float = env_settings.field("land_max_mb")  # shared with the land-mask reader
    scene_retention_days: float | None = Field(
        None,
        ge=0.0,
        allow_inf_nan=False,
        description="scenes in DATA/scenes older than this many days (since their ingest finished, "
        "else since the store was last written) that no accepted or running job names "
        "are removed, at start-up and then hourly (unset or 0: scenes are kept forever)",
    )
    min_free_mb: float = Field(
        100.0,
        ge=0.0,
        description="free space the data folder needs, MiB: below it /readyz answers 503 "
        "(not ready) with the reason (0: not checked)",
    )
    retry_s: float = Field(
        5.0,
        gt=0.0,
        description="first wait before a job that failed for a fault of the service (data folder "
        "full, job store busy, scheduler unreachable) is tried again, seconds; "
        "doubled at each attempt up to retry_max_s; such a job is never failed for it "
        "(an inbox pass is never quarantined for it)",
    )
    retry_max_s: float = Field(300.0, gt=0.0, description="longest wait between two tries of such a job, seconds")
    reconnect_s: float = Field(
        1.0,
        gt=0.0,
        description="with an external scheduler: first wait before the API makes a new Dask "
        "client once its client has closed (the scheduler went away), seconds; "
        "doubled after each failed try up to reconnect_max_s",
    )
    reconnect_max_s: float = Field(
        30.0, gt=0.0, description="longest wait between two reconnection tries to the scheduler, seconds"
    )
    preview_cache_mb: float = Field(
        256.0,
        ge=0.0,
        description="disk space of the cached preview PNGs of all jobs together, MiB; "
        "beyond it the oldest are removed (0: none kept)",
    )
    tokens: list[str] = Field(
        default_factory=list, description="API tokens (Authorization: Bearer TOKEN); when set, POST and DELETE need one"
    )
    allow_unauthenticated: bool = Field(
        False,
        description="serve on an address other machines can reach (not loopback) without tokens; refused otherwise",
    )
    dashboard_url: str | None = Field(
        None,
        pattern=r"^https?://\S+$",
        description="where GET /dashboard sends browsers when the scheduler "
        "serves a dashboard (default: the cluster's own link; set "
        "it when browsers reach the dashboard at another address)",
    )
    protect_reads: bool = Field(
        False, description="with tokens set, GET requests need one too (/livez, /readyz and /metrics stay open)"
    )
    # ---------------------------------------------------------------- scheduled ingest
    inbox: Annotated[list[Path], NoDecode] = Field(
        default_factory=list,
        description="inbox folders watched for new passes (JSON list or comma list); empty: the ingest loop is off",
    )
    inbox_interval_s: float | None = Field(
        None, gt=0.0, description=f"seconds between inbox scans (default {DEFAULT_INBOX_INTERVAL_S:g} when no cron)"
    )
    inbox_cron: str | None = Field(None, description="cron expression (UTC) of the inbox scans, instead of an interval")
    inbox_detectors: Annotated[list[dict[str, Any]], NoDecode] = Field(
        default_factory=list,
        description="detector jobs submitted for each new pass: JSON list like "
        '[{"detector": "os_cfar", "pfa": 1e-6}] or a comma list of names; '
        "empty: ingest only",
    )
    inbox_settle_s: float = Field(
        5.0,
        ge=0.0,
        description="a file is taken when its size and mtime have not changed for this long "
        "(at once when FILE.done exists and is not older than the file; the marker "
        "is removed when the file is taken)",
    )
    inbox_quarantine: Path | None = Field(
        None, description="where files that fail to ingest are moved (default DATA/quarantine)"
    )
    inbox_ais: Path | None = Field(
        None,
        description="folder of AIS files (CSV or NMEA, plain or compressed; sub-folders scanned) given to "
        "the detector jobs of each new pass as their 'ais' input (the newest first, within "
        "inbox_ais_max_files and inbox_ais_max_mb; the run keeps the reports of the scene's time and "
        "footprint); a pass whose scene has no georeference or time runs without AIS and says why; "
        "never inside an inbox folder; unset: no AIS",
    )
    inbox_ais_max_files: int = Field(
        DEFAULT_INBOX_AIS_MAX_FILES,
        ge=1,
        le=1000,
        description="the most AIS files of inbox_ais a pass's jobs read (the newest by modification time)",
    )
    inbox_ais_max_mb: float = Field(
        DEFAULT_INBOX_AIS_MAX_MB,
        gt=0.0,
        description="the largest total size of the AIS files of inbox_ais a pass's jobs read, MiB "
        "(newest first; a file that would pass it is left out, and the job says so)",
    )

    @field_validator("inbox", mode="before")
    @classmethod
    def _inbox_list(cls, v: Any) -> Any:
        if isinstance(v, str):
            text = v.strip()
            if not text:
                return []
            if text.startswith("["):
                try:
                    return json.loads(text)
                except ValueError as exc:
                    raise _bad(f"not a valid JSON list of folders ({exc})") from None
            return [p for p in re.split(r"[,:]", text) if p.strip()]
        return v

    @field_validator("inbox")
    @classmethod
    def _inbox_folders(cls, v: list[Path]) -> list[Path]:
        out = []
        for p in v:
            if not p.is_dir():
                raise _bad(f"inbox folder '{p}' does not exist or is not a folder")
            rp = p.resolve()
            if rp not in out:
                out.append(rp)
        return out

    @field_validator("inbox_ais")
    @classmethod
    def _inbox_ais(cls, v: Path | None, info: ValidationInfo) -> Path | None:
        if v is None or not str(v).strip():
            return None
        if not v.is_dir():
            raise _bad(f"AIS folder '{v}' does not exist or is not a folder")
        rv = v.resolve()
        for inbox in info.data.get("inbox") or ():
            if rv == inbox or inbox in rv.parents or rv in inbox.parents:
                raise _bad(
                    f"AIS folder '{v}' overlaps the inbox folder '{inbox}' (its files would be taken as passes): "
                    "keep it outside"
                )
        return rv

    @field_validator("inbox_detectors", mode="before")
    @classmethod
    def _detectors(cls, v: Any) -> list[dict[str, Any]]:
        try:
            return parse_inbox_detectors(v)
        except ValueError as exc:
            raise _bad(str(exc)) from None

    @field_validator("inbox_cron")
    @classmethod
    def _cron(cls, v: str | None, info: ValidationInfo) -> str | None:
        if v is None or not v.strip():
            return None
        if info.data.get("inbox_interval_s") is not None:
            raise _bad("set either inbox_interval_s or inbox_cron, not both")
        try:
            return check_cron(v.strip())
        except ValueError as exc:
            raise _bad(str(exc)) from None

    def local_workers(self) -> tuple[list[str], int]:
        """The local cluster (no ``scheduler``): the GPU IDs that get a pinned worker each, and
        the number of single-threaded CPU workers. Raises ``InputError`` for GPUs not visible."""
        import os

        from sarship.workers.gpus import parse_gpus

        gpu_ids = parse_gpus(self.gpus)
        cores = os.cpu_count() or 1
        return gpu_ids, self.workers or (max(1, cores - 2 * len(gpu_ids)) if gpu_ids else cores)

    @property
    def db_path(self) -> Path:
        return self.data / "jobs.sqlite"

    @property
    def jobs_dir(self) -> Path:
        return self.data / "jobs"

    @property
    def scenes_dir(self) -> Path:
        return self.data / "scenes"

    @property
    def uploads_dir(self) -> Path:
        return self.data / "uploads"

    @property
    def ais_dir(self) -> Path:
        """Uploaded AIS files (``POST /ais``): ``DATA/ais/ID`` and its record ``ID.json``."""
        return self.data / "ais"

    @property
    def quarantine_dir(self) -> Path:
        """Where the inbox moves files that failed to ingest."""
        return self.inbox_quarantine if self.inbox_quarantine is not None else self.data / "quarantine"

    @property
    def inbox_schedule(self) -> dict[str, Any | None]:
        """``{"interval_s": s, "cron": None}`` or ``{"interval_s": None, "cron": expr}``."""
        if self.inbox_cron:
            return {"interval_s": None, "cron": self.inbox_cron}
        return {"interval_s": self.inbox_interval_s or DEFAULT_INBOX_INTERVAL_S, "cron": None}

    def hide_paths(self, text: str) -> str:
        """``text`` (a job's error, a problem's detail) without the server's data folder: a path
        in ``DATA/scenes`` becomes its name there (how clients name scenes and land_mask files),
        any other path in ``DATA`` its path relative to it (``jobs/ID/...``, ``uploads/ID.tif``),
        and the folder itself ``the data folder``; as given, absolute and with symlinks
        resolved."""
        import os

        if not text:
            return text
        forms: dict[str, str] = {}
        for base, name in ((self.data, "the data folder"), (self.scenes_dir, "the scene folder")):
            for f in {str(base), os.path.abspath(base), str(base.resolve())}:
                if f not in ("", ".", "/"):
                    forms[f + os.sep] = ""
                    forms[f] = name
        alts = sorted(forms, key=len, reverse=True)  # the longest (most specific) first
        pattern = "|".join(re.escape(f) + ("" if f.endswith(os.sep) else r"(?![\w.-])") for f in alts)
        return re.sub(pattern, lambda m: forms[m.group(0)], text)

    def roots(self) -> list[Path]:
        """Resolved folders scenes may come from."""
        return [p.resolve() for p in [self.scenes_dir, *self.allowed_roots]]
