"""`bssrdf bench` / `python -m workers.bench`: throughput of the walk.

For the benchmark media of the engine issue, at normal incidence, each estimator alone:
M1: sigma_t 10/mm, albedo 0.99, g 0.9, eta 1.3 (about 380 steps per photon);
M2: sigma_t 1/mm, albedo 0.9, g 0, eta 1.0 (about 27.5 steps per photon).
Prints photons/s, interaction steps (free-path samples) per second per core and per CPU-second,
the thread count and the memory peak.  --threads N runs N shards at once (one core each), which is
how `bssrdf simulate` and the workers use cores.  A warm-up run first keeps compile time out.
"""

from __future__ import annotations

import argparse
import json
import resource
import sys
import time



from schema import SimulationSpec

from .simulate import run_shards

__all__ = ["MEDIA", "bench_one", "add_parser", "main"]

MEDIA = {
    "M1": {"sigma_a": 0.1, "sigma_s": 9.9, "g": 0.9, "eta": 1.3},
    "M2": {"sigma_a": 0.1, "sigma_s": 0.9, "g": 0.0, "eta": 1.0},
}
DEFAULT_PHOTONS = {("M1", "exits"): 200_000, ("M2", "exits"): 2_000_000, ("M1", "connections"): 2_000, ("M2", "connections"): 20_000}


def _spec(medium: str, estimator: str, photons: int, shards: int = 1) -> SimulationSpec:
    return SimulationSpec.model_validate({
        "name": f"bench-{medium}-{estimator}", "medium": MEDIA[medium], "photons": photons,
        "shards": shards, "batches_per_shard": 4, "estimator": estimator, "seed": 7,
    })  # fmt: skip


def bench_one(medium: str, estimator: str, photons: int, threads: int = 1) -> dict:
    """Run `threads` shards of `photons` photons each concurrently, after a small warm-up.

    Figures from wall time and process CPU time; per core = per thread (each shard runs on one
    torch thread, see workers.simulate.run_shards).
    """
    run_shards(_spec(medium, estimator, max(8, photons // 50), threads), range(threads), threads=threads)  # compile
    spec = _spec(medium, estimator, photons * threads, threads)
    cpu0, wall0 = time.process_time(), time.perf_counter()
    tallies = run_shards(spec, range(threads), threads=threads)
    cpu, wall = time.process_time() - cpu0, time.perf_counter() - wall0
    steps = sum(t.info["photon_steps"] for t in tallies)
    n = photons * threads
    return {
        "photons": n,
        "photons_per_s": n / wall,
        "steps_per_photon": steps / n,
        "steps_per_s": steps / wall,
        "steps_per_cpu_s": steps / cpu,
        "steps_per_s_per_core": steps / wall / threads,
        "vertices": sum(t.info["vertices"] for t in tallies),
        "wall_s": wall,
        "cpu_s": cpu,
        "threads": threads,
        "engine": tallies[0].info["engine"],
    }


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("bench", help="measure walk throughput (photons/s, steps/s per core)", description=__doc__)
    _arguments(p)
    p.set_defaults(func=main)


def _arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--media", default="M1,M2", help="comma-separated subset of M1,M2")
    p.add_argument("--estimators", default="exits,connections", help="comma-separated subset of exits,connections")
    p.add_argument("--photons", type=int, help="photons per run (default: per medium and estimator)")
    p.add_argument("--threads", type=int, default=1, help="shards run concurrently, one core each (default 1)")
    p.add_argument("--json", action="store_true", help="print one JSON object keyed by medium and estimator")


def main(args: argparse.Namespace) -> int:
    out: dict[str, dict] = {}
    for medium in args.media.split(","):
        for est in args.estimators.split(","):
            photons = args.photons or DEFAULT_PHOTONS[(medium, est)]
            r = bench_one(medium, est, photons, args.threads)
            out.setdefault(medium, {})[est] = r
            if not args.json:
                print(
                    f"{medium} {est:<12} {r['photons_per_s']:>10.4g} photons/s  {r['steps_per_s']:>9.3g} steps/s  "
                    f"{r['steps_per_s_per_core']:>9.3g} steps/s per core  {r['steps_per_cpu_s']:>9.3g} steps/CPU-s  ({r['steps_per_photon']:.1f} steps/photon, "
                    f"{r['threads']} threads, {r['engine']})",
                    flush=True,
                )
    peak_mib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    if args.json:
        print(json.dumps(dict(out, memory_peak_mib=peak_mib), sort_keys=True))
    else:
        print(f"memory peak {peak_mib:.0f} MiB")
    return 0


if __name__ == "__main__":
    parser = argparse.ArgumentParser(prog="python -m workers.bench", description=__doc__)
    _arguments(parser)
    sys.exit(main(parser.parse_args()))
