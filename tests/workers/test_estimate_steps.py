"""The cost model of schema.estimate against walked photons: mean steps per photon measured by the
shard runner (eager walk) for media from low to high albedo and backward to forward scattering.

The model claims a factor of two (module docstring of schema.estimate; it is used for limits, not
physics); the sample means here have relative errors of about 10 % at these photon counts
(path lengths are heavy-tailed), far inside that band.
"""

from __future__ import annotations

import pytest

from schema import parse_spec
from schema.estimate import steps_per_photon
from workers.run.shard import run_shard

MEDIA = {
    "M1": ({"sigma_a": 0.1, "sigma_s": 9.9, "g": 0.9, "eta": 1.3}, 600),
    "M2": ({"sigma_a": 0.1, "sigma_s": 0.9, "g": 0.0, "eta": 1.0}, 6000),
    "high-albedo": ({"sigma_a": 0.002, "sigma_s": 0.998, "g": 0.5, "eta": 1.4}, 400),
    "low-albedo": ({"sigma_a": 0.7, "sigma_s": 0.3, "g": -0.3, "eta": 1.5}, 6000),
    "forward": ({"sigma_a": 0.01, "sigma_s": 0.99, "g": 0.95, "eta": 1.3}, 400),
}


@pytest.mark.parametrize("name", sorted(MEDIA))
def test_steps_per_photon_model_within_factor_two(name):
    medium, photons = MEDIA[name]
    spec = parse_spec({"name": "steps", "medium": medium, "photons": photons, "shards": 1, "batches_per_shard": 2,
                       "estimator": "exits", "seed": 3,
                       "bins": {"radial": {"count": 4}, "cos_theta_o": {"count": 1}, "phi_o": {"count": 1}}})
    measured = run_shard(spec, 0).info["photon_steps"] / photons
    c = spec.channels()[0]
    model = steps_per_photon(c.albedo, c.g)
    assert 0.5 <= model / measured <= 2.0, (name, measured, model)
