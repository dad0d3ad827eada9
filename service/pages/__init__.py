"""Pages for people, served by ``bssrdf serve`` at ``/`` beside the JSON API.

Server-rendered HTML (Jinja2 templates in ``templates/``, autoescaped), one stylesheet and one
small script in ``static/`` (no build step, nothing fetched from elsewhere): the jobs with their
progress (a running job's page updates itself; without script it reloads itself), the datasets
and their versions with the spec, provenance, summary, the figures of the ``plots`` export and a
link to every table and export. The pages apply the API's rules (reads open or closed as
configured, writes need a token) through a sign-in form and a session cookie
(:mod:`service.pages.auth`).

    from service.pages import mount_pages
    mount_pages(app)            # the routes, /static, and the pages' error handler
"""

from __future__ import annotations

from pathlib import Path

from fastapi import FastAPI, Request
from fastapi.staticfiles import StaticFiles

from service.pages import datasets, jobs, session
from service.pages.auth import PageError
from service.pages.render import error_page

__all__ = ["mount_pages", "ROUTERS", "STATIC"]

ROUTERS = (jobs.router, datasets.router, session.router)
STATIC = Path(__file__).parent / "static"


def mount_pages(app: FastAPI) -> None:
    """Add the pages' routes, their static files at ``/static`` and the handler that turns a
    :class:`PageError` into an HTML page (a sign-in form for 401)."""
    for router in ROUTERS:
        app.include_router(router)
    app.mount("/static", StaticFiles(directory=STATIC), name="pages-static")

    @app.exception_handler(PageError)
    async def _page_error(request: Request, exc: PageError):
        return error_page(request, request.app.state.settings, exc.status, str(exc))
