"""Shared walks: one walk at a group's largest albedo tallies every albedo of the group by the
weight factor (a / a_w)^n (workers/fold/reweight.py).

- the per-photon squares a member's error bars come from are those of its reweighted entries
  (checked against the brute-force per-photon moments);
- reweighted albedos agree with their own independent walks (two seeds, z over every radial
  bin with >= 30 events in both and Rd, the absorbed power too: unit spread), for the exit
  tally and the hybrid;
- reweighted total Rd at eta = 1, g = 0 matches Chandrasekhar's H-function for every member;
- the same spec gives the same bytes on one thread and on two processes, and the group's leader
  equals its own single-medium job bit for bit.
"""

from __future__ import annotations

import numpy as np
import pyarrow.compute as pc
import pyarrow.parquet as pq
import pytest

from schema import SpecError, parse_spec
from tests.conftest import WalkStats
from tests.reference.hfunction import diffuse_reflectance_isotropic_matched
from tests.support.tables import bitwise_equal
from workers.fold.output import write_tables
from workers.fold.reweight import MemberTallies, member_factors
from workers.run.simulate import run_tasks, simulate, simulate_sweep
from workers.fold.job import JobFold
from workers.run.task import group_walk
from workers.fold.tally import photon_moments

TOTAL = 2
MIN_EVENTS = 30
ALBEDOS = [0.3, 0.6, 0.9, 0.99]


def sweep_spec(estimator: str, walks: str, seed: int, photons: int, eta: float = 1.33, albedos=ALBEDOS, **kw):
    d = {"name": "shared", "sweep": {"albedo": albedos, "g": [0.0], "eta": [eta], "walks": walks, "group_edges": [0.2]},
         "incidence_deg": [0.0], "photons": photons, "shards": 2, "batches_per_shard": 2, "estimator": estimator, "seed": seed,
         "bins": {"radial": {"count": 24, "spacing": "log", "max_mm": 8.0}, "cos_theta_o": {"count": 1}, "phi_o": {"count": 1}}}
    d.update(kw)
    return parse_spec(d)


def sweep_results(spec) -> list:
    """Every medium's Result, folded as a job folds them."""
    items = []
    for t in range(spec.task_count()):
        group, shard = spec.task_of(t)
        leader, members = group_walk(spec, group)
        items.append((spec.medium_spec(leader), shard, members))
    fold, out = JobFold(spec), []
    for t, tally in enumerate(run_tasks(items, threads=1)):
        if fold.add(t, tally) is not None:
            out.extend(fold.finished)
    assert fold.done and [r.medium_index for r in out] == list(range(spec.n_media))
    return out


# -- the squares of a member's entries ---------------------------------------------------------


@pytest.mark.parametrize("exit_bins", [None, 5])
def test_member_squares_are_the_per_photon_squares_of_the_reweighted_entries(exit_bins):
    rng = np.random.default_rng(3)
    p, e, n_cfg, hist = 500, 4, 1, (6, 1, 1, 1)
    members = MemberTallies([0.2, 0.7, 0.9], 0.9, np.array([0.97]), ["hybrid"], n_cfg, hist)
    size = int(members.accs[0].layout.square_offsets[-1])
    # keys drawn from few values so that entries of one photon often share a key
    key = rng.integers(0, 12, size=(8, p, e)) * (size // 12)
    if exit_bins is not None:  # as in the walk: the exit's eight keys are a function of where it left (few places)
        table = rng.integers(0, 12, size=(8, exit_bins)) * (size // 12)
        key[:, :, -1] = table[:, rng.integers(0, exit_bins, size=p)]
    flat2 = rng.integers(0, members.accs[0].linear["hybrid"].shape[1], size=(p, e))
    g = rng.exponential(size=(p, e)) * (rng.random((p, e)) < 0.7)
    s = g / rng.uniform(0.1, 1.0, size=(p, e))
    nscat = rng.integers(1, 40, size=p)
    members.add_hybrid(flat2, g, s, key, nscat)
    for acc, r, f in zip(members.accs, members.ratios, member_factors(members.ratios, nscat)):
        fac = np.concatenate([np.full((p, e - 1), r), f[:, None]], axis=1)
        gm, sm = g * fac, s * fac
        value = np.stack([gm, sm, gm, gm, gm, sm, gm, gm])
        np.testing.assert_allclose(acc.squares["hybrid"], photon_moments(key, value, size), rtol=1e-12, atol=1e-300)
        n_lin = acc.linear["hybrid"].shape[1]
        for row, w in ((0, gm), (2, sm), (4, (gm != 0.0).astype(np.float64))):
            np.testing.assert_allclose(acc.linear["hybrid"][row], np.bincount(flat2.ravel(), w.ravel(), n_lin), rtol=1e-12, atol=1e-300)


def test_member_walk_totals_are_the_balance_and_truncation_of_the_reweighted_photons():
    rng = np.random.default_rng(5)
    p, n_cfg = 700, 3
    w0 = np.array([0.97, 0.9, 1.0])
    members = MemberTallies([0.0, 0.5, 0.8], 0.8, w0, ["hybrid"], n_cfg, (6, 1, 1, 1))
    cfg = rng.integers(0, n_cfg, size=p)
    status = rng.integers(0, 3, size=p)  # 0 exited, 1 truncated, 2 absorbed (weight gone)
    w = rng.uniform(0.0, 1.0, size=p)
    nscat = rng.integers(0, 30, size=p)
    members.add_walk(cfg, status == 0, status == 1, w, nscat)
    for acc, f in zip(members.accs, member_factors(members.ratios, nscat)):
        left = np.where(status <= 1, w, 0.0) * f
        for q, v in (("absorbed", w0[cfg] - left), ("truncated", np.where(status == 1, w, 0.0) * f)):
            for row, x in enumerate((v, v * v, (v != 0.0).astype(np.float64))):
                # The members' sums run in another order than this sequential bincount: equal to
                # rounding, within the sequential sum's own bound (p eps of the sum of |x|).
                np.testing.assert_allclose(acc.walk[q][row], np.bincount(cfg, weights=x, minlength=n_cfg), rtol=p * 2.3e-16, atol=0)


def test_factors_are_the_albedo_ratio_to_the_scattering_count():
    f = member_factors(np.array([0.5, 1.0, 0.0]), np.array([0, 1, 3]))
    np.testing.assert_array_equal(f, [[1.0, 0.5, 0.125], [1.0, 1.0, 1.0], [1.0, 0.0, 0.0]])


# -- the spec ------------------------------------------------------------------------------------


def test_groups_cover_the_axis_in_order_with_the_largest_albedo_walked():
    spec = parse_spec({"name": "p", "sweep": {"albedo": {"count": 100, "spacing": "pbrt"}, "g": [0.0, 0.5], "eta": [1.33]}})
    groups = spec.walk_groups()
    assert spec.walk_mode() == "shared"
    assert [m for g in groups for m in g] == list(range(200))  # contiguous, in order, never across a g
    albedos = spec.sweep.albedos()
    for g in groups:
        assert g[0] // 100 == g[-1] // 100 and albedos[g[-1] % 100] == max(albedos[m % 100] for m in g)
    assert spec.task_count() == len(groups) * spec.shards


def test_independent_walks_are_one_medium_each_and_the_default_for_other_estimators():
    assert sweep_spec("exits", "independent", 1, 100).walk_groups() == [(0,), (1,), (2,), (3,)]
    d = {"name": "c", "sweep": {"albedo": [0.3, 0.9], "g": [0.0], "eta": [1.0]}, "estimator": "connections"}
    assert parse_spec(d).walk_mode() == "independent"
    assert parse_spec(dict(d, estimator="exits", absorption="analog")).walk_mode() == "independent"


@pytest.mark.parametrize("change, words", [
    ({"walks": "sharde"}, ["sweep.walks", "'shared' or 'independent'", "sharde"]),
    ({"group_edges": [0.5, 1.5]}, ["sweep.group_edges", "[0, 1]", "1.5"]),
    ({"group_edges": [0.5, 0.5]}, ["group_edges", "distinct"]),
])
def test_bad_walk_options_are_refused_with_the_field_and_range(change, words):
    d = {"name": "b", "sweep": {"albedo": [0.3, 0.9], "g": [0.0], "eta": [1.0], **change}}
    with pytest.raises(SpecError) as err:
        parse_spec(d)
    for w in words:
        assert w in str(err.value), str(err.value)


def test_shared_walks_with_a_batch_estimator_are_refused():
    d = {"name": "b", "sweep": {"albedo": [0.3, 0.9], "g": [0.0], "eta": [1.0], "walks": "shared"}, "estimator": "both"}
    with pytest.raises(SpecError, match='"independent"'):
        parse_spec(d)


# -- statistics ----------------------------------------------------------------------------------


@pytest.fixture(scope="module", params=["exits", "hybrid"])
def pair(request):
    est = request.param
    return est, sweep_results(sweep_spec(est, "shared", 1, 2**16)), sweep_results(sweep_spec(est, "independent", 2, 2**16))


def rows_z(first, second, est: str) -> tuple[np.ndarray, int]:
    """z of every albedo row of `first` against `second` (lists of Results, albedo by albedo):
    Rd, absorbed power and every radial bin with >= MIN_EVENTS events in both (chosen by events,
    never by the errors); and the number of such bins."""
    z, n_bins = [], 0
    for a, b in zip(first, second):
        ea, eb = a.events(f"{est}/radial_G")[0, TOTAL], b.events(f"{est}/radial_G")[0, TOTAL]
        keep = (ea >= MIN_EVENTS) & (eb >= MIN_EVENTS)
        n_bins += int(keep.sum())
        for name in (f"{est}/radial_G", f"{est}/Rd", "walk/absorbed"):
            ma, mb = a.mean(name)[0], b.mean(name)[0]
            sa, sb = a.stderr(name)[0], b.stderr(name)[0]
            if name.endswith("radial_G"):
                ma, mb, sa, sb = ma[TOTAL][keep], mb[TOTAL][keep], sa[TOTAL][keep], sb[TOTAL][keep]
            elif name.endswith("Rd"):
                ma, mb, sa, sb = ma[TOTAL], mb[TOTAL], sa[TOTAL], sb[TOTAL]
            z.append(np.atleast_1d(WalkStats.z(ma, sa, mb, sb)))
    return np.concatenate(z), n_bins


def assert_rows_agree(first, second, est: str, what: str, walk_stats) -> None:
    """Every albedo row of `first` agrees with `second` (:func:`rows_z`: Rd, absorbed power and
    the radial bins with >= MIN_EVENTS events, at least 60 of them): z with unit spread, none
    beyond the family's cut."""
    z, n_bins = rows_z(first, second, est)
    dof = min(r.dof(f"{est}/Rd") for r in first + second)
    what = f"{what}, {len(first)} albedos, {n_bins} radial bins"
    assert n_bins >= 60, what
    walk_stats.assert_unit_spread(z, dof, what)
    walk_stats.assert_within(z, dof, what)


def test_reweighted_albedos_agree_with_their_own_walks_in_every_bin(pair, walk_stats):
    est, shared, indep = pair
    assert_rows_agree(shared, indep, est, f"{est}: shared (seed 1) against independent (seed 2) walks", walk_stats)


def test_reweighted_error_bars_are_honest_against_the_direct_walks(pair):
    """Per-photon errors of the reweighted rows are no larger than the direct walks' (module
    docstring of workers.fold.reweight: less roulette noise), to within the spread of two estimates."""
    est, shared, indep = pair
    for a, b in zip(shared[:-1], indep[:-1]):
        ra, rb = a.stderr(f"{est}/Rd")[0, TOTAL], b.stderr(f"{est}/Rd")[0, TOTAL]
        assert ra <= 1.1 * rb, f"albedo {a.configs.albedo[0]}: reweighted se {ra:.3e} against direct {rb:.3e}"


def assert_rd_matches_the_h_function(results, albedos, what: str, walk_stats) -> None:
    """Total Rd of the exit tally of each result (eta = 1, g = 0) against Chandrasekhar's H-function."""
    z = []
    for r, a in zip(results, albedos):
        rd, se = r.mean("exits/Rd")[0, TOTAL], r.stderr("exits/Rd")[0, TOTAL]
        exact = diffuse_reflectance_isotropic_matched(a)
        print(f"a = {a}: Rd {rd:.6f} +- {se:.2e} vs {exact:.6f}")
        # The bar of the direct walk's H-function test: 3 se plus 0.2 % (float32 walk).
        assert abs(rd - exact) <= 3.0 * se + 0.002 * exact, f"{what}, a = {a}: {rd:.6f} +- {se:.2e} against {exact:.6f}"
        z.append((rd - exact) / se)
    walk_stats.assert_within(z, min(r.dof("exits/Rd") for r in results), f"{what} against the H-function")


def assert_optional_field(field: str, value) -> None:
    """A spec field that is off by default stays out of the canonical spec (old hashes hold), is
    passed to every medium's own spec and changes the hash when given."""
    plain = sweep_spec("hybrid", "shared", 1, 100)
    assert getattr(plain, field) is None and f'"{field}"' not in plain.canonical_json()
    spec = sweep_spec("hybrid", "shared", 1, 100, **{field: value})
    assert getattr(spec.medium_spec(0), field) == getattr(spec, field)
    assert spec.spec_hash() != plain.spec_hash()


def assert_refused(field: str, value, words) -> None:
    """A bad value of a spec field is refused with a message holding every one of ``words``."""
    with pytest.raises(SpecError) as err:
        sweep_spec("hybrid", "shared", 1, 100, **{field: value})
    for w in words:
        assert w in str(err.value), str(err.value)


def test_reweighted_rd_matches_the_h_function(walk_stats):
    spec = sweep_spec("exits", "shared", 5, 2**17, eta=1.0, bins={"radial": {"count": 1, "max_mm": 100.0}})
    results = sweep_results(spec)
    assert len(spec.walk_groups()) == 1
    assert_rd_matches_the_h_function(results, ALBEDOS, "reweighted Rd", walk_stats)


# -- determinism ---------------------------------------------------------------------------------


@pytest.mark.parametrize("est", ["exits", "hybrid"])
def test_same_bytes_on_one_thread_and_two_processes_and_the_leader_is_its_own_job(est, tmp_path):
    spec = sweep_spec(est, "shared", 9, 3000)
    simulate_sweep(spec, str(tmp_path / "a"), threads=1)
    simulate_sweep(spec, str(tmp_path / "b"), processes=2)
    leader = spec.walk_groups()[0][-1]
    write_tables(simulate(spec.medium_spec(leader), threads=1), str(tmp_path / "single"))
    for name in ("radial", "bins", "summary"):
        a, b = pq.read_table(tmp_path / "a" / f"{name}.parquet"), pq.read_table(tmp_path / "b" / f"{name}.parquet")
        assert bitwise_equal(a, b), name
        row = a.filter(pc.equal(a["medium"], leader)).drop(["medium"])
        single = pq.read_table(tmp_path / "single" / f"{name}.parquet")
        assert row.num_rows == single.num_rows > 0
        assert bitwise_equal(row, single.drop(["medium"])), name  # every value, every bit


def test_group_fold_saved_and_restored_after_every_task_gives_the_same_results():
    from tests.support.tallies import tally_digest
    from workers.fold.job import target_rule
    from workers.run.task import run_task
    from workers.fold.tally import ShardTally

    spec = sweep_spec("hybrid", "shared", 4, 600, shards=3, target={"rel_stderr": 0.05},
                      sweep={"albedo": [0.2, 0.5, 0.7, 0.9], "g": [0.0], "eta": [1.33], "group_edges": [0.6]})
    assert spec.walk_groups() == [(0, 1), (2, 3)]
    tallies = [run_task(spec, t) for t in range(spec.task_count())]
    straight, restored = JobFold(spec, target_rule(spec)), JobFold(spec, target_rule(spec))
    got = {"straight": [], "restored": []}
    while not straight.done:
        t = straight.next_task
        assert restored.next_task == t
        for name, fold in (("straight", straight), ("restored", restored)):
            if fold.add(t, tallies[t]) is not None:
                got[name] += [(r.medium_index, r.n_sum, tally_digest(ShardTally(0, r.stats, r.counts, r.n_sum))) for r in fold.finished]
        restored = JobFold.from_state(spec, ShardTally.from_bytes(restored.state().to_bytes()), target_rule(spec))
    assert restored.done and [m for m, _, _ in got["straight"]] == [0, 1, 2, 3]
    assert got["straight"] == got["restored"]
