"""Fixtures of the workers tests: small measured datasets the export tests share (made once per
session, eager walk, seconds each)."""

from __future__ import annotations

import pytest

from schema import parse_spec

# Two channels, normal and oblique incidence, both estimators, a few bins of every kind.
ARRAYS_SPEC = {
    "name": "arrays", "medium": {"sigma_a": [0.2, 0.05], "sigma_s": [1.8, 0.95], "g": [0.0, 0.7], "eta": 1.4,
                                 "channel_names": ["R", "G"]},
    "incidence_deg": [0, 45], "photons": 400, "shards": 2, "batches_per_shard": 2, "seed": 9, "estimator": "both",
    "bins": {"radial": {"count": 6, "max_mm": 3.0, "spacing": "linear"}, "theta_s": {"count": 3},
             "cos_theta_o": {"count": 2}, "phi_o": {"count": 2}},
}


@pytest.fixture(scope="session")
def arrays_source(tmp_path_factory):
    """The ExportSource of a measured ARRAYS_SPEC dataset."""
    from workers.exports.source import ExportSource
    from workers.fold.output import write_tables
    from workers.run.simulate import simulate

    out = tmp_path_factory.mktemp("arrays")
    write_tables(simulate(parse_spec(ARRAYS_SPEC), threads=1), str(out))
    return ExportSource.from_directory(out)
