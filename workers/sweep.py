"""A job's media in the workers: run a task, fold the tasks in order, write a sweep's tables.

A job is M media x S shards, task t = m S + s (:mod:`schema.media`). Task t runs shard s of
medium m's own single-medium spec (:func:`run_task`), so it has one medium, one eta and one
compiled walk kernel, and a sweep's entry is the single-medium job bit for bit.
:class:`JobFold` folds the tallies in task order, one medium at a time (a
:class:`workers.merge.Fold` each): memory is one accumulator and one shard whatever the shard
and medium counts. A finished medium's tables are written as a *part* (:func:`write_part`),
and the parts are streamed into the job's tables at the end (:func:`write_sweep_tables`):
a medium per row group, summary.json row by row.

Early stop (the spec's target error, schema/target.py): a ``stop_rule(result) -> bool`` given to
JobFold is asked after each folded shard of a medium; when it holds at K shards the medium ends
there (its result is exactly the fold of shards 0..K-1) and the fold moves on to the next
medium's shard 0; :meth:`JobFold.skipped` names the tasks whose results are then never counted.
"""

from __future__ import annotations

from typing import Callable, Iterable

import pyarrow as pa
import pyarrow.fs as pafs
import pyarrow.parquet as pq

from schema import SimulationSpec
from schema.version import code_version

from .merge import Fold, MergeError, Result
from .output import NORMALISATION, RNG_FACT, TableWriter, bins_table, engine_fact, radial_table, summary_table
from .shard import run_shard
from .tally import ShardTally
from .target import target_status

__all__ = [
    "run_task", "JobFold", "StopRule", "target_rule", "medium_facts", "sweep_run_facts",
    "write_part", "read_part", "write_sweep_tables", "PART_FILES",
]

StopRule = Callable[[Result], bool]
PART_FILES = ("radial.parquet", "bins.parquet", "summary.parquet")


def run_task(spec: SimulationSpec, task: int, *, progress: Callable[[int], None] | None = None) -> ShardTally:
    """Task ``task`` of the job: shard s of medium m's own spec (t = m * shards + s)."""
    medium, shard = spec.task_of(task)
    return run_shard(spec.medium_spec(medium), shard, progress=progress)


def target_rule(spec: SimulationSpec) -> StopRule | None:
    """The early-stop rule of the spec's target error (:func:`workers.target.target_status` on
    the merge of a medium's first K shards), or None without a target (every shard runs).
    The rule records the status on the result it judged (``result.target``)."""
    if spec.target is None:
        return None
    target = spec.target

    def reached(result: Result) -> bool:
        result.target = target_status(result, target)
        return result.target.reached

    return reached


def medium_facts(result: Result) -> dict:
    """What the job's run facts record of one finished medium (its target status if it ran to one)."""
    facts = {"medium": result.medium_index, "photons_per_config": int(result.n_sum),
             "batches": int(result.spec.batches_per_shard * len(result.shard_info)),  # the spec's batches run
             "shards": len(result.shard_info), "engine": engine_fact(result.shard_info),
             "photons": int(sum(i.get("photons", 0) for i in result.shard_info)),
             "walk_s": float(sum(i.get("elapsed_s", 0.0) for i in result.shard_info))}
    return facts | ({} if result.target is None else {"target": result.target.as_dict()})


class JobFold:
    """The job's tallies folded in task order, medium by medium (see the module docstring)."""

    def __init__(self, spec: SimulationSpec, stop_rule: StopRule | None = None):
        self.spec, self.stop_rule = spec, stop_rule
        self.medium = 0  # the medium being folded (n_media once done)
        self.fold: Fold | None = Fold(spec.medium_spec(0), 0)
        self.media: list[dict] = []  # medium_facts of the finished media
        self.last_skipped: range = range(0)

    @property
    def done(self) -> bool:
        """Whether every medium is finished."""
        return self.medium == self.spec.n_media

    @property
    def next_task(self) -> int:
        """The task to fold next (task_count once done)."""
        return self.spec.task_count() if self.done else self.medium * self.spec.shards + self.fold.shards

    def add(self, task: int, tally: ShardTally) -> Result | None:
        """Fold task ``task`` (it must be :attr:`next_task`); the medium's Result when this
        finished it (all shards, or the stop rule held), else None."""
        if task != self.next_task or self.done:
            raise MergeError(f"the fold expects task {self.next_task} next; received task {task}")
        self.fold.add(tally)
        if self.stop_rule is None and not self.fold.complete:
            return None
        result = self.fold.result()
        if not (self.stop_rule is not None and self.stop_rule(result)) and not self.fold.complete:
            return None
        first_unused = self.next_task
        self.media.append(medium_facts(result))
        self.medium += 1
        self.fold = None if self.done else Fold(self.spec.medium_spec(self.medium), self.medium)
        self.last_skipped = range(first_unused, self.medium * self.spec.shards)
        return result

    @property
    def skipped(self) -> range:
        """Tasks of the medium finished by the last :meth:`add` that were not folded (empty
        unless the stop rule ended it early): their results are never counted."""
        return self.last_skipped

    def state(self) -> ShardTally:
        """The fold to save between processes: the current medium's Fold state plus the facts
        of the finished media (``ShardTally.to_bytes`` of it)."""
        state = self.fold.state() if self.fold is not None else Fold(self.spec, self.medium).state()
        state.info = dict(state.info, job_medium=self.medium, media=self.media)
        return state

    @classmethod
    def from_state(cls, spec: SimulationSpec, state: ShardTally, stop_rule: StopRule | None = None) -> "JobFold":
        """The fold saved by :meth:`state`."""
        job = cls.__new__(cls)
        job.spec, job.stop_rule = spec, stop_rule
        job.medium, job.media = int(state.info["job_medium"]), list(state.info["media"])
        job.last_skipped = range(0)
        if len(job.media) != job.medium:
            raise MergeError(f"fold state at medium {job.medium} lists {len(job.media)} finished media")
        job.fold = None if job.done else Fold.from_state(spec.medium_spec(job.medium), state)
        return job


def sweep_run_facts(spec: SimulationSpec, media: list[dict]) -> dict:
    """Deterministic run facts of a sweep (every table's metadata): per medium the photons per
    configuration, batches and shards folded; the engine of all shards."""
    engines = sorted({e for m in media for e in ([m["engine"]] if isinstance(m["engine"], str) else m["engine"])})
    return {
        "code_version": code_version(),
        "engine": engines[0] if len(engines) == 1 else engines,
        "rng": RNG_FACT,
        "media": spec.n_media,
        "photons_per_config": [m["photons_per_config"] for m in media],
        "shards": spec.shards,
        "shards_folded": [m["shards"] for m in media],
        "batches": [m["batches"] for m in media],
        "seed": spec.seed,
        "units": {"length": "mm = mean free paths (sigma_t = 1/mm)", "Rd_r": "1/mm^2", "S": "1/(mm^2 sr)",
                  "G": "fraction of incident power"},
        "normalisation": NORMALISATION,
    }  # fmt: skip


def write_part(result: Result, directory: str, filesystem: pafs.FileSystem) -> list[str]:
    """One medium's tables as Parquet files in ``directory`` (no run metadata); the file names."""
    filesystem.create_dir(directory, recursive=True)
    for name, table in zip(PART_FILES, (radial_table(result), bins_table(result), summary_table(result))):
        with filesystem.open_output_stream(f"{directory}/{name}") as f:
            pq.write_table(table, f, compression="zstd")
    return list(PART_FILES)


def read_part(directory: str, filesystem: pafs.FileSystem) -> tuple[pa.Table, pa.Table, pa.Table]:
    """(radial, bins, summary) tables of a part written by :func:`write_part`."""
    return tuple(pq.read_table(f"{directory}/{name}", filesystem=filesystem) for name in PART_FILES)


def write_sweep_tables(spec: SimulationSpec, media: list[dict], parts: Iterable[tuple[pa.Table, pa.Table, pa.Table]],
                       out_dir: str, filesystem: pafs.FileSystem | None = None) -> list[str]:
    """The job's tables from its media's tables in medium order (``parts`` yields them one at a
    time: memory is one medium's tables); ``media`` are the finished media's facts."""
    targets = {"target": [m.get("target") for m in media]} if spec.target is not None else {}
    writer = TableWriter(out_dir, spec, sweep_run_facts(spec, media), filesystem, extra=targets)
    for tables in parts:
        writer.add_tables(*tables)
    return writer.close()
