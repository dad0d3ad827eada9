"""schema.estimate: the closed forms of the cost model and how the shard estimate scales."""

from __future__ import annotations

import math

import pytest

from schema import parse_spec
from schema.estimate import (
    CONNECTION_SECONDS_PER_BIN, ESCAPE_C, EXIT_SECONDS_PER_STEP, estimate_shard, job_photons, seconds_per_step,
    steps_per_photon,
)

BASE = {"name": "e", "medium": {"sigma_a": 0.1, "sigma_s": 0.9, "g": 0.0, "eta": 1.0}, "photons": 10_000,
        "shards": 4, "estimator": "exits"}


def test_bench_media_a_little_above_their_measured_steps():
    # BENCHMARKS.md: 319.6 (M1) and 23.4 (M2) steps per photon.
    assert 319.6 <= steps_per_photon(0.99, 0.9) <= 1.3 * 319.6
    assert 23.4 <= steps_per_photon(0.9, 0.0) <= 1.5 * 23.4


def test_closed_form_matches_the_sum_it_integrates():
    a, g = 0.97, 0.3
    n_kill = math.log(1e-3) / math.log(a)
    t = 1 - g
    # midpoint sum of min(1, c / sqrt(1 + t k)) over k in [0, n_kill]
    n = 200_000
    h = n_kill / n
    total = sum(min(1.0, ESCAPE_C / math.sqrt(1 + t * (i + 0.5) * h)) for i in range(n)) * h
    assert steps_per_photon(a, g) == pytest.approx(total, rel=1e-4)


def test_limits_of_the_model():
    # never rouletted: escape or the path cap ends the walk, so the cap sets the sum's end
    assert steps_per_photon(1.0, 0.0, max_scatter=500) == pytest.approx(
        (ESCAPE_C**2 - 1) + 2 * ESCAPE_C * (math.sqrt(501) - ESCAPE_C))
    assert steps_per_photon(1.0, 0.0, max_scatter=5) == 5
    assert steps_per_photon(0.0, 0.0) == 1.0
    assert steps_per_photon(0.5, 0.0, analog=True) == pytest.approx(2.0)  # mean lifetime 1 / (1 - a)
    assert steps_per_photon(0.9999, 0.99999) <= 100_000
    assert steps_per_photon(0.99, 0.0) < steps_per_photon(0.999, 0.0) < steps_per_photon(0.9999, 0.0)


def test_shard_estimate_scales_with_photons_shards_angles_and_bins():
    spec = parse_spec(BASE)
    e = estimate_shard(spec)
    assert e.photons == 2500 and e.cpu_s == pytest.approx(e.steps * EXIT_SECONDS_PER_STEP)
    assert estimate_shard(parse_spec(dict(BASE, shards=8))).photons == 1250
    assert estimate_shard(parse_spec(dict(BASE, shards=3))).photons == 3334  # the largest shard
    two = parse_spec(dict(BASE, incidence_deg=[0, 30]))
    assert estimate_shard(two).steps == pytest.approx(2 * e.steps)
    conn = parse_spec(dict(BASE, estimator="connections", bins={"radial": {"count": 10}}))
    assert seconds_per_step(conn) == pytest.approx(EXIT_SECONDS_PER_STEP + 10 * CONNECTION_SECONDS_PER_BIN)
    assert seconds_per_step(conn, speed=2.0) == pytest.approx(seconds_per_step(conn) / 2)
    rgb = parse_spec(dict(BASE, medium={"sigma_a": [0.1, 0.2, 0.3], "sigma_s": 0.9, "eta": 1.0}))
    assert job_photons(rgb) == 30_000 and estimate_shard(rgb).photons == 7500


def test_a_sweep_counts_every_medium_and_its_shard_is_its_costliest_medium():
    sweep = parse_spec({"name": "sw", "sweep": {"albedo": [0.5, 0.99], "g": [0.0, 0.8], "eta": [1.3]},
                        "photons": 1000, "shards": 2, "estimator": "exits"})
    assert job_photons(sweep) == 1000 * 4
    e = estimate_shard(sweep)
    assert e.photons == 500  # one medium, one channel
    assert e.steps == pytest.approx(500 * max(steps_per_photon(a, g) for a in (0.5, 0.99) for g in (0.0, 0.8)))


def test_shared_walks_walk_each_group_once():
    spec = {"name": "sw", "sweep": {"albedo": [0.8, 0.9, 0.99], "g": [0.0, 0.8], "eta": [1.3]}, "photons": 1000,
            "shards": 2, "estimator": "exits"}
    assert parse_spec(spec).walk_groups() == [(0, 1, 2), (3, 4, 5)]
    assert job_photons(parse_spec(spec)) == 1000 * 2
    spec["sweep"]["walks"] = "independent"
    assert job_photons(parse_spec(spec)) == 1000 * 6
