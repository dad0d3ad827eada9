"""The merge task: shard results -> merged tables -> a published dataset version."""

from __future__ import annotations

import hashlib
import json
import time

from schema import parse_spec
from service.datasets.metadata import build_metadata, metadata_bytes
from service.datasets.storage import METADATA_FILE, DatasetStorage
from service.store import JobStore, Lease, StoreError

__all__ = ["run_merge_task", "IncompleteShards"]


class IncompleteShards(StoreError):
    """The stored shard results are not exactly shards 0..N-1 (a bug: the merge is gated on them)."""


def run_merge_task(store: JobStore, storage: DatasetStorage, lease: Lease) -> int:
    """Merge every shard of the leased job in shard order and publish the next version.

    Steps: load the shard payloads (shard order), ``merge``, ``write_tables`` into a staging
    directory, write ``metadata.json`` (spec, seed, photons, shard count, code version, timings,
    summary, sha256 of every file), then ``store.complete_merge`` moves the directory to
    ``NAME/vN`` and commits the catalog row with the job's success. Staged files are deleted if
    anything fails, a lost lease included. Returns the version number.
    """
    # Deferred, not a cycle: the merge imports torch (seconds), which the API process, importing
    # this package for dataset reads, never needs.
    from workers.merge import merge
    from workers.output import summary, write_tables
    from workers.tally import ShardTally

    t0 = time.perf_counter()
    spec = parse_spec(json.loads(lease.spec_json))
    job = store.get_job(lease.job_id)
    payloads = store.load_shard_results(lease.job_id)
    if [i for i, _ in payloads] != list(range(spec.shards)):
        raise IncompleteShards(
            f"job {lease.job_id}: stored shards {[i for i, _ in payloads]}, expected 0..{spec.shards - 1}"
        )
    tallies = [ShardTally.from_bytes(p) for _, p in payloads]
    result = merge(spec, tallies)
    t_merge = time.perf_counter()
    staged = storage.stage(spec.name)
    try:
        files = write_tables(result, staged.path, filesystem=storage.fs)
        t_write = time.perf_counter()
        meta = build_metadata(
            name=spec.name, job_id=lease.job_id, spec_json=lease.spec_json, spec_hash=job.spec_hash,
            seed=spec.seed, shards=spec.shards,
            photons=int(sum(t.photons for t in tallies)),
            photons_per_shard=[int(t.photons) for t in tallies],
            timings={
                "shard_walk_s_sum": float(sum(t.elapsed_s for t in tallies)),
                "merge_s": t_merge - t0,
                "write_s": t_write - t_merge,
                "job_wall_s": (store.now() - job.started_at) if job.started_at else None,
            },
            summary=summary(result),
            files=staged.checksums(list(files)),
        )
        blob = metadata_bytes(meta)
        staged.write_bytes(METADATA_FILE, blob)
        row_meta = dict(meta, metadata_sha256=hashlib.sha256(blob).hexdigest())
        return store.complete_merge(lease, spec.name, row_meta, staged)
    except BaseException:
        staged.discard()
        raise
