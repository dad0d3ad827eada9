"""What an export is made from: a stored dataset version's tables, spec and provenance.

Every export writes :meth:`ExportSource.provenance` into its files: the dataset name and version,
the spec hash, the code version that made the export (:func:`schema.version.code_version`) and
the one that made the tables, and the sha256 of each table it read. Exports are derived from
stored tables only, never from live state (docs/architecture.md, "Datasets and exports").
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from schema import META_RUN, META_SPEC, SimulationSpec, parse_spec
from schema.version import code_version

__all__ = ["ExportSource", "ExportError", "TABLES", "table_arrays"]

TABLES = ("radial", "bins", "summary")
"""The tables an export reads (``NAME.parquet``)."""


class ExportError(ValueError):
    """The dataset cannot be exported in the requested format; the message says why and what
    to change (for example the spec fields a pbrt table needs)."""


@dataclass(frozen=True)
class ExportSource:
    """A dataset version's tables with their provenance; build it with :meth:`from_directory`
    (a ``bssrdf simulate`` output or a version's directory) or directly from stored tables."""

    name: str
    version: int | None
    spec: SimulationSpec
    spec_hash: str
    tables: dict[str, pa.Table] = field(repr=False)
    tables_sha256: dict[str, str]

    @classmethod
    def from_tables(cls, tables: dict[str, pa.Table], sha256: dict[str, str], *, name: str | None = None,
                    version: int | None = None) -> "ExportSource":
        """Stored tables (keys radial, bins, summary) with their sha256 by file name
        (``radial.parquet``, ...); the spec comes from the tables' metadata."""
        missing = [t for t in TABLES if t not in tables or f"{t}.parquet" not in sha256]
        if missing:
            raise ExportError(f"an export needs the tables {', '.join(TABLES)} and their sha256; missing {missing}")
        spec = parse_spec(tables["radial"].schema.metadata[META_SPEC].decode("utf-8"))
        digests = {f"{t}.parquet": sha256[f"{t}.parquet"] for t in TABLES}
        return cls(name or spec.name, version, spec, spec.spec_hash(), {t: tables[t] for t in TABLES}, digests)

    @classmethod
    def from_directory(cls, path: str | Path, *, name: str | None = None, version: int | None = None) -> "ExportSource":
        """The tables of a directory (a ``bssrdf simulate`` output), sha256 computed from the files."""
        path = Path(path)
        tables = {t: pq.read_table(path / f"{t}.parquet") for t in TABLES}
        digests = {f"{t}.parquet": hashlib.sha256((path / f"{t}.parquet").read_bytes()).hexdigest() for t in TABLES}
        return cls.from_tables(tables, digests, name=name, version=version)

    @property
    def label(self) -> str:
        """``NAME-vN`` (``NAME`` for tables outside the catalog), the prefix of export file names."""
        return self.name if self.version is None else f"{self.name}-v{self.version}"

    def run_facts(self) -> dict[str, Any]:
        """The run facts stored in the tables' metadata (seed, photons, code version, ...)."""
        return json.loads(self.tables["radial"].schema.metadata.get(META_RUN, b"{}"))

    def provenance(self, fmt: str) -> dict[str, Any]:
        """Where an export of format ``fmt`` came from (recorded in every export)."""
        return {
            "format": fmt,
            "dataset": self.name,
            "version": self.version,
            "spec_hash": self.spec_hash,
            "code_version": code_version(),
            "tables_code_version": self.run_facts().get("code_version"),
            "tables_sha256": dict(sorted(self.tables_sha256.items())),
        }

    def provenance_json(self, fmt: str) -> str:
        """:meth:`provenance` as compact sorted JSON (for header attributes and comments)."""
        return json.dumps(self.provenance(fmt), sort_keys=True, separators=(",", ":"))

    def sigma_t(self, medium: int, channel: str) -> float:
        """Extinction [1/mm] of a channel of medium ``medium`` (1 for every medium of a sweep)."""
        for c in self.spec.medium_spec(medium).channels():
            if c.name == channel:
                return c.sigma_t
        raise ExportError(f"medium {medium} of {self.label} has no channel {channel!r}")


def table_arrays(table: pa.Table, columns: list[str] | None = None) -> dict[str, np.ndarray]:
    """Columns of a table as numpy arrays (strings as object arrays); NaN stays NaN."""
    names = columns or table.schema.names
    return {n: table.column(n).to_numpy(zero_copy_only=False) for n in names}
