"""The fold of a job, whatever its media: its tasks' tallies in task order, then its tables.

A job is G walk groups x S shards, task t = k S + s (:mod:`schema.media`, :mod:`schema.groups`).
Task t runs shard s of the group leader's own single-medium spec (:func:`workers.run.task.run_task`), so it has one
eta and one compiled walk kernel, and tallies the group's other albedos from the same walk
(:mod:`workers.fold.reweight`).  With independent walks every group is one medium and a sweep's entry
is the single-medium job bit for bit; with shared walks that holds for each group's leader.
:class:`JobFold` folds the tallies in task order, one group at a time (a
:class:`workers.fold.merge.Fold` per member): memory is one accumulator per member of the group and
one shard whatever the shard and medium counts. A finished medium's tables are written as a *part* (:func:`write_part`),
and the parts are streamed into the job's tables at the end (:func:`write_sweep_tables`):
a medium per row group, summary.json row by row.

Early stop (the spec's target error, schema/target.py): a ``stop_rule(result) -> bool`` given to JobFold is asked
after each folded shard of a group, for every member; when it holds for all of them at K shards
the group ends there (each member's result is exactly the fold of shards 0..K-1: a group's
photons are set by its hardest member) and the fold moves on to the next group's shard 0; :meth:`JobFold.skipped` names the tasks whose results are then never counted.
"""

from __future__ import annotations

from typing import Callable, Iterable

import pyarrow as pa
import pyarrow.fs as pafs
import pyarrow.parquet as pq

from schema import SimulationSpec
from schema.version import code_version

from .finite import check_finite
from .merge import Fold, MergeError, Result
from .output import NORMALISATION, RNG_FACT, TableWriter, bins_table, engine_fact, radial_table, summary_table
from .reweight import member_prefix
from .tally import ShardTally
from .target import target_status

__all__ = [
    "walk_facts", "split_group_tally", "JobFold", "StopRule", "target_rule", "medium_facts", "sweep_run_facts",
    "write_part", "read_part", "write_sweep_tables", "PART_FILES",
]

StopRule = Callable[[Result], bool]
PART_FILES = ("radial.parquet", "bins.parquet", "summary.parquet")


def split_group_tally(tally: ShardTally, n_members: int) -> list[ShardTally]:
    """A group task's tally as one tally per medium of the group, in medium order (members, then
    the leader): member j's are its ``member_prefix(j)`` quantities; the leader's the rest."""
    if n_members == 0:
        return [tally]
    out = []
    for j in range(n_members):
        p = member_prefix(j)
        stats = {k[len(p):]: v for k, v in tally.stats.items() if k.startswith(p)}
        counts = {k[len(p):]: v for k, v in tally.counts.items() if k.startswith(p)}
        if not stats:
            raise MergeError(f"shard {tally.shard_index} has no quantities of group member {j}")
        out.append(ShardTally(tally.shard_index, stats, counts, tally.n_sum, dict(tally.info, shared_walk=True)))
    own = lambda k: not k.startswith(tuple(member_prefix(j) for j in range(n_members)))  # noqa: E731
    out.append(ShardTally(tally.shard_index, {k: v for k, v in tally.stats.items() if own(k)},
                          {k: v for k, v in tally.counts.items() if own(k)}, tally.n_sum, tally.info))  # fmt: skip
    return out


def target_rule(spec: SimulationSpec) -> StopRule | None:
    """The early-stop rule of the spec's target error (:func:`workers.fold.target.target_status` on
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
    shared = any(i.get("shared_walk") or i.get("members") for i in result.shard_info)
    facts = {"medium": result.medium_index, "photons_per_config": int(result.n_sum), "shared_walk": bool(shared),
             "batches": int(result.spec.batches_per_shard * len(result.shard_info)),  # the spec's batches run
             "shards": len(result.shard_info), "engine": engine_fact(result.shard_info),
             "photons": int(sum(i.get("photons", 0) for i in result.shard_info)),
             "walk_s": float(sum(i.get("elapsed_s", 0.0) for i in result.shard_info))}
    return facts | ({} if result.target is None else {"target": result.target.as_dict()})


class JobFold:
    """The job's tallies folded in task order, walk group by walk group (module docstring)."""

    def __init__(self, spec: SimulationSpec, stop_rule: StopRule | None = None):
        self.spec, self.stop_rule = spec, stop_rule
        self.groups = spec.walk_groups()
        self.group = 0  # the walk group being folded (len(groups) once done)
        self.folds: list[Fold] | None = self._folds(0)
        self.media: list[dict] = []  # medium_facts of the finished media
        self.finished: list[Result] = []  # the media finished by the last add (medium order)
        self.last_skipped: range = range(0)

    def _folds(self, group: int) -> list[Fold]:
        return [Fold(self.spec.medium_spec(m), m) for m in self.groups[group]]

    @property
    def medium(self) -> int:
        """Media finished so far (n_media once done): the first medium of the current group."""
        return len(self.media)

    @property
    def fold(self) -> Fold | None:
        """The current group leader's fold (None once done)."""
        return None if self.folds is None else self.folds[-1]

    @property
    def done(self) -> bool:
        """Whether every medium is finished."""
        return self.group == len(self.groups)

    @property
    def next_task(self) -> int:
        """The task to fold next (task_count once done)."""
        return self.spec.task_count() if self.done else self.group * self.spec.shards + self.folds[0].shards

    def add(self, task: int, tally: ShardTally) -> Result | None:
        """Fold task ``task`` (it must be :attr:`next_task`); when this finished its group (all
        shards, or the stop rule held for every member) the group's Results are in
        :attr:`finished` (medium order) and the last of them is returned, else None."""
        if task != self.next_task or self.done:
            raise MergeError(f"the fold expects task {self.next_task} next; received task {task}")
        for fold, part in zip(self.folds, split_group_tally(tally, len(self.folds) - 1)):
            fold.add(part)
        complete = self.folds[0].complete
        if self.stop_rule is None and not complete:
            return None
        results = [f.result() for f in self.folds]
        reached = self.stop_rule is not None and all([self.stop_rule(r) for r in results])  # every member judged
        if not reached and not complete:
            return None
        first_unused = self.next_task
        self.media.extend(medium_facts(r) for r in results)
        self.finished = results
        self.group += 1
        self.folds = None if self.done else self._folds(self.group)
        self.last_skipped = range(first_unused, self.group * self.spec.shards)
        return results[-1]

    @property
    def skipped(self) -> range:
        """Tasks of the group finished by the last :meth:`add` that were not folded (empty
        unless the stop rule ended it early): their results are never counted."""
        return self.last_skipped

    def state(self) -> ShardTally:
        """The fold to save between processes: the current group's Fold states (members'
        quantities prefixed as in a group task's tally) plus the facts of the finished media
        (``ShardTally.to_bytes`` of it)."""
        folds = self.folds if self.folds is not None else [Fold(self.spec, self.medium)]
        *members, leader = [f.state() for f in folds]
        state = ShardTally(leader.shard_index, dict(leader.stats), dict(leader.counts), leader.n_sum, leader.info)  # not the fold's own dicts
        for j, m in enumerate(members):
            state.stats.update({member_prefix(j) + k: v for k, v in m.stats.items()})
            state.counts.update({member_prefix(j) + k: v for k, v in m.counts.items()})
        state.info = dict(state.info, job_medium=self.medium, job_group=self.group, media=self.media,
                          member_info=[m.info for m in members])  # fmt: skip
        return state

    @classmethod
    def from_state(cls, spec: SimulationSpec, state: ShardTally, stop_rule: StopRule | None = None) -> "JobFold":
        """The fold saved by :meth:`state`."""
        job = cls(spec, stop_rule)
        job.group, job.media = int(state.info.get("job_group", state.info["job_medium"])), list(state.info["media"])
        if job.done:
            job.folds = None
        elif state.shard_index == 0:  # saved before the group's first shard: nothing to restore
            job.folds = job._folds(job.group)
        else:
            infos = state.info.get("member_info", [])
            parts = split_group_tally(state, len(infos))
            for part, info in zip(parts, infos):
                part.info = info
            job.folds = [Fold.from_state(spec.medium_spec(m), part) for m, part in zip(job.groups[job.group], parts)]
        first = sum(len(g) for g in job.groups[: job.group])
        if len(job.media) != first or int(state.info["job_medium"]) != first:
            raise MergeError(f"fold state at walk group {job.group} lists {len(job.media)} finished media, expected {first}")
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
        "walks": walk_facts(spec),
        "units": {"length": "mm = mean free paths (sigma_t = 1/mm)", "Rd_r": "1/mm^2", "S": "1/(mm^2 sr)",
                  "G": "fraction of incident power"},
        "normalisation": NORMALISATION,
    }  # fmt: skip


def walk_facts(spec: SimulationSpec) -> dict:
    """How the media were walked, and what that means for the correlation between rows."""
    groups = spec.walk_groups()
    if spec.walk_mode() == "independent":
        return {"mode": "independent", "correlation": "every medium has its own walk: rows of different media are independent"}
    return {
        "mode": "shared",
        "groups": [[g[0], g[-1]] for g in groups],  # first and last medium of each group; the last is the walked (leader) albedo
        "correlation": "media of one group (albedos first..last) are tallied from the same photons, walked at the group's "
                       "largest albedo and reweighted by (albedo / walked albedo)^n per photon with n scatterings: their rows "
                       "are positively correlated (nearly fully for neighbouring albedos); groups are independent. The walked "
                       "albedo's rows equal its own single-medium job bit for bit.",
    }  # fmt: skip


def write_part(result: Result, directory: str, filesystem: pafs.FileSystem) -> list[str]:
    """One medium's tables as Parquet files in ``directory`` (no run metadata); the file names.
    Refused (:class:`workers.fold.finite.NonFiniteResult`) if one holds a non-finite number."""
    tables = (radial_table(result), bins_table(result), summary_table(result))
    for name, table in zip(("radial", "bins", "summary"), tables):
        check_finite(table, name)
    filesystem.create_dir(directory, recursive=True)
    for name, table in zip(PART_FILES, tables):
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
