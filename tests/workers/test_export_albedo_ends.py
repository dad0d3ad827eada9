"""The ends of a pbrt albedo grid (workers.exports.pbrt, albedo_map): pbrt's spacing holds
rho = 0 and rho = 1. Albedo 0 reflects nothing: its row is zeros with no events and NaN errors
(never 0 +- 0); albedo 1 never ends but at the path cap, whose weight is reported, and with no
absorption the reflected and the truncated weight add up to the power entered. Nothing a
renderer reads (profile, rhoEff, profileCDF) is NaN."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from schema import parse_spec
from workers.exports import write_export
from workers.exports.albedo_map import albedo_maps
from workers.exports.pbrt import pbrt_tables
from workers.exports.pbrt_io import read_pbrt
from workers.exports.profiles import summary_rows
from workers.exports.source import ExportSource
from workers.run.simulate import simulate_sweep

ENDS = {
    "name": "albedo-ends", "sweep": {"albedo": {"count": 3, "spacing": "pbrt"}, "g": [0.0], "eta": [1.33]},
    "photons": 64, "shards": 2, "batches_per_shard": 2, "seed": 21, "max_scatter": 300,
    "estimator": "exits",  # every photon's weight exits or is cut: the energy balance below is exact
    "bins": {"radial": {"count": 64, "spacing": "pbrt"}, "cos_theta_o": {"count": 1}, "phi_o": {"count": 1}},
}


@pytest.fixture(scope="module")
def source(tmp_path_factory) -> ExportSource:
    out = tmp_path_factory.mktemp("ends")
    simulate_sweep(parse_spec(ENDS), str(out), threads=1)
    return ExportSource.from_directory(out)


def test_pbrt_rows_at_albedo_0_and_1(source, tmp_path):
    (table,) = pbrt_tables(source)
    assert table.rho_samples[0] == 0.0 and table.rho_samples[-1] == 1.0
    for field in ("profile", "rho_eff", "profile_cdf"):  # what a renderer reads
        assert np.all(np.isfinite(getattr(table, field))), field
    assert table.meta["rhoEffMonotone"]
    # albedo 0: nothing leaves; no event anywhere, so no error bars
    assert np.all(table.profile[0] == 0.0) and np.all(table.profile_cdf[0] == 0.0) and table.rho_eff[0] == 0.0
    assert np.all(np.isnan(table.profile_stderr[0])) and np.isnan(table.rho_eff_stderr[0])
    assert table.rho_eff_measured[0] == 0.0 and np.isnan(table.rho_eff_measured_stderr[0])
    assert table.rho_truncated[0] == 0.0 and np.isnan(table.rho_truncated_stderr[0])
    radial = source.tables["radial"]
    events = radial.column("events").to_numpy()[radial.column("medium").to_numpy() == 0]
    assert np.all(events == 0)
    rows = {k[1]: r for k, r in summary_rows(source.tables["summary"]).items() if k[4] == "total"}
    assert rows[0]["unresolved_bins"] == 64 and math.isnan(rows[0]["Rd_stderr"])
    # albedo 1: paths end at the cap, its weight reported; no absorption, so Rd + truncated = 1 - R_spec
    top = rows[2]
    assert top["absorbed"] == 0.0 and top["truncated"] > 0 and top["truncated_stderr"] > 0
    entered = 1.0 - top["R_spec"]
    assert table.rho_truncated[2] == top["truncated"] / entered
    assert table.rho_truncated_stderr[2] == top["truncated_stderr"] / entered
    # exact up to the walk's float32 weights (relative 6e-8 per photon, a sum of 64)
    assert table.rho_eff_measured[2] + table.rho_truncated[2] == pytest.approx(1.0, abs=1e-6)
    assert np.all(np.isfinite(table.profile_stderr[2][table.profile[2] > 0])) and table.rho_eff[2] > 0
    names = write_export("pbrt", source, tmp_path)
    for name in names[:-1]:
        assert read_pbrt(tmp_path / name).equals(table), name


def test_albedo_map_at_albedo_0_and_1(source, tmp_path):
    (m,) = albedo_maps(source)
    c = m.columns
    np.testing.assert_array_equal(c["albedo"][[0, 2]], [0.0, 1.0])
    assert c["rd_normal"][0] == 0.0 and np.isnan(c["rd_normal_stderr"][0])
    assert c["truncated_normal"][0] == 0.0 and np.isnan(c["truncated_normal_stderr"][0])
    assert c["truncated_normal"][2] > 0 and c["truncated_normal_stderr"][2] > 0
    assert np.all(np.isfinite(c["rd_normal_monotone"])) and np.all(np.diff(c["rd_normal_monotone"]) >= 0)
    names = write_export("albedo-map", source, tmp_path)
    doc = json.loads((tmp_path / names[1]).read_text())
    assert doc["columns"]["rd_normal_stderr"][0] is None and doc["columns"]["truncated_normal"][2] > 0
