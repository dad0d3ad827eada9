"""Node values from bins centred on pbrt's nodes (workers.exports.nodes): on smooth profiles whose
bin masses are known exactly (photon beam diffusion integrated by quadrature), the node values
are within 1 % where the profile matters and within their own error estimate everywhere."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import integrate

from schema.bins import pbrt_radial_edges, pbrt_radius_nodes
from workers.diffusion import pbd_rd
from workers.exports.nodes import check_pbrt_edges, node_values

EDGES = pbrt_radial_edges(64)
NODES = pbrt_radius_nodes(64)


def _exact(rho, g, eta):
    f = lambda r: 2 * math.pi * r * float(pbd_rd(r, 1 - rho, rho, g, eta))  # noqa: E731
    masses = np.array([integrate.quad(f, a, b, limit=200, epsrel=1e-11)[0] for a, b in zip(EDGES[:-1], EDGES[1:])])
    return masses, np.array([f(r) for r in NODES])


@pytest.mark.parametrize("rho, g, eta", [(0.3, 0.0, 1.33), (0.95, 0.0, 1.33), (0.999, 0.9, 1.0), (0.8, -0.3, 1.5),
                                         (1.0, 0.0, 1.33)])
def test_node_values_of_beam_diffusion_profiles(rho, g, eta):
    masses, exact = _exact(rho, g, eta)
    values, stderr, error = node_values(masses, np.full_like(masses, 1e-3))
    peak = exact.max()
    diff = np.abs(values - exact)[1:]
    assert np.all(diff <= 1.5 * error[1:] + 1e-6 * peak), np.flatnonzero(diff > 1.5 * error[1:] + 1e-6 * peak) + 1
    matters = exact[1:] > 1e-4 * peak
    assert np.max(diff[matters] / exact[1:][matters]) < 1e-2
    plain = masses[1:] / (2 * 0.5 * math.log(1.2) * NODES[1:])  # mass / width in ln r, uncorrected
    assert np.max(np.abs(plain - exact[1:])[matters] / exact[1:][matters]) > 1e-3  # the correction does something
    assert np.all(values >= 0) and np.all(np.isfinite(error))
    np.testing.assert_allclose(stderr[1:] / values[1:], 1e-3 / masses[1:], rtol=1e-12)  # se scales like the value


def test_unresolved_bins_give_zero_with_nan_error():
    masses, _ = _exact(0.5, 0.0, 1.33)
    masses[40:] = 0.0  # no events out there
    se = np.full_like(masses, 1e-4)
    se[40:] = np.nan
    values, stderr, error = node_values(masses, se)
    assert np.all(values[40:] == 0.0) and np.all(np.isnan(stderr[40:])) and np.all(np.isnan(error[40:]))
    assert np.isnan(error[39])  # its outer neighbour has no mass: slope unknown, error not estimated
    assert np.all(np.isfinite(values))


def test_edges_check():
    assert check_pbrt_edges(EDGES) and check_pbrt_edges(pbrt_radial_edges(10))
    assert not check_pbrt_edges(EDGES * 1.001) and not check_pbrt_edges(np.linspace(0, 200, 65))
