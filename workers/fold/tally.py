"""Tallies: per-photon and per-batch moments, event counts, and the shard result.

Every quantity Q (a histogram entry, a ring, Rd, the absorbed weight...) is estimated per launched
photon; its standard error comes from independent *units* whose sums x_u (over n_u photons) are
kept as

    S1 = sum_u x_u,   S2 = sum_u x_u^2,   SXN = sum_u x_u n_u,   K = units,   NN = sum_u n_u^2,

all of which add across shards.  With N photons the estimate is m = S1 / N and its standard error
the ratio estimator's

    se(m)^2 = K / (K - 1) * (S2 - 2 m SXN + m^2 NN) / N^2.

Two kinds of unit (docs/architecture.md, "Statistics"):

- **photons** (K = N, n_u = 1, SXN = S1, NN = N): exact per-photon second moments, se^2 =
  (S2 / N - m^2) / (N - 1) with N - 1 degrees of freedom.  Used for the exit tally, the hybrid
  estimator and the walk totals: each finished photon gives a few entries (its exit, its
  first-vertex connection samples) whose squares are summed per photon, cross terms included
  (:func:`photon_moments`), so ``total`` = single + multiple keeps the photon's covariance.
- **batches** (the spec's batches of photons): the connection estimator, whose contributions
  from every vertex of a photon to every bin are too many to square per photon; a batch's
  histogram is folded once all its photons have finished.

``events`` counts the contributions that made each entry (exits, connection samples with a
nonzero value, photons that deposited weight); an entry with no event has no error bar (NaN).
All sums are float64 np.bincount over inputs in the order fixed by the photon schedule, so a
shard's bytes do not depend on threads.
"""

from __future__ import annotations

import io
import json
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

__all__ = ["BATCH_ESTIMATORS", "BatchAccumulator", "PhotonAccumulator", "TallyLayout", "ShardTally", "QUANTITIES", "RD_SQUARE_ROWS",
           "entry_square_keys", "fold_square_totals", "ordered_sum", "photon_moments", "units_name"]

QUANTITIES = ("bins_G", "bins_S", "radial_G", "Rd", "absorbed", "truncated")
"""Per estimator: bins_G / bins_S [cfg, comp3, n_r+1, n_theta, n_cos, n_phi] (sum of w and of
w / cos_o per bin, radial index n_r = beyond r_max), radial_G [cfg, comp3, n_r+1], Rd [cfg, comp3];
absorbed and truncated [cfg] (walk totals, not per estimator, stored under the key "walk")."""

BATCH_ESTIMATORS = ("connections",)
"""Estimators whose standard errors come from batches; the others' from photons."""


RD_SQUARE_ROWS = 3
"""The last rows of a multi-entry estimator's square keys (workers.walk.hybrid.photon_entries) are
Rd's, one per component, each keyed by the photon's configuration alone."""


def ordered_sum(values: np.ndarray) -> float:
    """The sum of values in their order, (((0 + v_0) + v_1) + ...): the bits np.bincount gives a bin
    that receives all of them.  numpy's sum is pairwise and rounds otherwise; its cumulative sum
    is sequential (the shard runner passes a faster one with the same bits: workers.run.shard)."""
    return float(np.cumsum(values)[-1]) + 0.0 if values.size else 0.0  # + 0.0: a sum of -0.0 alone is +0.0, as in a bincount


def units_name(group: str) -> str:
    """Key in ShardTally.counts of the unit counts [K, NN] of a group ("exits", "walk", ...)."""
    return f"units/{group}"


def _add(stats: dict, counts: dict, name: str, s1: np.ndarray, s2: np.ndarray, sxn: np.ndarray, events: np.ndarray) -> None:
    if name not in stats:
        stats[name] = [np.zeros_like(s1), np.zeros_like(s1), np.zeros_like(s1)]
        counts[name] = np.zeros(s1.shape, dtype=np.int64)
    for acc, part in zip(stats[name], (s1, s2, sxn)):
        acc += part
    counts[name] += events


def photon_moments(key: np.ndarray, value: np.ndarray, size: int) -> np.ndarray:
    """S2 over `size` entries: sum over photons of (the photon's sum per entry)^2.

    key, value: [..., P, E]: photon p's E contributions (value 0 for an absent one) and the entry
    each adds to (any leading axes are further independent sets, keys already offset into one
    histogram).  Formed as sum_j x_j (x_j + 2 sum_{l > j, key_l = key_j} x_l), so several
    contributions of one photon to one entry are squared together, without sorting.
    """
    e = key.shape[-1]
    cross = np.zeros_like(value)
    for j in range(e - 1):  # E is small (a few samples per photon): pairwise
        same = key[..., j + 1 :] == key[..., j : j + 1]
        cross[..., j] = np.sum(np.where(same, value[..., j + 1 :], 0.0), axis=-1)
    return np.bincount(key.reshape(-1), weights=(value * (value + 2.0 * cross)).reshape(-1), minlength=size)


class TallyLayout:
    """Shapes and flat indices of one estimator's quantities (see QUANTITIES)."""

    def __init__(self, n_cfg: int, hist_shape: tuple[int, ...]):
        self.n_cfg, self.hist_shape = n_cfg, tuple(hist_shape)
        self.n_r1, self.n_theta = hist_shape[0], hist_shape[1]
        self.n_dir = int(np.prod(hist_shape[2:]))
        self.n_sp = self.n_r1 * self.n_theta
        self.size = {"bins": n_cfg * 3 * self.n_sp * self.n_dir, "radial": n_cfg * 3 * self.n_r1, "Rd": n_cfg * 3}
        # Squared sums of a multi-entry estimator: (quantity, level, value G or S) regions of one histogram.
        self.square_parts = [("bins_G", "bins", 0), ("bins_S", "bins", 1), ("radial_G", "radial", 0), ("Rd", "Rd", 0)]
        sizes = [self.size[level] for _, level, _ in self.square_parts]
        self.square_offsets = np.concatenate([[0], np.cumsum(sizes)])

    def shapes(self) -> dict[str, tuple[int, ...]]:
        return {"bins": (self.n_cfg, 3, *self.hist_shape), "radial": (self.n_cfg, 3, self.n_r1), "Rd": (self.n_cfg, 3)}


def fold_square_totals(sq: np.ndarray, layout: TallyLayout) -> np.ndarray:
    """Complete the squares histogram of the hybrid's compact entries, in place: in every
    square_parts region [n_cfg, 3 components, ...] the total component holds only the cross terms
    of a photon's single and multiple entries (workers.walk.hybrid.photon_entries); adding the
    components' squares makes it the per-photon squares of the total.  Returns sq."""
    for a, b in zip(layout.square_offsets[:-1], layout.square_offsets[1:]):
        region = sq[a:b].reshape(layout.n_cfg, 3, -1)
        region[:, 2] += region[:, 0] + region[:, 1]
    return sq


def entry_square_keys(flat2: np.ndarray, layout: TallyLayout) -> np.ndarray:
    """[8, P, E]: the square keys of the entries flat2 [P, E] ([cfg, comp (0/1), spatial,
    direction]) in the regions bins_G, bins_S, radial_G, Rd, first for the entry's component and
    then for the total (component 2): the keys whose per-photon sums of G, S, G, G, G, S, G, G are
    squared (workers.fold.reweight's members square their reweighted entries with them)."""
    o_bins_g, o_bins_s, o_radial, o_rd = (int(o) for o in layout.square_offsets[:4])
    # Three integer divisions, not six (~1 ns an element each): flat2 = (cfg * 2 + comp) * n_cell + cell
    # with cell = spatial * n_dir + direction, and the ring is cell // (n_theta * n_dir).
    n_cell = layout.n_sp * layout.n_dir
    level, cell = np.divmod(flat2, n_cell)
    cfg3 = (level >> 1) * 3  # level = cfg * 2 + comp
    ring = cell // (layout.n_theta * layout.n_dir)
    keys = []
    for c3 in (cfg3 + (level & 1), cfg3 + 2):  # the entry's component, then the total
        bins = c3 * n_cell + cell
        keys += [bins + o_bins_g, bins + o_bins_s, c3 * layout.n_r1 + ring + o_radial, c3 + o_rd]
    return np.stack(keys)


class PhotonAccumulator:
    """Per-photon moments of one shard (exit tally, hybrid estimator, walk totals).

    Sums of values and event counts are linear: they are kept per bin and component (single,
    multiple) and summed into rings, Rd and ``total`` at the end.  Squares are not: an estimator
    whose photons contribute one entry each (the exit tally: a photon leaves once) has no cross
    terms, so the squares of its entries are kept the same way (:meth:`add_exits`); one with
    several entries per photon (:meth:`add_photons`) has each photon's entries squared together
    at every level and component (:func:`photon_moments`).

    Sums into one bin are sequential in the order of the inputs, so their bits are fixed by the
    photon schedule.  A bincount into a bin that every input reaches (a sum per configuration
    with one configuration) is one chain of dependent additions through memory, ~4 ns a value;
    those sums go through ``ordered_sum`` (:func:`ordered_sum`'s bits), which a caller may
    replace by a faster implementation of the same sequential sum.
    """

    def __init__(self, estimators: list[str], n_cfg: int, hist_shape: tuple[int, ...], ordered_sum: Callable[[np.ndarray], float] = ordered_sum):
        self.layout = TallyLayout(n_cfg, hist_shape)
        self.estimators = list(estimators)
        self.n_cfg = n_cfg
        self.ordered_sum = ordered_sum
        size2 = self.layout.size["bins"] // 3 * 2
        # estimator -> [5, size2]: G, G^2, S, S^2, events per (cfg, comp, spatial, direction)
        self.linear = {e: np.zeros((5, size2)) for e in self.estimators}
        self.squares: dict[str, np.ndarray] = {}  # multi-entry estimator -> S2 of every level (square_parts)
        self.walk = {q: np.zeros((3, n_cfg)) for q in ("absorbed", "truncated")}  # sum, sum of squares, events

    def add_exits(self, estimator: str, flat: np.ndarray, g: np.ndarray, s: np.ndarray) -> None:
        """One entry per photon: flat index [cfg, comp (0/1), spatial, direction], G and S. An
        exit of zero weight (albedo 0: a weight of 0 can survive roulette) is no event, as in
        :meth:`add_photons`: a bin it alone reached stays unresolved (0, NaN error), not 0 +- 0."""
        acc = self.linear[estimator]
        for row, w in enumerate((g, g * g, s, s * s)):
            acc[row] += np.bincount(flat, weights=w, minlength=acc.shape[1])
        acc[4] += np.bincount(flat[g != 0.0], minlength=acc.shape[1])  # events: an integer count, exact in float64

    def add_photons(self, estimator: str, flat2: np.ndarray, g: np.ndarray, s: np.ndarray, square_key: np.ndarray, square_weight: np.ndarray) -> None:
        """Entries of several per photon (workers.walk.hybrid.photon_entries): flat2 [cfg, comp (0/1),
        spatial, direction], G and S contributions (0 for an absent entry), and the keys and
        weights of the photons' compact squares, whose sums per key with the components added to
        the total (:func:`fold_square_totals`) are the per-photon squares of every level
        (square_parts regions; see :func:`photon_moments`)."""
        acc = self.linear[estimator]
        # Entries are summed in memory order (ravel "K": no copy of the kernel's entry-major
        # arrays); the arrays of one call share their layout, so values stay with their keys.
        f, g, s = flat2.ravel("K"), g.ravel("K"), s.ravel("K")
        for row, w in ((0, g), (2, s), (4, (g != 0.0).astype(np.float64))):  # rows 1, 3 unused: squares kept below
            acc[row] += np.bincount(f, weights=w, minlength=acc.shape[1])
        size = int(self.layout.square_offsets[-1])
        if self.n_cfg == 1 and square_key.shape[1]:  # Rd's rows each add to one bin: summed in order, apart (no other row reaches Rd's bins)
            sq = np.bincount(square_key[:-RD_SQUARE_ROWS].ravel("K"), weights=square_weight[:-RD_SQUARE_ROWS].ravel("K"), minlength=size)
            for row in range(len(square_key) - RD_SQUARE_ROWS, len(square_key)):
                sq[square_key[row, 0]] += self.ordered_sum(square_weight[row])
        else:
            sq = np.bincount(square_key.ravel("K"), weights=square_weight.ravel("K"), minlength=size)
        fold_square_totals(sq, self.layout)
        if estimator in self.squares:
            self.squares[estimator] += sq
        else:
            self.squares[estimator] = sq

    def add_walk(self, cfg: np.ndarray, absorbed: np.ndarray, truncated: np.ndarray) -> None:
        """Absorbed and truncated weight of finished photons of configuration cfg (one each).

        Sums are sequential bincounts (the same bits on every machine); a quantity that is zero
        for every photon (truncated, nearly always) adds nothing and is skipped, and events are
        integer counts: both leave the sums bit for bit as the weighted bincounts would."""
        for q, v in (("absorbed", absorbed), ("truncated", truncated)):
            nonzero = v != 0.0
            if not nonzero.any():
                continue
            acc = self.walk[q]
            if self.n_cfg == 1:  # one bin: sequential sums (class docstring)
                acc[0, 0] += self.ordered_sum(v)
                acc[1, 0] += self.ordered_sum(v * v)
                acc[2, 0] += np.count_nonzero(nonzero)
                continue
            acc[0] += np.bincount(cfg, weights=v, minlength=self.n_cfg)
            acc[1] += np.bincount(cfg, weights=v * v, minlength=self.n_cfg)
            acc[2] += np.bincount(cfg[nonzero], minlength=self.n_cfg)

    def finish(self, n_photons: int) -> tuple[dict, dict]:
        """(stats, counts) with the histogram shapes of QUANTITIES and the photon units."""
        L = self.layout
        stats, counts = {}, {}
        shapes = L.shapes()

        def put(name: str, s1, s2, events, shape):
            stats[name] = [np.ascontiguousarray(s1).reshape(shape), np.ascontiguousarray(s2).reshape(shape),
                           np.ascontiguousarray(s1).reshape(shape).copy()]  # fmt: skip
            counts[name] = np.rint(events).astype(np.int64).reshape(shape)

        ring = lambda a: a.reshape(L.n_cfg, 3, L.n_r1, L.n_theta * L.n_dir).sum(axis=3)  # noqa: E731
        for e, acc in self.linear.items():
            two = acc.reshape(5, L.n_cfg, 2, L.n_sp, L.n_dir)
            g1, g2, s1, s2, ev = np.concatenate([two, two.sum(axis=2, keepdims=True)], axis=2)  # total = single + multiple
            r1, r2, rev = ring(g1), ring(g2), ring(ev)
            sums = {"bins_G": (g1, g2, ev), "bins_S": (s1, s2, ev), "radial_G": (r1, r2, rev), "Rd": (r1.sum(axis=2), r2.sum(axis=2), rev.sum(axis=2))}
            if e in self.squares:  # several entries per photon: the squares formed per photon
                sq = self.squares[e]
                for (q, level, _), a, b in zip(L.square_parts, L.square_offsets[:-1], L.square_offsets[1:]):
                    sums[q] = (sums[q][0], sq[a:b], sums[q][2])
            for q, (m1, m2, n) in sums.items():
                put(f"{e}/{q}", m1, m2, n, shapes[{"bins_G": "bins", "bins_S": "bins", "radial_G": "radial", "Rd": "Rd"}[q]])
        for q, (w1, w2, n) in self.walk.items():
            put(f"walk/{q}", w1, w2, n, (self.n_cfg,))
        for group in [*self.estimators, "walk"]:
            counts[units_name(group)] = np.array([n_photons, n_photons], dtype=np.int64)
        return stats, counts


class BatchAccumulator:
    """Batch bookkeeping of a shard: which batches are complete, and the histograms of the batch
    estimators (connections) in flight, folded into batch moments as each batch completes.

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
        self.folded: set[int] = set()
        self.stats: dict[str, list[np.ndarray]] = {}
        self.counts: dict[str, np.ndarray] = {}
        self.n_sum = self.nn_sum = self.k = 0

    def batch_of(self, photon: np.ndarray) -> np.ndarray:
        return np.searchsorted(self.starts, photon, side="right") - 1

    def _batch(self, b: int) -> dict[str, np.ndarray]:
        if b not in self.open:
            self.open[b] = {f"{e}/{q}": np.zeros(self.hist_size) for e in self.estimators for q in ("G", "S", "events")}
        return self.open[b]

    def add_hist(self, estimator: str, batch: np.ndarray, flat: np.ndarray, g: np.ndarray, s: np.ndarray) -> None:
        """Add contributions g (to G) and s (to S, i.e. g / cos_o) at flat histogram indices."""
        for b, sel in _groups(batch):
            f, gw, sw = (flat, g, s) if sel is None else (flat[sel], g[sel], s[sel])
            arrays = self._batch(b)
            arrays[f"{estimator}/G"] += np.bincount(f, weights=gw, minlength=self.hist_size)
            arrays[f"{estimator}/S"] += np.bincount(f, weights=sw, minlength=self.hist_size)
            arrays[f"{estimator}/events"] += np.bincount(f, weights=(gw != 0.0), minlength=self.hist_size)

    def finish_photons(self, key: np.ndarray) -> int:
        """Count finished photons; returns how many there were.

        key = batch * n_cfg + cfg per entry (a value from n_batches * n_cfg up marks an entry that
        is not a finished photon).  Complete batches are folded by :meth:`fold_ready`, which the
        caller invokes once every contribution of those photons has been added.
        """
        n = len(self.sizes) * self.n_cfg
        per_batch = np.bincount(key, minlength=n)[:n].reshape(-1, self.n_cfg).sum(axis=1)
        for b in np.flatnonzero(per_batch):
            self.remaining[b] -= int(per_batch[b])
        return int(per_batch.sum())

    @property
    def ready(self) -> bool:
        """Whether some batch has all its photons finished and is not folded yet."""
        return any(r == 0 and b not in self.folded for b, r in enumerate(self.remaining))

    def fold_ready(self) -> None:
        """Fold every complete batch into the statistics, in batch order."""
        for b in [b for b, r in enumerate(self.remaining) if r == 0 and b not in self.folded]:
            self._fold_batch(b)

    def _fold_batch(self, b: int) -> None:
        arrays = self.open.pop(b, None) or self._empty()
        n = self.sizes[b]
        for e in self.estimators:
            ev = arrays[f"{e}/events"].reshape(self.n_cfg, 2, *self.hist_shape)
            ev3 = np.concatenate([ev, ev.sum(axis=1, keepdims=True)], axis=1).astype(np.int64)
            for q in ("G", "S"):
                two = arrays[f"{e}/{q}"].reshape(self.n_cfg, 2, *self.hist_shape)
                three = np.concatenate([two, two.sum(axis=1, keepdims=True)], axis=1)
                _add(self.stats, self.counts, f"{e}/bins_{q}", three, three * three, three * n, ev3)
                if q == "G":
                    radial, ev_r = three.sum(axis=(3, 4, 5)), ev3.sum(axis=(3, 4, 5))
                    _add(self.stats, self.counts, f"{e}/radial_G", radial, radial * radial, radial * n, ev_r)
                    rd = radial.sum(axis=2)
                    _add(self.stats, self.counts, f"{e}/Rd", rd, rd * rd, rd * n, ev_r.sum(axis=2))
        self.folded.add(b)
        self.n_sum += n
        self.nn_sum += n * n
        self.k += 1

    def _empty(self) -> dict[str, np.ndarray]:
        return {f"{e}/{q}": np.zeros(self.hist_size) for e in self.estimators for q in ("G", "S", "events")}

    @property
    def complete(self) -> bool:
        return not self.open and len(self.folded) == len(self.sizes)

    def finish(self) -> tuple[dict, dict]:
        """(stats, counts) of the batch estimators with their batch units."""
        counts = dict(self.counts)
        for e in self.estimators:
            counts[units_name(e)] = np.array([self.k, self.nn_sum], dtype=np.int64)
        return dict(self.stats), counts


def _groups(batch: np.ndarray):
    """(batch, selection) for each batch present, in batch order; selection None when all
    events are in one batch (usual: photons run in order)."""
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
    """What one shard contributes: moments, event counts and unit counts, plus run facts.

    stats: name -> [S1, S2, SXN] (float64); counts: name -> events (int64, same shape), and
    ``units/<group>`` -> [K, NN] (see the module docstring); n_sum: photons per configuration.
    Serialises to bytes; every array adds across shards.
    """

    shard_index: int
    stats: dict[str, list[np.ndarray]]
    counts: dict[str, np.ndarray]
    n_sum: int
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
        for name, c in self.counts.items():
            arrays[f"{name}|count"] = c
        header = {"shard_index": self.shard_index, "n_sum": self.n_sum, "info": self.info}
        arrays["__header__"] = np.frombuffer(json.dumps(header, sort_keys=True).encode(), dtype=np.uint8)
        buf = io.BytesIO()
        np.savez_compressed(buf, **arrays)
        return buf.getvalue()

    @classmethod
    def from_bytes(cls, data: bytes) -> "ShardTally":
        with np.load(io.BytesIO(data), allow_pickle=False) as z:
            header = json.loads(z["__header__"].tobytes().decode())
            stats: dict[str, list[np.ndarray]] = {}
            counts: dict[str, np.ndarray] = {}
            for key in z.files:
                if key == "__header__":
                    continue
                name, part = key.rsplit("|", 1)
                if part == "count":
                    counts[name] = z[key]
                else:
                    stats.setdefault(name, [None, None, None])[("S1", "S2", "SXN").index(part)] = z[key]
        return cls(header["shard_index"], stats, counts, header["n_sum"], header["info"])
