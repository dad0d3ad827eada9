"""The searches of workers.walk.search against torch.searchsorted: the binary search on any sorted
rows, and the bucket index of non-negative edges on every edge, the floats next to it, every
bucket boundary, random values over and beyond the edges' range and the special values, in
float32 and float64, eager and compiled."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from workers.walk.search import EdgeIndex, count_le, indexed_count_le


@pytest.mark.parametrize("m", [1, 2, 3, 5, 8, 49, 64, 65])
def test_count_le_is_searchsorted_right(m):
    """Every value of a row, each just below and above, and values outside the row."""
    gen = torch.Generator().manual_seed(m)
    table = torch.sort(torch.rand(3, m, generator=gen, dtype=torch.float64) * 10.0, dim=1).values
    table[1, : m // 2] = table[1, 0]  # repeated edges
    for row in range(3):
        r = table[row]
        values = torch.cat((r, torch.nextafter(r, r - 1), torch.nextafter(r, r + 1), torch.tensor([-1.0, 0.0, 11.0, 1e300])))
        rows = torch.full(values.shape, row, dtype=torch.int64)
        want = torch.searchsorted(r, values, right=True)
        assert torch.equal(count_le(table, rows, values), want)


def _radial(n_r: int, r_min: float, r_max: float) -> np.ndarray:
    """The default layout's kind of radial edges: 0, then geometric from r_min to r_max."""
    return np.concatenate(([0.0], np.geomspace(r_min, r_max, n_r)))


TABLES = {
    # rows of one layout scaled per configuration (edges in optical units = mm x sigma_t)
    "geometric x sigma_t": np.stack([_radial(48, 0.016, 16.0) * s for s in (1.0, 2.0, 0.7, 13.3)]),
    "uniform": np.linspace(0.0, 10.0, 101)[None, :],
    "irregular": np.array([[0.0, 1e-3, 1.1e-3, 0.5, 0.5000001, 0.75, 3.0, 3.0000000001, 1e3]]),
    "repeats": np.array([[0.0, 0.0, 1.0, 1.0, 1.0, 2.0, 2.0], [0.0, 0.5, 0.5, 0.5, 0.5, 0.5, 4.0]]),
    "zero only": np.array([[0.0]]),
    "one positive": np.array([[0.0, 2.5]]),
    "wide": np.array([[0.0, 1e-300, 1e-200, 1e-30, 1.0, 1e30, 1e200, 1e300]]),
    "tiny": np.array([[0.0, 5e-324, 1e-323, 1e-310, 1e-308]]),
}


def _values(table: torch.Tensor, index: EdgeIndex | None, gen: torch.Generator) -> torch.Tensor:
    """Values to look up: every edge and its neighbouring floats, every bucket's first value and
    the float below it, random values log-uniform over and beyond the edges, special values."""
    dt = table.dtype
    e = table.reshape(-1)
    inf = torch.tensor(math.inf, dtype=dt)
    parts = [e, torch.nextafter(e, -inf), torch.nextafter(e, inf)]
    if index is not None:
        int_dtype = torch.int32 if dt == torch.float32 else torch.int64
        b = torch.arange(index.counts.shape[1] + 2, dtype=torch.int64) + index.first - 1
        starts = (torch.clamp(b, min=0) << index.shift).to(int_dtype).view(dt)
        parts += [starts, torch.nextafter(starts, -inf), torch.nextafter(starts, inf)]
    positive = e[e > 0]
    lo = math.log10(float(positive.min())) - 3 if len(positive) else -10.0
    hi = math.log10(float(e.max())) + 3 if float(e.max()) > 0 else 1.0
    lo, hi = max(lo, math.log10(float(torch.finfo(dt).tiny))), min(hi, math.log10(float(torch.finfo(dt).max)) - 0.01)
    parts.append(torch.pow(10.0, lo + (hi - lo) * torch.rand(20_000, generator=gen, dtype=torch.float64)).to(dt))
    fin = torch.finfo(dt)
    parts.append(torch.tensor([0.0, -0.0, -1.0, -fin.tiny, fin.tiny, fin.tiny / 4, fin.max, -fin.max, math.inf, -math.inf, math.nan, -math.nan], dtype=dt))
    return torch.cat(parts)


def _want(table: torch.Tensor, row: int, values: torch.Tensor) -> torch.Tensor:
    """torch.searchsorted(right=True) of the row, with NaN counting 0 (count_le's convention)."""
    return torch.where(torch.isnan(values), 0, torch.searchsorted(table[row], values, right=True))


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("name", list(TABLES))
def test_indexed_count_le_is_searchsorted_right(name, dtype):
    table = torch.from_numpy(TABLES[name]).to(dtype)
    float32_ranges = {"tiny": [[0.0, 1e-45, 3e-45, 1e-40, 1e-38]], "wide": [[0.0, 1e-38, 1e-30, 1e-10, 1.0, 1e10, 1e30, 3e38]]}
    if dtype == torch.float32 and name in float32_ranges:  # float32's own subnormals and range
        table = torch.tensor(float32_ranges[name], dtype=dtype)
    index = EdgeIndex.build(table)
    assert index is not None
    gen = torch.Generator().manual_seed(11)
    for row in range(table.shape[0]):
        values = _values(table, index, gen)
        rows = torch.full(values.shape, row, dtype=torch.int64)
        got = indexed_count_le(table, index, rows, values)
        want = _want(table, row, values)
        bad = torch.nonzero(got != want).squeeze(1)
        assert len(bad) == 0, f"row {row}: {values[bad[:5]].tolist()} -> {got[bad[:5]].tolist()}, want {want[bad[:5]].tolist()}"
        assert torch.equal(got, count_le(table, rows, values))


def test_the_default_layouts_index_has_one_check_per_value():
    """The radial edges of the tables (0, then geometric), in mm and scaled to optical units in
    float32 as the hybrid holds them: a gather and one comparison per lookup."""
    for table in (torch.from_numpy(TABLES["geometric x sigma_t"]), torch.from_numpy(TABLES["geometric x sigma_t"]).float()):
        index = EdgeIndex.build(table)
        assert index is not None and index.checks == 1
        assert index.counts.shape[0] == 4 and index.counts.shape[1] < 1000


def test_crowded_edges_fall_back_to_the_binary_search():
    """Edges closer than the finest bucket, many of them: no index, and the lookup still counts."""
    table = torch.tensor([[0.0, *(1.0 + k * 1e-15 for k in range(30)), 2.0]], dtype=torch.float64)
    assert EdgeIndex.build(table) is None
    values = torch.cat((table[0], torch.nextafter(table[0], table[0] + 1), torch.tensor([0.5, 1.5, 3.0, -1.0])))
    rows = torch.zeros(values.shape, dtype=torch.int64)
    assert torch.equal(indexed_count_le(table, None, rows, values), _want(table, 0, values))


@pytest.mark.parametrize(
    "table",
    [torch.tensor([[0.0, -1.0]]), torch.tensor([[-1.0, 0.0]]), torch.tensor([[0.0, 2.0, 1.0]]), torch.tensor([[0.0, math.nan]]),
     torch.tensor([[0.0, math.inf]]), torch.tensor([[0, 1]]), torch.zeros(3)],
)
def test_tables_the_index_cannot_serve_are_refused(table):
    with pytest.raises(ValueError, match="EdgeIndex"):
        EdgeIndex.build(table)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_compiled_indexed_count_le_agrees_with_the_eager_one(dtype):
    table = torch.from_numpy(TABLES["geometric x sigma_t"]).to(dtype)
    index = EdgeIndex.build(table)
    gen = torch.Generator().manual_seed(3)
    values = _values(table, index, gen)
    rows = torch.randint(0, table.shape[0], values.shape, generator=gen)
    compiled = torch.compile(indexed_count_le, fullgraph=True, dynamic=False)
    got = compiled(table, index, rows, values)
    assert torch.equal(got, indexed_count_le(table, index, rows, values))
    want = torch.stack([_want(table, int(r), v[None])[0] for r, v in zip(rows[:3000], values[:3000])])
    assert torch.equal(got[:3000], want)
