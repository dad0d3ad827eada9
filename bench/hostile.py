"""The hostile client of issue 21, replayed against a live ``bssrdf serve`` with a token.

    python -m bench.hostile [--db URL]

Starts ``bssrdf serve`` on a free loopback port against ``--db`` (default a temporary SQLite file;
with a PostgreSQL URL a fresh database on that server, dropped afterwards) and a temporary
storage directory, then sends every numbered case of the issue's list: integers of 309+ digits
(1), absurd media (2), big headers with a concurrent ``/healthz`` (3), the 983,040-task spec (4),
bad input to a second server whose job store is down (5), a submission while a worker is
stopped inside its publish (6), wrong job store URLs given to ``bssrdf worker`` and ``bssrdf
serve`` (7), and the smaller items (8). Prints one line per case: the request, the answer
(status, or exit code and stderr lines for a command), the seconds it took, and what changed in
the store (jobs, dataset versions) and in the storage directory (files) while it ran; then a
summary (5xx answers, hangs, published non-finite numbers, tracebacks) and exit status 1 if any.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import httpx
import pyarrow.parquet as pq
import sqlalchemy as sa

from bench.headers import _big_request
from bench.load import TOKEN, _env, _free_port, _start, wait_ready
from service.faults import PAUSE_ENV
from service.runner import start_workers, stop_workers

__all__ = ["main", "run"]

AUTH = {"Authorization": f"Bearer {TOKEN}"}
HANG_S = 30.0  # an answer slower than this counts as a hang

TINY = {"name": "tiny", "medium": {"sigma_a": 1.0, "sigma_s": 1.0, "g": 0.0, "eta": 1.3}, "photons": 200,
        "shards": 2, "batches_per_shard": 1, "seed": 7, "estimator": "exits",
        "bins": {"radial": {"count": 4, "max_mm": 4.0}, "cos_theta_o": {"count": 1}, "phi_o": {"count": 1}}}


def _tiny(**changes) -> dict:
    spec = json.loads(json.dumps(TINY))
    for path, value in changes.items():
        *parents, last = path.split("__")
        node = spec
        for p in parents:
            node = node[p]
        node[last] = value
    return spec


class Bench:
    def __init__(self, db_url: str, root: Path) -> None:
        from service.store import JobStore

        self.db_url, self.root, self.storage = db_url, root, root / "data"
        self.store = JobStore(db_url)
        self.rows: list[dict] = []
        self.nonfinite: list[str] = []

    def snapshot(self) -> tuple[int, int, int]:
        from service.store.tables import dataset_versions, jobs

        with self.store._read() as conn:
            n_jobs = conn.execute(sa.select(sa.func.count()).select_from(jobs)).scalar_one()
            n_versions = conn.execute(sa.select(sa.func.count()).select_from(dataset_versions)).scalar_one()
        files = sum(1 for p in self.storage.rglob("*") if p.is_file()) if self.storage.exists() else 0
        return n_jobs, n_versions, files

    def record(self, case: str, request: str, answer: str, seconds: float, before, expect: str, ok: bool,
               five_xx: bool = False, hang: bool = False, traceback: bool = False) -> None:
        after = self.snapshot()
        delta = f"jobs {after[0] - before[0]:+d}, versions {after[1] - before[1]:+d}, files {after[2] - before[2]:+d}"
        row = {"case": case, "request": request, "answer": answer, "seconds": round(seconds, 3), "store": delta,
               "expected": expect, "ok": ok, "5xx": five_xx, "hang": hang, "traceback": traceback}
        self.rows.append(row)
        print(f"{'ok ' if ok else 'BAD'} {case:4} {request:58.58} -> {answer:34.34} {seconds:7.3f} s  {delta}"
              f"  (expected {expect})", flush=True)

    def http(self, case: str, base: str, method: str, path: str, expect: set[int], *, content: bytes | None = None,
             json_body=None, headers: dict | None = None, label: str | None = None) -> httpx.Response | None:
        before = self.snapshot()
        t0 = time.perf_counter()
        try:
            r = httpx.request(method, base + path, content=content, json=json_body, headers=headers, timeout=HANG_S)
        except httpx.TimeoutException:
            self.record(case, label or f"{method} {path}", "no answer (hang)", time.perf_counter() - t0, before,
                        "/".join(map(str, sorted(expect))), False, hang=True)
            return None
        dt = time.perf_counter() - t0
        detail = r.text.replace("\n", " ")
        field = ""
        try:
            d = r.json().get("detail")
            if isinstance(d, list) and d and isinstance(d[0], dict):
                field = " " + ".".join(str(x) for x in d[0].get("loc", []))
        except ValueError:
            pass
        self.record(case, label or f"{method} {path}", f"{r.status_code}{field or ' ' + detail[:40]}", dt, before,
                    "/".join(map(str, sorted(expect))), r.status_code in expect, five_xx=r.status_code >= 500,
                    traceback="Traceback" in r.text)
        return r

    def command(self, case: str, args: list[str], label: str, expect_code: int, must_not_exist: Path | None,
                needle: str) -> None:
        before = self.snapshot()
        env = _env() | {"BSSRDF_DATA_DIR": str(self.root / "home")}
        t0 = time.perf_counter()
        try:
            out = subprocess.run([sys.executable, "-m", "service.cli", *args], env=env, capture_output=True,
                                 text=True, timeout=HANG_S * 4, cwd=self.root)
        except subprocess.TimeoutExpired:
            self.record(case, label, "no exit (hang)", time.perf_counter() - t0, before, f"exit {expect_code}", False,
                        hang=True)
            return
        lines = out.stderr.strip().splitlines()
        created = must_not_exist is not None and must_not_exist.exists()
        ok = out.returncode == expect_code and len(lines) == 1 and needle in lines[0] and not created
        self.record(case, label, f"exit {out.returncode}, {len(lines)} line(s)" + (", dir created" if created else ""),
                    time.perf_counter() - t0, before, f"exit {expect_code}, 1 line with {needle!r}", ok,
                    traceback="Traceback" in out.stderr)
        if not ok:
            print("    stderr:", out.stderr[-600:].replace("\n", " | "), flush=True)

    def check_published(self, name: str, version: int) -> None:
        """Every float of the version's tables finite (standard errors may be NaN: no error bar)."""
        from workers.fold.finite import NonFiniteResult, check_finite

        for table in ("radial", "bins", "summary"):
            path = self.storage / name / f"v{version}" / f"{table}.parquet"
            try:
                check_finite(pq.read_table(path), table)
            except NonFiniteResult as exc:
                self.nonfinite.append(str(exc))


def _raw(port: int, data: bytes, timeout: float = HANG_S) -> tuple[str, float]:
    """Send ``data`` on a new connection; (the status line or what happened, seconds to it)."""
    t0 = time.perf_counter()
    with socket.create_connection(("127.0.0.1", port), timeout=timeout) as sock:
        sock.sendall(data)
        try:
            first = sock.recv(64)
        except socket.timeout:
            return "no answer (hang)", time.perf_counter() - t0
    return (first.split(b"\r\n", 1)[0].decode("latin-1") or "closed"), time.perf_counter() - t0


def run(db_url: str, root: Path) -> Bench:
    b = Bench(db_url, root)
    env = _env()
    port = _free_port()
    base = f"http://127.0.0.1:{port}"
    serve = _start(["serve", "--host", "127.0.0.1", "--port", str(port), "--db", db_url, "--storage", str(b.storage),
                    "--log-level", "warning"], root / "serve.log", env)
    down_port = _free_port()
    down_url = f"postgresql+psycopg://postgres@127.0.0.1:{_free_port()}/nothing"
    procs = [serve]
    try:
        wait_ready(base, serve, root / "serve.log")
        post = lambda case, body, expect, label, **kw: b.http(case, base, "POST", "/v1/jobs", expect, content=body,
                                                               headers={**AUTH, "Content-Type": "application/json"},
                                                               label=label, **kw)
        huge = "1" + "0" * 309  # 1e309 > the largest double
        # 1. integers of 309+ digits anywhere
        for where in ("photons", "seed", "unknown"):
            spec = _tiny(**{where: "HUGE"})
            post("1", json.dumps({"spec": spec}).replace('"HUGE"', huge).encode(), {422},
                 f"POST /v1/jobs spec.{where} = 10**309")
        # 2. absurd media
        for label, changes in [
            ("eta 1e-300", {"medium__eta": 1e-300}),
            ("sigma_a 1e-320, sigma_s 0", {"medium__sigma_a": 1e-320, "medium__sigma_s": 0.0}),
            ("sigma_s 1e308", {"medium__sigma_s": 1e308}),
            ("sigma_a = sigma_s = 1e300", {"medium__sigma_a": 1e300, "medium__sigma_s": 1e300}),
            ("bins.radial.max_mfp 1e308", {"bins__radial": {"count": 4, "max_mfp": 1e308}}),
        ]:
            post("2", json.dumps({"spec": _tiny(**changes)}).encode(), {422}, f"POST /v1/jobs {label}")
        # 3. big headers, and a concurrent /healthz while the 60 MB one arrives
        for size in (1_000_000, 60_000_000):
            before = b.snapshot()
            lat: list[float] = []
            stop = threading.Event()

            def probe():
                while not stop.is_set():
                    t = time.perf_counter()
                    httpx.get(base + "/healthz", timeout=HANG_S)
                    lat.append(time.perf_counter() - t)
                    time.sleep(0.01)

            prober = threading.Thread(target=probe, daemon=True)
            prober.start()
            status, dt = _big_request(port, size, timeout=HANG_S)
            stop.set()
            prober.join()
            b.record("3", f"GET /healthz, one {size // 1_000_000} MB header (+ /healthz beside)",
                     f"{status}; beside: max {max(lat) * 1000:.0f} ms of {len(lat)}", dt, before, "431",
                     status == 431, five_xx=(status or 0) >= 500, hang=status is None)
        # 4. the 983,040-task spec
        big = {"name": "big", "sweep": {"albedo": {"count": 1024, "spacing": "linear"}, "g": [i / 128 for i in range(64)],
                                        "eta": [1.3], "walks": "independent"},
               "photons": 30, "shards": 15, "batches_per_shard": 2, "seed": 1, "estimator": "exits",
               "bins": {"radial": {"count": 4, "max_mm": 4.0}, "cos_theta_o": {"count": 1}, "phi_o": {"count": 1}}}
        post("4", json.dumps({"spec": big}).encode(), {422}, "POST /v1/jobs 1024 albedos x 64 g x 15 shards")
        # 5. bad input while the job store is down: a second server on a database that does not answer
        dport = down_port
        dbase = f"http://127.0.0.1:{dport}"
        down = _start(["serve", "--host", "127.0.0.1", "--port", str(dport), "--db", down_url, "--storage",
                       str(root / "down-data"), "--log-level", "warning"], root / "serve-down.log", env)
        procs.append(down)
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            try:
                httpx.get(dbase + "/healthz", timeout=2)
                break
            except httpx.TransportError:
                time.sleep(0.2)
        b.http("5", dbase, "POST", "/v1/jobs", {422}, json_body={"spec": _tiny(photons=-1)}, headers=AUTH,
               label="store down: POST /v1/jobs photons -1")
        b.http("5", dbase, "GET", "/v1/jobs/xyz", {404}, label="store down: GET /v1/jobs/xyz")
        # 6. a worker stopped inside its publish; a submission meanwhile
        r = httpx.post(base + "/v1/jobs", json={"spec": _tiny(seed=61)}, headers=AUTH, timeout=HANG_S)
        job_id = r.json()["id"]
        victim = start_workers(1, db_url, str(b.storage), root / "logs", lease_seconds=5.0,
                               extra_env={"BSSRDF_COMPILE": "0", "OMP_NUM_THREADS": "1", PAUSE_ENV: "publish"})[0]
        procs.append(victim)
        deadline = time.monotonic() + 180
        while True:
            pid, status = os.waitpid(victim.pid, os.WUNTRACED | os.WNOHANG)
            if pid and os.WIFSTOPPED(status):
                break
            if pid or time.monotonic() > deadline:
                raise RuntimeError(f"the worker did not stop at its publish; see {root / 'logs'}")
            time.sleep(0.05)
        post("6", json.dumps({"spec": _tiny(seed=62)}).encode(), {201}, "POST /v1/jobs while a publish is stopped")
        os.kill(victim.pid, signal.SIGCONT)
        deadline = time.monotonic() + 120
        while httpx.get(f"{base}/v1/jobs/{job_id}", timeout=HANG_S).json()["state"] not in ("succeeded", "failed"):
            if time.monotonic() > deadline:
                raise RuntimeError("the paused job did not finish")
            time.sleep(0.2)
        job = httpx.get(f"{base}/v1/jobs/{job_id}", timeout=HANG_S).json()
        stop_workers([victim])
        # the other job (seed 62) too, so that every published version is checked below
        helper = start_workers(1, db_url, str(b.storage), root / "logs2", extra_env={"BSSRDF_COMPILE": "0",
                                                                                     "OMP_NUM_THREADS": "1"})
        procs += helper
        deadline = time.monotonic() + 120
        while b.store.pending_tasks() and time.monotonic() < deadline:
            time.sleep(0.2)
        stop_workers(helper)
        # 7. wrong job store URLs, for the worker and for serve
        missing = root / "nonexistent" / "dir"
        from sqlalchemy.engine import make_url

        variants = [(f"sqlite:///{missing / 'jobs.sqlite'}", "does not exist"), ("notaurl", "is not a database URL")]
        if db_url.startswith("postgresql"):
            u = make_url(db_url)
            variants += [(u.set(port=(u.port or 5432) + 1).render_as_string(False), "cannot reach"),
                         (u.set(database="no_such_database").render_as_string(False), "no_such_database"),
                         (u.set(username="no_such_user").render_as_string(False), "no_such_user")]
        for url, needle in variants:
            shown = make_url(url).render_as_string(hide_password=True) if "://" in url else url
            shown = shown.replace(str(root), "TMP")
            b.command("7", ["worker", "--db", url, "--storage", str(root / "w-data"), "--once"],
                      f"bssrdf worker --db {shown}", 2, root / "nonexistent", needle)
            if needle != "cannot reach":  # serve starts on a server that does not answer (/readyz says why)
                b.command("7", ["serve", "--port", str(_free_port()), "--db", url, "--storage", str(root / "s-data")],
                          f"bssrdf serve --db {shown}", 2, root / "nonexistent", needle)
        # 8. the smaller items
        deep = b'{"spec": ' + b"[" * 100_000 + b"]" * 100_000 + b"}"
        post("8", deep, {422}, "POST /v1/jobs nesting 100,000 deep")
        post("8", json.dumps({"spec": _tiny(photons="HUGE")}).replace('"HUGE"', "9" * 5000).encode(), {422},
             "POST /v1/jobs photons of 5,000 digits")
        b.http("8", base, "POST", "/v1/jobs", {401}, content=b'{"spec": ', headers={"Content-Type": "application/json"},
               label="POST /v1/jobs malformed JSON, no token")
        if job.get("dataset_version"):
            files = f"/v1/datasets/{job['dataset_name']}/versions/{job['dataset_version']}/files/summary.json"
            whole = httpx.get(base + files, timeout=HANG_S)
            r = b.http("8", base, "GET", files, {200}, headers={"Range": "bytes=0-9", "If-Range": '"not-the-etag"'},
                       label="GET summary.json Range + If-Range of another ETag")
            if r is not None and r.status_code == 200 and r.content != whole.content:
                b.rows[-1]["ok"] = False
                print("    the 200 is not the whole file", flush=True)
            b.check_published(job["dataset_name"], job["dataset_version"])
        post("8", json.dumps({"spec": _tiny(seed=81)}).encode("utf-16"), {400, 415, 422}, "POST /v1/jobs in UTF-16")
        spec_a = json.dumps({"spec": _tiny(seed=82)}).encode()
        b.http("8", base, "POST", "/v1/jobs", {201}, content=spec_a,
               headers={**AUTH, "Content-Type": "application/json", "Idempotency-Key": "k1"}, label="POST spec A, key k1")
        b.http("8", base, "POST", "/v1/jobs", {200}, content=spec_a,
               headers={**AUTH, "Content-Type": "application/json", "Idempotency-Key": "k2"},
               label="POST spec A again, key k2 (a duplicate: the job of k1)")
        b.http("8", base, "POST", "/v1/jobs", {409}, content=json.dumps({"spec": _tiny(seed=83)}).encode(),
               headers={**AUTH, "Content-Type": "application/json", "Idempotency-Key": "k2"},
               label="POST spec B, key k2 (the key is kept)")
        before = b.snapshot()
        secret = "zq8Xw3Pv9LmT4kRb7Ny2"  # no 6 characters of it in an English message
        t0 = time.perf_counter()
        out = subprocess.run([sys.executable, "-m", "service.cli", "serve", "--port", str(_free_port()), "--db", db_url],
                             env=env | {"BSSRDF_API_TOKENS": f"[{secret}"}, capture_output=True, text=True, timeout=120)
        leaked = any(secret[i:i + 6] in out.stderr + out.stdout for i in range(len(secret) - 5))
        b.record("8", f"bssrdf serve, BSSRDF_API_TOKENS='[{secret}'",
                 f"exit {out.returncode}, secret {'ECHOED' if leaked else 'not shown'}", time.perf_counter() - t0,
                 before, "exit 2, no part of the secret", out.returncode == 2 and not leaked,
                 traceback="Traceback" in out.stderr)
        before = b.snapshot()
        head = (f"POST /v1/jobs HTTP/1.1\r\nHost: 127.0.0.1\r\nAuthorization: Bearer {TOKEN}\r\n"
                "Content-Type: application/json\r\nContent-Length: 1000\r\n\r\n{\"spec\":").encode()
        line, dt = _raw(port, head)
        b.record("8", "POST /v1/jobs Content-Length 1000, 8 bytes sent", line, dt, before, "408 within the read timeout",
                 line.startswith("HTTP/1.1 408"), five_xx=" 5" in line[8:10], hang="hang" in line)
        if serve.poll() is not None:
            raise RuntimeError(f"bssrdf serve died: {(root / 'serve.log').read_text()[-2000:]}")
        log = (root / "serve.log").read_text()
        if "Traceback" in log:
            print("serve.log holds a traceback:", log[log.index("Traceback"):][:1500], flush=True)
            b.rows.append({"case": "log", "ok": False, "traceback": True, "5xx": False, "hang": False})
        # every version published during the run holds finite numbers only
        from service.store.tables import dataset_versions

        with b.store._read() as conn:
            for name, version in conn.execute(sa.select(dataset_versions.c.name, dataset_versions.c.version)).all():
                b.check_published(name, version)
    finally:
        stop_workers(procs)
        b.store.dispose()
    return b


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m bench.hostile", description=__doc__.split("\n\n")[0])
    p.add_argument("--db", default=None, help="job store URL (default: a temporary SQLite file); with a "
                   "PostgreSQL URL, a fresh database is made on that server and dropped afterwards")
    args = p.parse_args(argv)
    from bench.pooler import database_url, drop_database, fresh_database

    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        fresh = None
        if args.db and args.db.startswith("postgresql"):
            fresh = fresh_database(args.db, "hostile")
            db_url = database_url(args.db, fresh)
        else:
            db_url = args.db or f"sqlite:///{root / 'jobs.sqlite'}"
        try:
            b = run(db_url, root)
        finally:
            if fresh:
                drop_database(args.db, fresh)
    bad = [r for r in b.rows if not r["ok"]]
    print(json.dumps({"backend": db_url.split(":", 1)[0].split("+")[0], "cases": len(b.rows),
                      "as_expected": len(b.rows) - len(bad), "5xx": sum(r["5xx"] for r in b.rows),
                      "hangs": sum(r["hang"] for r in b.rows), "tracebacks": sum(r["traceback"] for r in b.rows),
                      "published_non_finite": b.nonfinite}, indent=1))
    return 1 if bad or b.nonfinite else 0


if __name__ == "__main__":
    sys.exit(main())
