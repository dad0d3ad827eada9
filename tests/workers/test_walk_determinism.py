"""Determinism (docs/architecture.md, "Determinism").

A spec and seed give bitwise-identical statistics and tables whatever the shard order, the torch
thread count and how often a shard runs; the shard count belongs to the spec.  The walk here is
the eager one (conftest.py); the compiled one is checked the same way in a subprocess (slow:
compiling the step takes 30-60 s).  ShardTally.info holds timings and machine facts that the
run_shard docstring excludes from the contract, so bytes are compared with info set aside.
"""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from tests.support.tallies import tally_digest
from workers.fold.merge import merge
from workers.fold.output import write_tables
from workers.run.shard import run_shard
from workers.fold.tally import ShardTally

# "both" estimators, an oblique angle next to normal incidence, every bin axis split; analog
# absorption keeps the connection work small (~5 vertices per photon).
SPEC = dict(
    sigma_a=0.2, sigma_s=0.8, g=0.6, eta=1.3, n_r=4, max_mm=3.0, n_theta=3, n_cos=2, n_phi=2,
    incidence_deg=[0.0, 40.0], photons=1500, shards=3, batches_per_shard=4, estimator="both",
    absorption="analog", seed=91,
)  # fmt: skip


def _same_counts(a: dict[str, np.ndarray], b: dict[str, np.ndarray]) -> bool:
    return a.keys() == b.keys() and all(a[n].dtype == b[n].dtype and a[n].tobytes() == b[n].tobytes() for n in a)


def _same_stats(a: dict[str, list[np.ndarray]], b: dict[str, list[np.ndarray]]) -> bool:
    return a.keys() == b.keys() and all(
        x.dtype == y.dtype and x.shape == y.shape and x.tobytes() == y.tobytes() for n in a for x, y in zip(a[n], b[n])
    )


@pytest.fixture(scope="module")
def spec(walk_spec):
    return walk_spec(**SPEC)


@pytest.fixture(scope="module")
def tallies(spec):
    return [run_shard(spec, i) for i in range(spec.shards)]


def test_run_shard_is_a_pure_function(spec, tallies):
    again = run_shard(spec, 1)
    assert _same_stats(again.stats, tallies[1].stats)
    assert tally_digest(again) == tally_digest(tallies[1])
    assert (again.shard_index, again.n_sum) == (1, tallies[1].n_sum)
    assert _same_counts(again.counts, tallies[1].counts)


def test_shard_tally_round_trips_through_bytes(spec, tallies):
    for t in tallies:
        back = ShardTally.from_bytes(t.to_bytes())
        assert (back.shard_index, back.n_sum, back.info) == (t.shard_index, t.n_sum, t.info)
        assert _same_stats(back.stats, t.stats) and _same_counts(back.counts, t.counts)
        assert back.to_bytes() == t.to_bytes()
    restored = merge(spec, [ShardTally.from_bytes(t.to_bytes()) for t in tallies])
    assert _same_stats(restored.stats, merge(spec, tallies).stats)


def test_merge_is_bitwise_independent_of_shard_order(spec, tallies):
    reference = merge(spec, tallies)
    for order in ([2, 0, 1], [1, 2, 0], [2, 1, 0]):
        other = merge(spec, [tallies[i] for i in order])
        assert _same_stats(other.stats, reference.stats), order
        assert other.n_sum == reference.n_sum and _same_counts(other.counts, reference.counts)


def test_shards_run_in_another_order_give_the_same_bytes(spec, tallies):
    """Run the shards last-first (a different history of the process)."""
    late = {i: run_shard(spec, i) for i in reversed(range(spec.shards))}
    for i, t in enumerate(tallies):
        assert tally_digest(late[i]) == tally_digest(t), f"shard {i}"


def test_worker_processes_give_the_same_bytes(spec, tallies):
    """Shards on two worker processes (what `bssrdf simulate` does), in whatever order they
    finish, give the bytes of the shards run here; progress reaches this process."""
    from workers.run.pool import ShardPool

    seen = []
    with ShardPool(2) as pool:
        remote = pool.run(spec, [2, 0, 1], progress=seen.append)
    assert [t.shard_index for t in remote] == [2, 0, 1]
    for t in remote:
        assert tally_digest(t) == tally_digest(tallies[t.shard_index]), f"shard {t.shard_index}"
        assert t.info["cpu_s"] > 0
    n_cfg = len(spec.incidence_deg) * len(spec.channels())
    assert sum(seen) == spec.photons * n_cfg


def test_tables_are_byte_identical(spec, tallies, tmp_path):
    write_tables(merge(spec, tallies), str(tmp_path / "a"))
    rerun = [run_shard(spec, i) for i in reversed(range(spec.shards))]
    write_tables(merge(spec, rerun), str(tmp_path / "b"))
    names = sorted(p.name for p in (tmp_path / "a").iterdir())
    assert names == sorted(p.name for p in (tmp_path / "b").iterdir()) and "bins.parquet" in names
    for name in names:
        assert (tmp_path / "a" / name).read_bytes() == (tmp_path / "b" / name).read_bytes(), name


@pytest.mark.parametrize("threads", [1, 2])
def test_thread_count_does_not_change_the_bits(spec, tallies, threads):
    previous = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        t = run_shard(spec, 0)
    finally:
        torch.set_num_threads(previous)
    assert tally_digest(t) == tally_digest(tallies[0]), f"torch threads {threads} vs {previous}"


def test_shard_count_is_part_of_the_spec(walk_spec, spec, tallies, walk_stats):
    """Another shard count splits the photons differently; results agree within error bars."""
    other_spec = walk_spec(**dict(SPEC, shards=2, batches_per_shard=6))
    assert other_spec.spec_hash() != spec.spec_hash()
    a, b = merge(spec, tallies), merge(other_spec, [run_shard(other_spec, i) for i in range(2)])
    assert a.n_sum == b.n_sum == SPEC["photons"] and a.units("connections/Rd")[0] == b.units("connections/Rd")[0] == 12
    z = []
    for name in ("exits/Rd", "connections/Rd", "walk/absorbed"):
        # The two runs share photons, so their difference is smaller than sqrt(se_a^2 + se_b^2):
        # conservative, and enough to see that both describe the same medium.
        z.append(walk_stats.z(a.mean(name), a.stderr(name), b.mean(name), b.stderr(name)).ravel())
    walk_stats.assert_within(np.concatenate(z), walk_stats.dof(a), "3 shards vs 2 shards")


_COMPILED_SCRIPT = """
import dataclasses, hashlib, json, sys
import torch
from schema import SimulationSpec
from workers.run.shard import run_shard

spec = SimulationSpec.model_validate_json(sys.argv[1])
out = {}
for threads in (1, 2):
    torch.set_num_threads(threads)
    t = run_shard(spec, 0)
    out[threads] = {
        "engine": t.info["engine"],
        "digest": hashlib.sha256(dataclasses.replace(t, info={}).to_bytes()).hexdigest(),
        "stats": {name: [a.tolist() for a in t.stats[name]] for name in ("exits/Rd", "connections/Rd")},
        "n_sum": t.n_sum, "counts": {name: t.counts[name].tolist() for name in sorted(t.counts)},
    }
print(json.dumps(out))
"""


def _run_compiled(script: str, spec) -> dict:
    """Run script (which prints one JSON line last) with BSSRDF_COMPILE=1 in a fresh process."""
    env = dict(os.environ, BSSRDF_COMPILE="1")
    root = Path(__file__).resolve().parents[2]
    proc = subprocess.run(
        [sys.executable, "-c", script, spec.model_dump_json()],
        cwd=root, env=env, capture_output=True, text=True, timeout=900,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-4000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


@pytest.mark.slow
def test_compiled_walk_is_deterministic_and_agrees_with_eager(walk_spec, walk_stats):
    """BSSRDF_COMPILE=1 in a fresh process: bitwise the same for 1 and 2 torch threads, and the
    same physics as the eager walk within error bars (not bitwise: fused kernels round differently)."""
    spec = walk_spec(**dict(SPEC, incidence_deg=[40.0], shards=1, batches_per_shard=16, photons=2048))
    runs = _run_compiled(_COMPILED_SCRIPT, spec)
    one, two = runs["1"], runs["2"]
    assert one["engine"] == two["engine"] == "compiled"
    assert one["digest"] == two["digest"], "compiled walk: 1 and 2 torch threads differ"

    # Compiled vs eager: the same estimates within error bars.
    eager = merge(spec, [run_shard(spec, 0)])
    assert one["n_sum"] == eager.n_sum
    counts = {k: np.array(v) for k, v in one["counts"].items()}
    assert all(np.array_equal(v, eager.counts[k]) for k, v in counts.items() if k.startswith("units/"))
    compiled_result = dataclasses.replace(eager, stats={k: [np.array(a) for a in v] for k, v in one["stats"].items()}, counts=counts)
    z = []
    for name in ("exits/Rd", "connections/Rd"):
        z.append(walk_stats.z(compiled_result.mean(name), compiled_result.stderr(name), eager.mean(name), eager.stderr(name)).ravel())
    walk_stats.assert_within(np.concatenate(z), walk_stats.dof(eager), "compiled vs eager (same photons: conservative)")


_COMPILED_EXITS_SCRIPT = """
import json, sys
import torch
from schema import SimulationSpec
from workers.run.shard import run_shard

torch.set_num_threads(1)
spec = SimulationSpec.model_validate_json(sys.argv[1])
t = run_shard(spec, 0)
print(json.dumps({
    "engine": t.info["engine"], "tail_lanes": t.info["tail_lanes"], "tail_chunks": t.info["tail_chunks"], "lanes": t.info["lanes"], "n_sum": t.n_sum,
    "counts": {name: t.counts[name].tolist() for name in sorted(t.counts)},
    "stats": {name: [a.tolist() for a in t.stats[name]] for name in ("exits/Rd", "exits/radial_G", "walk/absorbed")},
}))
"""


@pytest.mark.slow
def test_compiled_exit_walk_with_its_compacted_tail_agrees_with_eager(walk_stats):
    """The compiled exit walk (8 steps per call, the shard's last photons compacted to ever fewer
    lanes) against the eager walk on independent photons (another seed): Rd, Rd(r) of every
    component and the absorbed power agree within error bars.  The medium is the benchmark's
    M2, whose kernels the benchmark has usually compiled already."""
    from workers.measure.bench import _spec
    from workers.run.plan import TAIL_FILL

    base = _spec("M2", "exits", 200_000).model_copy(update={"batches_per_shard": 64})
    compiled_spec = base.model_copy(update={"seed": base.seed + 1})
    got = _run_compiled(_COMPILED_EXITS_SCRIPT, compiled_spec)
    assert got["engine"] == "compiled"
    assert got["tail_lanes"] and 0 < got["tail_lanes"] <= TAIL_FILL * got["lanes"], "the tail must have been compacted"
    assert len(got["tail_chunks"]) >= 3 and all(n % 16 == 0 for n in got["tail_chunks"]), got["tail_chunks"]
    assert got["n_sum"] == 200_000

    eager = merge(base, [run_shard(base, 0)])
    counts = {k: np.array(v) for k, v in got["counts"].items()}
    compiled = dataclasses.replace(eager, stats={k: [np.array(a) for a in v] for k, v in got["stats"].items()}, counts=counts)
    def z_of(name: str, sel=slice(None)) -> np.ndarray:
        a, sa, b, sb = (v[sel] for v in (compiled.mean(name), compiled.stderr(name), eager.mean(name), eager.stderr(name)))
        keep = np.isfinite(sa) | np.isfinite(sb)  # bins no photon reached in either run carry no information
        sa, sb = np.nan_to_num(sa), np.nan_to_num(sb)  # reached in one run only: the other's estimate is an exact 0
        return walk_stats.z(a[keep], sa[keep], b[keep], sb[keep]).ravel()

    dof = walk_stats.dof(eager)
    headline = np.concatenate([z_of("exits/Rd"), z_of("walk/absorbed")])
    walk_stats.assert_within(headline, dof, "compiled (with tail) vs eager: Rd per component, absorbed")
    walk_stats.assert_within(z_of("exits/radial_G", (slice(None), 2)), dof, "compiled (with tail) vs eager: Rd(r), total")


def test_every_chunk_length_a_compiled_shard_steps_is_a_multiple_of_the_vector_width():
    """One step kernel serves every chunk length (workers.walk.kernels.compile_kernel's
    any_length).  Lanes past the last multiple of the vector width (16 float32 lanes with
    AVX-512) would run in the kernel's scalar loop, whose math functions may round differently,
    and a photon's result would depend on its lane: the chunks and every length a tail is
    compacted to are multiples of 16, and a tail's length holds its running photons."""
    from workers.run import plan
    from workers.run.shard import _tail_length

    assert all(n % 16 == 0 for n in (plan.CHUNK, plan.CONNECT_CHUNK, plan.EAGER_CHUNK, plan.LANE_MULTIPLE))
    for running in range(0, 5000):
        n = _tail_length(running)
        assert n % 16 == 0 and running <= n < running + 16 + (running == 0) * 16, (running, n)


def test_a_compacted_tail_tallies_the_same_photons(walk_spec, monkeypatch):
    """The last photons of a long tail (albedo 1: a few paths of thousands of steps) are moved
    to the front and stepped alone, the lanes rounded up to 16, each time they fill no more
    than TAIL_FILL of the stepped lanes (workers.run.shard: compact).  Moving lanes changes no
    photon's path, only when its results are summed: with and without compaction the same
    photons give the same event counts and the same sums to rounding (eager engine: the same
    code paths, no compile)."""
    import workers.run.shard as shard

    monkeypatch.setenv("BSSRDF_COMPILE", "0")
    spec = walk_spec(sigma_a=0.0, sigma_s=1.0, eta=1.33, photons=1000, estimator="hybrid", seed=11, max_scatter=3000,
                     path_roulette={"start": 64, "survival": 0.75})
    compacted = run_shard(spec, 0)
    monkeypatch.setattr(shard, "TAIL_FILL", -1.0)  # never
    plain = run_shard(spec, 0)
    lengths = compacted.info["tail_chunks"]
    assert len(lengths) >= 3 and lengths == sorted(lengths, reverse=True) and plain.info["tail_chunks"] == [], (compacted.info, plain.info)
    assert compacted.info["photon_steps"] == plain.info["photon_steps"]
    assert compacted.info["lane_steps"] == plain.info["lane_steps"], "compaction must not change how many steps the shard runs"
    assert compacted.counts.keys() == plain.counts.keys() and compacted.stats.keys() == plain.stats.keys()
    for name in compacted.counts:
        np.testing.assert_array_equal(compacted.counts[name], plain.counts[name], err_msg=name)
    for name in compacted.stats:
        for a, b in zip(compacted.stats[name], plain.stats[name]):
            np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-300, err_msg=name)


def test_the_padding_of_a_harvest_call_changes_no_bit(walk_spec, monkeypatch):
    """A harvest is one kernel call over its lanes, padded to a multiple of LANE_MULTIPLE with
    the scratch lane (workers.run.shard).  The hybrid's entries are tallied per harvest with the
    padding's entries set to weight 0, and the per-lane records are cut to the real lanes: so any
    padding gives the same bytes, members included (eager engine: the same code as the compiled
    path, no compile).  It fails if padded entries reach a sum or an event count."""
    import workers.run.shard as shard

    monkeypatch.setenv("BSSRDF_COMPILE", "0")
    spec = walk_spec(sigma_a=0.1, sigma_s=0.9, eta=1.0, photons=6000, estimator="hybrid", seed=5, shards=1, batches_per_shard=4)
    digests, padded = [], []
    harvest = shard._Runner.finish_and_refill

    def counting(self, idx, finished=True):
        padded.append(-len(idx) % shard.LANE_MULTIPLE)
        return harvest(self, idx, finished)

    monkeypatch.setattr(shard._Runner, "finish_and_refill", counting)
    for multiple in (1, 16, 512):
        monkeypatch.setattr(shard, "LANE_MULTIPLE", multiple)
        padded.clear()
        digests.append(tally_digest(run_shard(spec, 0, members=(0.7,))))
        assert multiple == 1 or sum(p > 0 for p in padded) >= 3, "the harvests must have been padded"
    assert digests[0] == digests[1] == digests[2]
