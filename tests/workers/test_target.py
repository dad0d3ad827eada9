"""Runs to a target error: the decision (workers.fold.target) and simulate's stop after the first K
shards, bitwise the merge of those shards whatever the number of threads."""

from __future__ import annotations

import math

import numpy as np
import pytest

from schema import SimulationSpec
from workers.fold.merge import merge
from workers.fold.output import summary
from workers.run.simulate import run_shards, simulate
from workers.fold.target import MIN_DOF, target_status

MEDIUM = {"sigma_a": 0.1, "sigma_s": 0.9, "g": 0.0, "eta": 1.0}


def _spec(target, photons=6000, shards=30, estimator="exits", incidence=(0.0,)) -> SimulationSpec:
    return SimulationSpec.model_validate({
        "name": "target", "medium": MEDIUM, "photons": photons, "shards": shards, "batches_per_shard": 4,
        "estimator": estimator, "seed": 5, "incidence_deg": list(incidence), "target": target,
        "bins": {"radial": {"count": 6, "max_mm": 6.0, "spacing": "linear"}, "cos_theta_o": {"count": 2}, "phi_o": {"count": 1}},
    })  # fmt: skip


@pytest.fixture(scope="module")
def tallies():
    """Every shard of a two-angle exit run (no target: the decision is tested on its prefixes)."""
    spec = _spec(None, incidence=(0.0, 40.0))
    return spec, run_shards(spec, range(spec.shards), threads=1)


def test_decision_follows_the_worst_relative_error(tallies):
    spec, ts = tallies
    result = merge(spec, ts[:5], prefix=True)
    assert result.n_sum == sum(b - a for i in range(5) for a, b in [spec.shard_photon_range(i)])
    loose = spec.model_validate({**spec.model_dump(), "target": {"rel_stderr": 0.5}}).target
    status = target_status(result, loose)
    rd, se = result.mean("exits/Rd")[:, 2], result.stderr("exits/Rd")[:, 2]
    rel = se / rd
    assert len(status.checks) == 2 and status.photons == result.n_sum
    assert status.worst.rel_stderr == pytest.approx(rel.max(), rel=1e-12)
    for limit, reached in ((rel.max() * 1.001, True), (rel.max() * 0.999, False), (rel.min() * 0.999, False)):
        t = spec.model_validate({**spec.model_dump(), "target": {"rel_stderr": limit}}).target
        s = target_status(result, t)
        assert s.reached is reached
        assert sum(c.met for c in s.checks) == int(np.sum(rel <= limit))
    doc = status.as_dict()
    assert doc["reached"] and doc["checks"] == 2 and doc["worst"]["quantity"] == "Rd"


def test_radial_checks_cover_the_bins_in_range(tallies):
    spec, ts = tallies
    result = merge(spec, ts[:5], prefix=True)
    # Edges 0, 1, ..., 6 mm: [1, 4] holds bins [1, 2), [2, 3), [3, 4).
    t = spec.model_validate({**spec.model_dump(), "target": {"rel_stderr": 0.5, "radial": {"rel_stderr": 0.9, "r_min_mm": 1.0, "r_max_mm": 4.0}}}).target
    status = target_status(result, t)
    radial = [c for c in status.checks if c.quantity == "Rd_r"]
    assert sorted({(c.r_lo_mm, c.r_hi_mm) for c in radial}) == [(1.0, 2.0), (2.0, 3.0), (3.0, 4.0)]
    assert len(radial) == 3 * result.configs.n
    se = result.stderr("exits/radial_G")[:, 2, 1:4]
    m = result.mean("exits/radial_G")[:, 2, 1:4]
    assert max(c.rel_stderr for c in radial) == pytest.approx(float((se / m).max()), rel=1e-12)


def test_no_estimate_never_meets_a_target(tallies):
    spec, ts = tallies
    result = merge(spec, ts[:2], prefix=True)
    result.stats["exits/Rd"][0][:] = 0.0  # as if no photon had left
    status = target_status(result, spec.model_validate({**spec.model_dump(), "target": {"rel_stderr": 0.99}}).target)
    assert not status.reached and math.isinf(status.worst.ratio)


def test_simulate_stops_at_the_first_prefix_meeting_the_target(tallies):
    spec0, ts = tallies
    target = {"rel_stderr": 0.03}
    spec = _spec(target, incidence=(0.0, 40.0))
    # The first K whose merge meets the target, found by hand from the same shards.
    k = next(k for k in range(1, spec.shards + 1) if target_status(merge(spec0, ts[:k], prefix=True), spec.target).reached)
    assert 1 < k < spec.shards, f"choose a target that stops inside the run (K = {k})"
    results = [simulate(spec, threads=1), simulate(spec, threads=2), simulate(spec, threads=3)]
    expected = merge(spec0, ts[:k], prefix=True)
    for r in results:
        assert len(r.shard_info) == k and r.target.reached and r.n_sum == expected.n_sum
        for name, arrays in expected.stats.items():
            for a, b in zip(arrays, r.stats[name]):
                assert np.array_equal(a, b), name
    doc = summary(results[0])
    assert doc["target"]["reached"] and doc["target"]["photons"] == expected.n_sum
    assert doc["run"]["photons_per_config"] == expected.n_sum and doc["run"]["shards"] == k
    assert all(row["photons"] == expected.n_sum for row in doc["results"])


@pytest.mark.parametrize("estimator, first_k", [("connections", 8), ("exits", 2)])
def test_no_target_is_met_on_fewer_than_30_units(estimator, first_k):
    """A loose target that the first shard's value meets still waits for 30 units (29 dof):
    8 shards of 4 batches for the batch-based connection errors, 2 shards of 20 photons for
    the per-photon exit errors; simulate stops at exactly that K."""
    spec = _spec({"rel_stderr": 0.9}, photons=600, shards=30, estimator=estimator)
    ts = run_shards(spec, range(first_k + 1), threads=1)
    for k in range(1, first_k + 1):
        status = target_status(merge(spec, ts[:k], prefix=True), spec.target)
        dof = merge(spec, ts[:k], prefix=True).dof(f"{estimator}/Rd")
        assert dof == (4 * k - 1 if estimator == "connections" else 20 * k - 1)
        # Every value is within the limit from the first shard on; only the units are missing.
        assert all(c.rel_stderr <= c.limit and c.dof == dof for c in status.checks), status.checks
        assert status.reached is (dof >= MIN_DOF) is (k == first_k), (k, dof)
        if not status.reached:
            assert math.isinf(status.worst.ratio) and status.as_dict()["worst"]["dof"] == dof
    result = simulate(spec, threads=1)
    assert len(result.shard_info) == first_k and result.target.reached and result.target.worst.dof == result.dof(f"{estimator}/Rd")


def test_unreachable_target_runs_every_shard():
    spec = _spec({"rel_stderr": 1e-6}, photons=600, shards=3)
    result = simulate(spec, threads=2)
    assert len(result.shard_info) == 3 and result.n_sum == 600 and not result.target.reached
    plain = simulate(_spec(None, photons=600, shards=3), threads=1)
    for name, arrays in plain.stats.items():
        for a, b in zip(arrays, result.stats[name]):
            assert np.array_equal(a, b), name


def test_merge_refuses_what_is_not_the_whole_run_or_a_prefix(tallies):
    from workers.fold.merge import Fold, MergeError

    spec, ts = tallies
    with pytest.raises(MergeError, match="shards 0..29"):
        merge(spec, ts[:3])
    with pytest.raises(MergeError, match="for some K"):
        merge(spec, ts[1:4], prefix=True)
    with pytest.raises(MergeError, match="for some K"):
        merge(spec, [], prefix=True)
    fold = Fold(spec)
    with pytest.raises(MergeError, match="expected shard 0"):
        fold.add(ts[1])
    fold.add(ts[0])
    with pytest.raises(MergeError, match="expected shard 1"):
        fold.add(ts[0])
