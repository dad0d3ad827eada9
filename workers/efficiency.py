"""`python -m workers.efficiency`: efficiency of the two estimators per radial bin.

Efficiency = 1 / (variance x CPU seconds): the inverse of the CPU time needed for a unit variance.
Each estimator runs alone on the same medium (M1 of the engine issue by default: sigma_t 10/mm,
albedo 0.99, g 0.9, eta 1.3, normal incidence); the table lists, per radial bin, Rd(r) of each,
their efficiencies for the multiple-scattering component and for single scattering, and the ratio
connections / exits (> 1: connections win).
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np
import torch

from schema import SimulationSpec

from .bench import MEDIA
from .simulate import simulate

__all__ = ["efficiency", "main"]


def _run(medium: str, estimator: str, photons: int, radial: dict) -> tuple[object, float]:
    spec = SimulationSpec.model_validate({
        "name": f"eff-{medium}-{estimator}", "medium": MEDIA[medium], "photons": photons, "shards": 4,
        "batches_per_shard": 8, "estimator": estimator, "seed": 11, "bins": {"radial": radial},
    })  # fmt: skip
    simulate(spec.model_copy(update={"photons": 64, "shards": 2, "batches_per_shard": 1}), threads=1)  # compile
    cpu0 = time.process_time()
    result = simulate(spec, threads=1)
    return result, time.process_time() - cpu0


def efficiency(medium: str, photons_exits: int, photons_connections: int, radial: dict) -> list[dict]:
    """Per radial bin: Rd(r) and efficiency of each estimator, for single and multiple."""
    torch.set_num_threads(1)
    rows = []
    res_e, cpu_e = _run(medium, "exits", photons_exits, radial)
    res_c, cpu_c = _run(medium, "connections", photons_connections, radial)
    edges = res_e.layout.radial_mm[0]
    area = np.pi * (edges[1:] ** 2 - edges[:-1] ** 2)
    n_r = res_e.layout.n_r
    for k, comp in ((0, "single"), (1, "multiple")):
        m_e, se_e = res_e.mean("exits/radial_G")[0, k, :n_r], res_e.stderr("exits/radial_G")[0, k, :n_r]
        m_c, se_c = res_c.mean("connections/radial_G")[0, k, :n_r], res_c.stderr("connections/radial_G")[0, k, :n_r]
        with np.errstate(divide="ignore", invalid="ignore"):
            eff_e = 1.0 / (se_e**2 * cpu_e)
            eff_c = 1.0 / (se_c**2 * cpu_c)
        for i in range(n_r):
            rows.append({
                "component": comp, "r_lo_mm": edges[i], "r_hi_mm": edges[i + 1],
                "Rd_r_exits": m_e[i] / area[i], "Rd_r_connections": m_c[i] / area[i],
                "eff_exits": float(eff_e[i]), "eff_connections": float(eff_c[i]),
                # Undefined where an estimator saw no event (zero variance of a zero estimate).
                "ratio": float(eff_c[i] / eff_e[i]) if np.isfinite(eff_c[i]) and np.isfinite(eff_e[i]) else float("nan"),
            })  # fmt: skip
    rows.append({"cpu_s_exits": cpu_e, "cpu_s_connections": cpu_c, "photons_exits": photons_exits, "photons_connections": photons_connections})
    return rows


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m workers.efficiency", description=__doc__)
    p.add_argument("--medium", default="M1", choices=sorted(MEDIA))
    p.add_argument("--photons-exits", type=int, default=200_000)
    p.add_argument("--photons-connections", type=int, default=4_000)
    p.add_argument("--radial-count", type=int, default=16)
    p.add_argument("--max-mm", type=float, default=2.0)
    p.add_argument("--json", action="store_true")
    a = p.parse_args(argv)
    radial = {"count": a.radial_count, "max_mm": a.max_mm, "spacing": "log", "min_fraction": 0.01}
    rows = efficiency(a.medium, a.photons_exits, a.photons_connections, radial)
    if a.json:
        print(json.dumps(rows))
        return 0
    info = rows.pop()
    print(f"{a.medium}: exits {info['photons_exits']} photons in {info['cpu_s_exits']:.1f} CPU-s, "
          f"connections {info['photons_connections']} photons in {info['cpu_s_connections']:.1f} CPU-s")  # fmt: skip
    print(f"{'component':<9} {'r_lo':>7} {'r_hi':>7} {'Rd_r exits':>11} {'Rd_r conn':>11} {'eff exits':>10} {'eff conn':>10} {'conn/exits':>10}")
    for r in rows:
        print(f"{r['component']:<9} {r['r_lo_mm']:>7.4f} {r['r_hi_mm']:>7.4f} {r['Rd_r_exits']:>11.4g} {r['Rd_r_connections']:>11.4g} "
              f"{r['eff_exits']:>10.3g} {r['eff_connections']:>10.3g} {r['ratio']:>10.3g}")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
