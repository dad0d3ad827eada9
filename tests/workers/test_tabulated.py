"""pbrt's tabulated BSSRDF (workers.models.tabulated): our Sample_Sr / Pdf_Sr / Sr / r_max on pbrt's own
photon-beam-diffusion table, proved against the density they must follow."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import integrate

from tests.support.stats import assert_samples_match_pdf
from workers.models.diffusion import pbd_rd
from workers.models.tabulated import BSSRDFTable, beam_diffusion_table, pbrt_rho_samples, pdf_sr, r_max, sample_sr, sr


@pytest.fixture(scope="module")
def table() -> BSSRDFTable:
    return beam_diffusion_table(g=0.0, eta=1.33)


def test_pbrt_albedo_nodes():
    rho = pbrt_rho_samples(100)
    assert rho[0] == 0.0 and rho[-1] == 1.0 and np.all(np.diff(rho) > 0)
    i = np.arange(100)
    np.testing.assert_allclose(rho, (1 - np.exp(-8 * i / 99)) / (1 - np.exp(-8)), rtol=1e-13, atol=1e-16)


def test_table_layout_and_rho_eff(table):
    assert table.profile.shape == (100, 64) and table.profile_cdf.shape == (100, 64)
    assert np.all(table.profile_cdf[:, 0] == 0.0)
    np.testing.assert_array_equal(table.profile_cdf[:, -1], table.rho_eff)
    assert np.all(table.profile[0] == 0.0)  # rho = 0 scatters nothing
    assert np.all(np.diff(table.rho_eff) > 0)  # invertible, as pbrt's SubsurfaceFromDiffuse needs


@pytest.mark.parametrize("i", [10, 50, 80, 95])
def test_catmull_rom_rho_eff_is_the_profiles_integral(table, i):
    """On pbrt's geometric radius nodes the spline's integral of the profile is within 1e-3 of
    the integral of the continuous profile it samples (the integration error a table adds)."""
    rho = table.rho_samples[i]
    nodes = table.radius_samples
    exact = sum(integrate.quad(lambda r: 2 * math.pi * r * float(pbd_rd(r, 1 - rho, rho, 0.0, 1.33)), a, b,
                               epsrel=1e-10, limit=100)[0] for a, b in zip(nodes[:-1], nodes[1:]))
    assert table.rho_eff[i] == pytest.approx(exact, rel=1e-3)


@pytest.mark.parametrize("rho, sigma_t", [(0.3, 1.0), (0.8, 2.5), (0.995, 0.7), (0.5, 10.0)])
def test_sample_sr_follows_pdf_sr(table, rho, sigma_t):
    """Radii drawn by Sample_Sr follow 2 pi r Pdf_Sr(r) (chi-square; cell masses by quad of
    Pdf_Sr, independently of the sampler), and Pdf_Sr integrates to 1 over the plane."""
    nodes = table.radius_samples / sigma_t
    density = lambda r: 2 * math.pi * r * float(pdf_sr(table, rho, r, sigma_t))  # noqa: E731
    norm = sum(integrate.quad(density, a, b, limit=100)[0] for a, b in zip(nodes[:-1], nodes[1:]))
    assert norm == pytest.approx(1.0, rel=1e-6)
    u = np.random.default_rng(11).random(80_000)
    radii = sample_sr(table, rho, u, sigma_t)
    assert np.all(radii >= 0) and np.all(radii <= nodes[-1])
    edges = np.unique(np.concatenate([nodes[:48], np.geomspace(nodes[1], nodes[-1], 40)]))
    assert_samples_match_pdf(radii, density, edges, n_tests=4, points=list(nodes), what=f"Sample_Sr rho={rho}")


@pytest.mark.parametrize("rho, sigma_t", [(0.3, 1.0), (0.9, 3.0), (0.999, 1.0)])
def test_r_max_holds_the_0_999_quantile(table, rho, sigma_t):
    rm = r_max(table, rho, sigma_t)
    nodes = table.radius_samples / sigma_t
    density = lambda r: 2 * math.pi * r * float(pdf_sr(table, rho, r, sigma_t))  # noqa: E731
    cuts = np.unique(np.concatenate([nodes[nodes < rm], [rm]]))
    inside = sum(integrate.quad(density, a, b, limit=100)[0] for a, b in zip(cuts[:-1], cuts[1:]))
    assert inside == pytest.approx(0.999, abs=1e-7)


def test_sr_is_world_units_of_the_profile(table):
    """Sr(r) = sigma_t^2 profile(r sigma_t) / (2 pi r sigma_t): at a node it is the node value."""
    rho, sigma_t = table.rho_samples[70], 2.0
    j = np.arange(1, 64)
    r = table.radius_samples[j] / sigma_t
    expected = sigma_t**2 * table.profile[70, j] / (2 * math.pi * table.radius_samples[j])
    np.testing.assert_allclose(sr(table, rho, r, sigma_t), np.maximum(expected, 0), rtol=1e-12)
    assert np.all(sr(table, rho, [-1.0, 1e6], sigma_t) == 0.0)
    assert np.all(sample_sr(table, 0.5, [0.5], 0.0) == -1.0)  # sigma_t = 0: no sample (pbrt-v3's -1)


@pytest.mark.parametrize("rho", [-0.1, 1.5, float("nan")])
def test_sample_sr_outside_the_albedo_nodes_is_zero_as_pbrt(table, rho):
    """pbrt's SampleCatmullRom2D returns 0 when CatmullRomWeights fails (rho outside the rows), so
    Sample_Sr gives radius 0 there, not a failure value; Sr and Pdf_Sr are 0 there too."""
    out = sample_sr(table, rho, [0.0, 0.5, 0.99], 1.0)
    assert out.shape == (3,) and np.all(out == 0.0)
    assert np.all(sr(table, rho, [0.1, 1.0], 1.0) == 0.0) and np.all(pdf_sr(table, rho, [0.1, 1.0], 1.0) == 0.0)
