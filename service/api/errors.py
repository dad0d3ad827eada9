"""Error bodies that say what to do, and the handlers that map exceptions to them.

Every error is JSON ``{"detail": ...}``:

- 422: ``detail`` is a list of :class:`~service.api.models.Problem` (``field`` as a dotted path
  such as ``spec.medium.g``, ``message``, ``allowed`` range, ``received`` value), one per problem;
  a request body is checked whole, so every bad field is named at once;
- anything else: ``detail`` is one sentence naming the problem and the way out.

Exceptions mapped here (store errors not caught by a route):

    RequestValidationError        -> 422 (problems)
    JobNotFound, VersionNotFound  -> 404
    JobNotActive                  -> 409
    IdempotencyConflict           -> 409
    ChecksumMismatch              -> 500 (the stored copy is corrupt; never served)
    sqlalchemy DBAPIError         -> 503 (job store unreachable)
"""

from __future__ import annotations

import math
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from sqlalchemy.exc import DBAPIError

from service.api.models import ErrorMessage, ValidationErrorBody
from service.store import ChecksumMismatch, IdempotencyConflict, JobNotActive, JobNotFound, VersionNotFound

__all__ = ["problems_from_errors", "problem", "install_error_handlers", "ERROR_RESPONSES", "error_responses"]

# Where a pydantic error's context names the bound: the key and how to show it.
_BOUNDS = (("gt", "> {}"), ("ge", ">= {}"), ("lt", "< {}"), ("le", "<= {}"),
           ("min_length", "at least {} characters"), ("max_length", "at most {} characters"))


def problem(field: str, message: str, allowed: str | None = None, received: Any = None) -> dict[str, Any]:
    """One 422 problem entry."""
    return {"field": field, "message": message, "allowed": allowed, "received": received}


def _field(loc: tuple[Any, ...]) -> str:
    """``("body", "spec", "medium", "g")`` -> ``spec.medium.g``; ``("query", "limit")`` stays."""
    parts = [str(p) for p in loc]
    if parts and parts[0] == "body":
        parts = parts[1:] or ["body"]
    return ".".join(parts) or "(request)"


def _allowed(e: dict[str, Any]) -> str | None:
    ctx = e.get("ctx") or {}
    if "allowed" in ctx:  # schema.constraints range errors
        return str(ctx["allowed"])
    if "expected" in ctx:  # enums and literals
        return str(ctx["expected"])
    bounds = [fmt.format(ctx[k]) for k, fmt in _BOUNDS if k in ctx]
    return " and ".join(bounds) or None


def _message(e: dict[str, Any]) -> str:
    if e["type"] == "extra_forbidden":
        return f"unknown key {e['loc'][-1]!r} is not allowed here (check the spelling)"
    if e["type"] == "missing":
        return "this field is required"
    msg = e["msg"]
    if "received" in msg:
        return msg
    value = repr(e.get("input"))
    return f"{msg}; received {value if len(value) <= 80 else value[:77] + '...'}"


def _jsonable(value: Any) -> Any:
    if isinstance(value, float) and not math.isfinite(value):
        return repr(value)  # JSON has no nan/inf
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    return repr(value)


def problems_from_errors(errors: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Pydantic / FastAPI error dicts -> 422 problem entries (field, message, allowed, received)."""
    out = []
    for e in errors:
        received = None if e["type"] == "missing" else _jsonable(e.get("input"))
        out.append(problem(_field(tuple(e["loc"])), _message(e), _allowed(e), received))
    return out


def _detail(status: int, message: str, headers: dict[str, str] | None = None) -> JSONResponse:
    return JSONResponse({"detail": message}, status_code=status, headers=headers)


def install_error_handlers(app: FastAPI) -> None:
    """Register the handlers listed in the module docstring."""

    @app.exception_handler(RequestValidationError)
    async def _validation(_request: Request, exc: RequestValidationError) -> JSONResponse:
        return JSONResponse({"detail": problems_from_errors(list(exc.errors()))}, status_code=422)

    @app.exception_handler(JobNotFound)
    async def _job_not_found(_request: Request, exc: JobNotFound) -> JSONResponse:
        return _detail(404, f"{exc}; list jobs with GET /v1/jobs")

    @app.exception_handler(VersionNotFound)
    async def _version_not_found(_request: Request, exc: VersionNotFound) -> JSONResponse:
        return _detail(404, f"{exc}; list datasets with GET /v1/datasets")

    @app.exception_handler(JobNotActive)
    async def _not_active(_request: Request, exc: JobNotActive) -> JSONResponse:
        return _detail(409, str(exc))

    @app.exception_handler(IdempotencyConflict)
    async def _conflict(_request: Request, exc: IdempotencyConflict) -> JSONResponse:
        return _detail(409, str(exc))

    @app.exception_handler(ChecksumMismatch)
    async def _corrupt(_request: Request, exc: ChecksumMismatch) -> JSONResponse:
        return _detail(500, f"checksum verification failed, file not served: {exc}")

    @app.exception_handler(DBAPIError)
    async def _db_down(_request: Request, exc: DBAPIError) -> JSONResponse:
        reason = str(exc.orig or exc).strip().splitlines()[0]
        return _detail(503, f"job store unavailable ({type(exc.orig or exc).__name__}: {reason}); "
                            "check BSSRDF_DATABASE_URL and that the database is up, then retry",
                       headers={"Retry-After": "5"})


def error_responses(*codes: int) -> dict[int | str, dict[str, Any]]:
    """OpenAPI ``responses=`` entries for these status codes."""
    return {code: ERROR_RESPONSES[code] for code in codes}


ERROR_RESPONSES: dict[int, dict[str, Any]] = {
    401: {"model": ErrorMessage, "description": "Missing or wrong bearer token."},
    404: {"model": ErrorMessage, "description": "No such job, dataset, version or file."},
    409: {"model": ErrorMessage, "description": "Conflicts with the stored state."},
    422: {"model": ValidationErrorBody,
          "description": "Invalid input: every bad field with the allowed range and the value received."},
    500: {"model": ErrorMessage, "description": "A stored file failed checksum verification."},
    503: {"model": ErrorMessage, "description": "The job store or storage is unreachable."},
}
