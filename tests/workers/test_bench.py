"""`bssrdf bench`: the figures it reports are consistent with the runs behind them."""

from __future__ import annotations

import argparse

import pytest

from workers.measure.bench import _arguments, bench_one, main, yardstick_rate


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


def test_bench_divides_each_run_by_the_yardstick_timed_before_it(tmp_path):
    """--yardstick: each timed run's steps per CPU-second over the rate the command printed just
    before it (the command sees the medium), the median of those ratios reported."""
    stick = tmp_path / "stick"
    stick.write_text('#!/bin/sh\n[ "$1" = M2 ] && echo "M2 simd time=1 s  steps/s=2.5e+07  Rd=0.4"\n')
    stick.chmod(0o755)
    rate = yardstick_rate(f"{stick} {{medium}}", "M2")
    assert rate == 2.5e7
    r = bench_one("M2", "exits", photons=400, threads=1, repeat=3, yardstick=lambda: rate)
    assert r["yardstick_steps_per_s"] == [2.5e7] * 3 and len(r["ratios"]) == 3
    assert r["ratio"] == sorted(r["ratios"])[1] and r["ratios"] == sorted(r["ratios"])
    assert min(r["ratios"]) <= r["steps_per_cpu_s"] / 2.5e7 <= max(r["ratios"])


@pytest.mark.parametrize("body", ['echo "no rate here"', 'echo "steps/s=1e8"; exit 3', 'echo "steps/s=0"'])
def test_a_yardstick_without_a_rate_is_an_error_naming_the_option(tmp_path, body):
    stick = tmp_path / "stick"
    stick.write_text(f"#!/bin/sh\n{body}\n")
    stick.chmod(0o755)
    with pytest.raises(ValueError, match="--yardstick"):
        yardstick_rate(str(stick), "M1")
    with pytest.raises(ValueError, match="--yardstick: could not run"):
        yardstick_rate(str(tmp_path / "missing"), "M1")


def test_the_command_stops_with_a_clear_error_on_a_bad_yardstick(tmp_path, capsys):
    p = argparse.ArgumentParser()
    _arguments(p)
    args = p.parse_args(["--media", "M2", "--estimators", "exits", "--photons", "200", "--repeat", "1", "--yardstick", str(tmp_path / "missing")])
    assert main(args) == 2
    assert "--yardstick: could not run" in capsys.readouterr().err


def test_profile_times_each_kernel_of_one_shard_without_changing_it():
    """--profile: the parts are the kernels the shard called plus the Python left over, on one
    torch thread (restored afterwards); lane-steps count every lane a step call advanced, so they
    bound the photons' own steps; timing wrappers leave the tallies as they are."""
    import numpy as np
    import torch

    from workers.measure.bench import _spec
    from workers.measure.profile import format_profile, profile_shard
    from workers.run.shard import run_shard

    threads = torch.get_num_threads()
    r = profile_shard("M2", "hybrid", photons=3000, repeat=3)
    assert torch.get_num_threads() == threads
    assert set(r["parts"]) == {"step", "harvest", "python"}  # no connections: the hybrid's are its entries, made by the harvest
    assert r["cpu_s"] == sorted(r["runs_cpu_s"])[1]
    assert sum(p["cpu_s"] for p in r["parts"].values()) == pytest.approx(r["cpu_s"])
    assert r["parts"]["step"]["calls"] > 0 and r["parts"]["harvest"]["calls"] > 0
    assert 0.0 < r["occupancy"] <= 1.0 and r["photon_steps"] <= r["lane_steps"]
    assert 15 < r["photon_steps"] / r["photons"] < 35
    assert "ns per lane-step" in format_profile(r)

    calls: list[str] = []

    def count(name, kernel):
        def call(*args):
            calls.append(name)
            return kernel(*args)
        return call

    spec = _spec("M2", "hybrid", 3000)
    plain, wrapped = run_shard(spec, 0), run_shard(spec, 0, wrap_kernels=count)
    assert {"step", "harvest"} <= set(calls)
    for q, parts in plain.stats.items():
        for a, b in zip(parts, wrapped.stats[q]):
            assert np.array_equal(np.asarray(a), np.asarray(b), equal_nan=True), q


def test_bench_profile_option_prints_json(capsys):
    p = argparse.ArgumentParser()
    _arguments(p)
    assert main(p.parse_args(["--media", "M2", "--estimators", "exits", "--photons", "500", "--repeat", "1", "--profile", "--json"])) == 0
    import json

    out = json.loads(capsys.readouterr().out)
    r = out["M2"]["exits"]
    assert r["photons"] == 500 and set(r["parts"]) == {"step", "harvest", "python"}
