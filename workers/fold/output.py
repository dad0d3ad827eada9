"""Result tables: radial.parquet, bins.parquet, summary.parquet and summary.json.

Only deterministic facts go into the files (spec, photon counts, engine, code version), never
timings, so the same spec and seed give the same bytes wherever and however the shards ran.
"""

from __future__ import annotations

import itertools
import json
import math

import numpy as np
import pyarrow as pa
import pyarrow.fs as pafs
import pyarrow.parquet as pq

from schema import BINS_SCHEMA, COMPONENTS, RADIAL_SCHEMA, SUMMARY_SCHEMA, table_metadata
from schema.version import code_version

from .finite import check_finite
from .merge import Result
from .tally import BATCH_ESTIMATORS

__all__ = [
    "radial_table", "bins_table", "summary_table", "summary_rows", "summary", "summary_head", "run_facts",
    "engine_fact", "target_entry", "write_tables", "TableWriter", "TABLE_FILES", "ROW_GROUP_ROWS",
    "s_infinite_variance",
]

TABLE_FILES = ("radial.parquet", "bins.parquet", "summary.parquet", "summary.json")


def _keys(result: Result):
    """(key columns, cfg, channel index, component index) per (estimator, cfg, component);
    the key columns are the tables' leading columns (schema.tables), as scalars."""
    c = result.configs
    for est in result.estimators:
        for cfg in range(c.n):
            ch = c.channel_of(cfg)
            for k, comp in enumerate(COMPONENTS):
                keys = {
                    "estimator": est, "medium": int(result.medium_index), "albedo": float(c.albedo[cfg]),
                    "g": float(c.g[cfg]), "eta": float(c.eta), "incidence_deg": c.incidence_of(cfg),
                    "channel": c.channel_names[ch], "component": comp,
                }  # fmt: skip
                yield keys, cfg, ch, k


def _repeat(keys: dict, n: int) -> dict:
    """Key columns of n rows."""
    return {name: [value] * n for name, value in keys.items()}


def radial_table(result: Result) -> pa.Table:
    """Rd(r) per annulus in 1/mm^2: mean flux through the annulus per unit incident power / area."""
    cols: dict[str, list] = {f.name: [] for f in RADIAL_SCHEMA}
    n_r = result.layout.n_r
    for keys, cfg, ch, k in _keys(result):
        est = keys["estimator"]
        edges = result.layout.radial_mm[ch]
        area = math.pi * (edges[1:] ** 2 - edges[:-1] ** 2)
        m = result.mean(f"{est}/radial_G")[cfg, k, :n_r]
        se = result.stderr(f"{est}/radial_G")[cfg, k, :n_r]
        for name, values in _repeat(keys, n_r).items():
            cols[name] += values
        cols["r_lo_mm"] += edges[:-1].tolist()
        cols["r_hi_mm"] += edges[1:].tolist()
        cols["Rd_r"] += (m / area).tolist()
        cols["Rd_r_stderr"] += (se / area).tolist()
        cols["events"] += result.events(f"{est}/radial_G")[cfg, k, :n_r].tolist()
    return pa.Table.from_pydict(cols, schema=RADIAL_SCHEMA)


def s_infinite_variance(estimator: str, component: str, eta: float, cos_lo: float) -> bool:
    """Whether S of a bin rests on contributions with an infinite second moment.

    The exit tally scores S = w / cos_o.  At eta = 1 nothing stops photons leaving near grazing
    (the radiance is finite there), so exits have density ~ cos_o as cos_o -> 0 and in the bin
    [0, c_1) E[(w / cos_o)^2] ~ int_0 dc / c diverges (workers/walk/harvest.py).  For eta > 1 the
    transmittance vanishes like cos_o (density ~ cos_o^2: finite), for eta < 1 refraction keeps
    cos_o >= sqrt(1 - eta^2) > 0, and every bin above the lowest has cos_o >= c_1 > 0.  The exit
    tally scores every component of ``exits`` and the ``multiple`` part (so ``total``) of the
    hybrid; connection samples score T cos_in / cos_o, bounded (workers.walk.connections).
    """
    exit_scored = estimator == "exits" or (estimator == "hybrid" and component != "single")
    return exit_scored and eta == 1.0 and cos_lo == 0.0


def bins_table(result: Result) -> pa.Table:
    """G and S per (spatial x directional) bin; S = sum w / cos_o / (A Omega) per photon.
    S_stderr is NaN where S has no valid error bar (:func:`s_infinite_variance`, flagged in
    S_infinite_variance) as well as where no event contributed."""
    L = result.layout
    n_r, n_t, n_c, n_p = L.n_r, L.n_theta, L.n_cos, L.n_phi
    omega = L.solid_angle()
    r_i, t_i, c_i, p_i = (a.reshape(-1) for a in np.meshgrid(np.arange(n_r), np.arange(n_t), np.arange(n_c), np.arange(n_p), indexing="ij"))
    parts = []
    for keys, cfg, ch, k in _keys(result):
        est = keys["estimator"]
        edges = L.radial_mm[ch]
        a_omega = (L.area_mm2(ch)[:, :, None, None] * omega[None, None, :, :]).reshape(-1)
        g = result.mean(f"{est}/bins_G")[cfg, k, :n_r].reshape(-1)
        g_se = result.stderr(f"{est}/bins_G")[cfg, k, :n_r].reshape(-1)
        s = result.mean(f"{est}/bins_S")[cfg, k, :n_r].reshape(-1) / a_omega
        s_se = result.stderr(f"{est}/bins_S")[cfg, k, :n_r].reshape(-1) / a_omega
        per_cos = [s_infinite_variance(est, keys["component"], keys["eta"], lo) for lo in L.cos_o[:-1]]
        flag = np.array(per_cos)[c_i]
        s_se = np.where(flag, np.nan, s_se)
        n = len(g)
        parts.append({
            **_repeat(keys, n), "r_lo_mm": edges[r_i], "r_hi_mm": edges[r_i + 1],
            "theta_s_lo": L.theta_s[t_i], "theta_s_hi": L.theta_s[t_i + 1],
            "cos_theta_o_lo": L.cos_o[c_i], "cos_theta_o_hi": L.cos_o[c_i + 1],
            "phi_o_lo": L.phi_o[p_i], "phi_o_hi": L.phi_o[p_i + 1],
            "G": g, "G_stderr": g_se, "S": s, "S_stderr": s_se, "S_infinite_variance": flag.astype(np.int64),
            "events": result.events(f"{est}/bins_G")[cfg, k, :n_r].reshape(-1),
        })  # fmt: skip
    cols = {f.name: list(itertools.chain.from_iterable(np.asarray(p[f.name]).tolist() for p in parts)) for f in BINS_SCHEMA}
    return pa.Table.from_pydict(cols, schema=BINS_SCHEMA)


def summary_rows(result: Result) -> list[dict]:
    """One dict per (estimator, incidence, channel, component): R_spec, Rd, beyond r_max, energy."""
    rows = []
    n_r = result.layout.n_r
    for keys, cfg, ch, k in _keys(result):
        est = keys["estimator"]
        rows.append({
            **keys, "R_spec": float(result.configs.r_spec[cfg]),
            "Rd": float(result.mean(f"{est}/Rd")[cfg, k]),
            "Rd_stderr": float(result.stderr(f"{est}/Rd")[cfg, k]),
            "Rd_beyond_rmax": float(result.mean(f"{est}/radial_G")[cfg, k, n_r]),
            "Rd_beyond_rmax_stderr": float(result.stderr(f"{est}/radial_G")[cfg, k, n_r]),
            "absorbed": float(result.mean("walk/absorbed")[cfg]),
            "absorbed_stderr": float(result.stderr("walk/absorbed")[cfg]),
            "truncated": float(result.mean("walk/truncated")[cfg]),
            "truncated_stderr": float(result.stderr("walk/truncated")[cfg]),
            "photons": int(result.n_sum),
            "unresolved_bins": int(np.sum(result.events(f"{est}/bins_G")[cfg, k, :n_r] == 0)),
        })  # fmt: skip
    return rows


def summary_table(result: Result) -> pa.Table:
    rows = summary_rows(result)
    return pa.Table.from_pylist(rows, schema=SUMMARY_SCHEMA)


RNG_FACT = ("walk: xoshiro128+ per photon, started from philox4x32-10 at counter (photon, 0, 0); other draws: "
            "philox4x32-10 at counter (photon, draw, purpose); key sha256(seed|configuration)")
UNITS = {"length": "mm", "Rd_r": "1/mm^2", "S": "1/(mm^2 sr)", "G": "fraction of incident power"}
NORMALISATION = "per unit incident power; the walk carries 1 - R_spec, so S includes the entry Fresnel factor"


def engine_fact(shard_info: list[dict]) -> str | list[str]:
    """The engine of the shards ("compiled" / "eager"), or the sorted list if they differ."""
    engines = sorted({i.get("engine", "?") for i in shard_info})
    return engines[0] if len(engines) == 1 else engines


def run_facts(result: Result) -> dict:
    """Deterministic facts about the run, stored in every table's metadata."""
    return {
        "code_version": code_version(),
        "engine": engine_fact(result.shard_info),
        "rng": RNG_FACT,
        "photons_per_config": int(result.n_sum),
        "shards": len(result.shard_info),  # the first K shards of a run to a target error
        "standard_errors": {e: ("batches" if e in BATCH_ESTIMATORS else "photons") for e in result.estimators},
        "error_units": {e: result.units(f"{e}/Rd")[0] for e in result.estimators},  # photons or batches behind each error
        "seed": result.spec.seed,
        "channels": [c.model_dump() for c in result.spec.channels()],
        "eta": result.configs.eta,
        "units": UNITS,
        "normalisation": NORMALISATION,
    }


def summary(result: Result) -> dict:
    """The summary printed by `bssrdf simulate --json` and stored as summary.json."""
    return summary_head(result.spec, run_facts(result), **target_entry(result)) | {"results": [json_row(r) for r in summary_rows(result)]}


def json_row(row: dict) -> dict:
    """A summary row for JSON: a NaN standard error (no event) becomes null."""
    return {k: (None if isinstance(v, float) and math.isnan(v) else v) for k, v in row.items()}


def summary_head(spec, run: dict, **extra) -> dict:
    """summary.json without its rows: name, spec hash, run facts and ``extra`` entries."""
    return {"name": spec.name, "spec_hash": spec.spec_hash(), "run": run, **extra}


def target_entry(result: Result) -> dict:
    """{"target": status} of a run to a target error (workers.fold.target.TargetStatus: reached,
    photons, worst check), else {}."""
    return {} if result.target is None else {"target": result.target.as_dict()}


ROW_GROUP_ROWS = 1 << 20
"""Most rows per Parquet row group (a medium's table is one or more row groups of its own)."""


class TableWriter:
    """The tables of a job written medium by medium: radial, bins and summary Parquet files
    open for the whole job (each medium appended as its own row groups, so memory is one
    medium's tables), summary.json written at :meth:`close` from the summary rows.

    ``run`` (the run facts) goes into every table's metadata, so it is known before the first
    medium is written; ``extra`` entries go into summary.json beside the rows.
    """

    def __init__(self, out_dir: str, spec, run: dict, filesystem: pafs.FileSystem | None = None, extra: dict | None = None):
        self.fs = filesystem or pafs.LocalFileSystem()
        self.out_dir = out_dir
        self.head = summary_head(spec, run, **(extra or {}))
        self.fs.create_dir(out_dir, recursive=True)
        meta = table_metadata(spec.canonical_json(), run)
        self._streams, self._writers = [], {}
        for name, schema in (("radial", RADIAL_SCHEMA), ("bins", BINS_SCHEMA), ("summary", SUMMARY_SCHEMA)):
            stream = self.fs.open_output_stream(f"{out_dir}/{name}.parquet")
            self._streams.append(stream)
            self._writers[name] = pq.ParquetWriter(stream, schema.with_metadata(meta), compression="zstd")

    def add(self, result: Result) -> None:
        """Append one medium's tables."""
        self.add_tables(radial_table(result), bins_table(result), summary_table(result))

    def add_tables(self, radial: pa.Table, bins: pa.Table, summary: pa.Table) -> None:
        """Append one medium's tables, already built (e.g. read back from a part file); refused
        (:class:`workers.fold.finite.NonFiniteResult`) if one holds a non-finite number."""
        tables = (("radial", radial), ("bins", bins), ("summary", summary))
        for name, table in tables:
            check_finite(table, name)
        for name, table in tables:
            self._writers[name].write_table(table, row_group_size=ROW_GROUP_ROWS)

    def close(self) -> list[str]:
        """Finish the Parquet files and write summary.json; returns the file names."""
        for writer in self._writers.values():
            writer.close()
        for stream in self._streams:
            stream.close()
        rows = pq.ParquetFile(f"{self.out_dir}/summary.parquet", filesystem=self.fs)
        with self.fs.open_output_stream(f"{self.out_dir}/summary.json") as f:
            _write_summary_json(f, self.head, (row for batch in rows.iter_batches() for row in batch.to_pylist()))
        return list(TABLE_FILES)


def _write_summary_json(f, head: dict, rows) -> None:
    """summary.json streamed row by row: the head's keys and "results", keys sorted, indent 2."""
    doc = dict(head, results=[])
    text = json.dumps(doc, indent=2, sort_keys=True)
    before, after = text.split('"results": []', 1)
    f.write((before + '"results": [').encode())
    for i, row in enumerate(rows):
        body = json.dumps(json_row(row), indent=2, sort_keys=True).replace("\n", "\n    ")
        f.write(((",\n    " if i else "\n    ") + body).encode())
    f.write(("\n  ]" + after + "\n").encode())


def write_tables(result: Result, out_dir: str, filesystem: pafs.FileSystem | None = None) -> list[str]:
    """Write one medium's tables into out_dir (on `filesystem`, local by default); returns the
    file names."""
    writer = TableWriter(out_dir, result.spec, run_facts(result), filesystem, extra=target_entry(result))
    writer.add(result)
    return writer.close()
