"""Radial path stretching: an exponential transform of the free paths that pushes photons outward.

**The problem.**  At low albedo the multiple scattering that leaves several mean free paths from
the entry point comes from the rare photons whose last vertices lie out there: the exit tally sees
the pbrt bin at 7-8 mfp in ~1e-5 of the photons at albedo 0.08, so 1 % there took ~1e9 photons.
Connecting vertices to those bins does not help much (measured: 2.3x less variance at 3 mfp for
2x the CPU; BENCHMARKS.md, "Far tails"): at eta 1.33 light leaves only inside the escape cone
(|cos| > 0.66), so a bin is lit by vertices nearly below it, and the variance is that of getting a
vertex there at all.

**The transform.**  A flight that starts at horizontal distance rho >= r_min from the entry axis
(optical units, sigma_t = 1), after the first scattering, along u with outward horizontal cosine
mu = (u_x x + u_y y) / rho (on the axis, rho < 1e-6, where every horizontal direction points
outward: mu = |u_h|, the length of u's horizontal part), draws its free path from sigma* exp(-sigma* s) with

    sigma* = 1 - gamma mu,      0 <= gamma < 1   (so sigma* in [1 - gamma, 1 + gamma]),

i.e. s = -ln(U) / sigma* with the walk's own uniform U: outward flights are stretched, inward ones
shortened.  Likelihood ratio of the true law exp(-s) to the drawn one:

- a collision at s:        exp(-s) / (sigma* exp(-sigma* s)) = exp(-gamma mu s) / sigma*;
- reaching the surface at distance t (probability exp(-t) under the true law, exp(-sigma* t)
  drawn): exp(-gamma mu t).

The photon's weight is multiplied by that ratio (before absorption, roulette and the Fresnel
decision), so every tally is unbiased: for any function of the path, E_drawn[ratio f] = E_true[f],
flight by flight (each flight's law may depend on the state it starts from; a product of
conditional likelihood ratios is the likelihood ratio of the path).  Each factor has a finite
second moment under the drawn law: int exp(-2 s) / (sigma* exp(-sigma* s)) ds = 1 / (sigma* (2 -
sigma*)) <= 1 / (1 - gamma^2), and likewise at the surface; the weights of a path of n stretched
flights spread by at most (1 - gamma^2)^(-n/2) in standard deviation, which roulette tames at low
albedo (few flights).  Hence it is kept to albedos below ``albedo_max``, where paths are short and
the far field is what costs.

**Higher moments, and a separate inward strength.**  A finite variance is not enough for a
``target`` that stops on estimated errors: the error estimate is itself a sample mean of squared
weights, and it settles only if the fourth moment is finite.  The k-th moment of a collision's
ratio under the drawn law is

    int (exp(-gamma mu s) / sigma*)^k sigma* exp(-sigma* s) ds = sigma*^(1-k) / (sigma* + k gamma mu),

finite iff sigma* + k gamma mu = 1 + (k - 1) gamma mu > 0 (the surface factor gives the same
condition).  Outward (mu >= 0) every moment is finite: the ratio is at most 1 / (1 - gamma).
Inward (mu < 0) it needs k < 1 + 1 / (gamma |mu|): at gamma 0.6 only k < 2.67 for a flight
straight inward, so the variance is finite but the variance of its estimate is not, and a far
bin's error estimate jumps when a rare inward photon lands there with a huge weight (measured: the
same target stopped at 1.6e8 photons with one seed and ran to a 1e9 cap with another).  Hence
``gamma_inward``: mu < 0 flights use their own strength gamma_in, sigma* = 1 - gamma_in mu.  With
gamma_in < 1/3 the fourth moment is finite for every direction (k = 4 needs gamma_in |mu| < 1/3);
gamma_in = 0 leaves inward flights unstretched (their ratio is 1).  The likelihood ratio is the
same formula with gamma_in in place of gamma, so unbiasedness is untouched; sigma* and the ratio
stay continuous at mu = 0.  Roulette's threshold keeps falling as exp(-gamma rho): outward
stretching, which sets how weights fall with distance, still uses gamma.  Without
``gamma_inward`` (or with it equal to gamma) the step computes exactly what it did before.

**What it leaves alone.**  The first flight (from the entry point, before any scattering) is never
stretched: the hybrid's first vertex is recomputed from the unstretched law (workers.walk.hybrid).
The albedo does not enter the drawn geometry, so a shared walk's members still reweight by
(a / a_w)^n (workers.fold.reweight).  The random draws are the same ones; only the free path is
scaled, so a spec without ``stretch`` runs bit for bit as before.  The weight a step returns for
a vertex (the connection estimator's) is the weight arriving there, the ratio included.
"""

from __future__ import annotations

import torch

__all__ = ["stretch_factors"]


def stretch_factors(x, y, ux, uy, nscat, albedo, running, *, gamma: float, r_min: float, albedo_max: float,
                    gamma_inward: float | None = None):
    """(sigma_star, gamma_mu) per lane for the flight starting at (x, y) along u: sigma* = 1 -
    gamma mu on stretched flights (started at rho >= r_min after a scattering, albedo < albedo_max),
    1 elsewhere; gamma_mu = gamma mu there (gamma_inward mu where mu < 0, when it is given and
    differs from gamma), 0 elsewhere.  The weight ratio is then exp(-gamma_mu s) / sigma* at a
    collision after s and exp(-gamma_mu t) at the surface."""
    rho2 = x * x + y * y
    on = running & (nscat >= 1) & (rho2 >= r_min * r_min) & (albedo < albedo_max)
    # On the axis (the first vertex at normal incidence) every horizontal direction is outward.
    axis = rho2 < 1e-12
    mu = torch.where(axis, torch.sqrt(ux * ux + uy * uy), (ux * x + uy * y) / torch.sqrt(torch.where(axis, 1.0, rho2)))
    if gamma_inward is None or gamma_inward == gamma:  # one strength: the expression of old, bit for bit
        gamma_mu = torch.where(on, gamma * mu, 0.0)
    else:
        gamma_mu = torch.where(on, torch.where(mu < 0.0, gamma_inward * mu, gamma * mu), 0.0)
    return 1.0 - gamma_mu, gamma_mu
