"""The FastAPI application factory.

    from service.api import create_app
    app = create_app()                   # settings from the environment (get_settings)
    app = create_app(Settings(...))      # explicit settings (installed as a dependency override)

Routers: ``/v1/jobs``, ``/v1/datasets``, ``/v1/version``, and the unversioned ``/healthz``,
``/readyz``, ``/metrics``. Request bodies over ``BSSRDF_MAX_BODY_BYTES`` are refused (413) before
they are read whole (:class:`service.api.limits.BodyLimit`), heads over ``BSSRDF_MAX_HEADER_BYTES``
or ``BSSRDF_MAX_HEADERS`` with 431 (:class:`~service.api.limits.HeaderLimit`; ``bssrdf serve``
refuses them while they arrive, :mod:`service.api.server`). The interactive OpenAPI documentation is at ``/docs``;
the document (``/openapi.json``) is corrected to the API's behaviour by :mod:`service.api.openapi`.
"""

from __future__ import annotations

import ipaddress
from contextlib import asynccontextmanager

from fastapi import FastAPI

from service.api.deps import Resources
from service.api.errors import install_error_handlers
from service.api.limits import BodyLimit, HeaderLimit
from service.api.models import API_VERSION
from service.api.openapi import install_openapi
from service.api.routers import datasets, health, jobs
from service.settings import Settings, get_settings

__all__ = ["create_app", "is_loopback", "check_auth_config", "InsecureBindError", "ROUTERS"]

ROUTERS = (jobs.router, datasets.router, health.router)


class InsecureBindError(RuntimeError):
    """The API would accept unauthenticated writes on a network-reachable address."""


def is_loopback(host: str) -> bool:
    """True for 127.0.0.0/8, ::1 and ``localhost``; False for 0.0.0.0, :: and any other name."""
    if host.strip().lower() == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False  # a host name: it may resolve to anything, treat it as exposed


def check_auth_config(settings: Settings) -> None:
    """Refuse a non-loopback bind address without API tokens (raises :class:`InsecureBindError`)."""
    if not settings.api_tokens and not is_loopback(settings.host):
        raise InsecureBindError(
            f"refusing to serve on {settings.host!r} without API tokens: anyone who can reach it could submit "
            "and cancel jobs. Set BSSRDF_API_TOKENS='[\"TOKEN\"]' (a JSON list; make a token with "
            "python -c 'import secrets; print(secrets.token_urlsafe(32))') "
            "or bind a loopback address (--host 127.0.0.1)."
        )


def create_app(settings: Settings | None = None) -> FastAPI:
    """A configured app; raises :class:`InsecureBindError` on an unsafe auth configuration.

    ``settings`` (default: the cached :func:`service.settings.get_settings`) is checked here and
    kept in ``app.state.settings``, where every request reads it (:func:`service.api.deps.app_settings`).
    """
    effective = settings if settings is not None else get_settings()
    check_auth_config(effective)
    resources = Resources()

    @asynccontextmanager
    async def lifespan(_app: FastAPI):
        yield
        resources.close()

    app = FastAPI(
        title="bssrdf-db",
        version=API_VERSION,
        summary="BSSRDF tables from Monte Carlo photon random walks, as a batch service.",
        description="Submit a medium as a simulation spec, follow the job while workers run its shards, "
        "then read and download the merged, immutable, checksummed dataset version.\n\n"
        "Mutating endpoints need `Authorization: Bearer TOKEN` (BSSRDF_API_TOKENS); read endpoints too "
        "when BSSRDF_READ_OPEN=false. Errors are `{\"detail\": ...}`; a 422 lists every bad field with "
        "its allowed range and the value received.",
        lifespan=lifespan,
    )
    app.state.resources = resources
    app.state.settings = effective
    install_error_handlers(app)
    app.add_middleware(BodyLimit, max_bytes=effective.max_body_bytes, timeout_s=effective.read_timeout_seconds)
    app.add_middleware(HeaderLimit, max_bytes=effective.max_header_bytes, max_count=effective.max_headers)
    for router in ROUTERS:
        app.include_router(router)
    # The API's routes, for the 405 answer's Allow header and the OpenAPI fixes.
    app.state.api_routes = [r for router in ROUTERS for r in router.routes]
    from service.pages import mount_pages  # here: service.pages imports the API's dependencies

    mount_pages(app)  # the HTML pages at / (service.pages), not part of the API's routes or OpenAPI
    install_openapi(app, read_open=effective.read_open)
    return app
