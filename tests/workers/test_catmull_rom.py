"""Catmull-Rom splines (workers.models.catmull_rom): interpolation, integration against quadrature,
inversion, and the 2-D sampler against its own density (chi-square)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import integrate

from tests.support.stats import assert_samples_match_pdf
from workers.models.catmull_rom import (
    catmull_rom,
    catmull_rom_weights,
    integrate_catmull_rom,
    invert_catmull_rom,
    bin_integral_matrix,
    find_interval,
    find_interval_pbrt,
    negative_mass,
    sample_catmull_rom_2d,
)

NODES = np.concatenate([[0.0], 0.05 * 1.3 ** np.arange(12)])  # non-uniform, like pbrt's radii


def _values(seed=0, n=len(NODES)):
    return np.random.default_rng(seed).uniform(0.1, 2.0, n)


def test_interpolates_nodes_and_reproduces_lines():
    f = _values()
    np.testing.assert_allclose(catmull_rom(NODES, f, NODES), f, rtol=1e-14)
    line = 0.3 + 2.0 * NODES
    x = np.linspace(NODES[0], NODES[-1], 777)
    np.testing.assert_allclose(catmull_rom(NODES, line, x), 0.3 + 2.0 * x, rtol=1e-12)
    assert np.all(catmull_rom(NODES, f, [-1e-9, NODES[-1] * 1.0001]) == 0.0)  # zero outside


def test_weights_give_the_same_spline_as_evaluation():
    f = _values(1)
    for x in np.linspace(NODES[0], NODES[-1], 301):
        offset, w = catmull_rom_weights(NODES, x)
        idx = [offset + k for k in range(4) if w[k] != 0.0]
        total = sum(w[k] * f[offset + k] for k in range(4) if w[k] != 0.0)
        assert min(idx) >= 0 and max(idx) < len(NODES)
        assert total == pytest.approx(float(catmull_rom(NODES, f, x)), rel=1e-12, abs=1e-14)
        assert sum(w) == pytest.approx(1.0, abs=1e-12)  # constants are reproduced
    assert catmull_rom_weights(NODES, -0.1) is None and catmull_rom_weights(NODES, 1e3) is None


def test_integral_and_cdf_equal_quadrature_of_the_spline():
    f = _values(2)
    total, cdf = integrate_catmull_rom(NODES, f)
    assert cdf[0] == 0.0 and cdf[-1] == total
    for j in range(1, len(NODES)):
        exact = integrate.quad(lambda x: float(catmull_rom(NODES, f, x)), NODES[0], NODES[j], points=NODES[1:j],
                               epsabs=1e-14, epsrel=1e-13, limit=200)[0]
        assert cdf[j] == pytest.approx(exact, rel=1e-11)
    rows = np.stack([f, 2 * f])  # one spline per row
    t2, c2 = integrate_catmull_rom(NODES, rows)
    np.testing.assert_allclose(t2, [total, 2 * total], rtol=1e-14)
    np.testing.assert_allclose(c2[1], 2 * cdf, rtol=1e-14)


def test_invert_monotone_spline():
    f = np.cumsum(_values(3))
    x = np.linspace(NODES[0], NODES[-1], 401)
    np.testing.assert_allclose(invert_catmull_rom(NODES, f, catmull_rom(NODES, f, x)), x, atol=1e-10)
    assert invert_catmull_rom(NODES, f, f[0] - 1.0) == NODES[0]
    assert invert_catmull_rom(NODES, f, f[-1] + 1.0) == NODES[-1]


@pytest.mark.parametrize("alpha", [0.0, 0.37, 0.5, 0.93, 1.0])
def test_sample_2d_follows_the_interpolated_density(alpha):
    """Samples at alpha (a node or between nodes) follow the spline of the interpolated row,
    normalised by its integral: chi-square against quad of catmull_rom, independently of the
    sampler's Newton inversion. The returned pdf is that same density."""
    nodes1 = np.array([0.0, 0.25, 0.5, 0.75, 1.0])
    base = np.exp(-NODES / 0.4) * (NODES + 0.05)
    values = np.stack([base * (1 + a) ** 2 * np.exp(a * NODES) for a in nodes1])
    _, cdf = integrate_catmull_rom(NODES, values)
    u = np.random.default_rng(4).random(60_000)
    x, f, pdf = sample_catmull_rom_2d(nodes1, NODES, values, cdf, alpha, u)
    offset, w = catmull_rom_weights(nodes1, alpha)
    row = sum(w[k] * values[offset + k] for k in range(4) if w[k] != 0)
    norm = integrate_catmull_rom(NODES, row)[0]
    np.testing.assert_allclose(f, catmull_rom(NODES, row, x), rtol=1e-6, atol=1e-10)
    np.testing.assert_allclose(pdf, f / norm, rtol=1e-12)
    edges = np.unique(np.concatenate([NODES, np.linspace(0, NODES[-1], 40)]))
    assert_samples_match_pdf(x, lambda t: float(catmull_rom(NODES, row, t)) / norm, edges, n_tests=5,
                             points=list(NODES), what=f"sample_catmull_rom_2d at alpha={alpha}")
    assert sample_catmull_rom_2d(nodes1, NODES, values, cdf, 1.5, u) is None


def test_sample_2d_quantiles_invert_the_cdf():
    """u -> x is the inverse of the interpolated running integral: cdf(x(u)) = u (exactly, to the
    solver's tolerance), so the 0.999 quantile holds 99.9 % of the mass."""
    nodes1 = np.array([0.0, 1.0])
    values = np.stack([np.exp(-NODES), np.exp(-2 * NODES)]) * NODES
    _, cdf = integrate_catmull_rom(NODES, values)
    u = np.linspace(0.0, 0.999999, 200)
    x, _, _ = sample_catmull_rom_2d(nodes1, NODES, values, cdf, 0.0, u)
    norm = cdf[0, -1]
    for ui, xi in zip(u[::20], x[::20]):
        mass = integrate.quad(lambda t: float(catmull_rom(NODES, values[0], t)), 0, xi, points=NODES[NODES < xi],
                              limit=200)[0]
        assert mass / norm == pytest.approx(ui, abs=1e-9)
    assert math.isclose(x[0], 0.0, abs_tol=1e-12)


def test_negative_mass_is_the_integral_of_the_negative_lobes():
    values = np.array([0.5, 0.4, 0.0, 0.0, 0.3, 0.01, 0, 0, 0.2, 0.0, 0, 0, 0])
    x = np.linspace(0, NODES[-1], 2_000_001)
    f = catmull_rom(NODES, values, x)
    assert negative_mass(NODES, values) == pytest.approx(np.trapezoid(np.minimum(f, 0), x), rel=1e-6)
    assert negative_mass(NODES, values) < 0
    np.testing.assert_array_equal(negative_mass(NODES, np.stack([1.0 + NODES, values])),
                                  [0.0, negative_mass(NODES, values)])  # a line has none


def test_negative_mass_of_many_random_rows_equals_quadrature():
    """The vectorised split at the cubic's turning points (bisection inside monotone pieces) on
    rows with steep falls, zeros and spikes: every row against fine trapezoid quadrature."""
    rows = np.random.default_rng(4).random((12, len(NODES))) ** 4
    rows[::2, 5:9] = 0.0
    x = np.linspace(0, NODES[-1], 400_001)
    expected = [np.trapezoid(np.minimum(catmull_rom(NODES, row, x), 0), x) for row in rows]
    got = negative_mass(NODES, rows)
    assert np.all(got <= 0) and np.min(got) < -1e-4
    np.testing.assert_allclose(got, expected, rtol=1e-5, atol=1e-12)


def test_bin_integral_matrix_integrates_the_spline_over_bins():
    """(B f)_j is the spline's integral over bin j, by quadrature; bins reaching past the last
    node count only their part inside; B's columns sum to the integration weights."""
    edges = np.concatenate([[0.0, 0.03], np.sqrt(NODES[1:-1] * NODES[2:]), [NODES[-1] * 1.2]])
    f = _values(3)
    B = bin_integral_matrix(NODES, edges)
    expected = [integrate.quad(lambda x: float(catmull_rom(NODES, f, x)), a, min(b, NODES[-1]), points=list(NODES),
                               limit=200, epsabs=0, epsrel=1e-12)[0] for a, b in zip(edges[:-1], edges[1:])]
    np.testing.assert_allclose(B @ f, expected, rtol=1e-10)
    total, _ = integrate_catmull_rom(NODES, np.eye(len(NODES)))
    np.testing.assert_allclose(B.sum(axis=0), total, rtol=1e-12)
    assert np.all(B[np.abs(np.subtract.outer(np.arange(len(edges) - 1), np.arange(len(NODES)))) > 3] == 0)  # banded


def _find_interval_scalar(values, y):
    """pbrt's FindInterval written out once, scalar, as the reference."""
    size, first = len(values) - 2, 1
    while size > 0:
        half = size >> 1
        middle = first + half
        if values[middle] <= y:
            first, size = middle + 1, size - (half + 1)
        else:
            size = half
    return min(max(first - 1, 0), len(values) - 2)


def test_find_interval_pbrt_is_pbrts_binary_search():
    """Equal to searchsorted on sorted arrays, and to pbrt's binary search on non-monotone ones
    (an interpolated CDF with a dip), where the two differ."""
    rng = np.random.default_rng(8)
    differs = False
    for n in (2, 3, 5, 16, 64):
        y = rng.uniform(-0.2, 1.2, 500)
        sorted_values = np.sort(rng.random(n))
        np.testing.assert_array_equal(find_interval_pbrt(sorted_values, y), find_interval(sorted_values, y))
        values = rng.random(n)
        expected = [_find_interval_scalar(values, v) for v in y]
        np.testing.assert_array_equal(find_interval_pbrt(values, y), expected)
        differs |= bool(np.any(find_interval(values, y) != expected))
    assert differs
