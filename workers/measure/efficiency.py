"""`python -m workers.measure.efficiency`: efficiency of each estimator per spatial bin.

Efficiency = 1 / (variance x CPU seconds): the inverse of the CPU time needed for a unit
variance.  Each estimator (hybrid, the default; exits; connections) runs alone on the same medium
(M1 of the engine issue by default: sigma_t 10/mm, albedo 0.99, g 0.9, eta 1.3; M2 with
--medium M2) at the given incidence; the table (Markdown, for BENCHMARKS.md) lists, per spatial bin and
component (single, multiple), the events each estimator saw, Rd of each and their efficiencies, the ratio connections / exits (> 1:
connections win) and the hybrid's efficiency over the better of the two (the bar: >= 0.5).
Spatial bins are radial rings at normal incidence and (r, theta_s) sectors at oblique incidence
(``--theta-s``, default 4 there), one direction bin each; the last lines give, per component,
the smallest hybrid / best ratio over the bins in which every estimator saw at least
``--min-events`` events (fewer make the variance itself too noisy to compare).
Variances are per-photon for exits and hybrid, from 32 batches for connections (whose ratios
therefore scatter by ~25 %).  A bin an estimator saw no event in has no efficiency (nan).

``--json`` prints the rows as a list of objects, the shape of the two-estimator tool with one more
estimator key each: per bin ``component, r_lo_mm, r_hi_mm, Rd_r_<est>, eff_<est>, ratio``
(connections / exits), plus ``theta_s_lo, theta_s_hi, Rd_<est>`` (the same value as Rd_r_<est>),
``events_<est>, ratio_hybrid``; the last object holds ``cpu_s_<est>, photons_<est>, medium,
incidence_deg``; <est> is each of hybrid, exits, connections.
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np
import torch

from schema import ESTIMATORS, SimulationSpec

from .bench import MEDIA
from workers.run.simulate import simulate

__all__ = ["efficiency", "table", "worst_hybrid_ratio", "main"]



def _run(medium: str, estimator: str, photons: int, radial: dict, incidence: float, n_theta: int) -> tuple[object, float]:
    bins = {"radial": radial, "theta_s": {"count": n_theta}, "cos_theta_o": {"count": 1}, "phi_o": {"count": 1}}
    spec = SimulationSpec.model_validate({
        "name": f"eff-{medium}-{estimator}", "medium": MEDIA[medium], "photons": photons, "shards": 4,
        "batches_per_shard": 8, "estimator": estimator, "seed": 11, "bins": bins, "incidence_deg": [incidence],
    })  # fmt: skip
    # Compile first, on shards with the same batch count (the batch starts are a kernel argument:
    # another count would compile new kernels inside the timed run) and a different seed.
    simulate(spec.model_copy(update={"photons": 4 * 64, "seed": 12}), threads=1)
    cpu0 = time.process_time()
    result = simulate(spec, threads=1)
    return result, time.process_time() - cpu0


def efficiency(medium: str, photons: dict[str, int], radial: dict, incidence: float = 0.0,
               n_theta: int = 1) -> list[dict]:
    """Per spatial bin (r, theta_s) and component: Rd of the bin per unit area, events and
    efficiency of each estimator; the last row holds the run facts."""
    torch.set_num_threads(1)
    runs = {est: _run(medium, est, photons[est], radial, incidence, n_theta) for est in ESTIMATORS}
    first = runs["exits"][0]
    edges, theta = first.layout.radial_mm[0], first.layout.theta_s
    area = first.layout.area_mm2(0)  # [n_r, n_theta]
    n_r = first.layout.n_r
    rows = []
    for k, comp in ((0, "single"), (1, "multiple")):
        m, eff, events = {}, {}, {}
        for est, (res, cpu) in runs.items():
            m[est] = res.mean(f"{est}/bins_G")[0, k, :n_r, :, 0, 0] / area
            se = res.stderr(f"{est}/bins_G")[0, k, :n_r, :, 0, 0]  # NaN where no event: no efficiency
            events[est] = res.events(f"{est}/bins_G")[0, k, :n_r, :, 0, 0]
            with np.errstate(divide="ignore", invalid="ignore"):
                eff[est] = np.where(se > 0, 1.0 / (se**2 * cpu), np.nan)
        for i in range(n_r):
            for j in range(n_theta):
                e = {est: float(eff[est][i, j]) for est in ESTIMATORS}
                pair = [e["exits"], e["connections"]]
                best = np.nanmax(pair) if np.isfinite(pair).any() else np.nan
                rows.append({
                    "component": comp, "r_lo_mm": float(edges[i]), "r_hi_mm": float(edges[i + 1]),
                    "theta_s_lo": float(theta[j]), "theta_s_hi": float(theta[j + 1]),
                    # Rd of the bin per unit area [1/mm^2] under its name before theta_s sectors
                    # (Rd_r_<estimator>, kept for readers of the JSON) and as Rd_<estimator>.
                    **{f"Rd_r_{est}": float(m[est][i, j]) for est in ESTIMATORS},
                    **{f"Rd_{est}": float(m[est][i, j]) for est in ESTIMATORS},
                    **{f"events_{est}": int(events[est][i, j]) for est in ESTIMATORS},
                    **{f"eff_{est}": e[est] for est in ESTIMATORS},
                    "ratio": e["connections"] / e["exits"],  # nan where either saw no event
                    "ratio_hybrid": e["hybrid"] / best if np.isfinite(best) else float("nan"),
                })  # fmt: skip
    rows.append({**{f"cpu_s_{est}": cpu for est, (_, cpu) in runs.items()}, **{f"photons_{est}": photons[est] for est in ESTIMATORS},
                 "medium": medium, "incidence_deg": incidence})  # fmt: skip
    return rows


def worst_hybrid_ratio(rows: list[dict], component: str, min_events: int) -> tuple[float, int]:
    """(smallest hybrid / best ratio, bins compared) over the bins of `component` in which
    every estimator saw at least `min_events` events."""
    ratios = [r["ratio_hybrid"] for r in rows if r["component"] == component
              and all(r[f"events_{est}"] >= min_events for est in ESTIMATORS) and np.isfinite(r["ratio_hybrid"])]
    return (min(ratios), len(ratios)) if ratios else (float("nan"), 0)


def _bin_line(r: dict, min_events: int) -> str:
    theta = f"{np.degrees(r['theta_s_lo']):.0f} - {np.degrees(r['theta_s_hi']):.0f}"
    events = " / ".join(str(r[f"events_{est}"]) for est in ESTIMATORS)
    # Bins some estimator saw fewer than min_events events in are left out of the summary: starred.
    star = "" if all(r[f"events_{est}"] >= min_events for est in ESTIMATORS) else " *"
    cells = [r["component"], f"{r['r_lo_mm']:.4g} - {r['r_hi_mm']:.4g}", theta, events,
             *(f"{r[f'Rd_r_{est}']:.4g}" for est in ESTIMATORS), *(f"{r[f'eff_{est}']:.3g}" for est in ESTIMATORS),
             f"{r['ratio']:.3g}", f"{r['ratio_hybrid']:.3g}{star}"]  # fmt: skip
    return "| " + " | ".join(cells) + " |"


def table(rows: list[dict], min_events: int) -> list[str]:
    """The rows of :func:`efficiency` (run facts last) as a Markdown table, one line per
    (component, r, theta_s) bin as BENCHMARKS.md shows them, then the run facts and, per
    component, the smallest hybrid / best ratio over the bins every estimator resolved."""
    *bins, info = rows
    lines = [
        f"{info['medium']}, incidence {info['incidence_deg']:g} deg: "
        + ", ".join(f"{est} {info[f'photons_{est}']} photons in {info[f'cpu_s_{est}']:.1f} CPU-s" for est in ESTIMATORS),
        "",
        "| component | r (mm) | theta_s (deg) | events hyb / exits / conn | Rd_r hybrid | Rd_r exits | Rd_r conn "
        "| eff hybrid | eff exits | eff conn | conn/exits | hyb/best |",
        "|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
        *(_bin_line(r, min_events) for r in bins),
        "",
        f"Rd_r in 1/mm^2, eff = 1 / (variance x CPU s); * fewer than {min_events} events in some estimator (not in the summary).",
    ]  # fmt: skip
    for comp in ("single", "multiple"):
        worst, n = worst_hybrid_ratio(bins, comp, min_events)
        lines.append(f"{comp}: hybrid / best >= {worst:.3g} over {n} bins with >= {min_events} events in every estimator (bar 0.5)")
    return lines


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m workers.measure.efficiency", description=__doc__)
    p.add_argument("--medium", default="M1", choices=sorted(MEDIA))
    p.add_argument("--incidence", type=float, default=0.0, help="incidence angle in degrees (default 0)")
    p.add_argument("--photons-exits", type=int, default=200_000)
    p.add_argument("--photons-hybrid", type=int, default=200_000)
    p.add_argument("--photons-connections", type=int, default=4_000)
    p.add_argument("--radial-count", type=int, default=16)
    p.add_argument("--max-mm", type=float, default=2.0)
    p.add_argument("--theta-s", type=int, default=None, help="theta_s bins (default 1 at normal incidence, else 4)")
    p.add_argument("--min-events", type=int, default=100, help="events every estimator needs in a bin for the summary")
    p.add_argument("--json", action="store_true")
    a = p.parse_args(argv)
    radial = {"count": a.radial_count, "max_mm": a.max_mm, "spacing": "log", "min_fraction": 0.01}
    photons = {"exits": a.photons_exits, "hybrid": a.photons_hybrid, "connections": a.photons_connections}
    n_theta = a.theta_s or (1 if a.incidence == 0 else 4)
    rows = efficiency(a.medium, photons, radial, a.incidence, n_theta)
    if a.json:
        print(json.dumps(rows))
        return 0
    print("\n".join(table(rows, a.min_events)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
