"""The pbrt export (workers.exports.pbrt): round trips of its JSON and binary files, pbrt's sampling
side on the measured table (chi-square, r_max), rhoEff against the measured Rd / (1 - R_spec),
and clear refusals of datasets it cannot be made from."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pytest
from scipy import integrate

from schema import parse_spec
from schema.bins import pbrt_radial_edges
from tests.support.stats import assert_samples_match_pdf
from workers.models.catmull_rom import catmull_rom
from workers.exports.pbrt import pbrt_tables, write_pbrt
from workers.exports.pbrt_io import read_pbrt
from workers.exports.profiles import radial_profiles
from workers.exports.source import ExportError, ExportSource
from workers.fold.output import write_tables
from workers.run.simulate import simulate
from workers.models.tabulated import pdf_sr, r_max, sample_sr

# Four albedos sharing (g, eta) as four channels of unit extinction: a small pbrt table.
PBRT_SPEC = {
    "name": "pbrt-small",
    "medium": {"sigma_a": [0.7, 0.4, 0.1, 0.01], "sigma_s": [0.3, 0.6, 0.9, 0.99], "g": 0.5, "eta": 1.33},
    "photons": 8000, "shards": 2, "batches_per_shard": 4, "seed": 3, "estimator": "exits",
    "bins": {"radial": {"count": 64, "spacing": "pbrt"}, "cos_theta_o": {"count": 1}, "phi_o": {"count": 1}},
}


@pytest.fixture(scope="module")
def source(tmp_path_factory) -> ExportSource:
    out = tmp_path_factory.mktemp("pbrt-small")
    write_tables(simulate(parse_spec(PBRT_SPEC), threads=1), str(out))
    return ExportSource.from_directory(out)


@pytest.fixture(scope="module")
def table(source):
    (t,) = pbrt_tables(source)
    return t


def test_layout_and_provenance(table, source):
    assert (table.g, table.eta) == (0.5, 1.33)
    np.testing.assert_array_equal(table.rho_samples, [0.3, 0.6, 0.9, 0.99])
    assert table.profile.shape == (4, 64) and table.radius_samples[0] == 0.0
    assert table.radius_samples[1] == 2.5e-3 and table.radius_samples[-1] == pytest.approx(202.85, rel=1e-4)
    np.testing.assert_array_equal(table.profile_cdf[:, -1], table.rho_eff)
    assert np.all(table.profile >= 0) and np.all(table.profile_stderr[table.profile > 0] > 0)
    assert table.range_negative_mass.shape == table.range_worst_rho.shape == (3,)
    prov = table.meta["provenance"]
    assert prov["dataset"] == "pbrt-small" and prov["spec_hash"] == source.spec.spec_hash()
    assert set(prov["tables_sha256"]) == {"radial.parquet", "bins.parquet", "summary.parquet"}
    assert prov["code_version"]["package"] and table.meta["estimator"] == "exits"


def test_json_and_binary_round_trip(table, source, tmp_path):
    names = write_pbrt(source, tmp_path)
    assert names == ["pbrt-exits-g+0.5000-eta1.3300.json", "pbrt-exits-g+0.5000-eta1.3300.bin"]
    for name in names:
        back = read_pbrt(tmp_path / name)
        assert back.equals(table), name
    raw = (tmp_path / names[1]).read_bytes()
    assert raw[:8] == b"BSSRDFTB"
    with pytest.raises(ValueError, match="not a pbrt table"):
        (tmp_path / "bad.bin").write_bytes(b"PNG" + raw[3:])
        read_pbrt(tmp_path / "bad.bin")


def test_rho_eff_is_the_measured_diffuse_reflectance(table):
    """rhoEff (pbrt's Catmull-Rom integral of the node values) holds exactly the measured energy:
    rhoEff + rhoBeyondRmax = Rd / (1 - R_spec) to rounding (the photons beyond the last node,
    below 1e-9 here, are in the measured total only); every row's spline is >= 0, so pbrt's
    Pdf_Sr and Sample_Sr agree at the rows."""
    assert np.all(table.rho_beyond_rmax < 1e-9)
    np.testing.assert_allclose(table.rho_eff + table.rho_beyond_rmax, table.rho_eff_measured, rtol=1e-12)
    np.testing.assert_allclose(table.rho_eff_stderr, table.rho_eff_measured_stderr, rtol=1e-9)  # c = 1 on every bin
    assert np.all(table.profile_negative_mass == 0.0)
    assert np.all(np.diff(table.rho_eff) > 0) and table.meta["rhoEffMonotone"]


@pytest.mark.parametrize("i, sigma_t", [(1, 1.0), (2, 3.0), (3, 0.5)])
def test_sample_sr_on_the_measured_table_follows_its_profile(table, i, sigma_t):
    """Our Sample_Sr on the exported table draws radii from the tabulated profile: chi-square
    against 2 pi r Pdf_Sr integrated by quadrature. Pdf_Sr clamps the spline's negative lobes
    (pbrt's max(0, ...)), so it integrates to 1 + |profileNegativeMass| / rhoEff; the reference
    is normalised by that integral. r_max holds 99.9 % of the spline's (signed) integral, the
    mass the sampler distributes."""
    t = table.bssrdf_table()
    rho = t.rho_samples[i]
    nodes = t.radius_samples / sigma_t
    density = lambda r: 2 * math.pi * r * float(pdf_sr(t, rho, r, sigma_t))  # noqa: E731
    norm = sum(integrate.quad(density, a, b, limit=100)[0] for a, b in zip(nodes[:-1], nodes[1:]))
    assert norm - 1 == pytest.approx(-table.profile_negative_mass[i] / table.rho_eff[i], abs=1e-7)
    radii = sample_sr(t, rho, np.random.default_rng(5).random(60_000), sigma_t)
    rm = r_max(t, rho, sigma_t)
    edges = np.unique(np.concatenate([nodes[nodes < 1.5 * rm], [1.5 * rm]]))
    assert_samples_match_pdf(radii, lambda r: density(r) / norm, edges, n_tests=3, points=list(nodes),
                             what=f"measured table rho={rho}")
    cuts = np.concatenate([nodes[nodes < rm], [rm]])
    signed = lambda r: float(catmull_rom(t.radius_samples, t.profile[i], r * sigma_t)) * sigma_t / t.rho_eff[i]  # noqa: E731
    inside = sum(integrate.quad(signed, a, b, limit=100)[0] for a, b in zip(cuts[:-1], cuts[1:]))
    assert inside == pytest.approx(0.999, abs=1e-7)


def test_sampled_radii_reproduce_the_measured_bins(table, source, walk_stats):
    """Radii drawn by Sample_Sr at a node albedo fall into the dataset's own radial bins as often
    as the measurement says: z-scores with the bins' standard errors and the sampling noise,
    over every bin holding at least 1 % of the mass (a cut on the measured mass, not its error)."""
    t = table.bssrdf_table()
    (key,) = [k for k in radial_profiles(source.tables["radial"]) if k[3] == "c2" and k[4] == "total"]
    masses, masses_se = radial_profiles(source.tables["radial"])[key].masses
    radii = sample_sr(t, t.rho_samples[2], np.random.default_rng(6).random(400_000), 1.0)
    counts, _ = np.histogram(radii, pbrt_radial_edges(64))
    frac = counts / len(radii)
    expected, expected_se = masses / masses.sum(), masses_se / masses.sum()
    keep = expected > 0.01
    z = (frac - expected)[keep] / np.sqrt(expected_se[keep] ** 2 + frac[keep] / len(radii))
    walk_stats.assert_within(z, dof=7, what="Sample_Sr vs measured bins")


def test_refusals_name_what_to_change(source):
    """Datasets a pbrt table cannot be made from are refused with what to change (the same
    tables under a different spec, or cut to one channel)."""
    def variant(**changes):
        return dataclasses.replace(source, spec=parse_spec(dict(PBRT_SPEC, **changes)))

    with pytest.raises(ExportError, match='"spacing": "pbrt"'):
        pbrt_tables(variant(bins={"radial": {"count": 64}}))
    oblique = {}
    for name, t in source.tables.items():  # the same rows relabelled as 30 degrees
        i = t.schema.get_field_index("incidence_deg")
        oblique[name] = t.set_column(i, t.schema.field(i), pa.array([30.0] * t.num_rows))
    with pytest.raises(ExportError, match="normal incidence"):
        pbrt_tables(dataclasses.replace(source, spec=parse_spec(dict(PBRT_SPEC, incidence_deg=[30])), tables=oblique))
    one = {name: t.filter(pc.equal(t["channel"], "c1")) for name, t in source.tables.items()}
    with pytest.raises(ExportError, match="at least 2 distinct albedos.*sweep"):
        pbrt_tables(dataclasses.replace(source, tables=one))
