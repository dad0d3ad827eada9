"""rhoEff's standard error (workers.exports.rho_eff): for the exit tally, formula (*) over bins a
photon reaches at most one of reproduces the tally's own se(Rd) from the radial bins (so the
bins' covariance is right), and over independent seeds rhoEff scatters as its reported errors
say; rhoEff is the measured Rd / (1 - R_spec) less what lies beyond the last node."""

from __future__ import annotations

import math

import numpy as np
import pytest

from schema import parse_spec
from schema.bins import pbrt_radius_nodes
from workers.models.catmull_rom import integrate_catmull_rom
from workers.exports.pbrt import pbrt_tables
from workers.exports.profiles import radial_profiles, summary_rows
from workers.exports.conserving import conserving_nodes
from workers.exports.rho_eff import disjoint_stderr, integration_weights
from workers.exports.source import ExportSource
from workers.fold.output import write_tables
from workers.run.simulate import simulate

SEEDS = (11, 12, 13, 14, 15, 16)
SPEC = {
    "name": "rho-eff-seeds",
    "medium": {"sigma_a": [0.5, 0.1, 0.02], "sigma_s": [0.5, 0.9, 0.98], "g": 0.5, "eta": 1.33},
    "photons": 1500, "shards": 2, "batches_per_shard": 2, "estimator": "exits",
    "bins": {"radial": {"count": 64, "spacing": "pbrt"}, "cos_theta_o": {"count": 1}, "phi_o": {"count": 1}},
}


def test_formula_reproduces_the_tallys_rd_stderr(arrays_source):
    """c = 1 over the radial bins and the part beyond r_max: (*) is the tally's se(Rd), per
    component and incidence angle (to rounding); without the covariance term it is not."""
    profiles = radial_profiles(arrays_source.tables["radial"])
    summary = summary_rows(arrays_source.tables["summary"])
    checked = several = 0
    for key, prof in profiles.items():
        if key[0] != "exits":
            continue
        row = summary[key]
        m, se = prof.masses
        mean = np.append(m, row["Rd_beyond_rmax"])
        stderr = np.append(se, row["Rd_beyond_rmax_stderr"])
        got = disjoint_stderr(np.ones_like(mean), mean, stderr, row["photons"])
        assert got == pytest.approx(row["Rd_stderr"], rel=1e-9), key
        if np.count_nonzero(np.isfinite(stderr)) > 1:  # the bins' covariance matters
            naive = math.sqrt(np.nansum(stderr**2))
            assert abs(naive - row["Rd_stderr"]) > 1e-3 * row["Rd_stderr"], key
            several += 1
        checked += 1
    assert checked == 12 and several >= 8  # 2 angles x 2 channels x 3 components


def test_integration_weights_give_rho_eff():
    nodes = pbrt_radius_nodes(64)
    rows = np.random.default_rng(1).random((3, 64))
    np.testing.assert_allclose(rows @ integration_weights(nodes), integrate_catmull_rom(nodes, rows)[0], rtol=1e-12)


@pytest.fixture(scope="module")
def tables(tmp_path_factory):
    out = []
    for seed in SEEDS:
        d = tmp_path_factory.mktemp(f"seed{seed}")
        write_tables(simulate(parse_spec(dict(SPEC, seed=seed)), threads=1), str(d))
        source = ExportSource.from_directory(d)
        (t,) = pbrt_tables(source)
        out.append((source, t))
    return out


def test_rho_eff_scatters_over_seeds_as_its_errors_say(tables, walk_stats):
    """sum over albedos of sum_k ((rhoEff_k - weighted mean) / se_k)^2 is chi-square with
    n_albedo (K - 1) degrees of freedom; also the coefficients reproduce rhoEff."""
    rho = np.array([t.rho_eff for _s, t in tables])  # [seed, albedo]
    se = np.array([t.rho_eff_stderr for _s, t in tables])
    assert all(t.meta["rhoEffStderrMeaning"].startswith("standard error of rhoEff itself") for _s, t in tables)
    w = 1.0 / se**2
    mean = np.sum(w * rho, axis=0) / np.sum(w, axis=0)
    q = float(np.sum(w * (rho - mean) ** 2))
    k, n = rho.shape
    lo, hi = walk_stats.chi2_band(n * (k - 1), dof=SPEC["photons"] - 1)
    print(f"rhoEff over {k} seeds: sum z^2 = {q:.2f} over {n * (k - 1)} dof, band [{lo:.2f}, {hi:.2f}]")
    assert lo <= q <= hi
    for source, t in tables:  # rhoEff is exactly sum_j c_j M_j, the combination whose error is reported
        for i, (key, prof) in enumerate(_rows(source)):
            m, se = prof.masses
            row = summary_rows(source.tables["summary"])[key]
            entered = 1 - row["R_spec"]
            c = conserving_nodes(m / entered, se / entered, int(row["photons"])).coefficients
            assert c @ (m / entered) == pytest.approx(t.rho_eff[i], rel=1e-12)
            assert t.rho_eff_stderr[i] == pytest.approx(disjoint_stderr(c, m / entered, se / entered, int(row["photons"])),
                                                        rel=1e-9)


def _rows(source):
    """(key, radial profile) of the total component, by albedo (the pbrt table's row order)."""
    rows = [(k, p) for k, p in radial_profiles(source.tables["radial"]).items() if k[4] == "total"]
    return sorted(rows, key=lambda kp: kp[1].albedo)


def test_rho_eff_is_rd_over_entered_less_the_part_beyond(tables):
    """rhoEff + rhoBeyondRmax = Rd / (1 - R_spec) to rounding: the spline holds every bin's
    measured mass, and rhoBeyondRmax is the measured part beyond the last edge plus the last
    bin's part outside the last node (0 here: no photon reaches 200 optical radii)."""
    for source, t in tables:
        summary = summary_rows(source.tables["summary"])
        for i, (key, _prof) in enumerate(_rows(source)):
            row = summary[key]
            assert t.rho_eff[i] + t.rho_beyond_rmax[i] == pytest.approx(row["Rd"] / (1 - row["R_spec"]), rel=1e-12)
            assert t.rho_beyond_rmax[i] == pytest.approx(row["Rd_beyond_rmax"] / (1 - row["R_spec"]), abs=1e-15)
