"""`python -m workers.measure.table_cost`: what a renderer's table costs, measured and projected.

The product's main use is a pbrt table of one material family: one g, one eta, pbrt's albedos
(the 99 non-zero ones of ``{"count": 100, "spacing": "pbrt"}``) x 64 radial bins centred on pbrt's
radius nodes.  This benchmark runs such a sweep (or any albedo list) with a fixed number of
photons per medium on one core, measures the CPU seconds of every walk (thread CPU time of each
shard, ``time.thread_time``) and the relative standard error of Rd(r) (total component) in every
radial bin whose node lies in [r_min, r_max] (default [0.001, 10] mean free paths), and projects
the cost of the table that meets a relative error of ``node_rel`` (1 %) in every such bin and
``rd_rel`` (0.2 %) on the total Rd:

- photons needed by a medium: N (max over its nodes of (rel. error / node_rel)^2, and
  (rel. error of Rd / rd_rel)^2): the variance of a per-photon mean falls as 1 / N;
- a node resolved by fewer than MIN_EVENTS events has no usable error estimate; it gets a
  lower bound instead: with k events in N photons its per-photon relative variance is at least
  N / k - 1 (Cauchy-Schwarz: E[x]^2 <= E[x^2] P(x != 0)), so it needs at least
  (N / max(k, 3) - 1) / node_rel^2 photons (k = 0: 3 is the 95 % upper bound on the events).
  Such nodes are counted (``unresolved``), and a projection that rests on one says so (``bound``);
- a walk group (:mod:`schema.groups`; one medium with independent walks) runs the photons its
  hardest member needs, at the CPU per photon measured for that group's walk:
  CPU-hours = max over members of photons needed x CPU seconds per photon / 3600;
- the same, separately, for the *major* nodes only: those that carry >= 1e-3 of the medium's
  total Rd (pbrt's rhoEff) each.

``--path-roulette START,SURVIVAL`` sets the spec's ``path_roulette`` (:mod:`schema.roulette`),
``--stretch GAMMA,R_MIN,ALBEDO_MAX[,GAMMA_INWARD]`` its ``stretch`` (:mod:`schema.stretch`).

A node's relative error is itself estimated from its events; where they are few and
heavy-tailed (the far nodes, ~9 mean free paths, of albedos below ~0.5: 30-100 events at 2e5
photons) it comes out low, and so does the projection: measured, 2e5 photons projected 2-3e8
photons for the far node of albedo 0.078 where 2e6 gave 2.9e9 (BENCHMARKS.md).  Project such
albedos from ``--photons 2000000`` or more.

``--yardstick S`` (steps per CPU-second of a reference walk measured in the same minutes, e.g. a
hand-vectorised C walk of M2 on this core, timed in user CPU seconds) adds figures normalised to the reference speed
``--yardstick-ref`` (default YARDSTICK_REF): CPU-hours x S / ref, which takes out how fast the
machine happens to run (shared machines, other CPUs).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time

import numpy as np

from schema import SimulationSpec
from schema.bins import pbrt_radius_nodes
from schema.sweep import pbrt_albedos

__all__ = ["MIN_EVENTS", "YARDSTICK_REF", "table_spec", "measure", "project", "main"]

MIN_EVENTS = 30
YARDSTICK_REF = 3.5e8
"""Reference speed of the yardstick: steps per CPU-second (user time) of a hand-vectorised C walk
of the M2 medium (float32 lanes, the same physics) on one core of the 2 vCPU AVX-512 EPYC
machine of BENCHMARKS.md, the best of several measurements on a day the machine was shared
(3.2-3.6e8).  Time it in CPU seconds, not wall time, on a shared machine."""
TOTAL = 2


def table_spec(albedos, g: float, eta: float, photons: int, estimator: str, walks: str, group_edges=None,
               seed: int = 1, shards: int = 1, path_roulette: dict | None = None, stretch: dict | None = None) -> SimulationSpec:
    """The sweep measured: pbrt's 64 radial bins, no direction resolution (Rd(r) is what the
    table holds), normal incidence; path_roulette and stretch as the spec's fields (None: off)."""
    sweep = {"albedo": list(albedos), "g": [g], "eta": [eta], "walks": walks}
    if group_edges is not None:
        sweep["group_edges"] = list(group_edges)
    return SimulationSpec.model_validate({
        "name": "table-cost", "sweep": sweep, "incidence_deg": [0.0], "photons": photons, "shards": shards,
        "batches_per_shard": 2, "estimator": estimator, "seed": seed,
        "bins": {"radial": {"count": 64, "spacing": "pbrt"}, "cos_theta_o": {"count": 1}, "phi_o": {"count": 1}},
        "path_roulette": path_roulette, "stretch": stretch,
    })  # fmt: skip


def measure(spec: SimulationSpec, progress=None) -> tuple[list, list[float]]:
    """Run every task on this thread; (Results in medium order, CPU seconds per walk group)."""
    from workers.run.simulate import run_tasks
    from workers.fold.job import JobFold
    from workers.run.task import group_walk

    def items():
        for t in range(spec.task_count()):
            group, shard = spec.task_of(t)
            leader, members = group_walk(spec, group)
            yield spec.medium_spec(leader), shard, members

    # Warm-up outside the measurement: compile or load the kernels for this shard size (a cheap
    # low albedo with the same photons per shard, hence the same lane count).
    roulette = None if spec.path_roulette is None else spec.path_roulette.model_dump()
    stretch = None if spec.stretch is None else spec.stretch.model_dump(exclude_none=True)
    warm = table_spec([0.05], spec.sweep.g[0], spec.sweep.eta[0], spec.photons, spec.estimator, "independent",
                      shards=spec.shards, path_roulette=roulette, stretch=stretch)  # fmt: skip
    list(run_tasks([(warm.medium_spec(0), 0)], threads=1))
    fold = JobFold(spec)
    results, cpu = [], [0.0] * len(spec.walk_groups())
    for t, tally in enumerate(run_tasks(items(), threads=1)):
        cpu[spec.task_of(t)[0]] += float(tally.info["cpu_s"])
        if fold.add(t, tally) is not None:
            results.extend(fold.finished)
        if progress:
            progress(t)
    return results, cpu


def node_needs(result, estimator: str, r_min: float, r_max: float, node_rel: float, rd_rel: float) -> dict:
    """Photons one medium needs (module docstring), for all nodes in [r_min, r_max] and for the
    major ones; with the hardest node of each."""
    n = result.n_sum
    mean, se = result.mean(f"{estimator}/radial_G")[0, TOTAL], result.stderr(f"{estimator}/radial_G")[0, TOTAL]
    ev = result.events(f"{estimator}/radial_G")[0, TOTAL]
    rd, rd_se = float(result.mean(f"{estimator}/Rd")[0, TOTAL]), float(result.stderr(f"{estimator}/Rd")[0, TOTAL])
    edges = result.layout.radial_mm[0]  # mm = mean free paths (sigma_t = 1)
    nodes = pbrt_radius_nodes(len(edges) - 1)  # bin j is centred on node j (spacing "pbrt")
    inside = np.flatnonzero((nodes >= r_min) & (nodes <= r_max))
    major = inside[mean[inside] >= 1e-3 * rd] if rd > 0 else inside[:0]
    need, bound = np.zeros(len(mean)), np.zeros(len(mean), dtype=bool)
    for i in inside:
        if ev[i] >= MIN_EVENTS and mean[i] > 0:
            need[i] = n * (se[i] / mean[i] / node_rel) ** 2
        else:
            need[i] = max(n / max(int(ev[i]), 3) - 1.0, 0.0) / node_rel**2
            bound[i] = True
    rd_need = n * (rd_se / rd / rd_rel) ** 2 if rd > 0 else math.inf

    def worst(sel):
        if len(sel) == 0:
            return {"photons": rd_need, "node": None, "r": None, "bound": False}
        i = int(sel[np.argmax(need[sel])])
        if need[i] < rd_need:
            return {"photons": rd_need, "node": "Rd", "r": None, "bound": False}
        return {"photons": float(need[i]), "node": i, "r": float(nodes[i]), "bound": bool(bound[i]),
                "rel_err": float(se[i] / mean[i]) if mean[i] > 0 else None, "events": int(ev[i])}

    return {"albedo": float(result.spec.medium.channels()[0].albedo), "photons_run": int(n), "Rd": rd,
            "Rd_rel_err": rd_se / rd if rd > 0 else None, "nodes": len(inside), "major_nodes": len(major),
            "unresolved": int(bound[inside].sum()), "all": worst(inside), "major": worst(major)}  # fmt: skip


def project(spec: SimulationSpec, results, cpu: list[float], r_min=0.001, r_max=10.0, node_rel=0.01, rd_rel=0.002) -> dict:
    """Per medium and per walk group: photons needed and projected CPU-hours (module docstring)."""
    est = spec.estimator
    needs = [node_needs(r, est, r_min, r_max, node_rel, rd_rel) for r in results]
    groups = []
    for k, media in enumerate(spec.walk_groups()):
        per_photon = cpu[k] / results[media[-1]].n_sum
        g = {"media": [media[0], media[-1]], "albedos": [needs[media[0]]["albedo"], needs[media[-1]]["albedo"]],
             "cpu_s": cpu[k], "cpu_s_per_photon": per_photon}
        for which in ("all", "major"):
            hard = max(media, key=lambda m: needs[m][which]["photons"])
            photons = needs[hard][which]["photons"]
            g[which] = {"photons": photons, "hardest_albedo": needs[hard]["albedo"], "node": needs[hard][which],
                        "cpu_hours": photons * per_photon / 3600.0}
        for m in media:
            for which in ("all", "major"):
                needs[m][which]["cpu_hours_alone"] = needs[m][which]["photons"] * per_photon / 3600.0
        groups.append(g)
    total = {which: sum(g[which]["cpu_hours"] for g in groups) for which in ("all", "major")}
    return {
        "g": spec.sweep.g[0], "eta": spec.sweep.eta[0], "estimator": est, "walks": spec.walk_mode(),
        "photons_per_medium": spec.photons, "media": spec.n_media,
        "path_roulette": None if spec.path_roulette is None else spec.path_roulette.model_dump(),
        "stretch": None if spec.stretch is None else spec.stretch.model_dump(exclude_none=True), "groups": groups, "albedos": needs,
        "cpu_s_measured": sum(cpu), "cpu_hours": total,
        "bound": any(g[w]["node"]["bound"] for g in groups for w in ("all",)),
        "target": {"node_rel": node_rel, "rd_rel": rd_rel, "r_min": r_min, "r_max": r_max, "major_share": 1e-3},
        "method": "photons needed = N max((rel err / target)^2) over the nodes in [r_min, r_max] and Rd; nodes with fewer "
                  f"than {MIN_EVENTS} events get the lower bound (N / max(k, 3) - 1) / target^2; a walk group runs its "
                  "hardest member's photons at its measured thread CPU seconds per photon",
    }  # fmt: skip


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m workers.measure.table_cost", description=__doc__.split("\n\n")[0])
    p.add_argument("--g", type=float, default=0.0)
    p.add_argument("--eta", type=float, default=1.33)
    p.add_argument("--albedos", default="pbrt:100", help="comma list, or pbrt:N (pbrt's N albedos without 0; default pbrt:100)")
    p.add_argument("--photons", type=int, default=200_000, help="photons per medium (default 2e5)")
    p.add_argument("--estimator", default="hybrid", choices=("hybrid", "exits"))
    p.add_argument("--walks", default="shared", choices=("shared", "independent"))
    p.add_argument("--group-edges", default=None, help="comma list of albedos starting walk groups (shared walks)")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--path-roulette", default=None, metavar="START,SURVIVAL",
                   help="the spec's path_roulette (schema/roulette.py), e.g. 1024,0.5 (default: off)")
    p.add_argument("--stretch", default=None, metavar="GAMMA,R_MIN,ALBEDO_MAX[,GAMMA_INWARD]",
                   help="the spec's stretch (schema/stretch.py), e.g. 0.8,0,0.3 or 0.6,0,0.7,0.2 (default: off)")
    p.add_argument("--yardstick", type=float, default=None, help="reference walk steps per CPU-second measured now")
    p.add_argument("--yardstick-ref", type=float, default=YARDSTICK_REF)
    p.add_argument("--json", action="store_true")
    a = p.parse_args(argv)
    if a.albedos.startswith("pbrt:"):
        albedos = [x for x in pbrt_albedos(int(a.albedos[5:])) if x > 0.0]
    else:
        albedos = [float(x) for x in a.albedos.split(",")]
    edges = None if a.group_edges is None else [float(x) for x in a.group_edges.split(",")]
    roulette = None
    if a.path_roulette is not None:
        start, survival = a.path_roulette.split(",")
        roulette = {"start": int(start), "survival": float(survival)}
    stretch = None
    if a.stretch is not None:
        values = [float(x) for x in a.stretch.split(",")]
        if len(values) not in (3, 4):
            p.error(f"--stretch takes GAMMA,R_MIN,ALBEDO_MAX[,GAMMA_INWARD], not {a.stretch!r}")
        stretch = dict(zip(("gamma", "r_min_mfp", "albedo_max", "gamma_inward"), values))
    spec = table_spec(albedos, a.g, a.eta, a.photons, a.estimator, a.walks, edges, seed=a.seed, path_roulette=roulette,
                      stretch=stretch)  # fmt: skip
    t0 = time.perf_counter()
    results, cpu = measure(spec)
    out = project(spec, results, cpu)
    out["wall_s"] = time.perf_counter() - t0
    if a.yardstick is not None:
        scale = a.yardstick / a.yardstick_ref
        out["yardstick"] = {"steps_per_s": a.yardstick, "ref": a.yardstick_ref, "scale": scale}
        out["cpu_hours_normalised"] = {k: v * scale for k, v in out["cpu_hours"].items()}
    if a.json:
        print(json.dumps(out))
        return 0
    print(f"table cost: g {out['g']}, eta {out['eta']}, {out['estimator']}, walks {out['walks']}, {len(albedos)} albedos, "
          f"{a.photons} photons each, {out['cpu_s_measured']:.1f} CPU s measured")
    print(f"{'group albedos':>22} {'CPU s/photon':>13} {'photons (all)':>14} {'hardest':>24} {'CPU h':>8} {'photons (major)':>16} {'CPU h':>8}")
    for g in out["groups"]:
        n = g["all"]["node"]
        hard = f"a={g['all']['hardest_albedo']:.4f} " + ("Rd" if n["node"] in (None, "Rd") else f"r={n['r']:.3g}") + (" (bound)" if n["bound"] else "")
        print(f"{g['albedos'][0]:>10.5f}-{g['albedos'][1]:<11.5f} {g['cpu_s_per_photon']:>13.3e} {g['all']['photons']:>14.3e} "
              f"{hard:>24} {g['all']['cpu_hours']:>8.4f} {g['major']['photons']:>16.3e} {g['major']['cpu_hours']:>8.4f}")
    line = f"total CPU-hours: all nodes {out['cpu_hours']['all']:.3f}, major nodes {out['cpu_hours']['major']:.3f}"
    if "cpu_hours_normalised" in out:
        c = out["cpu_hours_normalised"]
        line += f"; normalised to the yardstick: {c['all']:.3f} / {c['major']:.3f}"
    print(line + (" (a lower bound: some hardest node is unresolved)" if out["bound"] else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
