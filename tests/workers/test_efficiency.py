"""workers.efficiency: rows per (component, r, theta_s) bin, efficiencies from the runs' own
standard errors and CPU time, and the per-bin summary of the hybrid's bar."""

from __future__ import annotations

import math

from workers.efficiency import ESTIMATORS, efficiency, worst_hybrid_ratio


def test_efficiency_rows_per_spatial_bin_and_the_summary():
    radial = {"count": 3, "max_mm": 2.0, "spacing": "log", "min_fraction": 0.05}
    photons = {"exits": 4000, "hybrid": 4000, "connections": 200}
    rows = efficiency("M2", photons, radial, incidence=45.0, n_theta=2)
    info = rows.pop()
    assert info["incidence_deg"] == 45.0 and all(info[f"cpu_s_{e}"] > 0 for e in ESTIMATORS)
    assert len(rows) == 2 * 3 * 2
    assert [(r["component"], r["theta_s_lo"]) for r in rows[:2]] == [("single", 0.0), ("single", math.pi)]
    for r in rows:
        best = max(v for v in (r["eff_exits"], r["eff_connections"]) if math.isfinite(v))
        assert math.isclose(r["ratio_hybrid"], r["eff_hybrid"] / best)
        assert all(r[f"events_{e}"] >= 0 for e in ESTIMATORS)
        # The hybrid tallies multiple scattering with the exit walk: the same events and mean.
        if r["component"] == "multiple":
            assert r["events_hybrid"] == r["events_exits"] and math.isclose(r["Rd_hybrid"], r["Rd_exits"])
    worst, n = worst_hybrid_ratio(rows, "single", 10)
    eligible = [r for r in rows if r["component"] == "single" and all(r[f"events_{e}"] >= 10 for e in ESTIMATORS)]
    assert n == len(eligible) > 0 and worst == min(r["ratio_hybrid"] for r in eligible)
    none, count = worst_hybrid_ratio(rows, "single", 10**9)
    assert math.isnan(none) and count == 0
