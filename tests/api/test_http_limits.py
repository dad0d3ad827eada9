"""Limits of the HTTP layer on a real `bssrdf serve` (uvicorn, httptools): heads over the size or
field-count limit are 431, heads and bodies that do not arrive in time are 408, over raw sockets
(an HTTP client would not send what these tests send). The ASGI-level checks of the same limits
(any server) run in-process at the end.

Latency under a concurrent big header is measured by ``python -m bench.headers``
(BENCHMARKS.md), not asserted here.
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import httpx
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from service.runner import stop_workers

from tests.support.fuzzing import examples
from tests.support.net import free_port
from tests.support.waiting import wait_for

REPO = Path(__file__).resolve().parents[2]
READ_TIMEOUT = 1.0  # BSSRDF_READ_TIMEOUT_SECONDS of the server under test


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    """(host, port) of a running `bssrdf serve` with the default header limits."""
    tmp = tmp_path_factory.mktemp("serve")
    port = free_port()
    env = {**os.environ, "PYTHONPATH": str(REPO), "BSSRDF_DATA_DIR": str(tmp),
           "BSSRDF_READ_TIMEOUT_SECONDS": str(READ_TIMEOUT)}
    env.pop("BSSRDF_API_TOKENS", None)
    log = open(tmp / "serve.log", "wb")
    proc = subprocess.Popen([sys.executable, "-m", "service.cli", "serve", "--host", "127.0.0.1", "--port", str(port),
                             "--log-level", "warning"], cwd=tmp, env=env, stdout=log, stderr=subprocess.STDOUT,
                            stdin=subprocess.DEVNULL)

    def up():
        if proc.poll() is not None:
            raise AssertionError(f"bssrdf serve exited: {(tmp / 'serve.log').read_text()}")
        try:
            return httpx.get(f"http://127.0.0.1:{port}/healthz", timeout=2).status_code == 200
        except httpx.TransportError:
            return False

    try:
        wait_for(up, 30, "bssrdf serve to be ready", poll=0.2)
        yield "127.0.0.1", port
    finally:
        stop_workers([proc])  # SIGTERM, then SIGKILL after 15 s
        log.close()


def exchange(server, head: bytes, body: bytes = b"", timeout: float = 10.0) -> tuple[int, dict, float]:
    """Send ``head`` + ``body`` on a new connection (in a thread, so that the answer is read while
    sending) and return (status, JSON body, seconds to the answer); the answer must close."""
    sock = socket.create_connection(server, timeout=timeout)

    def write():
        try:
            sock.sendall(head + body)
        except OSError:
            pass  # the server closed after refusing: expected

    writer = threading.Thread(target=write, daemon=True)
    start = time.perf_counter()
    writer.start()
    data = b""
    try:
        while b"\r\n\r\n" not in data or len(data) < data.index(b"\r\n\r\n") + 4 + _length(data):
            chunk = sock.recv(65536)
            if not chunk:
                break
            data += chunk
    finally:
        elapsed = time.perf_counter() - start
        sock.close()
    status = int(data.split(b" ", 2)[1])
    payload = data.split(b"\r\n\r\n", 1)[1]
    try:
        return status, json.loads(payload or b"null"), elapsed
    except ValueError:
        return status, payload, elapsed  # uvicorn's own 400 is text


def _length(data: bytes) -> int:
    for line in data.split(b"\r\n\r\n", 1)[0].split(b"\r\n")[1:]:
        name, _, value = line.partition(b":")
        if name.strip().lower() == b"content-length":
            return int(value)
    return 0


def get(path: str = "/healthz", headers: list[tuple[str, str]] = ()) -> bytes:
    lines = [f"GET {path} HTTP/1.1", "Host: 127.0.0.1", "Connection: close", *(f"{k}: {v}" for k, v in headers)]
    return ("\r\n".join(lines) + "\r\n\r\n").encode("latin-1")


@pytest.mark.parametrize("size", [20_000, 1_000_000, 20_000_000])
def test_a_big_header_is_431(server, size):
    status, body, elapsed = exchange(server, get(headers=[("X-Big", "a" * size)]))
    assert status == 431, body
    assert "BSSRDF_MAX_HEADER_BYTES" in body["detail"] and "16384 bytes" in body["detail"], body


def test_many_small_headers_are_431(server):
    status, body, _ = exchange(server, get(headers=[(f"X-H{i}", "1") for i in range(150)]))
    assert status == 431 and "BSSRDF_MAX_HEADERS" in body["detail"] and "100" in body["detail"], body


def test_headers_within_the_limits_are_served(server):
    status, body, _ = exchange(server, get(headers=[("X-Big", "a" * 15_000)]))
    assert status == 200 and body == {"status": "ok"}
    status, body, _ = exchange(server, get(headers=[(f"X-H{i}", "1") for i in range(90)]))
    assert status == 200 and body == {"status": "ok"}


def test_an_http_client_gets_the_431_too(server):
    """A client that writes its whole request before reading (httpx) reads the 431, not a reset."""
    r = httpx.get(f"http://{server[0]}:{server[1]}/healthz", headers={"X-Big": "a" * 1_000_000}, timeout=10)
    assert r.status_code == 431 and "BSSRDF_MAX_HEADER_BYTES" in r.json()["detail"]


def test_the_server_serves_others_after_a_refusal(server):
    for _ in range(3):
        assert exchange(server, get(headers=[("X-Big", "a" * 1_000_000)]))[0] == 431
    assert httpx.get(f"http://{server[0]}:{server[1]}/healthz", timeout=5).status_code == 200


def test_a_content_length_larger_than_the_body_is_408_within_the_read_timeout(server):
    head = (b"POST /v1/jobs HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: application/json\r\n"
            b"Content-Length: 1000\r\n\r\n")
    status, body, elapsed = exchange(server, head, b'{"spec": {}}', timeout=READ_TIMEOUT + 10)
    assert status == 408 and "BSSRDF_READ_TIMEOUT_SECONDS" in body["detail"], body
    assert "12 bytes of the 1000 bytes its Content-Length announced" in body["detail"], body
    assert elapsed < READ_TIMEOUT + 5, elapsed


def test_a_head_that_never_ends_is_408(server):
    status, body, elapsed = exchange(server, b"GET /healthz HTTP/1.1\r\nHost: 127.0.0.1\r\n", timeout=READ_TIMEOUT + 10)
    assert status == 408 and "request line and headers" in body["detail"], body


_LINE = st.one_of(st.binary(max_size=200), st.integers(0, 40_000).map(lambda n: b"X-Big: " + b"v" * n),
                  st.builds(lambda k, v: k + b": " + v, st.binary(min_size=1, max_size=20), st.binary(max_size=100)))


@given(lines=st.lists(_LINE, max_size=130), target=st.sampled_from([b"GET /healthz", b"GET /v1/jobs", b"POST /v1/jobs",
                                                                      b"GET /v1/datasets", b"DELETE /v1/jobs/x"]))
@settings(max_examples=examples(60), deadline=None, suppress_health_check=list(HealthCheck), database=None)
def test_fuzz_raw_request_heads(server, lines, target):
    """Request heads of arbitrary bytes, sizes and field counts, straight to the server's parser:
    every answer is an HTTP status below 500 (400 for what does not parse, 431 past the limits)."""
    fields = [line.replace(b"\r", b"").replace(b"\n", b"") for line in lines]
    head = target + b" HTTP/1.1\r\nHost: 127.0.0.1\r\n" + b"".join(f + b"\r\n" for f in fields) + \
        b"Content-Length: 0\r\nConnection: close\r\n\r\n"
    status, body, _ = exchange(server, head)
    assert status < 500, (status, body)
    if len(head) > 16384 + 1000 or len(fields) > 100:
        assert status in (400, 431), status  # too big, or malformed before the limit was reached


# -- the same limits under any ASGI server (service.api.limits), in-process --------------------------------


def test_asgi_header_limits(make_client, sqlite_store, storage):
    client = make_client(sqlite_store, storage, max_header_bytes=4096, max_headers=20)
    r = client.get("/healthz", headers={"X-Big": "a" * 5000})
    assert r.status_code == 431 and "BSSRDF_MAX_HEADER_BYTES" in r.json()["detail"]
    r = client.get("/healthz", headers={f"X-H{i}": "1" for i in range(25)})
    assert r.status_code == 431 and "BSSRDF_MAX_HEADERS" in r.json()["detail"]
    assert client.get("/healthz", headers={"X-Big": "a" * 3000}).status_code == 200


def test_asgi_body_read_timeout():
    import anyio

    from service.api.limits import BodyLimit

    sent = []

    async def app(scope, receive, send):  # never reached
        raise AssertionError("the app was called")

    async def receive():
        if not sent:
            sent.append(0)
            return {"type": "http.request", "body": b"x" * 10, "more_body": True}
        await anyio.sleep(3600)  # the rest of the body never comes

    async def send(message):
        sent.append(message)

    scope = {"type": "http", "headers": [(b"content-length", b"1000")]}
    start = time.perf_counter()
    anyio.run(BodyLimit(app, max_bytes=10_000, timeout_s=0.2), scope, receive, send)
    assert time.perf_counter() - start < 2
    assert sent[1]["status"] == 408 and (b"connection", b"close") in sent[1]["headers"]
    assert b"10 bytes of the 1000 bytes" in sent[2]["body"]
