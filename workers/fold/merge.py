"""Deterministic merge of shard tallies into a result with means and standard errors: the fold in
shard order (:class:`Fold`, streaming: one float64 accumulator, saved and restored between
processes) and :func:`merge` of a set of shards, which is that fold."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from schema import SimulationSpec

from .configs import BinLayout, Configs, bin_layout, build_configs
from .tally import ShardTally, units_name

__all__ = ["Result", "Fold", "merge", "MergeError"]


class MergeError(ValueError):
    """The tallies given do not form the complete, consistent set of a spec's shards."""


@dataclass
class Result:
    """Merged statistics of a whole run; see workers.fold.tally for the definitions.

    mean(name) is the estimate per launched photon (per unit incident power, since every photon
    carries incident power 1 before the entry Fresnel split) and stderr(name) its standard error.
    """

    spec: SimulationSpec
    configs: Configs
    layout: BinLayout
    stats: dict[str, list[np.ndarray]]
    counts: dict[str, np.ndarray]
    n_sum: int
    shard_info: list[dict] = field(default_factory=list)
    medium_index: int = 0  # index of the medium in its job (schema.media); 0 for a single medium
    target: object | None = None  # workers.fold.target.TargetStatus of a run to a target error

    @property
    def estimators(self) -> list[str]:
        return sorted({name.split("/")[0] for name in self.stats} - {"walk"})

    def mean(self, name: str) -> np.ndarray:
        return self.stats[name][0] / self.n_sum

    def units(self, name: str) -> tuple[int, int]:
        """(K, NN) of the units quantity `name`'s standard error comes from (workers.fold.tally)."""
        k, nn = self.counts[units_name(name.split("/")[0])]
        return int(k), int(nn)

    def dof(self, name: str) -> int:
        """Degrees of freedom of stderr(name): units - 1 (photons - 1, or batches - 1)."""
        return self.units(name)[0] - 1

    def events(self, name: str) -> np.ndarray:
        """Contributing events per entry of `name` (int64)."""
        return self.counts[name]

    def stderr(self, name: str) -> np.ndarray:
        """Standard error per entry; NaN where no event contributed (no error bar, not 0)."""
        s1, s2, sxn = self.stats[name]
        k, nn = self.units(name)
        m = s1 / self.n_sum
        # Sum of squared residuals x_k - m n_k; clamp the tiny negative values rounding can leave.
        ss = np.maximum(s2 - 2.0 * m * sxn + m * m * nn, 0.0)
        se = np.sqrt(k / (k - 1) * ss) / self.n_sum
        return np.where(self.counts[name] > 0, se, np.nan)


class Fold:
    """Shard tallies added one at a time in shard order (0, 1, 2, ...) into float64 sums.

    After adding shards 0..K-1, :meth:`result` is bitwise the merge of those K shards: the sums
    are formed in the same order whether the shards come all at once or one by one.  Memory is
    one accumulator plus the shard being added, whatever the shard count.  ``medium_index`` is
    the medium's index in its job (:mod:`schema.media`); :meth:`state` / :meth:`from_state`
    save and restore a fold between processes.
    """

    def __init__(self, spec: SimulationSpec, medium_index: int = 0):
        self.spec, self.medium_index = spec, medium_index
        self.stats: dict[str, list[np.ndarray]] = {}
        self.counts: dict[str, np.ndarray] = {}
        self.n_sum = 0
        self.shard_info: list[dict] = []

    @property
    def shards(self) -> int:
        """Shards folded so far (0..shards-1)."""
        return len(self.shard_info)

    @property
    def complete(self) -> bool:
        """Whether every shard of the spec has been folded."""
        return self.shards == self.spec.shards

    def add(self, tally: ShardTally) -> None:
        """Fold the next shard; MergeError if it is not shard :attr:`shards` or its quantities differ."""
        if tally.shard_index != self.shards or self.shards >= self.spec.shards:
            raise MergeError(f"shards fold in order: expected shard {self.shards} of {self.spec.shards}, received {tally.shard_index}")
        if not self.stats:
            self.stats = {name: [a.copy() for a in tally.stats[name]] for name in sorted(tally.stats)}
            self.counts = {name: tally.counts[name].copy() for name in sorted(tally.counts)}
        elif set(tally.stats) != set(self.stats) or set(tally.counts) != set(self.counts):
            raise MergeError(f"shard {tally.shard_index} has quantities {sorted(tally.stats)}, expected {sorted(self.stats)}")
        else:
            for name, acc in self.stats.items():
                for a, part in zip(acc, tally.stats[name]):
                    a += part
            for name, acc in self.counts.items():
                acc += tally.counts[name]
        self.n_sum += tally.n_sum
        self.shard_info.append(dict(tally.info, shard_index=tally.shard_index))

    def result(self) -> Result:
        """The merged statistics of the shards folded so far (sharing this fold's arrays: fold no
        more shards into it while the result is in use)."""
        if not self.shards:
            raise MergeError("no shard folded yet")
        return Result(
            spec=self.spec, configs=build_configs(self.spec), layout=bin_layout(self.spec), stats=self.stats,
            counts=self.counts, n_sum=self.n_sum, shard_info=list(self.shard_info),
            medium_index=self.medium_index,
        )  # fmt: skip

    def state(self) -> ShardTally:
        """The fold as a ShardTally (``shard_index`` = shards folded; info holds the shards' info),
        to save with :meth:`ShardTally.to_bytes`."""
        return ShardTally(self.shards, self.stats, self.counts, self.n_sum,
                          {"shard_info": self.shard_info, "medium_index": self.medium_index})

    @classmethod
    def from_state(cls, spec: SimulationSpec, state: ShardTally) -> "Fold":
        """The fold saved by :meth:`state`."""
        fold = cls(spec, int(state.info["medium_index"]))
        fold.stats, fold.counts = state.stats, state.counts
        fold.n_sum = state.n_sum
        fold.shard_info = list(state.info["shard_info"])
        if fold.shards != state.shard_index:
            raise MergeError(f"fold state says {state.shard_index} shards but lists {fold.shards}")
        return fold


def merge(spec: SimulationSpec, tallies: Sequence[ShardTally], *, prefix: bool = False, medium_index: int = 0) -> Result:
    """Sum the shards' statistics in shard order (float64), so the result is bitwise fixed.

    Requires exactly one tally per shard index 0..spec.shards-1, in any order; with prefix=True,
    one per shard 0..K-1 for some K >= 1 (the first K shards, as a run to a target error uses).
    The merge of the first K shards does not depend on the shards after them.
    """
    ordered = sorted(tallies, key=lambda t: t.shard_index)
    indices = [t.shard_index for t in ordered]
    k = len(indices) if prefix else spec.shards
    if not indices or indices != list(range(k)) or k > spec.shards:
        want = f"shards 0..K-1 for some K in [1, {spec.shards}]" if prefix else f"shards 0..{spec.shards - 1}"
        raise MergeError(f"merge needs {want} exactly once; received {indices[:20]}")
    fold = Fold(spec, medium_index)
    for t in ordered:
        fold.add(t)
    return fold.result()
