"""`bssrdf bench`: the figures it reports are consistent with the runs behind them."""

from __future__ import annotations

import argparse

import pytest

from workers.measure.bench import _arguments, bench_one


def test_bench_reports_the_median_of_its_runs():
    r = bench_one("M2", "exits", photons=400, threads=1, repeat=3)
    runs = sorted(r["runs_photons_per_s"])
    assert len(runs) == 3 and r["photons_per_s"] == runs[1]
    assert r["photons"] == 400 and r["threads"] == 1
    assert r["steps_per_s"] == pytest.approx(r["photons_per_s"] * r["steps_per_photon"])
    # M2 (albedo 0.9, index-matched, isotropic): about 23 interaction steps per photon.
    assert 15 < r["steps_per_photon"] < 35


def test_bench_refuses_zero_repeats():
    p = argparse.ArgumentParser()
    _arguments(p)
    with pytest.raises(SystemExit):
        p.parse_args(["--repeat", "0"])


def test_bench_on_two_worker_processes():
    """--threads 2: both processes warm up before timing (the pool waits for each) and the
    figures count both shards."""
    r = bench_one("M2", "exits", photons=300, threads=2, repeat=1)
    assert r["threads"] == 2 and r["photons"] == 600
    assert r["steps_per_s_per_core"] == pytest.approx(r["steps_per_s"] / 2)
