"""Client commands of the HTTP API: ``bssrdf submit``, ``bssrdf status``, ``bssrdf datasets``.

    bssrdf submit SPEC.json --api URL [--token T] [--idempotency-key K] [--force] [--wait] [--json]
    bssrdf status JOB --api URL [--follow] [--json]
    bssrdf datasets --api URL [NAME [VERSION]] [--download FILE [-o PATH]] [--json]

``--api`` defaults to ``BSSRDF_API`` (else http://127.0.0.1:8000), ``--token`` to
``BSSRDF_TOKEN``. Following a job shows shards done / total, photons, rate and ETA (one updating
line on a terminal, a line every few seconds otherwise) and ends with the summary ``bssrdf
simulate`` prints, read from the stored version. API errors are printed field by field (allowed
range, value received); the exit status is 0 on success, 1 when the job failed or was cancelled,
2 on any error.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Any, TextIO
from urllib.parse import quote

import httpx

from service.runner import format_progress, format_si
from workers.run.simulate import format_summary

__all__ = ["ApiClient", "ApiError", "add_parser", "main", "format_error", "follow_job", "TERMINAL_STATES"]

DEFAULT_API = "http://127.0.0.1:8000"
TERMINAL_STATES = frozenset({"succeeded", "failed", "cancelled"})


def _seg(value: Any) -> str:
    """One URL path segment: a user-given name can never become a different path."""
    return quote(str(value), safe="")


class ApiError(Exception):
    """An error answer of the API (``status`` and its ``detail``), or an unreachable API (status 0)."""

    def __init__(self, status: int, detail: Any, url: str = "") -> None:
        super().__init__(format_error(status, detail, url))
        self.status, self.detail, self.url = status, detail, url


def format_error(status: int, detail: Any, url: str = "") -> str:
    """Readable text of an error body: one line per bad field with its allowed range and value."""
    head = f"HTTP {status}" if status else "cannot reach the API"
    if url:
        head += f" from {url}"
    if isinstance(detail, list):  # 422 problems
        lines = [f"{head}: {len(detail)} problem{'s' if len(detail) != 1 else ''}"]
        for p in detail:
            if isinstance(p, dict):
                allowed = f" (allowed: {p['allowed']})" if p.get("allowed") else ""
                lines.append(f"  {p.get('field', '?')}: {p.get('message', p)}{allowed}")
            else:
                lines.append(f"  {p}")
        return "\n".join(lines)
    return f"{head}: {detail}"


class ApiClient:
    """A thin httpx client of the API: bearer token, JSON, errors raised as :class:`ApiError`."""

    def __init__(self, base_url: str, token: str | None = None, timeout: float = 30.0,
                 http: httpx.Client | None = None) -> None:
        """``http``: an existing httpx client to send through (e.g. FastAPI's TestClient)."""
        self.base_url = base_url.rstrip("/")
        self.http = http if http is not None else httpx.Client(base_url=self.base_url, timeout=timeout)
        if token:
            self.http.headers["Authorization"] = f"Bearer {token}"

    def close(self) -> None:
        self.http.close()

    def request(self, method: str, path: str, **kwargs) -> httpx.Response:
        try:
            response = self.http.request(method, path, **kwargs)
        except httpx.TransportError as exc:
            raise ApiError(0, f"{type(exc).__name__}: {exc}; is `bssrdf serve` running at {self.base_url}? "
                              "(--api or BSSRDF_API)", self.base_url + path) from exc
        if response.status_code >= 400:
            try:
                detail = response.json().get("detail", response.text)
            except (ValueError, AttributeError):
                detail = response.text.strip() or response.reason_phrase
            raise ApiError(response.status_code, detail, f"{method} {path}")
        return response

    def get_json(self, path: str, **kwargs) -> Any:
        return self.request("GET", path, **kwargs).json()

    def submit(self, spec: Any, idempotency_key: str | None = None, force: bool = False) -> dict[str, Any]:
        body = {"spec": spec}
        if idempotency_key:
            body["idempotency_key"] = idempotency_key
        if force:
            body["force"] = True
        return self.request("POST", "/v1/jobs", json=body).json()

    def job(self, job_id: str) -> dict[str, Any]:
        return self.get_json(f"/v1/jobs/{_seg(job_id)}")

    def media(self, job_id: str) -> dict[str, Any]:
        """Every medium's progress (all pages of GET /v1/jobs/{id}/media, joined)."""
        page = self.get_json(f"/v1/jobs/{_seg(job_id)}/media", params={"limit": 1000})
        items = list(page["items"])
        while page["next_offset"] is not None:
            page = self.get_json(f"/v1/jobs/{_seg(job_id)}/media", params={"limit": 1000, "offset": page["next_offset"]})
            items += page["items"]
        return dict(page, items=items, offset=0, next_offset=None)

    def summary(self, name: str, version: int | str) -> dict[str, Any]:
        """The version's summary.json (checksum-verified by the server)."""
        return self.get_json(f"/v1/datasets/{_seg(name)}/versions/{_seg(version)}/files/summary.json")


# --- progress display ---
def progress_line(job: dict[str, Any]) -> str:
    """The progress line of ``bssrdf run`` for a job document."""
    p = job.get("progress") or {}
    fields = {"shards_done": 0, "shards_total": job.get("shards", 0), "shards_running": 0, "photons_done": 0,
              "rate_photons_per_s": None, "eta_s": None, "merge_state": "-", **p}
    return format_progress(SimpleNamespace(**fields, state=job["state"]))


def follow_job(client: ApiClient, job_id: str, *, stream: TextIO = sys.stderr, poll: float = 1.0,
               timeout: float | None = None, plain_every: float = 10.0) -> dict[str, Any]:
    """Poll the job until it ends (or ``timeout`` seconds pass: TimeoutError); the last document.

    On a terminal one line is rewritten in place; otherwise a line is printed when the shard count
    changes, and at least every ``plain_every`` seconds.
    """
    tty = stream.isatty()
    deadline = None if timeout is None else time.monotonic() + timeout
    last_text, last_time, failures = None, 0.0, 0
    try:
        while True:
            try:
                job = client.job(job_id)
                failures = 0
            except ApiError as exc:
                failures += 1
                if exc.status != 0 and exc.status < 500 or failures >= 5:
                    raise
                time.sleep(min(10.0, poll * 2**failures))  # API restarting: back off and retry
                continue
            line = progress_line(job)
            done = job["state"] in TERMINAL_STATES
            if tty:
                print(f"\r{line}\x1b[K", end="", file=stream, flush=True)
            else:
                key = (job["state"], (job.get("progress") or {}).get("shards_done"))
                if key != last_text or done or time.monotonic() - last_time >= plain_every:
                    print(line, file=stream, flush=True)
                    last_text, last_time = key, time.monotonic()
            if done:
                return job
            if deadline is not None and time.monotonic() > deadline:
                raise TimeoutError(f"job {job_id} still {job['state']} after {timeout} s")
            time.sleep(poll)
    finally:
        if tty:
            print(file=stream, flush=True)


def report_outcome(client: ApiClient, job: dict[str, Any], *, as_json: bool = False) -> int:
    """Print the summary of a succeeded job (as ``bssrdf simulate`` does) or its error; exit status."""
    if job["state"] != "succeeded":
        if as_json:
            print(json.dumps(job, sort_keys=True))
        print(f"job {job['id']} {job['state']}: {job.get('error') or 'no error recorded'}", file=sys.stderr)
        return 1
    summary = client.summary(job["dataset_name"], job["dataset_version"])
    if as_json:  # simulate's JSON document plus where the version lives
        print(json.dumps(dict(summary, job_id=job["id"], state=job["state"], dataset=job["dataset_name"],
                              version=job["dataset_version"]), sort_keys=True))
    else:
        print(format_summary(summary))
        print(f"dataset {job['dataset_name']} version {job['dataset_version']}  (job {job['id']})")
    return 0


# --- commands ---
def _client(args: argparse.Namespace) -> ApiClient:
    return ApiClient(args.api, args.token)


EXISTING = {"idempotency_key": "job (same idempotency key)", "job": "existing job (same spec and seed)",
            "version": "existing job (same spec and seed, already published)"}


def cmd_submit(args: argparse.Namespace) -> int:
    try:
        spec = json.loads(Path(args.spec).read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        print(f"error: cannot read spec {args.spec}: {exc}", file=sys.stderr)
        return 2
    client = _client(args)
    try:
        job = client.submit(spec, args.idempotency_key, force=args.force)
        print(f"{EXISTING.get(job.get('existing'), 'job')} {job['id']} {job['state']} ({job['name']}, "
              f"{job['shards']} shards)", file=sys.stderr)
        if job.get("existing") == "version":
            print(f"dataset {job['dataset_name']} version {job['dataset_version']} has this spec and seed: nothing "
                  "recomputed (--force runs it again)", file=sys.stderr)
        if not args.wait:
            print(json.dumps(job, sort_keys=True) if args.json else job["id"])
            return 0
        job = follow_job(client, job["id"], poll=args.poll, timeout=args.timeout)
        return report_outcome(client, job, as_json=args.json)
    finally:
        client.close()


def _status_text(job: dict[str, Any]) -> str:
    lines = [f"job {job['id']}  {job['name']}", progress_line(job)]
    if job.get("error"):
        lines.append(f"error: {job['error']}")
    if job.get("dataset_name"):
        lines.append(f"dataset {job['dataset_name']} version {job['dataset_version']}")
    return "\n".join(lines)


def cmd_status(args: argparse.Namespace) -> int:
    client = _client(args)
    try:
        if args.follow:
            job = follow_job(client, args.job, poll=args.poll, timeout=args.timeout)
            return report_outcome(client, job, as_json=args.json)
        job = client.job(args.job)
        if args.media:
            media = client.media(args.job)
            print(json.dumps(dict(job, media=media["items"]), sort_keys=True) if args.json
                  else _status_text(job) + "\n" + media_text(media["items"]))
            return 0
        print(json.dumps(job, sort_keys=True) if args.json else _status_text(job))
        return 0
    finally:
        client.close()


def media_text(items: list[dict[str, Any]]) -> str:
    """One line per medium: coordinates, shards done / skipped / running, folded, photons."""
    rows = [f"{'medium':>6}  {'albedo':<17} {'g':<17} {'eta':>6}  {'done':>5} {'skip':>5} {'run':>4} "
            f"{'folded':>6}  {'photons':>15}  state"]
    for m in items:
        albedo = ",".join(f"{a:.4g}" for a in m["albedo"])
        g = ",".join(f"{x:.4g}" for x in m["g"])
        state = "merged" if m["merged"] else "running" if m["shards_running"] else "waiting"
        rows.append(f"{m['medium']:>6}  {albedo[:17]:<17} {g[:17]:<17} {m['eta']:>6.4g}  "
                    f"{m['shards_done']:>2}/{m['shards_total']:<2} {m['shards_skipped']:>5} {m['shards_running']:>4} "
                    f"{m['shards_folded']:>6}  {format_si(m['photons_done']):>7}/{format_si(m['photons_total']):<7}  {state}")
    return "\n".join(rows)


def _datasets_text(items: list[dict[str, Any]]) -> str:
    if not items:
        return "no datasets yet"
    rows = [f"{'name':<30} {'latest':>6} {'versions':>8}"]
    rows += [f"{d['name']:<30} {d['latest_version']:>6} {d['versions']:>8}" for d in items]
    return "\n".join(rows)


def _versions_text(items: list[dict[str, Any]]) -> str:
    rows = [f"{'version':>7}  {'photons':>12}  {'shards':>6}  {'created (UTC)':<19}  job"]
    for v in items:
        created = time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime(v["created_at"]))
        rows.append(f"{v['version']:>7}  {v.get('photons') or '-':>12}  {v.get('shards') or '-':>6}  {created:<19}  "
                    f"{v.get('job_id') or '-'}")
    return "\n".join(rows)


def _version_text(v: dict[str, Any]) -> str:
    lines = [format_summary(v["summary"]) if v.get("summary") else "(no summary)",
             f"dataset {v['name']} version {v['version']}  (job {v.get('job_id') or '-'})", "files:"]
    lines += [f"  {name:<18} {f.get('bytes') or '':>10}  sha256 {f['sha256']}" for name, f in sorted(v["files"].items())]
    return "\n".join(lines)


def cmd_datasets(args: argparse.Namespace) -> int:
    if args.download and not args.version:
        print("error: --download needs NAME and VERSION (a number or latest)", file=sys.stderr)
        return 2
    client = _client(args)
    try:
        if args.download:
            path = f"/v1/datasets/{_seg(args.name)}/versions/{_seg(args.version)}/files/{_seg(args.download)}"
            out = Path(args.output or Path(args.download).name)
            data = client.request("GET", path).content  # verified against its sha256 by the server
            out.write_bytes(data)
            print(f"wrote {out} ({len(data)} bytes)", file=sys.stderr)
            return 0
        if args.version:
            doc = client.get_json(f"/v1/datasets/{_seg(args.name)}/versions/{_seg(args.version)}")
            text = _version_text
        elif args.name:
            doc = client.get_json(f"/v1/datasets/{_seg(args.name)}/versions")
            text = _versions_text
        else:
            doc = client.get_json("/v1/datasets")
            text = _datasets_text
        print(json.dumps(doc, sort_keys=True) if args.json else text(doc))
        return 0
    finally:
        client.close()


def _guard(command):
    """Run a command; API errors and timeouts become a readable message and exit status 2."""

    def run(args: argparse.Namespace) -> int:
        try:
            return command(args)
        except ApiError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
        except TimeoutError as exc:
            print(f"error: {exc}; follow it with `bssrdf status {getattr(args, 'job', '') or 'JOB'} --follow`",
                  file=sys.stderr)
            return 2
        except KeyboardInterrupt:
            print("\nstopped following; the job goes on (bssrdf status JOB --follow)", file=sys.stderr)
            return 130

    return run


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--api", default=os.environ.get("BSSRDF_API", DEFAULT_API),
                   help=f"API base URL (default: BSSRDF_API or {DEFAULT_API})")
    p.add_argument("--token", default=os.environ.get("BSSRDF_TOKEN"),
                   help="bearer token (default: BSSRDF_TOKEN)")
    p.add_argument("--json", action="store_true", help="print JSON")


def _follow_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--poll", type=float, default=1.0, metavar="S", help="seconds between progress polls")
    p.add_argument("--timeout", type=float, default=None, metavar="S", help="stop following after S seconds")


def add_parser(subparsers) -> None:
    """Add ``submit``, ``status`` and ``datasets`` to an argparse ``subparsers`` object."""
    p = subparsers.add_parser("submit", help="submit a spec to the HTTP API",
                              description="Submit a simulation spec (JSON file) to the API; --wait follows it.")
    p.add_argument("spec", help="simulation spec (JSON)")
    p.add_argument("--idempotency-key", default=None, help="resubmitting with this key returns the same job")
    p.add_argument("--force", action="store_true", help="run it even if a published version or a live job has "
                   "the same spec and seed (otherwise that one is returned and nothing is recomputed)")
    p.add_argument("--wait", action="store_true", help="follow the job and print its summary")
    _common(p)
    _follow_options(p)
    p.set_defaults(func=_guard(cmd_submit))

    p = subparsers.add_parser("status", help="show a job's state and progress",
                              description="Show a job; --follow until it ends, then its summary.")
    p.add_argument("job", help="job id")
    p.add_argument("--follow", action="store_true", help="follow until the job ends, then print its summary")
    p.add_argument("--media", action="store_true", help="also list every medium (a sweep's grid point): its "
                   "albedo, g and eta, shards done / skipped / running, shards merged, photons")
    _common(p)
    _follow_options(p)
    p.set_defaults(func=_guard(cmd_status))

    p = subparsers.add_parser("datasets", help="list datasets, versions, or show / download a version",
                              description="No NAME: every dataset. NAME: its versions. NAME VERSION (number or "
                              "latest): its summary and files; --download FILE saves one file.")
    p.add_argument("name", nargs="?", help="dataset name")
    p.add_argument("version", nargs="?", help="version number or latest")
    p.add_argument("--download", metavar="FILE", help="radial.parquet, bins.parquet, summary.parquet, "
                   "summary.json or metadata.json")
    p.add_argument("-o", "--output", metavar="PATH", help="where to save --download (default: FILE)")
    _common(p)
    p.set_defaults(func=_guard(cmd_datasets))


def main(argv: list[str] | None = None) -> int:
    """``python -m service.client submit|status|datasets ...`` (the same as ``bssrdf ...``)."""
    parser = argparse.ArgumentParser(prog="bssrdf", description="Client of the bssrdf-db HTTP API.")
    add_parser(parser.add_subparsers(dest="command", metavar="COMMAND", required=True))
    args = parser.parse_args(argv)
    return int(args.func(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
