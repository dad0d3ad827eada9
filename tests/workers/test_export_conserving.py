"""Node values that keep the measured energy (workers.exports.conserving): the spline through them
integrates over every bin to the bin's mass, stays >= 0 where bins are empty or spiky, states
each node's error, and carries the bins' covariance to the nodes and to rhoEff."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import integrate
from scipy import stats as sps

from schema.bins import pbrt_radial_edges, pbrt_radius_nodes
from workers.models.catmull_rom import bin_integral_matrix, integrate_catmull_rom, negative_mass
from workers.models.diffusion import pbd_rd
from workers.exports.conserving import TAIL_RATIO, conserving_nodes, interval_minima
from workers.exports.nodes import node_values

EDGES = pbrt_radial_edges(64)
NODES = pbrt_radius_nodes(64)
B = bin_integral_matrix(NODES, EDGES)


def _pbd(rho, g, eta):
    f = lambda r: 2 * math.pi * r * float(pbd_rd(r, 1 - rho, rho, g, eta))  # noqa: E731
    masses = np.array([integrate.quad(f, a, b, limit=200, epsrel=1e-11)[0] for a, b in zip(EDGES[:-1], EDGES[1:])])
    return masses, np.array([f(r) for r in NODES])


@pytest.fixture(scope="module", params=[(0.3, 0.0, 1.33), (0.95, 0.0, 1.33), (0.999, 0.9, 1.0), (0.8, -0.3, 1.5),
                                        (1.0, 0.0, 1.33)], ids=lambda p: f"rho{p[0]}-g{p[1]}-eta{p[2]}")
def exact(request):
    return _pbd(*request.param)


def test_spline_holds_every_bins_mass(exact):
    """B f = M for every measured node's bin (each pooled group, the bins after the previous
    measured node up to this one, holds its mass; the last also the tail beyond; the last bin
    only its part inside the last node) and rhoEff = sum M - that outer part, to rounding; the
    power-law point values (the previous construction) do not keep it."""
    masses, _f = exact
    row = conserving_nodes(masses, np.full_like(masses, 1e-6))
    total, _cdf = integrate_catmull_rom(NODES, row.values)
    assert total == pytest.approx(masses.sum() - row.beyond, rel=1e-12)
    held = B @ row.values
    anchors = np.flatnonzero(~row.modelled)
    starts = np.concatenate([[0], anchors[:-1] + 1])
    ends = np.concatenate([anchors[:-1] + 1, [64]])
    outer = np.zeros(64)
    outer[-1] = row.beyond
    for a, b in zip(starts, ends):
        assert held[a:b].sum() == pytest.approx((masses - outer)[a:b].sum(), rel=1e-9, abs=1e-15), (a, b)
    assert np.count_nonzero(ends - starts == 1) >= 40  # most groups are one bin: B f = M there
    assert 0 <= row.beyond <= 0.5 * masses[-1]
    np.testing.assert_allclose(row.coefficients[:-1], 1.0, atol=1e-12)  # rhoEff = sum of bin masses
    point, _se, _err = node_values(masses, np.ones_like(masses))
    assert abs(integrate_catmull_rom(NODES, point)[0] / masses.sum() - 1) > 5e-5


def test_nodes_are_the_profile_within_their_stated_error(exact):
    """|f_j - f(r_j)| <= 1.5 error_j + 1e-6 of the peak at every node but 0 (photon beam
    diffusion has f(0) = 0, an artefact: workers/exports/nodes.py), the spline >= 0; where the
    profile exceeds 1 % of its peak the nodes are within 1 %."""
    masses, f = exact
    row = conserving_nodes(masses, np.full_like(masses, 1e-6))
    peak = f.max()
    diff = np.abs(row.values - f)[1:]
    bad = np.flatnonzero(diff > 1.5 * row.error[1:] + 1e-6 * peak) + 1
    assert not bad.size, bad
    matters = f[1:] > 1e-2 * peak
    assert np.max(diff[matters] / f[1:][matters]) < 1e-2
    assert negative_mass(NODES, row.values) == 0.0 and np.all(interval_minima(NODES, row.values) >= 0)


def test_empty_bins_and_spikes_never_make_the_spline_dip():
    """Bins without events inside and beyond the profile, a lone heavy event, a lone light one:
    the spline is >= 0 everywhere, the mass is the measured mass, empty bins' nodes are
    modelled (error = their value), the tail beyond the last event decays by TAIL_RATIO."""
    masses, _f = _pbd(0.5, 0.0, 1.33)
    se = 0.05 * masses
    masses[[3, 4, 9, 30]] = 0.0
    se[[3, 4, 9, 30]] = np.nan
    masses[40:], se[40:] = 0.0, np.nan
    masses[12] *= 6.0  # a spike
    masses[20] *= 0.05  # a hole
    plain = np.linalg.solve(B, masses)
    assert negative_mass(NODES, plain) < 0  # what solving B f = M alone gives
    row = conserving_nodes(masses, se)
    assert negative_mass(NODES, row.values) == 0.0 and np.all(row.values >= 0)
    assert integrate_catmull_rom(NODES, row.values)[0] == pytest.approx(masses.sum(), rel=1e-12)
    assert np.all(row.modelled[[3, 4, 9, 30]]) and np.all(row.modelled[40:])
    np.testing.assert_array_equal(row.error[row.modelled], np.abs(row.values[row.modelled]))
    last = np.flatnonzero(~row.modelled).max()
    np.testing.assert_allclose(row.values[last + 1:], row.values[last] * TAIL_RATIO ** np.arange(1, 64 - last), rtol=1e-12)


def test_single_events_in_the_innermost_bins_stay_local():
    """A short run: one photon each in the three innermost bins, then a mix of empty bins and
    single events, then a measured profile (the exit tally of 8000 photons at albedo 0.9, g 0.5,
    eta 1.33 gave this).  Pooling removes the dips near the origin and must stop there: the
    measured bins further out keep their own nodes (earlier, the dip followed each pooled node
    outward until one node held the whole row, and the radii pbrt samples fell at the origin).
    Bins 13 to 47 are the profile's body (their masses within a decade of the largest)."""
    masses, _f = _pbd(0.9, 0.5, 1.33)
    masses = masses / masses.sum() * 0.17
    se = 0.1 * masses
    one = 0.17 / 8000 * 5  # the weight of one exit
    masses[:13] = [3 * one, one, one, 0, 0, one, 0, 0, one, one, one, 2 * one, 5 * one]
    se[:13] = [one * math.sqrt(3), one, one, np.nan, np.nan, one, np.nan, np.nan, one, one, one, one * math.sqrt(2), one * math.sqrt(5)]
    row = conserving_nodes(masses, se)
    assert negative_mass(NODES, row.values) == 0.0 and np.all(row.values >= 0)
    assert integrate_catmull_rom(NODES, row.values)[0] == pytest.approx(masses.sum(), rel=1e-12)
    # The profile's own far tail may pool (as for the exact rows); the body keeps its nodes.
    assert not row.modelled[13:48].any(), np.flatnonzero(row.modelled)


def test_no_events_at_all_gives_a_zero_row():
    row = conserving_nodes(np.zeros(64), np.full(64, np.nan))
    assert np.all(row.values == 0) and np.all(np.isnan(row.stderr)) and math.isnan(row.rho_eff_stderr)


def test_covariance_is_the_scatter_over_replicates():
    """Photons leaving into bin j with probability p_j (one exit each, as the exit tally): the
    bin masses' covariance is known, and over independent replicates the node values and rhoEff
    scatter as the propagated covariance says (sample variance against chi-square bounds with
    R - 1 degrees of freedom, Sidak over the checked quantities; the reported covariance is
    computed from each replicate's own masses, as the export does)."""
    masses, _f = _pbd(0.9, 0.0, 1.0)
    p = masses / masses.sum() * 0.6  # 40 % of the photons leave nothing (absorbed)
    photons, replicates = 200_000, 300
    rng = np.random.default_rng(21)
    picks = [5, 20, 35, 45]
    values, reported, rho, rho_se = [], [], [], []
    for _ in range(replicates):
        counts = rng.multinomial(photons, np.append(p, 1 - p.sum()))[:-1]
        m = counts / photons
        se = np.where(counts > 0, np.sqrt(m * (1 - m) / (photons - 1)), np.nan)  # one exit of weight 1
        row = conserving_nodes(m, se, photons)
        values.append(row.values[picks])
        reported.append(row.stderr[picks] ** 2)
        rho.append(integrate_catmull_rom(NODES, row.values)[0])
        rho_se.append(row.rho_eff_stderr**2)
    sample = np.concatenate([np.var(values, axis=0, ddof=1), [np.var(rho, ddof=1)]])
    expected = np.concatenate([np.mean(reported, axis=0), [np.mean(rho_se)]])
    ratio = sample / expected
    level = 1 - (1 - 1e-4) ** (1 / len(ratio))
    lo, hi = (sps.chi2.ppf(q, replicates - 1) / (replicates - 1) for q in (level / 2, 1 - level / 2))
    print(f"sample / reported variance {ratio}, band [{lo:.3f}, {hi:.3f}]")
    assert np.all((lo <= ratio) & (ratio <= hi)), ratio
