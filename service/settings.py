"""Service settings: environment variables with the ``SARSHIP_`` prefix, overridden by
``sarship serve`` flags (``sarship serve --help`` lists them)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

from pydantic import Field
from pydantic_settings import BaseSettings, SettingsConfigDict


class Settings(BaseSettings):
    model_config = SettingsConfigDict(env_prefix="SARSHIP_", extra="ignore")

    data: Path = Field(Path("sarship-data"), description="data folder: job store, scenes, job outputs")
    host: str = Field("127.0.0.1", description="address the API listens on")
    port: int = Field(8080, ge=0, le=65535, description="port the API listens on")
    scheduler: Optional[str] = Field(None, description="Dask scheduler address (default: a local cluster)")
    workers: Optional[int] = Field(None, ge=1, description="local cluster worker processes (default: all cores)")
    concurrency: int = Field(2, ge=1, le=64, description="jobs this API process runs at once")
    lease_s: float = Field(30.0, gt=1.0, description="job lease: a job whose runner stops renewing it is re-run")
    allowed_roots: list[Path] = Field(default_factory=list,
                                      description="folders a job may name scenes in (besides DATA/scenes)")
    sync_timeout_s: float = Field(600.0, gt=0.0, description="longest wait of a 'Prefer: respond-sync' execution")
    max_upload_mb: float = Field(4096.0, gt=0.0, description="largest scene upload (POST /scenes), MiB")
    tokens: list[str] = Field(default_factory=list,
                              description="API tokens (Authorization: Bearer TOKEN); when set, POST and DELETE need one")
    protect_reads: bool = Field(False, description="with tokens set, GET requests need one too "
                                                   "(/livez, /readyz and /metrics stay open)")

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

    def roots(self) -> list[Path]:
        """Resolved folders scenes may come from."""
        return [p.resolve() for p in [self.scenes_dir, *self.allowed_roots]]
