"""Sweeps in the workers: a sweep's entry equals the single-medium job of that medium
bit for bit; the streaming fold (one accumulator, shard by shard, saved and restored between
processes) gives the bytes of the merge of a list; the job fold runs media in task order and
stops a medium early under a stop rule with the result of exactly its first K shards; the same
sweep on one thread and on three worker processes gives identical bytes."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyarrow.compute as pc
import pyarrow.parquet as pq
import pytest

from schema import parse_spec
from tests.support.tables import bitwise_equal
from tests.support.tallies import tally_digest
from workers.fold.merge import Fold, MergeError, merge
from workers.fold.output import write_tables
from workers.run.shard import run_shard
from workers.run.simulate import simulate, simulate_sweep
from workers.fold.job import JobFold
from workers.run.task import run_task
from workers.fold.tally import ShardTally

TABLES = ("radial", "bins", "summary")
BINS = {"radial": {"count": 4, "max_mm": 3.0}, "theta_s": {"count": 2}, "cos_theta_o": {"count": 2}, "phi_o": {"count": 2}}


def sweep(**kw):
    # Two etas (one index-matched), a g on each side of the HG branch split, an oblique angle,
    # both estimators; analog absorption keeps the connection work small.
    d = {"name": "sw", "sweep": {"albedo": [0.4, 0.95], "g": [0.0, 0.8], "eta": [1.0, 1.4]},
         "incidence_deg": [0, 35], "photons": 36, "shards": 2, "batches_per_shard": 2, "estimator": "both",
         "absorption": "analog", "seed": 5, "bins": BINS}
    d.update(kw)
    return parse_spec(d)


@pytest.fixture(scope="module")
def spec():
    return sweep()


@pytest.fixture(scope="module")
def out(spec, tmp_path_factory):
    path = tmp_path_factory.mktemp("sweep")
    assert simulate_sweep(spec, str(path), threads=1) == ["radial.parquet", "bins.parquet", "summary.parquet", "summary.json"]
    return path


def _rows(path: Path, name: str, medium: int):
    t = pq.read_table(path / f"{name}.parquet")
    return t.filter(pc.equal(t["medium"], medium)).drop(["medium"])


@pytest.mark.parametrize("medium", [0, 3, 6])  # (albedo, g, eta) = (0.4, 0, 1), (0.95, 0.8, 1), (0.4, 0.8, 1.4)
def test_sweep_entry_is_the_single_medium_job_bit_for_bit(spec, out, medium, tmp_path):
    single = spec.medium_spec(medium)
    write_tables(simulate(single, threads=1), str(tmp_path))
    for name in TABLES:
        mine, theirs = _rows(out, name, medium), pq.read_table(tmp_path / f"{name}.parquet")
        assert set(theirs["medium"].to_pylist()) == {0}
        assert mine.num_rows == theirs.num_rows > 0
        assert bitwise_equal(mine, theirs.drop(["medium"])), name  # every value, every bit


def test_sweep_tables_hold_every_medium_in_order(spec, out):
    per_medium = {"radial": 2 * 2 * 3 * 4, "bins": 2 * 2 * 3 * 4 * 2 * 2 * 2, "summary": 2 * 2 * 3}
    for name in TABLES:
        t = pq.read_table(out / f"{name}.parquet")
        media = t["medium"].to_pylist()
        assert media == sorted(media) and t.num_rows == 8 * per_medium[name]
        assert pq.ParquetFile(out / f"{name}.parquet").metadata.num_row_groups == 8  # a row group per medium
        for m in spec.media():
            rows = t.filter(pc.equal(t["medium"], m.index))
            assert set(rows["albedo"].to_pylist()) == {m.albedo[0]} and set(rows["g"].to_pylist()) == {m.g[0]}
            assert set(rows["eta"].to_pylist()) == {m.eta}
    assert not (out / ".parts").exists()


def test_one_thread_and_three_processes_give_identical_bytes(spec, out, tmp_path):
    simulate_sweep(spec, str(tmp_path), processes=3)
    for name in ("radial.parquet", "bins.parquet", "summary.parquet", "summary.json"):
        assert (tmp_path / name).read_bytes() == (out / name).read_bytes(), name


def test_run_task_is_shard_of_the_mediums_own_spec(spec):
    t = spec.task_index(5, 1)
    assert tally_digest(run_task(spec, t)) == tally_digest(run_shard(spec.medium_spec(5), 1))


# ---- the streaming fold ---------------------------------------------------------------------


@pytest.fixture(scope="module")
def medium_tallies(spec):
    single = spec.medium_spec(4)
    return single, [run_shard(single, i) for i in range(single.shards)]


def _same(a, b) -> bool:
    return a.keys() == b.keys() and all(x.tobytes() == y.tobytes() for n in a for x, y in zip(a[n], b[n]))


def test_fold_saved_and_restored_midway_gives_the_merge_bytes(medium_tallies):
    single, tallies = medium_tallies
    fold = Fold(single, 4)
    fold.add(tallies[0])
    restored = Fold.from_state(single, ShardTally.from_bytes(fold.state().to_bytes()))
    assert restored.shards == 1 and restored.medium_index == 4 and not restored.complete
    for t in tallies[1:]:
        restored.add(t)
    assert restored.complete
    reference = merge(single, list(reversed(tallies)))
    assert _same(restored.result().stats, reference.stats)
    assert restored.n_sum == reference.n_sum
    assert restored.counts.keys() == reference.counts.keys()
    assert all(np.array_equal(restored.counts[k], reference.counts[k]) for k in reference.counts)


def test_fold_refuses_shards_out_of_order(medium_tallies):
    single, tallies = medium_tallies
    fold = Fold(single)
    with pytest.raises(MergeError, match="expected shard 0"):
        fold.add(tallies[1])
    with pytest.raises(MergeError, match="no shard"):
        fold.result()


def test_job_fold_in_task_order_with_an_early_stop(spec):
    """A stop rule holding at 1 shard for medium 1 ends it there: its result is exactly its
    shard 0, task 3 (its shard 1) is skipped, and the fold goes on with medium 2's shard 0;
    saved and restored midway it gives the same."""
    stop_at_one = lambda r: r.medium_index == 1 and len(r.shard_info) == 1  # noqa: E731
    job = JobFold(spec, stop_at_one)
    results = {}
    for task in range(6):  # media 0, 1 (stopped after 1 shard), 2
        if task == 3:
            assert job.next_task == 4 and list(job.skipped) == [3]
            continue
        if task == 5:
            job = JobFold.from_state(spec, ShardTally.from_bytes(job.state().to_bytes()), stop_at_one)
        r = job.add(task, run_task(spec, task))
        if r is not None:
            results[r.medium_index] = r
    assert sorted(results) == [0, 1, 2] and job.medium == 3 and job.next_task == 6
    single = spec.medium_spec(1)
    first = Fold(single, 1)
    first.add(run_shard(single, 0))
    assert _same(results[1].stats, first.result().stats) and results[1].n_sum == 18
    assert _same(results[2].stats, merge(spec.medium_spec(2), [run_task(spec, 4), run_task(spec, 5)]).stats)
    assert [m["shards"] for m in job.media] == [2, 1, 2]
    with pytest.raises(MergeError, match="expects task 6"):
        job.add(7, run_task(spec, 7))


def test_simulate_sweep_with_a_stop_rule_skips_the_rest_of_that_medium(tmp_path):
    small = sweep(sweep={"albedo": [0.5, 0.9], "g": [0.5], "eta": [1.3]}, estimator="exits", shards=4)
    simulate_sweep(small, str(tmp_path), threads=2, stop_rule=lambda r: r.medium_index == 0 and len(r.shard_info) == 1)
    summary = pq.read_table(tmp_path / "summary.parquet")
    photons = dict(zip(summary["medium"].to_pylist(), summary["photons"].to_pylist()))
    assert photons == {0: 36 // 4, 1: 36}


def test_sweep_to_a_target_error_equals_each_mediums_own_run_to_it(tmp_path):
    """With a target, each medium stops at the first K shards that meet it (workers.fold.target), the
    same K and the same bits as that medium's single-medium run to the target: here the bright
    medium stops before its last shard, the dark one never meets it and runs all six."""
    spec = sweep(sweep={"albedo": [0.3, 0.9], "g": [0.0], "eta": [1.3]}, estimator="exits", shards=6,
                 photons=240, target={"rel_stderr": 0.15})
    simulate_sweep(spec, str(tmp_path / "sweep"), threads=2)
    doc = __import__("json").loads((tmp_path / "sweep" / "summary.json").read_text())
    assert [t["reached"] for t in doc["target"]] == [False, True]
    for m in range(2):
        single = spec.medium_spec(m)
        result = simulate(single, threads=1)
        assert result.target.as_dict() == doc["target"][m]
        assert (len(result.shard_info) < 6) == (m == 1), len(result.shard_info)
        write_tables(result, str(tmp_path / f"m{m}"))
        assert doc["run"]["shards_folded"][m] == len(result.shard_info)
        for name in TABLES:
            theirs = pq.read_table(tmp_path / f"m{m}" / f"{name}.parquet").drop(["medium"])
            assert bitwise_equal(_rows(tmp_path / "sweep", name, m), theirs), (m, name)
