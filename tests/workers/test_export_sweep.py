"""Exports of a sweep: the pbrt table of a sweep with independent walks agrees, row by row and bit
for bit, with the single-medium datasets of its media (each medium's own spec run alone), and the
array exports carry the sweep's media as an axis.  (With shared walks, the default for a sweep of
several albedos, only a group's largest albedo is its own job bit for bit; the other rows are
proven against their own walks in test_shared_walks.)"""

from __future__ import annotations

import numpy as np
import pyarrow.compute as pc
import pytest

from schema import parse_spec
from workers.exports import write_export
from workers.exports.albedo_map import albedo_maps
from workers.exports.arrays import read_npz
from workers.exports.conserving import conserving_nodes
from workers.exports.pbrt import pbrt_tables
from workers.exports.profiles import radial_profiles, summary_rows
from workers.exports.source import ExportSource
from workers.fold.output import write_tables
from workers.run.simulate import simulate, simulate_sweep

SWEEP = {
    "name": "sweep-pbrt", "sweep": {"albedo": [0.3, 0.8, 0.95], "g": [0.5], "eta": [1.33], "walks": "independent"},
    "photons": 2000, "shards": 2, "batches_per_shard": 4, "seed": 13, "estimator": "exits",
    "bins": {"radial": {"count": 64, "spacing": "pbrt"}, "cos_theta_o": {"count": 1}, "phi_o": {"count": 1}},
}


def _source(spec, out) -> ExportSource:
    if spec.is_sweep:
        simulate_sweep(spec, str(out), threads=1)
    else:
        write_tables(simulate(spec, threads=1), str(out))
    return ExportSource.from_directory(out)


@pytest.fixture(scope="module")
def sweep_and_media(tmp_path_factory):
    spec = parse_spec(SWEEP)
    sweep = _source(spec, tmp_path_factory.mktemp("sweep"))
    media = [_source(spec.medium_spec(m), tmp_path_factory.mktemp(f"medium{m}")) for m in range(spec.n_media)]
    return sweep, media


def test_pbrt_table_of_a_sweep_is_its_media_datasets(sweep_and_media):
    sweep, media = sweep_and_media
    (table,) = pbrt_tables(sweep)
    assert (table.g, table.eta) == (0.5, 1.33)
    np.testing.assert_array_equal(table.rho_samples, [0.3, 0.8, 0.95])
    for m, source in enumerate(media):  # row m from medium m's own single-medium dataset
        key = ("exits", 0, 0.0, "c0", "total")
        masses, masses_se = radial_profiles(source.tables["radial"])[key].masses
        summary = summary_rows(source.tables["summary"])[key]
        entered = 1.0 - summary["R_spec"]
        row = conserving_nodes(masses / entered, masses_se / entered, int(summary["photons"]))
        np.testing.assert_array_equal(table.profile[m], row.values)
        np.testing.assert_array_equal(table.profile_stderr[m], row.stderr)
        np.testing.assert_array_equal(table.profile_node_error[m], row.error)
        assert table.rho_eff_measured[m] == summary["Rd"] / entered
        assert table.rho_eff_measured_stderr[m] == summary["Rd_stderr"] / entered
    assert table.meta["provenance"]["dataset"] == "sweep-pbrt"


def test_albedo_map_of_a_sweep_is_its_media_summaries(sweep_and_media):
    sweep, media = sweep_and_media
    (m,) = albedo_maps(sweep)
    for i, source in enumerate(media):
        row = summary_rows(source.tables["summary"])[("exits", 0, 0.0, "c0", "total")]
        assert (m.columns["rd_normal"][i], m.columns["rd_normal_stderr"][i]) == (row["Rd"], row["Rd_stderr"])


def test_npz_of_a_sweep_has_a_medium_axis(sweep_and_media, tmp_path):
    sweep, media = sweep_and_media
    write_export("npz", sweep, tmp_path)
    arrays, meta = read_npz(tmp_path / "sweep-pbrt.npz")
    assert meta["axes"]["radial/Rd_r"][1] == "medium" and arrays["radial/Rd_r"].shape[1] == 3
    np.testing.assert_array_equal(arrays["albedo"][:, 0], [0.3, 0.8, 0.95])
    for i, source in enumerate(media):
        own = source.tables["radial"].filter(pc.equal(source.tables["radial"]["component"], "total"))
        np.testing.assert_array_equal(arrays["radial/Rd_r"][0, i, 0, 0, 2], own.column("Rd_r").to_numpy())
