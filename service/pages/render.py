"""Rendering a page: the Jinja2 environment, the filters, the response headers.

Templates live in ``service/pages/templates`` and are autoescaped: every string a user supplied
(a spec's name, its description, an error message) is shown as text, never as markup. A page
answer carries a Content-Security-Policy that allows this site's own scripts, styles and images
only (no inline script, nothing fetched from elsewhere), ``X-Content-Type-Options: nosniff``,
``Referrer-Policy: same-origin``, and sets this browser's CSRF cookie if it has none.
"""

from __future__ import annotations

import datetime as dt
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from fastapi import Request
from fastapi.responses import HTMLResponse
from jinja2 import Environment, FileSystemLoader, select_autoescape

from service.pages.auth import CSRF_COOKIE, can_write, csrf_token, signed_in
from service.settings import Settings

__all__ = ["page", "error_page", "env", "HEADERS", "si", "duration", "when", "bar_segments", "segments_of", "Segment"]

TEMPLATES = Path(__file__).parent / "templates"

CSP = ("default-src 'self'; script-src 'self'; style-src 'self'; img-src 'self' data:; object-src 'none'; "
       "base-uri 'none'; form-action 'self'; frame-ancestors 'none'")
HEADERS = {"Content-Security-Policy": CSP, "X-Content-Type-Options": "nosniff", "Referrer-Policy": "same-origin",
           "X-Frame-Options": "DENY", "Cache-Control": "no-store"}


def si(x: float | None, digits: int = 3) -> str:
    """A count or rate with a k/M/G suffix: 12345 -> "12.3k" ("-" for None)."""
    if not isinstance(x, (int, float)) or isinstance(x, bool) or (isinstance(x, float) and not math.isfinite(x)):
        return "-"
    for unit, scale in (("G", 1e9), ("M", 1e6), ("k", 1e3)):
        if abs(x) >= scale:
            return f"{x / scale:.{digits}g}{unit}"
    return f"{x:.{digits}g}" if isinstance(x, float) else str(x)


def duration(seconds: float | None) -> str:
    """Seconds as "45 s", "3 min 20 s", "2 h 05 min" ("-" for None)."""
    if seconds is None or not math.isfinite(seconds):
        return "-"
    s = int(round(seconds))
    if s < 60:
        return f"{s} s"
    if s < 3600:
        return f"{s // 60} min {s % 60:02d} s"
    return f"{s // 3600} h {s % 3600 // 60:02d} min"


def when(epoch: float | None) -> str:
    """A Unix time as "2026-12-02 17:41:00 UTC" ("-" for None)."""
    if epoch is None:
        return "-"
    return dt.datetime.fromtimestamp(epoch, dt.timezone.utc).strftime("%Y-%m-%d %H:%M:%S UTC")


def number(x: Any, digits: int = 5) -> str:
    """A float to ``digits`` significant digits ("-" for None, "NaN" kept)."""
    if x is None:
        return "-"
    if isinstance(x, (int, float)) and not isinstance(x, bool):
        return f"{x:.{digits}g}" if isinstance(x, float) else str(x)
    return str(x)


def percent(part: float, whole: float) -> str:
    """``part / whole`` as an SVG width ("37.5%"), 0 for an empty whole."""
    return f"{(100.0 * part / whole) if whole else 0.0:.3f}%"


@dataclass(frozen=True)
class Segment:
    """One part of a progress bar: ``kind`` (merged, done, running, queued), count, start and width in %."""

    kind: str
    count: int
    x: float
    width: float


def bar_segments(total: int, merged: int, done: int, running: int) -> list[Segment]:
    """A stacked bar over ``total`` shards: merged, done (not yet merged), running, queued.

    merged <= done + skipped is what the merge folded; every count is clipped so that the
    segments never exceed the whole."""
    total = max(int(total), 0)
    merged = min(max(merged, 0), total)
    done_only = min(max(done - merged, 0), total - merged)
    run = min(max(running, 0), total - merged - done_only)
    out, x = [], 0.0
    for kind, n in (("merged", merged), ("done", done_only), ("running", run),
                    ("queued", total - merged - done_only - run)):
        width = 100.0 * n / total if total else 0.0
        out.append(Segment(kind, n, x, width))
        x += width
    return out


def segments_of(p) -> list[Segment]:
    """The bar of a job's progress (a ``JobProgress``)."""
    return bar_segments(p.shards_total, p.tasks_folded, p.shards_done + p.shards_skipped, p.shards_running)


def _pretty(value: Any) -> str:
    return json.dumps(value, indent=2, sort_keys=True, default=str)


env = Environment(loader=FileSystemLoader(str(TEMPLATES)), autoescape=select_autoescape(["html"]),
                  trim_blocks=True, lstrip_blocks=True)
env.filters.update(si=si, duration=duration, when=when, number=number, pretty=_pretty)
env.globals.update(percent=percent, segments_of=segments_of)


def _context(request: Request, settings: Settings, extra: dict[str, Any]) -> dict[str, Any]:
    return {"request": request, "csrf": csrf_token(request), "auth_on": bool(settings.api_tokens),
            "signed_in": bool(settings.api_tokens) and signed_in(request, settings),
            "can_write": can_write(request, settings), "path": request.url.path, **extra}


def page(request: Request, settings: Settings, template: str, status: int = 200, **context: Any) -> HTMLResponse:
    """``template`` rendered with ``context`` (plus who is signed in and the CSRF token)."""
    html = env.get_template(template).render(_context(request, settings, context))
    response = HTMLResponse(html, status_code=status, headers=HEADERS)
    new = getattr(request.state, "new_csrf", None)
    if new is not None:
        response.set_cookie(CSRF_COOKIE, new, httponly=True, samesite="strict", path="/",
                            secure=request.url.scheme == "https")
    return response


def error_page(request: Request, settings: Settings, status: int, message: str) -> HTMLResponse:
    """An error as a page: what went wrong and what to do (a sign-in form for 401)."""
    titles = {400: "Bad request", 401: "Sign in to read this", 403: "Forbidden", 404: "Not found", 409: "Conflict",
              410: "Deleted", 422: "Cannot do that", 501: "Not available on this server", 503: "Unavailable"}
    return page(request, settings, "error.html", status=status, status_code=status,
                title=titles.get(status, "Error"), message=message)
