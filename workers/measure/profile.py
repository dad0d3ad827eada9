"""Where a shard's CPU goes: `bssrdf bench --profile` (:func:`profile_shard`).

A shard of the bench's medium runs in this process on one torch thread, as a worker runs it,
with every kernel call wrapped by a timer of this thread's CPU time: the step kernel (lanes
advanced ``n_steps`` interactions per call), the harvest kernel (finished lanes recorded and
refilled; for the hybrid also its entries, made in the same pass) and the connections.  What is left of the shard's CPU is the
Python around them (finding the finished lanes, moving the kernels' outputs into numpy, the
tallies' bincounts, call wrappers and guards).  Per photon and per lane-step figures make the
parts comparable with the C walk's whole step.

One torch thread matters twice: the kernels are compiled per thread count (the workers' are
one-thread kernels), and with more threads the step runs on OpenMP threads whose CPU time this
thread's clock does not see, which once made a walk look 1.7x faster than it was.
"""

from __future__ import annotations

import time
from typing import Callable

import torch

from workers.measure.bench import _spec
from workers.run.plan import ShardPlan
from workers.run.shard import run_shard

__all__ = ["profile_shard", "format_profile"]


def _timed(totals: dict[str, list[float]], lane_steps: list[int], n_steps: int) -> Callable[[str, Callable], Callable]:
    """A kernel wrapper for run_shard: totals[name] = [CPU s, calls]; lane_steps[0] counts the
    lanes the step kernel advanced times n_steps."""

    def wrap(name: str, kernel: Callable) -> Callable:
        entry = totals.setdefault(name, [0.0, 0])

        def call(*args):
            c0 = time.thread_time()
            out = kernel(*args)
            entry[0] += time.thread_time() - c0
            entry[1] += 1
            if name == "step":
                lane_steps[0] += args[0].x.shape[0] * n_steps
            return out

        return call

    return wrap


def profile_shard(medium: str, estimator: str, photons: int, repeat: int = 3) -> dict:
    """Run one shard of `photons` photons of bench medium `medium` with `estimator` `repeat` times
    after a warm-up (kernels loaded or compiled), on one torch thread, timing each kernel; returns
    the run with the median CPU time:

    {"photons", "cpu_s", "photon_steps", "lane_steps", "occupancy" (photon steps / lane steps),
    "parts": {name: {"cpu_s", "calls", "ns_per_photon"}} with "python" the rest of the shard's
    CPU, "runs_cpu_s": every run's CPU seconds}.
    """
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        spec = _spec(medium, estimator, photons)
        n_steps = ShardPlan.build(spec, 0).n_steps
        run_shard(_spec(medium, estimator, max(8, photons // 50)), 0)
        run_shard(spec, 0)  # a full-size shard first: its tail's lengths seen (each length's first call checks guards)
        runs = []
        for _ in range(repeat):
            totals: dict[str, list[float]] = {}
            lane_steps = [0]
            c0 = time.thread_time()
            tally = run_shard(spec, 0, wrap_kernels=_timed(totals, lane_steps, n_steps))
            runs.append((time.thread_time() - c0, totals, lane_steps[0], tally.info["photon_steps"]))
    finally:
        torch.set_num_threads(threads)
    runs_cpu = [r[0] for r in runs]
    cpu, totals, lanes, steps = sorted(runs, key=lambda r: r[0])[len(runs) // 2]
    n = photons  # one configuration: normal incidence, one channel
    parts = {name: {"cpu_s": t, "calls": calls, "ns_per_photon": t / n * 1e9} for name, (t, calls) in totals.items() if calls}
    rest = cpu - sum(p["cpu_s"] for p in parts.values())
    parts["python"] = {"cpu_s": rest, "calls": 0, "ns_per_photon": rest / n * 1e9}
    return {
        "medium": medium, "estimator": estimator, "photons": n, "cpu_s": cpu, "photon_steps": steps, "lane_steps": lanes,
        "occupancy": steps / lanes if lanes else 0.0, "steps_per_cpu_s": steps / cpu, "parts": parts, "runs_cpu_s": runs_cpu,
    }  # fmt: skip


def format_profile(r: dict) -> str:
    """The profile as lines of text: one per part, then the shard."""
    lines = [f"{r['medium']} {r['estimator']}: {r['photons']} photons, {r['photon_steps'] / r['photons']:.1f} steps per photon, "
             f"median of {len(r['runs_cpu_s'])} runs ({min(r['runs_cpu_s']):.3f}-{max(r['runs_cpu_s']):.3f} CPU s), one torch thread"]
    for name, p in r["parts"].items():
        calls = f"{p['calls']:>6d} calls" if p["calls"] else " " * 12
        extra = ""
        if name == "step" and r["lane_steps"]:
            extra = f"  {p['cpu_s'] / r['lane_steps'] * 1e9:.2f} ns per lane-step, {r['occupancy']:.0%} of lane-steps carry a photon"
        lines.append(f"  {name:<8} {p['cpu_s']:8.3f} CPU s  {calls}  {p['ns_per_photon']:8.1f} ns per photon{extra}")
    lines.append(f"  {'shard':<8} {r['cpu_s']:8.3f} CPU s  {' ' * 12}  {r['cpu_s'] / r['photons'] * 1e9:8.1f} ns per photon  "
                 f"{r['steps_per_cpu_s']:.3g} steps per CPU-second")
    return "\n".join(lines)
