"""Signing in and out of the pages (:mod:`service.pages.auth` describes the session cookie).

    GET  /signin?next=/jobs/ID    the token form
    POST /signin                  token + csrf (+ next): sets the session cookie, back to ``next``
    POST /signout                 csrf: clears it
"""

from __future__ import annotations

from fastapi import APIRouter, Request
from fastapi.responses import RedirectResponse, Response

from service.api.deps import SettingsDep
from service.pages.auth import (
    SESSION_COOKIE, SESSION_SECONDS, check_post, read_form, safe_next, session_value, valid_token,
)
from service.pages.render import page

__all__ = ["router"]

router = APIRouter(include_in_schema=False)


@router.get("/signin")
def signin_form(request: Request, settings: SettingsDep, next: str | None = None) -> Response:
    return page(request, settings, "signin.html", next=safe_next(next), problem=None)


@router.post("/signin")
async def signin(request: Request, settings: SettingsDep) -> Response:
    form = await read_form(request)
    check_post(request, form)
    target = safe_next(form.get("next"))
    if not settings.api_tokens:
        return RedirectResponse(target, status_code=303)  # authentication is off: nothing to sign in to
    token = form.get("token", "").strip()
    if not token or not valid_token(settings, token):
        return page(request, settings, "signin.html", status=401, next=target,
                    problem="that is not one of this server's API tokens (BSSRDF_API_TOKENS); check it and "
                            "try again")
    response = RedirectResponse(target, status_code=303)
    response.set_cookie(SESSION_COOKIE, session_value(token), max_age=SESSION_SECONDS, httponly=True,
                        samesite="strict", secure=request.url.scheme == "https", path="/")
    return response


@router.post("/signout")
async def signout(request: Request, settings: SettingsDep) -> Response:
    form = await read_form(request)
    check_post(request, form)
    response = RedirectResponse("/", status_code=303)
    response.delete_cookie(SESSION_COOKIE, path="/", httponly=True, samesite="strict")
    return response
