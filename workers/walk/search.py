"""Searches of sorted edges that compile into elementwise kernels: ``torch.searchsorted(row,
value, right=True)`` per element, as the number of a row's entries <= the value.

:func:`count_le` is a branchless binary search for any sorted rows: log2(m) dependent gathers.
:class:`EdgeIndex` answers the same question for rows of non-negative edges in a constant number
of gathers, which is what the radial lookups of the exit tally and the hybrid's first vertex use.

**The bucket index.**  For a non-negative float v, the integer reading of its bits grows with v,
and ``bits >> shift`` cuts the positive floats into buckets of equal width on a log scale: with
``shift = mantissa bits - b`` every octave holds 2^b buckets.  :meth:`EdgeIndex.build` stores,
for every bucket between the one below the smallest positive edge and the one of the largest
edge, the count of edges <= the bucket's first value, and the most edges any bucket holds
strictly inside it (``checks``).  A value's count is its bucket's count plus the edges of its
bucket that are <= it: ``checks`` comparisons against the next edges, no more.  A value below the
first bucket (0, -0.0, tiny) takes the first bucket, whose count is that of the zero edges, and
no positive edge lies below that bucket's end; one above the last takes the last, which holds the
largest edge; negative values and NaN count 0, as in :func:`count_le`.  The result is exact: the
same integer as the binary search for every value, float32 or float64 (tests/workers/
test_search.py checks every edge, its neighbouring floats, every bucket boundary and random values).

Measured on 44448 real finished M2 lanes (Zen 4, compiled, the two versions timed alternately in
one process, ns per lane): the radial lookup (r from x, y and its bin) 22.1 with the binary search
(six dependent gathers for 49 edges), 14.2 with the index; the whole exit lookup 37.0 and 28.1
(BENCHMARKS.md).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

__all__ = ["count_le", "EdgeIndex", "indexed_count_le"]

# Float dtype -> (its integer reading, mantissa bits).
_BITS = {torch.float32: (torch.int32, 23), torch.float64: (torch.int64, 52)}
_MAX_BUCKETS = 1 << 16  # per index (all rows): 512 KiB of int64 counts at most
_MAX_OCTAVE_BITS = 12  # at most 4096 buckets per octave


def count_le(table: torch.Tensor, row: torch.Tensor, value: torch.Tensor) -> torch.Tensor:
    """Number of entries of table[row] that are <= value (int64), each table row sorted ascending.

    ``torch.searchsorted(table[row], value, right=True)`` elementwise, computed by binary lifting:
    k grows by the powers of two from the largest <= m down to 1 while the entry it would cover,
    table[row, k + step - 1], is still <= value.  A fixed number of gathers and no data-dependent
    loop, so it compiles into the surrounding elementwise kernel.  A NaN value counts 0.
    """
    m = table.shape[1]
    flat = table.reshape(-1)
    base = row * m
    k = torch.zeros_like(row)
    step = 1 << (m.bit_length() - 1)
    while step:
        cand = k + step
        entry = flat[base + torch.clamp(cand, max=m) - 1]
        k = torch.where((cand <= m) & (entry <= value), cand, k)
        step >>= 1
    return k


@dataclass(frozen=True)
class EdgeIndex:
    """The bucket index of a table of sorted, finite, non-negative edges [rows, m] (module
    docstring), for :func:`indexed_count_le`.

    counts: int64 [rows, n_buckets], the edges of each row <= the first value of each bucket;
    first: the bucket number (bits >> shift) of bucket 0; shift: bits dropped from a value's
    integer reading; checks: the most edges of a row strictly inside one bucket.
    """

    counts: torch.Tensor
    first: int
    shift: int
    checks: int

    @classmethod
    def build(cls, table: torch.Tensor) -> "EdgeIndex | None":
        """The index of ``table`` (float32 or float64, rows sorted ascending, finite, >= 0): of the
        bucket widths with at most _MAX_BUCKETS buckets in all, the coarsest with at most one
        edge inside a bucket, else the one with the fewest.  None where that is no faster than
        the binary search (more checks than its log2(m) + 1 gathers, or no width fits); a
        ValueError for other tables."""
        if table.dtype not in _BITS or table.dim() != 2 or table.shape[1] == 0:
            raise ValueError(f"EdgeIndex: a 2-d float32 or float64 table of edges is needed, not {table.dtype} {tuple(table.shape)}")
        edges = table.numpy()
        if not np.isfinite(edges).all() or (edges < 0).any() or (np.diff(edges, axis=1) < 0).any():
            raise ValueError("EdgeIndex: the edges must be finite, >= 0 and sorted ascending in every row")
        mantissa = _BITS[table.dtype][1]
        int_dtype = np.dtype(f"i{edges.itemsize}")  # the floats' integer reading, as in _BITS
        bits = edges.view(int_dtype).astype(np.int64)
        positive = bits[edges > 0]
        best = None
        for octave_bits in range(_MAX_OCTAVE_BITS + 1):
            shift = mantissa - octave_bits
            bucket = bits >> shift
            # One bucket below the smallest positive edge's: its first value lies below every positive edge.
            first = max(int(positive.min() >> shift) - 1, 0) if positive.size else 0
            n_buckets = int(bucket.max()) - first + 1
            if n_buckets * table.shape[0] > _MAX_BUCKETS:
                break
            inside = (bits & ((1 << shift) - 1)) != 0  # strictly inside its bucket (not its first value)
            checks = max((int(np.unique(bucket[i][inside[i]], return_counts=True)[1].max(initial=0)) for i in range(len(edges))), default=0)
            if best is None or checks < best[3]:
                best = (first, n_buckets, shift, checks)
            if checks <= 1:
                break
        if best is None or best[3] > table.shape[1].bit_length():
            return None
        first, n_buckets, shift, checks = best
        starts = ((np.arange(n_buckets, dtype=np.int64) + first) << shift).astype(int_dtype).view(edges.dtype)
        counts = np.stack([np.searchsorted(row, starts, side="right") for row in edges]).astype(np.int64)
        return cls(counts=torch.from_numpy(counts), first=first, shift=shift, checks=checks)


def indexed_count_le(table: torch.Tensor, index: EdgeIndex | None, row: torch.Tensor, value: torch.Tensor) -> torch.Tensor:
    """:func:`count_le` (the same int64 for every value) of a table of non-negative edges through
    its :class:`EdgeIndex`: one gather of the value's bucket, then ``index.checks`` comparisons
    (value has the table's dtype).  With no index (:meth:`EdgeIndex.build` gave None), the
    binary search."""
    if index is None:
        return count_le(table, row, value)
    int_dtype = _BITS[value.dtype][0]
    n_buckets = index.counts.shape[1]
    bucket = torch.clamp((value.view(int_dtype) >> index.shift).to(torch.int64) - index.first, 0, n_buckets - 1)
    k = index.counts.reshape(-1)[row * n_buckets + bucket]
    m = table.shape[1]
    flat = table.reshape(-1)
    base = row * m
    for _ in range(index.checks):
        k = k + ((k < m) & (flat[base + torch.clamp(k, max=m - 1)] <= value)).to(torch.int64)
    return torch.where(value >= 0, k, 0)  # negative and NaN: 0 (their bits took the first bucket)
