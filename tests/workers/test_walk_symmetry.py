"""Symmetries of the measured BSSRDF.

- Normal incidence: the medium and the beam are invariant under rotation about the normal, so G
  of a bin (r, theta_s, cos theta_o, phi_o) does not depend on theta_s (phi_o is measured from
  the outward radial direction, so it rotates with the bin).
- Oblique incidence in the x-z plane: invariant under the mirror y -> -y, which maps theta_s to
  2 pi - theta_s and phi_o to 2 pi - phi_o (the orientation of the azimuth flips), so bin
  (r, k, c, j) holds the same G as (r, n_theta - 1 - k, c, n_phi - 1 - j).

Bins of one run are compared with one another; they come from the same photons, whose exits
land in one bin each, so two bins' estimates are negatively correlated by -p_a p_b per photon,
negligible next to their variances p (p below a few percent here).  Compared bins must be
resolved: exit tallies to 20 % (25 or more exits, near-normal batch sums in analog mode), the
connection tallies to 10 % (see test_walk_estimators.py on why small connection bins are not).

Medium: albedo 0.8, g = 0.7, eta = 1.4, sigma_t = 1/mm (transport mfp 2.3 mm), analog
absorption; Rd ~0.1 over ~5 collisions per photon.  Four linear radial bins out to 4 mm, one
cos theta_o bin, 2 phi_o bins at normal incidence (rotating with theta_s only if phi_o is
measured from the radial direction) and 4 at 45 deg.  Exits: N = 6e5, ~6e4 exits over 48-96
bins; connections: N = 5e4, 16 kernels per vertex.
"""

from __future__ import annotations

import numpy as np
import pytest

from workers.simulate import simulate

MEDIUM = dict(sigma_a=0.2, sigma_s=0.8, g=0.7, eta=1.4)
RESOLVED = {"exits": 0.2, "connections": 0.1}  # largest relative se of a compared bin

# estimator -> (photons, theta_s bins)
LAYOUT = {"exits": (600_000, 6), "connections": (50_000, 4)}


def _run(walk_spec, est: str, incidence: float, n_phi: int, seed: int):
    photons, n_theta = LAYOUT[est]
    spec = walk_spec(
        **MEDIUM, n_r=4, max_mm=4.0, spacing="linear", n_theta=n_theta, n_cos=1, n_phi=n_phi,
        incidence_deg=[incidence], photons=photons, shards=2, batches_per_shard=16, estimator=est,
        absorption="analog", seed=seed,
    )  # fmt: skip
    return simulate(spec)


def _bins(result, est: str, comp: int):
    """G, se per bin [n_r, n_theta, n_cos, n_phi] (inside r_max; theta_s is undefined beyond)."""
    n_r = result.layout.n_r
    return result.mean(f"{est}/bins_G")[0, comp, :n_r], result.stderr(f"{est}/bins_G")[0, comp, :n_r]


@pytest.mark.parametrize("est, seed", [("exits", 61), ("connections", 62)])
def test_normal_incidence_does_not_depend_on_theta_s(walk_spec, walk_stats, est, seed):
    """Per (r, cos, phi) group: chi-square of the theta_s bins about their weighted mean."""
    result = _run(walk_spec, est, 0.0, n_phi=2, seed=seed)
    dof = walk_stats.dof(result)
    for comp, name in ((1, "multiple"), (2, "total")):
        g, se = _bins(result, est, comp)
        g, se = np.moveaxis(g, 1, -1), np.moveaxis(se, 1, -1)  # [..., theta_s]
        with np.errstate(divide="ignore", invalid="ignore"):
            resolved = np.all(se < RESOLVED[est] * g, axis=-1)  # groups with every theta_s bin resolved
        assert resolved.sum() >= 3, f"{est} {name}: only {resolved.sum()} resolved groups"
        g, se = g[resolved], se[resolved]  # [groups, n_theta]
        w = 1.0 / se**2
        mean = (w * g).sum(axis=1, keepdims=True) / w.sum(axis=1, keepdims=True)
        chi2 = float(((g - mean) ** 2 * w).sum())
        # sum over groups of chi-square with n_theta - 1 dof: the same band as that many z^2.
        n = resolved.sum() * (g.shape[1] - 1)
        lo, hi = walk_stats.chi2_band(int(n), dof)
        print(f"{est} {name}: theta_s chi-square {chi2:.1f} over {n} dof, band [{lo:.1f}, {hi:.1f}]")
        assert lo <= chi2 <= hi, f"{est} {name}: G depends on theta_s at normal incidence: chi2 {chi2:.1f}, dof {n}"


@pytest.mark.parametrize("est, seed", [("exits", 63), ("connections", 64)])
def test_oblique_incidence_is_mirror_symmetric(walk_spec, walk_stats, est, seed):
    """At 45 deg: bin (r, k, c, j) and its mirror (r, n_theta-1-k, c, n_phi-1-j) agree."""
    result = _run(walk_spec, est, 45.0, n_phi=4, seed=seed)
    n_theta = result.layout.n_theta
    half = n_theta // 2
    for comp, name in ((0, "single"), (1, "multiple")):
        g, se = _bins(result, est, comp)
        mirror_g, mirror_se = g[:, ::-1, :, ::-1], se[:, ::-1, :, ::-1]
        a, sa, b, sb = g[:, :half], se[:, :half], mirror_g[:, :half], mirror_se[:, :half]
        with np.errstate(divide="ignore", invalid="ignore"):
            resolved = (sa < RESOLVED[est] * a) & (sb < RESOLVED[est] * b)
        assert resolved.sum() >= 3, f"{est} {name}: only {resolved.sum()} resolved mirror pairs"
        z = walk_stats.z(a[resolved], sa[resolved], b[resolved], sb[resolved])
        what = f"{est} {name}: mirror pairs at 45 deg"
        walk_stats.assert_unit_spread(z, walk_stats.dof(result), what)
        walk_stats.assert_within(z, walk_stats.dof(result), what)
    # The mirror pairs must be a real test: the profile is far from theta_s-independent.
    g, se = _bins(result, est, 2)
    forward, backward = g[:, 0].sum(), g[:, half].sum()  # theta_s bins at 0 and at pi
    assert forward != pytest.approx(backward, rel=0.05)
