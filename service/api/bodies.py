"""JSON request bodies: UTF-8 only, integers of any length, any nesting, refused after the token.

    router = APIRouter(prefix="/v1/jobs", route_class=JSONRoute)

FastAPI reads a JSON body with ``json.loads`` before any dependency runs, so a body that does not
parse was a 422 (or a bare 400 "There was an error parsing the body") even without a token, and
``json.loads`` of bytes also takes UTF-16 and UTF-32. :class:`JSONRoute` parses bodies with
:func:`parse_body` instead, which never raises:

- a body that is not UTF-8 text (RFC 8259: UTF-8 only; a UTF-8 byte order mark is ignored, as the
  RFC allows), is not JSON, or nests arrays and objects deeper than the parser can follow becomes
  a :class:`BadBody`, which fails validation like any wrong value: after the auth dependency, so
  a caller without a valid token gets 401 first; :mod:`service.api.errors` answers it 422 on the
  field ``body`` with the reason and the character where it happened;
- an integer literal longer than :data:`LONG_DIGITS` digits (Python refuses to convert more than
  4300, and anything past 309 is beyond every bound of the API) becomes a :class:`LongInt`, so
  validation names the field it was sent in and the allowed range.
"""

from __future__ import annotations

import json
import re
from typing import Any

from fastapi import Request
from fastapi.routing import APIRoute

__all__ = ["JSONRoute", "JSONRequest", "BadBody", "LongInt", "parse_body", "LONG_DIGITS"]

LONG_DIGITS = 400
"""Integer literals with more digits than this are read as a :class:`LongInt`."""

DEPTH_SHOWN = 100
"""The depth whose position a :class:`BadBody` for too deep a nesting reports."""


class LongInt(int):
    """A JSON integer literal of more than :data:`LONG_DIGITS` digits: the integer of its first
    LONG_DIGITS digits (so beyond every bound the API checks, with the literal's sign and leading
    digits in a validation message), and its real length in ``digits``, shown by ``repr``."""

    digits: int

    def __new__(cls, literal: str) -> "LongInt":
        sign = "-" if literal.startswith("-") else ""
        digits = literal.lstrip("-")
        self = super().__new__(cls, sign + digits[:LONG_DIGITS])
        self.digits, self.head = len(digits), sign + digits[:5]
        return self

    def __repr__(self) -> str:
        return f"{self.head}... (an integer of {self.digits} digits)"

    __str__ = __repr__


class BadBody:
    """A request body that is not JSON in UTF-8: why, and where (character index, or None)."""

    def __init__(self, reason: str, position: int | None = None) -> None:
        self.reason, self.position = reason, position

    def message(self) -> str:
        where = f" at character {self.position}" if self.position is not None else ""
        return f"the request body is not valid JSON{where}: {self.reason}"

    def __repr__(self) -> str:
        return "<a body that is not JSON>"


def _int(literal: str) -> int:
    return int(literal) if len(literal) - literal.startswith("-") <= LONG_DIGITS else LongInt(literal)


_TOKEN = re.compile(r'"(?:[^"\\]|\\.)*"|[\[\]{}]')


def _too_deep_at(text: str) -> int | None:
    """Character index where arrays and objects first nest :data:`DEPTH_SHOWN` deep (strings skipped)."""
    depth = 0
    for m in _TOKEN.finditer(text):
        c = m.group()
        if c in "[{":
            depth += 1
            if depth >= DEPTH_SHOWN:
                return m.start()
        elif c in "]}":
            depth -= 1
    return None


def parse_body(raw: bytes) -> Any:
    """The JSON value of a request body, or a :class:`BadBody` saying why it is none."""
    if raw[:2] in (b"\xff\xfe", b"\xfe\xff") or b"\x00" in raw[:4]:
        return BadBody("it is UTF-16 or UTF-32 text (a byte order mark or NUL bytes at the start); "
                       "JSON must be UTF-8 (RFC 8259)")
    try:
        text = raw.removeprefix(b"\xef\xbb\xbf").decode("utf-8")
    except UnicodeDecodeError as exc:
        return BadBody(f"it is not UTF-8 text (byte {raw[exc.start]:#04x} at position {exc.start}); "
                       "JSON must be UTF-8 (RFC 8259)")
    try:
        return json.loads(text, parse_int=_int)
    except json.JSONDecodeError as exc:
        return BadBody(exc.msg, exc.pos)
    except RecursionError:
        return BadBody(f"arrays and objects nest too deep for the parser ({DEPTH_SHOWN} levels deep here; "
                       "a spec needs fewer than 10)", _too_deep_at(text))


class JSONRequest(Request):
    """A request whose ``json()`` is :func:`parse_body` (never raises)."""

    async def json(self) -> Any:
        if not hasattr(self, "_json"):
            self._json = parse_body(await self.body())
        return self._json


class JSONRoute(APIRoute):
    """An API route that reads its JSON body with :class:`JSONRequest`."""

    def get_route_handler(self):
        handler = super().get_route_handler()

        async def route_handler(request: Request):
            return await handler(JSONRequest(request.scope, request.receive))

        return route_handler
