"""The merge task: an incremental fold of the shard results in task order, then the version.

Each claim of a job's merge task is one *round* (:func:`run_merge_task`):

1. restore the fold the job store records (``jobs.folded``, ``fold_uri``: a
   :class:`workers.fold.job.JobFold` saved as a file in the job's staging area, sha256 checked),
   or start one;
2. fold the done tasks from there on, in task order, each shard file read once and checked
   against its recorded sha256, into one float64 accumulator per medium (memory: the
   accumulator and one shard, whatever the shard count); a finished medium of a sweep is
   written as a part (its three tables) beside the shards; a medium that met its target error
   ends early, and the round commits at once so that its remaining tasks stop being claimed;
3. if tasks remain: save the fold, commit cursor and file fenced by the lease
   (``store.advance_fold``), and wait for the next shards; a killed round leaves the last
   committed fold in place, and the next claim starts from it;
4. once every medium is folded: write the tables into a staging directory (a sweep's parts
   streamed in medium order), ``metadata.json``, and publish with ``store.complete_merge``;
   then remove the job's files (shards, folds, parts) unless ``keep_files``.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field

import pyarrow as pa
import pyarrow.parquet as pq

from schema import SimulationSpec, parse_spec
from service.datasets.jobfiles import JobFiles
from service.datasets.metadata import build_metadata, metadata_bytes
from service.datasets.storage import METADATA_FILE, DatasetStorage, StagedVersion, sha256_bytes
from service.faults import pause_point
from service.store import JobStore, Lease, StoredFile, StoreError
from workers.fold.job import PART_FILES, JobFold, sweep_run_facts, target_rule, write_part, write_sweep_tables
from workers.fold.merge import Result
from workers.fold.output import summary, summary_head, write_tables
from workers.fold.tally import ShardTally

__all__ = ["run_merge_task", "MergeRound", "IncompleteShards", "ResultWindow"]


class IncompleteShards(StoreError):
    """The stored fold does not match the job row's cursor (a bug: they are committed together)."""


class ResultWindow:
    """The fold's reads of shard results, ``size`` tasks per query: ``get(task)`` is the result
    of ``task`` if it was done when its window was read, else None (the fold stops there and
    waits; the commit that ends the round re-checks the next batch, so no wake-up is lost).
    Tasks are asked for in increasing order; a skipped range is jumped over."""

    def __init__(self, store: JobStore, job_id: str, size: int = 64) -> None:
        self.store, self.job_id, self.size = store, job_id, size
        self.results: dict = {}
        self.start = self.stop = 0

    def get(self, task: int):
        if not self.start <= task < self.stop:
            self.start, self.stop = task, task + self.size
            self.results = self.store.shard_results_in(self.job_id, self.start, self.stop)
        return self.results.pop(task, None)


def run_merge_task(store: JobStore, storage: DatasetStorage, lease: Lease, *, keep_files: bool = False) -> int | None:
    """One round of the leased job's merge (module docstring); the version number if it
    published one, else None (the fold advanced and waits for more shards)."""
    t0 = time.perf_counter()
    spec = parse_spec(json.loads(lease.spec_json))
    files = JobFiles(storage, lease.job_id)
    pos = store.fold_position(lease.job_id)
    rule = target_rule(spec)
    if pos.fold is None:
        fold, parts = JobFold(spec, rule), {}
    else:
        state = ShardTally.from_bytes(files.read(pos.fold, "fold"))
        fold, parts = JobFold.from_state(spec, state, rule), dict(state.info.get("parts", {}))
    if fold.next_task != pos.folded:
        raise IncompleteShards(f"job {lease.job_id}: the fold file is at task {fold.next_task}, the job row at {pos.folded}")
    merge_round = MergeRound(store, storage, lease, spec, files, fold, parts, t0=t0, keep_files=keep_files)
    skipped: list[range] = []
    folded_now = 0  # shards folded by this round
    results = ResultWindow(store, lease.job_id)
    while not fold.done:
        task = fold.next_task
        stored = results.get(task)
        if stored is None:
            break
        data = files.read(stored, f"task {task}") if isinstance(stored, StoredFile) else stored
        result = fold.add(task, ShardTally.from_bytes(data))
        del data
        folded_now += 1
        pause_point(f"fold:{folded_now}")  # tests only (service.faults)
        if result is None:
            continue
        if len(fold.skipped):
            skipped.append(fold.skipped)
        if spec.is_sweep:  # every medium of the walk group that finished (workers.fold.job.JobFold)
            for finished in fold.finished:
                merge_round.write_part(finished)
        merge_round.last = result
        if skipped and not fold.done:
            break  # commit the early stop now: its medium's remaining tasks stop being claimed
    if fold.done:
        return merge_round.publish()
    ref = None
    if fold.next_task != pos.folded or pos.fold is None:
        state = fold.state()
        state.info["parts"] = merge_round.parts
        ref = files.write(f"fold/{fold.next_task:08d}-{lease.token}.fold", state.to_bytes())
    try:
        store.advance_fold(lease, folded=fold.next_task, fold=ref or pos.fold, skipped=skipped)
    except BaseException:
        if ref is not None:
            files.delete(ref)
        raise
    if ref is not None:
        files.delete(pos.fold)  # the previous fold: nothing points to it any more
    return None


@dataclass
class MergeRound:
    """One round of a job's merge task: the lease it runs under, the job's spec and files, and
    the fold it advances (``parts``: the recorded tables of the sweep's finished media by medium
    index; ``last``: the result of the medium finished last).  ``t0`` is the round's start
    (``time.perf_counter``), for the merge time the metadata records."""

    store: JobStore
    storage: DatasetStorage
    lease: Lease
    spec: SimulationSpec
    files: JobFiles
    fold: JobFold
    parts: dict[str, dict[str, dict]] = field(default_factory=dict)
    last: Result | None = None
    t0: float = 0.0
    keep_files: bool = False

    def write_part(self, result: Result) -> None:
        """A finished medium's tables as a part of the job, recorded with uri, size and sha256."""
        files = self.files
        directory = files.part_dir(result.medium_index)
        write_part(result, directory, files.fs)
        out = {}
        for name in PART_FILES:
            with files.fs.open_input_stream(f"{directory}/{name}") as f:
                data = f.read()
            out[name] = {"uri": files.part_uri(result.medium_index, name), "bytes": len(data),
                         "sha256": sha256_bytes(data)}
        self.parts[str(result.medium_index)] = out

    def read_parts(self):
        """Each medium's (radial, bins, summary) tables in medium order, sha256 checked, one at a time."""
        for m in range(self.spec.n_media):
            refs = self.parts[str(m)]
            yield tuple(pq.read_table(pa.BufferReader(self.files.read(StoredFile(**refs[name]), f"medium {m} {name}")))
                        for name in PART_FILES)

    def publish(self) -> int:
        """Write the job's tables and metadata into a staging directory and publish the version."""
        store, storage, lease, spec, fold, last = self.store, self.storage, self.lease, self.spec, self.fold, self.last
        job = store.get_job(lease.job_id)
        t_fold = time.perf_counter()
        # In the job's directory: a round killed before the publish leaves its staging directory
        # there, and it goes with the job's files once another round publishes.
        staged = storage.stage(spec.name, within=self.files.path)
        try:
            if spec.is_sweep:
                names = write_sweep_tables(spec, fold.media, self.read_parts(), staged.path, storage.fs)
                doc = summary_head(spec, sweep_run_facts(spec, fold.media)) | {"results_file": "summary.json"}
                per_shard = []  # a sweep's photons are per medium in the run facts
            else:
                names = write_tables(last, staged.path, filesystem=storage.fs)
                doc = summary(last)
                per_shard = [int(i.get("photons", 0)) for i in last.shard_info]
            t_write = time.perf_counter()
            meta = build_metadata(
                name=spec.name, job_id=lease.job_id, spec_json=lease.spec_json, spec_hash=job.spec_hash,
                seed=spec.seed, shards=spec.shards,
                photons=int(sum(m["photons"] for m in fold.media)),
                photons_per_shard=per_shard,
                timings={
                    "shard_walk_s_sum": float(sum(m["walk_s"] for m in fold.media)),
                    "merge_s": t_fold - self.t0,  # the last fold round
                    "write_s": t_write - t_fold,
                    "job_wall_s": (store.now() - job.started_at) if job.started_at else None,
                },
                summary=doc,
                files=staged.checksums(list(names)),
            )
            blob = metadata_bytes(meta)
            staged.write_bytes(METADATA_FILE, blob)
            row_meta = dict(meta, metadata_sha256=sha256_bytes(blob))
            pause_point("staged")  # tests only (service.faults)
            version = store.complete_merge(lease, spec.name, row_meta, _Publisher(staged))
        except BaseException:
            staged.discard()
            raise
        if not self.keep_files:
            self.files.discard()
        return version


class _Publisher:
    """The staged version as ``complete_merge`` publishes it, with the test-only fault point
    ``publish`` (:mod:`service.faults`) once its files are in place, before the commit."""

    def __init__(self, staged: StagedVersion) -> None:
        self.staged = staged

    def uri_for(self, version: int) -> str:
        return self.staged.uri_for(version)

    def publish(self, version: int) -> None:
        self.staged.publish(version)
        pause_point("publish")
