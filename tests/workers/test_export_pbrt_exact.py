"""An independent normalisation check of the pbrt export: for isotropic scattering (g = 0) in an
index-matched half-space (eta = 1, so R_spec = 0 and power entered = incident power) the total
diffuse reflectance at normal incidence is exactly R = 1 - sqrt(1 - a) H(1) (Chandrasekhar's
H-function, tests/reference/hfunction.py); the export's measured total and rhoEff, the integral
of the exported profile, must equal it within their errors at every albedo."""

from __future__ import annotations

import numpy as np
import pytest

from schema import parse_spec
from tests.reference.hfunction import diffuse_reflectance_isotropic_matched
from workers.exports.pbrt import pbrt_tables
from workers.exports.profiles import summary_rows
from workers.exports.rho_eff import integration_weights
from workers.exports.source import ExportSource
from workers.output import write_tables
from workers.simulate import simulate

ALBEDOS = (0.5, 0.8, 0.95)
# Three albedos as three channels of one medium with sigma_t = 1: one walk, one pbrt table.
SPEC = {
    "name": "pbrt-exact", "medium": {"sigma_a": [1 - a for a in ALBEDOS], "sigma_s": list(ALBEDOS), "g": 0.0, "eta": 1.0},
    "photons": 40000, "shards": 2, "batches_per_shard": 8, "seed": 31, "estimator": "hybrid",
    "bins": {"radial": {"count": 64, "spacing": "pbrt"}, "cos_theta_o": {"count": 1}, "phi_o": {"count": 1}},
}


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    out = tmp_path_factory.mktemp("pbrt-exact")
    write_tables(simulate(parse_spec(SPEC), threads=1), str(out))
    source = ExportSource.from_directory(out)
    (table,) = pbrt_tables(source)
    return source, table


def test_rho_eff_equals_the_h_function_plane_albedo(exported, walk_stats):
    """The measured total Rd / (1 - R_spec) against the exact value: z-scores with unit spread.
    rhoEff against it: within the node-value error bound (sum_j |W_j| profileNodeError_j plus
    1e-3 rhoEff for the spline's integration, as in tests/workers/test_export_rho_eff.py) plus
    the Sidak z limit times its standard error."""
    source, t = exported
    np.testing.assert_allclose(t.rho_samples, ALBEDOS, rtol=1e-12)
    assert all(r["R_spec"] == 0.0 for r in summary_rows(source.tables["summary"]).values())
    exact = np.array([diffuse_reflectance_isotropic_matched(a) for a in ALBEDOS])
    se = t.rho_eff_stderr
    assert np.all(se / exact < 0.006) and np.all(t.rho_beyond_rmax < 1e-6)  # resolves the normalisation to ~0.5 %
    dof = SPEC["photons"] - 1  # the hybrid's standard errors come from photons (workers.tally)
    limit = walk_stats.z_limit(n_tests=2 * len(ALBEDOS), dof=dof)
    z_measured = (t.rho_eff_measured - exact) / t.rho_eff_measured_stderr
    print(f"rhoEff {t.rho_eff}, measured {t.rho_eff_measured}, exact {exact}, relative se {se / exact}, z {z_measured}")
    assert np.all(np.abs(z_measured) <= limit), z_measured
    walk_stats.assert_unit_spread(z_measured, dof=dof, what="Rd / (1 - R_spec) vs H-function plane albedo")
    weights = integration_weights(t.radius_samples)
    node = np.where(np.isfinite(t.profile_node_error), t.profile_node_error, t.profile)
    bound = np.abs(weights) @ node.T + 1e-3 * t.rho_eff
    print(f"rhoEff - exact {t.rho_eff - exact}, node bound {bound}")
    assert np.all(np.abs(t.rho_eff - exact) <= bound + limit * se), (t.rho_eff - exact, bound, se)
