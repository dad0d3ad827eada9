"""workers.measure.efficiency: rows per (component, r, theta_s) bin, efficiencies from the runs' own
standard errors and CPU time, and the per-bin summary of the hybrid's bar."""

from __future__ import annotations

import json
import math

from workers.measure.efficiency import ESTIMATORS, efficiency, main, table, worst_hybrid_ratio


def test_efficiency_rows_per_spatial_bin_and_the_summary():
    radial = {"count": 3, "max_mm": 2.0, "spacing": "log", "min_fraction": 0.05}
    photons = {"exits": 4000, "hybrid": 4000, "connections": 200}
    rows = efficiency("M2", photons, radial, incidence=45.0, n_theta=2)
    info = rows.pop()
    assert info["incidence_deg"] == 45.0 and all(info[f"cpu_s_{e}"] > 0 for e in ESTIMATORS)
    assert len(rows) == 2 * 3 * 2
    assert [(r["component"], r["theta_s_lo"]) for r in rows[:2]] == [("single", -math.pi / 2), ("single", math.pi / 2)]
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


def test_json_keeps_the_two_estimator_keys_and_adds_the_hybrid(capsys):
    """`--json` has the shape it had before the hybrid (Rd_r_exits, Rd_r_connections, eff_*,
    ratio; cpu_s_* and photons_* in the last object), with hybrid keys beside them."""
    argv = ["--medium", "M2", "--json", "--radial-count", "2", "--photons-exits", "2000",
            "--photons-hybrid", "2000", "--photons-connections", "100"]  # fmt: skip
    assert main(argv) == 0
    rows = json.loads(capsys.readouterr().out)
    info = rows.pop()
    old_row = {"component", "r_lo_mm", "r_hi_mm", "Rd_r_exits", "Rd_r_connections", "eff_exits", "eff_connections", "ratio"}
    old_info = {"cpu_s_exits", "cpu_s_connections", "photons_exits", "photons_connections"}
    new_row = {"Rd_r_hybrid", "eff_hybrid", "ratio_hybrid", "theta_s_lo", "theta_s_hi"}
    new_row |= {f"{key}_{e}" for key in ("Rd", "events") for e in ESTIMATORS}
    assert len(rows) == 2 * 2
    for r in rows:
        assert set(r) == old_row | new_row
        assert all(r[f"Rd_r_{e}"] == r[f"Rd_{e}"] for e in ESTIMATORS)
    assert set(info) == old_info | {"cpu_s_hybrid", "photons_hybrid", "medium", "incidence_deg"}
    assert info["photons_exits"] == 2000 and info["photons_connections"] == 100


def _row(component, r_lo, r_hi, theta_lo, theta_hi, events, ratio_hybrid):
    row = {"component": component, "r_lo_mm": r_lo, "r_hi_mm": r_hi, "theta_s_lo": theta_lo, "theta_s_hi": theta_hi,
           "ratio": 0.5, "ratio_hybrid": ratio_hybrid}  # fmt: skip
    for e, n in zip(ESTIMATORS, events):
        row |= {f"Rd_r_{e}": 0.25, f"Rd_{e}": 0.25, f"events_{e}": n, f"eff_{e}": 1e5}
    return row


def test_table_has_one_line_per_r_theta_s_bin_and_the_summary():
    """At oblique incidence the printed table has a Markdown row per (component, r, theta_s)
    bin, theta_s in degrees, events of each estimator, bins left out of the summary starred."""
    half = math.pi
    rows = [_row("single", 0.0, 0.02, 0.0, half, (500, 400, 300), 1.5), _row("single", 0.0, 0.02, half, 2 * half, (500, 40, 300), 0.2),
            _row("multiple", 0.0, 0.02, 0.0, half, (500, 500, 300), 0.6), _row("multiple", 0.0, 0.02, half, 2 * half, (0, 0, 300), math.nan),
            {f"{k}_{e}": v for e in ESTIMATORS for k, v in (("cpu_s", 1.0), ("photons", 1000))} | {"medium": "M2", "incidence_deg": 45.0}]  # fmt: skip
    lines = table(rows, min_events=100)
    assert lines[0].startswith("M2, incidence 45 deg: hybrid 1000 photons in 1.0 CPU-s")
    body = [line for line in lines if line.startswith("| single") or line.startswith("| multiple")]
    assert body == [
        "| single | 0 - 0.02 | 0 - 180 | 500 / 400 / 300 | 0.25 | 0.25 | 0.25 | 1e+05 | 1e+05 | 1e+05 | 0.5 | 1.5 |",
        "| single | 0 - 0.02 | 180 - 360 | 500 / 40 / 300 | 0.25 | 0.25 | 0.25 | 1e+05 | 1e+05 | 1e+05 | 0.5 | 0.2 * |",
        "| multiple | 0 - 0.02 | 0 - 180 | 500 / 500 / 300 | 0.25 | 0.25 | 0.25 | 1e+05 | 1e+05 | 1e+05 | 0.5 | 0.6 |",
        "| multiple | 0 - 0.02 | 180 - 360 | 0 / 0 / 300 | 0.25 | 0.25 | 0.25 | 1e+05 | 1e+05 | 1e+05 | 0.5 | nan * |",
    ]
    header = next(line for line in lines if line.startswith("| component"))
    assert header.count("|") == body[0].count("|")
    assert lines[-2:] == ["single: hybrid / best >= 1.5 over 1 bins with >= 100 events in every estimator (bar 0.5)",
                          "multiple: hybrid / best >= 0.6 over 1 bins with >= 100 events in every estimator (bar 0.5)"]  # fmt: skip
