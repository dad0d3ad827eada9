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

from schema import BINS_SCHEMA, RADIAL_SCHEMA, SUMMARY_SCHEMA, table_metadata
from schema.version import code_version

from .merge import Result

__all__ = ["radial_table", "bins_table", "summary_table", "summary", "write_tables", "TABLE_FILES"]

COMPONENTS3 = ("single", "multiple", "total")
TABLE_FILES = ("radial.parquet", "bins.parquet", "summary.parquet", "summary.json")


def _keys(result: Result):
    """(key columns, cfg, channel index, component index) per (estimator, cfg, component);
    the key columns are the tables' leading columns (schema.tables), as scalars."""
    c = result.configs
    for est in result.estimators:
        for cfg in range(c.n):
            ch = c.channel_of(cfg)
            for k, comp in enumerate(COMPONENTS3):
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
    return pa.Table.from_pydict(cols, schema=RADIAL_SCHEMA)


def bins_table(result: Result) -> pa.Table:
    """G and S per (spatial x directional) bin; S = sum w / cos_o / (A Omega) per photon."""
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
        n = len(g)
        parts.append({
            **_repeat(keys, n), "r_lo_mm": edges[r_i], "r_hi_mm": edges[r_i + 1],
            "theta_s_lo": L.theta_s[t_i], "theta_s_hi": L.theta_s[t_i + 1],
            "cos_theta_o_lo": L.cos_o[c_i], "cos_theta_o_hi": L.cos_o[c_i + 1],
            "phi_o_lo": L.phi_o[p_i], "phi_o_hi": L.phi_o[p_i + 1],
            "G": g, "G_stderr": g_se, "S": s, "S_stderr": s_se,
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
        })  # fmt: skip
    return rows


def summary_table(result: Result) -> pa.Table:
    rows = summary_rows(result)
    return pa.Table.from_pylist(rows, schema=SUMMARY_SCHEMA)


def run_facts(result: Result) -> dict:
    """Deterministic facts about the run, stored in every table's metadata."""
    engines = sorted({i.get("engine", "?") for i in result.shard_info})
    return {
        "code_version": code_version(),
        "engine": engines[0] if len(engines) == 1 else engines,
        "rng": "philox4x32-10, key sha256(seed|configuration), counter (photon, draw, purpose)",
        "photons_per_config": int(result.n_sum),
        "shards": len(result.shard_info),  # the first K shards of a run to a target error
        "batches": int(result.k),
        "seed": result.spec.seed,
        "channels": [c.model_dump() for c in result.spec.channels()],
        "eta": result.configs.eta,
        "units": {"length": "mm", "Rd_r": "1/mm^2", "S": "1/(mm^2 sr)", "G": "fraction of incident power"},
        "normalisation": "per unit incident power; the walk carries 1 - R_spec, so S includes the entry Fresnel factor",
    }


def summary(result: Result) -> dict:
    """The summary printed by `bssrdf simulate --json` and stored as summary.json."""
    doc = {
        "name": result.spec.name,
        "spec_hash": result.spec.spec_hash(),
        "run": run_facts(result),
        "results": summary_rows(result),
    }
    if result.target is not None:
        doc["target"] = result.target.as_dict()  # workers.target.TargetStatus: reached, photons, worst check
    return doc


def write_tables(result: Result, out_dir: str, filesystem: pafs.FileSystem | None = None) -> list[str]:
    """Write the tables into out_dir (on `filesystem`, local by default); returns the file names."""
    fs = filesystem or pafs.LocalFileSystem()
    fs.create_dir(out_dir, recursive=True)
    meta = table_metadata(result.spec.canonical_json(), run_facts(result))
    for name, table in (("radial", radial_table(result)), ("bins", bins_table(result)), ("summary", summary_table(result))):
        table = table.replace_schema_metadata({**(table.schema.metadata or {}), **meta})
        with fs.open_output_stream(f"{out_dir}/{name}.parquet") as f:
            pq.write_table(table, f, compression="zstd")
    with fs.open_output_stream(f"{out_dir}/summary.json") as f:
        f.write((json.dumps(summary(result), indent=2, sort_keys=True) + "\n").encode())
    return list(TABLE_FILES)
