"""Service settings from the environment (prefix ``BSSRDF_``) via pydantic-settings.

Every process of the service (API, worker, local runner) reads the same settings, so one set of
environment variables configures a whole deployment::

    BSSRDF_DATABASE_URL=postgresql+psycopg://user@db:5432/bssrdf
    BSSRDF_STORAGE_URI=s3://bucket/bssrdf
    BSSRDF_API_TOKENS='["token-a", "token-b"]'

Limits (a submission beyond one is refused with a 4xx naming the field, the limit and the value;
see deploy/README.md, "Limits")::

    BSSRDF_MAX_JOB_PHOTONS=100000000000      photons x incidence angles x channels of one job
    BSSRDF_MAX_SHARD_CPU_SECONDS=1200        estimated CPU seconds of one shard (schema.estimate)
    BSSRDF_WORKER_SPEED=1.0                  the fleet's speed relative to BENCHMARKS.md's machine
    BSSRDF_MAX_BODY_BYTES=1048576            request body (413 before it is parsed)
    BSSRDF_MAX_HEADER_BYTES=16384            request line and headers (431 while they arrive)
    BSSRDF_MAX_HEADERS=100                   header fields of a request (431)
    BSSRDF_READ_TIMEOUT_SECONDS=10           for the request's head, then for its body, to arrive (408)
    BSSRDF_MAX_SHARD_BYTES=2000000000        estimated shard tally before compression (schema.sizes)
    BSSRDF_MAX_DATASET_BYTES=100000000000    estimated dataset tables before compression
    BSSRDF_MAX_JOB_TASKS=50000               shard tasks of one job (walk groups x shards)

Shard results (files in dataset storage under .jobs/<job id>/, removed once the version is
published unless BSSRDF_KEEP_SHARD_FILES=true); BSSRDF_FOLD_BATCH=8: the merge folds shards in
task order as they arrive, once that many in a row are done.

Defaults are the one-machine setup: an SQLite job store and a local data directory under
``./.bssrdf``. Use :func:`get_settings` (cached) rather than constructing :class:`Settings`
in request paths.
"""

from __future__ import annotations

import json
import sys
from functools import lru_cache
from pathlib import Path
from typing import Annotated, Any

from pydantic import Field, ValidationError, field_validator, model_validator
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict, SettingsError

from schema.spec import MAX_TASKS

__all__ = ["Settings", "get_settings", "settings_or_exit", "sqlite_url_for", "DEFAULT_DATA_DIR"]

DEFAULT_DATA_DIR = "./.bssrdf"

IDLE_BACKOFF_CAP = 8.0
"""A worker's default ``max_poll_seconds`` as a multiple of its ``poll_seconds``."""


def sqlite_url_for(data_dir: str | Path) -> str:
    """SQLAlchemy URL of the embedded job store inside ``data_dir`` (``jobs.sqlite``)."""
    return f"sqlite:///{Path(data_dir) / 'jobs.sqlite'}"


class Settings(BaseSettings):
    """Configuration of the job store, dataset storage, leases and the HTTP API."""

    # hide_input_in_errors: a validation error never shows the value (tokens, database passwords).
    model_config = SettingsConfigDict(env_prefix="BSSRDF_", extra="ignore", hide_input_in_errors=True)

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
    stall_seconds: float = Field(
        300.0, gt=0, description="A shard reporting no progress this long (after its first report) stops "
        "heartbeating: its lease expires and another worker redoes it.")
    api_tokens: Annotated[list[str], NoDecode] = Field(
        default_factory=list, description="Bearer tokens accepted for mutating endpoints: a JSON list of strings.")
    host: str = Field("127.0.0.1", description="Bind address of `bssrdf serve`.")
    port: int = Field(8000, ge=1, le=65535, description="Bind port of `bssrdf serve`.")
    read_open: bool = Field(True, description="Whether read endpoints are served without a token.")
    max_job_photons: int = Field(
        100_000_000_000, ge=1, description="Most photons of one job: photons x incidence angles x channels.")
    max_shard_cpu_seconds: float = Field(
        1200.0, gt=0, description="Most estimated CPU seconds of one shard (schema.estimate, one core).")
    worker_speed: float = Field(
        1.0, gt=0, description="Speed of the fleet's cores relative to the BENCHMARKS.md machine the CPU "
        "estimate is calibrated on (2.0: twice as fast).")
    max_body_bytes: int = Field(1_048_576, ge=1024, description="Largest request body; larger ones get 413.")
    max_header_bytes: int = Field(
        16384, ge=1024, description="Largest request line and headers, in bytes; larger ones get 431 "
        "(bssrdf serve refuses them while they arrive).")
    max_headers: int = Field(100, ge=10, description="Most header fields of a request; more get 431.")
    read_timeout_seconds: float = Field(
        10.0, gt=0, description="Seconds a request's line and headers, then its body, may take to arrive "
        "(a Content-Length larger than the body sent); later: 408 and the connection closed.")
    max_shard_bytes: int = Field(
        2_000_000_000, ge=1, description="Most estimated bytes of one shard's tally before compression "
        "(schema.sizes); the merge holds one shard and one accumulator of that size.")
    max_dataset_bytes: int = Field(
        100_000_000_000, ge=1, description="Most estimated bytes of a dataset version's tables before "
        "compression (schema.sizes).")
    max_job_tasks: int = Field(
        50_000, ge=1, le=MAX_TASKS, description="Most shard tasks of one job (walk groups x shards, schema.media): "
        "each is a row of the job store created at submission (BENCHMARKS.md, job creation).")
    keep_shard_files: bool = Field(
        False, description="Keep a job's shard results, fold and parts (storage .jobs/<job id>/) after its "
        "version is published (default: removed).")
    fold_batch: int = Field(
        8, ge=1, description="Shards the merge waits for before folding (the next ones in task order): each "
        "fold round rewrites the accumulator once, so 8 costs 1/8 of the shards' I/O.")

    @field_validator("api_tokens", mode="before")
    @classmethod
    def _tokens_json_list(cls, value: Any) -> Any:
        """``BSSRDF_API_TOKENS`` is JSON: ``'["tok1", "tok2"]'``; anything else says how to write it,
        and what was wrong with it without showing any of it (it holds secrets)."""
        if not isinstance(value, str):
            return value
        try:
            tokens = json.loads(value) if value.strip() else []
        except ValueError:
            tokens = ValueError
        wrong = _tokens_problem(tokens, len(value))
        if wrong is not None:
            raise ValueError("BSSRDF_API_TOKENS must be a JSON list of non-empty strings, e.g. "
                             f"BSSRDF_API_TOKENS='[\"TOKEN1\", \"TOKEN2\"]'; received {wrong} (not shown: it holds secrets)")
        return tokens

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


_JSON_KINDS = {dict: "a JSON object", list: "a list", str: "a JSON string", bool: "a JSON boolean", int: "a number",
               float: "a number", type(None): "null"}


def _tokens_problem(tokens: Any, length: int) -> str | None:
    """What is wrong with parsed BSSRDF_API_TOKENS, in words that show none of it (None: nothing)."""
    if tokens is ValueError:
        return f"text that is not JSON ({length} characters)"
    if not isinstance(tokens, list):
        return _JSON_KINDS.get(type(tokens), "not a list")
    for i, t in enumerate(tokens, 1):
        if not isinstance(t, str):
            return f"a list whose entry {i} is {_JSON_KINDS.get(type(t), 'not a string')}"
        if not t:
            return f"a list whose entry {i} is an empty string"
    return None


@lru_cache
def get_settings() -> Settings:
    """The process-wide settings, read once from the environment."""
    return Settings()


def settings_or_exit(**overrides: Any) -> Settings:
    """Settings for a command-line entry point: a bad ``BSSRDF_*`` variable is one readable line
    per problem on stderr and exit status 2, not a traceback."""
    try:
        return Settings(**overrides)
    except ValidationError as exc:
        lines = [f"  BSSRDF_{'_'.join(map(str, e['loc'])).upper() or '?'}: {e['msg'].removeprefix('Value error, ')}" for e in exc.errors()]
        print("bssrdf: invalid configuration:\n" + "\n".join(lines), file=sys.stderr)
    except SettingsError as exc:
        print(f"bssrdf: invalid configuration: {exc}", file=sys.stderr)
    raise SystemExit(2)
