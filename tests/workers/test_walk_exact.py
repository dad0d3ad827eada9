"""The walk against exact references (tests/reference): the H-function and single scattering.

Every tolerance comes from the standard errors the engine reports (estimated from K batches, so
z-scores are Student-t with K - 1 degrees of freedom, see ``WalkStats`` in conftest.py).  Photon
counts come from the per-photon standard deviations (sd) noted at each spec: se = sd / sqrt(N).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from tests.reference.hfunction import diffuse_reflectance_isotropic_matched
from tests.reference.single_scattering import (
    single_scattering_radial,
    single_scattering_radial_cos,
    single_scattering_total,
)
from workers.run.simulate import simulate

SINGLE, MULTIPLE, TOTAL = 0, 1, 2

# ---------------------------------------------------------------------------------------------
# Chandrasekhar: isotropic scattering, eta = 1, normal incidence, Rd = 1 - sqrt(1 - a) H(1).
# Per-photon sd of Rd (total): weights ~0.21 (a = 0.5), ~0.30 (0.99); analog sqrt(Rd (1 - Rd)).
# Cost is the walk's tail: a shard runs until its longest photon ends (thousands of steps at
# a = 0.999, analog: lifetime 1 / (1 - a) collisions), so every case runs as two shards, one
# per core (simulate runs shards concurrently).
# a = 0.5: N = 2^19 -> se ~ 2.9e-4 (0.25 % of Rd); a = 0.9: N = 2^18 -> se ~ 9.6e-4 (0.23 %);
# a = 0.99: N = 2^17 -> se ~ 9e-4 (0.12 %); a = 0.999: N = 2^15 -> se ~ 1.6e-3 (0.18 %).
# Both estimators that square per photon: ``exits`` and the default ``hybrid`` (single
# scattering by first-vertex connections, multiple by the exit tally).  The tolerance is the
# Student-t cut alone, Sidak-corrected over the two z of a case (total and single): no fixed
# slack (3 se + 0.2 % of the value would let through a bias of 0.03-0.12 %, one to two se).
# ---------------------------------------------------------------------------------------------
H_CASES = [
    pytest.param(0.5, "weights", 2**19, 2, 16, id="a0.5-weights"),
    pytest.param(0.9, "analog", 2**18, 2, 16, id="a0.9-analog"),
    pytest.param(0.99, "weights", 2**17, 2, 16, id="a0.99-weights", marks=pytest.mark.slow),
    pytest.param(0.999, "analog", 2**15, 2, 16, id="a0.999-analog", marks=pytest.mark.slow),
]


@pytest.mark.parametrize("estimator", ["exits", "hybrid"])
@pytest.mark.parametrize("albedo, absorption, photons, shards, batches", H_CASES)
def test_rd_matches_h_function(albedo, absorption, photons, shards, batches, estimator, walk_spec, walk_stats):
    """Total Rd against 1 - sqrt(1-a) H(1) and single-scattering Rd against its closed form
    a (1 - ln 2) / 2, each within the t cut of its own standard error."""
    spec = walk_spec(
        1.0 - albedo, albedo, g=0.0, eta=1.0, n_r=1, max_mm=100.0, photons=photons, shards=shards,
        batches_per_shard=batches, estimator=estimator, absorption=absorption, seed=11 if estimator == "exits" else 12,
    )  # fmt: skip
    result = simulate(spec)
    rd, se = result.mean(f"{estimator}/Rd")[0], result.stderr(f"{estimator}/Rd")[0]
    dof = walk_stats.dof(result)

    exact = diffuse_reflectance_isotropic_matched(albedo)
    single = single_scattering_total(albedo, 0.0, 1.0, 0.0)
    assert math.isclose(single, albedo * (1.0 - math.log(2.0)) / 2.0, rel_tol=1e-9)  # closed form
    z = [(rd[TOTAL] - exact) / se[TOTAL], (rd[SINGLE] - single) / se[SINGLE]]
    print(f"{estimator} a = {albedo}: Rd total {rd[TOTAL]:.6f} +- {se[TOTAL]:.2e} vs {exact:.6f}: z = {z[0]:+.2f}; "
          f"single {rd[SINGLE]:.6f} +- {se[SINGLE]:.2e} vs {single:.6f}: z = {z[1]:+.2f}")  # fmt: skip
    walk_stats.assert_within(z, dof, f"{estimator} a = {albedo}: Rd total and single against the exact values")


# ---------------------------------------------------------------------------------------------
# Single scattering in an index-mismatched, anisotropic medium: eta = 1.3, g = 0.7, albedo 0.5,
# sigma_t = 2/mm (so mm and optical lengths differ), analog absorption (about 2 collisions per
# photon: cheap for the connection estimator, whose cost is (n_r + 1) kernels per vertex).
# Two configurations in one run: normal incidence (profiles) and 45 deg (total).
# Radial bins: 8 log bins out to 0.5 mm (1 optical mfp) plus the overflow ring [r_max, inf),
# each holding 3-13 % of the single flux Rd_single = 0.5 * 0.0088 = 0.0044 at normal incidence.
# Exits: N = 8e5 gives >= 130 single exits per ring (>= 20 per ring x cos bin): se 3-9 % per
# ring, 1.7 % on Rd_single.  Connections: N = 4e4 (8e4 vertices x 9 kernels): se ~1 % on Rd_single.
# ---------------------------------------------------------------------------------------------
SS_MEDIUM = dict(sigma_a=1.0, sigma_s=1.0, g=0.7, eta=1.3)
SS_SIGMA_T, SS_ALBEDO, SS_G, SS_ETA = 2.0, 0.5, 0.7, 1.3
SS_BINS = {
    "radial": {"count": 8, "max_mm": 0.5, "spacing": "log", "min_fraction": 0.05},
    "theta_s": {"count": 1},
    "cos_theta_o": {"count": 3},
    "phi_o": {"count": 2},
}
SS_PHOTONS = {"exits": 800_000, "connections": 40_000, "hybrid": 200_000}
ESTIMATORS = list(SS_PHOTONS)
NORMAL, OBLIQUE = 0, 1  # configurations (incidence 0 and 45 deg, one channel)


@pytest.fixture(scope="module")
def single_runs(walk_spec):
    """One run per estimator, with different seeds so they are independent."""
    runs = {}
    for seed, (est, photons) in enumerate(SS_PHOTONS.items(), start=21):
        spec = walk_spec(
            **SS_MEDIUM, bins=SS_BINS, incidence_deg=[0.0, 45.0], photons=photons, shards=2,
            batches_per_shard=16, estimator=est, absorption="analog", seed=seed,
        )  # fmt: skip
        runs[est] = simulate(spec)
    return runs


# The same medium index-matched (eta = 1), normal incidence only: no Fresnel boundary, so photons
# leave at grazing angles, where S = G / cos_o blew up (float32 cos_o rounded to 0) and the exit
# tally's w / cos_o has a logarithmically divergent second moment in the lowest cos bin.
SS1_PHOTONS = {"exits": 600_000, "connections": 30_000, "hybrid": 150_000}


@pytest.fixture(scope="module")
def matched_runs(walk_spec):
    runs = {}
    for seed, (est, photons) in enumerate(SS1_PHOTONS.items(), start=31):
        spec = walk_spec(
            **dict(SS_MEDIUM, eta=1.0), bins=SS_BINS, incidence_deg=[0.0], photons=photons, shards=2,
            batches_per_shard=16, estimator=est, absorption="analog", seed=seed,
        )  # fmt: skip
        runs[est] = simulate(spec)
    return runs


def _edges_to_infinity(result) -> np.ndarray:
    return np.append(result.layout.radial_mm[0], np.inf)


@pytest.mark.parametrize("est", ESTIMATORS)
def test_single_scattering_radial_profile(single_runs, est, walk_stats):
    """G_single per annulus (and beyond r_max) vs the quadrature; z-scores have unit spread."""
    result = single_runs[est]
    g = result.mean(f"{est}/radial_G")[NORMAL, SINGLE]
    se = result.stderr(f"{est}/radial_G")[NORMAL, SINGLE]
    exact = single_scattering_radial(_edges_to_infinity(result), SS_SIGMA_T, SS_ALBEDO, SS_G, SS_ETA)
    z = walk_stats.z(g, se, exact)
    dof = walk_stats.dof(result)
    walk_stats.assert_unit_spread(z, dof, f"{est}: single-scattering radial profile")
    walk_stats.assert_within(z, dof, f"{est}: single-scattering radial profile")
    # The annuli of [0, inf) sum to the total, which the walk reports as Rd single.
    total = single_scattering_total(SS_ALBEDO, SS_G, SS_ETA, 0.0)
    assert math.isclose(exact.sum(), total, rel_tol=1e-8)
    rd, rd_se = result.mean(f"{est}/Rd")[NORMAL, SINGLE], result.stderr(f"{est}/Rd")[NORMAL, SINGLE]
    walk_stats.assert_within([(rd - total) / rd_se], dof, f"{est}: Rd single at normal incidence")


@pytest.mark.parametrize("quantity", ["G", "S"])
@pytest.mark.parametrize("eta", [SS_ETA, 1.0])
@pytest.mark.parametrize("est", ESTIMATORS)
def test_single_scattering_directional(single_runs, matched_runs, est, eta, quantity, walk_stats):
    """G_single and S_single per (annulus, cos theta_o bin) vs the quadrature, summed over
    theta_s and phi_o, for eta = 1.3 and index-matched (eta = 1, the grazing bin included).

    S is compared as its raw sum (the radiance integrated over dA d omega: sum of w / cos_o),
    the table's S times A Omega.  At normal incidence a photon scattered once leaves radially
    (phi_o = 0), so all its flux is in phi_o bin 0, which is centred on phi_o = 0
    (workers.walk.conventions), and the others hold exactly 0.
    """
    result = (single_runs if eta == SS_ETA else matched_runs)[est]
    bins = result.mean(f"{est}/bins_{quantity}")[NORMAL, SINGLE]  # [n_r + 1, n_theta, n_cos, n_phi]
    bins_se = result.stderr(f"{est}/bins_{quantity}")[NORMAL, SINGLE]
    assert np.all(bins[..., 1:] == 0.0), "single scattering at normal incidence left a non-radial phi_o bin"
    g, se = bins[:, 0, :, 0], bins_se[:, 0, :, 0]  # n_theta = 1; phi_o bin 0 is the whole sum
    exact = single_scattering_radial_cos(
        _edges_to_infinity(result), result.layout.cos_o, SS_SIGMA_T, SS_ALBEDO, SS_G, eta, quantity=quantity
    )
    z = walk_stats.z(g, se, exact)
    dof = walk_stats.dof(result)
    what = f"{est}, eta {eta}: single-scattering {quantity} per (r, cos theta_o)"
    walk_stats.assert_unit_spread(z, dof, what)
    walk_stats.assert_within(z, dof, what)


@pytest.mark.parametrize("est", ESTIMATORS)
def test_single_scattering_total_oblique(single_runs, est, walk_stats):
    """Rd single at 45 deg incidence (Rd_single = 0.5 * 0.0110) vs the quadrature."""
    result = single_runs[est]
    assert result.configs.incidence_of(OBLIQUE) == 45.0
    rd, se = result.mean(f"{est}/Rd")[OBLIQUE, SINGLE], result.stderr(f"{est}/Rd")[OBLIQUE, SINGLE]
    exact = single_scattering_total(SS_ALBEDO, SS_G, SS_ETA, math.radians(45.0))
    walk_stats.assert_within([(rd - exact) / se], walk_stats.dof(result), f"{est}: Rd single at 45 deg")
