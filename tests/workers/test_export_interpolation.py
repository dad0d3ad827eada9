"""pbrt samples a tabulated BSSRDF at albedos between the rows (Catmull-Rom weights over rows, some
negative): on the README's small sparse table (4,000 photons per albedo, bins without events in
every row) every row's spline is >= 0, the per-range report of the export names where the
interpolated rows dip, pbrt's sampler (our port) follows the interpolated profile where the
report says the range is clean, and misses mass where it says it is not."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from scipy import integrate

from schema import parse_spec
from tests.support.stats import assert_samples_match_pdf
from workers.models.catmull_rom import catmull_rom, integrate_catmull_rom
from workers.exports.conserving import interval_minima
from workers.exports.interpolation import NEGLIGIBLE_NEGATIVE, RANGE_SAMPLES, interpolated_fraction
from workers.exports.pbrt import pbrt_tables
from workers.exports.source import ExportSource
from workers.run.simulate import simulate_sweep
from workers.models.tabulated import pdf_sr, sample_sr

README_SPEC = json.loads((Path(__file__).resolve().parents[2] / "examples" / "pbrt-sweep.json").read_text())


@pytest.fixture(scope="module")
def table(tmp_path_factory):
    out = tmp_path_factory.mktemp("pbrt-sweep")
    simulate_sweep(parse_spec(README_SPEC), str(out), threads=1)
    (t,) = pbrt_tables(ExportSource.from_directory(out))
    return t


def test_rows_are_non_negative_despite_empty_bins(table):
    """Every row has bins without events (NaN standard errors), yet every row's spline is >= 0
    on every interval, so its CDF is monotone: profileNegativeMass is 0."""
    assert np.all(np.isnan(table.profile_node_error).sum(axis=1) == 0)  # modelled nodes state their error
    assert np.all(table.profile_negative_mass == 0.0)
    for row in table.profile:
        assert np.all(interval_minima(table.radius_samples, row) >= 0)
        _total, cdf = integrate_catmull_rom(table.radius_samples, row)
        assert np.all(np.diff(cdf) >= 0)


def _dense_fraction(t, rho: float) -> float:
    """Negative mass / rhoEff of the interpolated row by trapezoid quadrature on a fine grid."""
    row = t.row(rho)
    x = np.unique(np.concatenate([np.linspace(a, b, 2001) for a, b in zip(t.radius_samples[:-1], t.radius_samples[1:])]))
    return float(np.trapezoid(np.minimum(catmull_rom(t.radius_samples, row, x), 0.0), x) / t.row(rho, t.rho_eff[:, None])[0])


def test_range_report_is_the_interpolated_rows_negative_mass(table):
    """rangeNegativeMass at rangeWorstRho equals independent quadrature of the interpolated row,
    is the minimum over the range's sampled albedos, and the warnings list exactly the ranges
    beyond NEGLIGIBLE_NEGATIVE; this sparse table has both kinds."""
    t = table.bssrdf_table()
    for i, (worst, at) in enumerate(zip(table.range_negative_mass, table.range_worst_rho)):
        lo, hi = table.rho_samples[i], table.rho_samples[i + 1]
        inside = lo + np.arange(1, RANGE_SAMPLES + 1) / (RANGE_SAMPLES + 1) * (hi - lo)
        assert worst == min([0.0] + [interpolated_fraction(t, float(a)) for a in inside])
        if worst < 0:
            assert lo < at < hi and worst == pytest.approx(_dense_fraction(t, at), rel=1e-4, abs=1e-9)
    warned = [w["rhoRange"] for w in table.meta["interpolationWarnings"]]
    expected = [[table.rho_samples[i], table.rho_samples[i + 1]] for i in np.flatnonzero(table.range_negative_mass < -NEGLIGIBLE_NEGATIVE)]
    assert warned == expected and 0 < len(warned) < len(table.range_negative_mass)


def test_sampling_between_rows_follows_the_interpolated_profile(table):
    """In every range the export calls clean, pbrt's Sample_Sr (our port) at the range's middle
    draws radii from 2 pi r Pdf_Sr: chi-square against the interpolated profile integrated by
    quadrature (normalised by its integral: Pdf_Sr clamps what little negative mass there is)."""
    t = table.bssrdf_table()
    clean = np.flatnonzero(table.range_negative_mass >= -NEGLIGIBLE_NEGATIVE)
    assert clean.size >= 1
    for i in clean:
        rho = 0.5 * (t.rho_samples[i] + t.rho_samples[i + 1])
        nodes = t.radius_samples
        density = lambda r: 2 * math.pi * r * float(pdf_sr(t, rho, r, 1.0))  # noqa: E731
        norm = sum(integrate.quad(density, a, b, limit=100)[0] for a, b in zip(nodes[:-1], nodes[1:]))
        assert norm == pytest.approx(1.0, abs=2 * NEGLIGIBLE_NEGATIVE)
        radii = sample_sr(t, rho, np.random.default_rng(int(i)).random(60_000), 1.0)
        edges = np.unique(np.concatenate([nodes[nodes < 40.0], [40.0, nodes[-1]]]))
        assert_samples_match_pdf(radii, lambda r: density(r) / norm, edges, n_tests=len(clean), points=list(nodes),
                                 what=f"Sample_Sr at rho = {rho:.4f}")


def test_flagged_ranges_really_misplace_mass(table):
    """Where the report says an interpolated row dips by more than 1e-3 of rhoEff, the row's CDF
    is not monotone and the sampler at that albedo does not follow Pdf_Sr: the same chi-square
    as above, with 400,000 radii, rejects it (the report names a real failure)."""
    t = table.bssrdf_table()
    flagged = np.flatnonzero(table.range_negative_mass < -1e-3)
    assert flagged.size >= 1
    nodes = t.radius_samples
    for i in flagged:
        rho = float(table.range_worst_rho[i])
        assert np.any(np.diff(t.row(rho, t.profile_cdf)) < 0)
        density = lambda r: 2 * math.pi * r * float(pdf_sr(t, rho, r, 1.0))  # noqa: E731
        norm = sum(integrate.quad(density, a, b, limit=100)[0] for a, b in zip(nodes[:-1], nodes[1:]))
        radii = sample_sr(t, rho, np.random.default_rng(int(i)).random(400_000), 1.0)
        edges = np.unique(np.concatenate([nodes[nodes < 40.0], [40.0, nodes[-1]]]))
        with pytest.raises(AssertionError):
            assert_samples_match_pdf(radii, lambda r: density(r) / norm, edges, n_tests=1, points=list(nodes),
                                     what=f"Sample_Sr at flagged rho = {rho:.4f}")
