"""`bssrdf bench` / `python -m workers.measure.bench`: throughput of the walk.

For the benchmark media of the engine issue, at normal incidence, each estimator alone (hybrid,
the default; exits; connections):
M1: sigma_t 10/mm, albedo 0.99, g 0.9, eta 1.3 (about 380 steps per photon);
M2: sigma_t 1/mm, albedo 0.9, g 0, eta 1.0 (about 27.5 steps per photon).
Prints photons/s, interaction steps (free-path samples) per second per core and per CPU-second,
the thread count and the memory peak (per worker process).  --threads N runs N shards at once in N
worker processes (one core each), which is how `bssrdf simulate` and the workers use cores.  A
warm-up run in every process first keeps compile time out.

Shared machines drift by tens of percent within minutes, so a speed is best stated as a ratio to
a reference walk timed in the same minutes.  --yardstick CMD runs CMD (a shell command whose
output holds ``steps/s=<number>``; ``{medium}`` in it becomes M1 or M2) before every timed run and
reports each run's steps per CPU-second over the yardstick's steps per second, and their median.

--profile instead runs one shard per medium and estimator in this process and prints where its
CPU goes, kernel by kernel (:mod:`workers.measure.profile`).
"""

from __future__ import annotations

import argparse
import json
import re
import shlex
import subprocess
import sys
import time
from typing import Callable

from schema import SimulationSpec

from workers.run.simulate import positive_int

__all__ = ["MEDIA", "bench_one", "yardstick_rate", "add_parser", "main"]

MEDIA = {
    "M1": {"sigma_a": 0.1, "sigma_s": 9.9, "g": 0.9, "eta": 1.3},
    "M2": {"sigma_a": 0.1, "sigma_s": 0.9, "g": 0.0, "eta": 1.0},
}
DEFAULT_PHOTONS = {
    ("M1", "hybrid"): 200_000, ("M2", "hybrid"): 2_000_000, ("M1", "exits"): 200_000, ("M2", "exits"): 2_000_000,
    ("M1", "connections"): 2_000, ("M2", "connections"): 20_000,
}  # fmt: skip


def _spec(medium: str, estimator: str, photons: int, shards: int = 1) -> SimulationSpec:
    return SimulationSpec.model_validate({
        "name": f"bench-{medium}-{estimator}", "medium": MEDIA[medium], "photons": photons,
        "shards": shards, "batches_per_shard": 4, "estimator": estimator, "seed": 7,
    })  # fmt: skip


def yardstick_rate(command: str, medium: str) -> float:
    """Run the yardstick command for `medium` and return the steps per second it printed
    (``steps/s=<number>``); a ValueError names --yardstick if it fails or prints none."""
    argv = shlex.split(command.replace("{medium}", medium))
    try:
        done = subprocess.run(argv, capture_output=True, text=True, timeout=600)
    except (OSError, subprocess.TimeoutExpired) as exc:
        raise ValueError(f"--yardstick: could not run {argv[0] if argv else command!r}: {exc}") from None
    found = re.search(r"steps/s=([0-9.]+(?:[eE][-+]?[0-9]+)?)", done.stdout)
    if done.returncode != 0 or found is None or float(found.group(1)) <= 0:
        raise ValueError(f"--yardstick: {command!r} exited {done.returncode} without a positive steps/s=<number> in its output")
    return float(found.group(1))


def bench_one(medium: str, estimator: str, photons: int, threads: int = 1, repeat: int = 3,
              yardstick: Callable[[], float] | None = None) -> dict:
    """Run `threads` shards of `photons` photons each concurrently, one worker process per shard
    (:class:`workers.run.pool.ShardPool`, as `bssrdf simulate` does), after every process has warmed up
    (compiled) on a small run; `repeat` times, reporting the median run (by wall time) and every
    run's photons/s (shared machines vary by tens of percent from run to run).

    Rates per core divide by `threads`; CPU time is the shards' own (thread CPU time in their
    processes), so steps per CPU-second show how much of each core the walk gets.  yardstick, if
    given, is called before every timed run (:func:`yardstick_rate`): each run's steps per
    CPU-second over the rate it returns is that run's ratio.
    """
    from workers.run.pool import ShardPool  # torch: not needed to build the command-line parser

    warm = _spec(medium, estimator, max(8, photons // 50), 1)
    spec = _spec(medium, estimator, photons * threads, threads)
    runs = []
    with ShardPool(threads, warm_spec=warm) as pool:
        # The pool's first run pays set-up costs, among them kernels compiled for the lane counts
        # of a full-size shard (a smaller first run left one timed run ~17x slow).
        pool.run(spec, range(threads))
        for _ in range(repeat):
            reference = yardstick() if yardstick is not None else None
            wall0 = time.perf_counter()
            tallies = pool.run(spec, range(threads))
            runs.append((time.perf_counter() - wall0, tallies, reference))
    ratios = sorted(_steps_per_cpu_s(t) / ref for _, t, ref in runs if ref is not None)
    runs.sort(key=lambda run: run[0])
    wall, tallies, _ = runs[len(runs) // 2]
    cpu = sum(t.info["cpu_s"] for t in tallies)
    peak = max(t.info.get("maxrss_mib", 0.0) for t in tallies)
    steps = sum(t.info["photon_steps"] for t in tallies)
    n = photons * threads
    return {
        "photons": n,
        "photons_per_s": n / wall,
        "steps_per_photon": steps / n,
        "steps_per_s": steps / wall,
        "steps_per_cpu_s": _steps_per_cpu_s(tallies),  # the figure each run's ratio divides
        "steps_per_s_per_core": steps / wall / threads,
        "vertices": sum(t.info["vertices"] for t in tallies),
        "wall_s": wall,
        "cpu_s": cpu,
        "threads": threads,
        "engine": tallies[0].info["engine"],
        "memory_peak_mib": peak,
        "runs_photons_per_s": [photons * threads / w for w, _, _ in runs],
        **({"yardstick_steps_per_s": [ref for _, _, ref in runs], "ratios": ratios, "ratio": ratios[len(ratios) // 2]} if ratios else {}),
    }


def _steps_per_cpu_s(tallies) -> float:
    """Interaction steps per CPU-second of one run's shards."""
    return sum(t.info["photon_steps"] for t in tallies) / sum(t.info["cpu_s"] for t in tallies)


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("bench", help="measure walk throughput (photons/s, steps/s per core)", description=__doc__)
    _arguments(p)
    p.set_defaults(func=main)


def _arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--media", default="M1,M2", help="comma-separated subset of M1,M2")
    p.add_argument("--estimators", default="hybrid,exits,connections", help="comma-separated subset of hybrid,exits,connections")
    p.add_argument("--photons", type=int, help="photons per run (default: per medium and estimator)")
    p.add_argument("--threads", type=int, default=1, help="shards run concurrently, one worker process and core each (default 1)")
    p.add_argument("--repeat", type=positive_int, default=3, help="timed runs; the median is reported (default 3)")
    p.add_argument("--json", action="store_true", help="print one JSON object keyed by medium and estimator")
    p.add_argument("--profile", action="store_true", help="instead: run one shard per medium and estimator in this process on one "
                   "torch thread and print the CPU of each kernel and of the Python around them (workers.measure.profile)")
    p.add_argument("--yardstick", metavar="CMD", help="a reference walk run before every timed run ({medium} -> M1/M2; "
                   "its output holds steps/s=<number>): reports each run's steps per CPU-second over it, and the median")


def main(args: argparse.Namespace) -> int:
    if args.profile:
        return _profile(args)
    out: dict[str, dict] = {}
    for medium in args.media.split(","):
        for est in args.estimators.split(","):
            photons = args.photons or DEFAULT_PHOTONS[(medium, est)]
            ystick = (lambda m=medium: yardstick_rate(args.yardstick, m)) if args.yardstick else None
            try:
                r = bench_one(medium, est, photons, args.threads, args.repeat, ystick)
            except ValueError as exc:  # a yardstick that does not run or print its rate
                print(f"bench: error: {exc}", file=sys.stderr)
                return 2
            out.setdefault(medium, {})[est] = r
            if not args.json:
                print(
                    f"{medium} {est:<12} {r['photons_per_s']:>10.4g} photons/s  {r['steps_per_s']:>9.3g} steps/s  "
                    f"{r['steps_per_s_per_core']:>9.3g} steps/s per core  {r['steps_per_cpu_s']:>9.3g} steps/CPU-s  ({r['steps_per_photon']:.1f} steps/photon, "
                    f"{r['threads']} threads, {r['engine']}, peak {r['memory_peak_mib']:.0f} MiB per process; "
                    f"median of {len(r['runs_photons_per_s'])}: {min(r['runs_photons_per_s']):.4g}-{max(r['runs_photons_per_s']):.4g} photons/s)"
                    + (f"; {r['ratio']:.3f}x the yardstick (runs {', '.join(f'{x:.3f}' for x in r['ratios'])})" if "ratio" in r else ""),
                    flush=True,
                )
    if args.json:
        print(json.dumps(out, sort_keys=True))
    return 0


def _profile(args: argparse.Namespace) -> int:
    """--profile: workers.measure.profile for each medium and estimator (--threads and
    --yardstick do not apply: one shard, this process)."""
    from workers.measure.profile import format_profile, profile_shard

    out: dict[str, dict] = {}
    for medium in args.media.split(","):
        for est in args.estimators.split(","):
            r = profile_shard(medium, est, args.photons or DEFAULT_PHOTONS[(medium, est)], args.repeat)
            out.setdefault(medium, {})[est] = r
            if not args.json:
                print(format_profile(r), flush=True)
    if args.json:
        print(json.dumps(out, sort_keys=True))
    return 0


if __name__ == "__main__":
    parser = argparse.ArgumentParser(prog="python -m workers.measure.bench", description=__doc__)
    _arguments(parser)
    sys.exit(main(parser.parse_args()))
