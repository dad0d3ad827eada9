"""The ``npz`` and ``csv`` exports: the tables as arrays with named axes and units.

``npz`` (one ``NAME-vN.npz``, ``numpy.load(path)`` without pickle): for each table T in radial,
bins, summary and each value column V (workers.exports.grid), the array ``T/V`` over the axes
listed in ``axes`` (a JSON string: ``{"T/V": [axis, ...]}``), NaN where the table has no row;
coordinates ``estimator``, ``medium``, ``incidence_deg``, ``channel``, ``component``,
``albedo`` / ``g`` [medium, channel], ``eta`` [medium], ``r_lo_mm`` / ``r_hi_mm`` [medium,
channel, r], ``theta_s_lo`` / ``_hi``, ``cos_theta_o_lo`` / ``_hi``, ``phi_o_lo`` / ``_hi``; and
the JSON strings ``units`` (column -> meaning and unit, from the tables' column docs) and
``provenance``.

``csv``: ``radial.csv``, ``bins.csv``, ``summary.csv``, one row per table row with the table's
columns (floats in shortest round-trip form, NaN as ``nan``), ``columns.csv`` (file, column,
type, meaning and unit) and ``provenance.json``.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pyarrow as pa

from .grid import table_grid
from .source import TABLES, ExportSource

__all__ = ["write_npz", "read_npz", "write_csv", "read_csv", "column_docs"]


def column_docs(table: pa.Table) -> dict[str, str]:
    """Column -> its meaning and unit (the ``doc`` field metadata of the stored schema)."""
    return {f.name: (f.metadata or {}).get(b"doc", b"").decode("utf-8") for f in table.schema}


def npz_arrays(source: ExportSource) -> dict[str, np.ndarray]:
    """The arrays of the npz file (module docstring)."""
    out: dict[str, np.ndarray] = {}
    axes: dict[str, list[str]] = {}
    units: dict[str, str] = {}
    for name in TABLES:
        grid = table_grid(source.tables[name], name)
        units.update(column_docs(source.tables[name]))
        for column, array in grid.values.items():
            out[f"{name}/{column}"] = array
            axes[f"{name}/{column}"] = list(grid.axes)
        if name == "bins":
            for axis, (lo, hi) in grid.edges.items():
                prefix = "r" if axis == "r" else axis
                lo_name, hi_name = (f"{prefix}_lo_mm", f"{prefix}_hi_mm") if axis == "r" else (f"{prefix}_lo", f"{prefix}_hi")
                out[lo_name], out[hi_name] = lo, hi
                axes[lo_name] = axes[hi_name] = ["medium", "channel", "r"] if axis == "r" else [axis]
            keys = grid.keys
            out.update(estimator=keys["estimator"].astype(str), medium=keys["medium"], incidence_deg=keys["incidence"],
                       channel=keys["channel"].astype(str), component=keys["component"].astype(str),
                       albedo=grid.albedo, g=grid.g, eta=grid.eta)
            axes.update(albedo=["medium", "channel"], g=["medium", "channel"], eta=["medium"])
    out["axes"] = np.array(json.dumps(axes, sort_keys=True))
    out["units"] = np.array(json.dumps(units, sort_keys=True))
    out["provenance"] = np.array(source.provenance_json("npz"))
    return out


def write_npz(source: ExportSource, out_dir: str | Path) -> list[str]:
    """Write ``LABEL.npz`` (compressed) into ``out_dir``; the file names."""
    name = f"{source.label}.npz"
    np.savez_compressed(Path(out_dir) / name, **npz_arrays(source))
    return [name]


def read_npz(path: str | Path) -> tuple[dict[str, np.ndarray], dict]:
    """(arrays, {"axes", "units", "provenance"}) of an npz export (no pickle)."""
    with np.load(path, allow_pickle=False) as f:
        arrays = {k: f[k] for k in f.files}
    meta = {k: json.loads(str(arrays.pop(k))) for k in ("axes", "units", "provenance")}
    return arrays, meta


def _cell(value) -> str:
    if isinstance(value, float):
        return repr(value)  # shortest form that reads back to the same float64; nan and inf as such
    return str(value)


def write_csv(source: ExportSource, out_dir: str | Path) -> list[str]:
    """Write the three tables, ``columns.csv`` and ``provenance.json`` into ``out_dir``."""
    out = Path(out_dir)
    names = []
    with open(out / "columns.csv", "w", newline="", encoding="utf-8") as fcols:
        writer_cols = csv.writer(fcols)
        writer_cols.writerow(["file", "column", "type", "meaning_and_unit"])
        for name in TABLES:
            table = source.tables[name]
            with open(out / f"{name}.csv", "w", newline="", encoding="utf-8") as f:
                writer = csv.writer(f)
                writer.writerow(table.schema.names)
                cols = [table.column(c).to_pylist() for c in table.schema.names]
                writer.writerows([_cell(v) for v in row] for row in zip(*cols))
            docs = column_docs(table)
            writer_cols.writerows([f"{name}.csv", fld.name, str(fld.type), docs[fld.name]] for fld in table.schema)
            names.append(f"{name}.csv")
    (out / "provenance.json").write_text(json.dumps(source.provenance("csv"), indent=2, sort_keys=True) + "\n",
                                         encoding="utf-8")
    return names + ["columns.csv", "provenance.json"]


def read_csv(path: str | Path, types: dict[str, str]) -> dict[str, list]:
    """A table CSV of the export as columns, parsed with the types of ``columns.csv``
    (``double`` -> float, ``int64`` -> int, else str)."""
    parse = {"double": float, "int64": int}
    with open(path, newline="", encoding="utf-8") as f:
        rows = list(csv.reader(f))
    header, body = rows[0], rows[1:]
    return {c: [parse.get(types[c], str)(r[i]) for r in body] for i, c in enumerate(header)}
