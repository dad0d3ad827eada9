"""schema.sizes against what is really stored: the shard payload estimate is exactly the bytes of
a shard's arrays, and the dataset estimate bounds the tables' Parquet size before compression."""

from __future__ import annotations

import pyarrow.parquet as pq
import pytest

from schema import parse_spec
from schema.sizes import estimate_sizes, size_limit_problems
from workers.fold.output import write_tables
from workers.run.shard import run_shard
from workers.run.simulate import simulate


@pytest.mark.parametrize("estimator, channels", [("exits", "preset"), ("both", "explicit")])
def test_estimates_against_a_real_shard_and_dataset(estimator, channels, tmp_path):
    medium = {"preset": "skin1"} if channels == "preset" else {"sigma_a": 0.1, "sigma_s": 0.9, "eta": 1.3}
    spec = parse_spec({"name": "sz", "medium": medium, "photons": 16, "shards": 2, "estimator": estimator,
                       "incidence_deg": [0, 30], "absorption": "analog",
                       "bins": {"radial": {"count": 5}, "cos_theta_o": {"count": 3}, "phi_o": {"count": 2}}})
    est = estimate_sizes(spec)
    tally = run_shard(spec, 0)
    assert est.shard_payload_bytes == sum(a.nbytes for v in tally.stats.values() for a in v) + sum(c.nbytes for c in tally.counts.values())
    write_tables(simulate(spec, threads=1), str(tmp_path))
    parquet = [pq.ParquetFile(tmp_path / f"{n}.parquet").metadata for n in ("radial", "bins", "summary")]
    assert est.rows == sum(m.num_rows for m in parquet)
    uncompressed = sum(m.row_group(i).total_byte_size for m in parquet for i in range(m.num_row_groups))
    assert uncompressed <= est.dataset_bytes


def test_limits_name_the_field_the_estimate_and_the_limit():
    sweep = parse_spec({"name": "sz", "sweep": {"albedo": {"count": 100}, "g": [0.0, 0.5], "eta": [1.3]},
                        "photons": 1000, "shards": 2})
    est = estimate_sizes(sweep)
    # Shared walks (the default here): a task tallies every albedo of its walk group.
    largest = max(len(g) for g in sweep.walk_groups())
    one = estimate_sizes(sweep.medium_spec(7)).shard_payload_bytes
    assert est.media == 200 and largest > 1 and est.shard_payload_bytes == largest * one
    independent = parse_spec({**sweep.model_dump(mode="json"), "sweep": {**sweep.sweep.model_dump(mode="json"), "walks": "independent"}})
    assert estimate_sizes(independent).shard_payload_bytes == one
    assert size_limit_problems(sweep, est.shard_payload_bytes, est.dataset_bytes) == []
    (shard,) = size_limit_problems(sweep, est.shard_payload_bytes - 1, est.dataset_bytes)
    assert shard[0] == "spec.bins" and str(est.shard_payload_bytes) in shard[1] and "BSSRDF_MAX_SHARD_BYTES" in shard[1]
    (data,) = size_limit_problems(sweep, est.shard_payload_bytes, est.dataset_bytes - 1)
    assert data[0] == "spec.sweep" and str(est.dataset_bytes) in data[1] and "200 media" in data[1]
    assert data[3] == est.dataset_bytes
