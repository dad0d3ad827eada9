"""Dependencies of the routes, as ``Annotated`` aliases.

    SettingsDep   the app's settings, ``app.state.settings`` (tests may override :func:`app_settings`)
    StoreDep      the app's JobStore (one per process, created on first use); one that cannot
                  be opened is a :class:`StoreUnavailable`, whose first call is the 503
    StorageDep    the app's DatasetStorage
    AuthDep       a bearer token from ``settings.api_tokens``: mutating endpoints
    ReadAuthDep   the same unless ``settings.read_open``: read endpoints
    JobDep        the job named by the ``{job_id}`` path parameter, or 404

The dependencies that only read memory are ``async def``: FastAPI runs a plain ``def`` dependency
in its thread pool, a thread hop each (six per status read before, a quarter of its CPU time);
those that query the database (:func:`job_or_404`) stay plain functions, off the event loop. The
first request of a process opens the store (and migrates it) in :func:`get_store`, on the loop.
A store that cannot be opened is not a 503 there: the dependency runs before the body, path and
query are validated, and bad input must get its 4xx (not an outage) whatever the store does.

Routes declare the auth dependency as their first parameter: dependencies are resolved in order,
so a caller without a valid token gets 401 before anything is looked up (no 404 or 422 leaks).
With no tokens configured, authentication is off; :func:`service.api.app.create_app` allows that
only on a loopback address.
"""

from __future__ import annotations

import hashlib
import re
import secrets
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Annotated, TypeVar

from fastapi import Depends, HTTPException, Path, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from service.api.errors import shorten
from service.datasets import DatasetStorage
from service.settings import Settings
from service.store import JobNotFound, JobRecord, JobStore

__all__ = [
    "SettingsDep", "StoreDep", "StorageDep", "AuthDep", "ReadAuthDep", "JobDep", "JobIdPath", "JOB_ID_PATTERN",
    "app_settings", "get_store", "token_fingerprint", "get_storage", "require_token", "require_read_token", "job_or_404",
    "lookup_job", "StoreUnavailable",
    "Resources", "API_POOL_SIZE",
]



async def app_settings(request: Request) -> Settings:
    """The settings :func:`service.api.app.create_app` was made with. Read from the app's state,
    not installed as a dependency override: FastAPI analyses an overridden dependency's
    signature again on every request (a third of a status read's CPU time, BENCHMARKS.md)."""
    return request.app.state.settings


SettingsDep = Annotated[Settings, Depends(app_settings)]


@contextmanager
def _unavailable(what: str, setting: str) -> Iterator[None]:
    """Turn a failure to open the store or storage into a 503 that names the setting to check."""
    try:
        yield
    except Exception as exc:
        text = str(getattr(exc, "orig", None) or exc).strip()
        reason = f"{type(exc).__name__}: {text.splitlines()[0] if text else ''}"
        raise HTTPException(503, f"{what} unavailable ({reason}); check {setting} and that it is up, then retry",
                            headers={"Retry-After": "5"}) from exc


API_POOL_SIZE = 8
"""Job store connections an API process keeps open (requests run concurrently in the thread pool)."""


class Resources:
    """The store and storage of one app, created on first use (a down database does not stop the
    process from starting: ``/readyz`` reports it) and reused by every request."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._store: tuple[tuple, JobStore] | None = None
        self._storage: tuple[str, DatasetStorage] | None = None

    def store(self, settings: Settings) -> JobStore:
        key = (settings.database_url, settings.max_attempts)
        with self._lock:
            if self._store is None or self._store[0] != key:
                with _unavailable("job store", "BSSRDF_DATABASE_URL"):
                    self._store = (key, JobStore(settings.database_url, max_attempts=settings.max_attempts,
                                                 pool_size=API_POOL_SIZE))
            return self._store[1]

    def storage(self, settings: Settings) -> DatasetStorage:
        with self._lock:
            if self._storage is None or self._storage[0] != settings.storage_uri:
                with _unavailable("dataset storage", "BSSRDF_STORAGE_URI"):
                    self._storage = (settings.storage_uri, DatasetStorage(settings.storage_uri))
            return self._storage[1]

    def close(self) -> None:
        with self._lock:
            if self._store is not None:
                self._store[1].dispose()
            self._store = self._storage = None


class StoreUnavailable:
    """Stands in for a job store that could not be opened: calling any of its methods raises the
    503 (naming BSSRDF_DATABASE_URL). Routes call the store only once their input is valid."""

    def __init__(self, error: HTTPException) -> None:
        self._error = error

    def __getattr__(self, name: str):
        def unavailable(*_args, **_kwargs):
            raise HTTPException(self._error.status_code, self._error.detail, headers=self._error.headers)

        return unavailable


async def get_store(request: Request, settings: SettingsDep) -> JobStore:
    """The job store of ``settings.database_url`` (a :class:`StoreUnavailable` if it cannot be opened)."""
    try:
        return request.app.state.resources.store(settings)
    except HTTPException as exc:
        return StoreUnavailable(exc)  # type: ignore[return-value]


async def get_storage(request: Request, settings: SettingsDep) -> DatasetStorage:
    """The dataset storage at ``settings.storage_uri``."""
    return request.app.state.resources.storage(settings)


StoreDep = Annotated[JobStore, Depends(get_store)]
StorageDep = Annotated[DatasetStorage, Depends(get_storage)]

_bearer = HTTPBearer(
    auto_error=False,
    description="One of the tokens in BSSRDF_API_TOKENS. Needed by every mutating endpoint, and by "
    "read endpoints when BSSRDF_READ_OPEN=false.",
)
Credentials = Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)]


def _unauthorized(message: str, error: str | None = None) -> HTTPException:
    challenge = 'Bearer realm="bssrdf"' + (f', error="{error}"' if error else "")
    return HTTPException(401, message, headers={"WWW-Authenticate": challenge})


def _check(settings: Settings, credentials: HTTPAuthorizationCredentials | None) -> str | None:
    if not settings.api_tokens:
        return None  # authentication off (loopback only; create_app enforces it)
    if credentials is None:
        raise _unauthorized("this endpoint needs a bearer token: send the header 'Authorization: Bearer TOKEN' "
                            "with one of the tokens in BSSRDF_API_TOKENS (bssrdf client: --token or BSSRDF_TOKEN)")
    given = credentials.credentials.encode()
    # Constant time per token, and every token is compared (no early exit on a match).
    matches = [secrets.compare_digest(given, t.encode()) for t in settings.api_tokens]
    if not any(matches):
        raise _unauthorized("the bearer token is not one of BSSRDF_API_TOKENS; check --token / BSSRDF_TOKEN",
                            "invalid_token")
    return credentials.credentials


async def require_token(settings: SettingsDep, credentials: Credentials) -> str | None:
    """A valid bearer token (mutating endpoints)."""
    return _check(settings, credentials)


async def require_read_token(settings: SettingsDep, credentials: Credentials) -> str | None:
    """A valid bearer token unless reads are open (``settings.read_open``)."""
    return None if settings.read_open else _check(settings, credentials)


def token_fingerprint(token: str | None) -> str:
    """Who a token is, in a form safe to store and show: ``token sha256:1a2b3c4d5e6f``."""
    if token is None:
        return "anonymous (authentication off)"
    return "token sha256:" + hashlib.sha256(token.encode()).hexdigest()[:12]


AuthDep = Annotated[str | None, Depends(require_token)]
ReadAuthDep = Annotated[str | None, Depends(require_read_token)]


T = TypeVar("T")

JOB_ID_PATTERN = "^[0-9a-f]{8}-[0-9a-f]{4}-[0-9a-f]{4}-[0-9a-f]{4}-[0-9a-f]{12}$"
"""Job ids are uuid4 text (service.store.jobs): no other string names a job."""

JobIdPath = Annotated[str, Path(description="Job id returned by POST /v1/jobs (a UUID).")]


def lookup_job(job_id: str, lookup: Callable[[str], T]) -> T:
    """``lookup(job_id)`` (a store read raising JobNotFound), or 404; an id that is no UUID is
    not looked up."""
    try:
        if re.fullmatch(JOB_ID_PATTERN, job_id) is None:
            raise JobNotFound(shorten(job_id))
        return lookup(job_id)
    except JobNotFound as exc:
        raise HTTPException(404, f"{exc}; job ids are UUIDs as returned by POST /v1/jobs; "
                                 "list jobs with GET /v1/jobs") from None


def job_or_404(job_id: JobIdPath, store: StoreDep) -> JobRecord:
    """The job named in the path (404 if there is none)."""
    return lookup_job(job_id, store.get_job)


JobDep = Annotated[JobRecord, Depends(job_or_404)]
