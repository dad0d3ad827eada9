"""Path-length roulette (schema/roulette.py, workers/walk/path_roulette.py).

- a round touches exactly the running photons at step start * 2^k, survives with probability s
  (binomial bound), divides survivors' weights by s, ends the others (weight 0, absorbed), and
  depends on the photon, not on its lane; the step function plays it after its last step
  exactly as the eager round does;
- a shared walk with aggressive roulette (start 16, survival 0.5, leader at albedo 0.99) agrees
  with independent walks without it in every radial bin with >= 30 events, Rd and absorbed
  power (two seeds, z with unit spread), for the exit tally and the hybrid;
- with roulette (start 16, survival 0.75), total Rd at eta = 1, g = 0 matches Chandrasekhar's
  H-function for every member of a walk at albedo 1 (where a path without it runs up to the
  cap), and at albedo 1 Rd plus the truncated weight is 1;
- the same spec gives the same bytes on one thread and on two processes;
- bad fields are refused with their name and range.

The statistical tests are marked slow: the two walk pairs take ~15 s each and the albedo-1 walk
~13 s on one core of the 2 vCPU test machine under load 4-5.
"""

from __future__ import annotations

import math
from dataclasses import fields, replace

import numpy as np
import pyarrow.parquet as pq
import pytest
import torch

from tests.reference.hfunction import diffuse_reflectance_isotropic_matched
from tests.support.tables import bitwise_equal
from tests.workers.test_shared_walks import TOTAL, assert_optional_field, assert_refused, assert_rows_agree, sweep_results, sweep_spec
from workers.walk.path_roulette import check_steps_per_call, roulette_round
from workers.run.simulate import simulate_sweep
from workers.walk.walk import ABSORBED, EXITED, RUNNING, Lanes, WalkParams, step_function

ROULETTE = {"start": 16, "survival": 0.5}
ROULETTE_ALBEDO_1 = {"start": 16, "survival": 0.75}


def lanes_at(steps, status, photon) -> Lanes:
    n = len(steps)
    lanes = Lanes.empty(n)
    lanes.step[:] = torch.as_tensor(steps, dtype=torch.int32)
    lanes.status[:] = torch.as_tensor(status, dtype=torch.int32)
    lanes.photon[:] = torch.as_tensor(photon, dtype=torch.int64)
    lanes.c_lo[:] = (lanes.photon & 0xFFFFFFFF).to(torch.int32)  # low words; high words 0 here
    lanes.k0[:], lanes.k1[:] = 12345, -777
    lanes.w[:] = 0.75
    return lanes


def test_a_round_touches_only_running_photons_at_start_times_powers_of_two():
    steps = [0, 8, 15, 16, 24, 32, 48, 64, 1024, 1032, 16, 64]
    status = [RUNNING] * 10 + [EXITED, ABSORBED]
    lanes = lanes_at(steps, status, range(len(steps)))
    roulette_round(lanes, 16, 0.5)
    due = np.array([s >= 16 and s & (s - 1) == 0 for s in steps]) & (np.array(status) == RUNNING)
    w, st = lanes.w.numpy(), lanes.status.numpy()
    assert np.all(w[~due] == np.float32(0.75)) and np.all(st[~due] == np.array(status)[~due])
    assert np.all((w[due] == np.float32(1.5)) & (st[due] == RUNNING) | (w[due] == 0.0) & (st[due] == ABSORBED))


def test_survival_fraction_weights_and_lane_independence():
    n, s = 1 << 16, 0.3
    lanes = lanes_at(np.full(n, 64), np.full(n, RUNNING), np.arange(n))
    ended = roulette_round(lanes, 16, s)
    live = lanes.status.numpy() == RUNNING
    assert ended == n - live.sum()
    sd = math.sqrt(n * s * (1 - s))
    assert abs(live.sum() - n * s) <= 4.0 * sd, (live.sum(), n * s, sd)  # 4 sigma binomial bound
    assert np.all(lanes.w.numpy()[live] == np.float32(np.float32(0.75) * np.float32(1 / s)))
    assert np.all(lanes.w.numpy()[~live] == 0.0)
    # Expected weight after the round is the weight before: mean of w' against 0.75, with its error.
    wm, se = lanes.w.double().mean().item(), lanes.w.double().std().item() / math.sqrt(n)
    assert abs(wm - 0.75) <= 4.0 * se
    # The same photons in another lane order (and lane count) get the same outcome.
    perm = np.random.default_rng(1).permutation(n)[: n // 3]
    other = lanes_at(np.full(len(perm), 64), np.full(len(perm), RUNNING), perm)
    roulette_round(other, 16, s)
    assert np.array_equal(other.status.numpy(), lanes.status.numpy()[perm])
    # Another step count is another round: not the same outcomes.
    again = lanes_at(np.full(n, 128), np.full(n, RUNNING), np.arange(n))
    roulette_round(again, 16, s)
    assert not np.array_equal(again.status.numpy(), lanes.status.numpy())


def test_the_step_function_plays_the_round_after_its_last_step():
    """The walk plays the round inside its (compiled) step function: the same lanes as stepping
    without it and then playing :func:`roulette_round`, to the bit, with some lanes due."""
    n = 4096
    lanes = lanes_at(np.full(n, 8), np.full(n, RUNNING), np.arange(n))  # step 8 + 8 steps = 16: due
    lanes.step[: n // 4] = 0  # a quarter reaches step 8 only: not due
    lanes.z[:], lanes.uz[:], lanes.albedo[:] = -3.0, -1.0, 0.999
    lanes.start_streams()
    base = WalkParams(inv_eta=1.0 / 1.33, analog=False, max_scatter=1 << 20)
    plain, fused = lanes.view(0, n), Lanes(*(t.clone() for t in lanes.tensors()))
    step_function(base, 8, False, False)(plain)
    ended = roulette_round(plain, 16, 0.5)
    step_function(replace(base, roulette=(16, 0.5)), 8, False, False)(fused)
    assert ended > 0 and (plain.status.numpy() == RUNNING).sum() > 0
    for name, a, b in zip((f.name for f in fields(Lanes)), plain.tensors(), fused.tensors()):
        assert torch.equal(a, b), name


def test_start_must_be_a_multiple_of_the_steps_per_call():
    check_steps_per_call(16, 8)
    with pytest.raises(ValueError, match="path_roulette.start 16 must be a multiple"):
        check_steps_per_call(16, 32)


@pytest.mark.parametrize("value, words", [
    ({"start": 24}, ["path_roulette.start", "power of two", "24"]),
    ({"start": 8}, ["path_roulette.start", "[16, 2**24]", "8"]),
    ({"start": 1 << 25}, ["path_roulette.start", "[16, 2**24]"]),
    ({"start": 64, "survival": 0.0}, ["path_roulette.survival", "(0, 1]", "0"]),
    ({"start": 64, "survival": 1.5}, ["path_roulette.survival", "(0, 1]", "1.5"]),
    ({"start": 64, "surviv": 0.5}, ["path_roulette.surviv"]),
])
def test_bad_roulette_fields_are_refused_with_the_field_and_range(value, words):
    assert_refused("path_roulette", value, words)


def test_off_by_default_and_absent_from_the_canonical_spec():
    assert_optional_field("path_roulette", ROULETTE)


# -- statistics ----------------------------------------------------------------------------------


@pytest.fixture(scope="module", params=["exits", "hybrid"])
def pair(request):
    est = request.param
    return (est, sweep_results(sweep_spec(est, "shared", 1, 2**16, path_roulette=ROULETTE)),
            sweep_results(sweep_spec(est, "independent", 2, 2**16)))


@pytest.mark.slow
def test_roulette_shared_walks_agree_with_plain_independent_walks_in_every_bin(pair, walk_stats):
    est, rr, plain = pair
    assert_rows_agree(rr, plain, est, f"{est}: roulette {ROULETTE} shared (seed 1) against plain independent (seed 2)", walk_stats)


@pytest.mark.slow
def test_roulette_bites_at_this_setting(pair):
    """The agreement above is not vacuous: the leader's walk (albedo 0.99, mean path ~100 steps)
    loses most of its long paths to the rounds, so its absorbed power's error grows."""
    est, rr, plain = pair
    assert rr[-1].stderr("walk/absorbed")[0] > 1.5 * plain[-1].stderr("walk/absorbed")[0]


@pytest.mark.slow
def test_roulette_rd_at_albedo_one_matches_the_h_function(walk_stats):
    albedos = [0.6, 0.9, 0.99, 1.0]
    # survival > 1/sqrt(2): at albedo 1 the weights of the paths surviving k rounds stay bounded
    # in variance (workers.walk.path_roulette), so the per-photon error bar holds.
    spec = sweep_spec("exits", "shared", 5, 2**15, eta=1.0, albedos=albedos, path_roulette=ROULETTE_ALBEDO_1, max_scatter=4096,
                      bins={"radial": {"count": 1, "max_mm": 100.0}})
    results = sweep_results(spec)
    assert len(spec.walk_groups()) == 1
    z = []
    for r, a in zip(results, albedos):
        rd, se = r.mean("exits/Rd")[0, TOTAL], r.stderr("exits/Rd")[0, TOTAL]
        if a == 1.0:  # nothing absorbed: what did not exit was truncated (or ended by a round, mean 0)
            exact = 1.0 - float(r.mean("walk/truncated")[0])
            # Var(Rd + truncated) <= Var(Rd) + Var(truncated): the two are anticorrelated per photon.
            se_t = float(r.stderr("walk/truncated")[0])
            se = math.hypot(se, se_t if math.isfinite(se_t) else 0.0)  # nan: nothing truncated
        else:
            exact = diffuse_reflectance_isotropic_matched(a)
        print(f"a = {a}: Rd {rd:.6f} +- {se:.2e} vs {exact:.6f}")
        # The bar of the direct walk's H-function test: 3 se plus 0.2 % (float32 walk).
        assert abs(rd - exact) <= 3.0 * se + 0.002 * exact, f"a = {a}: {rd:.6f} +- {se:.2e} against {exact:.6f}"
        z.append((rd - exact) / se)
    walk_stats.assert_within(z, min(r.dof("exits/Rd") for r in results), "roulette Rd against the H-function")


def test_same_bytes_on_one_thread_and_two_processes(tmp_path):
    spec = sweep_spec("hybrid", "shared", 9, 3000, path_roulette=ROULETTE)
    simulate_sweep(spec, str(tmp_path / "a"), threads=1)
    simulate_sweep(spec, str(tmp_path / "b"), processes=2)
    for name in ("radial", "bins", "summary"):
        a, b = pq.read_table(tmp_path / "a" / f"{name}.parquet"), pq.read_table(tmp_path / "b" / f"{name}.parquet")
        assert bitwise_equal(a, b), name


def test_table_cost_passes_the_roulette_to_its_sweep(capsys):
    import json

    from workers.measure.table_cost import main

    assert main(["--albedos", "0.5,0.9", "--photons", "3000", "--path-roulette", "16,0.75", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["path_roulette"] == {"start": 16, "survival": 0.75}
    assert [g["albedos"] for g in out["groups"]] == [[0.5, 0.5], [0.9, 0.9]]  # the default edges 0.3, 0.7 part them
    assert all(math.isfinite(out["cpu_hours"][k]) and out["cpu_hours"][k] > 0 for k in ("all", "major"))
