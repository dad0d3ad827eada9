"""Radial path stretching (schema/stretch.py, workers/walk/stretch.py).

- one step: a stretched free path follows sigma* exp(-sigma* s) with sigma* = 1 - gamma mu
  (chi-square against that density for outward, sideways and inward flights, and on the axis),
  the weight after it is exactly the likelihood ratio exp(-gamma mu s) / sigma* and its mean is 1;
  a flight that reaches the surface carries exp(-gamma mu t), so the weight leaving has the
  expectation exp(-t) of the unstretched law; first flights, flights inside r_min and albedos at
  or above albedo_max are left alone; with gamma_inward, inward flights follow their own density
  and ratio (and the derived second and fourth moments of the ratio), outward ones are bitwise
  unchanged;
- whole walks with stretching agree with plain independent walks in every radial bin with >= 30
  events, Rd and absorbed power (two seeds, z with unit spread), exit tally and hybrid, shared
  walks and gamma_inward included; Rd at eta = 1, g = 0 matches Chandrasekhar's H-function; the far bins get many
  more events (the point of it);
- the same spec gives the same bytes on one thread and on two processes; bad fields are refused
  with their name and range; off by default and absent from the canonical spec (gamma_inward too).
"""

from __future__ import annotations

import math

import numpy as np
import pyarrow.parquet as pq
import pytest
import torch

from tests.support.stats import assert_samples_match_pdf
from tests.support.tables import bitwise_equal
from tests.workers.test_shared_walks import TOTAL, assert_optional_field, assert_rd_matches_the_h_function, assert_refused, assert_rows_agree, sweep_results, sweep_spec
from workers.run.simulate import simulate_sweep
from workers.walk.walk import EXITED, RUNNING, Lanes, WalkParams, walk_step

GAMMA = 0.8
STRETCH = {"gamma": GAMMA, "r_min_mfp": 0.0, "albedo_max": 0.7}
LOW = [0.05, 0.15, 0.3, 0.6]  # the albedos stretching is for


def lanes_from(n: int, x: float, u: tuple[float, float, float], z: float, *, nscat: int = 1, albedo: float = 0.5, seed: int = 3) -> Lanes:
    lanes = Lanes.empty(n)
    lanes.x[:], lanes.z[:] = x, z
    lanes.ux[:], lanes.uy[:], lanes.uz[:] = u
    lanes.w[:], lanes.albedo[:], lanes.nscat[:] = 1.0, albedo, nscat
    lanes.status[:] = RUNNING
    lanes.photon[:] = torch.arange(n)
    lanes.c_lo[:] = torch.arange(n, dtype=torch.int32)
    lanes.k0[:], lanes.k1[:] = seed, 99
    lanes.start_streams()
    return lanes


def step(lanes: Lanes, stretch=(GAMMA, 1.0, 0.7, GAMMA)) -> Lanes:
    """One step at eta = 1, without Russian roulette (w_min 0): the weight after a collision is
    w albedo times the flight's factor."""
    return walk_step(lanes, p=WalkParams(inv_eta=1.0, analog=False, max_scatter=1 << 20, w_min=0.0, stretch=stretch))[0]


def flight_lengths(before: Lanes, after: Lanes) -> np.ndarray:
    dx, dy, dz = (getattr(after, a).double() - getattr(before, a).double() for a in ("x", "y", "z"))
    return torch.sqrt(dx * dx + dy * dy + dz * dz).numpy()


# mu (outward horizontal cosine) and where: outward, sideways, inward at rho = 2; on the axis
CASES = [(2.0, (1.0, 0.0, 0.0), 1.0), (2.0, (0.6, 0.0, -0.8), 0.6), (2.0, (0.0, 0.6, -0.8), 0.0), (2.0, (-1.0, 0.0, 0.0), -1.0),
         (0.0, (0.6, 0.0, -0.8), 0.6)]


@pytest.mark.parametrize("x, u, mu", CASES)
def test_stretched_free_path_follows_its_density_and_carries_the_likelihood_ratio(x, u, mu):
    n = 1 << 17
    before = lanes_from(n, x, u, z=-300.0)  # deep: every flight ends in a collision (and float32 resolves it)
    after = step(before, stretch=(GAMMA, 0.0 if x == 0.0 else 1.0, 0.7, GAMMA))  # r_min 0 on the axis
    s = flight_lengths(before, after)
    sig = 1.0 - GAMMA * mu
    edges = np.concatenate([np.linspace(0.0, 6.0 / sig, 41), [np.inf]])
    assert_samples_match_pdf(s, lambda v: sig * math.exp(-sig * v), edges, n_tests=len(CASES), what=f"stretched free path, mu {mu}")
    w = after.w.double().numpy() / np.float32(0.5)  # the albedo's factor out
    np.testing.assert_allclose(w, np.exp(-GAMMA * mu * s) / sig, rtol=2e-5)
    se = w.std() / math.sqrt(n)
    assert abs(w.mean() - 1.0) <= 4.0 * se, (w.mean(), se)  # E_drawn[p / q] = 1


@pytest.mark.parametrize("mu", [0.9, 0.0, -0.9])
def test_a_stretched_flight_leaves_with_the_unstretched_expectation(mu):
    """From depth h along u (uz > 0): E[weight leaving] = exp(-t), t = h / uz, as without stretching;
    the share leaving is exp(-sigma* t) (eta = 1: no reflection)."""
    n, h = 1 << 17, 0.4
    uz = math.sqrt(1.0 - mu * mu)
    before = lanes_from(n, 2.0, (mu, 0.0, uz), z=-h)
    after = step(before)
    out = after.status.numpy() == EXITED
    t, sig = h / uz, 1.0 - GAMMA * mu
    share, sd = out.mean(), math.sqrt(math.exp(-sig * t) * (1 - math.exp(-sig * t)) / n)
    assert abs(share - math.exp(-sig * t)) <= 4.0 * sd, (share, math.exp(-sig * t))
    left = np.where(out, after.w.double().numpy(), 0.0)
    np.testing.assert_allclose(after.w.double().numpy()[out], math.exp(-GAMMA * mu * t), rtol=1e-5)
    assert abs(left.mean() - math.exp(-t)) <= 4.0 * left.std() / math.sqrt(n), (left.mean(), math.exp(-t))


# -- a separate inward strength ------------------------------------------------------------------

GAMMA_IN = 0.3  # the largest allowed: the fourth moment of an inward ratio is finite below 1/3


@pytest.mark.parametrize("u, mu", [((-1.0, 0.0, 0.0), -1.0), ((-0.6, 0.0, -0.8), -0.6)])
def test_inward_flights_use_gamma_inward_for_their_density_and_ratio(u, mu):
    n = 1 << 17
    before = lanes_from(n, 2.0, u, z=-300.0)
    after = step(before, stretch=(GAMMA, 1.0, 0.7, GAMMA_IN))
    s = flight_lengths(before, after)
    sig = 1.0 - GAMMA_IN * mu
    edges = np.concatenate([np.linspace(0.0, 6.0 / sig, 41), [np.inf]])
    assert_samples_match_pdf(s, lambda v: sig * math.exp(-sig * v), edges, n_tests=2, what=f"inward free path, mu {mu}")
    w = after.w.double().numpy() / np.float32(0.5)
    np.testing.assert_allclose(w, np.exp(-GAMMA_IN * mu * s) / sig, rtol=2e-5)
    se = w.std() / math.sqrt(n)
    assert abs(w.mean() - 1.0) <= 4.0 * se, (w.mean(), se)


def test_an_inward_ratio_has_the_second_moment_derived_and_a_finite_fourth():
    """E[ratio^k] = sigma*^(1-k) / (1 + (k-1) gamma mu) (workers.walk.stretch): at gamma_in 0.3
    straight inward (sigma* 1.3) k = 2 gives 1 / (1.3 * 0.7) and k = 4 is finite (4.55), so the
    sample mean of ratio^2 has a finite variance and is tested against the formula with its own
    error bar.  (The ratio's tail is Pareto, P(ratio > x) = (x sigma*)^-(1 + 1 / (gamma |mu|)), index
    4.33 here: the chi-square of the free path above pins it.  Higher sample moments are not tested:
    the eighth is infinite, so the spread of ratio^2 itself would not settle.  At gamma 0.8 the
    same flight's fourth moment is infinite: 1 + 3 * 0.8 * -1 < 0.)"""
    n = 1 << 18
    before = lanes_from(n, 2.0, (-1.0, 0.0, 0.0), z=-300.0)
    w = step(before, stretch=(GAMMA, 1.0, 0.7, GAMMA_IN)).w.double().numpy() / np.float32(0.5)
    sig = 1.0 + GAMMA_IN

    def moment(k):
        return sig ** (1 - k) / (1.0 - (k - 1) * GAMMA_IN)

    w2 = w * w
    se = math.sqrt((moment(4) - moment(2) ** 2) / n)  # from the derived moments, not the sample
    assert abs(w2.mean() - moment(2)) <= 4.0 * se, (w2.mean(), moment(2), se)


@pytest.mark.parametrize("x, u", [(2.0, (1.0, 0.0, 0.0)), (2.0, (0.6, 0.0, -0.8)), (2.0, (0.0, 0.6, -0.8)), (0.0, (0.6, 0.0, -0.8))])
def test_outward_and_sideways_flights_ignore_gamma_inward_bit_for_bit(x, u):
    n = 1 << 12
    before = lanes_from(n, x, u, z=-300.0)
    one = step(before, stretch=(GAMMA, 0.0, 0.7, GAMMA))
    two = step(before, stretch=(GAMMA, 0.0, 0.7, GAMMA_IN))
    for name in ("x", "y", "z", "w", "status"):
        assert torch.equal(getattr(one, name), getattr(two, name)), name


def test_an_inward_flight_with_gamma_inward_leaves_with_the_unstretched_expectation():
    n, h, mu = 1 << 17, 0.4, -0.9
    uz = math.sqrt(1.0 - mu * mu)
    after = step(lanes_from(n, 2.0, (mu, 0.0, uz), z=-h), stretch=(GAMMA, 1.0, 0.7, GAMMA_IN))
    out = after.status.numpy() == EXITED
    t, sig = h / uz, 1.0 - GAMMA_IN * mu
    share, sd = out.mean(), math.sqrt(math.exp(-sig * t) * (1 - math.exp(-sig * t)) / n)
    assert abs(share - math.exp(-sig * t)) <= 4.0 * sd, (share, math.exp(-sig * t))
    np.testing.assert_allclose(after.w.double().numpy()[out], math.exp(-GAMMA_IN * mu * t), rtol=1e-5)
    left = np.where(out, after.w.double().numpy(), 0.0)
    assert abs(left.mean() - math.exp(-t)) <= 4.0 * left.std() / math.sqrt(n), (left.mean(), math.exp(-t))


@pytest.mark.parametrize("x, nscat, albedo", [(2.0, 0, 0.5), (0.5, 3, 0.5), (2.0, 3, 0.7), (2.0, 3, 0.9)])
def test_first_flights_near_flights_and_high_albedos_are_not_stretched(x, nscat, albedo):
    n = 1 << 12
    before = lanes_from(n, x, (1.0, 0.0, 0.0), z=-1e6, nscat=nscat, albedo=albedo)
    plain = walk_step(before, p=WalkParams(inv_eta=1.0, analog=False, max_scatter=1 << 20, w_min=0.0))[0]
    stretched = step(before)
    for name in ("x", "y", "z", "w", "status", "absorbed"):
        assert torch.equal(getattr(plain, name), getattr(stretched, name)), name


# -- whole walks --------------------------------------------------------------------------------


STRETCH_IN = {**STRETCH, "gamma_inward": GAMMA_IN}


@pytest.fixture(scope="module", params=[("exits", STRETCH), ("hybrid", STRETCH), ("exits", STRETCH_IN)],
                ids=["exits", "hybrid", "exits-gamma-inward"])
def pair(request):
    est, stretch = request.param
    return (est, sweep_results(sweep_spec(est, "shared", 1, 2**15, albedos=LOW, stretch=stretch)),
            sweep_results(sweep_spec(est, "independent", 2, 2**15, albedos=LOW)))


@pytest.mark.slow
def test_stretched_shared_walks_agree_with_plain_independent_walks_in_every_bin(pair, walk_stats):
    est, st, plain = pair
    assert_rows_agree(st, plain, est, f"{est}: stretched shared (seed 1) against plain independent (seed 2)", walk_stats)


@pytest.mark.slow
def test_stretched_bssrdf_s_agrees_with_plain_walks_in_every_bin(pair, walk_stats):
    """S (the BSSRDF averaged over a bin, w / cos_o per exit) as well as G: every bin with >= 30
    events in both runs (chosen by events, not by errors), z with unit spread."""
    est, st, plain = pair
    z = []
    for a, b in zip(st, plain):
        ea, eb = a.events(f"{est}/bins_S")[0, TOTAL], b.events(f"{est}/bins_S")[0, TOTAL]
        keep = (ea >= 30) & (eb >= 30)
        ma, mb = a.mean(f"{est}/bins_S")[0, TOTAL][keep], b.mean(f"{est}/bins_S")[0, TOTAL][keep]
        sa, sb = a.stderr(f"{est}/bins_S")[0, TOTAL][keep], b.stderr(f"{est}/bins_S")[0, TOTAL][keep]
        z.append((ma - mb) / np.sqrt(sa * sa + sb * sb))
    z = np.concatenate(z)
    what = f"{est}: S of stretched shared against plain independent walks, {len(z)} bins"
    assert len(z) >= 60, what
    dof = min(r.dof(f"{est}/Rd") for r in st + plain)
    walk_stats.assert_unit_spread(z, dof, what)
    walk_stats.assert_within(z, dof, what)


@pytest.mark.slow
def test_stretching_sends_photons_to_the_far_bins(pair):
    """The agreement above is not vacuous: beyond 4 mean free paths the stretched walk has at least
    twice the events of the plain one at every albedo (measured 2.6-2.7x at 0.6, where walks are
    longest, 11-50x at 0.05)."""
    est, st, plain = pair
    r = st[0].layout.radial_mm[0]
    far = r[:-1] >= 4.0
    for a, b, albedo in zip(st, plain, LOW):
        ea, eb = a.events(f"{est}/radial_G")[0, TOTAL][:-1][far].sum(), b.events(f"{est}/radial_G")[0, TOTAL][:-1][far].sum()
        print(f"albedo {albedo}: {ea} events beyond 4 mfp stretched, {eb} plain")
        assert ea >= 2 * max(eb, 1), (albedo, ea, eb)


@pytest.mark.slow
def test_stretched_rd_matches_the_h_function(walk_stats):
    albedos = [0.1, 0.3, 0.6]
    spec = sweep_spec("exits", "shared", 5, 2**15, eta=1.0, albedos=albedos, stretch=STRETCH, bins={"radial": {"count": 1, "max_mm": 100.0}})
    assert_rd_matches_the_h_function(sweep_results(spec), albedos, "stretched Rd", walk_stats)


def test_same_bytes_on_one_thread_and_two_processes(tmp_path):
    spec = sweep_spec("hybrid", "shared", 9, 3000, albedos=LOW, stretch=STRETCH)
    simulate_sweep(spec, str(tmp_path / "a"), threads=1)
    simulate_sweep(spec, str(tmp_path / "b"), processes=2)
    for name in ("radial", "bins", "summary"):
        a, b = pq.read_table(tmp_path / "a" / f"{name}.parquet"), pq.read_table(tmp_path / "b" / f"{name}.parquet")
        assert bitwise_equal(a, b), name


# -- the spec -----------------------------------------------------------------------------------


@pytest.mark.parametrize("value, words", [
    ({"gamma": 0.0}, ["stretch.gamma", "(0, 0.95]", "0"]),
    ({"gamma": 1.0}, ["stretch.gamma", "(0, 0.95]", "1.0"]),
    ({"r_min_mfp": -1}, ["stretch.r_min_mfp", "[0, 10000]", "-1"]),
    ({"albedo_max": 0}, ["stretch.albedo_max", "(0, 1]", "0"]),
    ({"albedo_max": 1.5}, ["stretch.albedo_max", "(0, 1]", "1.5"]),
    ({"gama": 0.5}, ["stretch.gama"]),
    ({"gamma_inward": 0.31}, ["stretch.gamma_inward", "[0, 0.3]", "0.31"]),
    ({"gamma_inward": -0.1}, ["stretch.gamma_inward", "[0, 0.3]", "-0.1"]),
])
def test_bad_stretch_fields_are_refused_with_the_field_and_range(value, words):
    assert_refused("stretch", value, words)


def test_off_by_default_and_absent_from_the_canonical_spec():
    assert_optional_field("stretch", STRETCH)


def test_gamma_inward_is_absent_from_the_canonical_spec_unless_given():
    """A stretch written before gamma_inward existed hashes as it did; giving it (even equal to
    gamma, which walks the same paths) is a different spec."""
    import json

    old = sweep_spec("hybrid", "shared", 1, 100, stretch=STRETCH)
    assert json.loads(old.canonical_json())["stretch"] == {"gamma": GAMMA, "r_min_mfp": 0.0, "albedo_max": 0.7}
    assert old.stretch.inward() == GAMMA
    new = sweep_spec("hybrid", "shared", 1, 100, stretch=STRETCH_IN)
    assert json.loads(new.canonical_json())["stretch"]["gamma_inward"] == GAMMA_IN and new.stretch.inward() == GAMMA_IN
    assert len({old.spec_hash(), new.spec_hash(), sweep_spec("hybrid", "shared", 1, 100, stretch={**STRETCH, "gamma_inward": 0.0}).spec_hash()}) == 3


@pytest.mark.parametrize("arg, want", [("0.8,0,0.3", {"gamma": 0.8, "r_min_mfp": 0.0, "albedo_max": 0.3}),
                                       ("0.8,0,0.3,0.1", {"gamma": 0.8, "r_min_mfp": 0.0, "albedo_max": 0.3, "gamma_inward": 0.1})])
def test_table_cost_passes_the_stretch_to_its_sweep(capsys, arg, want):
    import json

    from workers.measure.table_cost import main

    assert main(["--albedos", "0.2,0.5", "--photons", "3000", "--stretch", arg, "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["stretch"] == want
    assert all(math.isfinite(out["cpu_hours"][k]) and out["cpu_hours"][k] > 0 for k in ("all", "major"))


def test_stretched_sweeps_group_albedos_below_0_7_in_tenths_and_walks_above_run_unstretched():
    from schema import parse_spec
    from schema.sweep import pbrt_albedos
    from workers.run.plan import ShardPlan

    albedos = [a for a in pbrt_albedos(100) if a > 0]
    d = {"name": "t", "sweep": {"albedo": albedos, "g": [0.0], "eta": [1.33]}, "stretch": STRETCH, "photons": 100}
    spec = parse_spec(d)
    leaders = [albedos[g[-1]] for g in spec.walk_groups()]
    firsts = [albedos[g[0]] for g in spec.walk_groups()]
    assert [round(a, 3) for a in firsts] == [0.078, 0.332, 0.432, 0.517, 0.621, 0.703]
    assert leaders[-1] == 1.0
    assert len(parse_spec({k: v for k, v in d.items() if k != "stretch"}).walk_groups()) == 3  # (0.3, 0.7) without it
    # the plans: stretching compiled into the walks below albedo_max only
    for group in spec.walk_groups():
        leader = group[-1]
        plan = ShardPlan.build(spec.medium_spec(leader), 0)
        assert (plan.params.stretch is not None) == (albedos[leader] < STRETCH["albedo_max"]), albedos[leader]
