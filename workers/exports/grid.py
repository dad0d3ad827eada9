"""The stored tables as dense arrays with named axes (for the npz, exr and plots exports).

Axes, in this order: ``estimator``, ``medium``, ``incidence``, ``channel``, ``component``, then
the table's own bins: ``r`` (radial), and for bins also ``theta_s``, ``cos_theta_o``, ``phi_o``.
A value column of a table (every column that is neither a key, a medium coordinate nor a bin
edge: Rd_r, S, G, their standard errors, events when present, the summary figures) becomes one
array over those axes; a combination the table has no row for is NaN. Coordinates: the key
values along each axis, ``albedo`` and ``g`` [medium, channel], ``eta`` [medium], radial edges
[medium, channel, r] (mm; per channel, as they scale with its mean free path) and the angular
edges [theta_s], [cos_theta_o], [phi_o].
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pyarrow as pa

from .profiles import KEY_COLUMNS
from .source import ExportError, table_arrays

__all__ = ["Grid", "table_grid", "KEY_AXES", "BIN_AXES"]

KEY_AXES = ("estimator", "medium", "incidence", "channel", "component")
_COORDS = {"albedo", "g", "eta"}
BIN_AXES = {
    "radial": (("r", "r_lo_mm", "r_hi_mm"),),
    "bins": (("r", "r_lo_mm", "r_hi_mm"), ("theta_s", "theta_s_lo", "theta_s_hi"),
             ("cos_theta_o", "cos_theta_o_lo", "cos_theta_o_hi"), ("phi_o", "phi_o_lo", "phi_o_hi")),
    "summary": (),
}
"""Per table: (axis, lower-edge column, upper-edge column) of its bins, in row order."""


@dataclass(frozen=True)
class Grid:
    """Arrays of one table: ``values[name]`` over ``axes``; ``keys[axis]`` the key values;
    ``edges[axis]`` the (lo, hi) edges of a bin axis (radial edges [medium, channel, r])."""

    table: str
    axes: tuple[str, ...]
    keys: dict[str, np.ndarray]
    values: dict[str, np.ndarray]
    edges: dict[str, tuple[np.ndarray, np.ndarray]]
    albedo: np.ndarray  # [medium, channel]
    g: np.ndarray  # [medium, channel]
    eta: np.ndarray  # [medium]


def _unique_in_order(values) -> list:
    seen: dict = {}
    for v in values:
        seen.setdefault(v, None)
    return list(seen)


def table_grid(table: pa.Table, name: str) -> Grid:
    """The dense arrays of stored table ``name`` (radial, bins or summary)."""
    cols = table_arrays(table)
    bin_axes = BIN_AXES[name]
    edge_cols = {c for _a, lo, hi in bin_axes for c in (lo, hi)}
    value_names = [c for c in table.schema.names if c not in KEY_COLUMNS and c not in _COORDS and c not in edge_cols]
    keys = {axis: np.array(_unique_in_order(cols[col].tolist())) for axis, col in zip(KEY_AXES, KEY_COLUMNS)}
    keys["medium"] = np.sort(keys["medium"].astype(np.int64))
    keys["incidence"] = np.sort(keys["incidence"].astype(np.float64))
    index = {axis: {v: i for i, v in enumerate(keys[axis].tolist())} for axis in KEY_AXES}
    key_idx = [np.array([index[axis][v] for v in cols[col].tolist()]) for axis, col in zip(KEY_AXES, KEY_COLUMNS)]
    key_shape = tuple(len(keys[a]) for a in KEY_AXES)
    flat_key = np.ravel_multi_index(key_idx, key_shape)
    rows_per_key = len(flat_key) // len(np.unique(flat_key))
    # rows of one key are contiguous; within them the bins run r-major (workers.fold.output)
    order = np.argsort(flat_key, kind="stable")
    n_bins = []
    edges: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    first = order[:rows_per_key]
    for axis, lo, hi in bin_axes:
        los = _unique_in_order(cols[lo][first].tolist())
        n_bins.append(len(los))
        if axis != "r":
            edges[axis] = (np.array(los), np.array(_unique_in_order(cols[hi][first].tolist())))
    if int(np.prod(n_bins, dtype=np.int64)) != rows_per_key:
        raise ExportError(f"{name} table: {rows_per_key} rows per key, not the product of its bin counts {n_bins}")
    shape = key_shape + tuple(n_bins)
    slot = flat_key[order] * rows_per_key + np.tile(np.arange(rows_per_key), len(order) // rows_per_key)
    values = {}
    for v in value_names:
        dense = np.full(int(np.prod(shape, dtype=np.int64)), np.nan)
        dense[slot] = cols[v][order].astype(np.float64)
        values[v] = dense.reshape(shape)
    n_m, n_ch = len(keys["medium"]), len(keys["channel"])
    albedo, g, eta = np.full((n_m, n_ch), np.nan), np.full((n_m, n_ch), np.nan), np.full(n_m, np.nan)
    m_i, c_i = key_idx[1], key_idx[3]
    albedo[m_i, c_i], g[m_i, c_i], eta[m_i] = cols["albedo"], cols["g"], cols["eta"]
    if bin_axes:
        n_r = n_bins[0]
        r_lo, r_hi = np.full((n_m, n_ch, n_r), np.nan), np.full((n_m, n_ch, n_r), np.nan)
        per_key = order.reshape(-1, rows_per_key)[:, ::rows_per_key // n_r]  # first row of each r bin
        idx = np.unravel_index(flat_key[per_key[:, 0]], key_shape)
        r_lo[idx[1], idx[3]], r_hi[idx[1], idx[3]] = cols["r_lo_mm"][per_key], cols["r_hi_mm"][per_key]
        edges["r"] = (r_lo, r_hi)
    axes = KEY_AXES + tuple(a for a, _lo, _hi in bin_axes)
    return Grid(name, axes, keys, values, edges, albedo, g, eta)
