"""``/healthz``, ``/readyz`` and ``/metrics`` (unversioned: probes and scrapers use fixed paths), and
``/v1/version`` (the code version recorded in every dataset version)."""

from __future__ import annotations

from fastapi import APIRouter, HTTPException
from fastapi.responses import JSONResponse, PlainTextResponse

from service.api.deps import ReadAuthDep, StorageDep, StoreDep
from service.api.errors import error_responses
from schema.version import code_version
from service.api.models import API_VERSION, Health, Readiness, VersionInfo
from service.api.prometheus import CONTENT_TYPE, render_metrics

__all__ = ["router"]

router = APIRouter(tags=["health"])


@router.get("/healthz", summary="Liveness: the process is up", response_model=Health)
def healthz() -> Health:
    """Always 200 while the process serves requests; checks nothing else (see /readyz)."""
    return Health()


def _first_line(exc: BaseException) -> str:
    text = str(getattr(exc, "orig", None) or exc).strip()
    return f"{type(exc).__name__}: {text.splitlines()[0] if text else ''}"


@router.get("/v1/version", summary="Code and API version", response_model=VersionInfo)
def version() -> VersionInfo:
    """The package version and git commit (as recorded in every dataset version's metadata) and
    the API version. Needs no token: it tells a client what it talks to."""
    return VersionInfo(api=API_VERSION, **code_version())


@router.get("/readyz", summary="Readiness: job store and storage reachable", response_model=Readiness,
            responses={503: {"model": Readiness, "description": "A check failed; its reason is in checks."}})
def readyz(store: StoreDep, storage: StorageDep) -> Readiness | JSONResponse:
    """200 when the job store answers a query and the storage root is a reachable directory;
    503 with the reason of each failed check otherwise (``{"detail": ...}`` when the store or
    storage could not even be opened)."""
    checks: dict[str, str] = {}
    for what, target in (("store", store), ("storage", storage)):
        try:
            target.ping()
            checks[what] = "ok"
        except HTTPException:
            raise  # the store could not even be opened (service.api.deps.StoreUnavailable): 503 with detail
        except Exception as exc:
            checks[what] = _first_line(exc)
    ready = all(v == "ok" for v in checks.values())
    body = Readiness(status="ok" if ready else "unavailable", checks=checks)
    return body if ready else JSONResponse(body.model_dump(), status_code=503)


@router.get("/metrics", summary="Prometheus metrics", response_class=PlainTextResponse,
            responses={200: {"content": {CONTENT_TYPE: {}}, "description": "Prometheus text format 0.0.4."},
                       **error_responses(401, 503)})
def metrics(_token: ReadAuthDep, store: StoreDep) -> PlainTextResponse:
    """Jobs by state; task claims, completed shards and merges, expired leases; photons simulated."""
    return PlainTextResponse(render_metrics(store.metrics()), media_type=CONTENT_TYPE)
