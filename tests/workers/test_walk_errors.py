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
"""

from __future__ import annotations

import numpy as np
import pytest

from workers.simulate import simulate

MIN_EVENTS = 30
# eta = 1.3, g = 0.9, albedo 0.9, sigma_t = 1/mm, analog absorption (~10 collisions per photon);
# 8 log rings from 0.05 mm (a twentieth of a mean free path) to 10 mm, 3 x 2 direction bins.
MEDIUM = dict(sigma_a=0.1, sigma_s=0.9, g=0.9, eta=1.3)
BINS = {
    "radial": {"count": 8, "max_mm": 10.0, "spacing": "log", "min_fraction": 0.005},
    "theta_s": {"count": 1},
    "cos_theta_o": {"count": 3},
    "phi_o": {"count": 2},
}
PHOTONS = {"exits": 60_000, "hybrid": 60_000, "connections": 6_000}


FAMILIES = ("bins_G", "bins_S", "radial_G")


def _z(a, b, name: str) -> tuple[np.ndarray, int]:
    """z over the single and multiple entries of `name` with >= MIN_EVENTS events in both runs,
    and the number of entries unresolved (no event) in either."""
    ea, eb = a.events(name)[:, :2], b.events(name)[:, :2]
    for r in (a, b):
        assert np.array_equal(np.isnan(r.stderr(name)), r.events(name) == 0), f"{name}: NaN error bars exactly where no event"
    keep = (ea >= MIN_EVENTS) & (eb >= MIN_EVENTS)
    z = (a.mean(name) - b.mean(name))[:, :2] / np.sqrt(a.stderr(name)[:, :2] ** 2 + b.stderr(name)[:, :2] ** 2)
    return z[keep], int(np.sum((ea == 0) | (eb == 0)))


@pytest.fixture(scope="module", params=list(PHOTONS))
def seed_pair(request, walk_spec):
    est = request.param
    runs = [
        simulate(walk_spec(**MEDIUM, bins=BINS, photons=PHOTONS[est], shards=2, batches_per_shard=16, estimator=est,
                           absorption="analog", seed=seed))
        for seed in (1, 2)
    ]  # fmt: skip
    return est, runs


@pytest.mark.parametrize("family", FAMILIES)
def test_two_seeds_agree_within_their_errors_in_every_bin(seed_pair, family, walk_stats):
    est, (a, b) = seed_pair
    z, unresolved = _z(a, b, f"{est}/{family}")
    dof = min(walk_stats.dof(a), walk_stats.dof(b))
    what = f"{est} {family}: {len(z)} entries with >= {MIN_EVENTS} events in both runs ({unresolved} unresolved in one)"
    assert len(z) >= 8, what  # enough entries for the spread to say something
    walk_stats.assert_unit_spread(z, dof, what, n_tests=len(FAMILIES))
    walk_stats.assert_within(z, dof, what)
