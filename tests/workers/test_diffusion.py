"""Diffusion models (workers.models.diffusion) against closed forms, independent quadrature, the exact
single-scattering reference and the published fits they replace."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import integrate

from tests.reference.fresnel import fresnel_reflectance_array
from tests.reference.hfunction import diffuse_reflectance_isotropic_matched
from tests.reference.single_scattering import single_scattering_radial
from workers.models.diffusion import (
    albedo_from_reduced,
    burley_reduced_albedo,
    burley_total_rd,
    dipole_exitance,
    dipole_exitance_total,
    dipole_rd,
    dipole_total_rd,
    fresnel_moment,
    fresnel_reflectance,
    hg_phase,
    pbd_multiple,
    pbd_single,
    reduced_albedo,
)

ETAS = [0.7, 0.9, 1.0, 1.1, 1.3, 1.5, 2.0]


@pytest.mark.parametrize("eta", ETAS)
def test_fresnel_reflectance_equals_the_reference(eta):
    cos = np.concatenate([np.linspace(0.0, 1.0, 501), [1e-12, 0.5 ** 0.5]])
    if eta == 1.0:  # no interface: nothing reflects, grazing included (as workers.walk.optics)
        assert np.all(fresnel_reflectance(cos, eta) == 0.0)
        return
    np.testing.assert_allclose(fresnel_reflectance(cos, eta), fresnel_reflectance_array(cos, eta), rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize("eta", ETAS)
@pytest.mark.parametrize("i", [0, 1, 2])
def test_fresnel_moment_equals_adaptive_quadrature(eta, i):
    mu_c = math.sqrt(max(0.0, 1.0 - 1.0 / eta**2))
    exact, _ = integrate.quad(lambda m: fresnel_reflectance_array(np.array([m]), 1.0 / eta)[0] * m**i, 0.0, 1.0,
                              points=[mu_c] if 0 < mu_c < 1 else None, epsabs=1e-14, epsrel=1e-12, limit=400)
    assert fresnel_moment(i, eta) == pytest.approx(exact, rel=1e-10, abs=1e-14)


def _pbrt_fresnel_moments(eta: float) -> tuple[float, float]:
    """pbrt-v3's polynomial fits FresnelMoment1 / FresnelMoment2 (bssrdf.cpp)."""
    e = [eta**k for k in range(6)]
    if eta < 1:
        m1 = 0.45966 - 1.73965 * e[1] + 3.37668 * e[2] - 3.904945 * e[3] + 2.49277 * e[4] - 0.68441 * e[5]
        m2 = 0.27614 - 0.87350 * e[1] + 1.12077 * e[2] - 0.65095 * e[3] + 0.07883 * e[4] + 0.04860 * e[5]
    else:
        m1 = -4.61686 + 11.1136 * e[1] - 10.4646 * e[2] + 5.11455 * e[3] - 1.27198 * e[4] + 0.12746 * e[5]
        r = 1.0 / eta
        m2 = (-547.033 + 45.3087 * r**3 - 218.725 * r**2 + 458.843 * r + 404.557 * eta - 189.519 * e[2]
              + 54.9327 * e[3] - 9.00603 * e[4] + 0.63942 * e[5])
    return m1, m2


@pytest.mark.parametrize("eta", [0.75, 0.85, 0.95, 1.0, 1.1, 1.2, 1.33, 1.5, 1.75, 2.0])
def test_fresnel_moments_are_what_pbrts_fits_approximate(eta):
    """The convention (the boundary seen from inside) fixed by pbrt's fits: they agree to their
    fitting accuracy (~2e-3), where the other convention differs by up to 0.2."""
    m1, m2 = _pbrt_fresnel_moments(eta)
    assert fresnel_moment(1, eta) == pytest.approx(m1, abs=2.5e-3)
    assert fresnel_moment(2, eta) == pytest.approx(m2, abs=2.5e-3)


@pytest.mark.parametrize("eta", [1.1, 1.3, 1.5, 2.0])
def test_diffuse_fresnel_reflectance_matches_egan_hilgeman_fit(eta):
    """F_dr = 2 FM_1 against the fit Jensen et al. 2001 use, -1.440/eta^2 + 0.710/eta + 0.668 + 0.0636 eta."""
    fit = -1.440 / eta**2 + 0.710 / eta + 0.668 + 0.0636 * eta
    assert 2.0 * fresnel_moment(1, eta) == pytest.approx(fit, abs=2e-3)


def _radial_total(profile, scale: float) -> float:
    """int_0^inf 2 pi r profile(r) dr by adaptive quadrature, split at a few length scales."""
    pts = [0.0] + [scale * 10.0**k for k in range(-3, 4)] + [np.inf]
    return sum(integrate.quad(lambda r: 2 * math.pi * r * float(profile(r)), a, b, epsabs=1e-12, epsrel=1e-10,
                              limit=400)[0] for a, b in zip(pts[:-1], pts[1:]))


@pytest.mark.parametrize("sigma_a, sigma_s_red, eta", [(0.01, 1.0, 1.3), (0.3, 0.7, 1.0), (1e-4, 2.0, 1.5),
                                                       (0.5, 0.5, 0.8)])
def test_dipole_total_formula_is_the_integral_of_its_profile(sigma_a, sigma_s_red, eta):
    total = _radial_total(lambda r: dipole_rd(r, sigma_a, sigma_s_red, eta), 1.0 / (sigma_a + sigma_s_red))
    alpha_r = sigma_s_red / (sigma_a + sigma_s_red)
    assert total == pytest.approx(float(dipole_total_rd(alpha_r, eta)), rel=1e-8)


def test_dipole_total_limits():
    assert float(dipole_total_rd(0.0, 1.3)) == 0.0
    assert float(dipole_total_rd(1.0, 1.3)) == pytest.approx(1.0)  # no absorption: everything comes back
    a = np.linspace(0, 1, 101)
    assert np.all(np.diff(dipole_total_rd(a, 1.3)) > 0)


# At sigma_tr = 0 the fluence term decays as 1/r^3 through a difference of two 1/d terms; quad
# warns of roundoff on [1000 mm, inf) while its result still meets the tolerance below.
@pytest.mark.filterwarnings("ignore::scipy.integrate.IntegrationWarning")
@pytest.mark.parametrize("sigma_tr", [0.0, 0.1, 3.0])
def test_dipole_exitance_total_is_the_integral_of_its_exitance(sigma_tr):
    z_r, z_v, d, c_phi, c_e = 0.7, -1.9, 0.4, 0.13, 0.41
    total = _radial_total(lambda r: dipole_exitance(r, z_r, z_v, sigma_tr, d, c_phi, c_e), 1.0)
    assert total == pytest.approx(float(dipole_exitance_total(z_r, z_v, sigma_tr, d, c_phi, c_e)), rel=1e-8)


def _pbd_ms_integrand(r, z, sigma_a, sigma_s, g, eta):
    """The depth integrand of photon beam diffusion written out again from its formula."""
    s_red = sigma_s * (1 - g)
    st_red = sigma_a + s_red
    d_g = (2 * sigma_a + s_red) / (3 * st_red**2)
    s_tr = math.sqrt(sigma_a / d_g)
    fm1, fm2 = fresnel_moment(1, eta), fresnel_moment(2, eta)
    z_e = -2 * d_g * (1 + 3 * fm2) / (1 - 2 * fm1)
    e = dipole_exitance(r, z, -z + 2 * z_e, s_tr, d_g, 0.25 * (1 - 2 * fm1), 0.5 * (1 - 3 * fm2))
    kappa = 1 - math.exp(-2 * st_red * (math.hypot(r, z) + z))
    return st_red * math.exp(-st_red * z) * kappa * (s_red / st_red) ** 2 * float(e)


@pytest.mark.parametrize("sigma_a, sigma_s, g, eta", [(0.05, 0.95, 0.0, 1.33), (0.2, 0.8, 0.7, 1.5), (0.01, 0.99, -0.3, 1.0)])
@pytest.mark.parametrize("r", [0.03, 0.5, 4.0])
def test_pbd_multiple_depth_integral_converges_to_adaptive_quadrature(sigma_a, sigma_s, g, eta, r):
    """pbrt's midpoint-in-quantile depth samples converge to the depth integral (checks the
    sample placement and weights); pbrt's 100 samples are within 2 %."""
    exact, _ = integrate.quad(lambda z: _pbd_ms_integrand(r, z, sigma_a, sigma_s, g, eta), 0, np.inf,
                              epsabs=0, epsrel=1e-10, limit=400)
    assert float(pbd_multiple(r, sigma_a, sigma_s, g, eta, n_depth=20000)) == pytest.approx(exact, rel=2e-4)
    assert float(pbd_multiple(r, sigma_a, sigma_s, g, eta)) == pytest.approx(exact, rel=2e-2)


@pytest.mark.parametrize("albedo, g, eta", [(0.5, 0.0, 1.3), (0.9, 0.8, 1.5), (0.99, -0.4, 1.0), (0.7, 0.3, 0.8)])
def test_pbd_single_is_the_exact_single_scattering(albedo, g, eta):
    """Integrated over annuli, pbrt's single-scattering profile equals the exact single
    scattering of tests/reference (normalised per unit power entered)."""
    edges = np.array([0.0, 0.01, 0.05, 0.2, 0.5, 1.0, 2.0, 4.0])
    exact = single_scattering_radial(edges, 1.0, albedo, g, eta) / (1.0 - fresnel_reflectance_array(np.array([1.0]), eta)[0])

    def annulus(a, b, n_depth):
        return integrate.quad(lambda r: 2 * math.pi * r * float(pbd_single(r, 1 - albedo, albedo, g, eta, n_depth)),
                              a, b, epsabs=1e-13, epsrel=1e-10, limit=400)[0]

    fine = np.array([annulus(a, b, 20000) for a, b in zip(edges[:-1], edges[1:])])
    np.testing.assert_allclose(fine, exact, rtol=2e-3, atol=1e-9)


def test_hg_phase_normalised_with_mean_cosine_g():
    for g in (-0.7, 0.0, 0.5, 0.95):
        norm = integrate.quad(lambda c: 2 * math.pi * float(hg_phase(c, g)), -1, 1, points=[1.0], limit=400)[0]
        mean = integrate.quad(lambda c: 2 * math.pi * c * float(hg_phase(c, g)), -1, 1, points=[1.0], limit=400)[0]
        assert norm == pytest.approx(1.0, rel=1e-9) and mean == pytest.approx(g, abs=1e-9)


def test_burley_relation_monotone_with_inverse():
    a = np.linspace(0.0, 1.0, 1001)
    alpha = burley_reduced_albedo(a)
    assert np.all(np.diff(alpha) > 0)
    assert alpha[0] == pytest.approx(0.0, abs=1e-5) and alpha[-1] == pytest.approx(1.0, abs=1e-5)
    np.testing.assert_allclose(burley_total_rd(alpha[1:-1]), a[1:-1], atol=1e-12)


@pytest.mark.parametrize("albedo", [0.1, 0.3, 0.5, 0.8, 0.9, 0.95, 0.99, 0.999])
def test_burley_relation_is_the_diffuse_albedo_of_an_index_matched_isotropic_half_space(albedo):
    """What the fit fits: int_0^1 R(albedo, mu0) 2 mu0 dmu0, R the exact reflectance of an
    index-matched isotropic half space (Chandrasekhar's H-function, tests/reference)."""
    mu, w = np.polynomial.legendre.leggauss(24)
    mu, w = 0.5 * (mu + 1), 0.5 * w
    diffuse = sum(2 * m * wi * diffuse_reflectance_isotropic_matched(albedo, m) for m, wi in zip(mu, w))
    assert float(burley_total_rd(albedo)) == pytest.approx(diffuse, abs=2.5e-3)


def test_reduced_albedo_round_trip():
    alpha = np.linspace(0, 1, 11)
    for g in (-0.5, 0.0, 0.9):
        np.testing.assert_allclose(albedo_from_reduced(reduced_albedo(alpha, g), g), alpha, atol=1e-15)
    assert reduced_albedo(0.99, 0.9) == pytest.approx(0.099 / 0.109)
