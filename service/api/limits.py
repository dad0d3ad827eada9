"""Limits of the API: request body size (413 before parsing) and the cost of a submitted spec.

    BodyLimit            ASGI middleware: a body over ``settings.max_body_bytes`` is answered 413
                         from its Content-Length, or as soon as a chunked body passes the limit,
                         before any of it is parsed
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

from schema import SimulationSpec
from schema.estimate import estimate_shard, job_photons
from schema.sizes import size_limit_problems
from service.api.errors import problem
from service.settings import Settings

__all__ = ["BodyLimit", "spec_limit_problems"]


class BodyLimit:
    """Refuse request bodies over ``max_bytes`` with 413 ``{"detail": ...}``."""

    def __init__(self, app, max_bytes: int) -> None:
        self.app, self.max_bytes = app, max_bytes

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
        while True:
            message = await receive()
            messages.append(message)
            if message["type"] != "http.request":
                break
            seen += len(message.get("body", b""))
            if seen > self.max_bytes:
                return await self._send_413(send, f"more than {self.max_bytes}")
            if not message.get("more_body", False):
                break
        replay = iter(messages)

        async def replayed_receive():
            message = next(replay, None)
            return message if message is not None else await receive()

        await self.app(scope, replayed_receive, send)

    async def _send_400(self, send, text: str) -> None:
        body = json.dumps({"detail": f"Content-Length must be a non-negative integer; received {text[:20]!r}"}).encode()
        await send({"type": "http.response.start", "status": 400,
                    "headers": [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode())]})
        await send({"type": "http.response.body", "body": body})


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
