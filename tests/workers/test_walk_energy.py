"""Energy balance of the walk: Rd (beyond r_max included) + absorbed + truncated = 1 - R_spec.

Per photon the balance is exact in analog mode (the weight 1 - R_spec is never split) and for
albedo 1 (nothing is absorbed), up to the float32 rounding of that weight; with weights and
Russian roulette it holds in expectation only, and for the connection estimator Rd is a
different estimate from the walk's absorbed weight.  The engine reports a standard error per
quantity but not of their sum, whose terms are strongly correlated (what is not reflected is
absorbed), so the error bar of the sum comes from the spread of the per-shard sums: the shards
are independent, 16 of them, t with 15 degrees of freedom.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from tests.reference.fresnel import fresnel_reflectance
from workers.fold.merge import merge
from workers.fold.output import summary
from workers.run.shard import run_shard

TOTAL = 2
SHARDS = 16
INCIDENCE = [0.0, 60.0]
# float32 weight 1 - R_spec: relative rounding 6e-8; float64 sums of 1e5 photons add ~1e-11.
EXACT_TOL = 1e-6


def _run(spec):
    tallies = [run_shard(spec, i) for i in range(spec.shards)]
    return tallies, merge(spec, tallies)


def _energy_per_shard(tallies, est: str, cfg: int) -> np.ndarray:
    """(Rd + absorbed + truncated) per photon, one value per shard."""
    out = []
    for t in tallies:
        s = t.stats[f"{est}/Rd"][0][cfg, TOTAL] + t.stats["walk/absorbed"][0][cfg] + t.stats["walk/truncated"][0][cfg]
        out.append(s / t.n_sum)
    return np.array(out)


# Medium: albedo 0.8, g = 0.5, sigma_t = 1/mm; radial bins out to 2 mm, so part of Rd is beyond
# r_max.  Weights: ~30 collisions per photon (roulette below 1e-3 = 0.8^31); the sum's per-photon
# sd is the roulette noise, ~1e-3, so N = 16384 resolves an energy leak of ~1e-4.  The
# connection estimator (eta = 1.4 runs) costs 5 kernels per vertex with 4 radial bins.
ENERGY_CASES = {
    ("weights", 1.0): dict(estimator="exits", photons=2**15, seed=41),
    ("analog", 1.0): dict(estimator="exits", photons=2**15, seed=42),
    ("weights", 1.4): dict(estimator="both", photons=2**14, seed=43),
    ("analog", 1.4): dict(estimator="both", photons=2**15, seed=44),
}


@pytest.fixture(scope="module")
def energy_runs(walk_spec):
    runs = {}
    for (absorption, eta), kw in ENERGY_CASES.items():
        spec = walk_spec(
            0.2, 0.8, g=0.5, eta=eta, n_r=4, max_mm=2.0, incidence_deg=INCIDENCE,
            shards=SHARDS, batches_per_shard=2, absorption=absorption, **kw,
        )  # fmt: skip
        runs[absorption, eta] = _run(spec)
    return runs


@pytest.mark.parametrize("absorption, eta", list(ENERGY_CASES))
def test_energy_balance_within_errors(energy_runs, absorption, eta, walk_stats):
    tallies, result = energy_runs[absorption, eta]
    z = []
    for est in result.estimators:
        for cfg in range(result.configs.n):
            per_shard = _energy_per_shard(tallies, est, cfg)
            expected = 1.0 - result.configs.r_spec[cfg]
            mean = result.mean(f"{est}/Rd")[cfg, TOTAL] + result.mean("walk/absorbed")[cfg] + result.mean("walk/truncated")[cfg]
            assert math.isclose(mean, per_shard.mean(), rel_tol=1e-12)  # equal shards: same mean
            se = per_shard.std(ddof=1) / math.sqrt(len(per_shard))
            if se == 0.0:  # every photon balanced exactly (analog exit tally)
                assert abs(mean - expected) <= EXACT_TOL, f"{est} cfg {cfg}: {mean} vs {expected}"
                continue
            z.append((mean - expected) / se)
    if z:
        walk_stats.assert_within(z, SHARDS - 1, f"{absorption}, eta {eta}: Rd + absorbed + truncated - (1 - R_spec)")


@pytest.mark.parametrize("eta", [1.0, 1.4])
def test_energy_balance_exact_in_analog_mode(energy_runs, eta):
    """Analog exit tally: every photon's weight 1 - R_spec ends exited or absorbed, exactly."""
    _, result = energy_runs["analog", eta]
    rd = result.mean("exits/Rd")[:, TOTAL]
    radial = result.mean("exits/radial_G")[:, TOTAL]  # last index: beyond r_max
    assert np.all(radial[:, -1] > 0), "the test needs flux beyond r_max"
    np.testing.assert_allclose(radial.sum(axis=1), rd, rtol=1e-12)
    balance = rd + result.mean("walk/absorbed") + result.mean("walk/truncated")
    np.testing.assert_allclose(balance, 1.0 - result.configs.r_spec, rtol=0, atol=EXACT_TOL)


@pytest.mark.parametrize("eta", [1.0, 1.4])
def test_analog_and_weights_agree(energy_runs, eta, walk_stats):
    """Independent runs (different seeds) in the two absorption modes agree within errors."""
    _, a = energy_runs["analog", eta]
    _, w = energy_runs["weights", eta]
    z = []
    for est in sorted(set(a.estimators) & set(w.estimators)):
        for name in (f"{est}/Rd", f"{est}/radial_G"):
            z.append(walk_stats.z(a.mean(name), a.stderr(name), w.mean(name), w.stderr(name)).ravel())
    z.append(walk_stats.z(a.mean("walk/absorbed"), a.stderr("walk/absorbed"), w.mean("walk/absorbed"), w.stderr("walk/absorbed")))
    z = np.concatenate(z)
    z = z[np.isfinite(z)]  # components that are exactly 0 in both (none expected; guards 0/0)
    dof = min(walk_stats.dof(a), walk_stats.dof(w))
    walk_stats.assert_within(z, dof, f"eta {eta}: analog vs weights")


@pytest.mark.parametrize("absorption", ["weights", "analog"])
def test_truncation_is_reported_and_energy_closes(absorption, walk_spec, walk_stats):
    """Albedo 1 with a path cap of 10 scatterings: a visible share is truncated, none lost.

    With albedo 1 nothing is absorbed and the weight never changes, so per photon
    Rd + truncated = 1 - R_spec exactly.  The truncated share (~0.4 here) is many standard
    errors above 0 and appears in the summary.
    """
    spec = walk_spec(
        0.0, 1.0, g=0.0, eta=1.4, n_r=4, max_mm=3.0, incidence_deg=INCIDENCE, photons=4096,
        shards=2, batches_per_shard=16, estimator="exits", absorption=absorption, max_scatter=10, seed=45,
    )  # fmt: skip
    _, result = _run(spec)
    truncated, se = result.mean("walk/truncated"), result.stderr("walk/truncated")
    assert np.all(truncated > walk_stats.z_limit(2, walk_stats.dof(result)) * se), f"truncated {truncated} +- {se}"
    assert np.all(result.mean("walk/absorbed") == 0.0)
    balance = result.mean("exits/Rd")[:, TOTAL] + truncated
    np.testing.assert_allclose(balance, 1.0 - result.configs.r_spec, rtol=0, atol=EXACT_TOL)
    rows = [r for r in summary(result)["results"] if r["component"] == "total"]
    assert [r["truncated"] for r in rows] == pytest.approx(truncated.tolist(), rel=1e-12)
    assert all(r["truncated_stderr"] > 0 for r in rows)


def test_r_spec_is_the_fresnel_formula(energy_runs):
    """R_spec per configuration and in the summary equals the exact dielectric Fresnel formula."""
    for (absorption, eta), (_, result) in energy_runs.items():
        expected = [fresnel_reflectance(math.cos(math.radians(t)), eta) for t in INCIDENCE]
        np.testing.assert_allclose(result.configs.r_spec, expected, rtol=1e-12, atol=1e-15)
        rows = summary(result)["results"]
        got = {r["incidence_deg"]: r["R_spec"] for r in rows}
        assert got == pytest.approx(dict(zip(INCIDENCE, expected)), rel=1e-12, abs=1e-15)
    assert fresnel_reflectance(1.0, 1.4) == pytest.approx((0.4 / 2.4) ** 2, rel=1e-12)
