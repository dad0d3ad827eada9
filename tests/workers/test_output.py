"""The tables' key columns: every row of radial, bins and summary (and of summary.json) names its
estimator, medium index and coordinates (albedo, g, eta of its channel), incidence angle, channel
and component, in the column order of schema.tables."""

from __future__ import annotations

import json

import numpy as np
import pyarrow.parquet as pq
import pytest

from schema import BINS_SCHEMA, RADIAL_SCHEMA, SUMMARY_SCHEMA, parse_spec
from workers.fold.output import write_tables
from workers.run.simulate import simulate


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


# ---------------------------------------------------------------------------------------------
# The grazing bin at eta = 1: the exit tally's S = w / cos_o has an infinite second moment in the
# lowest cos(theta_o) bin (workers.fold.output.s_infinite_variance), so no error bar is valid there.
# ---------------------------------------------------------------------------------------------
def _grazing_tables(tmp_path_factory, eta: float, estimator: str) -> dict[str, np.ndarray]:
    spec = parse_spec({
        "name": "grazing", "medium": {"sigma_a": 0.1, "sigma_s": 0.9, "g": 0.5, "eta": eta},
        "incidence_deg": [0, 40], "photons": 1500, "shards": 2, "batches_per_shard": 2, "estimator": estimator,
        "bins": {"radial": {"count": 3, "max_mm": 6.0}, "theta_s": {"count": 2}, "cos_theta_o": {"count": 3},
                 "phi_o": {"count": 2}},
    })  # fmt: skip
    out = tmp_path_factory.mktemp(f"grazing-{estimator}-{eta}")
    write_tables(simulate(spec, threads=1), str(out))
    return {k: np.asarray(v) for k, v in pq.read_table(out / "bins.parquet").to_pydict().items()}


@pytest.fixture(scope="module")
def grazing_tables(tmp_path_factory):
    return {(eta, est): _grazing_tables(tmp_path_factory, eta, est) for eta in (1.0, 1.3) for est in ("both", "hybrid")}


def test_s_infinite_variance_rule():
    from workers.fold.output import s_infinite_variance

    for comp in ("single", "multiple", "total"):
        assert s_infinite_variance("exits", comp, 1.0, 0.0)
        assert not s_infinite_variance("exits", comp, 1.0, 1.0 / 3.0)  # cos_o >= c_1: bounded
        assert not s_infinite_variance("exits", comp, 1.3, 0.0)  # Fresnel: density ~ cos_o^2
        assert not s_infinite_variance("exits", comp, 0.8, 0.0)  # cos_o >= sqrt(1 - eta^2)
        assert not s_infinite_variance("connections", comp, 1.0, 0.0)  # T cos_in / cos_o bounded
    assert s_infinite_variance("hybrid", "multiple", 1.0, 0.0) and s_infinite_variance("hybrid", "total", 1.0, 0.0)
    assert not s_infinite_variance("hybrid", "single", 1.0, 0.0)  # first-vertex connections


@pytest.mark.parametrize("estimator", ["both", "hybrid"])
def test_grazing_bins_at_eta_1_are_flagged_with_no_error_bar(grazing_tables, estimator):
    """bins.parquet at eta = 1: S_infinite_variance is 1 exactly in the lowest cos(theta_o) bin
    of the exit-scored rows (exits: every component; hybrid: multiple and total), S_stderr is
    NaN exactly there and where no event contributed, and G keeps its error bar.  The flagged
    bins hold exits (the flag marks measured bins, not empty ones)."""
    t = grazing_tables[1.0, estimator]
    grazing = t["cos_theta_o_lo"] == 0.0
    exit_scored = (t["estimator"] == "exits") | ((t["estimator"] == "hybrid") & (t["component"] != "single"))
    want = grazing & exit_scored
    assert t["S_infinite_variance"].dtype == np.int64
    assert np.array_equal(t["S_infinite_variance"], want.astype(np.int64))
    assert np.array_equal(np.isnan(t["S_stderr"]), want | (t["events"] == 0))
    assert np.array_equal(np.isnan(t["G_stderr"]), t["events"] == 0)
    assert t["events"][want].sum() > 100, t["events"][want]
    assert np.all(np.isfinite(t["S"]))  # the estimate itself is kept: unbiased


@pytest.mark.parametrize("estimator", ["both", "hybrid"])
def test_no_bin_is_flagged_at_eta_1_3(grazing_tables, estimator):
    t = grazing_tables[1.3, estimator]
    assert not t["S_infinite_variance"].any()
    assert np.array_equal(np.isnan(t["S_stderr"]), t["events"] == 0)
