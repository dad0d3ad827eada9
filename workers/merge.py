"""Deterministic merge of shard tallies into a result with means and standard errors."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from schema import SimulationSpec

from .binning import BinLayout
from .shard import Configs, bin_layout, build_configs
from .tally import ShardTally

__all__ = ["Result", "merge", "MergeError"]


class MergeError(ValueError):
    """The tallies given do not form the complete, consistent set of a spec's shards."""


@dataclass
class Result:
    """Merged statistics of a whole run; see workers.tally for the definitions.

    mean(name) is the estimate per launched photon (per unit incident power, since every photon
    carries incident power 1 before the entry Fresnel split) and stderr(name) its standard error.
    """

    spec: SimulationSpec
    configs: Configs
    layout: BinLayout
    stats: dict[str, list[np.ndarray]]
    n_sum: int
    nn_sum: int
    k: int
    shard_info: list[dict] = field(default_factory=list)
    medium_index: int = 0  # index of the medium in its job (schema.media); 0 for a single medium

    @property
    def estimators(self) -> list[str]:
        return sorted({name.split("/")[0] for name in self.stats} - {"walk"})

    def mean(self, name: str) -> np.ndarray:
        return self.stats[name][0] / self.n_sum

    def stderr(self, name: str) -> np.ndarray:
        s1, s2, sxn = self.stats[name]
        m = s1 / self.n_sum
        # Sum of squared residuals x_k - m n_k; clamp the tiny negative values rounding can leave.
        ss = np.maximum(s2 - 2.0 * m * sxn + m * m * self.nn_sum, 0.0)
        return np.sqrt(self.k / (self.k - 1) * ss) / self.n_sum


def merge(spec: SimulationSpec, tallies: Sequence[ShardTally]) -> Result:
    """Sum the shards' statistics in shard order (float64), so the result is bitwise fixed.

    Requires exactly one tally per shard index 0..spec.shards-1, in any order.
    """
    ordered = sorted(tallies, key=lambda t: t.shard_index)
    indices = [t.shard_index for t in ordered]
    if indices != list(range(spec.shards)):
        raise MergeError(f"merge needs shards 0..{spec.shards - 1} exactly once; received {indices}")
    names = set(ordered[0].stats)
    stats = {name: [a.copy() for a in ordered[0].stats[name]] for name in sorted(names)}
    for t in ordered[1:]:
        if set(t.stats) != names:
            raise MergeError(f"shard {t.shard_index} has quantities {sorted(t.stats)}, expected {sorted(names)}")
        for name in stats:
            for acc, part in zip(stats[name], t.stats[name]):
                acc += part
    return Result(
        spec=spec, configs=build_configs(spec), layout=bin_layout(spec), stats=stats,
        n_sum=sum(t.n_sum for t in ordered), nn_sum=sum(t.nn_sum for t in ordered), k=sum(t.k for t in ordered),
        shard_info=[dict(t.info, shard_index=t.shard_index) for t in ordered],
    )  # fmt: skip
