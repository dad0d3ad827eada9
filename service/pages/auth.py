"""Signing in to the pages, and the checks every page and form makes.

The pages follow the API's rules: reads are open unless ``BSSRDF_READ_OPEN=false``, writes
(cancel, delete) need one of ``BSSRDF_API_TOKENS``, and without tokens (a loopback server)
authentication is off. A browser cannot send a bearer header from a link, so a user signs in
once on ``/signin`` with a token and gets a session cookie:

    session = EXPIRES "." hex(HMAC-SHA256(key=token, msg="bssrdf-pages-session:" EXPIRES))

``HttpOnly`` (no script reads it), ``SameSite=Strict`` (no other site's request carries it),
``Secure`` on https, valid for :data:`SESSION_SECONDS`. The cookie is not the token: it cannot
be replayed against the JSON API, it expires, and removing the token from the configuration
ends every session made with it. A request may also send ``Authorization: Bearer TOKEN``.

Every form POST is checked against cross-site requests twice: a double-submit token (the
``bssrdf_csrf`` cookie, random per browser, must equal the form's ``csrf`` field, which only a
page of this site can read) and, when the browser sends one, the ``Origin`` header must be this
server's. This holds with authentication off too, where a loopback server would otherwise take
a cancel from any web page the user visits.
"""

from __future__ import annotations

import hashlib
import hmac
import secrets
import time
from urllib.parse import parse_qs

from fastapi import Request

from service.settings import Settings

__all__ = ["SESSION_COOKIE", "CSRF_COOKIE", "SESSION_SECONDS", "session_value", "valid_token", "signed_in",
           "can_read", "can_write", "csrf_token", "check_post", "read_form", "safe_next", "PageError"]

SESSION_COOKIE = "bssrdf_session"
CSRF_COOKIE = "bssrdf_csrf"
SESSION_SECONDS = 12 * 3600
"""How long a sign-in lasts."""
MAX_FORM_BYTES = 4096
"""Largest form body the pages read (a token and a CSRF field)."""


class PageError(Exception):
    """A request the pages refuse: ``status`` 401 (sign in), 403 (forbidden) or 400."""

    def __init__(self, status: int, message: str) -> None:
        super().__init__(message)
        self.status = status


def _mac(token: str, expires: int) -> str:
    return hmac.new(token.encode(), f"bssrdf-pages-session:{expires}".encode(), hashlib.sha256).hexdigest()


def session_value(token: str, now: float | None = None) -> str:
    """The session cookie's value for a valid ``token`` (module docstring)."""
    expires = int(now if now is not None else time.time()) + SESSION_SECONDS
    return f"{expires}.{_mac(token, expires)}"


def valid_token(settings: Settings, token: str) -> bool:
    """Whether ``token`` is one of the configured tokens (constant time per token, all compared)."""
    given = token.encode()
    return any([secrets.compare_digest(given, t.encode()) for t in settings.api_tokens])


def _valid_session(settings: Settings, value: str, now: float) -> bool:
    expires, _, mac = value.partition(".")
    if not expires.isdigit() or len(expires) > 12 or int(expires) < now or len(mac) != 64:
        return False
    return any([secrets.compare_digest(mac, _mac(t, int(expires))) for t in settings.api_tokens])


def signed_in(request: Request, settings: Settings) -> bool:
    """True with a valid session cookie or bearer header, or when authentication is off."""
    if not settings.api_tokens:
        return True
    header = request.headers.get("authorization", "")
    if header.lower().startswith("bearer ") and valid_token(settings, header[7:].strip()):
        return True
    cookie = request.cookies.get(SESSION_COOKIE)
    return cookie is not None and _valid_session(settings, cookie, time.time())


def can_read(request: Request, settings: Settings) -> bool:
    """The API's read rule: open unless ``read_open`` is false, then a token is needed."""
    return settings.read_open or signed_in(request, settings)


def can_write(request: Request, settings: Settings) -> bool:
    """The API's write rule: a token (or authentication off)."""
    return signed_in(request, settings)


def csrf_token(request: Request) -> str:
    """This browser's CSRF token: its ``bssrdf_csrf`` cookie, or a new random one (the page
    sets it, :func:`service.pages.render.page`)."""
    value = request.cookies.get(CSRF_COOKIE, "")
    if len(value) == 43 and value.replace("-", "").replace("_", "").isalnum():
        return value
    return getattr(request.state, "new_csrf", None) or _new_csrf(request)


def _new_csrf(request: Request) -> str:
    request.state.new_csrf = secrets.token_urlsafe(32)
    return request.state.new_csrf


async def read_form(request: Request) -> dict[str, str]:
    """An ``application/x-www-form-urlencoded`` body (the pages' forms) as a dict of its first
    values; 400 for another content type or more than :data:`MAX_FORM_BYTES`."""
    kind = request.headers.get("content-type", "").split(";")[0].strip().lower()
    if kind != "application/x-www-form-urlencoded":
        raise PageError(400, f"the pages' forms send application/x-www-form-urlencoded; received {kind or 'none'!r}")
    body = await request.body()
    if len(body) > MAX_FORM_BYTES:
        raise PageError(400, f"form body over {MAX_FORM_BYTES} bytes")
    fields = parse_qs(body.decode("utf-8", "replace"), keep_blank_values=True, max_num_fields=20)
    return {k: v[0] for k, v in fields.items()}


def _same_origin(request: Request) -> bool:
    """The Origin header names this server's host (the scheme is not compared: behind a TLS
    proxy the browser says https and the server sees http). No header: the CSRF token decides;
    ``null`` (an opaque origin: a sandboxed frame, a data: page) is refused."""
    origin = request.headers.get("origin")
    if origin is None:
        return True
    host = origin.partition("://")[2]
    return bool(host) and host == request.headers.get("host", request.url.netloc)


def check_post(request: Request, form: dict[str, str]) -> None:
    """Refuse a cross-site form POST (403): the Origin must be ours and the form's ``csrf``
    field must equal the ``bssrdf_csrf`` cookie."""
    if not _same_origin(request):
        raise PageError(403, "this form was sent from another site (Origin header); reload the page and "
                                 "submit it again from there")
    cookie = request.cookies.get(CSRF_COOKIE, "")
    given = form.get("csrf", "")
    if not cookie or not secrets.compare_digest(cookie.encode(), given.encode()):
        raise PageError(403, "the form's CSRF token does not match this browser's cookie (cookies off, or "
                                 "the form came from elsewhere); reload the page and submit it again")


def safe_next(target: str | None) -> str:
    """Where to go after signing in: a path on this site ("/..."), never another site."""
    if not target or not target.startswith("/") or target.startswith("//") or "\\" in target:
        return "/"
    return target
