"""What a spec will cost before it runs: photons, walk steps and CPU seconds per shard (torch-free).

The service refuses a submission whose estimate exceeds a configured limit, so the estimate must
come from the spec alone, in microseconds, without torch. It is a model calibrated on the
walk-throughput figures of BENCHMARKS.md (``bssrdf bench``, this project's 2-core AMD EPYC with
AVX-512, compiled walk), written out so it can be checked:

    cpu_s(shard) = sum over configurations c (channel x incidence angle) of
                   n_photons(shard) * steps_per_photon(albedo_c, g_c) * seconds_per_step(spec)

**Steps per photon.** With weights and Russian roulette a photon's weight after k collisions is
a^k (a the single-scattering albedo), so it is rouletted after about

    n_kill = ln(w_min) / ln(a)            (w_min = 1e-3: workers.walk.walk.WalkParams)

steps (analog absorption: its mean lifetime 1 / (1 - a)); a = 1 never stops before the path cap
``max_scatter``. Escape cuts the walk short: from a half-space the probability of a walk still
inside after k steps falls like a first-passage time, P(N > k) ~ c / sqrt(1 + (1 - g) k) (k (1 - g)
transport steps), capped at 1. Summed up to n_kill:

    steps = k0 + (2 c / (1 - g)) * (sqrt(1 + (1 - g) n_kill) - c),   k0 = (c^2 - 1) / (1 - g)

(``steps = n_kill`` when n_kill < k0). c = 2.5 puts the estimate a little above both benchmark
media: M1 (a 0.99, g 0.9, eta 1.3) 345 against 319.6 measured, M2 (a 0.9, g 0, eta 1) 33.5
against 23.4 (tests/schema/test_estimate.py measures more media).

**Seconds per step** (per core): the exit tally's slower medium, 6.32e7 steps/s (M2) -> 1.58e-8 s;
connections add one kernel evaluation per spatial bin (n_r x n_theta_s) at every vertex:
(1 / 7.15e5 - 1 / 8.15e7) / 48 = 2.9e-8 s per bin (M1, 48 radial bins, the slower of M1 and M2).
``both`` costs what connections cost (the exit tally rides on the same walk). A slower fleet
scales every figure with ``speed`` (> 1: faster machines).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from .spec import SimulationSpec

__all__ = [
    "ShardEstimate", "steps_per_photon", "seconds_per_step", "estimate_shard", "job_photons",
    "EXIT_SECONDS_PER_STEP", "CONNECTION_SECONDS_PER_BIN", "ESCAPE_C", "ROULETTE_W_MIN",
]

EXIT_SECONDS_PER_STEP = 1.0 / 6.32e7
"""Seconds per walk step with the exit tally (BENCHMARKS.md, M2 exits, one core)."""
CONNECTION_SECONDS_PER_BIN = 2.9e-8
"""Extra seconds per step and spatial bin with next-event connections (BENCHMARKS.md, M1)."""
ESCAPE_C = 2.5
"""Constant of the half-space survival model P(N > k) ~ c / sqrt(1 + (1 - g) k)."""
ROULETTE_W_MIN = 1e-3
"""Roulette threshold of the walk (workers.walk.walk.WalkParams.w_min)."""


@dataclass(frozen=True)
class ShardEstimate:
    """The largest shard of a spec: photons it walks, steps and CPU seconds on one core."""

    photons: int  # photons of the shard, every channel and incidence angle included
    steps: float
    cpu_s: float


def steps_per_photon(albedo: float, g: float, *, analog: bool = False, max_scatter: int = 100_000) -> float:
    """Estimated mean interaction steps of one photon (see the module docstring), <= max_scatter."""
    # Guards: a = 1 never rouletted (cap instead); a = 0 dies at its first collision.
    if albedo >= 1.0:
        n_kill = float(max_scatter)
    elif albedo <= 0.0:
        n_kill = 1.0
    elif analog:
        n_kill = 1.0 / (1.0 - albedo)
    else:
        n_kill = math.log(ROULETTE_W_MIN) / math.log(albedo)
    n_kill = min(n_kill, float(max_scatter))
    t = max(1.0 - g, 1e-6)  # g -> 1: forward scattering, transport steps vanish (kept finite)
    k0 = (ESCAPE_C**2 - 1.0) / t
    if n_kill <= k0:
        return max(1.0, n_kill)
    steps = k0 + 2.0 * ESCAPE_C / t * (math.sqrt(1.0 + t * n_kill) - ESCAPE_C)
    return min(float(max_scatter), max(1.0, steps))


def seconds_per_step(spec: SimulationSpec, speed: float = 1.0) -> float:
    """Estimated CPU seconds per walk step on one core for this spec's estimator and bins."""
    per_step = EXIT_SECONDS_PER_STEP
    if spec.estimator in ("connections", "both"):
        per_step += CONNECTION_SECONDS_PER_BIN * spec.bins.radial.count * spec.theta_s_count()
    return per_step / speed


def job_photons(spec: SimulationSpec) -> int:
    """Photons the whole job walks: photons x incidence angles x channels, summed over its walks
    (the media, or with shared walks one per walk group: schema.groups)."""
    if spec.walk_mode() == "shared":
        return spec.photons * len(spec.incidence_deg) * len(spec.walk_groups())
    return spec.photons * len(spec.incidence_deg) * sum(len(m.albedo) for m in spec.media())


def estimate_shard(spec: SimulationSpec, speed: float = 1.0) -> ShardEstimate:
    """Photons, steps and CPU seconds of the spec's largest shard: ceil(photons / shards) photons
    per channel and incidence angle of one medium (a sweep's shard holds one medium), the
    medium whose photons take the most steps."""
    per_config = -(-spec.photons // spec.shards)
    analog = spec.absorption == "analog"
    n_angles = len(spec.incidence_deg)
    worst, channels = 0.0, 1
    for m in spec.media():
        steps = sum(steps_per_photon(a, g, analog=analog, max_scatter=spec.max_scatter) for a, g in zip(m.albedo, m.g))
        if steps > worst:
            worst, channels = steps, len(m.albedo)
    steps = per_config * n_angles * worst
    return ShardEstimate(photons=per_config * n_angles * channels, steps=steps,
                         cpu_s=steps * seconds_per_step(spec, speed))
