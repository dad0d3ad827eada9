"""The albedo map (workers.exports.albedo_map): on an index-matched isotropic medium, where the
exact reflectance is known (Chandrasekhar's H-function), the measured normal and diffuse maps
agree with it within their errors; the monotone fit, its inverse, the model columns and the
files' round trip."""

from __future__ import annotations

import csv
import dataclasses
import json

import numpy as np
import pyarrow.compute as pc
import pytest

from schema import parse_spec
from tests.reference.hfunction import diffuse_reflectance_isotropic_matched
from workers.models.diffusion import burley_total_rd, dipole_total_rd
from workers.exports import write_export
from workers.models.catmull_rom import invert_catmull_rom
from workers.exports.albedo_map import (
    COLUMNS,
    albedo_for_reflectance,
    albedo_maps,
    diffuse_incidence_deg,
    isotonic,
    pchip,
)
from workers.exports.source import ExportError, ExportSource
from workers.fold.output import write_tables
from workers.run.simulate import simulate

ALBEDOS = (0.5, 0.9, 0.98)
SPEC = {
    "name": "map", "medium": {"sigma_a": [1 - a for a in ALBEDOS], "sigma_s": list(ALBEDOS), "g": 0.0, "eta": 1.0},
    "incidence_deg": [0.0] + diffuse_incidence_deg(4), "photons": 6000, "shards": 2, "batches_per_shard": 4,
    "seed": 21, "estimator": "exits",
    "bins": {"radial": {"count": 2, "max_mm": 50.0}, "cos_theta_o": {"count": 1}, "phi_o": {"count": 1}},
}


@pytest.fixture(scope="module")
def source(tmp_path_factory) -> ExportSource:
    out = tmp_path_factory.mktemp("map")
    write_tables(simulate(parse_spec(SPEC), threads=1), str(out))
    return ExportSource.from_directory(out)


def _exact_diffuse(albedo: float) -> float:
    mu, w = np.polynomial.legendre.leggauss(24)
    mu, w = 0.5 * (mu + 1), 0.5 * w
    return float(sum(2 * m * wi * diffuse_reflectance_isotropic_matched(albedo, m) for m, wi in zip(mu, w)))


def test_measured_map_equals_the_exact_index_matched_reflectance(source, walk_stats):
    (m,) = albedo_maps(source)
    c = m.columns
    np.testing.assert_array_equal(c["albedo"], ALBEDOS)
    assert m.meta["diffuse_rule"]["points"] == 4 and m.meta["diffuse_needs"] is None
    exact_normal = [diffuse_reflectance_isotropic_matched(a, 1.0) for a in ALBEDOS]
    walk_stats.assert_within((c["rd_normal"] - exact_normal) / c["rd_normal_stderr"], dof=7, what="normal", n_tests=2)
    np.testing.assert_array_equal(c["rho_eff_normal"], c["rd_normal"])  # eta = 1: no specular reflection
    exact_diffuse = np.array([_exact_diffuse(a) for a in ALBEDOS])
    assert np.all(c["rd_diffuse_quadrature_error"] == 0.0)  # the Fresnel-based estimate vanishes at eta = 1
    # the 4-point rule's own error on the exact curve (< 2e-4 relative) is far below the noise
    walk_stats.assert_within((c["rd_diffuse"] - exact_diffuse) / c["rd_diffuse_stderr"], dof=7, what="diffuse",
                             n_tests=2)
    # Christensen-Burley fits exactly this (diffuse, index-matched, isotropic): within 2.5e-3 + the noise
    assert np.all(np.abs(c["burley_error_diffuse"]) < 2.5e-3 + 5 * c["rd_diffuse_stderr"])
    np.testing.assert_allclose(c["burley_rho_eff"], burley_total_rd(np.array(ALBEDOS)))
    np.testing.assert_allclose(c["dipole_rho_eff"], dipole_total_rd(np.array(ALBEDOS), 1.0))
    np.testing.assert_allclose(c["dipole_error"], c["dipole_rho_eff"] - c["rho_eff_normal"])
    assert m.meta["provenance"]["format"] == "albedo-map"


def test_monotone_and_invertible(source):
    (m,) = albedo_maps(source)
    c = m.columns
    for col in ("rd_normal", "rd_diffuse"):
        assert np.all(np.diff(c[f"{col}_monotone"]) >= 0)
        np.testing.assert_array_equal(c[f"{col}_monotone"], c[col])  # already increasing: unchanged
        back = albedo_for_reflectance(c["albedo"], c[f"{col}_monotone"], c[col], g=m.g)
        np.testing.assert_allclose(back, c["albedo"], rtol=1e-12)
    mid = 0.5 * (c["rd_normal"][0] + c["rd_normal"][1])
    assert c["albedo"][0] < albedo_for_reflectance(c["albedo"], c["rd_normal"], mid) < c["albedo"][1]


def test_no_diffuse_rule_is_not_a_monotone_adjustment(source):
    """Without the Gauss-Legendre angles the diffuse columns are NaN: nothing was adjusted there."""
    normal = {name: t.filter(pc.equal(t["incidence_deg"], 0.0)) for name, t in source.tables.items()}
    only_normal = dataclasses.replace(source, spec=parse_spec(dict(SPEC, incidence_deg=[0.0])), tables=normal)
    (m,) = albedo_maps(only_normal)
    assert np.all(np.isnan(m.columns["rd_diffuse_monotone"]))
    assert m.meta["monotone_adjusted"] == {"rd_normal_monotone": 0, "rd_diffuse_monotone": 0}


def test_inversion_of_a_sparse_map_against_the_dense_exact_relation():
    """A 4-albedo map (the exact index-matched isotropic reflectance at 0.5, 0.9, 0.99, 0.999)
    inverted at 60 reflectances between its ends; each albedo found is put back through a dense
    exact relation (48 H-function values, interpolated in s = sqrt(1 - a), where it is smooth):
    the reflectance error is below 6 % everywhere, and below both straight lines in albedo
    (19 % at Rd 0.2) and pbrt's InvertCatmullRom of the same points."""
    s_dense = np.linspace(0.0, np.sqrt(0.55), 48)
    r_dense = np.array([diffuse_reflectance_isotropic_matched(1 - s * s) for s in s_dense])
    exact = lambda a: np.interp(np.sqrt(1 - np.asarray(a)), s_dense, r_dense)  # noqa: E731
    albedo = np.array([0.5, 0.9, 0.99, 0.999])
    rd = np.array([diffuse_reflectance_isotropic_matched(a) for a in albedo])
    target = np.linspace(rd[0], rd[-1], 62)[1:-1]
    ours = albedo_for_reflectance(albedo, rd, target)
    assert np.all(np.diff(ours) > 0)
    np.testing.assert_allclose(albedo_for_reflectance(albedo, rd, rd), albedo, rtol=1e-12)
    err = {name: np.abs(exact(a) / target - 1) for name, a in
           (("ours", ours), ("linear", np.interp(target, rd, albedo)), ("pbrt", invert_catmull_rom(albedo, rd, target)))}
    print({k: float(v.max()) for k, v in err.items()})
    assert err["ours"].max() < 0.06
    assert err["ours"].max() < 0.5 * err["pbrt"].max() and err["ours"].max() < 0.3 * err["linear"].max()


def test_pchip_is_monotone_and_interpolates():
    x = np.array([0.0, 0.1, 0.5, 0.6, 2.0])
    y = np.array([0.0, 0.05, 0.06, 1.0, 1.01])  # steep and flat stretches: a plain cubic overshoots
    xq = np.linspace(0, 2, 2001)
    yq = pchip(x, y, xq)
    np.testing.assert_allclose(pchip(x, y, x), y, rtol=1e-14)
    assert np.all(np.diff(yq) >= 0) and yq.min() >= 0 and yq.max() <= 1.01


def test_isotonic_regression():
    np.testing.assert_array_equal(isotonic([1, 2, 3], [1, 1, 1]), [1, 2, 3])
    np.testing.assert_allclose(isotonic([1, 3, 2, 4], [1, 1, 1, 1]), [1, 2.5, 2.5, 4])
    # weights 1/se^2: the precise value dominates the pooled block
    np.testing.assert_allclose(isotonic([1, 3, 2], [1, 0.1, 1]), [1, (3 * 100 + 2) / 101, (3 * 100 + 2) / 101])
    y = np.random.default_rng(0).normal(size=50).cumsum()
    assert np.all(np.diff(isotonic(y, np.ones(50))) >= -1e-12)


def test_files_round_trip_and_refusals(source, tmp_path):
    names = write_export("albedo-map", source, tmp_path)
    assert names == ["albedo-map-exits-g+0.0000-eta1.0000.csv", "albedo-map-exits-g+0.0000-eta1.0000.json", "export.json"]
    (m,) = albedo_maps(source)
    with open(tmp_path / names[0], newline="") as f:
        rows = list(csv.reader(f))
    assert tuple(rows[0]) == COLUMNS
    for j, col in enumerate(COLUMNS):
        np.testing.assert_array_equal([float(r[j]) for r in rows[1:]], m.columns[col])
    doc = json.loads((tmp_path / names[1]).read_text())
    for col in COLUMNS:
        np.testing.assert_array_equal(np.array([np.nan if x is None else x for x in doc["columns"][col]]), m.columns[col])
    assert doc["eta"] == 1.0 and "rd_diffuse" in doc["definitions"]
    oblique = {name: t.filter(pc.not_equal(t["incidence_deg"], 0.0)) for name, t in source.tables.items()}
    with pytest.raises(ExportError, match="normal incidence"):
        albedo_maps(dataclasses.replace(source, tables=oblique))
