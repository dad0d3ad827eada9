"""Tallies: per-batch histograms folded into batch statistics, and the shard result.

Standard errors come from independent batches of photons (ARCHITECTURE.md).  Every quantity Q is
summed per batch k of n_k photons (x_k = sum of Q over the batch), and a shard keeps only

    S1 = sum_k x_k,   S2 = sum_k x_k^2,   SXN = sum_k x_k n_k,
    N = sum_k n_k,    NN = sum_k n_k^2,   K = number of batches,

which add across shards.  The estimate per photon is m = S1 / N and its standard error, the ratio
estimator's (batches may differ by one photon in size),

    se(m)^2 = K / (K - 1) * (S2 - 2 m SXN + m^2 NN) / N^2.

``total`` (single + multiple) is formed per batch before squaring, so its error keeps the
covariance of the two components.  All sums are float64; a batch's histogram is accumulated with
np.bincount, which adds in input order, and the input order is fixed by the photon schedule, so
a shard's bytes do not depend on threads.
"""

from __future__ import annotations

import io
import json
from dataclasses import dataclass, field

import numpy as np

__all__ = ["BatchAccumulator", "ShardTally", "QUANTITIES"]

QUANTITIES = ("bins_G", "bins_S", "radial_G", "Rd", "absorbed", "truncated")
"""Per estimator: bins_G / bins_S [cfg, comp3, n_r+1, n_theta, n_cos, n_phi] (sum of w and of
w / cos_o per bin, radial index n_r = beyond r_max), radial_G [cfg, comp3, n_r+1], Rd [cfg, comp3];
absorbed and truncated [cfg] (walk totals, not per estimator, stored under the key "walk")."""


def _fold(stats: dict[str, list[np.ndarray]], name: str, q: np.ndarray, n: int) -> None:
    if name not in stats:
        stats[name] = [np.zeros_like(q), np.zeros_like(q), np.zeros_like(q)]
    s1, s2, sxn = stats[name]
    s1 += q
    s2 += q * q
    sxn += q * n


class BatchAccumulator:
    """Histograms of the batches in flight, folded into statistics as each batch completes.

    estimators: names of the estimators tallied ("exits", "connections").
    hist_shape: (n_r + 1, n_theta, n_cos, n_phi).  batch_ranges: [(start, stop)] photon ranges
    of this shard's batches; each photon index runs once per configuration.
    """

    def __init__(self, estimators: list[str], n_cfg: int, hist_shape: tuple[int, ...], batch_ranges: list[tuple[int, int]]):
        self.estimators = list(estimators)
        self.n_cfg = n_cfg
        self.hist_shape = tuple(hist_shape)
        self.hist_size = n_cfg * 2 * int(np.prod(self.hist_shape))
        self.starts = np.array([a for a, _ in batch_ranges], dtype=np.int64)
        self.sizes = [b - a for a, b in batch_ranges]
        self.remaining = [size * n_cfg for size in self.sizes]
        self.open: dict[int, dict[str, np.ndarray]] = {}
        self.stats: dict[str, list[np.ndarray]] = {}
        self.n_sum = 0
        self.nn_sum = 0
        self.k = 0

    def batch_of(self, photon: np.ndarray) -> np.ndarray:
        return np.searchsorted(self.starts, photon, side="right") - 1

    def _batch(self, b: int) -> dict[str, np.ndarray]:
        if b not in self.open:
            arrays = {f"{e}/{q}": np.zeros(self.hist_size) for e in self.estimators for q in ("G", "S")}
            arrays["absorbed"] = np.zeros(self.n_cfg)
            arrays["truncated"] = np.zeros(self.n_cfg)
            self.open[b] = arrays
        return self.open[b]

    def add_hist(self, estimator: str, batch: np.ndarray, flat: np.ndarray, g: np.ndarray, s: np.ndarray) -> None:
        """Add contributions g (to G) and s (to S, i.e. g / cos_o) at flat histogram indices."""
        for b, sel in _groups(batch):
            f, gw, sw = (flat, g, s) if sel is None else (flat[sel], g[sel], s[sel])
            arrays = self._batch(b)
            arrays[f"{estimator}/G"] += np.bincount(f, weights=gw, minlength=self.hist_size)
            arrays[f"{estimator}/S"] += np.bincount(f, weights=sw, minlength=self.hist_size)

    def finish_photons(self, key: np.ndarray, absorbed: np.ndarray, truncated: np.ndarray) -> int:
        """Record finished photons; returns how many there were.

        key = batch * n_cfg + cfg per entry (a value from n_batches * n_cfg up marks an entry that
        is not a finished photon), with the photon's absorbed and truncated weights.

        Complete batches are folded by :meth:`fold_ready`, which the caller invokes once every
        contribution of those photons has been added (connections are tallied in chunks).
        """
        n = len(self.sizes) * self.n_cfg
        counts = np.bincount(key, minlength=n)[:n].reshape(-1, self.n_cfg)
        ab = np.bincount(key, weights=absorbed, minlength=n)[:n].reshape(-1, self.n_cfg)
        tr = np.bincount(key, weights=truncated, minlength=n)[:n].reshape(-1, self.n_cfg)
        per_batch = counts.sum(axis=1)
        for b in np.flatnonzero(per_batch):
            arrays = self._batch(int(b))
            arrays["absorbed"] += ab[b]
            arrays["truncated"] += tr[b]
            self.remaining[b] -= int(per_batch[b])
        return int(per_batch.sum())

    @property
    def ready(self) -> bool:
        """Whether some open batch has all its photons finished."""
        return any(self.remaining[b] == 0 for b in self.open)

    def fold_ready(self) -> None:
        """Fold every complete batch into the statistics, in batch order."""
        for b in sorted(b for b in self.open if self.remaining[b] == 0):
            self._fold_batch(b)

    def _fold_batch(self, b: int) -> None:
        arrays = self.open.pop(b)
        n = self.sizes[b]
        for e in self.estimators:
            for q in ("G", "S"):
                two = arrays[f"{e}/{q}"].reshape(self.n_cfg, 2, *self.hist_shape)
                three = np.concatenate([two, two.sum(axis=1, keepdims=True)], axis=1)
                _fold(self.stats, f"{e}/bins_{q}", three, n)
                if q == "G":
                    radial = three.sum(axis=(3, 4, 5))
                    _fold(self.stats, f"{e}/radial_G", radial, n)
                    _fold(self.stats, f"{e}/Rd", radial.sum(axis=2), n)
        _fold(self.stats, "walk/absorbed", arrays["absorbed"], n)
        _fold(self.stats, "walk/truncated", arrays["truncated"], n)
        self.n_sum += n
        self.nn_sum += n * n
        self.k += 1

    @property
    def complete(self) -> bool:
        return not self.open and all(r == 0 for r in self.remaining)


def _groups(batch: np.ndarray):
    """(batch, selection) for each batch present, in batch order; selection None when all
    events are in one batch (usual: photons run in order).  Only the batches present: one in
    between may already be folded and must not be reopened."""
    if batch.size == 0:
        return
    lo, hi = int(batch.min()), int(batch.max())
    if lo == hi:
        yield lo, None
        return
    for b in range(lo, hi + 1):  # few batches: a comparison each beats sorting the events
        sel = batch == b
        if sel.any():
            yield b, sel


@dataclass
class ShardTally:
    """What one shard contributes: batch statistics plus run facts.  Serialises to bytes."""

    shard_index: int
    stats: dict[str, list[np.ndarray]]  # name -> [S1, S2, SXN]
    n_sum: int  # photons per configuration, summed over batches
    nn_sum: int
    k: int  # batches
    info: dict = field(default_factory=dict)  # steps, vertices, elapsed_s, engine, lanes

    @property
    def photons(self) -> int:
        """Photons simulated in this shard, all configurations together."""
        return int(self.info.get("photons", 0))

    @property
    def elapsed_s(self) -> float:
        return float(self.info.get("elapsed_s", 0.0))

    def to_bytes(self) -> bytes:
        arrays = {}
        for name, (s1, s2, sxn) in self.stats.items():
            arrays[f"{name}|S1"], arrays[f"{name}|S2"], arrays[f"{name}|SXN"] = s1, s2, sxn
        header = {"shard_index": self.shard_index, "n_sum": self.n_sum, "nn_sum": self.nn_sum, "k": self.k, "info": self.info}
        arrays["__header__"] = np.frombuffer(json.dumps(header, sort_keys=True).encode(), dtype=np.uint8)
        buf = io.BytesIO()
        np.savez_compressed(buf, **arrays)
        return buf.getvalue()

    @classmethod
    def from_bytes(cls, data: bytes) -> "ShardTally":
        with np.load(io.BytesIO(data), allow_pickle=False) as z:
            header = json.loads(z["__header__"].tobytes().decode())
            stats: dict[str, list[np.ndarray]] = {}
            for key in z.files:
                if key == "__header__":
                    continue
                name, part = key.rsplit("|", 1)
                stats.setdefault(name, [None, None, None])[("S1", "S2", "SXN").index(part)] = z[key]
        return cls(header["shard_index"], stats, header["n_sum"], header["nn_sum"], header["k"], header["info"])
