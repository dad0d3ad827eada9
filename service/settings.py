"""Service settings from the environment (prefix ``BSSRDF_``) via pydantic-settings.

Every process of the service (API, worker, local runner) reads the same settings, so one set of
environment variables configures a whole deployment::

    BSSRDF_DATABASE_URL=postgresql+psycopg://user@db:5432/bssrdf
    BSSRDF_STORAGE_URI=s3://bucket/bssrdf
    BSSRDF_API_TOKENS='["token-a", "token-b"]'

Defaults are the one-machine setup: an SQLite job store and a local data directory under
``./.bssrdf``. Use :func:`get_settings` (cached) rather than constructing :class:`Settings`
in request paths.
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

from pydantic import Field, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

__all__ = ["Settings", "get_settings", "sqlite_url_for", "DEFAULT_DATA_DIR"]

DEFAULT_DATA_DIR = "./.bssrdf"


def sqlite_url_for(data_dir: str | Path) -> str:
    """SQLAlchemy URL of the embedded job store inside ``data_dir`` (``jobs.sqlite``)."""
    return f"sqlite:///{Path(data_dir) / 'jobs.sqlite'}"


class Settings(BaseSettings):
    """Configuration of the job store, dataset storage, leases and the HTTP API."""

    model_config = SettingsConfigDict(env_prefix="BSSRDF_", extra="ignore")

    data_dir: str = Field(DEFAULT_DATA_DIR, description="Local data directory (SQLite store, default storage).")
    database_url: str | None = Field(
        None, description="SQLAlchemy URL of the job store; default: SQLite file in data_dir."
    )
    storage_uri: str | None = Field(
        None, description="pyarrow filesystem URI of dataset storage (path, file://, s3://...); default: data_dir/data."
    )
    lease_seconds: float = Field(60.0, gt=0, description="Lease length of a claimed task, seconds.")
    heartbeat_seconds: float | None = Field(
        None, gt=0, description="Heartbeat period of a worker, seconds; default lease_seconds / 4."
    )
    max_attempts: int = Field(3, ge=1, description="Claims of one task before its job fails.")
    api_tokens: list[str] = Field(default_factory=list, description="Bearer tokens accepted for mutating endpoints.")
    host: str = Field("127.0.0.1", description="Bind address of `bssrdf serve`.")
    port: int = Field(8000, ge=1, le=65535, description="Bind port of `bssrdf serve`.")
    read_open: bool = Field(True, description="Whether read endpoints are served without a token.")

    @model_validator(mode="after")
    def _fill_defaults(self) -> "Settings":
        if self.database_url is None:
            self.database_url = sqlite_url_for(self.data_dir)
        if self.storage_uri is None:
            self.storage_uri = str(Path(self.data_dir) / "data")
        if self.heartbeat_seconds is None:
            self.heartbeat_seconds = self.lease_seconds / 4
        if self.heartbeat_seconds >= self.lease_seconds:
            raise ValueError(
                f"heartbeat_seconds must be below lease_seconds={self.lease_seconds}; "
                f"received {self.heartbeat_seconds}"
            )
        return self


@lru_cache
def get_settings() -> Settings:
    """The process-wide settings, read once from the environment."""
    return Settings()
