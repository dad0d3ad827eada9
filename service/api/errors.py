"""Error bodies that say what to do, and the handlers that map exceptions to them.

Every error is JSON ``{"detail": ...}``:

- 422: ``detail`` is a list of :class:`~service.api.models.Problem` (``field`` as a dotted path
  such as ``spec.medium.g``, ``message``, ``allowed`` range, ``received`` value), one per problem;
  a request body is checked whole, so every bad field is named at once;
- anything else: ``detail`` is one sentence naming the problem and the way out.

Exceptions mapped here (store errors not caught by a route):

    RequestValidationError        -> 422 (problems; a body that is not JSON in UTF-8, a
                                     :class:`~service.api.bodies.BadBody`, is field ``body``)
    HTTPException 405             -> 405 whose ``Allow`` lists the methods of every route of the path
    JobNotFound, VersionNotFound  -> 404
    VersionDeleted                -> 410 (the tombstone: who deleted it, the spec hash)
    JobNotActive, JobPublished    -> 409
    IdempotencyConflict           -> 409
    ChecksumMismatch              -> 500 (the stored copy is corrupt; never served)
    sqlalchemy OperationalError,
    InterfaceError                -> 503 (job store unreachable; other database errors are bugs: 500)

Values received are echoed shortened (:func:`shorten`: strings to 80 characters, integers past
10**30 to 4 significant digits, lists and objects to their first entries, nesting to 4 levels), so
a huge request never gets a huge answer.
"""

from __future__ import annotations

import math
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exception_handlers import http_exception_handler
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.routing import Match
from sqlalchemy.exc import InterfaceError, OperationalError

from service.api.bodies import BadBody, LongInt
from service.api.models import ErrorMessage, ValidationErrorBody
from service.store import (
    ChecksumMismatch, IdempotencyConflict, JobNotActive, JobNotFound, JobPublished, VersionDeleted, VersionNotFound,
)

__all__ = ["problems_from_errors", "problem", "shorten", "install_error_handlers", "allowed_methods", "ERROR_RESPONSES",
           "error_responses"]

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
    if "pattern" in ctx:
        return f"matching {ctx['pattern']}"
    bounds = [fmt.format(ctx[k]) for k, fmt in _BOUNDS if k in ctx]
    return " and ".join(bounds) or None


def _message(e: dict[str, Any]) -> str:
    if e["type"] == "json_invalid":
        where = f" at character {e['loc'][-1]}" if isinstance(e["loc"][-1], int) else ""
        reason = (e.get("ctx") or {}).get("error", "")
        return f"the request body is not valid JSON{where}: {_text(str(reason))}".rstrip(": ")
    if e["type"] == "extra_forbidden":
        return f"unknown key {_text(str(e['loc'][-1]))!r} is not allowed here (check the spelling)"
    if e["type"] == "missing":
        return "this field is required"
    msg = _text(e["msg"]) if len(e["msg"]) > 400 else e["msg"]
    if "received" in msg:
        return msg
    return f"{msg}; received {_text(repr(e.get('input')))}"


_TEXT_MAX, _ITEMS_MAX, _DEPTH_MAX = 80, 8, 4


def _text(value: str) -> str:
    # Lone surrogates (from JSON "\ud800") cannot be encoded in the answer: escape them.
    value = value.encode("utf-8", "backslashreplace").decode("utf-8")
    return value if len(value) <= _TEXT_MAX else value[:_TEXT_MAX - 3] + "..."


def _big_int(value: int) -> str:
    """``-123456...`` of n digits -> ``"-1.235e+{n-1}"``, without converting it to a float (which
    overflows past 1.8e308) or to text whole (Python refuses past 4300 digits)."""
    sign = "-" if value < 0 else ""
    if isinstance(value, LongInt):
        return f"{sign}{value.head.lstrip('-')[0]}.{value.head.lstrip('-')[1:5]}...e+{value.digits - 1}"
    value = abs(value)
    if value.bit_length() > 14_000:  # about 4200 digits: text from arithmetic, never from JSON
        return f"{sign}an integer of about {int(value.bit_length() * math.log10(2)) + 1} digits"
    digits = str(value)
    mantissa = (int(digits[:5]) + 5) // 10  # 4 significant digits, rounded
    exponent = len(digits) - 1 + (mantissa >= 10_000)
    mantissa = f"{mantissa // 10 if mantissa >= 10_000 else mantissa}"
    return f"{sign}{mantissa[0]}.{mantissa[1:]}e+{exponent}"


def shorten(value: Any, depth: int = 0) -> Any:
    """A JSON-safe, bounded copy of a received value for an error body."""
    if isinstance(value, float) and not math.isfinite(value):
        return repr(value)  # JSON has no nan/inf
    if isinstance(value, int) and not isinstance(value, bool) and abs(value) >= 10**30:
        return _big_int(value)
    if value is None or isinstance(value, (bool, int, float)):
        return value
    if isinstance(value, str):
        return _text(value)
    if depth >= _DEPTH_MAX:
        return "..."
    if isinstance(value, (list, tuple)):
        head = [shorten(v, depth + 1) for v in value[:_ITEMS_MAX]]
        return head + [f"... ({len(value)} items)"] if len(value) > _ITEMS_MAX else head
    if isinstance(value, dict):
        items = list(value.items())
        out = {_text(str(k)): shorten(v, depth + 1) for k, v in items[:_ITEMS_MAX]}
        if len(items) > _ITEMS_MAX:
            out["..."] = f"({len(items)} keys)"
        return out
    return _text(repr(value))


PROBLEMS_MAX = 20
"""Most problems listed in one 422 (a list of 10,000 bad entries is one problem repeated)."""


def problems_from_errors(errors: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Pydantic / FastAPI error dicts -> 422 problem entries (field, message, allowed, received);
    past :data:`PROBLEMS_MAX` one last entry says how many more there were."""
    out = []
    if len(errors) > PROBLEMS_MAX:
        rest = len(errors) - PROBLEMS_MAX + 1
        errors = errors[:PROBLEMS_MAX - 1]
    else:
        rest = 0
    for e in errors:
        loc = tuple(e["loc"])
        if isinstance(e.get("input"), BadBody):  # service.api.bodies: refused after the token
            out.append(problem("body", e["input"].message(), "a JSON object (UTF-8)", None))
            continue
        if e["type"] == "json_invalid":
            out.append(problem("body", _message(e), "a JSON object", None))
            continue
        received = None if e["type"] in ("missing", "json_invalid") else shorten(e.get("input"))
        out.append(problem(_text(_field(loc)), _message(e), _allowed(e), received))
    if rest:
        out.append(problem("(more)", f"{rest} more problems not listed; fix the ones above and send again"))
    return out


def _detail(status: int, message: str, headers: dict[str, str] | None = None) -> JSONResponse:
    return JSONResponse({"detail": message}, status_code=status, headers=headers)


def allowed_methods(request: Request) -> list[str]:
    """Methods of every route whose path matches the request's (a path served by several
    routes, such as GET and DELETE of a version, lists them all)."""
    methods: set[str] = set()
    for route in request.app.state.api_routes:
        match, _ = route.matches(request.scope)
        if match != Match.NONE:
            methods |= set(route.methods)
    return sorted(methods)


def install_error_handlers(app: FastAPI) -> None:
    """Register the handlers listed in the module docstring."""

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, exc: StarletteHTTPException):
        if exc.status_code != 405:
            return await http_exception_handler(request, exc)
        allow = allowed_methods(request)
        return _detail(405, f"method {shorten(request.method)} is not allowed on this path; use one of "
                            f"{', '.join(allow)}", headers={"Allow": ", ".join(allow)})

    @app.exception_handler(RequestValidationError)
    async def _validation(_request: Request, exc: RequestValidationError) -> JSONResponse:
        return JSONResponse({"detail": problems_from_errors(list(exc.errors()))}, status_code=422)

    @app.exception_handler(JobNotFound)
    async def _job_not_found(_request: Request, exc: JobNotFound) -> JSONResponse:
        return _detail(404, f"{exc}; list jobs with GET /v1/jobs")

    @app.exception_handler(VersionNotFound)
    async def _version_not_found(_request: Request, exc: VersionNotFound) -> JSONResponse:
        if isinstance(exc, VersionDeleted):
            return _detail(410, str(exc))
        return _detail(404, f"{exc}; list datasets with GET /v1/datasets")

    @app.exception_handler(JobPublished)
    async def _published(_request: Request, exc: JobPublished) -> JSONResponse:
        return _detail(409, str(exc))

    @app.exception_handler(JobNotActive)
    async def _not_active(_request: Request, exc: JobNotActive) -> JSONResponse:
        return _detail(409, str(exc))

    @app.exception_handler(IdempotencyConflict)
    async def _conflict(_request: Request, exc: IdempotencyConflict) -> JSONResponse:
        return _detail(409, str(exc))

    @app.exception_handler(ChecksumMismatch)
    async def _corrupt(_request: Request, exc: ChecksumMismatch) -> JSONResponse:
        return _detail(500, f"checksum verification failed, file not served: {exc}")

    @app.exception_handler(OperationalError)
    @app.exception_handler(InterfaceError)
    async def _db_down(_request: Request, exc: OperationalError | InterfaceError) -> JSONResponse:
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
    410: {"model": ErrorMessage, "description": "The version was deleted (who and when, its spec hash)."},
    422: {"model": ValidationErrorBody,
          "description": "Invalid input: every bad field with the allowed range and the value received."},
    500: {"model": ErrorMessage, "description": "A stored file failed checksum verification."},
    501: {"model": ErrorMessage, "description": "The server lacks an optional package this needs (named)."},
    503: {"model": ErrorMessage, "description": "The job store or storage is unreachable."},
}
