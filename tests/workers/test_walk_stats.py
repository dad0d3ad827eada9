"""Standard errors are honest, and the stored tables are the tallies in the documented units.

Honesty: N_RUNS independent runs (different seeds) of one small spec; for every quantity q the
scatter of the runs' estimates x_i about their mean must match the reported standard errors:
with the pooled se^2 = mean_i se_i^2 (N_RUNS x (K - 1) degrees of freedom, nearly exact),
Q = sum_i (x_i - mean x)^2 / se^2 is chi-square with N_RUNS - 1 degrees of freedom.  Each run is
also compared with the mean of the others, z_i = (x_i - mean_{j != i} x_j) / sqrt(se_i^2 +
sum_{j != i} se_j^2 / (N_RUNS - 1)^2): (N_RUNS - 1) / N_RUNS * sum z_i^2 ~ chi-square(N_RUNS - 1)
as well, and every |z_i| stays under the Student-t cut.  Quantities: Rd single / multiple /
total and the multiple component of every radial ring, for every estimator (the hybrid, the
default, in runs of its own, also the single component of every ring).
"""

from __future__ import annotations

import math

import numpy as np
import pyarrow.parquet as pq
import pytest

from workers.fold.output import summary, write_tables
from workers.run.simulate import simulate
from workers.walk.walk import WalkParams

N_RUNS = 24
# Weights mode, albedo 0.7 (~20 vertices per photon), g = 0.5, eta = 1.3, sigma_t = 1/mm; four
# 0.75 mm rings.  2048 photons per run in 16 batches resolve each quantity to 2-10 %.
HONEST_SPEC = dict(
    sigma_a=0.3, sigma_s=0.7, g=0.5, eta=1.3, n_r=4, max_mm=3.0, photons=2048, shards=2,
    batches_per_shard=8, estimator="both",
)  # fmt: skip


@pytest.fixture(scope="module")
def repeated_runs(walk_spec):
    return [simulate(walk_spec(**HONEST_SPEC, seed=1000 + i)) for i in range(N_RUNS)]


@pytest.fixture(scope="module")
def hybrid_runs(walk_spec):
    """The same spec with the default estimator, the hybrid (its own seeds)."""
    return [simulate(walk_spec(**dict(HONEST_SPEC, estimator="hybrid"), seed=2000 + i)) for i in range(N_RUNS)]


@pytest.mark.parametrize("est", ["exits", "connections", "hybrid"])
def test_standard_errors_are_honest(request, est, walk_stats):
    """The replicate spread of every quantity matches its reported standard error; for the
    hybrid also the single scattering of every ring (its first-vertex connections)."""
    runs = request.getfixturevalue("hybrid_runs" if est == "hybrid" else "repeated_runs")

    def stack(name: str, index) -> tuple[np.ndarray, np.ndarray]:
        return (np.array([r.mean(name)[index] for r in runs]), np.array([r.stderr(name)[index] for r in runs]))

    n_r = runs[0].layout.n_r
    quantities = {f"Rd {c}": stack(f"{est}/Rd", (0, k)) for k, c in enumerate(("single", "multiple", "total"))}
    quantities.update({f"ring {i} multiple": stack(f"{est}/radial_G", (0, 1, i)) for i in range(n_r)})
    if est == "hybrid":
        quantities.update({f"ring {i} single": stack(f"{est}/radial_G", (0, 0, i)) for i in range(n_r)})
    m = len(quantities)
    n = N_RUNS
    lo, hi = walk_stats.chi2_band(n - 1, n_tests=m)
    dof = walk_stats.dof(runs[0])
    for what, (x, se) in quantities.items():
        assert np.all(se > 0), f"{est} {what}: zero standard error"
        q = float(np.sum((x - x.mean()) ** 2) / np.mean(se**2))
        others = (x.sum() - x) / (n - 1)
        z = (x - others) / np.sqrt(se**2 + (np.sum(se**2) - se**2) / (n - 1) ** 2)
        q_loo = (n - 1) / n * float(np.sum(z * z))
        print(f"{est} {what}: Q = {q:.1f}, from z_i {q_loo:.1f} (chi-square {n - 1}, band [{lo:.1f}, {hi:.1f}]), "
              f"sample variance of z {np.var(z, ddof=1):.2f}")  # fmt: skip
        assert lo <= q <= hi, f"{est} {what}: spread of {n} runs is {math.sqrt(q / (n - 1)):.2f} x the reported se (Q = {q:.1f})"
        walk_stats.assert_within(z, dof, f"{est} {what}: leave-one-out z", n_tests=n * m)


ROUNDING_TOL = 1e-6
"""Float32 rounding of a photon's weight 1 - R_spec and of its absorbed sum (~1e-7 relative per
step over tens of steps), far below any accounting error of a batch."""


def roulette_sd_bound(w_min: float = WalkParams.w_min, survival: float = WalkParams.survival) -> float:
    """Bound on the per-photon sd of D = Rd + absorbed + truncated - (1 - R_spec) in weights mode.

    Weights mode moves weight only between exits, absorption and truncation, except at Russian
    roulette: a weight w < w_min survives with probability q (= survival) as w / q or is killed,
    a change dE of mean 0 and variance w^2 (1 - q) / q < w_min^2 (1 - q) / q.  The changes are
    martingale differences, so Var D = E[sum of their conditional variances] < w_min^2 (1 - q) / q
    times the expected number of roulettes, which is below 1 / (1 - q) (every roulette after the
    first follows a survival): Var D < w_min^2 / q, sd D < w_min / sqrt(q) (3.2e-3 here).
    """
    return w_min / math.sqrt(survival)


@pytest.mark.parametrize(
    "estimator, absorption, photons, shards, batches",
    [("exits", "analog", 20_000, 1, 32), ("connections", "analog", 10_000, 1, 32), ("both", "weights", 3000, 3, 7),
     ("hybrid", "weights", 3000, 2, 3)],
)
def test_every_batch_is_counted_once(walk_spec, walk_stats, estimator, absorption, photons, shards, batches):
    """The error bars rest on the unit bookkeeping: for the connection estimator K = shards x
    batches_per_shard batches whose sizes add up to the photons (a batch folded twice would add
    photons that never ran, diluting every mean, and a batch lost would drop some); for the
    others and the walk totals K = NN = photons, one unit per photon."""
    spec = walk_spec(
        0.1, 0.9, g=0.9, eta=1.3, n_r=6, max_mm=20.0, spacing="log", n_theta=4, incidence_deg=[45.0],
        photons=photons, shards=shards, batches_per_shard=batches, estimator=estimator, absorption=absorption, seed=53,
    )  # fmt: skip
    result = simulate(spec)
    sizes = [b - a for i in range(shards) for a, b in spec.batch_photon_ranges(i)]
    assert result.n_sum == photons
    for est in result.estimators:
        want = (len(sizes), sum(n * n for n in sizes)) if est == "connections" else (photons, photons)
        assert result.units(f"{est}/Rd") == want, est
    assert result.units("walk/absorbed") == (photons, photons)
    # Every photon's weight 1 - R_spec is accounted for once (exactly in analog mode).
    walk = result.mean("walk/absorbed") + result.mean("walk/truncated")
    if estimator in ("exits", "both"):
        balance = walk + result.mean("exits/Rd")[:, 2]
        tol = ROUNDING_TOL
        if absorption == "weights":  # roulette: exact only in expectation, see roulette_sd_bound
            tol += walk_stats.z_limit(result.configs.n) * roulette_sd_bound() / math.sqrt(photons)
        off = float(np.abs(balance - 1.0 + result.configs.r_spec).max())
        print(f"{estimator} {absorption}: energy balance off by {off:.2e}, tolerance {tol:.2e}")
        np.testing.assert_allclose(balance, 1.0 - result.configs.r_spec, rtol=0, atol=tol)
    assert np.all(walk > 0.5)  # about 0.93 absorbed here


# ---------------------------------------------------------------------------------------------
# Tables: two channels (so radial edges in transport mfp differ per channel), two incidence
# angles (configuration = incidence index * n_channels + channel), every bin axis split.
# ---------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def table_run(tmp_path_factory):
    from schema import SimulationSpec

    spec = SimulationSpec.model_validate({
        "name": "tables",
        "medium": {"sigma_a": [0.3, 0.1], "sigma_s": [0.7, 1.8], "g": [0.5, 0.0], "eta": 1.3},
        "incidence_deg": [0.0, 30.0],
        "bins": {"radial": {"count": 3, "max_mfp": 2.0, "spacing": "linear"}, "theta_s": {"count": 3},
                 "cos_theta_o": {"count": 2}, "phi_o": {"count": 2}},
        "photons": 2000, "shards": 2, "batches_per_shard": 4, "estimator": "both", "absorption": "analog", "seed": 77,
    })  # fmt: skip
    result = simulate(spec)
    out = tmp_path_factory.mktemp("tables")
    write_tables(result, str(out))
    return result, out


def _columns(path) -> dict[str, np.ndarray]:
    return {k: np.asarray(v) for k, v in pq.read_table(path).to_pydict().items()}


def _cfg_comp(result, t: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Configuration and component index of every row, from its incidence and channel names."""
    c = result.configs
    inc = np.searchsorted(np.array(c.incidence_deg), t["incidence_deg"])
    assert np.array_equal(np.array(c.incidence_deg)[inc], t["incidence_deg"])
    ch = np.array([c.channel_names.index(name) for name in t["channel"]])
    comp = np.array([("single", "multiple", "total").index(name) for name in t["component"]])
    return inc * len(c.channel_names) + ch, comp


def test_radial_table_is_radial_g_over_annulus_area(table_run):
    result, out = table_run
    t = _columns(out / "radial.parquet")
    cfg, comp = _cfg_comp(result, t)
    ch = cfg % len(result.configs.channel_names)
    edges = result.spec.radial_edges_mm()  # [channel, n_r + 1]
    ir = np.array([np.flatnonzero(edges[c] == lo)[0] for c, lo in zip(ch, t["r_lo_mm"])])
    assert np.array_equal(edges[ch, ir + 1], t["r_hi_mm"])
    area = math.pi * (t["r_hi_mm"] ** 2 - t["r_lo_mm"] ** 2)
    n_rows = 0
    for est in ("exits", "connections"):
        sel = t["estimator"] == est
        n_rows += sel.sum()
        g = result.mean(f"{est}/radial_G")[cfg[sel], comp[sel], ir[sel]]
        se = result.stderr(f"{est}/radial_G")[cfg[sel], comp[sel], ir[sel]]
        np.testing.assert_allclose(t["Rd_r"][sel], g / area[sel], rtol=1e-12, atol=0)
        np.testing.assert_allclose(t["Rd_r_stderr"][sel], se / area[sel], rtol=1e-12, atol=0)
    assert n_rows == len(t["Rd_r"]) == 2 * result.configs.n * 3 * result.layout.n_r


def test_bins_table_is_g_and_s_over_area_and_solid_angle(table_run):
    result, out = table_run
    t = _columns(out / "bins.parquet")
    L = result.layout
    cfg, comp = _cfg_comp(result, t)
    ch = cfg % len(result.configs.channel_names)
    edges = result.spec.radial_edges_mm()
    ir = np.array([np.flatnonzero(edges[c] == lo)[0] for c, lo in zip(ch, t["r_lo_mm"])])
    it = np.searchsorted(L.theta_s, t["theta_s_lo"])
    ic = np.searchsorted(L.cos_o, t["cos_theta_o_lo"])
    ip = np.searchsorted(L.phi_o, t["phi_o_lo"])
    for lo_col, hi_col, ax, idx in (("theta_s_lo", "theta_s_hi", L.theta_s, it), ("cos_theta_o_lo", "cos_theta_o_hi", L.cos_o, ic),
                                    ("phi_o_lo", "phi_o_hi", L.phi_o, ip)):  # fmt: skip
        assert np.array_equal(ax[idx], t[lo_col]) and np.array_equal(ax[idx + 1], t[hi_col])
    # A = (r_hi^2 - r_lo^2) / 2 * dtheta_s, Omega = dcos * dphi (schema/bins.py).
    area = 0.5 * (t["r_hi_mm"] ** 2 - t["r_lo_mm"] ** 2) * (t["theta_s_hi"] - t["theta_s_lo"])
    omega = (t["cos_theta_o_hi"] - t["cos_theta_o_lo"]) * (t["phi_o_hi"] - t["phi_o_lo"])
    for est in ("exits", "connections"):
        sel = t["estimator"] == est
        index = (cfg[sel], comp[sel], ir[sel], it[sel], ic[sel], ip[sel])
        for col, q, scale in (("G", "bins_G", 1.0), ("S", "bins_S", area[sel] * omega[sel])):
            np.testing.assert_allclose(t[col][sel], result.mean(f"{est}/{q}")[index] / scale, rtol=1e-12, atol=0)
            np.testing.assert_allclose(t[f"{col}_stderr"][sel], result.stderr(f"{est}/{q}")[index] / scale, rtol=1e-12, atol=0)
        # Every bin inside r_max appears exactly once.
        assert len(set(zip(*index))) == sel.sum() == result.configs.n * 3 * L.n_r * L.n_theta * L.n_cos * L.n_phi


def test_g_over_all_bins_and_beyond_is_rd(table_run):
    result, out = table_run
    rows = summary(result)["results"]
    t = _columns(out / "bins.parquet")
    for est in ("exits", "connections"):
        bins_g = result.mean(f"{est}/bins_G")
        rd = result.mean(f"{est}/Rd")
        np.testing.assert_allclose(bins_g.sum(axis=(2, 3, 4, 5)), rd, rtol=1e-12, atol=1e-17)
        np.testing.assert_allclose(result.mean(f"{est}/radial_G").sum(axis=2), rd, rtol=1e-12, atol=1e-17)
        # total = single + multiple
        np.testing.assert_allclose(rd[:, 0] + rd[:, 1], rd[:, 2], rtol=1e-12, atol=1e-17)
        assert np.all(rd[:, 2] > 0)
        # From the files: G of the table's rows plus the summary's flux beyond r_max is Rd.
        for r in (r for r in rows if r["estimator"] == est):
            sel = (t["estimator"] == est) & (t["incidence_deg"] == r["incidence_deg"]) & (t["channel"] == r["channel"]) & (t["component"] == r["component"])
            assert t["G"][sel].sum() + r["Rd_beyond_rmax"] == pytest.approx(r["Rd"], rel=1e-12, abs=1e-17)


def test_tables_carry_events_nan_errors_and_unresolved_counts(table_run):
    """events per row = the result's event counts; NaN errors exactly where a row has no event
    (never 0 +- 0); the summary counts the bins without events."""
    result, out = table_run
    for name, q in (("radial", "radial_G"), ("bins", "bins_G")):
        t = _columns(out / f"{name}.parquet")
        assert t["events"].dtype == np.int64 and np.all(t["events"] >= 0)
        err = t["Rd_r_stderr"] if name == "radial" else t["G_stderr"]
        assert np.array_equal(np.isnan(err), t["events"] == 0)
        assert np.all(err[t["events"] > 0] > 0)
        if name == "bins":
            assert np.array_equal(np.isnan(t["S_stderr"]), t["events"] == 0)
            assert (t["events"] == 0).any(), "the layout must leave some bins empty for this test"
            rows = summary(result)["results"]
            for r in rows:
                sel = (t["estimator"] == r["estimator"]) & (t["incidence_deg"] == r["incidence_deg"]) & (t["channel"] == r["channel"]) & (t["component"] == r["component"])
                assert r["unresolved_bins"] == int(np.sum(t["events"][sel] == 0))
        total = sum(int(result.events(f"{e}/{q}")[:, :, : result.layout.n_r].sum()) for e in result.estimators)
        assert int(t["events"].sum()) == total
