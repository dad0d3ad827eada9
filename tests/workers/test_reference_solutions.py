"""Self-checks of the exact reference solutions in tests/reference/.

These validate the references themselves (identities, closed forms, two independent
numerical methods, a brute-force Monte Carlo) so that the walk can be compared to them.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import integrate

from tests.reference.fresnel import (
    critical_cosine,
    fresnel_amplitudes,
    fresnel_reflectance,
    fresnel_reflectance_array,
    refracted_cosine,
)
from tests.reference.hfunction import (
    diffuse_reflectance_isotropic_matched,
    h_function,
    h_function_integral,
    h_moment,
)
from tests.reference.single_scattering import (
    hg_azimuthal_integral,
    hg_phase,
    inside_cosine_from_outside,
    single_scattering_radial,
    single_scattering_radial_cos,
    single_scattering_total,
)

ALBEDOS = [0.5, 0.8, 0.9, 0.95, 0.99, 0.999]

# H(1) and the plane albedo R(mu0 = 1) = 1 - sqrt(1 - a) H(1), isotropic scattering,
# index matched; computed here and confirmed by the explicit integral formula.
H1_TABLE = {
    0.5: 1.2512595634,
    0.8: 1.5982195185,
    0.9: 1.8500985168,
    0.95: 2.0771238419,
    0.99: 2.4727928284,
    0.999: 2.7560725073,
}
R1_TABLE = {
    0.5: 0.1152258777,
    0.8: 0.2852545027,
    0.9: 0.4149474791,
    0.95: 0.5355409892,
    0.99: 0.7527207172,
    0.999: 0.9128453348,
}


# --------------------------------------------------------------------------- Fresnel


def test_fresnel_normal_incidence():
    assert fresnel_reflectance(1.0, 1.5) == pytest.approx(0.04, abs=1e-15)
    assert fresnel_reflectance(1.0, 1.0 / 1.5) == pytest.approx(0.04, abs=1e-15)
    assert fresnel_reflectance(1.0, 1.0) == 0.0
    assert fresnel_reflectance(0.3, 1.0) == pytest.approx(0.0, abs=1e-16)


def test_fresnel_brewster_and_tir():
    for eta in (1.33, 1.5, 1 / 1.4):
        theta_b = math.atan(eta)
        rs, rp = fresnel_amplitudes(math.cos(theta_b), eta)
        assert abs(rp) < 1e-15
        assert fresnel_reflectance(math.cos(theta_b), eta) == pytest.approx(0.5 * rs * rs, rel=1e-14)
    eta = 1 / 1.5  # leaving glass
    mu_c = critical_cosine(1.5)
    assert mu_c == pytest.approx(math.sqrt(1 - 1 / 1.5**2))
    assert fresnel_reflectance(mu_c * 0.999, eta) == 1.0
    assert fresnel_reflectance(mu_c * 1.001, eta) < 1.0
    assert fresnel_reflectance(0.0, 1.5) == 1.0
    assert fresnel_reflectance(1e-9, 1.5) == pytest.approx(1.0, abs=1e-8)


def test_fresnel_reciprocity_and_array():
    # Reflectance is the same from both sides for a pair of refracted directions.
    for eta in (1.2, 1.5, 2.0):
        for cos_i in np.linspace(0.01, 1.0, 23):
            cos_t = refracted_cosine(cos_i, eta)
            assert fresnel_reflectance(cos_i, eta) == pytest.approx(
                fresnel_reflectance(cos_t, 1 / eta), abs=1e-12)
    c = np.linspace(0.0, 1.0, 101)
    for eta in (1.4, 1 / 1.4, 1.0):
        arr = fresnel_reflectance_array(c, eta)
        ref = np.array([fresnel_reflectance(x, eta) for x in c])
        np.testing.assert_allclose(arr, ref, rtol=0, atol=1e-15)


# --------------------------------------------------------------------------- H-function


def test_h_function_known_values():
    assert h_function(1.0, 1.0) == pytest.approx(2.9078, abs=5e-5)  # Chandrasekhar's table
    assert h_function(1.0, 1.0) == pytest.approx(2.90781, abs=5e-6)
    for a in ALBEDOS + [1.0]:
        assert h_function(0.0, a) == pytest.approx(1.0, abs=1e-14)
        alpha0 = 2.0 / a * (1.0 - math.sqrt(1.0 - a))
        assert h_moment(0, a) == pytest.approx(alpha0, abs=1e-12)
    assert h_moment(0, 1.0) == pytest.approx(2.0, abs=1e-12)
    assert h_moment(1, 1.0) == pytest.approx(2.0 / math.sqrt(3.0), abs=1e-12)


@pytest.mark.parametrize("a", ALBEDOS + [1.0])
def test_h_function_two_independent_methods(a):
    mus = [1e-6, 1e-3, 0.02, 0.1, 0.25, 0.5, 0.75, 1.0]
    nystrom = h_function(np.array(mus), a)
    for mu, h in zip(mus, nystrom):
        assert h == pytest.approx(h_function_integral(mu, a), abs=1e-10)


def test_h_function_equation_residual():
    # The original (non-inverted) equation H = 1 + (a/2) mu H int H/(mu+mu') dmu' holds too.
    for a in (0.5, 0.99, 1.0):
        for mu in (0.05, 0.5, 1.0):
            val, _ = integrate.quad(lambda m: h_function(m, a) / (mu + m), 0.0, 1.0,
                                    epsabs=1e-13, epsrel=1e-12, limit=200)
            h = h_function(mu, a)
            assert h == pytest.approx(1.0 + 0.5 * a * mu * h * val, abs=1e-10)


@pytest.mark.parametrize("a", ALBEDOS)
def test_plane_albedo_table(a):
    assert h_function(1.0, a) == pytest.approx(H1_TABLE[a], abs=1e-9)
    assert h_function_integral(1.0, a) == pytest.approx(H1_TABLE[a], abs=1e-9)
    assert diffuse_reflectance_isotropic_matched(a) == pytest.approx(R1_TABLE[a], abs=1e-9)


def test_plane_albedo_limits():
    assert diffuse_reflectance_isotropic_matched(1.0) == pytest.approx(1.0, abs=1e-14)
    # Flux form: R = (a/2) H(mu0) int mu H(mu)/(mu + mu0) dmu.
    for a in (0.5, 0.95):
        for mu0 in (0.2, 1.0):
            val, _ = integrate.quad(lambda m: m * h_function(m, a) / (m + mu0), 0, 1,
                                    epsabs=1e-13, limit=200)
            assert diffuse_reflectance_isotropic_matched(a, mu0) == pytest.approx(
                0.5 * a * h_function(mu0, a) * val, abs=1e-10)
    # To first order in the albedo, all reflectance is single scattering.
    for a in (1e-3, 2e-3):
        for theta in (0.0, 1.0):
            r = diffuse_reflectance_isotropic_matched(a, math.cos(theta))
            r1 = single_scattering_total(a, 0.0, 1.0, theta)
            assert 0.0 < r - r1 < 0.5 * a * a


# --------------------------------------------------------------------------- single scattering


def test_single_isotropic_matched_closed_form():
    for a in (0.3, 0.99, 1.0):
        assert single_scattering_total(a, 0.0, 1.0) == pytest.approx(
            a * (1 - math.log(2)) / 2, abs=1e-13)
        for theta in (0.3, 1.0, 1.4):
            mu0 = math.cos(theta)
            closed = 0.5 * a * (1 - mu0 * math.log((1 + mu0) / mu0))
            assert single_scattering_total(a, 0.0, 1.0, theta) == pytest.approx(closed, abs=1e-13)


def test_hg_azimuthal_closed_form():
    for mu, g, theta_t in [(0.3, 0.8, 0.5), (0.9, -0.9, 0.7), (0.01, 0.95, 1.4), (0.5, 0.0, 0.3)]:
        st, mt = math.sin(theta_t), math.cos(theta_t)
        num, _ = integrate.quad(
            lambda p: float(hg_phase(st * math.sqrt(1 - mu * mu) * math.cos(p) - mt * mu, g)),
            0.0, 2 * math.pi, epsabs=1e-14, limit=500)
        assert hg_azimuthal_integral(mu, g, st, mt) == pytest.approx(num, rel=1e-12)


@pytest.mark.parametrize("g,eta,theta", [(0.6, 1.33, 0.9), (-0.8, 1.5, 0.6), (0.9, 1.0, 1.2)])
def test_single_total_vs_2d_quadrature(g, eta, theta):
    """Elliptic azimuthal form vs a plain 2-D quadrature over the upward hemisphere."""
    a = 0.9
    st = math.sin(theta) / eta
    mt = math.sqrt(1 - st * st)
    mu_c = critical_cosine(eta)

    def inner(mu):
        sth = math.sqrt(1 - mu * mu)
        v, _ = integrate.quad(lambda p: float(hg_phase(st * sth * math.cos(p) - mt * mu, g)),
                              0.0, math.pi, epsabs=1e-13, limit=200)
        return 2 * v * mu / (mu + mt) * (1 - fresnel_reflectance(mu, 1 / eta))

    pts = [mt] if mu_c < mt < 1 else None
    val, _ = integrate.quad(inner, mu_c, 1.0, points=pts, epsabs=1e-12, limit=400)
    expect = (1 - fresnel_reflectance(math.cos(theta), eta)) * a * val
    assert single_scattering_total(a, g, eta, theta) == pytest.approx(expect, abs=1e-10)


def _radial_nested_quad(r_lo, r_hi, sigma_t, a, g, eta):
    """Independent check of (b): explicit (mu, z) quadrature with a numerical z integral."""
    mu_c = critical_cosine(eta)
    t_in = 1 - fresnel_reflectance(1.0, eta)

    def outer(mu):
        s = math.sqrt(1 - mu * mu)
        z_lo = r_lo * mu / s
        z_hi = r_hi * mu / s if math.isfinite(r_hi) else math.inf
        k = sigma_t * (1 + 1 / mu)
        zi, _ = integrate.quad(lambda z: sigma_t * math.exp(-k * z), z_lo, z_hi,
                               epsabs=1e-14, epsrel=1e-12, limit=200)
        return 2 * math.pi * float(hg_phase(-mu, g)) * (1 - fresnel_reflectance(mu, 1 / eta)) * zi

    pts = [1 - (1 - abs(g)) ** 2 * k for k in (1, 5, 25)] if g < 0 else None
    val, _ = integrate.quad(outer, mu_c, 1.0, points=pts, epsabs=1e-12, epsrel=1e-10, limit=500)
    return t_in * a * val


@pytest.mark.parametrize("g,eta", [(-0.9, 1.4), (0.95, 1.4), (0.0, 1.0), (0.5, 1 / 1.2)])
def test_single_radial_vs_nested_quadrature(g, eta):
    sigma_t, a = 2.0, 0.95
    edges = np.array([0.0, 0.001, 0.01, 0.1, 0.5, 2.0, 10.0, np.inf])
    got = single_scattering_radial(edges, sigma_t, a, g, eta)
    for i in (0, 1, 3, 5, 6):
        assert got[i] == pytest.approx(
            _radial_nested_quad(edges[i], edges[i + 1], sigma_t, a, g, eta), abs=1e-9)


@pytest.mark.parametrize("g", [-0.9, -0.3, 0.0, 0.5, 0.9, 0.95])
@pytest.mark.parametrize("eta", [1.0, 1.3, 1.5, 1 / 1.3])
def test_single_radial_sums(g, eta):
    sigma_t, a = 1.7, 0.99
    edges = np.concatenate((np.linspace(0.0, 3.0, 64), [np.inf]))
    radial = single_scattering_radial(edges, sigma_t, a, g, eta)
    total = single_scattering_total(a, g, eta, 0.0)
    assert np.all(radial >= 0.0)
    assert radial.sum() == pytest.approx(total, abs=1e-10)
    cos_edges = np.linspace(0.0, 1.0, 9)
    rc = single_scattering_radial_cos(edges, cos_edges, sigma_t, a, g, eta)
    assert rc.shape == (64, 8)
    assert np.all(rc >= 0.0)
    np.testing.assert_allclose(rc.sum(axis=1), radial, rtol=0, atol=1e-11)
    # Scale invariance: G depends on sigma_t r only.
    np.testing.assert_allclose(
        single_scattering_radial(edges * 2.0, sigma_t / 2.0, a, g, eta), radial, rtol=0, atol=1e-12)


def test_single_radial_isotropic_closed_form_first_annulus_limit():
    # eta = 1, isotropic: G over [r, inf) -> 0 as r -> inf, and for tiny r the inner disc
    # carries almost nothing: C(0) - C(r) = O(r log r).
    edges = np.array([0.0, 1e-6, np.inf])
    g_in, g_out = single_scattering_radial(edges, 1.0, 1.0, 0.0, 1.0)
    assert g_in < 1e-4
    assert g_in + g_out == pytest.approx((1 - math.log(2)) / 2, abs=1e-12)


def test_inside_cosine_mapping():
    eta = 1.4
    c = np.linspace(0.0, 1.0, 11)
    m = inside_cosine_from_outside(c, eta)
    assert m[0] == pytest.approx(critical_cosine(eta))
    assert m[-1] == 1.0
    np.testing.assert_allclose(np.sqrt(1 - eta**2 * (1 - m**2)), c, atol=1e-12)


# --------------------------------------------------------------------------- brute-force MC


def _sample_hg(g, u):
    if g == 0.0:
        return 1.0 - 2.0 * u
    s = (1.0 - g * g) / (1.0 - g + 2.0 * g * u)
    return (1.0 + g * g - s * s) / (2.0 * g)


def _mc_single(n, sigma_t, a, g, eta, theta_i, seed):
    """Plain-numpy Monte Carlo of exactly-one-scattering paths (weights per incident power)."""
    rng = np.random.default_rng(seed)
    sin_t = math.sin(theta_i) / eta
    mu_t = math.sqrt(1 - sin_t * sin_t)
    t_in = 1 - fresnel_reflectance(math.cos(theta_i), eta)
    s = -np.log1p(-rng.random(n)) / sigma_t
    depth = s * mu_t
    cos_rel = _sample_hg(g, rng.random(n))
    phi = 2 * math.pi * rng.random(n)
    sin_rel = np.sqrt(np.maximum(0.0, 1 - cos_rel * cos_rel))
    # d0 = (sin_t, 0, -mu_t); e1 = (mu_t, 0, sin_t) and e2 = (0, 1, 0) complete the frame.
    wx = cos_rel * sin_t + sin_rel * np.cos(phi) * mu_t
    wy = sin_rel * np.sin(phi)
    wz = -cos_rel * mu_t + sin_rel * np.cos(phi) * sin_t
    up = wz > 0
    wz_safe = np.where(up, wz, 1.0)
    w = np.where(up, t_in * a * np.exp(-sigma_t * depth / wz_safe)
                 * (1 - fresnel_reflectance_array(wz_safe, 1 / eta)), 0.0)
    # exit point relative to the entry point
    ex = s * sin_t + depth / wz_safe * wx
    ey = depth / wz_safe * wy
    r = np.hypot(ex, ey)
    cos_o = np.sqrt(np.maximum(0.0, 1 - eta * eta * (1 - wz_safe * wz_safe)))
    return w, r, cos_o


def test_single_total_vs_brute_force_mc_oblique():
    n = 1_000_000
    a, g, eta, theta = 0.9, -0.6, 1.4, math.radians(50.0)
    w, _, _ = _mc_single(n, 1.0, a, g, eta, theta, seed=12345)
    est, se = w.mean(), w.std(ddof=1) / math.sqrt(n)
    ref = single_scattering_total(a, g, eta, theta)
    assert abs(est - ref) < 4 * se, (est, ref, se)


def test_single_radial_cos_vs_brute_force_mc():
    n = 1_000_000
    sigma_t, a, g, eta = 2.0, 0.95, 0.7, 1.4
    edges = np.array([0.0, 0.05, 0.1, 0.2, 0.4, 0.8, 1.6, np.inf])
    cos_edges = np.linspace(0.0, 1.0, 5)
    w, r, cos_o = _mc_single(n, sigma_t, a, g, eta, 0.0, seed=2024)
    ir = np.clip(np.searchsorted(edges, r, side="right") - 1, 0, edges.size - 2)
    ic = np.clip(np.searchsorted(cos_edges, cos_o, side="right") - 1, 0, cos_edges.size - 2)
    flat = ir * (cos_edges.size - 1) + ic
    nb = (edges.size - 1) * (cos_edges.size - 1)
    s1 = np.bincount(flat, weights=w, minlength=nb)
    s2 = np.bincount(flat, weights=w * w, minlength=nb)
    est = s1 / n
    se = np.sqrt(np.maximum(s2 / n - est**2, 0.0) / (n - 1))
    ref = single_scattering_radial_cos(edges, cos_edges, sigma_t, a, g, eta).ravel()
    z = (est - ref) / np.maximum(se, 1e-12)
    populated = ref > 1e-6
    assert populated.sum() >= 12
    assert np.all(np.abs(z[populated]) < 4.0), z
    assert np.all(est[~populated] < 1e-5)
    assert abs(w.mean() - single_scattering_total(a, g, eta)) < 4 * w.std() / math.sqrt(n)


def test_single_scattering_s_integral_closed_form_isotropic_matched():
    """eta = 1, g = 0, normal incidence: the S integral over [0, inf) x [c0, c1) is
    int_{c0}^{c1} (a / 2) mu / (1 + mu) / mu dmu = (a / 2) ln((1 + c1) / (1 + c0)), finite in the
    grazing bin (the flux there carries the factor mu that 1 / cos_o removes)."""
    from tests.reference.single_scattering import single_scattering_radial_cos

    a = 0.8
    cos_edges = np.array([0.0, 0.1, 0.5, 1.0])
    s = single_scattering_radial_cos([0.0, np.inf], cos_edges, 3.0, a, 0.0, 1.0, quantity="S")[0]
    want = 0.5 * a * np.log((1.0 + cos_edges[1:]) / (1.0 + cos_edges[:-1]))
    np.testing.assert_allclose(s, want, rtol=1e-9)
    g = single_scattering_radial_cos([0.0, np.inf], cos_edges, 3.0, a, 0.0, 1.0)[0]
    np.testing.assert_allclose(g, 0.5 * a * np.diff(cos_edges - np.log1p(cos_edges)), rtol=1e-9)


@pytest.mark.parametrize("eta", [1.0, 1.3, 0.8])
def test_transmittance_over_cos_out_is_t_over_cos(eta):
    from tests.reference.fresnel import fresnel_reflectance
    from tests.reference.single_scattering import transmittance_over_cos_out

    for mu in np.linspace(0.02, 1.0, 50):
        c2 = 1.0 - eta * eta * (1.0 - mu * mu)
        if c2 <= 1e-6:
            assert c2 > 0 or transmittance_over_cos_out(mu, eta) == 0.0
            continue
        want = (1.0 - fresnel_reflectance(mu, 1.0 / eta)) / math.sqrt(c2)
        assert transmittance_over_cos_out(mu, eta) == pytest.approx(want, rel=1e-10), (mu, eta)
