"""``bssrdf run SPEC.json``: the one-machine job on embedded defaults.

Creates (or reuses) the local data directory with its SQLite job store and dataset storage,
submits the job, starts N local worker processes (``python -m service.worker``), shows progress
(shards done / total, photons, rate, ETA) while they work, stops them, and prints the same summary
as ``bssrdf simulate`` (read back from the stored, checksum-verified version) plus the dataset name
and version. ``--json`` prints one JSON object instead. Ctrl-C cancels the job.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from workers.run.cores import default_workers
from workers.run.simulate import format_summary  # torch-free: the walk is imported where it runs

__all__ = ["add_parser", "main", "run_local", "start_workers", "signal_workers", "stop_workers", "format_progress", "format_si", "format_summary"]

_REPO = Path(__file__).resolve().parents[1]


def start_workers(n: int, db_url: str, storage_uri: str, log_dir: Path, *, lease_seconds: float | None = None,
                  extra_env: dict[str, str] | None = None) -> list[subprocess.Popen]:
    """Start ``n`` worker processes; their JSON logs go to ``log_dir/worker-I.log``."""
    log_dir.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(_REPO), env.get("PYTHONPATH")) if p)
    # One walk per core: without this, every worker's torch would use every core.
    env.setdefault("OMP_NUM_THREADS", str(max(1, (os.cpu_count() or 1) // n)))
    env.update(extra_env or {})
    cmd = [sys.executable, "-m", "service.worker", "--db", db_url, "--storage", storage_uri, "--poll-seconds", "0.2"]
    if lease_seconds:
        cmd += ["--lease-seconds", str(lease_seconds)]
    procs = []
    for i in range(n):
        with open(log_dir / f"worker-{i}.log", "ab") as log:
            procs.append(subprocess.Popen(cmd + ["--worker-id", f"local-{i}"], env=env, stdout=log,
                                          stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL))
    return procs


def signal_workers(procs: list[subprocess.Popen]) -> None:
    """SIGTERM every worker still running (each releases its lease and exits); does not wait."""
    for p in procs:
        if p.poll() is None:
            p.terminate()


def stop_workers(procs: list[subprocess.Popen], timeout: float = 15.0) -> None:
    """SIGTERM every worker (each releases its lease), then SIGKILL whoever is still there."""
    signal_workers(procs)
    deadline = time.monotonic() + timeout
    for p in procs:
        try:
            p.wait(max(0.1, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()


def format_si(x: float | None) -> str:
    """A count or rate with a k/M/G suffix ("-" for None)."""
    if x is None:
        return "-"
    for unit, scale in (("G", 1e9), ("M", 1e6), ("k", 1e3)):
        if abs(x) >= scale:
            return f"{x / scale:.2f}{unit}"
    return f"{x:.0f}"


def format_progress(p) -> str:
    """One status line of a ``JobProgress``."""
    eta = "-" if p.eta_s is None else f"{p.eta_s:.0f}s"
    stalled = getattr(p, "shards_stalled", 0)
    running = f"running {p.shards_running}" + (f", stalled {stalled}" if stalled else "")
    media = getattr(p, "media_total", 1)
    merged = (f"merged {getattr(p, 'tasks_folded', 0)}/{p.shards_total}"
              + (f" (media {getattr(p, 'media_merged', 0)}/{media})" if media > 1 else ""))
    skipped = getattr(p, "shards_skipped", 0)
    head = (f"{p.state:<9} shards {p.shards_done}/{p.shards_total} ({running}"
            + (f", skipped {skipped}" if skipped else "") + ") ")
    phase, compiling = getattr(p, "phase", None), getattr(p, "shards_compiling", 0)
    if phase and not p.photons_done:  # nothing walked yet: say what the workers are doing
        return head + phase
    if phase:
        eta = "-"  # the rate counts the compile's minutes: no ETA until it is over
    line = head + (f"photons {format_si(p.photons_done)}  {format_si(p.rate_photons_per_s)}/s  ETA {eta}  "
                   f"merge {p.merge_state}, {merged}")
    return line + (f"  ({compiling} compiling: {phase})" if phase else "")


def run_local(spec, *, db_url: str, storage_uri: str, data_dir: Path, workers: int,
              show_progress: bool = True, lease_seconds: float | None = None, poll: float = 0.5,
              force: bool = False) -> dict[str, Any]:
    """Submit ``spec``, run it with ``workers`` local processes, return the run report.

    A spec already published (same spec hash, seed included) is not run again: the report is
    that version's, with ``existing = "version"``; a live job of the same spec is followed
    (``existing = "job"``). ``force`` runs it anyway.
    """
    t0 = time.monotonic()
    # Workers first: their start-up (interpreter, torch, the compiled walk) overlaps importing
    # the store, opening it and submitting here; until the job exists they poll for work.
    procs = start_workers(workers, db_url, storage_uri, data_dir / "logs", lease_seconds=lease_seconds)
    tty = show_progress and sys.stderr.isatty()
    last_line = 0.0
    job = None
    try:
        # Deferred so that the workers' start-up overlaps these imports (measured: README, BENCHMARKS).
        from service.datasets import DatasetStorage, open_version
        from service.store import TERMINAL_JOB_STATES, JobState, JobStore

        store = JobStore(db_url)
        storage = DatasetStorage(storage_uri)
        submitted = store.submit_unique(spec, force=force)
        job = submitted.job
        while True:
            p = store.progress(job.id)
            if show_progress and (tty or time.monotonic() - last_line > 10):
                print(("\r" if tty else "") + format_progress(p) + ("\x1b[K" if tty else ""),
                      end="" if tty else "\n", file=sys.stderr, flush=True)
                last_line = time.monotonic()
            if p.state in TERMINAL_JOB_STATES:
                break
            if all(proc.poll() is not None for proc in procs):
                raise RuntimeError(f"every worker exited before job {job.id} ended; see {data_dir / 'logs'}")
            time.sleep(poll)
    except BaseException as exc:
        if isinstance(exc, KeyboardInterrupt) and job is not None:
            store.cancel(job.id)  # Ctrl-C cancels the job
        stop_workers(procs)
        raise
    finally:
        if tty:
            print(file=sys.stderr)
    # The job has ended: let the workers exit while the result is read back.
    signal_workers(procs)
    try:
        wall = time.monotonic() - t0
        job = store.get_job(job.id)
        report: dict[str, Any] = {"job_id": job.id, "state": str(job.state), "workers": workers, "wall_s": wall,
                                  "photons": p.photons_done, "photons_per_s": p.photons_done / wall if wall else None,
                                  "existing": submitted.existing}
        if job.state != JobState.SUCCEEDED:
            report["error"] = job.error
            return report
        version = open_version(store, storage, job.dataset_name, job.dataset_version)
        report.update(dataset=job.dataset_name, version=job.dataset_version, uri=version.record.uri,
                      summary=version.read_json("summary.json"))
        store.dispose()
        return report
    finally:
        stop_workers(procs)


def add_parser(subparsers) -> argparse.ArgumentParser:
    """Add the ``run`` subcommand to an argparse ``subparsers`` object."""
    p = subparsers.add_parser("run", help="run a spec locally (SQLite store, local workers)",
                              description=__doc__.split("\n\n")[0])
    _add_arguments(p)
    p.set_defaults(func=main)
    return p


def _add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("spec", help="simulation spec (JSON)")
    p.add_argument("--workers", type=int, default=default_workers(), help="worker processes (default: cores)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--data-dir", default=None, help="data directory (default: BSSRDF_DATA_DIR or ./.bssrdf)")
    p.add_argument("--force", action="store_true", help="run it even if this spec and seed are already published "
                   "(otherwise that version is printed and nothing is recomputed)")


def main(args: argparse.Namespace) -> int:
    """Run ``bssrdf run`` with parsed arguments; returns the exit status."""
    from schema import SpecError, load_spec
    from service.settings import settings_or_exit, sqlite_url_for

    settings = settings_or_exit()
    if args.data_dir:
        data_dir = Path(args.data_dir)
        db_url, storage_uri = sqlite_url_for(data_dir), str(data_dir / "data")
    else:
        data_dir = Path(settings.data_dir)
        db_url, storage_uri = settings.database_url, settings.storage_uri
    if args.workers < 1:
        print(f"--workers must be >= 1; received {args.workers}", file=sys.stderr)
        return 2
    try:
        spec = load_spec(args.spec)
    except (SpecError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    from schema.sizes import size_limit_problems

    too_big = size_limit_problems(spec, settings.max_shard_bytes, settings.max_dataset_bytes, settings.max_job_tasks)
    if too_big:  # refused before anything is stored, as the API refuses it
        print("error: " + "\n  ".join(f"{field}: {message}" for field, message, _, _ in too_big), file=sys.stderr)
        return 2
    data_dir.mkdir(parents=True, exist_ok=True)
    try:
        report = run_local(spec, db_url=db_url, storage_uri=storage_uri, data_dir=data_dir, workers=args.workers,
                           force=args.force)
    except KeyboardInterrupt:
        print("cancelled", file=sys.stderr)
        return 130
    if args.json:  # simulate's JSON (the summary document) plus where the version lives
        doc = dict(report.pop("summary", {}), **report)
        print(json.dumps(doc, sort_keys=True))
    elif "summary" in report:
        print(format_summary(report["summary"]))
        print(f"dataset {report['dataset']} version {report['version']}  ({report['uri']})")
        if report["existing"] == "version":
            print("existing version: same spec and seed, nothing recomputed (--force runs it again)")
        else:
            print(f"{report['photons']} photons in {report['wall_s']:.1f} s with {report['workers']} workers")
    else:
        print(f"job {report['job_id']} {report['state']}: {report.get('error')}", file=sys.stderr)
    if args.json:
        return 0 if report["state"] == "succeeded" else 1
    return 0 if "summary" in report else 1


if __name__ == "__main__":
    parser = argparse.ArgumentParser(prog="bssrdf run", description=__doc__.split("\n\n")[0])
    _add_arguments(parser)
    sys.exit(main(parser.parse_args()))
