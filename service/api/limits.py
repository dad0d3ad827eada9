"""Limits of the API: request head and body size (431, 413 before parsing), the time a body may
take to arrive (408), and the cost of a submitted spec.

    HeaderLimit          ASGI middleware: a request line and headers over ``settings.max_header_bytes``
                         or with more than ``settings.max_headers`` fields are answered 431 (the
                         server read them already: ``bssrdf serve`` refuses them while they arrive,
                         service.api.server; this holds the limits under any other server)
    BodyLimit            ASGI middleware: a body over ``settings.max_body_bytes`` is answered 413
                         from its Content-Length, or as soon as a chunked body passes the limit,
                         before any of it is parsed; a body not all there within
                         ``settings.read_timeout_seconds`` (a Content-Length larger than what is
                         sent) is answered 408 and the connection closed
    spec_limit_problems  the 422 problems of a spec beyond ``max_job_photons`` or whose estimated
                         shard CPU time (:func:`schema.estimate.estimate_shard`) is beyond
                         ``max_shard_cpu_seconds``, or whose estimated shard payload or dataset size
                         (:func:`schema.sizes.size_limit_problems`) is beyond ``max_shard_bytes`` /
                         ``max_dataset_bytes``, or whose shard tasks are over ``max_job_tasks``;
                         each names the field, the limit and the value

Every limit is a setting (``service/settings.py``) documented in deploy/README.md, "Limits".
"""

from __future__ import annotations

import json
import math
from typing import Any

import anyio

from schema import SimulationSpec
from schema.estimate import estimate_shard, job_photons
from schema.sizes import size_limit_problems
from service.api.errors import problem
from service.settings import Settings

__all__ = ["BodyLimit", "HeaderLimit", "header_problem", "spec_limit_problems"]


async def _send_json(send, status: int, detail: str, close: bool = True) -> None:
    body = json.dumps({"detail": detail}).encode()
    headers = [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode())]
    await send({"type": "http.response.start", "status": status,
                "headers": headers + [(b"connection", b"close")] * close})
    await send({"type": "http.response.body", "body": body})


def header_problem(size: int, count: int, max_bytes: int, max_count: int, *, incomplete: bool = False) -> str | None:
    """Why a request head of ``size`` bytes and ``count`` fields is refused (431), or None.
    ``incomplete``: counted while it arrives, so it is at least that large."""
    more = "more than " if incomplete else ""
    if size > max_bytes:
        return (f"the request line and headers ({more}{size} bytes) exceed the limit of {max_bytes} bytes "
                "(BSSRDF_MAX_HEADER_BYTES); a request to this API needs a few hundred")
    if count > max_count:
        return (f"the request has {f'more than {max_count}' if incomplete else count} header fields, over the limit "
                f"of {max_count} (BSSRDF_MAX_HEADERS)")
    return None


class HeaderLimit:
    """Refuse request heads over ``max_bytes`` or with more than ``max_count`` fields: 431."""

    def __init__(self, app, max_bytes: int, max_count: int) -> None:
        self.app, self.max_bytes, self.max_count = app, max_bytes, max_count

    async def __call__(self, scope, receive, send) -> None:
        if scope["type"] == "http":
            headers = scope.get("headers") or []
            size = len(scope.get("raw_path") or b"") + len(scope.get("query_string") or b"") + sum(
                len(n) + len(v) + 4 for n, v in headers)
            problem = header_problem(size, len(headers), self.max_bytes, self.max_count)
            if problem is not None:
                return await _send_json(send, 431, problem)
        await self.app(scope, receive, send)


class BodyLimit:
    """Refuse request bodies over ``max_bytes`` with 413 ``{"detail": ...}``."""

    def __init__(self, app, max_bytes: int, timeout_s: float = 10.0) -> None:
        self.app, self.max_bytes, self.timeout_s = app, max_bytes, timeout_s

    def _message(self, size: str) -> bytes:
        return json.dumps({"detail": f"request body of {size} bytes exceeds the limit of {self.max_bytes} bytes "
                                     "(BSSRDF_MAX_BODY_BYTES); a simulation spec needs a few kilobytes"}).encode()

    async def _send_413(self, send, size: str) -> None:
        body = self._message(size)
        await send({"type": "http.response.start", "status": 413,
                    "headers": [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode()),
                                (b"connection", b"close")]})
        await send({"type": "http.response.body", "body": body})

    async def __call__(self, scope, receive, send) -> None:
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        length = dict(scope.get("headers") or []).get(b"content-length")
        if length is not None:
            text = length.decode("latin-1").strip()
            if not text.isdigit():
                return await self._send_400(send, text)
            if int(text) > self.max_bytes:
                return await self._send_413(send, text[:20])
        # Read the body here (at most max_bytes of it), then replay it to the app: a chunked body
        # without Content-Length is cut off as soon as it passes the limit.
        messages, seen = [], 0
        with anyio.move_on_after(self.timeout_s) as reading:
            while True:
                message = await receive()
                messages.append(message)
                if message["type"] != "http.request":
                    break
                seen += len(message.get("body", b""))
                if seen > self.max_bytes or not message.get("more_body", False):
                    break
        if reading.cancelled_caught:
            told = f" of the {length.decode('latin-1')} bytes its Content-Length announced" if length else ""
            return await _send_json(send, 408, f"the request body did not arrive within {self.timeout_s:g} s "
                                               f"(BSSRDF_READ_TIMEOUT_SECONDS): {seen} bytes{told}")
        if seen > self.max_bytes:
            return await self._send_413(send, f"more than {self.max_bytes}")
        replay = iter(messages)

        async def replayed_receive():
            message = next(replay, None)
            return message if message is not None else await receive()

        await self.app(scope, replayed_receive, send)

    async def _send_400(self, send, text: str) -> None:
        await _send_json(send, 400, f"Content-Length must be a non-negative integer; received {text[:20]!r}",
                         close=False)


def spec_limit_problems(spec: SimulationSpec, settings: Settings) -> list[dict[str, Any]]:
    """422 problems of a valid spec that exceeds a configured cost limit (empty list: within)."""
    out = []
    total = job_photons(spec)
    if total > settings.max_job_photons:
        out.append(problem(
            "spec.photons",
            f"the job would walk photons x incidence angles x channels (of every medium) = {spec.photons} x "
            f"{len(spec.incidence_deg)} x {total // (spec.photons * len(spec.incidence_deg))} = {total} photons, "
            "over the limit "
            f"{settings.max_job_photons} (BSSRDF_MAX_JOB_PHOTONS); use fewer photons",
            allowed=f"photons x angles x channels <= {settings.max_job_photons}", received=spec.photons))
    shard = estimate_shard(spec, settings.worker_speed)
    if shard.cpu_s > settings.max_shard_cpu_seconds:
        # Shards needed so that the largest one fits: the estimate is linear in the photons of a
        # shard per configuration, ceil(photons / shards).
        per_config = -(-spec.photons // spec.shards)
        fits = math.floor(settings.max_shard_cpu_seconds / (shard.cpu_s / per_config))
        needed = "more" if fits < 1 else str(min(spec.photons, -(-spec.photons // fits)))
        out.append(problem(
            "spec.shards",
            f"a shard would take an estimated {shard.cpu_s:.4g} CPU seconds ({shard.photons} photons x "
            f"{shard.steps / max(shard.photons, 1):.4g} steps each, schema.estimate), over the limit "
            f"{settings.max_shard_cpu_seconds:g} s (BSSRDF_MAX_SHARD_CPU_SECONDS); use at least {needed} "
            "shards, or fewer photons or bins",
            allowed=f"estimated CPU seconds per shard <= {settings.max_shard_cpu_seconds:g}", received=spec.shards))
    out += [problem(field, message, allowed=allowed, received=received) for field, message, allowed, received in
            size_limit_problems(spec, settings.max_shard_bytes, settings.max_dataset_bytes, settings.max_job_tasks)]
    return out
