"""Symmetries of the measured BSSRDF, read off the table's own bins.

- Mirror symmetry about the plane of incidence (the x-z plane), at every incidence angle: the
  mirror y -> -y maps theta_s to -theta_s and phi_o to -phi_o (both azimuths flip orientation),
  so G and S of a bin equal G and S of its mirror bin, the bin whose azimuth intervals are
  [-hi, -lo) of its own (modulo 2 pi), same r and cos(theta_o).  The mirror is found from the
  stored edges, whatever the binning convention, and every bin must have one.  With bins centred
  on the plane of incidence (workers.walk.conventions) the mirror of (k, m) is ((n_t - k) mod n_t,
  (n_p - m) mod n_p).  Single scattering at normal incidence leaves exactly at phi_o = 0: with
  an edge at phi_o = 0 all of it lands on one side of the edge ([0, h)) and none in the mirror
  bin ([-h, 0)), which this test reports.
- Normal incidence: the medium and the beam are invariant under rotation about the normal, so G
  of a bin (r, theta_s, cos theta_o, phi_o) does not depend on theta_s (phi_o is measured from
  the outward radial direction, so it rotates with the bin).

Bins are compared when they hold enough contributions, chosen by event counts (the tables'
``events`` column), never by a bin's estimated error: a cut such as se < 0.2 G is correlated
with the estimate itself (in a sparse bin a high estimate comes with a relatively small error),
so it keeps upward fluctuations.  A mirror pair is compared when the two bins together hold
2 MIN_EVENTS events (a function of the pair, symmetric under the mirror); both must then have
events.  Bins of one run come from the same photons, whose contributions land in few bins
each, so two bins' estimates are negatively correlated by about -p_a p_b per photon, negligible
next to their variances.

Medium: albedo 0.8, g = 0.7, eta = 1.4, sigma_t = 1/mm (transport mfp 2.3 mm), analog
absorption; Rd ~0.1 over ~5 collisions per photon.  Four log radial bins [0, 0.2, 0.54, 1.5,
4] mm (single scattering stays near the entry point), one cos theta_o bin, 6 theta_s x 4 phi_o
bins (on each axis the bins at 0 and pi are their own mirror, the others pair up).  Photons per
estimator in LAYOUT.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from workers.run.simulate import simulate

MEDIUM = dict(sigma_a=0.2, sigma_s=0.8, g=0.7, eta=1.4)
MIN_EVENTS = 30  # events of a compared bin (the mirror pair: 2 MIN_EVENTS together)
MIN_PAIRS = 3  # fewer compared pairs would say little
SINGLE, MULTIPLE, TOTAL = 0, 1, 2

# estimator -> photons (connections: 16 + 1 kernels per vertex; the hybrid's multiple
# scattering is its exit tally, so it needs the exit run's photons for the same bins)
LAYOUT = {"exits": 600_000, "connections": 50_000, "hybrid": 300_000}
N_THETA, N_PHI = 6, 4


def _run(walk_spec, est: str, incidence: float, seed: int):
    bins = {
        "radial": {"count": 4, "max_mm": 4.0, "spacing": "log", "min_fraction": 0.05},
        "theta_s": {"count": N_THETA}, "cos_theta_o": {"count": 1}, "phi_o": {"count": N_PHI},
    }
    spec = walk_spec(
        **MEDIUM, bins=bins, incidence_deg=[incidence], photons=LAYOUT[est], shards=2, batches_per_shard=16,
        estimator=est, absorption="analog", seed=seed,
    )  # fmt: skip
    return simulate(spec)


def mirror_map(edges: np.ndarray) -> np.ndarray:
    """Index of the mirror bin of every bin of an azimuth axis: bin j with [lo_j, hi_j) =
    [-hi_k, -lo_k) modulo 2 pi.  AssertionError if some bin has no mirror in the table."""
    lo, hi = edges[:-1], edges[1:]
    out = np.empty(len(lo), dtype=np.int64)
    for k in range(len(lo)):
        d_lo = np.remainder(lo + hi[k] + math.pi, 2 * math.pi) - math.pi  # lo_j - (-hi_k), wrapped
        d_hi = np.remainder(hi + lo[k] + math.pi, 2 * math.pi) - math.pi
        match = np.flatnonzero((np.abs(d_lo) < 1e-9) & (np.abs(d_hi) < 1e-9))
        assert len(match) == 1, f"bin [{lo[k]:.4f}, {hi[k]:.4f}) has no mirror bin among the edges {edges.tolist()}"
        out[k] = match[0]
    return out


def _mirror_pairs(result, est: str, quantity: str, comp: int):
    """(a, se_a, b, se_b, events_a, events_b) over the unordered mirror pairs (bin, mirror) of
    distinct bins inside r_max with 2 MIN_EVENTS events together."""
    n_r, L = result.layout.n_r, result.layout
    name = f"{est}/bins_{quantity}"
    x, se, ev = (f(name)[0, comp, :n_r] for f in (result.mean, result.stderr, result.events))  # [r, t, c, p]
    mt, mp = mirror_map(L.theta_s), mirror_map(L.phi_o)
    t, p = np.meshgrid(np.arange(L.n_theta), np.arange(L.n_phi), indexing="ij")
    first = (t * L.n_phi + p) < (mt[t] * L.n_phi + mp[p])  # each distinct pair once
    a = (slice(None), t[first], slice(None), p[first])
    b = (slice(None), mt[t[first]], slice(None), mp[p[first]])
    keep = ev[a] + ev[b] >= 2 * MIN_EVENTS
    return x[a][keep], se[a][keep], x[b][keep], se[b][keep], ev[a][keep], ev[b][keep]


MIRROR_CASES = [(est, inc) for est in LAYOUT for inc in (0.0, 45.0)]


@pytest.fixture(scope="module")
def mirror_runs(walk_spec):
    return {(est, inc): _run(walk_spec, est, inc, seed=61 + i) for i, (est, inc) in enumerate(MIRROR_CASES)}


@pytest.mark.parametrize("comp, comp_name", [(SINGLE, "single"), (MULTIPLE, "multiple")])
@pytest.mark.parametrize("est, incidence", MIRROR_CASES)
def test_mirror_bins_agree(mirror_runs, est, incidence, comp, comp_name, walk_stats):
    """G and S of every bin and of its mirror bin agree within their errors (unit spread of z
    over the compared pairs, every |z| under the cut), for single and multiple scattering at
    normal and oblique incidence."""
    result = mirror_runs[est, incidence]
    dof = walk_stats.dof(result)
    for quantity in ("G", "S"):
        a, sa, b, sb, ea, eb = _mirror_pairs(result, est, quantity, comp)
        what = f"{est} {comp_name} {quantity} at {incidence:g} deg: {len(a)} mirror pairs"
        assert len(a) >= MIN_PAIRS, f"{what} with {2 * MIN_EVENTS} events together"
        one_sided = (ea == 0) | (eb == 0)
        assert not one_sided.any(), (
            f"{what}: a bin holds events and its mirror bin none (events {ea[one_sided].tolist()} "
            f"against {eb[one_sided].tolist()}; G {a[one_sided].tolist()} against {b[one_sided].tolist()})"
        )
        z = walk_stats.z(a, sa, b, sb)
        walk_stats.assert_unit_spread(z, dof, what, n_tests=2)
        walk_stats.assert_within(z, dof, what)


def test_oblique_mirror_pairs_are_a_real_test(mirror_runs):
    """At 45 deg the profile is far from theta_s-independent: forward (bin 0, centred on +x)
    and backward (bin n/2, centred on -x) differ, so agreeing mirror pairs mean something."""
    result = mirror_runs["exits", 45.0]
    g = result.mean("exits/bins_G")[0, TOTAL, : result.layout.n_r]
    forward, backward = g[:, 0].sum(), g[:, N_THETA // 2].sum()
    assert forward != pytest.approx(backward, rel=0.05)


@pytest.mark.parametrize("est", ["exits", "connections", "hybrid"])
def test_normal_incidence_does_not_depend_on_theta_s(mirror_runs, est, walk_stats):
    """Per (r, cos, phi) group whose every theta_s bin holds MIN_EVENTS events: chi-square of
    the theta_s bins about their weighted mean (the normal-incidence runs of the mirror test)."""
    result = mirror_runs[est, 0.0]
    dof = walk_stats.dof(result)
    n_r = result.layout.n_r
    for comp, name in ((SINGLE, "single"), (MULTIPLE, "multiple"), (TOTAL, "total")):
        g, se, ev = (np.moveaxis(f(f"{est}/bins_G")[0, comp, :n_r], 1, -1) for f in (result.mean, result.stderr, result.events))
        resolved = np.all(ev >= MIN_EVENTS, axis=-1)  # [r, cos, phi] groups, by event counts only
        assert resolved.sum() >= 3, f"{est} {name}: only {resolved.sum()} groups with {MIN_EVENTS} events per bin"
        g, se = g[resolved], se[resolved]  # [groups, n_theta]
        w = 1.0 / se**2
        mean = (w * g).sum(axis=1, keepdims=True) / w.sum(axis=1, keepdims=True)
        chi2 = float(((g - mean) ** 2 * w).sum())
        # sum over groups of chi-square with n_theta - 1 dof: the same band as that many z^2.
        n = resolved.sum() * (g.shape[1] - 1)
        lo, hi = walk_stats.chi2_band(int(n), dof, n_tests=3)
        print(f"{est} {name}: theta_s chi-square {chi2:.1f} over {n} dof, band [{lo:.1f}, {hi:.1f}]")
        assert lo <= chi2 <= hi, f"{est} {name}: G depends on theta_s at normal incidence: chi2 {chi2:.1f}, dof {n}"
