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
