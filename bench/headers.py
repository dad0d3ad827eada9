"""Big request headers against a real server, and what they do to a concurrent client.

    python -m bench.headers [--requests 1000] [--block 100] [--header-bytes 1000000] [--rate 20] [--stock]

Starts ``bssrdf serve`` on a free loopback port (``--stock``: uvicorn's own httptools protocol,
``uvicorn --factory service.api:create_app --http httptools``, without the header limits of
service/api/server.py, for comparison), then:

1. the client reads ``/healthz`` ``--requests`` times on a keep-alive connection, in blocks of
   ``--block`` reads that alternate between baseline (no attacker) and under load (an attacker
   process sends requests with one header of ``--header-bytes`` bytes, ``--rate`` per second,
   one connection each; ``--rate 0``: one after the other, as fast as they are answered), so
   that the machine's own drift (other processes) falls on both alike;
2. one request with a header of ``--huge-bytes`` (default 60 MB) alone.

Prints latency percentiles of the client's reads without and with the attacker, the attacker's
requests and the time each took to be answered (status counts), the time to answer the huge
header and the server's peak resident memory (VmHWM) before and after.
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import httpx

from service.runner import stop_workers

from bench.load import percentile

__all__ = ["main"]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _peak_rss_mib(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def _big_request(port: int, size: int, timeout: float = 120) -> tuple[int | None, float]:
    """(status or None, seconds) of a GET /healthz with one header of ``size`` bytes."""
    head = (f"GET /healthz HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\nX-Big: ").encode()
    start = time.perf_counter()
    with socket.create_connection(("127.0.0.1", port), timeout=timeout) as sock:
        def write():
            try:
                sock.sendall(head)
                chunk = b"a" * 65536
                for _ in range(size // len(chunk)):
                    sock.sendall(chunk)
                sock.sendall(b"\r\n\r\n")
            except OSError:
                pass  # refused and closed

        writer = threading.Thread(target=write, daemon=True)
        writer.start()
        try:
            first = sock.recv(64)
        except OSError:
            first = b""
        elapsed = time.perf_counter() - start
    status = int(first.split(b" ", 2)[1]) if first.startswith(b"HTTP/") else None
    return status, elapsed


def _attack(port: int, size: int, rate: float, active, stop, results) -> None:
    out = []
    while not stop.is_set():
        if not active.wait(0.05):
            continue
        start = time.perf_counter()
        out.append(_big_request(port, size))
        if rate > 0:
            time.sleep(max(0.0, start + 1 / rate - time.perf_counter()))
    results.put(out)


def _reads(port: int, n: int) -> list[float]:
    out = []
    with httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=60) as client:
        for _ in range(n):
            start = time.perf_counter()
            r = client.get("/healthz")
            out.append(time.perf_counter() - start)
            assert r.status_code == 200, r.status_code
    return out


def _show(name: str, values: list[float]) -> str:
    ms = [v * 1e3 for v in values]
    return (f"{name:<34} n={len(ms):<5} p50 {percentile(ms, 0.5):8.2f} ms  p99 {percentile(ms, 0.99):8.2f} ms  "
            f"max {max(ms):8.2f} ms")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m bench.headers", description=__doc__.split("\n\n")[0])
    p.add_argument("--requests", type=int, default=1000, help="client reads without, and again with, the attacker")
    p.add_argument("--block", type=int, default=100, help="reads per block (blocks alternate)")
    p.add_argument("--header-bytes", type=int, default=1_000_000, help="the attacker's header size")
    p.add_argument("--rate", type=float, default=20.0, help="the attacker's requests per second (0: no pause)")
    p.add_argument("--huge-bytes", type=int, default=60_000_000, help="the single huge header (0: skip)")
    p.add_argument("--stock", action="store_true", help="uvicorn's own httptools protocol, without limits")
    args = p.parse_args(argv)

    port = _free_port()
    tmp = tempfile.mkdtemp(prefix="bench-headers-")
    env = {**os.environ, "BSSRDF_DATA_DIR": tmp, "OMP_NUM_THREADS": "1"}
    env.pop("BSSRDF_API_TOKENS", None)
    if args.stock:
        cmd = [sys.executable, "-m", "uvicorn", "--factory", "service.api:create_app", "--http", "httptools",
               "--host", "127.0.0.1", "--port", str(port), "--log-level", "warning"]
    else:
        cmd = [sys.executable, "-m", "service.cli", "serve", "--port", str(port), "--log-level", "warning"]
    server = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 30
        while True:
            try:
                if httpx.get(f"http://127.0.0.1:{port}/healthz", timeout=1).status_code == 200:
                    break
            except httpx.TransportError:
                pass
            if time.monotonic() > deadline or server.poll() is not None:
                raise SystemExit("the server did not start")
            time.sleep(0.2)
        print(f"server: {'uvicorn httptools (stock)' if args.stock else 'bssrdf serve'}, pid {server.pid}, "
              f"peak RSS {_peak_rss_mib(server.pid):.0f} MiB")
        _reads(port, 50)  # warm up
        # The attacker is a process of its own: in a thread it would share the client's GIL and
        # slow the measuring client itself.
        active, stop, results = multiprocessing.Event(), multiprocessing.Event(), multiprocessing.Queue()
        attacker = multiprocessing.Process(target=_attack, daemon=True,
                                           args=(port, args.header_bytes, args.rate, active, stop, results))
        attacker.start()
        baseline, loaded = [], []
        for block in range(max(2, args.requests // args.block * 2)):
            (active.set if block % 2 else active.clear)()
            time.sleep(0.1)
            (loaded if block % 2 else baseline).extend(_reads(port, args.block))
        stop.set()
        attacks = results.get(timeout=120)
        attacker.join(120)
        print(_show("baseline /healthz", baseline))
        print(_show(f"/healthz with {args.header_bytes:,} B headers", loaded) +
              f"  (attacker: {'no pause' if args.rate <= 0 else f'{args.rate:g}/s'})")
        statuses: dict[object, int] = {}
        for status, _ in attacks:
            statuses[status] = statuses.get(status, 0) + 1
        print(_show(f"{args.header_bytes:,} B header answered", [t for _, t in attacks]) + f"  statuses {statuses}")
        if args.huge_bytes:
            status, elapsed = _big_request(port, args.huge_bytes)
            print(f"{args.huge_bytes:,} B header: status {status} after {elapsed * 1e3:.1f} ms; "
                  f"server peak RSS {_peak_rss_mib(server.pid):.0f} MiB")
    finally:
        stop_workers([server])  # SIGTERM, then SIGKILL after 15 s
    return 0


if __name__ == "__main__":
    sys.exit(main())
