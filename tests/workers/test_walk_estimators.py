"""The exit and connection estimators measure the same G per bin (docs/architecture.md, "Estimators").

Each comparison runs the two estimators in separate walks with different seeds, so the two
estimates are independent and z = (a - b) / sqrt(se_a^2 + se_b^2) has unit spread exactly when
both are unbiased and both error bars are honest.  (In one ``both`` run the estimators share
photons: a photon that leaves near x_o also tends to have connected there, a positive covariance
that shrinks the variance of the difference, so se_a^2 + se_b^2 would overstate it and the
spread test would only be conservative.  Separate seeds avoid that.)  A last test checks that
``both`` tallies exactly what the single-estimator runs tally.

Medium: eta = 1.3, g = 0.9, albedo 0.9 (reduced albedo 0.47), sigma_t = 1/mm; six radial bins
log spaced from 1 mm out to 20 mm (~4 transport mean free paths, 5.3 mm), plus [0, 1 mm).
Rd_multiple ~0.033, Rd_single ~0.002.  Per-bin relative se of the multiple component: exits
~10-20 / sqrt(N) (N = 1e5: 3-6 %), connections ~6-15 / sqrt(N) (N = 2e4: 4-10 %); the connection
estimator costs ~60 vertices x 7 kernels per photon in weights mode (~10 vertices in analog
mode), which sets N.

Bins are compared wherever both runs saw at least MIN_EVENTS contributing events (the tables'
``events`` column), never chosen by their estimated error (a cut correlated with the estimate):
near-field bins are in.  The hybrid estimator (the default) is compared with both for single
scattering and with the connection estimator for multiple scattering (its multiple scattering is
the exit tally itself, so comparing it with ``exits`` would test nothing independent).  Single
scattering is compared at 45 deg, where the exit run is large enough; at normal incidence
test_walk_exact checks it bin by bin against the exact profile for every estimator.
"""

from __future__ import annotations

import numpy as np
import pytest

from workers.run.simulate import simulate

MEDIUM = dict(sigma_a=0.1, sigma_s=0.9, g=0.9, eta=1.3)
MIN_EVENTS = 30  # events in each run for a bin to be compared
MIN_BINS = {"single": 2, "multiple": 5}  # fewer compared bins would say little

# (incidence, radial bins, first radial edge / r_max, n_theta, absorption, exit photons,
# connection photons)
CASES = {
    "normal": ([0.0], 6, 0.05, 1, "weights", 100_000, 20_000),
    "oblique45": ([45.0], 6, 0.05, 4, "analog", 500_000, 40_000),
}


def _spec(walk_spec, case: str, estimator: str, photons: int, seed: int):
    incidence, n_r, min_fraction, n_theta, absorption, _, _ = CASES[case]
    bins = {
        "radial": {"count": n_r, "max_mm": 20.0, "spacing": "log", "min_fraction": min_fraction},
        "theta_s": {"count": n_theta},
        "cos_theta_o": {"count": 1},
        "phi_o": {"count": 1},
    }
    return walk_spec(
        **MEDIUM, bins=bins, incidence_deg=incidence, photons=photons, shards=2, batches_per_shard=16,
        estimator=estimator, absorption=absorption, seed=seed,
    )  # fmt: skip


@pytest.fixture(scope="module")
def estimator_runs(walk_spec):
    runs = {}
    for i, (case, (*_, n_exit, n_conn)) in enumerate(CASES.items()):
        runs[case] = {
            "exits": simulate(_spec(walk_spec, case, "exits", n_exit, seed=51 + 3 * i)),
            "connections": simulate(_spec(walk_spec, case, "connections", n_conn, seed=52 + 3 * i)),
            "hybrid": simulate(_spec(walk_spec, case, "hybrid", n_exit // 2, seed=53 + 3 * i)),
        }
    return runs


def _spatial(result, est: str, comp: int):
    """G, its se and events per spatial bin (r incl. beyond r_max, theta_s): one direction bin each."""
    name = f"{est}/bins_G"
    return result.mean(name)[0, comp, ..., 0, 0], result.stderr(name)[0, comp, ..., 0, 0], result.events(name)[0, comp, ..., 0, 0]


PAIRS = [("exits", "connections"), ("hybrid", "exits"), ("hybrid", "connections")]
# The hybrid's multiple scattering *is* the exit tally (same algorithm, other photons), so for
# multiple scattering it is checked against the connection estimator, an independent method,
# not against ``exits``; its single scattering (first-vertex connections) against both.
PER_BIN = [
    (case, comp, comp_name, a, b)
    for case, comp, comp_name in (("normal", 1, "multiple"), ("oblique45", 1, "multiple"), ("oblique45", 0, "single"))
    for a, b in PAIRS
    if not (comp_name == "multiple" and (a, b) == ("hybrid", "exits"))
]


@pytest.mark.parametrize("case, comp, comp_name, a, b", PER_BIN)
def test_estimators_agree_per_bin(estimator_runs, case, comp, comp_name, a, b, walk_stats):
    ra, rb = estimator_runs[case][a], estimator_runs[case][b]
    g_a, se_a, ev_a = _spatial(ra, a, comp)
    g_b, se_b, ev_b = _spatial(rb, b, comp)
    keep = (ev_a >= MIN_EVENTS) & (ev_b >= MIN_EVENTS)
    assert keep.sum() >= MIN_BINS[comp_name], f"only {keep.sum()} bins with {MIN_EVENTS} events: {ev_a} / {ev_b}"
    z = walk_stats.z(g_a[keep], se_a[keep], g_b[keep], se_b[keep])
    dof = min(walk_stats.dof(ra), walk_stats.dof(rb))
    what = f"{case}, {comp_name}: {a} vs {b} over {keep.sum()} bins"
    walk_stats.assert_unit_spread(z, dof, what, n_tests=len(PAIRS))
    walk_stats.assert_within(z, dof, what)


@pytest.mark.parametrize("a, b", PAIRS)
@pytest.mark.parametrize("case", list(CASES))
def test_estimators_agree_on_rd(estimator_runs, case, a, b, walk_stats):
    ra, rb = estimator_runs[case][a], estimator_runs[case][b]
    z = walk_stats.z(ra.mean(f"{a}/Rd")[0], ra.stderr(f"{a}/Rd")[0], rb.mean(f"{b}/Rd")[0], rb.stderr(f"{b}/Rd")[0])
    walk_stats.assert_within(z, min(walk_stats.dof(ra), walk_stats.dof(rb)), f"{case}: {a} vs {b}, Rd single, multiple, total")


def test_both_tallies_what_each_estimator_tallies(walk_spec):
    """estimator="both" gives the exit tally of an exits run and the connection tally of a
    connections run with the same seed: the walk draws the same numbers for every photon."""
    both = simulate(_spec(walk_spec, "oblique45", "both", 2000, seed=59))
    for est in ("exits", "connections"):
        alone = simulate(_spec(walk_spec, "oblique45", est, 2000, seed=59))
        assert alone.estimators == [est]
        for q in ("bins_G", "bins_S", "radial_G", "Rd"):
            name = f"{est}/{q}"
            # Summation order may differ (harvest timing), so equal to rounding, not bitwise.
            np.testing.assert_allclose(both.mean(name), alone.mean(name), rtol=1e-10, atol=1e-15, err_msg=name)
            np.testing.assert_allclose(both.stderr(name), alone.stderr(name), rtol=1e-6, atol=1e-13, err_msg=name)
        for name in ("walk/absorbed", "walk/truncated"):
            np.testing.assert_allclose(both.mean(name), alone.mean(name), rtol=1e-10, atol=1e-15, err_msg=name)
