"""Honest error bars in every bin: two runs with different seeds agree within their own errors.

For each estimator, two independent runs (seeds 1 and 2) of one spec; over every entry where
*both* runs saw at least MIN_EVENTS contributing events, z = (a - b) / sqrt(se_a^2 + se_b^2)
must have unit spread (sum z^2 in its chi-square band, every |z| under the Sidak-corrected
cut).  Families of nearly independent entries are tested apart: G of every bin (inside and
beyond r_max), S of every bin, Rd(r) of every ring, each for single and multiple scattering
(``total`` is their sum, and G, S and the rings share their events).  No entry is chosen by
its estimated error: near-field bins, a few tenths of a mean free path across, are in.  Entries
of one run with no event have a NaN error bar and are reported as unresolved.

The two runs are independent, so the test holds exactly when both are unbiased for the same
quantity and both error bars are right; an error bar that is too small in sparse bins (a batch
estimate resting on a handful of events, a low estimate coming with a low error) shows up as
excess spread.

Two media: eta = 1.3 with analog absorption, and the index-matched eta = 1 with the default
weights absorption (Russian roulette).  At eta = 1 the exit tally's S in the lowest cos(theta_o)
bin sums w / cos_o over exits whose density goes like cos_o near grazing, so its second moment
diverges logarithmically (workers/walk/harvest.py); exits score both components that way and the
hybrid its multiple scattering.  That grazing bin is its own entry here (3 cos bins) and must be
among the tested entries.  What this two-run test can and cannot see there: the difference of two
self-normalised estimates stays symmetric with unit spread (in a model of the bin, 280 events:
var z 1.00 +- 0.03), while one run's t against the truth is skewed (mean -0.27, var 1.16, 1 %
below -3 instead of 0.13 %: a run missing the rare grazing exits is low and has a low error bar),
fading only like 1 / ln N.  The walk shows the same: over 20 exit runs of the eta = 1 medium
below, t of each run's grazing multiple-scattering S against the mean of the other 19 has mean
-0.20, var 1.26, skew -0.56 (G in the same bins: -0.04, 0.85, +0.17).  Only a comparison with a
reference sees it, not this test; the tables therefore flag those bins and give them no error bar
(bins.parquet ``S_infinite_variance``, tests/workers/test_output.py).
"""

from __future__ import annotations

import numpy as np
import pytest

from workers.run.simulate import simulate

MIN_EVENTS = 30
# g = 0.9, albedo 0.9, sigma_t = 1/mm (~10 collisions per photon): eta = 1.3 with analog
# absorption, and eta = 1 with Russian roulette (the default), whose grazing cos bin has the
# log-divergent S; 8 log rings from 0.05 mm (a twentieth of a mean free path) to 10 mm, 3 cos_o
# bins (the grazing one [0, 1/3) apart) x 2 phi_o bins.
MEDIA = {
    "eta1.3-analog": (dict(sigma_a=0.1, sigma_s=0.9, g=0.9, eta=1.3), "analog"),
    "eta1-roulette": (dict(sigma_a=0.1, sigma_s=0.9, g=0.9, eta=1.0), "weights"),
}
GRAZING = 0  # cos_o bin index of [0, 1/3)
BINS = {
    "radial": {"count": 8, "max_mm": 10.0, "spacing": "log", "min_fraction": 0.005},
    "theta_s": {"count": 1},
    "cos_theta_o": {"count": 3},
    "phi_o": {"count": 2},
}
# exits: 1e5, so that at eta 1.3 (analog) the single-scattering rings (~25 events per 6e4 photons) and
# the third multiple-scattering ring (~30) clear MIN_EVENTS with a margin: >= 8 entries are tested.
PHOTONS = {"exits": 100_000, "hybrid": 60_000, "connections": 6_000}


FAMILIES = ("bins_G", "bins_S", "radial_G")


def _z(a, b, name: str) -> tuple[np.ndarray, np.ndarray, int]:
    """z over the single and multiple entries of `name` with >= MIN_EVENTS events in both runs,
    the mask of those entries, and the number of entries unresolved (no event) in either."""
    ea, eb = a.events(name)[:, :2], b.events(name)[:, :2]
    for r in (a, b):
        assert np.array_equal(np.isnan(r.stderr(name)), r.events(name) == 0), f"{name}: NaN error bars exactly where no event"
    keep = (ea >= MIN_EVENTS) & (eb >= MIN_EVENTS)
    z = (a.mean(name) - b.mean(name))[:, :2] / np.sqrt(a.stderr(name)[:, :2] ** 2 + b.stderr(name)[:, :2] ** 2)
    return z[keep], keep, int(np.sum((ea == 0) | (eb == 0)))


@pytest.fixture(scope="module", params=[(m, e) for m in MEDIA for e in PHOTONS], ids=lambda p: f"{p[0]}-{p[1]}")
def seed_pair(request, walk_spec):
    medium, est = request.param
    fields, absorption = MEDIA[medium]
    runs = [
        simulate(walk_spec(**fields, bins=BINS, photons=PHOTONS[est], shards=2, batches_per_shard=16, estimator=est,
                           absorption=absorption, seed=seed))
        for seed in (1, 2)
    ]  # fmt: skip
    return medium, est, runs


@pytest.mark.parametrize("family", FAMILIES)
def test_two_seeds_agree_within_their_errors_in_every_bin(seed_pair, family, walk_stats):
    medium, est, (a, b) = seed_pair
    z, keep, unresolved = _z(a, b, f"{est}/{family}")
    dof = min(walk_stats.dof(a), walk_stats.dof(b))
    what = f"{medium} {est} {family}: {len(z)} entries with >= {MIN_EVENTS} events in both runs ({unresolved} unresolved in one)"
    assert len(z) >= 8, what  # enough entries for the spread to say something
    if family.startswith("bins_") and MEDIA[medium][0]["eta"] == 1.0:
        # At eta = 1 the grazing cos_o bin is tested, in multiple scattering (where every estimator
        # has events there; at eta = 1.3 the Fresnel transmittance leaves it nearly empty), in at
        # least 4 of its (r, phi_o) entries: keep is [cfg, comp, r, theta_s, cos_o, phi_o].
        grazing = int(np.sum(keep[:, 1, :, :, GRAZING]))
        assert grazing >= 4, f"{what}: only {grazing} grazing-bin multiple-scattering entries tested"
    walk_stats.assert_unit_spread(z, dof, what, n_tests=len(FAMILIES))
    walk_stats.assert_within(z, dof, what)
