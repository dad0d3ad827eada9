"""The tables' key columns: every row of radial, bins and summary (and of summary.json) names its
estimator, medium index and coordinates (albedo, g, eta of its channel), incidence angle, channel
and component, in the column order of schema.tables."""

from __future__ import annotations

import json

import numpy as np
import pyarrow.parquet as pq
import pytest

from schema import BINS_SCHEMA, RADIAL_SCHEMA, SUMMARY_SCHEMA, parse_spec
from workers.output import write_tables
from workers.simulate import simulate


@pytest.fixture(scope="module")
def tables(tmp_path_factory):
    spec = parse_spec({
        "name": "keys", "medium": {"sigma_a": [0.1, 0.5], "sigma_s": [9.9, 2.0], "g": [0.0, 0.8], "eta": 1.4},
        "incidence_deg": [0, 40], "photons": 64, "shards": 2, "batches_per_shard": 1, "estimator": "both",
        "bins": {"radial": {"count": 3, "max_mm": 2.0}, "theta_s": {"count": 2}, "cos_theta_o": {"count": 2},
                 "phi_o": {"count": 1}},
    })
    out = tmp_path_factory.mktemp("keys")
    write_tables(simulate(spec, threads=1), str(out))
    read = {name: pq.read_table(out / f"{name}.parquet") for name in ("radial", "bins", "summary")}
    return spec, read, json.loads((out / "summary.json").read_text())


def test_key_columns_follow_estimator(tables):
    _, read, _ = tables
    for name, schema in (("radial", RADIAL_SCHEMA), ("bins", BINS_SCHEMA), ("summary", SUMMARY_SCHEMA)):
        assert read[name].schema.names == schema.names
        assert schema.names[:5] == ["estimator", "medium", "albedo", "g", "eta"]


def test_key_columns_carry_each_channels_coordinates(tables):
    spec, read, doc = tables
    by_channel = {c.name: c for c in spec.channels()}
    rows_per_cfg = {"radial": 3, "bins": 3 * 2 * 2, "summary": 1}
    for name, t in read.items():
        cols = t.to_pydict()
        assert set(cols["medium"]) == {0}
        for ch, a, g, eta in zip(cols["channel"], cols["albedo"], cols["g"], cols["eta"]):
            c = by_channel[ch]
            assert (a, g, eta) == (c.albedo, c.g, 1.4)  # bit for bit
        # every (estimator, incidence, channel, component) once, its rows contiguous
        n_keys = 2 * 2 * 2 * 3
        assert t.num_rows == n_keys * rows_per_cfg[name]
        assert np.all(np.diff(np.array(cols["albedo"]).reshape(n_keys, -1), axis=1) == 0)
    assert [r["medium"] for r in doc["results"]] == [0] * 24
    assert all(set(r) >= {"medium", "albedo", "g", "eta"} for r in doc["results"])  # keys sorted in the file
    assert {(r["channel"], r["albedo"], r["g"], r["eta"]) for r in doc["results"]} == {
        (c.name, c.albedo, c.g, 1.4) for c in spec.channels()}
