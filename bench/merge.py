"""Merge memory against shard count: ``python -m bench.merge [--shards 16 64 256] [--json]``.

For each shard count N it stages a single-medium job of N done shards in a fresh SQLite store
and local storage (one real shard's tally, written N times as shards 0..N-1: the merge reads
and folds every file whatever it holds), then runs the merge in a fresh process and reports that
process's RSS before the merge (interpreter, torch, store: the baseline) and its peak during the
merge (Linux: the peak is reset to the baseline first, /proc/self/clear_refs), with
the shard payload (raw arrays and file) and the merge's wall time. A merge that held every shard
at once would grow by N x the payload; the streaming fold grows by about one shard and one
accumulator whatever N.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

__all__ = ["bench_spec", "stage_job", "measure", "main"]


def bench_spec(n_shards: int, radial: int = 256, cos: int = 16, phi: int = 16, name: str = "bench-merge"):
    """A one-channel, normal-incidence exit-tally spec whose shard payload is
    24 * 3 * ((radial + 1) * (2 cos phi + 1) + 1) + 48 bytes (schema.sizes): 9.5 MB by default."""
    from schema import parse_spec

    return parse_spec({
        "name": name, "medium": {"sigma_a": 0.1, "sigma_s": 0.9, "g": 0.0, "eta": 1.3}, "photons": 2 * n_shards,
        "shards": n_shards, "batches_per_shard": 2, "estimator": "exits", "max_scatter": 200,
        "bins": {"radial": {"count": radial, "max_mm": 10.0, "spacing": "linear"},
                 "cos_theta_o": {"count": cos}, "phi_o": {"count": phi}},
    })


def stage_job(db_url: str, storage_uri: str, spec, shards: range | None = None, job_id: str | None = None,
              fold_batch: int | None = None) -> str:
    """Submit ``spec`` (unless ``job_id`` names it) and complete the next ``len(shards)`` shard
    tasks (default all) with copies of shard 0's real tally as their files; the job id. The
    store holds the merge until every shard is done (``fold_batch`` above the shard count) unless
    told another ``fold_batch``."""
    from service.datasets import DatasetStorage, JobFiles
    from service.store import JobStore
    from workers.run.shard import run_shard

    store = JobStore(db_url, fold_batch=fold_batch or spec.task_count() + 1)
    storage = DatasetStorage(storage_uri)
    job_id = job_id or store.submit(spec).id
    tally = run_shard(spec, 0)
    files = JobFiles(storage, job_id)
    for _ in shards if shards is not None else range(spec.task_count()):
        lease = store.claim("bench-stager", 600)
        tally.shard_index = lease.shard_index
        ref = files.write(f"shards/{lease.shard_index:08d}-{lease.token}.tally", tally.to_bytes())
        store.complete_shard(lease, ref, photons=tally.photons, elapsed_s=0.0)
    store.dispose()
    return job_id


def _status_kib(key: str) -> float:
    """A figure of /proc/self/status in KiB (VmRSS, VmHWM)."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(key + ":"):
                return float(line.split()[1])
    raise KeyError(key)


def _reset_peak_rss() -> float | None:
    """Reset this process's peak RSS to its current RSS (Linux: clear_refs 5) and return that
    RSS in MiB, so the peak read later is the merge's own; None where that is not possible."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return _status_kib("VmRSS") / 1024
    except OSError:
        return None


def _merge_in_this_process(db_url: str, storage_uri: str) -> None:
    """Claim the merge task and run rounds until the version is published; print the figures."""
    import resource
    import time

    from service.datasets import DatasetStorage, run_merge_task
    from service.store import JobStore, TaskKind

    import workers.fold.job  # noqa: F401  (the fold and the tables, imported before the baseline)

    store, storage = JobStore(db_url), DatasetStorage(storage_uri)
    base = _reset_peak_rss()
    t0 = time.perf_counter()
    version = None
    while version is None:
        lease = store.claim("bench-merger", 600)
        assert lease is not None and lease.kind == TaskKind.MERGE, lease
        version = run_merge_task(store, storage, lease)
    peak = _status_kib("VmHWM") / 1024 if base is not None else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    base = base if base is not None else float("nan")
    print(json.dumps({"baseline_rss_mib": round(base, 1), "peak_rss_mib": round(peak, 1),
                      "merge_s": round(time.perf_counter() - t0, 2), "version": version}))


def measure(n_shards: int, workdir: Path, **bins) -> dict:
    """Stage N shards in ``workdir`` and measure their merge in a fresh process."""
    from schema.sizes import estimate_sizes

    spec = bench_spec(n_shards, **bins)
    db_url, storage_uri = f"sqlite:///{workdir / 'jobs.sqlite'}", str(workdir / "data")
    job_id = stage_job(db_url, storage_uri, spec)
    shard_file = next((workdir / "data" / ".jobs" / job_id / "shards").iterdir()).stat().st_size
    out = subprocess.run([sys.executable, "-m", "bench.merge", "--merge", db_url, storage_uri],
                         check=True, capture_output=True, text=True, cwd=Path(__file__).resolve().parents[1])
    figures = json.loads(out.stdout.strip().splitlines()[-1])
    return {"shards": n_shards, "payload_mib": round(estimate_sizes(spec).shard_payload_bytes / 2**20, 2),
            "shard_file_mib": round(shard_file / 2**20, 2), **figures,
            "growth_mib": round(figures["peak_rss_mib"] - figures["baseline_rss_mib"], 1)}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m bench.merge", description=__doc__.split("\n\n")[0])
    p.add_argument("--shards", type=int, nargs="+", default=[16, 64, 256])
    p.add_argument("--radial", type=int, default=256, help="radial bins (payload scale; default 256: 9.5 MB)")
    p.add_argument("--json", action="store_true")
    p.add_argument("--merge", nargs=2, metavar=("DB", "STORAGE"), help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.merge:
        _merge_in_this_process(*args.merge)
        return 0
    rows = []
    for n in args.shards:
        with tempfile.TemporaryDirectory(prefix="bench-merge-") as tmp:
            rows.append(measure(n, Path(tmp), radial=args.radial))
        if not args.json:
            r = rows[-1]
            print(f"{r['shards']:>5} shards  payload {r['payload_mib']} MiB (file {r['shard_file_mib']} MiB)  "
                  f"peak RSS {r['peak_rss_mib']} MiB (baseline {r['baseline_rss_mib']}, +{r['growth_mib']})  "
                  f"merge {r['merge_s']} s")
    if args.json:
        print(json.dumps(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
