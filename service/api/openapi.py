"""The OpenAPI document, made to say what the API does (checked by tests/api/test_fuzz.py).

FastAPI's generated document differs from the running API in four ways, fixed here once the
document is built:

- read endpoints depend on a token only when ``BSSRDF_READ_OPEN=false``; with open reads their
  security is optional (``[{}, {"HTTPBearer": []}]``), as OpenAPI writes "no token, or this one";
- every 422 is our problem list (:class:`~service.api.models.ValidationErrorBody`, see
  :mod:`service.api.errors`), never FastAPI's ``HTTPValidationError`` (``loc``/``msg``/``type``);
- a route answering GET and HEAD is two operations and needs two operation ids;
- an operation with a request body documents 413 and 408 (:class:`~service.api.limits.BodyLimit`),
  and every operation 431 (:class:`~service.api.limits.HeaderLimit`, :mod:`service.api.server`);
- errors are JSON on every route, also where the success is text (``/metrics``).
"""

from __future__ import annotations

import warnings
from typing import Any

from fastapi import FastAPI
from fastapi.openapi.utils import get_openapi
from fastapi.routing import APIRoute

from service.api.deps import require_read_token

__all__ = ["install_openapi", "read_operations"]

_OURS = "#/components/schemas/ValidationErrorBody"
_THEIRS = "#/components/schemas/HTTPValidationError"
_TOO_LARGE = {"description": "The request body is over BSSRDF_MAX_BODY_BYTES (refused before it is read).",
              "content": {"application/json": {"schema": {"$ref": "#/components/schemas/ErrorMessage"}}}}
_TOO_SLOW = {"description": "The request body did not arrive within BSSRDF_READ_TIMEOUT_SECONDS (a Content-Length "
             "larger than the body sent); the connection is closed.", "content": _TOO_LARGE["content"]}
_HEAD_TOO_LARGE = {"description": "The request line and headers are over BSSRDF_MAX_HEADER_BYTES, or the header "
                   "fields more than BSSRDF_MAX_HEADERS (refused while they arrive).", "content": _TOO_LARGE["content"]}


def _depends_on(dependant, call) -> bool:
    return any(d.call is call or _depends_on(d, call) for d in dependant.dependencies)


def read_operations(app: FastAPI) -> set[tuple[str, str]]:
    """``(path, method)`` of every operation whose token requirement is ``ReadAuthDep``."""
    return {(r.path, m.lower()) for r in app.state.api_routes if isinstance(r, APIRoute)
            and _depends_on(r.dependant, require_read_token) for m in r.methods}


def _replace_refs(node: Any) -> Any:
    if isinstance(node, dict):
        return {k: (_OURS if k == "$ref" and v == _THEIRS else _replace_refs(v)) for k, v in node.items()}
    if isinstance(node, list):
        return [_replace_refs(v) for v in node]
    return node


def _fix(doc: dict[str, Any], reads: set[tuple[str, str]], read_open: bool) -> dict[str, Any]:
    doc = _replace_refs(doc)
    schemas = doc.get("components", {}).get("schemas", {})
    for unused in ("HTTPValidationError", "ValidationError"):
        schemas.pop(unused, None)
    for path, operations in doc["paths"].items():
        ids = [o.get("operationId") for o in operations.values()]
        for method, op in operations.items():
            if read_open and (path, method) in reads and op.get("security"):
                op["security"] = [{}, *op["security"]]
            # FastAPI names a GET+HEAD route's operations after one of its methods (a set: either).
            if ids.count(op.get("operationId")) > 1:
                op["operationId"] = op["operationId"].rsplit("_", 1)[0] + "_" + method
            if "requestBody" in op:
                op["responses"].setdefault("413", _TOO_LARGE)
                op["responses"].setdefault("408", _TOO_SLOW)
            op["responses"].setdefault("431", _HEAD_TOO_LARGE)
            for status, response in op["responses"].items():
                content = response.get("content") or {}
                if status >= "400" and content and "application/json" not in content:
                    response["content"] = {"application/json": next(iter(content.values()))}
    return doc


def install_openapi(app: FastAPI, *, read_open: bool) -> None:
    """Serve the fixed document at ``/openapi.json`` (built once, on first request)."""

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is None:
            with warnings.catch_warnings():  # the GET/HEAD routes' shared operation id, fixed in _fix
                warnings.filterwarnings("ignore", "Duplicate Operation ID", UserWarning)
                doc = get_openapi(title=app.title, version=app.version, summary=app.summary,
                                  description=app.description, routes=app.routes)
            app.openapi_schema = _fix(doc, read_operations(app), read_open)
        return app.openapi_schema

    app.openapi = openapi
